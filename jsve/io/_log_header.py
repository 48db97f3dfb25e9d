"""What surrounds a log's rows: line 1's magic and metadata, line 2's header of columns, and the trailer
lines after the rows, each checked against the format (jsve.io._schema) with errors that name the file,
the line and the key or column (LogFormatError). jsve.io._logs reads and writes whole logs with them.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence

from jsve.io import _schema as schema
from jsve.io import _text as text
from jsve.io._errors import LogFormatError, shorten

GT_METADATA = {"gt_missing_frames": int, "gt_source": str}
"""Metadata keys written by `associate_ground_truth`: frames left without ground truth (count) and
the ground-truth file used."""

_GROUP_WORDS = {
    schema.GT_COLUMNS: ("ground-truth", "seven gt_*"),
    schema.WORLD_COLUMNS: ("world-frame", "eight world_*"),
    schema.KEYFRAME_COLUMNS: ("keyframe", "ten keyframe (events, traj, ref_kf, rel_*)"),
}

# --------------------------------------------------------------------------------------------------
# Metadata


_MISSING = object()  # a metadata key that is absent


def check_meta(meta, source: str, line: int | None) -> None:
    """Validate a metadata object against schema.REQUIRED_METADATA / OPTIONAL_METADATA / GT_METADATA."""

    def fail(key, reason, value=None):
        shown = None if value is _MISSING else json.dumps(value, default=repr)
        raise LogFormatError(source, line, reason, column=key, value=shown, what="metadata key")

    if not isinstance(meta, dict):
        raise LogFormatError(source, line, f"metadata must be a JSON object, got {type(meta).__name__}")
    required = ", ".join(schema.REQUIRED_METADATA)
    for key, types in schema.REQUIRED_METADATA.items():
        if key not in meta:
            fail(key, f"required key missing (every log has {required})", _MISSING)
        if not text.is_type(meta[key], types):
            fail(key, f"must be {text.type_name(types)}, got {type(meta[key]).__name__}", meta[key])
    if not (math.isfinite(meta["fps"]) and 0 < meta["fps"] <= schema.FLOAT_MAX):
        fail("fps", "must be a positive number of frames per second (within float32's range)", meta["fps"])
    for key, types in {**schema.OPTIONAL_METADATA, **GT_METADATA}.items():
        if key in meta and not text.is_type(meta[key], types):
            fail(key, f"must be {text.type_name(types)}, got {type(meta[key]).__name__}", meta[key])
    gravity = meta.get("gravity")
    if gravity is not None and (
        len(gravity) != 3
        or not all(text.is_type(g, (int, float)) and abs(g) <= schema.FLOAT_MAX for g in gravity)
    ):
        fail("gravity", "must be a list of 3 numbers (world gravity, m/s^2, within float32's range)", gravity)
    size = meta.get("image_size")
    if size is not None and (len(size) != 2 or not all(text.is_type(s, int) and s > 0 for s in size)):
        fail("image_size", "must be [width, height] in pixels", size)
    grid = meta.get("grid")
    if grid is not None and list(grid) != [8, 8]:
        fail("grid", "must be [8, 8] (SVE bins, cols x rows)", grid)
    missing = meta.get("gt_missing_frames")
    if missing is not None and missing < 0:
        fail("gt_missing_frames", "must be >= 0", missing)
    t_bc = meta.get("camera_in_body")
    if t_bc is not None and not _is_pose(t_bc):
        fail(
            "camera_in_body",
            "must be the camera pose in the body frame, [qw, qx, qy, qz, tx, ty, tz] (unit quaternion, m)",
            t_bc,
        )


def _is_pose(values) -> bool:
    """[qw, qx, qy, qz, tx, ty, tz] of finite numbers within float32's range with a unit quaternion."""
    if len(values) != 7 or not all(text.is_type(v, (int, float)) for v in values):
        return False
    if not all(math.isfinite(v) and abs(v) <= schema.FLOAT_MAX for v in values):
        return False
    return abs(math.sqrt(sum(v * v for v in values[:4])) - 1.0) <= schema.UNIT_QUATERNION_TOLERANCE


_READS = ", ".join(f"v{v}" for v in schema.READ_VERSIONS[:-1]) + f" and v{schema.READ_VERSIONS[-1]}"


