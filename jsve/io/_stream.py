"""A Parquet study (from `jsve ingest`) as LogBatch chunks, straight from Arrow, with bounded memory.

`read_parquet` gives one pandas frame per run, and `jsve.io._batching.from_runs` copies each into the
padded arrays run by run: at 8 M frames that is gigabytes of frames and a minute of Python. Here the
file is read in Arrow record batches, every column turned into one numpy array per batch, and whole
runs are scattered into the padded arrays of their length bucket with one fancy-indexed assignment per
column. A bucket's arrays are handed on (as a Bucket) the moment they hold `chunk` runs, so memory
follows the chunk sizes, never the study: at most one partly filled chunk per bucket is held.

Dtypes are the compact ones of LogBatch (bins uint16, counts int32, state int8, map ranks int32, poses
float32 unless float64 is asked for); times are int64 ns in the file and become float seconds since
each run's first frame after an exact int64 difference. Each Bucket is exactly what `from_runs` builds
for the same runs (tests/test_stream.py checks every leaf), padded to the chunk size by `pad_runs`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from jsve.core._batch import (
    DEVICE_BUDGET_BYTES,
    LADDER_RATIO,
    LogBatch,
    bucket_by_ladder,
    ladder,
    ladder_chunk_size,
    runs_per_chunk_for,
)
from jsve.io import _schema as schema
from jsve.io._batching import Bucket, meta_table
from jsve.io._errors import LogFormatError
from jsve.io._saved_trajectory import SAVED_COLUMN, largest_map_frames
from jsve.io._world import segment_last_frame, to_last_world_frame

PARQUET_RUNS_KEY = b"jsve.runs"
"""Parquet key-value metadata key: a JSON list of {run_id, source, meta, n_frames, has_ground_truth}."""

PARQUET_FORMAT_KEY = b"jsve.format"
PARQUET_FORMAT_VERSION = 3
"""The study layout written: format v2's columns, and `in_saved` for runs of v3 logs with ORB-SLAM3's
trailer, whose poses are stored in the saved trajectory's frame (jsve.io._saved_trajectory); a log's
keyframe columns and trailers themselves stay in the log."""
PARQUET_READ_VERSIONS = (1, 2, 3)
"""Parquet key-value metadata key: the log format version of its columns, "2" (files written before v2
say "1" and have no map_id / imu_ba2: read_parquet fills v1 defaults)."""

HOST_BYTES_PER_FRAME = 263
"""Bytes a frame takes in a float32 LogBatch on the host: 64 uint16 bins (128), 28 float32 pose, IMU
and ground-truth values (112), 4 int32 counts and map rank (16), t (4) and 6 flags."""

DEFAULT_HOST_BUDGET = 0.6e9
"""Bytes of partly filled chunks held at once, shared by the buckets (`iter_buckets`)."""


@dataclass(frozen=True)
class ParquetStudy:
    """What a jsve Parquet file says about its runs, read from its footer without the frames.

    Attributes:
        path: the file.
        version: its jsve format (1 or 2).
        entries: the run list (`jsve.runs`: run_id, source, meta, n_frames, has_ground_truth, ...),
            in file order.
        columns: the frame columns the file has.
    """

    path: str
    version: int
    entries: list[dict]
    columns: tuple[str, ...]
    lengths: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "lengths", np.array([e["n_frames"] for e in self.entries], np.int64))

    @property
    def n_runs(self) -> int:
        return len(self.entries)

    @property
    def n_frames(self) -> int:
        return int(self.lengths.sum())

    def file_order(self, run_ids) -> np.ndarray:
        """Position in the file of each run id (for putting per-run results back in file order)."""
        index = {e["run_id"]: i for i, e in enumerate(self.entries)}
        return np.array([index[r] for r in run_ids], np.int64)


def open_study(path: str | os.PathLike) -> ParquetStudy:
    """The run list and format of a Parquet file written by `ingest`, checked against its rows' count.

    Raises:
        LogFormatError: not a jsve Parquet file, a format this reader does not know, a row count that
            disagrees with the run list, or required columns missing.
    """
    source = os.fspath(path)
    pf = pq.ParquetFile(source)
    kv = pf.metadata.metadata or {}
    if PARQUET_RUNS_KEY not in kv:
        raise LogFormatError(
            source, None, f"not a jsve Parquet file: no {PARQUET_RUNS_KEY.decode()!r} metadata"
        )
    version_text = kv.get(PARQUET_FORMAT_KEY, b"").decode("utf-8", errors="replace")
    if version_text not in {str(v) for v in PARQUET_READ_VERSIONS}:
        raise LogFormatError(
            source,
            None,
            f"unsupported jsve Parquet format {version_text!r} in its {PARQUET_FORMAT_KEY.decode()!r} "
            f"metadata (this reader reads {' and '.join(map(str, PARQUET_READ_VERSIONS))})",
        )
    version = int(version_text)
    study = ParquetStudy(source, version, json.loads(kv[PARQUET_RUNS_KEY]), tuple(pf.schema_arrow.names))
    if pf.metadata.num_rows != study.n_frames:
        raise LogFormatError(
            source, None, f"has {pf.metadata.num_rows} rows but its run list accounts for {study.n_frames}"
        )
    lacking = [c for c in schema.required_columns(version) + schema.GT_COLUMNS if c not in study.columns]
    if lacking:
        raise LogFormatError(
            source, None, f"a format-{version} jsve Parquet file without the column(s) {', '.join(lacking)}"
        )
    world = [c for c in schema.WORLD_COLUMNS if c in study.columns]
    for e in study.entries:
        if e.get("has_world_frame", False) and len(world) < len(schema.WORLD_COLUMNS):
            raise LogFormatError(
                source,
                None,
                f"run {e['run_id']!r} has world_* columns in its run list but the file lacks them",
            )
    return study


# --------------------------------------------------------------------------------------------------
# Blocks of whole runs, as numpy columns


@dataclass
class _Block:
    """Frames of runs `first .. first + len(starts) - 1` (file order), end to end, as numpy columns."""

    first: int
    starts: np.ndarray  # [n] row of each run's first frame in the block
    lengths: np.ndarray  # [n]
    cols: dict[str, np.ndarray]


def _blocks(
    study: ParquetStudy, columns: list[str], batch_rows: int, row_groups: list[int] | None = None
) -> Iterator[_Block]:
    """Whole runs in file order, a few Arrow record batches at a time; the rows' grouping (run_id,
    frame) is checked against the run list as they come.

    row_groups: read only these row groups of the file (sorted): the runs wholly inside each stretch
    of consecutive ones come, a run cut by a stretch's edge does not. None: every run of the file.
    """
    # pre_buffer off: with it, Arrow's reader keeps every row group it has read (about 1 GB per 60
    # batches of a 3,600-frame study), so memory grows with the study; without it memory stays flat.
    pf = pq.ParquetFile(study.path, pre_buffer=False)
    first_row = _row_group_starts(pf)
    groups = list(range(pf.num_row_groups)) if row_groups is None else list(row_groups)
    for stretch in _consecutive(groups):
        yield from _stretch_blocks(pf, study, columns, batch_rows, stretch, first_row)


def _row_group_starts(pf: pq.ParquetFile) -> np.ndarray:
    """File row of each row group's first row, and the file's row count after them."""
    counts = [pf.metadata.row_group(i).num_rows for i in range(pf.num_row_groups)]
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)


def _consecutive(groups: list[int]) -> list[list[int]]:
    """Sorted row group numbers cut into stretches of consecutive ones."""
    stretches: list[list[int]] = []
    for g in groups:
        if stretches and stretches[-1][-1] == g - 1:
            stretches[-1].append(g)
        else:
            stretches.append([g])
    return stretches


def _stretch_blocks(pf, study, columns, batch_rows, groups: list[int], first_row: np.ndarray):
    """`_blocks` of one stretch of consecutive row groups: its rows before the first run that starts in
    it are skipped, and a run that goes on past its end is left out (the whole file: an error)."""
    offsets = np.concatenate([[0], np.cumsum(study.lengths)])
    whole_file = groups[0] == 0 and groups[-1] == pf.num_row_groups - 1
    start_row, end_row = int(first_row[groups[0]]), int(first_row[groups[-1] + 1])
    run = int(np.searchsorted(offsets[:-1], start_row, side="left"))  # the first run not yet handed on
    skip = int(offsets[run]) - start_row if run < study.n_runs else end_row - start_row
    pending: list[pa.RecordBatch] = []
    row0 = start_row + skip  # file row of the first pending row
    n_pending = 0
    batches = pf.iter_batches(
        batch_size=batch_rows, row_groups=groups, columns=["run_id", "frame", *columns], use_threads=True
    )
    for rb in batches:
        if skip:  # the tail of a run that began before the stretch
            cut = min(skip, rb.num_rows)
            rb, skip = rb.slice(cut), skip - cut
        pending.append(rb)
        n_pending += rb.num_rows
        # Runs wholly inside the pending rows.
        stop = int(np.searchsorted(offsets, row0 + n_pending, side="right")) - 1
        if stop <= run:
            continue
        table = pa.Table.from_batches(pending)
        n_rows = int(offsets[stop] - row0)
        block, rest = table.slice(0, n_rows), table.slice(n_rows)
        check_run_rows(study, block, first_run=run, stop_run=stop)
        cols = {c: _column(block, c) for c in columns}
        yield _Block(run, offsets[run:stop] - row0, study.lengths[run:stop], cols)
        pending, n_pending = rest.to_batches(), rest.num_rows
        row0, run = row0 + n_rows, stop
    if whole_file and (run != study.n_runs or n_pending):
        raise LogFormatError(study.path, None, "rows end before the runs of its run list do")


def _column(table: pa.Table, name: str) -> np.ndarray:
    """A column as one numpy array; nulls (a run without gt_* / world_*) become NaN."""
    column = table.column(name)
    if column.num_chunks == 1:
        return column.chunk(0).to_numpy(zero_copy_only=False)
    return column.to_numpy()


def check_run_rows(study: ParquetStudy, rows: pa.Table, *, first_run: int, stop_run: int) -> None:
    """Raise LogFormatError unless `rows` (run_id and frame columns) are exactly the frames of runs
    first_run .. stop_run - 1 of the run list, grouped by run in its order, frames 0, 1, 2 ..."""
    lengths = study.lengths[first_run:stop_run]
    index = {e["run_id"]: i for i, e in enumerate(study.entries)}
    ids = []
    for chunk in rows.column("run_id").chunks:
        lut = np.array([index.get(s, -1) for s in chunk.dictionary.to_pylist()] or [-1], np.int64)
        ids.append(lut[chunk.indices.to_numpy(zero_copy_only=False)])
    ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    expected_frame = np.arange(int(lengths.sum())) - np.repeat(starts, lengths)
    frame = rows.column("frame").to_numpy()
    if not (
        np.array_equal(ids, np.repeat(np.arange(first_run, stop_run), lengths))
        and np.array_equal(frame, expected_frame)
    ):
        raise LogFormatError(study.path, None, "rows are not grouped by run in the order of its run list")


def _stack(cols: dict[str, np.ndarray], names, dtype) -> np.ndarray:
    """Columns side by side as one [n, k] array of `dtype` (filled column by column into a transposed
    buffer: far faster than column_stack for 64 bins)."""
    out = np.empty((len(names), len(cols[names[0]])), dtype)
    for k, name in enumerate(names):
        out[k] = cols[name]
    return out.T


# --------------------------------------------------------------------------------------------------
# Per-frame values of a block, as LogBatch wants them


def _frame_values(study: ParquetStudy, block: _Block, fdt) -> dict[str, np.ndarray]:
    """A block's frames as LogBatch's per-frame leaves (flat [N, ...]) plus per-run t0_ns."""
    c = block.cols
    n_runs = len(block.starts)
    run_of = np.repeat(np.arange(n_runs), block.lengths)
    run_start = np.zeros(len(run_of), bool)
    run_start[block.starts] = True
    t_ns = c["t_ns"].astype(np.int64)
    t0 = t_ns[block.starts]
    vis_p, vis_q, vis_v = (_stack(c, names, np.float64) for names in
                           (schema.VIS_POSITION, schema.VIS_QUATERNION, schema.VIS_VELOCITY))  # fmt: skip
    posed = np.isfinite(vis_p).all(axis=1)
    if study.version == 1:
        map_id = np.zeros(len(run_of), np.int64)
        ba2 = np.concatenate([
            schema.v1_defaults(t_ns[a : a + n], c["imu_init"][a : a + n])["imu_ba2"]
            for a, n in zip(block.starts, block.lengths, strict=True)
        ])  # fmt: skip
    else:
        map_id, ba2 = c["map_id"].astype(np.int64), c["imu_ba2"]
    entries = study.entries[block.first : block.first + n_runs]
    has_world = np.array([bool(e.get("has_world_frame", False)) for e in entries])
    if has_world.any():
        vis_p, vis_q, vis_v = _in_one_world_frame(c, entries, has_world[run_of], run_of, run_start,
                                                  posed, map_id, vis_p, vis_q, vis_v)  # fmt: skip
    gt_p = _stack(c, schema.GT_POSITION, np.float64)
    gt_q = _stack(c, schema.GT_QUATERNION, np.float64)
    gt_ok = np.isfinite(gt_p).all(axis=1) & np.isfinite(gt_q).all(axis=1)
    return {
        "t": ((t_ns - np.repeat(t0, block.lengths)) / 1e9).astype(fdt),
        "state": c["state"].astype(np.int8),
        "imu_init": c["imu_init"] != 0,
        "imu_ba2": np.asarray(ba2) != 0,
        "map_id": _map_ranks(run_of, map_id),
        "has_pose": posed,
        "in_saved": _in_saved(c, posed, map_id, run_start),
        "n_extracted": c["n_extracted"].astype(np.int32),
        "n_inliers": c["n_inliers"].astype(np.int32),
        "n_frustum": c["n_frustum"].astype(np.int32),
        "bins": _stack(c, schema.BIN_COLUMNS, np.uint16),
        "vis_p": np.where(posed[:, None], vis_p, 0.0).astype(fdt),
        "vis_q": np.where(posed[:, None], vis_q, np.array([1.0, 0, 0, 0])).astype(fdt),
        "vis_v": np.where(posed[:, None], vis_v, 0.0).astype(fdt),
        "imu_dt": c["imu_dt"].astype(fdt),
        "imu_dp": _stack(c, schema.IMU_DP, fdt),
        "imu_dv": _stack(c, schema.IMU_DV, fdt),
        "imu_dq": _stack(c, schema.IMU_DQ, fdt),
        "gt_p": np.where(gt_ok[:, None], gt_p, 0.0).astype(fdt),
        "gt_q": np.where(gt_ok[:, None], gt_q, np.array([1.0, 0, 0, 0])).astype(fdt),
        "gt_valid": gt_ok,
        "t0_ns": t0,
    }


def _in_saved(c, posed, map_id, run_start) -> np.ndarray:
    """The block's LogBatch.in_saved: the stored column where a run has one (v3 logs with ORB-SLAM3's
    trailer, jsve.io._saved_trajectory.in_saved_frame), else largest_map_frames."""
    default = largest_map_frames(posed, map_id, run_start)
    stored = c.get(SAVED_COLUMN)
    if stored is None:
        return default
    stored = np.asarray(stored, np.float64)  # null (NaN) for runs without it
    return np.where(np.isnan(stored), default, stored != 0)


def _map_ranks(run_of: np.ndarray, map_id: np.ndarray) -> np.ndarray:
    """`map_ranks` of every run at once: dense ranks of each run's distinct map ids."""
    if len(run_of) == 0:
        return np.zeros(0, np.int32)
    if not map_id.any():
        return np.zeros(len(run_of), np.int32)
    order = np.lexsort((map_id, run_of))
    r, m = run_of[order], map_id[order]
    new_run = np.concatenate([[True], r[1:] != r[:-1]])
    new_id = new_run | np.concatenate([[True], m[1:] != m[:-1]])
    distinct = np.cumsum(new_id) - 1  # global rank of the (run, id) pair
    first_of_run = np.maximum.accumulate(np.where(new_run, distinct, 0))
    ranks = np.empty(len(run_of), np.int32)
    ranks[order] = distinct - first_of_run
    return ranks


