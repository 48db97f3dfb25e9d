"""Nelder-Mead for the fit's hard objective: many simplexes moved in lockstep, each stopping when it stops
improving.

The hard objective is piecewise constant in the thresholds (finitely many frames cross them), so a
simplex rarely meets the usual test, which asks every vertex to lie within rtol/atol of the best point:
it keeps finding steps of a few frames' worth and runs to its step limit (docs/fitting.md). A stall
test stops a run once its best value has improved by no more than `ftol` (metres of the objective)
over `window` steps: a polish that has stopped paying.

The step is optimistix.NelderMead's (v0.1.0), with two of its defects left out; tests/test_simplex.py
compares the two step for step:
- its initial simplex for a vector y adds adelta at the wrong flat indices (it unravels vertex indices
  1..d into the [d + 1, d] array: row 0 gets columns 1..d-1, row 1 column 0, the other rows nothing),
  so the simplex is degenerate and every move stays in a plane through the start;
- its best and worst vertices are read from the simplex before the step's update (`_structured_index(
  simplex, ...)` of the old simplex), so it reflects through a stale worst vertex and can return a
  vertex other than its best (on a smooth bowl it returns 0.0499 where its simplex holds 0.0115).
`previous_simplex_vertices=True` keeps the second, to show that otherwise the steps are optimistix's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LockstepResult:
    """Where each of F Nelder-Mead runs ended.

    Attributes:
        z: [F, d] each run's best vertex. value: [F] its objective there.
        steps: [F] steps each run took (optimistix's count: the initial simplex is step 1).
        stalled: [F] whether the stall test stopped it. evaluations: objective points scored in all.
    """

    z: np.ndarray
    value: np.ndarray
    steps: np.ndarray
    stalled: np.ndarray
    evaluations: int


def lockstep_nelder_mead(
    objective: Callable[[np.ndarray, np.ndarray], np.ndarray],
    z0,
    *,
    adelta: float,
    rtol: float,
    atol: float,
    window: int = 25,
    ftol: float = 1e-4,
    max_steps: int = 200,
    on_finish: Callable[[int], None] | None = None,
    initial_simplex=None,
    previous_simplex_vertices: bool = False,
) -> LockstepResult:
    """F independent Nelder-Mead runs moved together, so that each step scores the points of every
    unfinished run in one call.

    One simplex at a time, each objective call scores one setting: a scan over the polish's runs whose
    lanes (settings x runs) are too few to fill a core, so one call of many settings costs a fraction
    of as many calls of one (benchmarks/profile_fit.py). A cross-validation polishes 2 starts x 19 folds;
    in lockstep their reflections are one call, their expansions and contractions another, their
    shrinks a third.

    The step is optimistix.NelderMead's (moves from the worst vertex along the direction to the others'
    centroid: reflection 2, expansion 3, contractions 0.5 and 1.5; a shrink by 0.5 towards the best
    when the new point is worse than the worst; the initial simplex z0 + adelta e_i; its convergence
    test on the simplex) without its defects (module docstring), on the host, where a choice per run
    costs nothing: under jax.vmap its lax.conds would score every run's shrink on every step. A point
    equal to the reflection is not scored twice.

    Arguments:
        objective: (points [M, d], owners [M] run indices) -> [M] values; each point is scored for its
            owner (its run's weights). Called with the points of the unfinished runs only.
        z0: [F, d] starts. adelta: the initial simplex's size. rtol, atol: the convergence test
            (optimistix's: every vertex and value within atol + rtol |best| of the best's).
        window, ftol: stop a run once `window` steps in a row improve its best value by at most
            `ftol`, judged from the initial simplex (step 1) at steps 1, 1 + window, ...; window 0: no
            stall test. max_steps: each run's limit (the initial simplex counts as step 1).
        on_finish: called with a run's index when it stops (a progress bar).
        initial_simplex: [F, d + 1, d] instead of z0 + adelta e_i.
        previous_simplex_vertices: optimistix 0.1.0's bookkeeping (module docstring), for the
            comparison with it only.
    Returns:
        LockstepResult.
    """
    z0 = np.asarray(z0)
    n_runs, dim = z0.shape
    dtype = z0.dtype
    n_vertices = dim + 1
    calls = [0]

    def score(points: np.ndarray, owners: np.ndarray) -> np.ndarray:
        calls[0] += len(points)
        return np.array(objective(points.astype(dtype), owners), dtype)  # writable

    if initial_simplex is None:
        simplex = np.repeat(z0[:, None, :], n_vertices, axis=1)
        simplex[:, 1:, :] += (np.asarray(adelta, dtype) * np.eye(dim, dtype=dtype))[None]
    else:
        simplex = np.array(initial_simplex, dtype)
    every = np.arange(n_runs)
    f = score(simplex.reshape(-1, dim), np.repeat(every, n_vertices)).reshape(n_runs, n_vertices)
    steps = np.ones(n_runs, int)
    mark = np.full(n_runs, np.inf, dtype)
    stalled = np.zeros(n_runs, bool)
    active = np.ones(n_runs, bool)
    # The step's bookkeeping, as optimistix's state keeps it: the best and worst vertices (and their
    # indices), the worst and second-worst values.
    best_i, worst_i = np.zeros(n_runs, int), np.zeros(n_runs, int)
    best_v, worst_v = simplex[:, 0].copy(), simplex[:, 0].copy()
    # The step at which each vertex joined its simplex: among equal values the oldest is the worst.
    # optimistix takes the first index, and on a plateau (a step of the hard objective) its simplex
    # then reflects the vertex it has just placed straight back: two points, forever.
    born = np.zeros((n_runs, n_vertices), int)

    def settle(runs: np.ndarray, before: np.ndarray) -> None:
        """After a step of `runs` (`before`: their simplexes before it): the bookkeeping, the stall test's
        checkpoint, then optimistix's stop."""
        best_i[runs], worst_i[runs] = _first_min(f[runs]), _worst_two(f[runs], born[runs])[0]
        source = before if previous_simplex_vertices else simplex[runs]
        best_v[runs] = source[np.arange(len(runs)), best_i[runs]]
        worst_v[runs] = source[np.arange(len(runs)), worst_i[runs]]
        best = f[runs].min(axis=1)
        at = (steps[runs] - 1) % max(window, 1) == 0 if window > 0 else np.zeros(len(runs), bool)
        with np.errstate(invalid="ignore"):
            stalled[runs] = at & (mark[runs] - best <= ftol)
        mark[runs] = np.where(at, best, mark[runs])
        x_scale = atol + rtol * np.abs(best_v[runs])
        x_diff = np.abs(simplex[runs] - best_v[runs][:, None]) / x_scale[:, None]
        f_scale = atol + rtol * np.abs(best)
        with np.errstate(invalid="ignore"):
            converged = (x_diff.max(axis=(1, 2)) < 1) & (
                (np.abs(f[runs] - best[:, None]) / f_scale[:, None]).max(axis=1) < 1
            )
        done = converged | ~np.isfinite(best) | stalled[runs] | (steps[runs] >= max_steps)
        for r in runs[done]:
            active[r] = False
            if on_finish is not None:
                on_finish(int(r))

    settle(every, simplex.copy())
    while active.any():
        runs = np.flatnonzero(active)
        before = simplex[runs].copy()
        _, f_worst, f_second = _worst_two(f[runs], born[runs])
        f_best = f[runs].min(axis=1)
        worst = worst_v[runs]
        direction = np.sum(simplex[runs] - worst[:, None], axis=1) / dtype.type(n_vertices - 1)
        reflection = worst + dtype.type(2) * direction
        f_new = score(reflection, runs)
        expand = f_new < f_best
        contract = f_new > f_second
        moved = expand | contract
        scale = np.where(expand, 3.0, np.where(f_new > f_worst, 0.5, 1.5)).astype(dtype)
        new = np.where(moved[:, None], worst + scale[:, None] * direction, reflection)
        if moved.any():
            f_new[moved] = score(new[moved], runs[moved])
        shrink = f_new > f_worst
        keep = ~shrink
        simplex[runs[keep], worst_i[runs[keep]]] = new[keep]
        f[runs[keep], worst_i[runs[keep]]] = f_new[keep]
        born[runs[keep], worst_i[runs[keep]]] = steps[runs[keep]]
        if shrink.any():
            shrunk = runs[shrink]
            toward = best_v[shrunk][:, None]
            simplex[shrunk] = toward + dtype.type(0.5) * (simplex[shrunk] - toward)
            owners = np.repeat(shrunk, n_vertices)
            f[shrunk] = score(simplex[shrunk].reshape(-1, dim), owners).reshape(len(shrunk), n_vertices)
            born[shrunk] = steps[shrunk][:, None]
        steps[runs] += 1
        settle(runs, before)
    return LockstepResult(
        z=best_v.copy(),
        value=f[every, best_i],
        steps=steps,
        stalled=stalled,
        evaluations=calls[0],
    )


def _first_min(f: np.ndarray) -> np.ndarray:
    """Each row's best vertex, the first of ties (lax.top_k's order, which optimistix takes)."""
    return np.argmin(f, axis=1)


def _worst_two(f: np.ndarray, born: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's worst vertex (of equal values the oldest, then the first), its value and the
    second-largest value."""
    order = np.lexsort((born, -f), axis=-1)
    rows = np.arange(len(f))
    return order[:, 0], f[rows, order[:, 0]], f[rows, order[:, 1]]


__all__ = ["LockstepResult", "lockstep_nelder_mead"]
