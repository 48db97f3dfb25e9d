"""Where Nelder-Mead polishes: on every run, or on a stratified subset of the runs packed into one part.

Nelder-Mead evaluates the hard objective of one setting at a time, about 460 times a polish (200 steps),
and a study polishes twice per family for the full fit and every cross-validation fold: on a large study
this is almost all of `jsve fit`'s time (jsve.fitting._estimate: 90 % of the 3,410-log study's
estimate), and each evaluation scans every run of every part (27 length buckets there, each its own scan,
all compiled into the objective).

With `FitConfig.polish_runs = N` and more than N training runs, the polish runs on the first N training
runs of the study's stratified order (jsve.fitting._halving.stratified_order, as balanced over sequence,
disturbance and level as N runs can be), gathered from their parts into one part padded to the longest
part's frames: one scan of N runs per evaluation, one compilation per study (its shape is fixed), a cost
that no longer grows with the study. The search that picks the starts has seen every training run, and
`fit` keeps a polished setting only if its objective on every training run beats the search's best: the
subset moves the optimiser, never the verdict. This is the multi-fidelity idea of the halving search
(screen on few runs, decide on all) applied to the local optimiser.
"""

from __future__ import annotations

import numpy as np

from jsve.fitting._halving import stratified_order
from jsve.fitting._packing import pack_runs
from jsve.fitting._search import SearchBatch


def polish_runs(meta, weights: np.ndarray, n: int, *, seed: int = 0) -> np.ndarray | None:
    """The runs Nelder-Mead polishes on: the first n runs with weight > 0 in the stratified order of the
    study (sorted), or None where n is 0 or there are at most n such runs (polish on every run)."""
    weights = np.asarray(weights)
    train = weights > 0
    if n <= 0 or int(train.sum()) <= n:
        return None
    order = stratified_order(meta, len(weights), seed=seed)
    return np.sort(order[train[order]][:n])


def packed_subset(
    data, weights: np.ndarray, n: int, *, seed: int = 0
) -> tuple[SearchBatch, np.ndarray] | None:
    """The first n weighted runs of FitData `data`'s stratified order (`polish_runs`) packed into one part
    (`pack_runs`), and their indices: how Nelder-Mead, the heat map and the bootstrap's screen score a
    large study on a subset. None where `polish_runs` is (n is 0 or at most n runs have weight)."""
    subset = polish_runs(data.meta, weights, n, seed=seed)
    if subset is None:
        return None
    return pack_runs(data.parts, data.run_counts, subset), subset


__all__ = ["polish_runs", "packed_subset"]
