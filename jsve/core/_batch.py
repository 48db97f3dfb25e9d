"""LogBatch: many runs' tracking logs as one padded pytree [runs, frames, ...], plus host metadata.

Runs of different lengths are padded at the end and marked by `valid`; `bucket_by_length` groups
runs so padding stays small, and `iter_chunks` cuts a batch into fixed-size chunks of runs so that
10,000 runs x 3,600 frames never has to sit on the device at once. Per-run metadata (sequence,
disturbance, level, ...) lives host-side in a pandas DataFrame aligned with the runs axis; the pytree
carries only arrays, so jit caches depend on shapes alone.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt

if TYPE_CHECKING:
    Leaf = Array  # what the compiled functions that read a LogBatch see: traced arrays
else:
    Leaf = Array | np.ndarray
"""A LogBatch leaf at run time (the shape checks): a device array, or a numpy array in a host-side
chunk (jsve.io._stream builds chunks in numpy, `pad_runs` and `iter_chunks` keep them there) that goes
to the device when a compiled function is called on it."""


class LogBatch(eqx.Module):
    """Padded arrays of R runs x F frames. Times are seconds since each run's first frame.

    Attributes (shapes; units; frames):
        t: [R, F] s since the run's first frame (relative, so float32 keeps 0.1 ms over hours).
        valid: [R, F] frame exists (False on padding).
        state: [R, F] int8, the front-end's own logged eTrackingState.
        imu_init: [R, F] IMU initialised in the recorded run's map (Atlas::isImuInitialized).
        imu_ba2: [R, F] inertial BA2 done for the recorded run's map (Map::GetIniertialBA2).
        map_id: [R, F] int32, the recorded run's Atlas map (Map::GetId; a reset keeps it), as the rank
            of its id among the run's distinct ids (jsve.io._batching.map_ranks): only equality counts.
        has_pose: [R, F] the recorded run posed the frame (vis_* are zeros / identity where not).
        in_saved: [R, F] the frame's pose belongs to the trajectory the front-end saves when a rule
            tracks it (its keyframe ends in the saved map: jsve.io._saved_trajectory.in_saved_frame).
        n_extracted, n_inliers, n_frustum: [R, F] counts (int32).
        bins: [R, F, 64] keypoints per SVE bin (uint16).
        vis_p, vis_q, vis_v: [R, F, 3|4|3] visual estimate: m, wxyz, m/s; world frame.
        imu_dt, imu_dp, imu_dv, imu_dq: preintegration from the previous frame: s, m, m/s, wxyz.
        gt_p, gt_q: [R, F, 3|4] ground truth (NaN-free; zeros/identity where gt_valid is False).
        gt_valid: [R, F] ground truth available.
        fps: [R] frames per second (sets the relocalisation window).
        gravity: [R, 3] m/s^2, world frame.
        imu_init_delay: [R] s from the first posed frame to the first imu_init frame (inf if never).
        ba2_delay: [R] s from the first posed frame to the first imu_ba2 frame (inf if never).
        n_features: [R] ORB nFeatures of the front-end (the original S_a divides by it).
        stereo: [R] the sensor is IMU_STEREO or IMU_RGBD (log metadata `sensor`).
        run_index: [R] row of the run in the host metadata table; -1 for padding runs.
    """

    t: Float[Leaf, "R F"]
    valid: Bool[Leaf, "R F"]
    state: Int[Leaf, "R F"]
    imu_init: Bool[Leaf, "R F"]
    imu_ba2: Bool[Leaf, "R F"]
    map_id: Int[Leaf, "R F"]
    has_pose: Bool[Leaf, "R F"]
    in_saved: Bool[Leaf, "R F"]
    n_extracted: Int[Leaf, "R F"]
    n_inliers: Int[Leaf, "R F"]
    n_frustum: Int[Leaf, "R F"]
    bins: UInt[Leaf, "R F 64"]
    vis_p: Float[Leaf, "R F 3"]
    vis_q: Float[Leaf, "R F 4"]
    vis_v: Float[Leaf, "R F 3"]
    imu_dt: Float[Leaf, "R F"]
    imu_dp: Float[Leaf, "R F 3"]
    imu_dv: Float[Leaf, "R F 3"]
    imu_dq: Float[Leaf, "R F 4"]
    gt_p: Float[Leaf, "R F 3"]
    gt_q: Float[Leaf, "R F 4"]
    gt_valid: Bool[Leaf, "R F"]
    fps: Float[Leaf, " R"]
    gravity: Float[Leaf, "R 3"]
    imu_init_delay: Float[Leaf, " R"]
    ba2_delay: Float[Leaf, " R"]
    n_features: Float[Leaf, " R"]
    stereo: Bool[Leaf, " R"]
    run_index: Int[Leaf, " R"]

    @property
    def n_runs(self) -> int:
        return self.t.shape[0]

    @property
    def n_frames(self) -> int:
        return self.t.shape[1]


def padded_length(n: int, multiple: int) -> int:
    return max(multiple, int(math.ceil(n / multiple)) * multiple)


LADDER_RATIO = 2**0.25
"""Step between padded lengths of the ladder: at most 19 % padding, 4 rungs per doubling, so a study's
runs of 1,000 to 4,000 frames share 9 compiled shapes whatever their exact lengths."""


def ladder(n: int, *, ratio: float = LADDER_RATIO, multiple: int = 64) -> int:
    """The smallest rung >= n of the geometric ladder multiple, multiple * ratio, multiple * ratio^2, ...
    (each rung rounded up to `multiple`).

    Padded shapes taken from the ladder are few (about log(longest / shortest) / log(ratio)), so a
    compiled function keyed on them is reused across runs, buckets and studies of similar lengths.
    """
    if n < 1:
        raise ValueError(f"ladder: n must be >= 1, got {n}")
    if ratio <= 1.0:
        raise ValueError(f"ladder: ratio must be > 1, got {ratio}")
    k = max(0, math.floor(math.log(n / multiple) / math.log(ratio))) if n > multiple else 0
    while True:  # from just below n: float logs may land a rung low
        rung = padded_length(math.ceil(multiple * ratio**k - 1e-9), multiple)
        if rung >= n:
            return rung
        k += 1


def bucket_by_ladder(
    lengths: Sequence[int] | Int[np.ndarray, " R"], *, ratio: float = LADDER_RATIO, multiple: int = 64
) -> list[np.ndarray]:
    """Group run indices by their rung of `ladder`: one group per padded length, shortest first.

    Returns:
        Index arrays into `lengths`, each sorted ascending by length, covering every run exactly once;
        group g pads to `ladder(max(lengths[g]))`.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    if lengths.size == 0:
        return []
    order = np.argsort(lengths, kind="stable")
    rungs = np.array([ladder(int(n), ratio=ratio, multiple=multiple) for n in lengths[order]])
    cuts = np.flatnonzero(np.diff(rungs)) + 1
    return [g.astype(np.int64) for g in np.split(order, cuts)]


