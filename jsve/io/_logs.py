"""Tracking logs, format v3 (v2 and v1 still read): write, read and validate one log.

The I/O edge of jsve (docs/log-format.md describes the format for people; jsve.io._schema is the one
home of its names). Everything downstream receives `RunLog`s whose frames have been validated here:

    write_log(run, path)                 one run -> one v2 CSV log, atomically (`.partial`, then rename)
    read_log(path)                       one v2 (or v1) CSV log -> RunLog; any defect raises LogFormatError
    parse_log(data), validate_run(run)   the same rules on bytes, and on an in-memory run

A v1 log reads with `schema.v1_defaults` for map_id and imu_ba2 and a `LogVersionWarning` naming the
file (`read_log_version` returns the version instead of warning: jsve.io._ingest summarises many).

Ground truth is associated through jsve.io._groundtruth (`GroundTruth`: gt_* columns from an EuRoC /
TUM / KITTI trajectory); many logs are read by jsve.io._ingest (`read_logs`, `ingest`, `read_parquet`).

Errors name the file, the 1-based line, the column and the value as written in the file, e.g.
`logs/r7.csv:1288: column 'imu_dt' = '-0.05': must be >= 0`.

The layout (magic line with the metadata JSON, header, rows, end marker) and the number rules are
jsve.io._text's, shared with the keypoint side files. Rows are parsed by Arrow's CSV reader with one
explicit type per column: int64 columns (t_ns above all) never pass through float, and floats are parsed
correctly rounded, so a log written by `write_log` (shortest round-trip decimal representation, as
Python's repr) reads back bit for bit.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from jsve.io import _atomic as atomic
from jsve.io import _schema as schema
from jsve.io import _text as text
from jsve.io._errors import LogFormatError, LogIncompleteError, LogVersionWarning, shorten
from jsve.io._groundtruth import GroundTruthSpec, apply_ground_truth
from jsve.io._log_header import check_header, check_meta, parse_meta_line, parse_trailers
from jsve.io._row_rules import Problem, find_problem
from jsve.io._schema import RunLog

PARTIAL_SUFFIX = atomic.PARTIAL_SUFFIX
"""A file whose name ends in this is a log (or Parquet file) that its writer has not finished."""

_INT_SET = frozenset(schema.INT_COLUMNS + schema.KEYFRAME_INT_COLUMNS)
_GT_SET = frozenset(schema.GT_COLUMNS)
_WORLD_SET = frozenset(schema.WORLD_COLUMNS)
_REL_SET = frozenset(schema.REL_COLUMNS)
TRAILERS_KEY = b"jsve.trailers"
"""Where a parsed table (parse_table) carries the log's trailers: its schema metadata, as JSON."""
_VIS_SET = frozenset(schema.VIS_COLUMNS)


# --------------------------------------------------------------------------------------------------
# In-memory validation and writing


def validate_run(run: RunLog) -> RunLog:
    """Check an in-memory run against format v3 and return it in canonical form.

    Canonical form: columns in v2 order (schema.REQUIRED_COLUMNS, then GT_COLUMNS and WORLD_COLUMNS when
    present), int
    columns int64, float columns float64, a RangeIndex, metadata as it reads back from JSON (tuples
    become lists, numpy scalars Python numbers). gt_* NaN marks a frame without ground truth, all ten
    vis_* NaN a frame without a pose (allowed outside schema.POSED_STATES).

    Raises:
        LogFormatError: with `frame` (0-based) instead of a line, e.g.
            `<memory>: frame 12: column 'imu_dt' = '-0.05': must be >= 0 (...)`.
    """
    source = run.source
    meta = text.canonical_meta(run.meta, source)
    check_meta(meta, source, None)

    frames = run.frames
    has_gt = any(c in frames.columns for c in schema.GT_COLUMNS)
    has_world = any(c in frames.columns for c in schema.WORLD_COLUMNS)
    has_keyframes = any(c in frames.columns for c in schema.KEYFRAME_COLUMNS)
    names = [str(c) for c in frames.columns]
    order = schema.column_order(schema.FORMAT_VERSION, has_gt, has_world, has_keyframes)
    # In memory the order is free; the file order is fixed by the writer.
    check_header(sorted(names, key=lambda c: order.index(c) if c in order else len(order)), source, None)
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
    vis_missing = np.stack([np.isnan(columns[c]) for c in schema.VIS_COLUMNS], axis=1)
    problem = find_problem(columns, gt_missing, vis_missing)
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
    return RunLog(meta=meta, frames=canonical, source=source, trailers=run.trailers)


