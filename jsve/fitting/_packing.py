"""Runs of many parts gathered into few parts of few shapes: how a search scores a subset of the runs.

The search kernel compiles once per input shape (frames x runs x settings per call, per device). A study
streamed from disk is cut into length buckets (a few dozen for a EuRoC study), so a subset of its runs
taken part by part, as halving's rungs and the cross-validation folds' rungs take them, gives every
part a shape of its own in every rung: hundreds of compilations for one family's halving search, about
half its time (benchmarks/profile_fit.py counts them). Packing the subset's runs by length class instead
(FRAME_CLASSES classes of about equal runs, each padded to its longest part's frames, each padded to a
power of 2 of runs) leaves a few shapes per rung, and the same shapes recur in the next rung and fold.
The padding costs frames: within a class the runs are at most one class's range shorter than its
longest (EuRoC: about 10 % more frames scanned).

All gathering is on the host (numpy takes: no kernel compiled per shape for a gather) and a packed run
scores exactly as on its own part: its added frames are marked as a length bucket marks a shorter
run's padding (not valid, no ground truth, no recorded pose), tests/test_polish.py.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np

from jsve.fitting._kernel import SearchBatch
from jsve.fitting._search import call_size

FRAME_CLASSES = 4
"""Length classes a subset of runs is packed into (`frame_classes`): fewer classes mean fewer shapes to
compile and more padded frames to scan."""

PACK_RUNS = 256
"""Most runs of a packed part: a class of more selected runs fills parts of PACK_RUNS runs and packs the
rest in a power of 2, so a large subset pads at most one part (a power of 2 of all 570 runs of a class
would scan 1,024)."""


def gathered(part: SearchBatch, local: np.ndarray, n_frames: int) -> SearchBatch:
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


def pack(
    parts: Sequence[SearchBatch], picks: Sequence[tuple[int, np.ndarray]], n_frames: int, n_runs: int = 0
) -> SearchBatch:
    """One SearchBatch of the runs `picks` ((part, local run indices) in order) at n_frames frames, then
    copies of its first run up to n_runs runs (padding whose results the search drops)."""
    taken = [gathered(parts[p], local, n_frames) for p, local in picks if len(local)]
    if not taken:
        raise ValueError("pack: no run selected")

    def joined(*xs):
        x = np.concatenate(xs, axis=-1)
        extra = n_runs - x.shape[-1]
        if extra > 0:
            x = np.concatenate([x, np.repeat(x[..., :1], extra, axis=-1)], axis=-1)
        return jax.device_put(x)  # a transfer; jnp.asarray would compile a copy per shape and dtype

    return jax.tree.map(joined, *taken)


def padded_runs(n: int) -> int:
    """Runs of a packed part holding n selected runs: the power of 2 at or above n."""
    return 2 ** math.ceil(math.log2(max(n, 1)))


def frame_classes(part_frames: Sequence[int], part_runs: Sequence[int], n: int = FRAME_CLASSES) -> np.ndarray:
    """[P] the length class of each part: the parts sorted by frames, cut into n classes of about equal
    runs (a part is never split); a class is padded to its longest part's frames."""
    frames = np.asarray(part_frames, np.int64)
    runs = np.asarray(part_runs, np.float64)
    order = np.argsort(frames, kind="stable")
    before = np.cumsum(runs[order]) - runs[order]  # runs of the shorter parts
    cls = np.minimum((before / max(runs.sum(), 1.0) * n).astype(np.int64), n - 1)
    out = np.empty(len(frames), np.int64)
    out[order] = cls
    return out


@dataclass(frozen=True)
class Packed:
    """One part of a subset's kernel inputs.

    Attributes:
        picks: (part, local run indices) whose runs it holds, in order; `whole` parts hold one pick.
        frames: its frames; runs: its runs, padding included; n_real: its selected runs (the first ones,
            the rest copies of the first).
        whole: a part all of whose real runs are selected, passed as it is.
    """

    picks: tuple[tuple[int, np.ndarray], ...]
    frames: int
    runs: int
    n_real: int
    whole: bool


