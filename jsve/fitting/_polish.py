"""Where Nelder-Mead polishes: on every run, or on a stratified subset of the runs; and how the simplexes
of many fits move together.

A Nelder-Mead run evaluates the hard objective of one setting at a time, 2-3 times a step, and a study
polishes n_starts times per family for the full fit and every cross-validation fold: polishing on
every run, each evaluation scanning every run of every part, would be almost all of `jsve fit`'s time
on a large study (jsve.fitting._estimate says how much).

With `FitConfig.polish_runs = N` and more than N training runs, a fit polishes on the first N training
runs of the study's stratified order (jsve.fitting._halving.stratified_order, as balanced over sequence,
disturbance and level as N runs can be): a cost that does not grow with the study. The search that
picks the starts has seen every training run, and `fit` keeps a polished setting only if its objective
on every training run beats the search's best: the subset moves the optimiser, never the verdict. This
is the multi-fidelity idea of the halving search (screen on few runs, decide on all) applied to the
local optimiser.

`polish_in_lockstep` moves the Nelder-Mead runs of many fits together (jsve.fitting._simplex): the
union of their polish runs is laid out once (jsve.fitting._packing.subset_layout: by length class, or in
one part where a step's few points cost less so), and each step's points of all fits are one batched
search whose rows are averaged over each point's own fit's polish runs, so a fit moves exactly as it
would alone.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jsve.fitting._halving import stratified_order
from jsve.fitting._simplex import lockstep_nelder_mead


def polish_runs(
    meta, weights: np.ndarray, n: int, *, seed: int = 0, pool: np.ndarray | None = None
) -> np.ndarray | None:
    """The runs Nelder-Mead polishes on: the first n runs with weight > 0 in `pool` (default: in
    `weights`) in the stratified order of the study, less those without weight in `weights` (sorted);
    or None where n is 0 or at most n runs have weight in the pool (polish on every weighted run).

    A cross-validation fold passes the study's weights as its pool: it polishes on the full fit's polish
    runs less its held-out ones (as its halving screens on the full fit's rungs less them), so the folds
    moving in lockstep scan the full fit's n runs, not a union of n runs a fold (which on a large
    study is well above n)."""
    weights = np.asarray(weights)
    pool = weights if pool is None else np.asarray(pool)
    if pool.shape != weights.shape:
        raise ValueError(f"polish_runs: pool has shape {pool.shape}, weights {weights.shape}")
    eligible = pool > 0
    if n <= 0 or int(eligible.sum()) <= n:
        return None
    order = stratified_order(meta, len(weights), seed=seed)
    first = order[eligible[order]][:n]
    return np.sort(first[weights[first] > 0])


@dataclass(frozen=True)
class Polishes:
    """Where the Nelder-Mead runs of `polish_in_lockstep` ended.

    Attributes:
        values: [N, d] each run's free values. steps: [N] its steps. polish_runs: [N] the runs its fit
            moved on. runs_scanned: runs of the shared scan (the union of every fit's polish runs).
        seconds: wall time of all of them together. evaluations: objective points scored.
    """

    values: np.ndarray
    steps: np.ndarray
    polish_runs: np.ndarray
    runs_scanned: int
    seconds: float
    evaluations: int


def polish_in_lockstep(
    data,
    space,
    weights: Sequence[np.ndarray],
    starts: Sequence[tuple[int, np.ndarray]],
    *,
    n_runs: int,
    seed: int,
    step: float,
    max_steps: int,
    window: int,
    ftol: float,
    rtol: float = 1e-4,
    atol: float = 1e-4,
    pool: np.ndarray | None = None,
    progress: bool = False,
    desc: str = "Nelder-Mead",
) -> Polishes:
    """Nelder-Mead from every start of every fit, all moved together (jsve.fitting._simplex.
    lockstep_nelder_mead): each step scores the points of all unfinished runs in one batched search.

    Each fit moves on its own `polish_runs` (its first n_runs weighted runs in the stratified order, or
    all of them), exactly as it would alone: the scan covers the union of the fits' polish runs, packed
    by length class once (jsve.fitting._packing), and a point is averaged over its own fit's runs only.

    Arguments:
        data: FitData. weights: [R] run weights of each fit. starts: (fit index, free values [d]) of
            each Nelder-Mead run. step, max_steps, window, ftol, rtol, atol: the simplex
            (nelder_mead's arguments). pool: [R] the weights every fit's polish runs are drawn from
            (`polish_runs`; default each fit's own).
    """
    t0 = time.perf_counter()
    weights = [np.asarray(w, np.float64) for w in weights]
    own = [polish_runs(data.meta, w, n_runs, seed=seed, pool=pool) for w in weights]
    own = [np.flatnonzero(w > 0) if runs is None else runs for w, runs in zip(weights, own, strict=True)]
    union = np.unique(np.concatenate(own))
    # a step scores about one point per simplex, on the union packed once for steps of that size
    scorer = data.scorer.on(union, len(starts))
    columns = scorer.runs
    fit_weights = np.zeros((len(weights), len(columns)))
    for f, (w, runs) in enumerate(zip(weights, own, strict=True)):
        mine = np.isin(columns, runs)
        fit_weights[f, mine] = w[columns[mine]]
    owner_fit = np.asarray([f for f, _ in starts], np.int64)
    dtype = data.parts[0].t.dtype

    def objective(z: np.ndarray, owners: np.ndarray) -> np.ndarray:
        values = np.asarray(space.values_from_z(jnp.asarray(z, dtype)), np.float64)
        scored = scorer.score(space, values)
        return _weighted_rows(scored, fit_weights[owner_fit[owners]])

    z0 = np.stack([np.asarray(space.z_from_values(jnp.asarray(v, dtype))) for _, v in starts])
    with tqdm(total=len(starts), desc=desc, unit="simplex", disable=not progress) as bar:
        ended = lockstep_nelder_mead(
            objective, z0, adelta=step, rtol=rtol, atol=atol, window=window, ftol=ftol,
            max_steps=max_steps, on_finish=lambda _: bar.update(1),
        )  # fmt: skip
    values = np.asarray(space.values_from_z(jnp.asarray(ended.z, dtype)), np.float64)
    return Polishes(
        values=values,
        steps=ended.steps,
        polish_runs=np.asarray([len(own[f]) for f in owner_fit]),
        runs_scanned=len(union),
        seconds=time.perf_counter() - t0,
        evaluations=ended.evaluations,
    )


def _weighted_rows(scored, weights: np.ndarray) -> np.ndarray:
    """[M] each setting's weighted mean loss over its included runs under its own weights [M, R] (over
    all its runs where none is included, as jsve.core._objective.weighted_objective)."""
    loss, inc = scored.loss.astype(np.float64), scored.included.astype(np.float64)
    num, den = np.sum(weights * inc * loss, axis=1), np.sum(weights * inc, axis=1)
    every = np.sum(weights * loss, axis=1) / np.sum(weights, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), every)


__all__ = ["polish_runs", "Polishes", "polish_in_lockstep"]