def _memory_error(p: Problem, cols: Mapping[str, np.ndarray], source: str) -> LogFormatError:
    if p.value is not None:
        value = p.value
    else:
        value = ",".join(text.format_value(cols[c][p.row]) for c in p.value_cols)
    reason = p.reason.replace("{ref}", f"frame {p.ref_row}")
    return LogFormatError(source, None, reason, column=p.column, value=value, what=p.what, frame=p.row)


def write_log(run: RunLog, path: str | os.PathLike) -> Path:
    """Write one run as a format-v3 CSV log, atomically (always v3, whatever the run was read from).

    Line 1 is MAGIC + the metadata as JSON, line 2 the header (schema.REQUIRED_COLUMNS, plus
    GT_COLUMNS and WORLD_COLUMNS when the frames have them), then one row per frame and last the end
    marker with the frame count. Integers are written exactly; floats in the shortest decimal form that
    reads back to the same double (as Python's repr), so `read_log` returns the frames bit for bit. A
    frame without ground truth has its seven gt_* fields empty, a frame without a pose (NaN) its ten
    vis_* fields.

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
        # Only gt_* and vis_* may be missing: NaN there becomes an empty field (Arrow writes nulls as "").
        arrays.append(pa.array(values, from_pandas=c in _GT_SET or c in _VIS_SET or c in _REL_SET))
    table = pa.Table.from_arrays(arrays, names=list(frames.columns))
    trailers = "".join(
        f"{schema.TRAILER_PREFIX}{key} {json.dumps(value, allow_nan=False, separators=(',', ':'))}\n"
        for key, value in (run.trailers or {}).items()
    ).encode("utf-8")
    return atomic.write_bytes(
        path,
        text.head(schema.MAGIC, run.meta, [str(c) for c in frames.columns]),
        text.write_rows(table),
        trailers,
        text.tail(schema.END_MARKER, len(frames)),
    )


# --------------------------------------------------------------------------------------------------
# Reading one log


def read_log(path: str | os.PathLike, *, ground_truth: GroundTruthSpec | None = None) -> RunLog:
    """Read and validate one log of format v3 or v2, or v1 with defaults.

    Arguments:
        path: the CSV log. A name ending in `.partial` is an unfinished log and is reported as such.
        ground_truth: optionally a `GroundTruth` (or a path: EuRoC with defaults), or a mapping from
            metadata `sequence` to one, associated when the log carries no ground truth of its own
            (see `associate_ground_truth`).

    Returns:
        The run: frames with int64 / float64 columns in v2 order, vis_* NaN where a frame has no
        pose, gt_* NaN where a frame has no ground truth; `source` is `path` as given. A v1 log gets
        map_id and imu_ba2 from `schema.v1_defaults`, with a `LogVersionWarning` naming the file.

    Raises:
        LogIncompleteError: empty file, no end marker, a frame count that disagrees with the rows, or
            a `.partial` name (the writer died mid-run or is still running).
        LogFormatError: any other defect, naming file, line, column and value.
        OSError: the file cannot be read.
    """
    run, version = read_log_version(path, ground_truth=ground_truth)
    if version == 1:
        _warn_v1(run.source)
    return run


def _warn_v1(source: str) -> None:
    # stacklevel 3: this function, read_log / parse_log, then their caller.
    warnings.warn(
        f"{source}: format v1 log read with defaults: {schema.V1_DEFAULTS_TEXT} (docs/log-format.md, "
        "'Reading v1 logs: defaults'); write_log rewrites it as v3",
        LogVersionWarning,
        stacklevel=3,
    )


def read_log_version(
    path: str | os.PathLike, *, ground_truth: GroundTruthSpec | None = None
) -> tuple[RunLog, int]:
    """`read_log` without the v1 warning: (the run, the file's format version, 1 or 2).

    For callers that report v1 logs themselves (jsve.io._ingest gives one summary for many logs).
    """
    source = os.fspath(path)
    meta, version, table = read_log_table(path)
    run = run_from_table(meta, version, table, source)
    if ground_truth is not None:
        run = apply_ground_truth(run, ground_truth)
    return run, version


def read_log_table(path: str | os.PathLike) -> tuple[dict, int, pa.Table]:
    """Read and validate one log without building pandas frames (`jsve ingest`'s path to Parquet).

    Returns:
        (metadata, format version, rows): the rows in the file's column order, int64 and float64
        columns, null where a field is empty (vis_* of a frame without a pose, gt_* of one without
        ground truth); a v1 log without its defaults (`run_from_table` adds them).

    Raises:
        LogIncompleteError, LogFormatError, OSError: as `read_log`.
    """
    return parse_table(read_log_bytes(path), os.fspath(path))


def unreadable(path: str, error: OSError) -> LogFormatError:
    """The LogFormatError of a log that cannot be read (quarantined or raised like any bad log)."""
    return LogFormatError(path, None, f"cannot read the file: {error.strerror or error}")


def read_log_bytes(path: str | os.PathLike) -> bytes:
    """The whole file of a log.

    Raises:
        LogIncompleteError: a `.partial` name (its writer has not finished).
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
        return f.read()


def parse_log(data: bytes, source: str = "<memory>") -> RunLog:
    """Parse and validate the bytes of a log (what `read_log` does after reading the file).

    Arguments:
        data: the whole file.
        source: the name used in messages and stored in RunLog.source.
    """
    run, version = _parse(data, source)
    if version == 1:
        _warn_v1(source)
    return run


def _parse(data: bytes, source: str) -> tuple[RunLog, int]:
    meta, version, table = parse_table(data, source)
    return run_from_table(meta, version, table, source), version


def run_from_table(meta: dict, version: int, table: pa.Table, source: str) -> RunLog:
    """The RunLog of a table from `read_log_table` (pandas frames; a v1 log with its defaults; a v3
    log's trailers)."""
    stored = (table.schema.metadata or {}).get(TRAILERS_KEY)
    frames = table.replace_schema_metadata(None).to_pandas()
    if version == 1:
        frames = with_v1_defaults(frames)
    return RunLog(meta=meta, frames=frames, source=source, trailers=json.loads(stored) if stored else None)


@dataclass(frozen=True)
class LogLayout:
    """A log's lines around its rows, checked (metadata, header, end marker): all but the rows' values.

    Attributes:
        meta, version: line 1's metadata and format version. columns: the header's names.
        count: frames the end marker says. parts: where the lines are (rows: the bytes of the rows,
            each ending in '\\n'; n_lines: the end marker's line number).
    """

    meta: dict
    version: int
    columns: list[str]
    count: int
    parts: text.Sections
    trailers: dict | None = None

    @property
    def rows(self) -> bytes:
        return self.parts.rows


def log_layout(data: bytes, source: str) -> LogLayout:
    data = text.file_bytes(data, source)
    if not data:
        raise LogIncompleteError(
            source, 1, "empty file (0 bytes): the log is incomplete (its writer wrote nothing)"
        )
    parts = text.cut(data)
    meta, version = parse_meta_line(parts.first, source)

    # The last non-blank line must be the end marker; without it the writer stopped mid-run.
    count_text = text.end_count(parts.last, schema.END_MARKER)
    if count_text is None:
        n_lines = parts.n_lines
        raise LogIncompleteError(
            source,
            n_lines,
            f"the log is incomplete: the file ends at line {n_lines} without the end marker "
            f"'{schema.END_MARKER}N' (its writer stopped before the end of the run)",
        )
    if not text.is_count(count_text):
        raise LogFormatError(
            source,
            parts.n_lines,
            f"end marker frame count must be a non-negative integer, found '{shorten(count_text)}'",
        )
    count = int(count_text)

    if parts.header is None:
        raise LogFormatError(source, 2, "missing header line: line 2 is the end marker")
    try:
        header = parts.header.decode("utf-8")
    except UnicodeDecodeError:
        raise LogFormatError(source, 2, "header line is not UTF-8 text") from None
    if not header.strip():
        raise LogFormatError(source, 2, "empty line (line 2 is the header)")
    columns = check_header(header.split(","), source, 2, version)

    if parts.rows_start == parts.rows_end:
        if count == 0:
            raise LogFormatError(source, parts.n_lines, "the log has no frames")
        raise LogIncompleteError(
            source,
            parts.n_lines,
            f"the log is incomplete: the end marker says {count} frames but the file has no rows",
        )
    trailers = None
    if version >= 3:
        parts, lines = text.split_trailers(parts, schema.TRAILER_PREFIX)
        trailers = parse_trailers(lines, source) if lines else None
    return LogLayout(meta, version, columns, count, parts, trailers)


def parse_table(data: bytes, source: str) -> tuple[dict, int, pa.Table]:
    """(metadata, format version, validated rows): what `read_log_table` returns, from the bytes."""
    layout = log_layout(data, source)
    meta, region, columns, version, count = (
        layout.meta,
        layout.rows,
        layout.columns,
        layout.version,
        layout.count,
    )
    # Arrow ends a row at a bare '\r': the row would be cut in two and every line after it shifted.
    bare_cr = _search(_BARE_CR, region)
    # Arrow's int64 parser reads hexadecimal ('0x10' = 16); an integer field is digits with an optional '-'.
    hex_number = _search(_HEX, region)
    if bare_cr is not None or hex_number is not None:
        _raise_on_blank_line(region, columns, source)
    if bare_cr is not None:
        line = region.count(b"\n", 0, bare_cr.start()) + 3
        raise LogFormatError(
            source, line, "a carriage return ('\\r') inside the row: lines end in '\\n' or '\\r\\n'"
        )
    if hex_number is not None:
        row = region.count(b"\n", 0, hex_number.start())
        raw = text.raw_line(region, row)
        start = region.rfind(b"\n", 0, hex_number.start()) + 1
        k = raw.count(b",", 0, hex_number.start() - start)
        c = columns[min(k, len(columns) - 1)]
        reason = "not an integer" if c in _INT_SET else "not a number"
        raise LogFormatError(source, row + 3, reason, column=c, value=text.raw_field(raw, k))
    table = _parse_rows(region, columns, source)
    if table.num_rows != count:
        _raise_on_blank_line(region, columns, source)  # Arrow reads a blank line as a row of nulls
        raise LogIncompleteError(
            source,
            layout.parts.n_lines,
            f"the log is incomplete: the end marker says {count} frames "
            f"but the file has {table.num_rows} rows",
        )

    first_empty = _first_empty(table, columns, version)
    if first_empty is not None:
        _raise_on_blank_line(region, columns, source)
        r, c = first_empty
        raw = text.raw_line(region, r)
        reason = (
            "empty value (only gt_* and vis_* fields may be empty)"
            if version >= 2
            else "empty value (only gt_* fields may be empty in a v1 log)"
        )
        raise LogFormatError(source, r + 3, reason, column=c, value=text.raw_field(raw, columns.index(c)))

    problem = _value_problem(table, columns, version)
    if problem is not None:
        raise _file_error(problem, region, columns, source)
    if layout.trailers is not None:
        table = table.replace_schema_metadata({TRAILERS_KEY: json.dumps(layout.trailers).encode("utf-8")})
    return meta, version, table


def _first_empty(table: pa.Table, columns: Sequence[str], version: int) -> tuple[int, str] | None:
    """(row, column) of the first empty field where none may be, or None.

    Empty fields are allowed only in gt_* (a frame without ground truth) and, from v2, in vis_* (a
    frame without a pose); checked on Arrow's null masks before conversion, since pandas would silently
    turn an int column with a null into floats.
    """
    may_be_empty = (_GT_SET | _VIS_SET | _REL_SET) if version >= 2 else _GT_SET
    first_empty = None
    for c in columns:
        col = table.column(c)
        if col.null_count and c not in may_be_empty:
            r = int(np.argmax(np.asarray(col.is_null())))
            if first_empty is None or r < first_empty[0]:
                first_empty = (r, c)
    return first_empty


def _value_problem(
    table: pa.Table, columns: Sequence[str], version: int, starts: np.ndarray | None = None
) -> Problem | None:
    """find_problem on parsed rows (their null masks: empty gt_* and vis_* fields)."""

    def nulls(names):
        return np.stack([np.asarray(table.column(c).is_null()) for c in names], axis=1)

    gt_missing = nulls(schema.GT_COLUMNS) if schema.GT_COLUMNS[0] in columns else None
    vis_missing = nulls(schema.VIS_COLUMNS) if version >= 2 else None
    cols = {c: table.column(c).to_numpy() for c in columns}
    return find_problem(cols, gt_missing, vis_missing, starts)


def rows_are_valid(table: pa.Table, columns: Sequence[str], version: int, starts: np.ndarray) -> bool:
    """Whether several logs' rows parsed as one table (each log's first row at `starts`) pass every
    value rule that `read_log` applies to each alone: no empty field where none may be, no
    find_problem. Which log and line fails is left to reading that log alone."""
    return (
        _first_empty(table, columns, version) is None
        and _value_problem(table, columns, version, starts) is None
    )


def with_v1_defaults(frames: pd.DataFrame) -> pd.DataFrame:
    """v1 frames (no map_id / imu_ba2) with `schema.v1_defaults` inserted after imu_init: v2 order."""
    defaults = schema.v1_defaults(frames["t_ns"].to_numpy(), frames["imu_init"].to_numpy())
    out = frames.copy(deep=False)
    at = out.columns.get_loc("imu_init") + 1
    for k, c in enumerate(schema.MAP_COLUMNS):
        out.insert(at + k, c, defaults[c])
    return out


_BLANK_LINE = re.compile(rb"^[ \t\r]*\n", re.MULTILINE)
_BARE_CR = re.compile(rb"\r(?!\n)")
_HEX = re.compile(rb"[xX]")  # no number of a log has an x: a hexadecimal one, or garbage

# Bytes without which each pattern cannot match: bytes.find runs at memchr speed, a regex over a
# 2 MB region at a tenth of it (the three searches would be a large share of `jsve ingest`), so the regex runs
# only where a needle is present and finds what it would have found anyway.
_NEEDLES = {
    _BLANK_LINE: (b"\n\n", b"\n\r", b"\n ", b"\n\t"),
    _BARE_CR: (b"\r",),
    _HEX: (b"x", b"X"),
}


def _search(pattern: re.Pattern, region: bytes) -> re.Match | None:
    """pattern.search(region), skipped where none of its needles occurs (_NEEDLES)."""
    at_start = pattern is _BLANK_LINE and region[:1] in (b" ", b"\t", b"\r", b"\n")
    if not at_start and not any(needle in region for needle in _NEEDLES[pattern]):
        return None
    return pattern.search(region)


def _raise_on_blank_line(region: bytes, columns: list[str], source: str) -> None:
    """A blank line is reported as itself, before any other defect of the rows.

    Searched only once a defect is known: Arrow reads a blank line as a row of empty fields, so the
    frame count or the empty-field rule fails anyway, and the search would cost a tenth of a clean
    log's parse.
    """
    blank = _search(_BLANK_LINE, region)
    if blank is not None:
        line = region.count(b"\n", 0, blank.start()) + 3
        raise LogFormatError(source, line, f"empty line (a row has {len(columns)} comma-separated fields)")


def _parse_rows(region: bytes, columns: list[str], source: str) -> pa.Table:
    try:
        return text.read_rows(region, columns, _INT_SET)
    except pa.ArrowInvalid as e:
        _raise_on_blank_line(region, columns, source)
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
            f"too many fields: the row has {n}, the header has {n_cols} (last column '{columns[-1]}')",
        )
    # Rectangular, so a field did not convert. Arrow names the column and the value; find its line.
    m = re.search(r"column #(\d+).*?CSV conversion error to (\w+): invalid value '(.*)'", arrow_message, re.S)
    if m:
        k, value = int(m.group(1)), m.group(3)
        c = columns[k]
        reason = "not an integer" if c in _INT_SET else "not a number"
        for i, raw in enumerate(lines):
            field_text = text.raw_field(raw, k)
            if field_text == value or field_text.strip().strip('"') == value:
                return LogFormatError(source, i + 3, reason, column=c, value=field_text)
        row = re.search(r"Row #(\d+)", arrow_message)
        return LogFormatError(source, int(row.group(1)) + 2 if row else None, reason, column=c, value=value)
    return LogFormatError(source, None, f"cannot parse the rows: {arrow_message}")


def _file_error(p: Problem, region: bytes, columns: list[str], source: str) -> LogFormatError:
    if p.value is not None:
        value = p.value
    else:
        raw = text.raw_line(region, p.row)
        value = ",".join(text.raw_field(raw, columns.index(c)) for c in p.value_cols)
    reason = p.reason.replace("{ref}", f"line {p.ref_row + 3}") if p.ref_row is not None else p.reason
    return LogFormatError(source, p.row + 3, reason, column=p.column, value=value, what=p.what)