def packing(
    run_counts: Sequence[int],
    parts: Sequence[tuple[int, int]],
    runs: np.ndarray,
    n_classes: int = FRAME_CLASSES,
) -> list[Packed]:
    """How `runs` (global indices, any order, no repeats) are laid out for the kernel: a part all of whose
    real runs are selected as it is; the others' selected runs packed by length class (`frame_classes`),
    each class in parts of its longest part's frames: parts of PACK_RUNS runs, the rest in a power of 2
    of runs (`pack`: the padding repeats the part's first run; its results are dropped).

    Arguments:
        run_counts: real runs per part; parts: (frames, runs with padding) per part.
        n_classes: length classes (`frame_classes`).
    Returns:
        Packed per kernel part, whole parts first (in part order), then the classes (shortest first).
    """
    chosen = np.zeros(sum(run_counts), bool)
    chosen[np.asarray(runs, np.int64)] = True
    classes = frame_classes([f for f, _ in parts], [r for _, r in parts], n_classes)
    whole, partial = [], {}
    start = 0
    for p, (n_real, (frames, part_runs)) in enumerate(zip(run_counts, parts, strict=True)):
        local = np.flatnonzero(chosen[start : start + n_real])
        start += n_real
        if len(local) == n_real:
            whole.append(Packed(((p, local),), frames, part_runs, n_real, True))
        elif len(local):
            partial.setdefault(int(classes[p]), []).append((p, local))
    packed = []
    for c in sorted(partial):
        frames = max(parts[p][0] for p in np.flatnonzero(classes == c))
        owner = np.concatenate([np.full(len(local), p) for p, local in partial[c]])  # part order
        local = np.concatenate([local for _, local in partial[c]])
        for first in range(0, len(local), PACK_RUNS):
            part, chunk = owner[first : first + PACK_RUNS], local[first : first + PACK_RUNS]
            picks = tuple((int(p), chunk[part == p]) for p in dict.fromkeys(part.tolist()))
            packed.append(Packed(picks, frames, padded_runs(len(chunk)), len(chunk), False))
    return whole + packed


class PackedParts(Sequence):
    """The kernel's parts of a `packing`, each gathered when it is read and not kept: `search` holds at
    most two parts at once, so a subset of most of the study costs two parts' copies, not a copy of the
    study (a halving rung's subset of a large study, gathered at once, takes gigabytes)."""

    def __init__(self, parts: Sequence[SearchBatch], layout: Sequence[Packed]):
        self._parts, self._layout = parts, list(layout)

    def __len__(self) -> int:
        return len(self._layout)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        item = self._layout[i]
        if item.whole:
            return self._parts[item.picks[0][0]]
        return pack(self._parts, item.picks, item.frames, item.runs)


def subset_parts(
    parts: Sequence[SearchBatch], run_counts: Sequence[int], runs: np.ndarray, n_classes: int = FRAME_CLASSES
) -> tuple[PackedParts, list[int], np.ndarray]:
    """The kernel's inputs for a subset of the runs (`packing`), gathered as they are read.

    Arguments:
        runs: global run indices (data order, as FitData.meta), any order, no repeats.
        n_classes: length classes (`frame_classes`).
    Returns:
        (parts, real runs per part, the global run index of each result column in order).
    """
    layout = packing(run_counts, [(p.n_frames, p.n_runs) for p in parts], runs, n_classes)
    starts = np.concatenate([[0], np.cumsum(run_counts)[:-1]]).astype(np.int64)
    columns = [starts[p] + local for item in layout for p, local in item.picks]
    counts = [item.n_real for item in layout]
    return PackedParts(parts, layout), counts, np.concatenate(columns) if columns else np.zeros(0, np.int64)


SCAN_STEP_LANES = 1900
"""What a call of the search kernel costs per frame whatever its lanes, in lanes: a scan step of L lanes
takes about 48 us + 0.025 us x L on a 2-core CPU (benchmarks/bench_layout.py; docs/fitting.md,
"Nelder-Mead on a subset of the runs"), so a narrow call is dominated by its steps. `cheapest_layout`
weighs calls by it."""


ONE_PART_RUNS = 512
"""Most runs `subset_layout` packs into one part (the heat map's default subset; 512 runs of 4,096
frames are about 0.4 GB)."""


def scan_cost(shapes: Sequence[tuple[int, int]], n_settings: int) -> float:
    """Relative cost of `search` scoring n_settings settings on parts of these (frames, runs) shapes:
    per call, frames x (SCAN_STEP_LANES + lanes), the calls cut as `search` cuts them (call_size)."""
    total = 0.0
    for frames, runs in shapes:
        size = call_size(runs, n_settings)
        total += math.ceil(n_settings / size) * frames * (SCAN_STEP_LANES + size * runs)
    return total