def _in_one_world_frame(c, entries, world, run_of, run_start, posed, map_id, p, q, v):
    """jsve.io._world.in_one_world_frame for every run of the block at once (runs with world_*)."""
    t_bc = np.array([e["meta"].get("camera_in_body") or [1.0, 0, 0, 0, 0, 0, 0] for e in entries], np.float64)
    last = segment_last_frame(posed, map_id, run_start)
    world_q = _stack(c, schema.WORLD_QUATERNION, np.float64)
    world_t = _stack(c, schema.WORLD_TRANSLATION, np.float64)
    world_s = np.asarray(c[schema.WORLD_SCALE], np.float64)
    # Runs without world_* (null there: NaN) keep their poses; identity similarities make that so.
    world_q = np.where(world[:, None], world_q, np.array([1.0, 0, 0, 0]))
    world_t = np.where(world[:, None], world_t, 0.0)
    world_s = np.where(world, world_s, 1.0)
    moved = to_last_world_frame(p, q, v, world_q, world_t, world_s, last, t_bc[run_of])
    keep = (world & posed)[:, None]
    return tuple(np.where(keep, new, old) for new, old in zip(moved, (p, q, v), strict=True))


# --------------------------------------------------------------------------------------------------
# Chunks


class _Chunk:
    """A chunk of one bucket being filled: [capacity, n_frames] arrays and the runs' metadata."""

    FRAME_LEAVES = ("t", "state", "imu_init", "imu_ba2", "map_id", "has_pose", "in_saved", "n_extracted",
                    "n_inliers", "n_frustum", "bins", "vis_p", "vis_q", "vis_v", "imu_dt", "imu_dp", "imu_dv",
                    "imu_dq", "gt_p", "gt_q", "gt_valid")  # fmt: skip

    def __init__(self, capacity: int, n_frames: int, like: dict[str, np.ndarray]):
        self.capacity, self.n_frames, self.n = capacity, n_frames, 0
        # np.zeros: pages come zeroed from the OS as they are first written, no pass of its own.
        self.arrays = {
            name: np.zeros((capacity, n_frames) + like[name].shape[1:], like[name].dtype)
            for name in self.FRAME_LEAVES
        }
        for name in ("vis_q", "imu_dq", "gt_q"):
            self.arrays[name][..., 0] = 1.0
        self.valid = np.zeros((capacity, n_frames), bool)
        self.records: list[tuple] = []
        self.run_scalars: list[tuple] = []

    def add(self, values: dict[str, np.ndarray], starts, lengths, records, scalars) -> None:
        """Copy whole runs (rows `starts[i]:starts[i]+lengths[i]` of the flat `values`) into the next
        slots: one contiguous slice per run and column (a run is contiguous on both sides, so this is
        memcpy, several times faster than one fancy-indexed scatter)."""
        slots = range(self.n, self.n + len(starts))
        for name in self.FRAME_LEAVES:
            src, dst = values[name], self.arrays[name]
            for slot, a, n in zip(slots, starts, lengths, strict=True):
                dst[slot, :n] = src[a : a + n]
        for slot, n in zip(slots, lengths, strict=True):
            self.valid[slot, :n] = True
        self.records.extend(records)
        self.run_scalars.extend(scalars)
        self.n += len(starts)

    def bucket(self, fdt) -> Bucket:
        """The filled runs as a Bucket of `capacity` runs, padded in place as `pad_runs` pads (the last
        real run repeated, invalid, run_index -1), without copying the chunk."""
        n, a = self.n, self.arrays
        rows = np.arange(n)
        t, posed, init, ba2 = a["t"][:n], a["has_pose"][:n], a["imu_init"][:n], a["imu_ba2"][:n]
        # Delays from the recorded run's first map (its first posed frame), as from_runs has them.
        t_first = np.where(posed.any(1), t[rows, np.argmax(posed, 1)], 0.0)
        delay = np.where(init.any(1), t[rows, np.argmax(init, 1)] - t_first, np.inf).astype(fdt)
        ba2_delay = np.where(ba2.any(1), t[rows, np.argmax(ba2, 1)] - t_first, np.inf).astype(fdt)
        fps, gravity, n_features, stereo = (np.array(x) for x in zip(*self.run_scalars, strict=True))
        per_run = {
            "fps": fps.astype(fdt),
            "gravity": gravity.astype(fdt).reshape(n, 3),
            "imu_init_delay": delay,
            "ba2_delay": ba2_delay,
            "n_features": n_features.astype(fdt),
            "stereo": stereo.astype(bool),
        }
        if n < self.capacity:
            for x in a.values():
                x[n:] = x[n - 1]
            a["gt_valid"][n:] = False  # valid[n:] is False already
            per_run = {
                k: np.concatenate([v, np.repeat(v[-1:], self.capacity - n, axis=0)])
                for k, v in per_run.items()
            }
        run_index = np.where(np.arange(self.capacity) < n, np.arange(self.capacity), -1).astype(np.int32)
        batch = LogBatch(**a, valid=self.valid, **per_run, run_index=run_index)
        return Bucket(batch=batch, meta=meta_table(self.records))


