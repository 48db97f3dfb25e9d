"""Keypoint side files, format v1: every keypoint of every frame of a run, beside its tracking log.

A tracking log (jsve.io._logs) holds per-frame counts; the side file `<log>.keypoints.csv` holds the
keypoints those counts were made of, so that counts and SVE bins can be recomputed after removing some
of them (dynamic-object masks, jsve.masks._masks). docs/masks.md describes the format for people:

    # jsve-keypoints v1 {"sequence": "KITTI_00", "run": 0, "image_size": [1241, 376]}   <- line 1
    t_ns,x,y,ux,uy,octave,inlier                                                     <- line 2
    1000000000,612.25,187.5,612.25,187.5,0,1                                         <- one row per keypoint
    # jsve-keypoints end keypoints=1                                                 <- last line

Rows are grouped by frame in time order (t_ns non-decreasing); a frame without keypoints has no row.
The layout and number rules are the log's (jsve.io._text). Errors are `LogFormatError`s
(jsve.io._errors) naming the file, the 1-based line, the column and the value, like the log reader's;
files are written as `<path>.partial` and renamed when complete.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from jsve.io import _atomic as atomic
from jsve.io import _text as text
from jsve.io._errors import LogFormatError, LogIncompleteError, shorten
from jsve.io._schema import RunLog

MAGIC = "# jsve-keypoints v1 "
"""Prefix of line 1; the rest of the line is a JSON object of metadata."""

END_MARKER = "# jsve-keypoints end keypoints="
"""Prefix of the last line, followed by the number of keypoint rows."""

SUFFIX = ".keypoints.csv"
"""A log `runs/r7.csv` has its keypoints in `runs/r7.keypoints.csv`."""

COLUMNS = ("t_ns", "x", "y", "ux", "uy", "octave", "inlier")
"""Header of the side file, in this order."""

INT_COLUMNS = ("t_ns", "octave", "inlier")
FLOAT_COLUMNS = ("x", "y", "ux", "uy")

UNITS = {
    "t_ns": "ns, the stamp of the frame (the log's t_ns)",
    "x, y": "px, keypoint position in the image as extracted (ORB-SLAM3 mvKeys[i].pt): masks apply here",
    "ux, uy": "px, undistorted position (mvKeysUn[i].pt): the SVE bins are taken here",
    "octave": "pyramid level of the keypoint (mvKeys[i].octave), >= 0",
    "inlier": "1 when the keypoint is a map-point inlier after TrackLocalMap (counted in n_inliers), else 0",
}

REQUIRED_METADATA = {"sequence": str, "run": int, "image_size": list}
OPTIONAL_METADATA = {"disturbance": str, "level": (int, float), "image_bounds": list, "frontend": str}
MATCHED_METADATA = ("sequence", "disturbance", "level", "run")
"""Keys that must agree between a side file and its log (the run id), defaults as in RunLog.run_id."""

_INT_SET = frozenset(INT_COLUMNS)


@dataclass(frozen=True)
class KeypointLog:
    """The keypoints of one run, as read from (or about to be written to) a side file.

    Attributes:
        meta: metadata of line 1: sequence, run, image_size [width, height] px at least; optionally
            disturbance, level, image_bounds [min_x, max_x, min_y, max_y] px (ORB-SLAM3's undistorted
            image bounds, Frame::ComputeImageBounds; default [0, width, 0, height]).
        keypoints: one row per keypoint, COLUMNS: t_ns, octave, inlier int64; x, y, ux, uy float64.
        source: the file (or a name for in-memory data), used in every message.
    """

    meta: dict
    keypoints: pd.DataFrame
    source: str = "<memory>"

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height), px."""
        width, height = self.meta["image_size"]
        return int(width), int(height)

    @property
    def image_bounds(self) -> tuple[float, float, float, float]:
        """(min_x, max_x, min_y, max_y), px: the region ORB-SLAM3's 64 x 48 grid spans."""
        bounds = self.meta.get("image_bounds")
        if bounds is None:
            width, height = self.image_size
            return 0.0, float(width), 0.0, float(height)
        min_x, max_x, min_y, max_y = (float(b) for b in bounds)
        return min_x, max_x, min_y, max_y


def keypoints_path(log_path: str | os.PathLike) -> Path:
    """The side file of a log: `r7.csv` -> `r7.keypoints.csv` (a name without `.csv` gets SUFFIX appended)."""
    path = Path(log_path)
    stem = path.name[: -len(".csv")] if path.name.endswith(".csv") else path.name
    return path.with_name(stem + SUFFIX)


# --------------------------------------------------------------------------------------------------
# Metadata


def _is_number(value) -> bool:
    return text.is_type(value, (int, float)) and math.isfinite(value)