def one_part_shape(parts: Sequence[tuple[int, int]], runs) -> tuple[int, int]:
    """The (frames, runs) of `pack_runs`' part for `runs` of parts of these (frames, runs) shapes."""
    return max(f for f, _ in parts), len(np.unique(np.asarray(runs, np.int64)))


LAYOUT_CLASSES = (2, FRAME_CLASSES)
"""Length classes `cheapest_layout` weighs against one part. Two classes pad less than one part and
call fewer times than four, which makes them the faster layout for the heat map's 400 settings on 512
runs (benchmarks/bench_layout.py; docs/fitting.md, "Nelder-Mead on a subset of the runs")."""


def layout_shapes(
    run_counts: Sequence[int], parts: Sequence[tuple[int, int]], runs, n_classes: int
) -> list[tuple[int, int]]:
    """The (frames, runs) of each kernel part that `subset_layout` gives `runs` of parts of these
    (frames, runs) shapes: n_classes 0 is one packed part, else `packing` by that many length classes."""
    if n_classes == 0:
        return [one_part_shape(parts, runs)]
    return [(item.frames, item.runs) for item in packing(run_counts, parts, runs, n_classes)]


def cheapest_layout(
    run_counts: Sequence[int], parts: Sequence[tuple[int, int]], runs, n_settings: int
) -> int:
    """How n_settings settings on `runs` are scored fastest by `scan_cost`: 0 for one part (`pack_runs`:
    one call per settings chunk, every run padded to the longest part's frames), else the number of
    length classes (LAYOUT_CLASSES; `packing`: a call per class, less padding); the first of equals.
    Few settings favour the one part (fewer calls, each dominated by its steps), many the classes
    (less padding). Never one part above ONE_PART_RUNS runs: it pads every run to the study's
    longest."""
    one_part = len(np.unique(np.asarray(runs, np.int64))) <= ONE_PART_RUNS
    candidates = ([0] if one_part else []) + list(LAYOUT_CLASSES)
    costs = [scan_cost(layout_shapes(run_counts, parts, runs, k), n_settings) for k in candidates]
    return candidates[int(np.argmin(costs))]


def subset_layout(
    parts: Sequence[SearchBatch], run_counts: Sequence[int], runs, n_settings: int
) -> tuple[Sequence[SearchBatch], list[int], np.ndarray]:
    """One packed part (`pack_runs`) or `subset_parts` by length class, as `cheapest_layout` says scores
    n_settings settings on `runs` fastest; the same (parts, real runs per part, global run index of each
    result column). A run scores the same in any (tests/test_polish.py)."""
    runs = np.unique(np.asarray(runs, np.int64))
    n_classes = cheapest_layout(run_counts, [(p.n_frames, p.n_runs) for p in parts], runs, n_settings)
    if n_classes == 0:
        return [pack_runs(parts, run_counts, runs)], [len(runs)], runs
    return subset_parts(parts, run_counts, runs, n_classes)


def pack_runs(parts: Sequence[SearchBatch], run_counts: Sequence[int], runs) -> SearchBatch:
    """One SearchBatch of the runs `runs` (global indices into FitData.meta, taken in increasing order)
    gathered from the search parts (the first run_counts[p] runs of part p real), every run padded to
    the longest part's frames: added frames are invalid, without ground truth or pose, as the padding of
    a shorter run in a length bucket is, so each run scores as on its own part. The per-run alignment
    statistics (Gram matrix, means) are over the real frames and are taken as they are.

    Built on the host from the parts already in memory: its cost is the packed runs' size (256 runs of
    3,712 frames: ~0.2 GB), never a copy of a part or the study."""
    runs = np.unique(np.asarray(runs, np.int64))
    picks, start = [], 0
    for p, n in enumerate(run_counts):
        picks.append((p, runs[(runs >= start) & (runs < start + n)] - start))
        start += n
    if not any(len(local) for _, local in picks):
        raise ValueError("pack_runs: no run selected")
    return pack(parts, picks, max(p.n_frames for p in parts))


__all__ = [
    "FRAME_CLASSES",
    "Packed",
    "PackedParts",
    "frame_classes",
    "gathered",
    "pack",
    "pack_runs",
    "packing",
    "padded_runs",
    "subset_parts",
    "SCAN_STEP_LANES",
    "scan_cost",
    "LAYOUT_CLASSES",
    "layout_shapes",
    "cheapest_layout",
    "subset_layout",
]