def bucket_by_length(
    lengths: Sequence[int] | Int[np.ndarray, " R"], *, max_padding: float = 0.1, pad_multiple: int = 64
) -> list[np.ndarray]:
    """Group run indices so that the padding a group adds stays within `max_padding` of its frames.

    Runs are sorted by length; a group is closed when adding the next (longer) run would make the
    padding beyond each run's own rounding to `pad_multiple` exceed `max_padding` x the group's
    rounded frames. Runs of equal length therefore always share a group, whatever the multiple, and
    padded lengths are multiples of `pad_multiple` so that similar buckets share a compiled shape.

    Returns:
        Index arrays into `lengths`, each sorted ascending by length, covering every run exactly once.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    if lengths.size == 0:
        return []
    order = np.argsort(lengths, kind="stable")
    groups: list[list[int]] = []
    current: list[int] = []
    own = 0  # sum of the group's lengths, each rounded up to pad_multiple on its own
    for idx in order:
        rounded = padded_length(int(lengths[idx]), pad_multiple)
        # Sorted ascending: the new run sets the group's padded length.
        extra = rounded * (len(current) + 1) - (own + rounded)
        if current and extra > max_padding * (own + rounded):
            groups.append(current)
            current, own = [], 0
        current.append(int(idx))
        own += rounded
    groups.append(current)
    return [np.asarray(g, dtype=np.int64) for g in groups]


def take_runs(batch: LogBatch, index: np.ndarray | Array) -> LogBatch:
    """The sub-batch of the given run indices (a gather on the leading axis of every leaf)."""
    index = jnp.asarray(index)
    return jax.tree.map(lambda x: x[index], batch)


def pad_runs(batch: LogBatch, n_runs: int) -> LogBatch:
    """Append padding runs (valid False everywhere, run_index -1) up to `n_runs` runs.

    A batch of numpy leaves is padded in numpy (host-side chunking that compiles nothing); otherwise
    in jax.numpy.
    """
    extra = n_runs - batch.n_runs
    if extra < 0:
        raise ValueError(f"pad_runs: batch has {batch.n_runs} runs, more than n_runs={n_runs}")
    if extra == 0:
        return batch
    xp = np if all(isinstance(x, np.ndarray) for x in jax.tree.leaves(batch)) else jnp

    def pad(x):
        return xp.concatenate([x, xp.repeat(x[-1:], extra, axis=0)], axis=0)

    padded = jax.tree.map(pad, batch)
    keep = xp.arange(n_runs) < batch.n_runs
    return eqx.tree_at(
        lambda b: (b.valid, b.gt_valid, b.run_index),
        padded,
        (
            padded.valid & keep[:, None],
            padded.gt_valid & keep[:, None],
            xp.where(keep, padded.run_index, -1),
        ),
    )


def iter_chunks(batch: LogBatch, runs_per_chunk: int) -> Iterator[tuple[slice, LogBatch]]:
    """Yield (run slice, chunk) pairs; every chunk has exactly `runs_per_chunk` runs (the last is
    padded) so one compiled function serves them all. Results for padding runs must be dropped by
    the caller using the slice (or run_index == -1)."""
    if runs_per_chunk < 1:
        raise ValueError(f"iter_chunks: runs_per_chunk must be >= 1, got {runs_per_chunk}")
    for start in range(0, batch.n_runs, runs_per_chunk):
        stop = min(start + runs_per_chunk, batch.n_runs)
        chunk = jax.tree.map(lambda x, a=start, b=stop: x[a:b], batch)
        yield slice(start, stop), pad_runs(chunk, runs_per_chunk)


def ladder_chunk_size(n_runs: int, cap: int, *, ratio: float = 2**0.5, multiple: int = 8) -> int:
    """Runs per chunk for a bucket of `n_runs` runs with at most `cap` runs a chunk: the fewest chunks,
    all of one size taken from a coarse ladder (8, 16, 24, 32, 48, 64, 96, 128, ...; `ladder`), so a
    bucket compiles once and buckets of similar sizes share the shape. At most 41 % padding runs
    beyond the rounding to `multiple`; `cap` itself where one chunk does not suffice."""
    if n_runs < 1 or cap < 1:
        raise ValueError(f"ladder_chunk_size: n_runs and cap must be >= 1, got {n_runs} and {cap}")
    n_chunks = math.ceil(n_runs / cap)
    return min(cap, ladder(math.ceil(n_runs / n_chunks), ratio=ratio, multiple=multiple))


DEVICE_BUDGET_BYTES = 1.5e9
"""Working set of one compiled evaluation (inputs, replay outputs, temporaries): 1.5 GB keeps `jsve
evaluate` of any study under 3 GB with the host's chunk being read beside it, while chunks stay
hundreds of runs long (600 runs of 4,096 frames), past which a larger chunk is not faster."""


def runs_per_chunk_for(
    n_frames: int, *, bytes_budget: float = DEVICE_BUDGET_BYTES, bytes_per_frame: int = 600
) -> int:
    """How many runs of `n_frames` fit a device-memory budget, counting inputs, replay outputs and
    temporaries at about `bytes_per_frame` (float32)."""
    return max(1, int(bytes_budget // (bytes_per_frame * max(n_frames, 1))))
