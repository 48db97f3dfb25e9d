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

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsve.fitting._halving import stratified_order
from jsve.fitting._search import SearchBatch


def _gathered(part: SearchBatch, local: np.ndarray, n_frames: int) -> SearchBatch:
    """Runs `local` of a part (host copies: numpy gathers without compiling a kernel per shape), its
    frame leaves ([F, R]) extended to n_frames by repeating their last frame, the added frames marked as
    a length bucket marks a shorter run's padding: not valid, without ground truth or a recorded pose."""
    frames = part.n_frames

    def take(x):
        x = np.asarray(x)[..., local]
        # frame leaves are the [F, R] ones; per-run leaves are [R], [3, R] or [3, 3, R] (F >= 64 > 3)
        if x.ndim == 2 and x.shape[0] == frames and n_frames > frames:
            x = np.pad(x, [(0, n_frames - frames), (0, 0)], mode="edge")
        return x

    taken = jax.tree.map(take, part)
    if n_frames == frames:
        return taken
    real = (np.arange(n_frames) < frames)[:, None]
    none = lambda x: np.where(real, x, np.zeros_like(x))  # noqa: E731
    data = taken.data
    data = eqx.tree_at(
        lambda d: (d.has_pose, d.init_keys, d.rec_start, d.rec_loss, d.rec_reloc),
        data,
        (
            none(data.has_pose),
            none(data.init_keys),
            none(data.rec_start),
            none(data.rec_loss),
            np.where(real, data.rec_reloc, -np.ones_like(data.rec_reloc)),
        ),
    )
    return eqx.tree_at(
        lambda b: (b.valid, b.gt, b.weight, b.g_c, b.data),
        taken,
        (none(taken.valid), none(taken.gt), none(taken.weight), tuple(none(c) for c in taken.g_c), data),
    )


def pack_runs(parts: Sequence[SearchBatch], run_counts: Sequence[int], runs) -> SearchBatch:
    """One SearchBatch of the runs `runs` (global indices into FitData.meta, taken in increasing order)
    gathered from the search parts (the first run_counts[p] runs of part p real), every run padded to
    the longest part's frames: added frames are invalid, without ground truth or pose, as the padding of
    a shorter run in a length bucket is, so each run scores as on its own part. The per-run alignment
    statistics (Gram matrix, means) are over the real frames and are taken as they are.

    Built on the host from the parts already in memory: its cost is the packed runs' size (256 runs of
    3,712 frames: ~0.2 GB), never a copy of a part or the study."""
    runs = np.unique(np.asarray(runs, np.int64))
    n_frames = max(p.n_frames for p in parts)
    picked, start = [], 0
    for part, n in zip(parts, run_counts, strict=True):
        local = runs[(runs >= start) & (runs < start + n)] - start
        start += n
        if len(local):
            picked.append(_gathered(part, local, n_frames))
    if not picked:
        raise ValueError("pack_runs: no run selected")
    return jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs, axis=-1)), *picked)


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


__all__ = ["pack_runs", "polish_runs", "packed_subset"]
