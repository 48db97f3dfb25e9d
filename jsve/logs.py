"""Tracking logs, format v1: write, read and validate, batch-read, ground truth, Parquet.

The I/O edge of jsve (docs/log-format.md describes the format for people; jsve.schema is the one
home of its names). Everything downstream receives `RunLog`s whose frames have been validated here:

    write_log(run, path)                 one run -> one CSV log, atomically (`<path>.partial`, then rename)
    read_log(path)                       one CSV log -> RunLog, strict; any defect raises LogFormatError
    read_logs(source)                    many logs, in parallel, sorted, raise or quarantine
    associate_ground_truth(run, file)    gt_* columns from an EuRoC / TUM / KITTI trajectory
    ingest(source, out)                  many logs -> one Parquet file;  read_parquet(out) -> RunLogs

Errors name the file, the 1-based line, the column and the value as written in the file, e.g.
`logs/r7.csv:1288: column 'imu_dt' = '-0.05': must be >= 0`.

Parsing uses Arrow's CSV reader with one explicit type per column: int64 columns (t_ns above all)
never pass through float, and floats are parsed correctly rounded, so a log written by `write_log`
(shortest round-trip decimal representation, as Python's repr) reads back bit for bit.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import glob as globlib
import json
import logging
import math
import multiprocessing
import os
import re
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
from tqdm.auto import tqdm

from . import schema
from .schema import RunLog

logger = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".partial"
"""A file whose name ends in this is a log (or Parquet file) that its writer has not finished."""

GT_FORMATS = ("euroc", "tum", "kitti")
"""Ground-truth file formats accepted by `associate_ground_truth`."""

DEFAULT_MAX_GAP_NS = 200_000_000
"""Default largest gap (ns) between two ground-truth samples that a frame may be interpolated across.

0.2 s covers EuRoC's 200 Hz state estimate and ORB-SLAM3's 20 Hz left-camera files (50 ms) and KITTI's
10 Hz poses (~104 ms), and leaves frames in genuine ground-truth dropouts without ground truth."""

GT_METADATA = {"gt_missing_frames": int, "gt_source": str}
"""Metadata keys written by `associate_ground_truth`: frames left without ground truth (count) and
the ground-truth file used."""

QUARANTINE_COLUMNS = ("path", "line", "column", "reason", "message", "incomplete")
"""Columns of the quarantine report (`ReadResult.report()`, `write_quarantine_report`)."""

PARQUET_RUNS_KEY = b"jsve.runs"
"""Parquet key-value metadata key: a JSON list of {run_id, source, meta, n_frames, has_ground_truth}."""

PARQUET_FORMAT_KEY = b"jsve.format"

_NOT_LOGS = tuple(s + p for s in (".quarantine.csv", ".keypoints.csv") for p in ("", PARTIAL_SUFFIX))
"""CSV files a directory search skips: quarantine reports and keypoint side files (jsve.keypoints)."""

_INT_SET = frozenset(schema.INT_COLUMNS)
_GT_SET = frozenset(schema.GT_COLUMNS)
_MAX_SHOWN = 80  # characters of a value shown in a message
_ROW_GROUP_ROWS = 262_144  # Parquet row group target: ~70 runs of 3,600 frames, ~200 MB in memory
_MIN_LOGS_PER_WORKER = 8  # below 16 logs in all, starting processes (~1 s) costs more than it saves
_MAX_WORKER_WARNINGS = 20  # warnings from worker processes re-emitted per batch, then one summary line

OnError = Literal["raise", "quarantine"]


# --------------------------------------------------------------------------------------------------
# Errors


class LogFormatError(ValueError):
    """A tracking log (or jsve Parquet file) that does not follow format v1.

    The message reads `path:line: column 'name' = 'value': reason`; parts that do not apply are left
    out (`path: reason` when the problem has no line, e.g. a `.partial` file).

    Attributes:
        path: the file, as given to the reader.
        line: 1-based line number in the file, or None (in-memory runs report `frame` instead).
        column: the column (or metadata key, or column range such as 'vis_qw..vis_qz'), or None.
        value: the offending value as written in the file, or None.
        reason: what is wrong, in words.
        frame: 0-based frame index, for runs validated in memory (`validate_run`, `write_log`).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        line: int | None,
        reason: str,
        *,
        column: str | None = None,
        value: str | None = None,
        what: str = "column",
        frame: int | None = None,
    ):
        self.path = os.fspath(path)
        self.line = line
        self.reason = reason
        self.column = column
        self.value = value
        self.what = what
        self.frame = frame
        super().__init__(self._message())

    def _message(self) -> str:
        loc = self.path
        if self.line is not None:
            loc = f"{loc}:{self.line}"
        elif self.frame is not None:
            loc = f"{loc}: frame {self.frame}"
        if self.column is None:
            return f"{loc}: {self.reason}"
        if self.value is None:
            return f"{loc}: {self.what} '{self.column}': {self.reason}"
        return f"{loc}: {self.what} '{self.column}' = '{_shorten(self.value)}': {self.reason}"

    def __reduce__(self):
        # Exceptions pickle through self.args by default, which does not fit this signature; worker
        # processes send these back to the parent.
        kwargs = dict(column=self.column, value=self.value, what=self.what, frame=self.frame)
        return (_rebuild_error, (type(self), self.path, self.line, self.reason, kwargs))


class LogIncompleteError(LogFormatError):
    """A log whose writer did not finish: no end marker, a frame count that disagrees with the rows,
    an empty file, or a `.partial` file. The message always says that the log is incomplete."""


def _rebuild_error(cls, path, line, reason, kwargs):
    return cls(path, line, reason, **kwargs)


def _shorten(text: str) -> str:
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


# --------------------------------------------------------------------------------------------------
# Metadata