def _check_meta(meta, source: str, line: int | None) -> None:
    def fail(key, reason):
        shown = json.dumps(meta.get(key), default=repr) if key in meta else None
        raise LogFormatError(source, line, reason, column=key, value=shown, what="metadata key")

    if not isinstance(meta, dict):
        raise LogFormatError(source, line, f"metadata must be a JSON object, got {type(meta).__name__}")
    for key in REQUIRED_METADATA:
        if key not in meta:
            fail(key, f"required key missing (keypoint files require {', '.join(REQUIRED_METADATA)})")
    for key, types in {**REQUIRED_METADATA, **OPTIONAL_METADATA}.items():
        if key in meta and not text.is_type(meta[key], types):
            fail(key, f"must be {text.type_name(types)}, got {type(meta[key]).__name__}")
    size = meta["image_size"]
    if len(size) != 2 or not all(text.is_type(s, int) and s > 0 for s in size):
        fail("image_size", "must be [width, height] in pixels")
    bounds = meta.get("image_bounds")
    if bounds is not None and (
        len(bounds) != 4
        or not all(_is_number(b) for b in bounds)
        or not (bounds[0] < bounds[1] and bounds[2] < bounds[3])
    ):
        fail("image_bounds", "must be [min_x, max_x, min_y, max_y] in pixels with min < max")


def _parse_meta_line(raw: bytes, source: str) -> dict:
    try:
        line = raw.decode("utf-8").rstrip("\r")
    except UnicodeDecodeError as e:
        raise LogFormatError(source, 1, f"line 1 is not UTF-8 text ({e.reason})") from None
    if not line.startswith(MAGIC):
        version = re.match(r"# jsve-keypoints (v\S+)", line)
        if version:
            reason = f"unsupported keypoint format version '{version.group(1)}' (this reader reads v1)"
        else:
            reason = (
                f"not a jsve keypoint file: line 1 must start with '{MAGIC}' followed by the JSON "
                f"metadata, found '{shorten(line)}'"
            )
        raise LogFormatError(source, 1, reason)
    meta = text.load_meta(line[len(MAGIC) :], source)
    _check_meta(meta, source, 1)
    return meta


# --------------------------------------------------------------------------------------------------
# Rows


def _scan_fields(lines: list[bytes], source: str) -> LogFormatError | None:
    """The first row with a wrong field count or a field that is not a number (the slow path, taken
    only after Arrow refused the rows)."""
    n_cols = len(COLUMNS)
    for i, raw in enumerate(lines):
        line = i + 3
        row = raw.decode("utf-8", errors="replace").rstrip("\r")
        if not row.strip():
            return LogFormatError(source, line, f"empty line (a row has {n_cols} comma-separated fields)")
        fields = row.split(",")
        if len(fields) < n_cols:
            return LogFormatError(
                source,
                line,
                f"missing: the row has {len(fields)} of {n_cols} fields (truncated row)",
                column=COLUMNS[len(fields)],
            )
        if len(fields) > n_cols:
            return LogFormatError(
                source,
                line,
                f"too many fields: the row has {len(fields)}, expected {n_cols} ({','.join(COLUMNS)})",
            )
        for name, field in zip(COLUMNS, fields, strict=True):
            if field == "":
                return LogFormatError(source, line, "empty value", column=name, value=field)
            if name in INT_COLUMNS:
                if not text.INT64_TEXT.fullmatch(field):
                    return LogFormatError(source, line, "not an integer", column=name, value=field)
                if not text.in_int64(int(field)):
                    return LogFormatError(source, line, "out of the int64 range", column=name, value=field)
            elif not (text.DECIMAL.fullmatch(field) or text.is_non_finite_word(field)):
                return LogFormatError(source, line, "not a number", column=name, value=field)
    return None


def _parse_rows(region: bytes, source: str) -> pd.DataFrame:
    if not region:
        return pd.DataFrame({c: np.zeros(0, np.int64 if c in INT_COLUMNS else np.float64) for c in COLUMNS})
    try:
        table = text.read_rows(region, COLUMNS, _INT_SET)
    except pa.ArrowInvalid as e:
        error = _scan_fields(region.split(b"\n")[:-1], source)
        raise (error or LogFormatError(source, None, f"cannot parse the rows: {e}")) from None
    if any(table.column(c).null_count for c in COLUMNS):
        error = _scan_fields(region.split(b"\n")[:-1], source)
        raise error or LogFormatError(source, None, "empty value in the rows")
    return table.to_pandas()