def parse_meta_line(raw: bytes, source: str) -> tuple[dict, int]:
    """(metadata, format version) of line 1."""
    try:
        line = raw.decode("utf-8").rstrip("\r")
    except UnicodeDecodeError as e:
        raise LogFormatError(source, 1, f"not a jsve log: line 1 is not UTF-8 text ({e.reason})") from None
    version = next((v for v, magic in schema.MAGICS.items() if line.startswith(magic)), None)
    if version is None:
        other = re.match(r"# jsve-log (v\S+)", line)
        if other:
            reason = f"unsupported format version '{other.group(1)}' (this reader reads {_READS})"
        else:
            reason = (
                f"not a jsve log: line 1 must start with '{schema.MAGIC}' (or a v1 log's "
                f"'{schema.MAGICS[1]}') followed by the JSON metadata, found '{shorten(line)}'"
            )
        raise LogFormatError(source, 1, reason)
    meta = text.load_meta(line[len(schema.MAGICS[version]) :], source)
    check_meta(meta, source, 1)
    return meta, version


# --------------------------------------------------------------------------------------------------
# Header


def check_header(
    names: list[str], source: str, line: int | None, version: int = schema.FORMAT_VERSION
) -> list[str]:
    """The column list `names` must be in format `version`; raises naming missing, unexpected or
    misplaced columns."""

    def fail(reason, column=None):
        raise LogFormatError(source, line, reason, column=column, what="column")

    seen = set()
    for name in names:
        if name in seen:
            fail("appears more than once in the header", name)
        seen.add(name)
    for group, (what, all_of) in _GROUP_WORDS.items():
        present = [c for c in group if c in seen]
        if 0 < len(present) < len(group):
            lacking = [c for c in group if c not in seen]
            fail(
                f"{what} columns partially present: has {_quote(present)}, lacks {_quote(lacking)} "
                f"(give all {all_of} columns or none)",
                lacking[0],
            )
    required = schema.required_columns(version)
    gt, world = schema.GT_COLUMNS[0] in seen, schema.WORLD_COLUMNS[0] in seen
    keyframes = schema.KEYFRAME_COLUMNS[0] in seen
    if keyframes and version < 3:
        fail(f"the keyframe columns are format v3; this log says v{version}", schema.KEYFRAME_COLUMNS[0])
    expected = list(schema.column_order(version, gt, world, keyframes))
    missing = [c for c in expected if c not in seen]
    known = set(required + schema.GT_COLUMNS + schema.WORLD_COLUMNS + schema.KEYFRAME_COLUMNS)
    unexpected = [c for c in names if c not in known]
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
            f"wrong column order: header position {k + 1} holds '{names[k]}', v{version} expects "
            f"'{expected[k]}' there (order: {expected[0]}, {expected[1]}, ..., see docs/log-format.md)",
            names[k],
        )
    return expected


def _quote(names: Sequence[str], limit: int = 8) -> str:
    shown = ", ".join(f"'{n}'" for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


# --------------------------------------------------------------------------------------------------
# Trailers


def parse_trailers(lines: Sequence[tuple[int, str]], source: str) -> dict:
    """key -> parsed JSON of a log's trailer lines, given as (1-based line, text) pairs.

    Raises:
        LogFormatError: naming the line, for a key that is not [a-z0-9_]+, a key given twice, or JSON
            that does not parse.
    """
    trailers: dict = {}
    for line, raw in lines:
        key, _, body = raw[len(schema.TRAILER_PREFIX) :].partition(" ")
        if not re.fullmatch(r"[a-z0-9_]+", key):
            raise LogFormatError(source, line, f"trailer key must be [a-z0-9_]+, found '{shorten(key)}'")
        if key in trailers:
            raise LogFormatError(source, line, f"trailer '{key}' appears more than once")
        try:
            trailers[key] = json.loads(body)
        except json.JSONDecodeError as e:
            raise LogFormatError(
                source, line, f"trailer '{key}': not JSON ({e.msg} at column {e.colno})"
            ) from None
    return trailers


__all__ = ["GT_METADATA", "check_meta", "parse_meta_line", "check_header", "parse_trailers"]