def _run_scalars(entry: dict) -> tuple:
    meta = entry["meta"]
    return (
        float(meta["fps"]),
        list(meta.get("gravity", schema.DEFAULT_GRAVITY)),
        meta.get("n_features", schema.DEFAULT_N_FEATURES),
        meta.get("sensor", "imu_monocular") in schema.STEREO_SENSORS,
    )


def chunk_plan(
    lengths: np.ndarray, *, ratio: float = LADDER_RATIO, host_budget: float = DEFAULT_HOST_BUDGET,
    device_budget: float = DEVICE_BUDGET_BYTES, fdt=np.float32,
) -> tuple[np.ndarray, list[int], list[int]]:  # fmt: skip
    """Bucket of each run, and each bucket's padded length and chunk size (runs).

    A chunk is at most what the device budget allows (`runs_per_chunk_for`) and at most the bucket's
    share of the host budget (one partly filled chunk per bucket is held while the file streams), and
    its size is `ladder_chunk_size`'s, so that `jsve.evaluation.evaluate` keeps it as one compiled
    chunk shape.
    """
    groups = bucket_by_ladder(lengths, ratio=ratio)
    bucket_of = np.empty(len(lengths), np.int64)
    n_frames, sizes = [], []
    per_frame = HOST_BYTES_PER_FRAME * (2 if np.dtype(fdt).itemsize == 8 else 1)
    for g, runs in enumerate(groups):
        bucket_of[runs] = g
        frames = ladder(int(lengths[runs[-1]]), ratio=ratio)
        host_cap = max(1, int(host_budget / len(groups) // (per_frame * frames)))
        cap = min(runs_per_chunk_for(frames, bytes_budget=device_budget), host_cap)
        n_frames.append(frames)
        sizes.append(ladder_chunk_size(len(runs), cap))
    return bucket_of, n_frames, sizes


def iter_buckets(
    study: ParquetStudy | str | os.PathLike,
    *,
    dtype=jnp.float32,
    ratio: float = LADDER_RATIO,
    host_budget: float = DEFAULT_HOST_BUDGET,
    batch_rows: int = 131_072,
    by_length: bool = False,
) -> Iterator[Bucket]:
    """The study's runs as Buckets of one chunk each, streamed from the file (see the module docstring).

    Every Bucket's batch has numpy leaves, `chunk` runs (its last ones padding where the bucket ran out:
    run_index -1) of its bucket's padded length; its meta has one row per real run. Runs come in the
    order their chunks fill, not file order (ParquetStudy.file_order puts results back).

    Arguments:
        study: a ParquetStudy (`open_study`) or the file's path.
        dtype: float dtype of the arrays (float64 needs jax_enable_x64).
        ratio: the padded-length ladder's step.
        host_budget: bytes of partly filled chunks held at once (the peak follows it, not the study).
        batch_rows: rows per Arrow record batch read.
        by_length: every chunk of a length bucket before any of the next, shortest first, read bucket by
            bucket from the row groups that hold its runs (those shared by two buckets are read twice;
            where that would read more than READ_AGAIN_AT_MOST times the file, the file is read once
            and the chunks come as they fill). A pass that compiles per chunk shape then meets each
            shape once, so what it compiled for one length can be dropped for good (jsve._memory).
    """
    if not isinstance(study, ParquetStudy):
        study = open_study(study)
    if study.n_runs == 0:
        return
    fdt = np.dtype(jnp.dtype(dtype).name)
    bucket_of, n_frames, sizes = chunk_plan(study.lengths, ratio=ratio, host_budget=host_budget, fdt=fdt)
    wanted = (
        schema.required_columns(study.version) + schema.GT_COLUMNS + schema.WORLD_COLUMNS + (SAVED_COLUMN,)
    )
    columns = [c for c in wanted if c in study.columns]
    plan = _reading_by_length(study, bucket_of) if by_length else None
    if plan is None:
        yield from _fill(study, _blocks(study, columns, batch_rows), bucket_of, n_frames, sizes, fdt)
        return
    for g in np.argsort(n_frames, kind="stable"):
        only_g = np.where(bucket_of == g, g, -1)
        blocks = _blocks(study, columns, batch_rows, row_groups=plan[g])
        handed = 0
        for bucket in _fill(study, blocks, only_g, n_frames, sizes, fdt):
            handed += len(bucket.meta)
            yield bucket
        if handed != np.count_nonzero(only_g >= 0):  # never a bucket short of runs without a word
            raise LogFormatError(
                study.path, None, f"row groups {plan[g]} hold {handed} of the "
                f"{np.count_nonzero(only_g >= 0)} runs of {n_frames[g]} frames its run list places there",
            )  # fmt: skip


READ_AGAIN_AT_MOST = 1.5
"""`iter_buckets(by_length=True)` reads the file bucket by bucket only where that reads at most this
many times its rows (row groups shared by buckets are read once for each)."""


def _reading_by_length(study: ParquetStudy, bucket_of: np.ndarray) -> dict[int, list[int]] | None:
    """The row groups holding each bucket's runs, or None where reading them bucket by bucket would
    read more than READ_AGAIN_AT_MOST times the file's rows."""
    first_row = _row_group_starts(pq.ParquetFile(study.path))
    offsets = np.concatenate([[0], np.cumsum(study.lengths)])
    plan, rows = {}, 0
    for g in np.unique(bucket_of):
        runs = np.flatnonzero(bucket_of == g)
        first = np.searchsorted(first_row, offsets[runs], side="right") - 1
        last = np.searchsorted(first_row, offsets[runs + 1] - 1, side="right") - 1
        groups = sorted({int(k) for a, b in zip(first, last, strict=True) for k in range(a, b + 1)})
        plan[int(g)] = groups
        rows += int(sum(first_row[k + 1] - first_row[k] for k in groups))
    return plan if rows <= READ_AGAIN_AT_MOST * study.n_frames else None


def _fill(study, blocks, bucket_of, n_frames, sizes, fdt) -> Iterator[Bucket]:
    """Blocks' runs scattered into their buckets' chunks, each handed on when full and the partly filled
    ones at the end; runs of bucket -1 are passed over."""
    open_chunks: dict[int, _Chunk] = {}
    for block in blocks:
        values = _frame_values(study, block, fdt)
        runs = np.arange(block.first, block.first + len(block.starts))
        for g in np.unique(bucket_of[runs]):
            if g < 0:
                continue
            mine = np.flatnonzero(bucket_of[runs] == g)
            while len(mine):
                chunk = open_chunks.get(g) or _Chunk(sizes[g], n_frames[g], values)
                open_chunks[g] = chunk
                take, mine = mine[: chunk.capacity - chunk.n], mine[chunk.capacity - chunk.n :]
                entries = [study.entries[block.first + i] for i in take]
                records = [(e["run_id"], e["source"], e["n_frames"], int(t0), e["meta"])
                           for e, t0 in zip(entries, values["t0_ns"][take], strict=True)]  # fmt: skip
                chunk.add(values, block.starts[take], block.lengths[take], records,
                          [_run_scalars(e) for e in entries])  # fmt: skip
                if chunk.n == chunk.capacity:
                    yield chunk.bucket(fdt)
                    del open_chunks[g]
    for g in sorted(open_chunks):
        yield open_chunks[g].bucket(fdt)


__all__ = ["ParquetStudy", "check_run_rows", "chunk_plan", "iter_buckets", "open_study"]