def _first_problem(kp: pd.DataFrame) -> tuple[int, str, str] | None:
    """(row, column, reason) of the first value that breaks the v1 keypoint rules, or None."""
    found = []

    def first(bad: np.ndarray, column: str, reason) -> None:
        if bad.any():
            r = int(np.argmax(bad))
            found.append((r, COLUMNS.index(column), column, reason(r) if callable(reason) else reason))

    for c in FLOAT_COLUMNS:
        first(~np.isfinite(kp[c].to_numpy()), c, "NaN or inf is not allowed")
    t = kp["t_ns"].to_numpy()
    if len(t) > 1:
        back = np.concatenate([[False], np.diff(t) < 0])
        first(
            back,
            "t_ns",
            lambda r: (
                f"t_ns must not decrease (rows are grouped by frame in time order): "
                f"{int(t[r - 1]) - int(t[r])} ns earlier than the previous row"
            ),
        )
    first(kp["octave"].to_numpy() < 0, "octave", "must be >= 0 (a pyramid level)")
    inlier = kp["inlier"].to_numpy()
    first((inlier != 0) & (inlier != 1), "inlier", "must be 0 or 1")
    if not found:
        return None
    r, _, column, reason = min(found)
    return r, column, reason


# --------------------------------------------------------------------------------------------------
# Reading and writing


def parse_keypoints(data: bytes, source: str = "<memory>") -> KeypointLog:
    """Parse and validate the bytes of a keypoint side file (what `read_keypoints` does after reading).

    Raises:
        LogIncompleteError: empty, no end marker, or a count that disagrees with the rows.
        LogFormatError: any other defect, naming file, line, column and value.
    """
    data = text.file_bytes(data, source)
    if not data:
        raise LogIncompleteError(source, 1, "empty file (0 bytes): the keypoint file is incomplete")
    parts = text.cut(data)
    meta = _parse_meta_line(parts.first, source)

    n_lines = parts.n_lines
    count_text = text.end_count(parts.last, END_MARKER)
    if count_text is None:
        raise LogIncompleteError(
            source,
            n_lines,
            f"the keypoint file is incomplete: it ends at line {n_lines} without the end marker "
            f"'{END_MARKER}N' (its writer stopped before the end of the run)",
        )
    if not text.is_count(count_text):
        raise LogFormatError(
            source,
            n_lines,
            f"end marker keypoint count must be a non-negative integer, found '{shorten(count_text)}'",
        )
    if parts.header is None:
        raise LogFormatError(source, 2, "missing header line: line 2 is the end marker")
    header = parts.header.decode("utf-8", errors="replace").split(",")
    if header != list(COLUMNS):
        k = next(
            (i for i, (a, b) in enumerate(zip(header, COLUMNS, strict=False)) if a != b),
            min(len(header), len(COLUMNS)),
        )
        shown = header[k] if k < len(header) else COLUMNS[k]
        raise LogFormatError(
            source, 2, f"wrong header: expected '{','.join(COLUMNS)}'", column=shown, what="column"
        )

    region = parts.rows
    kp = _parse_rows(region, source)
    if len(kp) != int(count_text):
        raise LogIncompleteError(
            source,
            n_lines,
            f"the keypoint file is incomplete: the end marker says {int(count_text)} keypoints "
            f"but the file has {len(kp)} rows",
        )
    problem = _first_problem(kp)
    if problem is not None:
        r, column, reason = problem
        value = text.raw_field(text.raw_line(region, r), COLUMNS.index(column))
        raise LogFormatError(source, r + 3, reason, column=column, value=value)
    return KeypointLog(meta=meta, keypoints=kp, source=source)


def read_keypoints(path: str | os.PathLike) -> KeypointLog:
    """Read and validate one keypoint side file (see the module docstring and docs/masks.md).

    Returns:
        KeypointLog with int64 t_ns, octave, inlier and float64 x, y, ux, uy; `source` is `path`.

    Raises:
        LogIncompleteError: empty file, no end marker, wrong count, or a `.partial` name.
        LogFormatError: any other defect, as `path:line: column 'x' = 'abc': not a number`.
        OSError: the file cannot be read.
    """
    source = os.fspath(path)
    if source.endswith(atomic.PARTIAL_SUFFIX):
        raise LogIncompleteError(
            source, None, "the keypoint file is incomplete: a '.partial' file's writer has not finished"
        )
    with open(path, "rb") as f:
        return parse_keypoints(f.read(), source)