def _json_default(obj):
    """json.dumps fallback for numpy scalars and arrays in metadata."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"metadata value {obj!r} of type {type(obj).__name__} is not JSON serialisable")


def _reject_constant(name: str):
    raise ValueError(f"{name} is not valid JSON (metadata values must be finite)")


def _is_type(value, types) -> bool:
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in types:
        return False  # JSON true/false are not numbers
    return isinstance(value, types)


def _type_name(types) -> str:
    types = types if isinstance(types, tuple) else (types,)
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", dict: "an object"}
    return " or ".join(names.get(t, t.__name__) for t in types)


_MISSING = object()  # a metadata key that is absent


def _check_meta(meta, source: str, line: int | None) -> None:
    """Validate a metadata object against schema.REQUIRED_METADATA / OPTIONAL_METADATA / GT_METADATA."""

    def fail(key, reason, value=None):
        shown = None if value is _MISSING else json.dumps(value, default=repr)
        raise LogFormatError(source, line, reason, column=key, value=shown, what="metadata key")

    if not isinstance(meta, dict):
        raise LogFormatError(source, line, f"metadata must be a JSON object, got {type(meta).__name__}")
    required = ", ".join(schema.REQUIRED_METADATA)
    for key, types in schema.REQUIRED_METADATA.items():
        if key not in meta:
            fail(key, f"required key missing (v1 requires {required})", _MISSING)
        if not _is_type(meta[key], types):
            fail(key, f"must be {_type_name(types)}, got {type(meta[key]).__name__}", meta[key])
    if not (math.isfinite(meta["fps"]) and meta["fps"] > 0):
        fail("fps", "must be a positive number of frames per second", meta["fps"])
    for key, types in {**schema.OPTIONAL_METADATA, **GT_METADATA}.items():
        if key in meta and not _is_type(meta[key], types):
            fail(key, f"must be {_type_name(types)}, got {type(meta[key]).__name__}", meta[key])
    gravity = meta.get("gravity")
    if gravity is not None and (len(gravity) != 3 or not all(_is_type(g, (int, float)) for g in gravity)):
        fail("gravity", "must be a list of 3 numbers (world gravity, m/s^2)", gravity)
    size = meta.get("image_size")
    if size is not None and (len(size) != 2 or not all(_is_type(s, int) and s > 0 for s in size)):
        fail("image_size", "must be [width, height] in pixels", size)
    grid = meta.get("grid")
    if grid is not None and list(grid) != [8, 8]:
        fail("grid", "must be [8, 8] in format v1 (SVE bins, cols x rows)", grid)
    missing = meta.get("gt_missing_frames")
    if missing is not None and missing < 0:
        fail("gt_missing_frames", "must be >= 0", missing)


def _parse_meta_line(raw: bytes, source: str) -> dict:
    try:
        text = raw.decode("utf-8").rstrip("\r")
    except UnicodeDecodeError as e:
        raise LogFormatError(source, 1, f"not a jsve v1 log: line 1 is not UTF-8 text ({e.reason})") from None
    if not text.startswith(schema.MAGIC):
        version = re.match(r"# jsve-log (v\S+)", text)
        if version and version.group(1) != f"v{schema.FORMAT_VERSION}":
            reason = (
                f"unsupported format version '{version.group(1)}' "
                f"(this reader reads v{schema.FORMAT_VERSION})"
            )
        else:
            reason = (
                f"not a jsve v1 log: line 1 must start with '{schema.MAGIC}' followed by the JSON metadata, "
                f"found '{_shorten(text)}'"
            )
        raise LogFormatError(source, 1, reason)
    try:
        meta = json.loads(text[len(schema.MAGIC) :], parse_constant=_reject_constant)
    except ValueError as e:
        raise LogFormatError(source, 1, f"metadata is not valid JSON: {e}") from None
    _check_meta(meta, source, 1)
    return meta


# --------------------------------------------------------------------------------------------------
# Header


def _check_header(names: list[str], source: str, line: int | None) -> list[str]:
    """The v1 column list `names` must be; raises naming missing, unexpected or misplaced columns."""

    def fail(reason, column=None):
        raise LogFormatError(source, line, reason, column=column, what="column")

    seen = set()
    for name in names:
        if name in seen:
            fail("appears more than once in the header", name)
        seen.add(name)
    gt_present = [c for c in schema.GT_COLUMNS if c in seen]
    if 0 < len(gt_present) < len(schema.GT_COLUMNS):
        lacking = [c for c in schema.GT_COLUMNS if c not in seen]
        fail(
            f"ground-truth columns partially present: has {_quote(gt_present)}, lacks {_quote(lacking)} "
            "(give all seven gt_* columns or none)",
            lacking[0],
        )
    expected = list(schema.COLUMNS if gt_present else schema.REQUIRED_COLUMNS)
    missing = [c for c in expected if c not in seen]
    unexpected = [c for c in names if c not in set(schema.COLUMNS)]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing column{'s' * (len(missing) > 1)} {_quote(missing)}")
        if unexpected:
            parts.append(f"unexpected column{'s' * (len(unexpected) > 1)} {_quote(unexpected)}")
        fail("wrong header: " + "; ".join(parts), (missing or unexpected)[0])
    if names != expected:
        k = next(i for i, (a, b) in enumerate(zip(names, expected, strict=True)) if a != b)
        fail(
            f"wrong column order: header position {k + 1} holds '{names[k]}', v1 expects '{expected[k]}' "
            f"there (order: {expected[0]}, {expected[1]}, ..., see docs/log-format.md)",
            names[k],
        )
    return expected


def _quote(names: Sequence[str], limit: int = 8) -> str:
    shown = ", ".join(f"'{n}'" for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


# --------------------------------------------------------------------------------------------------
# Row validation (vectorised; shared by the reader and the in-memory validator)


@dataclass
class _Problem:
    """The first defect found in the frames; turned into a LogFormatError by the caller."""

    row: int  # 0-based frame
    order: int  # column position used to pick the first defect of a row
    column: str
    reason: str  # may contain '{ref}', replaced by 'line N' or 'frame N' of ref_row
    value_cols: tuple[str, ...] = ()  # columns whose values make up the value shown
    value: str | None = None  # explicit value, when it is not a field of the row
    what: str = "column"
    ref_row: int | None = None


def _find_problem(cols: Mapping[str, np.ndarray], gt_missing: np.ndarray | None) -> _Problem | None:
    """First (lowest row, then leftmost column) violation of the v1 value rules, or None.

    Arguments:
        cols: column name -> values [frames], in v1 order; ints int64, floats float64, gt_* NaN where
            missing.
        gt_missing: bool [frames, 7], True where a gt value is absent (an empty field in a file; NaN in
            memory), or None when there are no gt columns.
    """
    pos = {c: i for i, c in enumerate(cols)}
    n_frames = len(cols["t_ns"])

    def block(names: Sequence[str]) -> np.ndarray:
        return np.stack([cols[c] for c in names], axis=1)

    found: list[_Problem] = []

    def first_cell(bad: np.ndarray) -> tuple[int, int] | None:
        """(row, column index) of the first True of bad [frames, k] (or [frames]), or None."""
        bad2 = bad if bad.ndim == 2 else bad[:, None]
        rows = bad2.any(axis=1)
        if not rows.any():
            return None
        r = int(np.argmax(rows))
        return r, int(np.argmax(bad2[r]))

    def per_cell(bad: np.ndarray, names: Sequence[str], reason) -> None:
        """One-field rule: reason is a string, or a function of the row."""
        hit = first_cell(bad)
        if hit is not None:
            r, k = hit
            c = names[k]
            text = reason(r) if callable(reason) else reason
            found.append(_Problem(r, pos[c], c, text, (c,)))

    ints = cols
    float_names = list(schema.FLOAT_COLUMNS)
    floats = block(float_names)

    # NaN / inf anywhere (an empty gt_* field is a missing value, not NaN).
    per_cell(~np.isfinite(floats), float_names, "NaN or inf is not allowed")
    if gt_missing is not None:
        gt = block(schema.GT_COLUMNS)
        per_cell(
            ~np.isfinite(gt) & ~gt_missing,
            schema.GT_COLUMNS,
            "NaN or inf is not allowed (leave all seven gt_* fields empty for a frame without ground truth)",
        )
        n_missing = gt_missing.sum(axis=1)
        partial = (n_missing > 0) & (n_missing < len(schema.GT_COLUMNS))
        hit = first_cell(gt_missing & partial[:, None])
        if hit is not None:
            r, k = hit
            c = schema.GT_COLUMNS[k]
            present = len(schema.GT_COLUMNS) - int(n_missing[r])
            found.append(
                _Problem(
                    r,
                    pos[c],
                    c,
                    f"missing while {present} other gt_* values of this frame are present "
                    "(a frame has all seven gt_* values or none)",
                    value="",
                )
            )

    # Timestamps strictly increasing.
    t = ints["t_ns"]
    if len(t) > 1:
        bad = np.diff(t) <= 0
        if bad.any():
            r = int(np.argmax(bad)) + 1
            if t[r] == t[r - 1]:
                reason = "duplicate timestamp: the same as {ref} (t_ns must be strictly increasing)"
            else:
                reason = (
                    f"t_ns must be strictly increasing: {int(t[r - 1]) - int(t[r])} ns earlier than {{ref}} "
                    f"({int(t[r - 1])}; rows unsorted)"
                )
            found.append(_Problem(r, pos["t_ns"], "t_ns", reason, ("t_ns",), ref_row=r - 1))

    states = ", ".join(map(str, schema.VALID_STATES))
    per_cell(
        ~np.isin(ints["state"], schema.VALID_STATES),
        ("state",),
        f"must be one of {states} (ORB-SLAM3 eTrackingState)",
    )
    imu_init = ints["imu_init"]
    per_cell((imu_init != 0) & (imu_init != 1), ("imu_init",), "must be 0 or 1")

    count_names = schema.COUNT_COLUMNS + schema.BIN_COLUMNS
    counts = block(count_names)
    per_cell(counts < 0, count_names, "must be >= 0 (a count)")

    n_ext, n_inl = ints["n_extracted"], ints["n_inliers"]
    per_cell(n_inl > n_ext, ("n_inliers",), lambda r: f"must be <= n_extracted ({int(n_ext[r])})")
    bin_sum = counts[:, len(schema.COUNT_COLUMNS) :].sum(axis=1)
    hit = first_cell(bin_sum > n_ext)
    if hit is not None:
        r = hit[0]
        found.append(
            _Problem(
                r,
                pos[schema.BIN_COLUMNS[-1]],  # after the single-field rules of the same row
                f"{schema.BIN_COLUMNS[0]}..{schema.BIN_COLUMNS[-1]}",
                f"the binned keypoints (sum {int(bin_sum[r])}) must not exceed n_extracted ({int(n_ext[r])})",
                value=str(int(bin_sum[r])),
                what="columns",
            )
        )

    tol = schema.UNIT_QUATERNION_TOLERANCE
    for names in schema.QUATERNION_GROUPS.values():
        if names[0] not in pos:
            continue
        q = block(names)
        norm = np.sqrt(np.sum(q * q, axis=1))
        hit = first_cell(np.abs(norm - 1.0) > tol)  # NaN rows compare False: reported above, or missing gt
        if hit is not None:
            r = hit[0]
            found.append(
                _Problem(
                    r,
                    pos[names[-1]],
                    f"{names[0]}..{names[-1]}",
                    f"not a unit quaternion: |q| = {norm[r]:.12g} (tolerance {tol:g})",
                    tuple(names),
                    what="columns",
                )
            )

    per_cell(cols["imu_dt"] < 0, ("imu_dt",), "must be >= 0 (seconds since the previous frame)")

    # First frame: nothing to preintegrate from (docs/log-format.md, "First frame").
    if n_frames:
        first_reason = "must be {} on the first frame (no previous frame to preintegrate from)"
        for c in ("imu_dt",) + schema.IMU_DP + schema.IMU_DV:
            if cols[c][0] != 0.0:
                found.append(_Problem(0, pos[c], c, first_reason.format(0), (c,)))
        if not np.array_equal([cols[c][0] for c in schema.IMU_DQ], [1.0, 0.0, 0.0, 0.0]):
            found.append(
                _Problem(
                    0,
                    pos[schema.IMU_DQ[-1]],
                    f"{schema.IMU_DQ[0]}..{schema.IMU_DQ[-1]}",
                    first_reason.format("the identity (1, 0, 0, 0)"),
                    schema.IMU_DQ,
                    what="columns",
                )
            )
    return min(found, key=lambda p: (p.row, p.order)) if found else None


# --------------------------------------------------------------------------------------------------
# In-memory validation and writing


def validate_run(run: RunLog) -> RunLog:
    """Check an in-memory run against format v1 and return it in canonical form.

    Canonical form: columns in v1 order (schema.REQUIRED_COLUMNS, then GT_COLUMNS when present), int
    columns int64, float columns float64, a RangeIndex, metadata as it reads back from JSON (tuples
    become lists, numpy scalars Python numbers). gt_* NaN marks a frame without ground truth.

    Raises:
        LogFormatError: with `frame` (0-based) instead of a line, e.g.
            `<memory>: frame 12: column 'imu_dt' = '-0.05': must be >= 0 (...)`.
    """
    source = run.source
    try:
        text = json.dumps(run.meta, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise LogFormatError(source, None, f"metadata cannot be written as JSON: {e}") from None
    meta = json.loads(text)
    _check_meta(meta, source, None)

    frames = run.frames
    has_gt = any(c in frames.columns for c in schema.GT_COLUMNS)
    names = [str(c) for c in frames.columns]
    order = schema.COLUMNS if has_gt else schema.REQUIRED_COLUMNS
    # In memory the order is free; the file order is fixed by the writer.
    _check_header(sorted(names, key=lambda c: order.index(c) if c in order else len(order)), source, None)
    if len(frames) == 0:
        raise LogFormatError(source, None, "the run has no frames")
    columns = {}
    for c in order:
        values = frames[c].to_numpy()
        if c in _INT_SET:
            if not np.issubdtype(values.dtype, np.integer):
                raise LogFormatError(
                    source, None, f"has dtype {values.dtype}; integer columns need an integer dtype", column=c
                )
            columns[c] = values.astype(np.int64, copy=False)
        else:
            if not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
                raise LogFormatError(source, None, f"has dtype {values.dtype}; expected float64", column=c)
            columns[c] = values.astype(np.float64, copy=False)
    gt_missing = np.stack([np.isnan(columns[c]) for c in schema.GT_COLUMNS], axis=1) if has_gt else None
    problem = _find_problem(columns, gt_missing)
    if problem is not None:
        raise _memory_error(problem, columns, source)
    if (
        frames.columns.tolist() == list(order)
        and isinstance(frames.index, pd.RangeIndex)
        and all(frames[c].dtype == columns[c].dtype for c in order)
    ):
        canonical = frames  # already canonical: no copy
    else:
        canonical = pd.DataFrame(columns, columns=list(order))
    return RunLog(meta=meta, frames=canonical, source=source)


def _memory_error(p: _Problem, cols: Mapping[str, np.ndarray], source: str) -> LogFormatError:
    if p.value is not None:
        value = p.value
    else:
        value = ",".join(_format_value(cols[c][p.row]) for c in p.value_cols)
    reason = p.reason.replace("{ref}", f"frame {p.ref_row}")
    return LogFormatError(source, None, reason, column=p.column, value=value, what=p.what, frame=p.row)


def _format_value(x) -> str:
    if isinstance(x, (np.integer, int)):
        return str(int(x))
    return repr(float(x))


def write_log(run: RunLog, path: str | os.PathLike) -> Path:
    """Write one run as a format-v1 CSV log, atomically.

    Line 1 is MAGIC + the metadata as JSON, line 2 the header (schema.REQUIRED_COLUMNS, plus
    GT_COLUMNS when the frames have them), then one row per frame and last the end marker with the
    frame count. Integers are written exactly; floats in the shortest decimal form that reads back to
    the same double (as Python's repr), so `read_log` returns the frames bit for bit. A frame without
    ground truth has its seven gt_* fields empty.

    The file is written as `<path>.partial` and renamed to `path` when complete, so a reader never
    sees a half-written log under the final name. (No fsync: this guards against the writer dying,
    not against the machine losing power.)

    Arguments:
        run: a valid run (see `validate_run`; invalid runs raise LogFormatError and nothing is written).
        path: destination, conventionally `*.csv`; parent folders are created.

    Returns:
        The path written.
    """
    run = validate_run(run)
    path = Path(path)
    frames = run.frames
    arrays = []
    for c in frames.columns:
        values = frames[c].to_numpy()
        # Only gt_* may be missing: NaN there becomes an empty field (Arrow writes nulls as "").
        arrays.append(pa.array(values, from_pandas=c in _GT_SET))
    table = pa.Table.from_arrays(arrays, names=list(frames.columns))
    sink = pa.BufferOutputStream()
    pacsv.write_csv(table, sink, pacsv.WriteOptions(include_header=False, quoting_style="none"))
    head = (
        schema.MAGIC + json.dumps(run.meta, allow_nan=False) + "\n" + ",".join(frames.columns) + "\n"
    ).encode("utf-8")
    tail = f"{schema.END_MARKER}{len(frames)}\n".encode("ascii")

    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        with open(partial, "wb") as f:
            f.write(head)
            f.write(sink.getvalue())
            f.write(tail)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return path


# --------------------------------------------------------------------------------------------------
# Reading one log


def read_log(path: str | os.PathLike, *, ground_truth: GroundTruthSpec | None = None) -> RunLog:
    """Read and validate one format-v1 log.

    Arguments:
        path: the CSV log. A name ending in `.partial` is an unfinished log and is reported as such.
        ground_truth: optionally a `GroundTruth` (or a path: EuRoC with defaults), or a mapping from
            metadata `sequence` to one, associated when the log carries no ground truth of its own
            (see `associate_ground_truth`).

    Returns:
        The run: frames with int64 / float64 columns in v1 order, gt_* NaN where a frame has none;
        `source` is `path` as given.

    Raises:
        LogIncompleteError: empty file, no end marker, a frame count that disagrees with the rows, or
            a `.partial` name (the writer died mid-run or is still running).
        LogFormatError: any other defect, naming file, line, column and value.
        OSError: the file cannot be read.
    """
    source = os.fspath(path)
    if source.endswith(PARTIAL_SUFFIX):
        raise LogIncompleteError(
            source,
            None,
            "the log is incomplete: a '.partial' file is a log whose writer has not finished "
            "(it is still running, or it died mid-run)",
        )
    with open(path, "rb") as f:
        data = f.read()
    run = parse_log(data, source)
    if ground_truth is not None:
        run = _apply_ground_truth(run, ground_truth)
    return run


def parse_log(data: bytes, source: str = "<memory>") -> RunLog:
    """Parse and validate the bytes of a format-v1 log (what `read_log` does after reading the file).

    Arguments:
        data: the whole file.
        source: the name used in messages and stored in RunLog.source.
    """
    if not data:
        raise LogIncompleteError(
            source, 1, "empty file (0 bytes): the log is incomplete (its writer wrote nothing)"
        )
    nl1 = data.find(b"\n")
    meta = _parse_meta_line(data if nl1 < 0 else data[:nl1], source)

    # The last non-blank line must be the end marker; without it the writer stopped mid-run.
    body_end = len(data.rstrip())
    last_nl = data.rfind(b"\n", 0, body_end)
    n_lines = data.count(b"\n", 0, body_end) + 1
    last = data[last_nl + 1 : body_end].decode("utf-8", errors="replace").rstrip("\r")
    if last_nl < 0 or not last.startswith(schema.END_MARKER):
        raise LogIncompleteError(
            source,
            n_lines,
            f"the log is incomplete: the file ends at line {n_lines} without the end marker "
            f"'{schema.END_MARKER}N' (its writer stopped before the end of the run)",
        )
    count_text = last[len(schema.END_MARKER) :].strip()
    if not re.fullmatch(r"[0-9]+", count_text):
        raise LogFormatError(
            source,
            n_lines,
            f"end marker frame count must be a non-negative integer, found '{_shorten(count_text)}'",
        )
    count = int(count_text)

    if last_nl == nl1:
        raise LogFormatError(source, 2, "missing header line: line 2 is the end marker")
    nl2 = data.find(b"\n", nl1 + 1)
    try:
        header = data[nl1 + 1 : nl2].decode("utf-8").rstrip("\r")
    except UnicodeDecodeError:
        raise LogFormatError(source, 2, "header line is not UTF-8 text") from None
    columns = _check_header(header.split(","), source, 2)

    region = data[nl2 + 1 : last_nl + 1]  # the rows, each ending in "\n"
    if not region:
        if count == 0:
            raise LogFormatError(source, n_lines, "the log has no frames")
        raise LogIncompleteError(
            source,
            n_lines,
            f"the log is incomplete: the end marker says {count} frames but the file has no rows",
        )
    table = _parse_rows(region, columns, source)
    if table.num_rows != count:
        raise LogIncompleteError(
            source,
            n_lines,
            f"the log is incomplete: the end marker says {count} frames "
            f"but the file has {table.num_rows} rows",
        )

    # Empty fields: allowed only in gt_* (a frame without ground truth); checked on Arrow's null masks
    # before conversion, since pandas would silently turn an int column with a null into floats.
    first_empty = None
    for c in columns:
        col = table.column(c)
        if col.null_count and c not in _GT_SET:
            r = int(np.argmax(np.asarray(col.is_null())))
            if first_empty is None or r < first_empty[0]:
                first_empty = (r, c)
    if first_empty is not None:
        r, c = first_empty
        raw = _raw_line(region, r)
        if not raw.strip():
            raise LogFormatError(
                source, r + 3, f"empty line (a row has {len(columns)} comma-separated fields)"
            )
        raise LogFormatError(
            source,
            r + 3,
            "empty value (only gt_* fields may be empty)",
            column=c,
            value=_raw_field(raw, columns.index(c)),
        )
    gt_missing = None
    if columns[-1] in _GT_SET:
        gt_missing = np.stack([np.asarray(table.column(c).is_null()) for c in schema.GT_COLUMNS], axis=1)
    problem = _find_problem({c: table.column(c).to_numpy() for c in columns}, gt_missing)
    if problem is not None:
        raise _file_error(problem, region, columns, source)
    return RunLog(meta=meta, frames=table.to_pandas(), source=source)


def _parse_rows(region: bytes, columns: list[str], source: str) -> pa.Table:
    types = {c: (pa.int64() if c in _INT_SET else pa.float64()) for c in columns}
    try:
        return pacsv.read_csv(
            pa.py_buffer(region),
            read_options=pacsv.ReadOptions(column_names=columns, use_threads=False),
            parse_options=pacsv.ParseOptions(ignore_empty_lines=False),
            convert_options=pacsv.ConvertOptions(
                column_types=types,
                null_values=[""],
                strings_can_be_null=False,
                quoted_strings_can_be_null=False,
            ),
        )
    except pa.ArrowInvalid as e:
        raise _locate_parse_error(region, columns, source, str(e)) from None


def _locate_parse_error(region: bytes, columns: list[str], source: str, arrow_message: str) -> LogFormatError:
    """Turn an Arrow parse failure into a message with line, column and value (cheap scan of the rows)."""
    lines = region.split(b"\n")[:-1]
    n_cols = len(columns)
    for i, raw in enumerate(lines):
        n = raw.count(b",") + 1
        if n == n_cols:
            continue
        if not raw.strip(b"\r \t"):
            return LogFormatError(source, i + 3, f"empty line (a row has {n_cols} comma-separated fields)")
        if n < n_cols:
            return LogFormatError(
                source,
                i + 3,
                f"missing: the row has {n} of {n_cols} fields (truncated row)",
                column=columns[n],
            )
        return LogFormatError(
            source,
            i + 3,
            f"too many fields: the row has {n}, v1 expects {n_cols} (last column '{columns[-1]}')",
        )
    # Rectangular, so a field did not convert. Arrow names the column and the value; find its line.
    m = re.search(r"column #(\d+).*?CSV conversion error to (\w+): invalid value '(.*)'", arrow_message, re.S)
    if m:
        k, value = int(m.group(1)), m.group(3)
        c = columns[k]
        reason = "not an integer" if c in _INT_SET else "not a number"
        for i, raw in enumerate(lines):
            field_text = _raw_field(raw, k)
            if field_text == value or field_text.strip().strip('"') == value:
                return LogFormatError(source, i + 3, reason, column=c, value=field_text)
        row = re.search(r"Row #(\d+)", arrow_message)
        return LogFormatError(source, int(row.group(1)) + 2 if row else None, reason, column=c, value=value)
    return LogFormatError(source, None, f"cannot parse the rows: {arrow_message}")


def _raw_line(region: bytes, row: int) -> bytes:
    start = 0
    for _ in range(row):
        start = region.index(b"\n", start) + 1
    end = region.find(b"\n", start)
    return region[start : end if end >= 0 else len(region)].rstrip(b"\r")


def _raw_field(raw: bytes, k: int) -> str:
    fields = raw.rstrip(b"\r").split(b",")
    return fields[k].decode("utf-8", errors="replace") if k < len(fields) else ""


def _file_error(p: _Problem, region: bytes, columns: list[str], source: str) -> LogFormatError:
    if p.value is not None:
        value = p.value
    else:
        raw = _raw_line(region, p.row)
        value = ",".join(_raw_field(raw, columns.index(c)) for c in p.value_cols)
    reason = p.reason.replace("{ref}", f"line {p.ref_row + 3}") if p.ref_row is not None else p.reason
    return LogFormatError(source, p.row + 3, reason, column=p.column, value=value, what=p.what)


# --------------------------------------------------------------------------------------------------
# Ground truth


@dataclass(frozen=True)
class GroundTruth:
    """A ground-truth trajectory file and how to associate it with logs (see `associate_ground_truth`).

    Attributes:
        path: the file.
        fmt: "euroc" (CSV, int ns stamps, p, q wxyz), "tum" (s stamps, p, q xyzw) or "kitti" (3x4 poses).
        kitti_times: KITTI times file (s, one per pose); None associates KITTI poses by frame index.
        max_gap_ns: frames are only given ground truth between samples less than this apart (ns).
        interpolate: linear in position and slerp in rotation; False takes the nearer sample.
    """

    path: str
    fmt: str = "euroc"
    kitti_times: str | None = None
    max_gap_ns: int = DEFAULT_MAX_GAP_NS
    interpolate: bool = True

    def __post_init__(self):
        object.__setattr__(self, "path", os.fspath(self.path))
        if self.kitti_times is not None:
            object.__setattr__(self, "kitti_times", os.fspath(self.kitti_times))
        _check_gt_args(self.fmt, self.kitti_times, self.max_gap_ns)


GroundTruthSpec = GroundTruth | str | os.PathLike | Mapping[str, GroundTruth | str | os.PathLike]
"""What `read_log` / `read_logs` / `ingest` accept as `ground_truth`: one GroundTruth (or a path, read
as EuRoC) for every log, or a mapping from metadata `sequence` to one."""


def _check_gt_args(fmt, kitti_times, max_gap_ns) -> None:
    if fmt not in GT_FORMATS:
        raise ValueError(f"fmt must be one of {GT_FORMATS}, got {fmt!r}")
    if kitti_times is not None and fmt != "kitti":
        raise ValueError(f"kitti_times is only used with fmt='kitti', got fmt={fmt!r}")
    if not max_gap_ns > 0:
        raise ValueError(f"max_gap_ns must be positive (nanoseconds), got {max_gap_ns!r}")


@dataclass(frozen=True)
class _Trajectory:
    stamps: np.ndarray | None  # int64 ns, strictly increasing; None for KITTI without times
    p: np.ndarray  # [n, 3] metres
    q: np.ndarray  # [n, 4] unit wxyz


def _decimal_ns(text: str, exponent: int) -> int:
    """Exact integer nanoseconds of a decimal string in units of 10^-exponent... i.e. value * 10^exponent."""
    d = Decimal(text)
    if not d.is_finite():
        raise InvalidOperation
    return int(d.scaleb(exponent).to_integral_value(rounding=ROUND_HALF_EVEN))


def _read_stamps_ns(path: str, delimiter: str | None, exponent: int) -> np.ndarray:
    """First field of every non-comment line as int64 ns (parsed from the text: evo's float seconds
    lose ~200 ns at 1.4e9 s). Comment and skipping rules follow evo's csv_read_matrix."""
    stamps = []
    with open(path, encoding="utf-8-sig") as f:
        for lineno, line in enumerate(f, start=1):
            if line.startswith("#") or not line.strip():
                continue
            text = line.strip().split(delimiter)[0]
            try:
                stamps.append(_decimal_ns(text, exponent))
            except (InvalidOperation, ValueError):
                raise ValueError(f"{path}:{lineno}: timestamp '{_shorten(text)}' is not a number") from None
    return np.asarray(stamps, dtype=np.int64)


def _unit_quaternions(q: np.ndarray, path: str) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > 1e-3
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{path}: pose {k} has a quaternion of norm {norm[k]:.6g}: not a rotation")
    # Files store ~10 digits; normalising moves values by < 1e-9 and keeps the v1 tolerance.
    return q / norm[:, None]


def _file_key(path: str | None):
    if path is None:
        return None
    st = os.stat(path)
    return (os.path.abspath(path), st.st_mtime_ns, st.st_size)


def load_ground_truth(
    gt_path: str | os.PathLike, fmt: str = "euroc", *, kitti_times: str | os.PathLike | None = None
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """Read a ground-truth trajectory: poses through evo's file_interface, stamps as exact int64 ns.

    Arguments:
        gt_path: EuRoC CSV (state_groundtruth_estimate0/data.csv or ORB-SLAM3's *_GT.txt; stamps in ns,
            a trailing '.000...' accepted), TUM (stamps in s) or KITTI poses (no stamps).
        fmt: "euroc", "tum" or "kitti".
        kitti_times: KITTI times file (seconds, one line per pose).

    Returns:
        (stamps int64 ns [n] or None for KITTI without times, positions [n, 3] in metres,
        quaternions [n, 4] wxyz normalised). Arrays are read-only and cached per file version.
    """
    _check_gt_args(fmt, kitti_times, 1)
    gt_path = os.fspath(gt_path)
    kitti_times = None if kitti_times is None else os.fspath(kitti_times)
    traj = _load_cached(gt_path, fmt, kitti_times, _file_key(gt_path), _file_key(kitti_times))
    return traj.stamps, traj.p, traj.q


@lru_cache(maxsize=32)
def _load_cached(gt_path, fmt, kitti_times, _key, _times_key) -> _Trajectory:
    from evo.tools import file_interface  # 0.4 s import; only when ground truth is used

    readers = {
        "euroc": file_interface.read_euroc_csv_trajectory,
        "tum": file_interface.read_tum_trajectory_file,
        "kitti": file_interface.read_kitti_poses_file,
    }
    try:
        evo_traj = readers[fmt](gt_path)
    except file_interface.FileInterfaceException as e:
        raise ValueError(f"{gt_path}: not a readable {fmt} ground-truth file: {e}") from None
    if fmt == "euroc":
        stamps = _read_stamps_ns(gt_path, ",", 0)
    elif fmt == "tum":
        stamps = _read_stamps_ns(gt_path, None, 9)
    else:
        stamps = None if kitti_times is None else _read_stamps_ns(kitti_times, None, 9)
    p = np.array(evo_traj.positions_xyz, dtype=np.float64)
    q = _unit_quaternions(np.array(evo_traj.orientations_quat_wxyz, dtype=np.float64), gt_path)
    if stamps is not None:
        source = kitti_times if fmt == "kitti" else gt_path
        if len(stamps) != len(p):
            raise ValueError(f"{source}: {len(stamps)} timestamps for {len(p)} poses in {gt_path}")
        step = np.diff(stamps)
        if (step <= 0).any():
            k = int(np.argmax(step <= 0)) + 1
            raise ValueError(f"{source}: timestamps not strictly increasing at pose {k} ({stamps[k]} ns)")
    for a in (p, q) + (() if stamps is None else (stamps,)):
        a.setflags(write=False)
    return _Trajectory(stamps, p, q)


def _slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit wxyz quaternions, row-wise, along the shorter arc."""
    sign = np.where(np.sum(q0 * q1, axis=1) < 0.0, -1.0, 1.0)
    q1 = q1 * sign[:, None]
    # Angle between the 4-vectors via atan2: accurate near 0, unlike arccos of the dot product.
    omega = 2.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=1), np.linalg.norm(q1 + q0, axis=1))
    sin_omega = np.sin(omega)
    small = sin_omega < 1e-9
    safe = np.where(small, 1.0, sin_omega)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * omega) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * omega) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _associate_by_time(stamps, p_gt, q_gt, t, max_gap_ns: int, interpolate: bool):
    """Ground truth at frame times t (int64 ns); NaN where t is outside the span or in a gap."""
    n, m = len(t), len(stamps)
    p = np.full((n, 3), np.nan)
    q = np.full((n, 4), np.nan)
    j = np.searchsorted(stamps, t, side="left")  # stamps[j-1] < t <= stamps[j]
    jc = np.minimum(j, m - 1)
    exact = (j < m) & (stamps[jc] == t)
    p[exact] = p_gt[jc[exact]]
    q[exact] = q_gt[jc[exact]]
    lo, hi = np.clip(j - 1, 0, m - 1), jc
    gap = stamps[hi] - stamps[lo]
    between = ~exact & (j > 0) & (j < m) & (gap < max_gap_ns)
    if between.any():
        lo, hi = lo[between], hi[between]
        # Differences of int64 stamps are exact in float64 (< 2^53 ns).
        alpha = (t[between] - stamps[lo]).astype(np.float64) / (stamps[hi] - stamps[lo]).astype(np.float64)
        if interpolate:
            p[between] = p_gt[lo] + alpha[:, None] * (p_gt[hi] - p_gt[lo])
            q[between] = _slerp(q_gt[lo], q_gt[hi], alpha)
        else:
            nearest = np.where(alpha <= 0.5, lo, hi)
            p[between] = p_gt[nearest]
            q[between] = q_gt[nearest]
    return p, q


def associate_ground_truth(
    run: RunLog,
    gt_path: str | os.PathLike,
    fmt: str = "euroc",
    *,
    kitti_times: str | os.PathLike | None = None,
    max_gap_ns: int = DEFAULT_MAX_GAP_NS,
    interpolate: bool = True,
) -> RunLog:
    """Fill the gt_* columns of a run from a ground-truth trajectory file.

    EuRoC and TUM files, and KITTI with a times file, are associated by time: a frame whose t_ns equals
    a ground-truth stamp takes that pose; a frame between two samples less than `max_gap_ns` apart
    takes the interpolated pose (linear in position, slerp in rotation), or the nearer sample when
    `interpolate` is False. Stamps are compared as exact int64 ns (the frames' clock must be the
    ground truth's: EuRoC ns, KITTI seconds from the times file). KITTI without times is associated by
    frame index: frame i takes pose i.

    Frames left without ground truth (outside the file's span, in a gap, or past the last KITTI pose)
    get NaN in all seven gt_* columns; their count is stored in meta['gt_missing_frames'] (and the
    file in meta['gt_source']) and logged as a warning. Existing gt_* columns are replaced.

    Arguments:
        run: the run (not modified).
        gt_path: ground-truth file; poses read with evo.tools.file_interface.
        fmt: "euroc", "tum" or "kitti".
        kitti_times: KITTI times file (s), or None to associate by index.
        max_gap_ns: largest ground-truth sample spacing to interpolate across, ns.
        interpolate: interpolate between samples (True) or take the nearer one (False).

    Returns:
        A new RunLog with gt_px, gt_py, gt_pz (metres, ground-truth world frame) and gt_qw..gt_qz
        (unit quaternion wxyz, body to world), as the file defines body and world.
    """
    _check_gt_args(fmt, kitti_times, max_gap_ns)
    stamps, p_gt, q_gt = load_ground_truth(gt_path, fmt, kitti_times=kitti_times)
    t = run.frames["t_ns"].to_numpy(dtype=np.int64)
    if stamps is None:
        n, k = len(t), min(len(t), len(p_gt))
        p = np.full((n, 3), np.nan)
        q = np.full((n, 4), np.nan)
        p[:k], q[:k] = p_gt[:k], q_gt[:k]
    else:
        p, q = _associate_by_time(stamps, p_gt, q_gt, t, int(max_gap_ns), interpolate)
    missing = int(np.isnan(p[:, 0]).sum())
    base = run.frames.drop(columns=list(schema.GT_COLUMNS), errors="ignore")
    gt = pd.DataFrame(np.concatenate([p, q], axis=1), columns=list(schema.GT_COLUMNS), index=base.index)
    frames = pd.concat([base, gt], axis=1)
    meta = {**run.meta, "gt_missing_frames": missing, "gt_source": os.fspath(gt_path)}
    out = RunLog(meta=meta, frames=frames, source=run.source)
    if missing:
        how = (
            "by frame index" if stamps is None else f"outside its span or in gaps >= {max_gap_ns / 1e6:g} ms"
        )
        logger.warning(
            "%s (%s): %d of %d frames have no ground truth in %s (%s); their gt_* are NaN "
            "(meta['gt_missing_frames'])",
            out.run_id,
            run.source,
            missing,
            len(t),
            os.fspath(gt_path),
            how,
        )
    return out


def _apply_ground_truth(run: RunLog, spec: GroundTruthSpec) -> RunLog:
    if isinstance(spec, Mapping):
        sequence = run.meta["sequence"]
        if sequence not in spec:
            logger.warning(
                "%s (%s): no ground truth given for sequence '%s'; the run has none",
                run.run_id,
                run.source,
                sequence,
            )
            return run
        spec = spec[sequence]
    if not isinstance(spec, GroundTruth):
        spec = GroundTruth(spec)
    if run.has_ground_truth and not run.frames[list(schema.GT_COLUMNS)].isna().all(axis=None):
        logger.warning(
            "%s (%s): the log carries its own ground truth; kept it and did not use %s",
            run.run_id,
            run.source,
            spec.path,
        )
        return run
    return associate_ground_truth(
        run,
        spec.path,
        spec.fmt,
        kitti_times=spec.kitti_times,
        max_gap_ns=spec.max_gap_ns,
        interpolate=spec.interpolate,
    )


# --------------------------------------------------------------------------------------------------
# Many logs


@dataclass(frozen=True)
class Quarantined:
    """A log that was set aside, with why.

    Attributes:
        path: the file.
        line: 1-based line of the defect, or None.
        column: column / metadata key / column range, or None.
        reason: what is wrong.
        message: the full LogFormatError message.
        incomplete: True when the log is incomplete (its writer did not finish).
    """

    path: str
    line: int | None
    column: str | None
    reason: str
    message: str
    incomplete: bool = False

    @classmethod
    def from_error(cls, err: LogFormatError) -> Quarantined:
        return cls(err.path, err.line, err.column, err.reason, str(err), isinstance(err, LogIncompleteError))


@dataclass
class ReadResult:
    """What `read_logs` returns: the valid runs in sorted path order, and every log set aside."""

    runs: list[RunLog]
    quarantined: list[Quarantined] = field(default_factory=list)

    def report(self) -> pd.DataFrame:
        """One row per quarantined log; columns QUARANTINE_COLUMNS (line as nullable Int64)."""
        df = pd.DataFrame(
            [[getattr(q, c) for c in QUARANTINE_COLUMNS] for q in self.quarantined],
            columns=list(QUARANTINE_COLUMNS),
        )
        return df.astype({"line": "Int64", "incomplete": bool})


def write_quarantine_report(result: ReadResult | Sequence[Quarantined], path: str | os.PathLike) -> Path:
    """Write the quarantine report (one row per quarantined log) as CSV, atomically.

    Arguments:
        result: a ReadResult, or the list of Quarantined entries.
        path: destination CSV.
    """
    if not isinstance(result, ReadResult):
        result = ReadResult(runs=[], quarantined=list(result))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        result.report().to_csv(tmp, index=False)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def find_logs(source: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str]:
    """The log files of `source`, sorted.

    Arguments:
        source: a directory (searched recursively for `*.csv` and `*.csv.partial`, skipping jsve's own
            `*.quarantine.csv` reports and `*.keypoints.csv` side files), a single file, a glob pattern
            ('**' recursive), or a list of paths (taken as given).

    Raises:
        FileNotFoundError: the path does not exist or the pattern matches nothing.
    """
    if isinstance(source, (str, os.PathLike)):
        text = os.fspath(source)
        path = Path(text)
        if path.is_dir():
            files = [
                os.fspath(p)
                for p in path.rglob("*")
                if p.is_file()
                and (p.name.endswith(".csv") or p.name.endswith(".csv" + PARTIAL_SUFFIX))
                and not p.name.endswith(_NOT_LOGS)
            ]
        elif path.exists():
            files = [text]
        elif any(ch in text for ch in "*?["):
            files = [p for p in globlib.glob(text, recursive=True) if os.path.isfile(p)]
            if not files:
                raise FileNotFoundError(f"no files match {text!r}")
        else:
            raise FileNotFoundError(f"no such file or directory: {text!r}")
    else:
        files = [os.fspath(p) for p in source]
    return sorted(set(files))


def _read_one(path: str, ground_truth) -> RunLog | LogFormatError:
    try:
        return read_log(path, ground_truth=ground_truth)
    except LogFormatError as e:
        return e
    except OSError as e:
        return LogFormatError(path, None, f"cannot read the file: {e.strerror or e}")


class _Collect(logging.Handler):
    def __init__(self, records: list):
        super().__init__(logging.WARNING)
        self.records = records

    def emit(self, record: logging.LogRecord) -> None:
        record.msg, record.args, record.exc_info = record.getMessage(), None, None
        self.records.append(record)


def _read_chunk(paths: list[str], ground_truth, stop_on_error: bool):
    """Worker: read a chunk of logs; warnings are returned to the parent to be logged there."""
    records: list = []
    handler = _Collect(records)
    logger.addHandler(handler)
    propagate, logger.propagate = logger.propagate, False
    try:
        out = []
        for p in paths:
            result = _read_one(p, ground_truth)
            out.append((p, result))
            if stop_on_error and isinstance(result, LogFormatError):
                break
        return out, records
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _mp_context():
    # Not fork: the parent may hold JAX's (or Arrow's) threads, and fork with threads can deadlock.
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["jsve.logs"])
        return ctx
    return multiprocessing.get_context("spawn")


def _iter_read(paths: list[str], *, workers: int | None, progress: bool, ground_truth, stop_on_error: bool):
    """(path, RunLog | LogFormatError) in the order of `paths`, read in parallel chunks."""
    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    bar = tqdm(total=len(paths), disable=not progress, file=sys.stderr, unit="log", desc="reading logs")
    try:
        if workers == 1 or len(paths) < _MIN_LOGS_PER_WORKER * 2:
            for p in paths:
                result = _read_one(p, ground_truth)
                bar.update(1)
                yield p, result
            return
        chunk = max(1, min(16, math.ceil(len(paths) / (4 * workers))))
        chunks = iter([paths[i : i + chunk] for i in range(0, len(paths), chunk)])
        executor = cf.ProcessPoolExecutor(max_workers=min(workers, len(paths)), mp_context=_mp_context())
        try:
            pending = collections.deque()
            # A bounded window of chunks in flight keeps memory flat however many logs there are.
            for c in chunks:
                pending.append(executor.submit(_read_chunk, c, ground_truth, stop_on_error))
                if len(pending) >= 2 * workers:
                    break
            n_warnings = 0
            while pending:
                out, records = pending.popleft().result()
                for record in records:
                    n_warnings += 1
                    if n_warnings <= _MAX_WORKER_WARNINGS:
                        logger.handle(record)
                nxt = next(chunks, None)
                if nxt is not None:
                    pending.append(executor.submit(_read_chunk, nxt, ground_truth, stop_on_error))
                for p, result in out:
                    bar.update(1)
                    yield p, result
            if n_warnings > _MAX_WORKER_WARNINGS:
                logger.warning("... and %d more warnings like these", n_warnings - _MAX_WORKER_WARNINGS)
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()


def _good_runs(
    paths, *, on_error: OnError, workers, progress, ground_truth, quarantined: list
) -> Iterator[RunLog]:
    """Valid runs in path order; bad logs raise (on_error='raise') or go to `quarantined`."""
    if on_error not in ("raise", "quarantine"):
        raise ValueError(f"on_error must be 'raise' or 'quarantine', got {on_error!r}")
    seen: dict[str, str] = {}
    results = _iter_read(
        paths,
        workers=workers,
        progress=progress,
        ground_truth=ground_truth,
        stop_on_error=on_error == "raise",
    )
    for path, result in results:
        if isinstance(result, RunLog) and result.run_id in seen:
            result = LogFormatError(
                path,
                1,
                f"duplicate run id: '{result.run_id}' is also the run id of {seen[result.run_id]} "
                "(sequence/disturbance-level/run must be unique)",
            )
        if isinstance(result, LogFormatError):
            if on_error == "raise":
                results.close()
                raise result
            quarantined.append(Quarantined.from_error(result))
            continue
        seen[result.run_id] = path
        yield result


def read_logs(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    on_error: OnError = "raise",
    workers: int | None = None,
    progress: bool = True,
    ground_truth: GroundTruthSpec | None = None,
) -> ReadResult:
    """Read and validate many logs in parallel.

    Arguments:
        source: a directory (recursive `*.csv` and `*.csv.partial`), a glob, a file or a list of paths
            (see `find_logs`). `.partial` files are always reported as incomplete, never skipped.
        on_error: "raise" stops at the first bad log in sorted path order with its LogFormatError;
            "quarantine" sets bad logs aside in ReadResult.quarantined (nothing is dropped silently).
        workers: processes (default os.cpu_count()); 1, or fewer than 16 logs, reads in this process.
            Processes start with multiprocessing's "forkserver" method (not fork: the caller may hold
            JAX's threads), so a script that calls this needs the usual `if __name__ == "__main__":`.
        progress: tqdm progress bar on stderr.
        ground_truth: associated with logs that carry none (see `read_log`); must be picklable.

    Returns:
        ReadResult(runs in sorted path order, quarantined). A run id (RunLog.run_id) met a second time
        is an error naming both files (the later file is the one raised or quarantined).
    """
    paths = find_logs(source)
    quarantined: list[Quarantined] = []
    runs = list(
        _good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
        )
    )
    return ReadResult(runs=runs, quarantined=quarantined)


# --------------------------------------------------------------------------------------------------
# Parquet


PARQUET_SCHEMA = pa.schema(
    [
        pa.field("run_id", pa.dictionary(pa.int32(), pa.string()), nullable=False),
        pa.field("frame", pa.int32(), False),
    ]
    + [pa.field(c, pa.int64(), nullable=False) for c in schema.INT_COLUMNS]
    + [pa.field(c, pa.float64(), nullable=False) for c in schema.FLOAT_COLUMNS]
    + [pa.field(c, pa.float64(), nullable=True) for c in schema.GT_COLUMNS]
)
"""Layout of the consolidated Parquet file: one row per frame, runs contiguous in sorted path order.
gt_* are null for runs without ground truth, NaN for frames without it in runs that have it."""


@dataclass(frozen=True)
class IngestSummary:
    """What `ingest` did.

    Attributes:
        out_path: the Parquet file written.
        n_runs: runs written.
        n_frames: frames (rows) written.
        quarantined: logs set aside (on_error='quarantine').
        quarantine_report: the CSV report written, or None when nothing was quarantined.
    """

    out_path: Path
    n_runs: int
    n_frames: int
    quarantined: list[Quarantined]
    quarantine_report: Path | None

    def line(self) -> str:
        """A one-line summary for people."""
        text = (
            f"ingested {self.n_runs} runs, {self.n_frames} frames -> {self.out_path}; "
            f"quarantined {len(self.quarantined)}"
        )
        if self.quarantine_report is not None:
            text += f" (report: {self.quarantine_report})"
        return text


def _runs_to_table(runs: list[RunLog]) -> pa.Table:
    lengths = np.array([len(r.frames) for r in runs])
    run_ids = pa.DictionaryArray.from_arrays(
        pa.array(np.repeat(np.arange(len(runs), dtype=np.int32), lengths)),
        pa.array([r.run_id for r in runs], pa.string()),
    )
    frame = np.concatenate([np.arange(n, dtype=np.int32) for n in lengths])
    arrays = [run_ids, pa.array(frame)]
    for c in schema.REQUIRED_COLUMNS:
        arrays.append(pa.array(np.concatenate([r.frames[c].to_numpy() for r in runs])))
    no_gt = np.repeat([not r.has_ground_truth for r in runs], lengths)
    for c in schema.GT_COLUMNS:
        values = np.concatenate(
            [r.frames[c].to_numpy() if r.has_ground_truth else np.full(len(r.frames), np.nan) for r in runs]
        )
        # NaN stays NaN (a frame without ground truth); null marks a run without gt columns.
        arrays.append(pa.array(values, mask=no_gt if no_gt.any() else None))
    return pa.Table.from_arrays(arrays, schema=PARQUET_SCHEMA)


def default_quarantine_report_path(out_path: str | os.PathLike) -> Path:
    """`OUT.quarantine.csv` beside `OUT.parquet`."""
    return Path(out_path).with_suffix(".quarantine.csv")


def ingest(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    out_path: str | os.PathLike,
    *,
    on_error: OnError = "raise",
    workers: int | None = None,
    progress: bool = True,
    ground_truth: GroundTruthSpec | None = None,
    quarantine_report: str | os.PathLike | None = None,
) -> IngestSummary:
    """Validate many logs (optionally associating ground truth) and consolidate them into one Parquet file.

    The file (layout PARQUET_SCHEMA) holds one row per frame: `run_id` (dictionary-encoded string),
    `frame` (int32, 0-based), then the v1 columns; runs are contiguous, in sorted path order. The
    schema's key-value metadata holds b'jsve.runs': a JSON list of {run_id, source, meta, n_frames,
    has_ground_truth}, one per run in file order. Logs are streamed (row groups of ~260k frames), so
    memory stays flat. The file is written as `<out>.partial` and renamed when complete.

    Arguments:
        source: logs (see `find_logs`).
        out_path: the Parquet file.
        on_error, workers, progress, ground_truth: as in `read_logs`.
        quarantine_report: CSV path for the report of quarantined logs; default `OUT.quarantine.csv`
            beside the output. Written only when logs were quarantined (a stale report at the default
            path is removed).

    Returns:
        IngestSummary.

    Raises:
        LogFormatError: the first bad log, with on_error='raise' (nothing is written).
        FileNotFoundError: no logs in `source`.
    """
    paths = find_logs(source)
    if not paths:
        raise FileNotFoundError(f"no tracking logs (*.csv, *.csv.partial) in {os.fspath(source)!r}")
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + PARTIAL_SUFFIX)
    quarantined: list[Quarantined] = []
    entries = []
    n_frames = 0
    writer = pq.ParquetWriter(tmp, PARQUET_SCHEMA, compression="zstd")
    try:
        batch: list[RunLog] = []
        batch_rows = 0
        runs = _good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
        )
        for run in runs:
            entries.append(
                {
                    "run_id": run.run_id,
                    "source": run.source,
                    "meta": run.meta,
                    "n_frames": len(run.frames),
                    "has_ground_truth": run.has_ground_truth,
                }
            )
            n_frames += len(run.frames)
            batch.append(run)
            batch_rows += len(run.frames)
            if batch_rows >= _ROW_GROUP_ROWS:
                writer.write_table(_runs_to_table(batch))
                batch, batch_rows = [], 0
        if batch:
            writer.write_table(_runs_to_table(batch))
        writer.add_key_value_metadata(
            {
                PARQUET_RUNS_KEY: json.dumps(entries, allow_nan=False),
                PARQUET_FORMAT_KEY: str(schema.FORMAT_VERSION),
            }
        )
        writer.close()
        os.replace(tmp, out)
    except BaseException:
        writer.close()
        tmp.unlink(missing_ok=True)
        raise

    default_report = default_quarantine_report_path(out)
    report = Path(quarantine_report) if quarantine_report is not None else default_report
    if quarantined:
        write_quarantine_report(quarantined, report)
        logger.warning("%d logs quarantined; see %s", len(quarantined), report)
    else:
        if quarantine_report is None and default_report.exists():
            logger.info("removing the stale quarantine report %s", default_report)
            default_report.unlink()
        report = None
    return IngestSummary(out, len(entries), n_frames, quarantined, report)


def read_parquet(path: str | os.PathLike) -> list[RunLog]:
    """Restore the runs of a Parquet file written by `ingest`, exactly (ints exact, floats bitwise).

    Returns:
        RunLogs in file order, with the metadata and source recorded at ingest; runs ingested without
        ground truth have no gt_* columns.

    Raises:
        LogFormatError: not a jsve Parquet file, or its rows disagree with its run list.
    """
    source = os.fspath(path)
    pf = pq.ParquetFile(source)
    kv = pf.metadata.metadata or {}
    if PARQUET_RUNS_KEY not in kv:
        raise LogFormatError(
            source, None, f"not a jsve Parquet file: no {PARQUET_RUNS_KEY.decode()!r} metadata"
        )
    entries = json.loads(kv[PARQUET_RUNS_KEY])
    table = pf.read()
    lengths = np.array([e["n_frames"] for e in entries], dtype=np.int64)
    if table.num_rows != lengths.sum():
        raise LogFormatError(
            source, None, f"has {table.num_rows} rows but its run list accounts for {int(lengths.sum())}"
        )
    index = {e["run_id"]: i for i, e in enumerate(entries)}
    ids = []
    for chunk in table.column("run_id").chunks:
        lut = np.array([index.get(s, -1) for s in chunk.dictionary.to_pylist()] or [-1], dtype=np.int64)
        ids.append(lut[chunk.indices.to_numpy(zero_copy_only=False)])
    ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    expected_frame = np.arange(table.num_rows) - np.repeat(offsets[:-1], lengths)
    frame = table.column("frame").to_numpy()
    if not (
        np.array_equal(ids, np.repeat(np.arange(len(entries)), lengths))
        and np.array_equal(frame, expected_frame)
    ):
        raise LogFormatError(source, None, "rows are not grouped by run in the order of its run list")
    columns = {c: table.column(c).to_numpy() for c in schema.COLUMNS}
    runs = []
    for e, start, stop in zip(entries, offsets[:-1], offsets[1:], strict=True):
        names = schema.COLUMNS if e["has_ground_truth"] else schema.REQUIRED_COLUMNS
        frames = pd.DataFrame({c: columns[c][start:stop].copy() for c in names}, columns=list(names))
        runs.append(RunLog(meta=e["meta"], frames=frames, source=e["source"]))
    return runs