def validate_keypoints(kp: KeypointLog) -> KeypointLog:
    """Check in-memory keypoints against the v1 rules; return them in canonical form (COLUMNS order,
    int64 / float64, RangeIndex, metadata as it reads back from JSON).

    Raises:
        LogFormatError: `<memory>: column 'inlier' = '2': must be 0 or 1 (keypoint row 12)` (0-based).
    """
    source = kp.source
    meta = text.canonical_meta(kp.meta, source)
    _check_meta(meta, source, None)
    missing = [c for c in COLUMNS if c not in kp.keypoints.columns]
    extra = [c for c in kp.keypoints.columns if c not in COLUMNS]
    if missing or extra:
        raise LogFormatError(
            source, None, f"columns must be {', '.join(COLUMNS)}: missing {missing}, unexpected {extra}"
        )
    columns = {}
    for c in COLUMNS:
        values = kp.keypoints[c].to_numpy()
        if c in INT_COLUMNS and not np.issubdtype(values.dtype, np.integer):
            raise LogFormatError(
                source, None, f"has dtype {values.dtype}; expected an integer dtype", column=c
            )
        if c in FLOAT_COLUMNS and not np.issubdtype(values.dtype, np.number):
            raise LogFormatError(source, None, f"has dtype {values.dtype}; expected float64", column=c)
        columns[c] = values.astype(np.int64 if c in INT_COLUMNS else np.float64, copy=False)
    frame = pd.DataFrame(columns, columns=list(COLUMNS))
    problem = _first_problem(frame)
    if problem is not None:
        r, column, reason = problem
        raise LogFormatError(
            source,
            None,
            f"{reason} (keypoint row {r})",
            column=column,
            value=text.format_value(frame[column].iloc[r]),
        )
    return KeypointLog(meta=meta, keypoints=frame, source=source)


def write_keypoints(kp: KeypointLog, path: str | os.PathLike) -> Path:
    """Write a keypoint side file atomically (`<path>.partial`, then rename).

    Integers are written exactly, floats in the shortest form that reads back to the same double, so
    `read_keypoints` returns the keypoints bit for bit.

    Arguments:
        kp: valid keypoints (see `validate_keypoints`; invalid ones raise and nothing is written).
        path: destination, conventionally `keypoints_path(log)`; parent folders are created.
    """
    kp = validate_keypoints(kp)
    return atomic.write_bytes(
        path,
        text.head(MAGIC, kp.meta, COLUMNS),
        text.write_rows(pa.Table.from_pandas(kp.keypoints, preserve_index=False)),
        text.tail(END_MARKER, len(kp.keypoints)),
    )


# --------------------------------------------------------------------------------------------------
# Joining keypoints with their log


def check_matches_log(kp: KeypointLog, run: RunLog) -> None:
    """Raise unless the side file describes the run: same run id metadata and image size.

    Raises:
        LogFormatError: naming the side file, line 1 and the key that disagrees.
    """
    defaults = {"disturbance": "none", "level": 0}
    for key in MATCHED_METADATA:
        mine, theirs = kp.meta.get(key, defaults.get(key)), run.meta.get(key, defaults.get(key))
        if mine != theirs:
            raise LogFormatError(
                kp.source,
                1,
                f"does not match the log's {key} {json.dumps(theirs)} ({run.source}): "
                "not this run's keypoints",
                column=key,
                value=json.dumps(mine),
                what="metadata key",
            )
    size = run.meta.get("image_size")
    if size is not None and list(size) != list(kp.meta["image_size"]):
        raise LogFormatError(
            kp.source,
            1,
            f"does not match the log's image_size {list(size)} ({run.source})",
            column="image_size",
            value=json.dumps(kp.meta["image_size"]),
            what="metadata key",
        )


def frame_of_keypoints(kp: KeypointLog, t_ns: np.ndarray, log_source: str = "the log") -> np.ndarray:
    """The 0-based frame of every keypoint: the index of its t_ns among the log's frame stamps.

    Arguments:
        kp: the keypoints (t_ns non-decreasing).
        t_ns: [F] int64 frame stamps of the log, strictly increasing.
        log_source: the log's name, for messages.

    Returns:
        [K] int64 frame indices, non-decreasing.

    Raises:
        LogFormatError: a keypoint whose t_ns is no frame of the log (file and line of that keypoint).
    """
    t_ns = np.asarray(t_ns, np.int64)
    kt = kp.keypoints["t_ns"].to_numpy()
    frame = np.searchsorted(t_ns, kt)
    clipped = np.minimum(frame, max(len(t_ns) - 1, 0))
    bad = (frame >= len(t_ns)) | (t_ns[clipped] != kt) if len(t_ns) else np.ones(len(kt), bool)
    if bad.any():
        r = int(np.argmax(bad))
        line = r + 3 if kp.source != "<memory>" else None
        raise LogFormatError(
            kp.source,
            line,
            f"no frame of {log_source} has this stamp{'' if line else f' (row {r})'}",
            column="t_ns",
            value=str(int(kt[r])),
        )
    return frame.astype(np.int64)
