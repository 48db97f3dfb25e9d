"""jsve.io._logs: tracking logs, format v2 (and v1 read with defaults): writing, reading and
validating one log, exactly."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from logfactory import (
    EUROC_T0_NS,
    edit_line,
    get_field,
    make_run,
    read_lines,
    same_bits,
    set_field,
    v1_text,
    write_lines,
)

from jsve.io import _logs as logs
from jsve.io import _schema as schema
from jsve.io import _text as text
from jsve.io._errors import LogVersionWarning
from jsve.io._logs import LogFormatError, LogIncompleteError

N = 20  # frames of the small logs below; frame i is on line i + 3, the end marker on line N + 3
LAST = N + 3


def same_runs(a: list[schema.RunLog], b: list[schema.RunLog]) -> bool:
    return len(a) == len(b) and all(
        x.meta == y.meta and x.source == y.source and same_bits(x.frames, y.frames)
        for x, y in zip(a, b, strict=True)
    )


@pytest.fixture
def log(tmp_path) -> Path:
    """A valid log of N frames with ground truth."""
    return logs.write_log(make_run(N, seed=3), tmp_path / "r7.csv")


def expect(path, exc, line, column=None, value=None, reason=None) -> LogFormatError:
    """read_log(path) raises exactly `exc`, at `line`, naming `column` (and `value`) in the message."""
    with pytest.raises(LogFormatError) as info:
        logs.read_log(path)
    err = info.value
    assert type(err) is exc, str(err)
    assert err.line == line, str(err)
    assert err.column == column, str(err)
    loc = f"{path}:{line}: " if line is not None else f"{path}: "
    assert str(err).startswith(loc), str(err)
    if column is not None:
        named = re.escape(loc) + rf"(column|columns|metadata key) '{re.escape(column)}'"
        if value is not None:  # long values are shortened in the message
            named += re.escape(f" = '{value[:60]}")
        assert re.match(named, str(err)), str(err)
    if value is not None:
        assert err.value == value
    if reason is not None:
        assert reason in err.reason, str(err)
    return err


# ---------------------------------------------------------------------------------------------------
# Round trip


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("with_gt", [True, False])
def test_round_trip_is_exact(tmp_path, seed, with_gt):
    map_id = np.repeat([0, 3, 3, 1 << 40], 100)  # ids change (a new map) and repeat (a reset keeps it)
    run = make_run(
        400,
        seed,
        with_gt=with_gt,
        gt_missing=0.25,
        awkward_floats=True,
        no_pose=0.3,
        map_id=map_id,
        sequence="MH_04",
        level=15,
    )
    no_pose = run.frames["vis_px"].isna().to_numpy()
    assert 0 < no_pose.sum() and 0 < run.frames["imu_ba2"].sum()
    path = logs.write_log(run, tmp_path / "a.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a v2 log reads without a version warning
        back = logs.read_log(path)
    assert same_bits(back.frames, run.frames)
    assert np.array_equal(back.frames["map_id"].to_numpy(), map_id)
    assert np.array_equal(back.frames[list(schema.VIS_COLUMNS)].isna().all(axis=1).to_numpy(), no_pose)
    assert back.meta == run.meta
    assert back.source == str(path)
    assert isinstance(back.frames.index, pd.RangeIndex)
    lines = read_lines(path)
    assert lines[0] == "# jsve-log v3 " + json.dumps(run.meta)
    assert lines[1].startswith("t_ns,state,imu_init,map_id,imu_ba2,n_extracted,")
    assert lines[1] == ",".join(schema.COLUMNS if with_gt else schema.REQUIRED_COLUMNS)
    assert lines[-1] == f"{schema.END_MARKER}400"
    assert len(lines) == 403
    assert not (tmp_path / "a.csv.partial").exists()
    # A frame without a pose has its ten vis_* fields empty, and only those.
    k = int(np.argmax(no_pose))
    fields = dict(zip(lines[1].split(","), lines[k + 2].split(","), strict=True))
    assert [c for c, v in fields.items() if v == "" and not c.startswith("gt_")] == list(schema.VIS_COLUMNS)


def test_round_trip_keeps_int64_stamps_that_float64_cannot_hold(tmp_path):
    run = make_run(5, 0)
    t = np.array([2**62 + 1, 2**62 + 2, 2**62 + 3, 2**63 - 2, 2**63 - 1], dtype=np.int64)
    assert len(set(t.astype(np.float64))) < len(t)  # what float64 would have lost
    run = dataclasses.replace(run, frames=run.frames.assign(t_ns=t))
    back = logs.read_log(logs.write_log(run, tmp_path / "a.csv"))
    assert back.frames["t_ns"].dtype == np.int64
    assert np.array_equal(back.frames["t_ns"].to_numpy(), t)


def test_gt_missing_frames_are_empty_fields(tmp_path):
    run = make_run(N, 5, gt_missing=0.5)
    missing = run.frames["gt_px"].isna().to_numpy()
    assert 0 < missing.sum() < N
    path = logs.write_log(run, tmp_path / "a.csv")
    k = int(np.argmax(missing))
    assert read_lines(path)[k + 2].endswith(",,,,,,,")
    assert np.array_equal(logs.read_log(path).frames["gt_qz"].isna().to_numpy(), missing)


@settings(max_examples=40, deadline=None)
@given(
    values=st.lists(st.floats(-schema.FLOAT_MAX, schema.FLOAT_MAX), min_size=6, max_size=6),
    steps=st.lists(st.integers(0, 2**20), min_size=5, max_size=5),
)
def test_any_double_in_range_and_int64_round_trips(values, steps, tmp_path_factory):
    run = make_run(6, 1, with_gt=False)
    t = np.cumsum(np.array([2**62, *steps], dtype=np.int64) + 1)
    frames = run.frames.assign(vis_vx=np.array(values), t_ns=t)
    path = tmp_path_factory.mktemp("h") / "a.csv"
    back = logs.read_log(logs.write_log(dataclasses.replace(run, frames=frames), path))
    assert same_bits(back.frames, frames)


def test_crlf_line_ends_read_the_same(log, tmp_path):
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(log.read_bytes().replace(b"\n", b"\r\n"))
    assert same_bits(logs.read_log(crlf).frames, logs.read_log(log).frames)


def test_write_is_atomic(tmp_path, monkeypatch):
    path = logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    before = path.read_bytes()

    def die(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(text.pacsv, "write_csv", die)
    with pytest.raises(OSError, match="disk full"):
        logs.write_log(make_run(N, 2), path)
    assert path.read_bytes() == before  # the old log is untouched
    assert not (tmp_path / "a.csv.partial").exists()


def test_invalid_runs_are_not_written(tmp_path):
    run = make_run(N, 1)
    frames = run.frames.copy()
    frames.loc[12, "imu_dt"] = -0.05
    with pytest.raises(LogFormatError) as info:
        logs.write_log(dataclasses.replace(run, frames=frames, source="sim/r1"), tmp_path / "a.csv")
    assert str(info.value).startswith("sim/r1: frame 12: column 'imu_dt' = '-0.05': must be >= 0")
    assert info.value.frame == 12 and info.value.line is None
    assert not list(tmp_path.iterdir())


def test_validate_run_checks_memory_dtypes_and_columns():
    run = make_run(N, 1)
    with pytest.raises(LogFormatError, match="column 'n_inliers': has dtype float64"):
        logs.validate_run(dataclasses.replace(run, frames=run.frames.astype({"n_inliers": float})))
    with pytest.raises(LogFormatError, match="unexpected column 'extra'"):
        logs.validate_run(dataclasses.replace(run, frames=run.frames.assign(extra=1.0)))
    with pytest.raises(LogFormatError, match="metadata key 'fps'"):
        logs.validate_run(dataclasses.replace(run, meta={k: v for k, v in run.meta.items() if k != "fps"}))
    # Column order in memory is free; the canonical form has the v1 order.
    shuffled = run.frames[list(reversed(run.frames.columns))]
    assert list(logs.validate_run(dataclasses.replace(run, frames=shuffled)).frames.columns) == list(
        schema.COLUMNS
    )
    # numpy scalars in metadata are written as JSON numbers.
    meta = {**run.meta, "run": np.int64(4), "level": np.float32(2.5)}
    assert logs.validate_run(dataclasses.replace(run, meta=meta)).meta["run"] == 4


# ---------------------------------------------------------------------------------------------------
# Malformed logs: each names the exact line and column


def test_empty_file(tmp_path):
    path = tmp_path / "empty.csv"
    path.write_bytes(b"")
    err = expect(path, LogIncompleteError, 1, reason="empty file")
    assert "incomplete" in str(err)


def test_wrong_magic(log):
    edit_line(log, 1, "# some other tool {}")
    expect(log, LogFormatError, 1, reason="not a jsve log: line 1 must start with '# jsve-log v3 '")


def test_missing_magic_line(log):
    edit_line(log, 1, None)  # the file now starts with the header
    expect(log, LogFormatError, 1, reason="found 't_ns,state,imu_init,")


@pytest.mark.parametrize("version", ["v4", "v0", "v2.1"])
def test_other_format_version(log, version):
    edit_line(log, 1, f'# jsve-log {version} {{"sequence": "X", "run": 1, "fps": 20}}')
    err = expect(log, LogFormatError, 1)
    assert err.reason == f"unsupported format version '{version}' (this reader reads v1, v2 and v3)"


def test_metadata_not_json(log):
    edit_line(log, 1, schema.MAGIC + '{"sequence": "X", "run": 1, "fps": 20')
    expect(log, LogFormatError, 1, reason="metadata is not valid JSON")
    edit_line(log, 1, schema.MAGIC + '{"sequence": "X", "run": 1, "fps": NaN}')
    expect(log, LogFormatError, 1, reason="metadata is not valid JSON")
    edit_line(log, 1, schema.MAGIC + "[1, 2]")
    expect(log, LogFormatError, 1, reason="metadata must be a JSON object, got list")


def test_metadata_missing_required_key(log):
    edit_line(log, 1, schema.MAGIC + '{"sequence": "X", "run": 1}')
    err = expect(log, LogFormatError, 1, column="fps", reason="required key missing")
    assert f"{log}:1: metadata key 'fps': required key missing" in str(err)


@pytest.mark.parametrize(
    "meta, key, shown, reason",
    [
        ('{"sequence": "X", "run": "7", "fps": 20}', "run", '"7"', "must be an integer, got str"),
        ('{"sequence": "X", "run": true, "fps": 20}', "run", "true", "must be an integer, got bool"),
        ('{"sequence": 3, "run": 1, "fps": 20}', "sequence", "3", "must be a string, got int"),
        ('{"sequence": "X", "run": 1, "fps": 0}', "fps", "0", "must be a positive number"),
        (
            '{"sequence": "X", "run": 1, "fps": 20, "gravity": [0, -9.81]}',
            "gravity",
            "[0, -9.81]",
            "3 numbers",
        ),
        ('{"sequence": "X", "run": 1, "fps": 20, "grid": [4, 4]}', "grid", "[4, 4]", "[8, 8]"),
        ('{"sequence": "X", "run": 1, "fps": 20, "n_features": 1.5}', "n_features", "1.5", "an integer"),
    ],
)
def test_metadata_wrong_type(log, meta, key, shown, reason):
    edit_line(log, 1, schema.MAGIC + meta)
    err = expect(log, LogFormatError, 1, column=key, value=shown, reason=reason)
    assert f"{log}:1: metadata key '{key}' = '{shown}': " in str(err)


def test_header_missing_column(log):
    header = read_lines(log)[1].replace(",n_frustum", "")
    edit_line(log, 2, header)
    expect(log, LogFormatError, 2, column="n_frustum", reason="missing column 'n_frustum'")


def test_header_unexpected_column(log):
    edit_line(log, 2, read_lines(log)[1] + ",speed")
    expect(log, LogFormatError, 2, column="speed", reason="unexpected column 'speed'")


def test_header_missing_and_unexpected_are_both_named(log):
    edit_line(log, 2, read_lines(log)[1].replace("imu_dt", "imu_dt_s"))
    err = expect(log, LogFormatError, 2, column="imu_dt")
    assert "missing column 'imu_dt'" in err.reason and "unexpected column 'imu_dt_s'" in err.reason


def test_header_wrong_order(log):
    edit_line(log, 2, read_lines(log)[1].replace("n_extracted,n_inliers", "n_inliers,n_extracted"))
    expect(
        log,
        LogFormatError,
        2,
        column="n_inliers",
        reason="wrong column order: header position 6 holds 'n_inliers', v3 expects 'n_extracted'",
    )


def test_header_duplicate_column(log):
    edit_line(log, 2, read_lines(log)[1].replace("bin_7,", "bin_6,"))
    expect(log, LogFormatError, 2, column="bin_6", reason="appears more than once")


def test_header_gt_partially_present(log):
    lines = read_lines(log)
    lines[1] = lines[1].replace(",gt_qy,gt_qz", "")
    write_lines(log, lines)
    expect(log, LogFormatError, 2, column="gt_qy", reason="ground-truth columns partially present")


def test_truncated_row(log):
    lines = read_lines(log)
    lines[6] = ",".join(lines[6].split(",")[:-3])  # line 7 loses its last three fields
    write_lines(log, lines)
    n = len(schema.COLUMNS)
    assert n == 100  # 98 v1 columns + map_id + imu_ba2
    expect(
        log,
        LogFormatError,
        7,
        column=schema.COLUMNS[-3],
        reason=f"row has {n - 3} of {n} fields (truncated row)",
    )


def test_too_many_fields(log):
    lines = read_lines(log)
    lines[8] += ",1.0"
    write_lines(log, lines)
    expect(log, LogFormatError, 9, reason="too many fields: the row has 101, the header has 100")


def test_empty_line(log):
    edit_line(log, 8, "")
    expect(log, LogFormatError, 8, reason="empty line")


@pytest.mark.parametrize(
    "column, text, reason",
    [
        ("n_inliers", "abc", "not an integer"),
        ("state", "2.0", "not an integer"),
        ("t_ns", "1e18", "not an integer"),
        ("t_ns", "99999999999999999999", "not an integer"),  # beyond int64
        ("vis_px", "1.2.3", "not a number"),
        ("gt_qx", "0x1p-3", "not a number"),
        ("state", "0x2", "not an integer"),  # Arrow's int64 parser reads hexadecimal (found by fuzzing)
        ("t_ns", "0X1F", "not an integer"),
    ],
)
def test_non_numeric_value(log, column, text, reason):
    set_field(log, 10, column, text)
    expect(log, LogFormatError, 10, column=column, value=text, reason=reason)


@pytest.mark.parametrize(
    "column, text",
    [("vis_vy", "nan"), ("imu_dpx", "inf"), ("vis_qw", "-inf"), ("imu_dvz", "1e400"), ("gt_px", "NaN")],
)
def test_nan_or_inf(log, column, text):
    set_field(log, 11, column, text)
    expect(log, LogFormatError, 11, column=column, value=text, reason="NaN or inf is not allowed")


@pytest.mark.parametrize("column", ["n_frustum", "t_ns", "map_id", "imu_ba2", "imu_dt"])
def test_empty_value_outside_gt_and_vis(log, column):
    set_field(log, 6, column, "")
    expect(log, LogFormatError, 6, column=column, value="", reason="only gt_* and vis_* fields may be empty")


def test_duplicate_timestamp(log):
    set_field(log, 12, "t_ns", get_field(log, 11, "t_ns"))
    expect(log, LogFormatError, 12, column="t_ns", reason="duplicate timestamp: the same as line 11")


def test_unsorted_timestamps(log):
    lines = read_lines(log)
    lines[11], lines[12] = lines[12], lines[11]  # swap lines 12 and 13
    write_lines(log, lines)
    err = expect(log, LogFormatError, 13, column="t_ns", reason="strictly increasing")
    assert "earlier than line 12" in err.reason and "unsorted" in err.reason


@pytest.mark.parametrize("column", ["n_extracted", "n_inliers", "n_frustum", "bin_5"])
def test_negative_count(log, column):
    set_field(log, 9, column, "-1")
    expect(log, LogFormatError, 9, column=column, value="-1", reason="must be >= 0")


def test_more_inliers_than_extracted(log):
    n_ext = int(get_field(log, 14, "n_extracted"))
    set_field(log, 14, "n_inliers", str(n_ext + 1))
    expect(
        log, LogFormatError, 14, column="n_inliers", value=str(n_ext + 1), reason=f"<= n_extracted ({n_ext})"
    )


def test_bins_exceed_extracted(log):
    n_ext = int(get_field(log, 15, "n_extracted"))
    total = sum(int(get_field(log, 15, c)) for c in schema.BIN_COLUMNS)
    bin0 = int(get_field(log, 15, "bin_0"))
    set_field(log, 15, "bin_0", str(bin0 + n_ext - total + 1))  # sum = n_extracted + 1
    expect(
        log,
        LogFormatError,
        15,
        column="bin_0..bin_63",
        value=str(n_ext + 1),
        reason=f"must not exceed n_extracted ({n_ext})",
    )


@pytest.mark.parametrize("text", ["6", "-2"])
def test_state_not_valid(log, text):
    set_field(log, 5, "state", text)
    expect(log, LogFormatError, 5, column="state", value=text, reason="must be one of -1, 0, 1, 2, 3, 4, 5")


def test_imu_init_not_boolean(log):
    set_field(log, 5, "imu_init", "2")
    expect(log, LogFormatError, 5, column="imu_init", value="2", reason="must be 0 or 1")


@pytest.mark.parametrize("group", ["vis_q", "imu_dq", "gt_q"])
def test_non_unit_quaternion(log, group):
    names = schema.QUATERNION_GROUPS[group]
    w = float(get_field(log, 16, names[0]))
    set_field(log, 16, names[0], repr(w + 0.1 if w >= 0 else w - 0.1))  # |q|^2 grows by >= 0.01
    fields = ",".join(get_field(log, 16, c) for c in names)
    expect(
        log,
        LogFormatError,
        16,
        column=f"{names[0]}..{names[-1]}",
        value=fields,
        reason="not a unit quaternion",
    )


def test_quaternion_within_tolerance_is_accepted(log):
    w = float(get_field(log, 16, "vis_qw"))
    # |q| changes by about w * 1e-7 < 1e-6 = schema.UNIT_QUATERNION_TOLERANCE.
    set_field(log, 16, "vis_qw", repr(w * (1 + 1e-7)))
    assert logs.read_log(log).frames["vis_qw"].iat[13] == w * (1 + 1e-7)


def test_negative_imu_dt(log):
    set_field(log, 12, "imu_dt", "-0.05")
    err = expect(log, LogFormatError, 12, column="imu_dt", value="-0.05", reason="must be >= 0")
    assert str(err).startswith(f"{log}:12: column 'imu_dt' = '-0.05': must be >= 0")


def test_gt_partially_empty_row(log):
    set_field(log, 10, "gt_py", "")
    expect(log, LogFormatError, 10, column="gt_py", value="", reason="all seven gt_* values or none")


def test_gt_fully_empty_row_is_no_ground_truth(log):
    for c in schema.GT_COLUMNS:
        set_field(log, 10, c, "")
    frames = logs.read_log(log).frames
    assert frames.loc[7, list(schema.GT_COLUMNS)].isna().all()
    assert frames.drop(index=7)[list(schema.GT_COLUMNS)].notna().all(axis=None)


@pytest.mark.parametrize("column", ["imu_dt", "imu_dpy", "imu_dvz"])
def test_first_frame_has_no_preintegration(log, column):
    set_field(log, 3, column, "0.05")
    expect(log, LogFormatError, 3, column=column, value="0.05", reason="must be 0 on the first frame")


def test_first_frame_rotation_is_identity(log):
    c = 0.5**0.5
    for name, value in zip(schema.IMU_DQ, [c, c, 0.0, 0.0], strict=True):
        set_field(log, 3, name, repr(value))
    expect(log, LogFormatError, 3, column="imu_dqw..imu_dqz", reason="identity (1, 0, 0, 0)")


def test_first_defect_in_reading_order_is_reported(log):
    set_field(log, 9, "imu_dt", "-1")
    set_field(log, 5, "bin_3", "-1")
    set_field(log, 5, "vis_px", "nan")
    expect(log, LogFormatError, 5, column="bin_3")  # line 5 before line 9; bin_3 left of vis_px


def test_missing_end_marker(log):
    edit_line(log, LAST, None)
    err = expect(log, LogIncompleteError, LAST - 1, reason="the log is incomplete")
    assert "without the end marker" in str(err)


def test_writer_died_mid_row(log):
    data = log.read_bytes()
    log.write_bytes(data[: data.index(b"\n", len(data) // 2) - 40])
    err = expect(log, LogIncompleteError, log.read_bytes().count(b"\n") + 1)
    assert "incomplete" in str(err)


def test_only_the_magic_line(log):
    write_lines(log, read_lines(log)[:1])
    expect(log, LogIncompleteError, 1, reason="incomplete")


def test_end_marker_count_disagrees(log):
    edit_line(log, 10, None)  # a row lost; the marker still says N
    err = expect(
        log, LogIncompleteError, LAST - 1, reason=f"the end marker says {N} frames but the file has {N - 1}"
    )
    assert "incomplete" in str(err)


def test_end_marker_count_not_a_number(log):
    edit_line(log, LAST, schema.END_MARKER + "twenty")
    expect(log, LogFormatError, LAST, reason="frame count must be a non-negative integer")


def test_no_frames(tmp_path):
    path = tmp_path / "a.csv"
    meta = json.dumps({"sequence": "X", "run": 1, "fps": 20})
    write_lines(path, [schema.MAGIC + meta, ",".join(schema.REQUIRED_COLUMNS), schema.END_MARKER + "0"])
    expect(path, LogFormatError, 3, reason="the log has no frames")


def test_partial_file_is_incomplete(log):
    partial = log.with_name(log.name + ".partial")
    log.rename(partial)
    err = expect(partial, LogIncompleteError, None, reason="the log is incomplete")
    assert "'.partial'" in str(err)


def test_errors_deep_in_a_large_log_name_the_right_line(tmp_path):
    # 3,000 frames are ~2 MB: past Arrow's 1 MB parse blocks.
    path = logs.write_log(make_run(3000, 4), tmp_path / "big.csv")
    good = path.read_bytes()
    for line, column, bad, reason in [
        (2900, "n_inliers", "x", "not an integer"),
        (2950, "vis_px", "1.2.3", "not a number"),
        (2999, "imu_dt", "-1", "must be >= 0"),
    ]:
        path.write_bytes(good)
        set_field(path, line, column, bad)
        expect(path, LogFormatError, line, column=column, value=bad, reason=reason)
    path.write_bytes(good)
    lines = read_lines(path)
    lines[2700] = ",".join(lines[2700].split(",")[:50])
    write_lines(path, lines)
    expect(path, LogFormatError, 2701, column=schema.COLUMNS[50], reason="truncated row")


# ---------------------------------------------------------------------------------------------------
# Format v2: map_id, imu_ba2, frames without a pose, metadata


def clear_pose(path, line: int, state: str = "4") -> None:
    """Make line `line` a frame without a pose: `state` and ten empty vis_* fields."""
    set_field(path, line, "state", state)
    for c in schema.VIS_COLUMNS:
        set_field(path, line, c, "")


@pytest.mark.parametrize("state", ["-1", "0", "1", "4"])
def test_frame_without_a_pose_reads_as_nan(log, state):
    clear_pose(log, 8, state)
    frames = logs.read_log(log).frames
    assert frames.loc[5, list(schema.VIS_COLUMNS)].isna().all()  # line 8 is frame 5
    assert frames.drop(index=5)[list(schema.VIS_COLUMNS)].notna().all(axis=None)
    assert frames["vis_px"].dtype == np.float64


@pytest.mark.parametrize("state", ["2", "3", "5"])
def test_frame_in_a_tracked_state_must_have_a_pose(log, state):
    clear_pose(log, 8, state)
    name = schema.STATE_NAMES[int(state)]
    err = expect(
        log, LogFormatError, 8, column="vis_px", value="", reason=f"no pose in state {state} ({name})"
    )
    assert "frames in states 2 (OK), 3 (RECENTLY_LOST) and 5 (OK_KLT) have one" in err.reason


@pytest.mark.parametrize("column", ["vis_px", "vis_qy", "vis_vz"])
def test_partially_empty_pose_names_the_column(log, column):
    set_field(log, 8, "state", "4")
    set_field(log, 8, column, "")
    err = expect(log, LogFormatError, 8, column=column, value="")
    assert "missing while 9 other vis_* values of this frame are present" in err.reason


def test_partially_empty_pose_reports_the_first_empty_column(log):
    clear_pose(log, 8)
    set_field(log, 8, "vis_qx", "0.5")  # nine empty, one present: the first empty is named
    expect(log, LogFormatError, 8, column="vis_px", value="", reason="missing while 1 other vis_*")


def test_nan_text_in_a_pose_field_is_not_an_empty_field(log):
    clear_pose(log, 8)
    set_field(log, 8, "vis_vy", "nan")
    expect(log, LogFormatError, 8, column="vis_vy", value="nan", reason="leave all ten vis_* fields empty")


def test_quaternion_check_skips_frames_without_a_pose_only(log):
    clear_pose(log, 8)
    logs.read_log(log)  # NaN quaternion: no unit-norm error
    set_field(log, 9, "vis_qw", "3.0")  # a posed frame is still checked
    expect(log, LogFormatError, 9, column="vis_qw..vis_qz", reason="not a unit quaternion")


def test_imu_ba2_requires_imu_init(log):
    set_field(log, 7, "imu_init", "0")
    set_field(log, 7, "imu_ba2", "1")
    err = expect(log, LogFormatError, 7, column="imu_ba2", value="1", reason="requires imu_init = 1")
    assert str(err).startswith(f"{log}:7: column 'imu_ba2' = '1': requires imu_init = 1")
    set_field(log, 7, "imu_ba2", "0")
    assert logs.read_log(log).frames.loc[4, ["imu_init", "imu_ba2"]].tolist() == [0, 0]


@pytest.mark.parametrize(
    "column, text, reason",
    [
        ("imu_ba2", "2", "must be 0 or 1"),
        ("imu_ba2", "-1", "must be 0 or 1"),
        ("map_id", "-1", "must be >= 0 (ORB-SLAM3 Map::GetId()"),
        ("map_id", "1.0", "not an integer"),
        ("imu_ba2", "yes", "not an integer"),
    ],
)
def test_map_columns_are_checked(log, column, text, reason):
    set_field(log, 7, "imu_init", "1")
    set_field(log, 7, column, text)
    expect(log, LogFormatError, 7, column=column, value=text, reason=reason)


def test_v2_header_needs_the_map_columns(log):
    edit_line(log, 2, read_lines(log)[1].replace(",map_id,imu_ba2", ""))
    err = expect(log, LogFormatError, 2, column="map_id")
    assert "missing columns 'map_id', 'imu_ba2'" in err.reason


def test_in_memory_runs_follow_the_same_pose_rules(tmp_path):
    run = make_run(N, 2)
    frames = run.frames.copy()
    frames.loc[6, "state"] = schema.STATE_LOST
    frames.loc[6, list(schema.VIS_COLUMNS)] = np.nan
    assert logs.validate_run(dataclasses.replace(run, frames=frames)).frames["vis_qz"].isna().sum() == 1
    back = logs.read_log(logs.write_log(dataclasses.replace(run, frames=frames), tmp_path / "a.csv"))
    assert same_bits(back.frames, frames)

    partial = frames.copy()
    partial.loc[6, "vis_qx"] = 0.0
    with pytest.raises(LogFormatError) as info:
        logs.validate_run(dataclasses.replace(run, frames=partial))
    assert str(info.value).startswith("<memory>: frame 6: column 'vis_px' = 'nan': missing while 1 other")

    posed = frames.copy()
    posed.loc[6, "state"] = schema.STATE_OK_KLT
    with pytest.raises(
        LogFormatError, match=r"frame 6: column 'vis_px' = 'nan': no pose in state 5 \(OK_KLT\)"
    ):
        logs.write_log(dataclasses.replace(run, frames=posed), tmp_path / "b.csv")
    assert not (tmp_path / "b.csv").exists()

    infinite = run.frames.copy()
    infinite.loc[3, "vis_vx"] = np.inf
    with pytest.raises(LogFormatError, match="frame 3: column 'vis_vx' = 'inf': NaN or inf is not allowed"):
        logs.validate_run(dataclasses.replace(run, frames=infinite))

    ba2 = run.frames.copy()
    ba2.loc[2, ["imu_init", "imu_ba2"]] = [0, 1]
    with pytest.raises(LogFormatError, match="frame 2: column 'imu_ba2' = '1': requires imu_init = 1"):
        logs.validate_run(dataclasses.replace(run, frames=ba2))

    with pytest.raises(LogFormatError, match="missing columns 'map_id', 'imu_ba2'"):
        logs.validate_run(dataclasses.replace(run, frames=run.frames.drop(columns=list(schema.MAP_COLUMNS))))


@pytest.mark.parametrize(
    "key, value",
    [
        ("rule", "sve-option2"),
        ("rule", {"kind": "inliers", "thresholds": {"imu_init": 15.0, "not_init": 50.0, "reloc": 50.0}}),
        ("switch_model", "imu-coast"),
    ],
)
def test_rule_and_switch_model_metadata_round_trip(tmp_path, key, value):
    run = make_run(N, 1, **{key: value})
    back = logs.read_log(logs.write_log(run, tmp_path / "a.csv"))
    assert back.meta[key] == value


@pytest.mark.parametrize(
    "extra, key, shown, reason",
    [
        ('"rule": 15', "rule", "15", "must be a string or an object, got int"),
        ('"rule": ["orbslam3"]', "rule", '["orbslam3"]', "must be a string or an object, got list"),
        ('"switch_model": {"name": "orbslam3"}', "switch_model", '{"name": "orbslam3"}', "must be a string"),
        ('"switch_model": null', "switch_model", "null", "must be a string, got NoneType"),
    ],
)
def test_rule_and_switch_model_metadata_types(log, extra, key, shown, reason):
    edit_line(log, 1, schema.MAGIC + '{"sequence": "X", "run": 1, "fps": 20, ' + extra + "}")
    expect(log, LogFormatError, 1, column=key, value=shown, reason=reason)


# ---------------------------------------------------------------------------------------------------
# Reading v1 logs: defaults


def v1_run(tmp_path, n=400, seed=6, **kwargs) -> tuple[schema.RunLog, Path]:
    """A v2 run with a pose on every frame, and the v1 file of the same frames."""
    run = make_run(n, seed, **kwargs)
    path = logs.write_log(run, tmp_path / "v1.csv")
    v1_text(path)
    return run, path


@pytest.mark.parametrize("with_gt", [True, False])
def test_v1_log_reads_with_defaults_and_a_warning(tmp_path, with_gt):
    run, path = v1_run(tmp_path, with_gt=with_gt, gt_missing=0.1)
    lines = read_lines(path)
    assert lines[0].startswith("# jsve-log v1 {") and "map_id" not in lines[1]
    with pytest.warns(LogVersionWarning) as record:
        back = logs.read_log(path)
    (w,) = record
    message = str(w.message)
    assert message.startswith(f"{path}: format v1 log read with defaults: ")
    assert "map_id = 0, imu_ba2 = imu_init & (t - t_first >= 15 s)" in message
    assert w.filename == __file__  # attributed to the caller of read_log
    assert list(back.frames.columns) == list(schema.COLUMNS if with_gt else schema.REQUIRED_COLUMNS)
    # Everything v1 has is read as written; the defaults, computed here independently: one map, and
    # BA2 from 15 s (15e9 ns, exact in integers) after the first frame where the IMU is initialised.
    others = [c for c in back.frames.columns if c not in schema.MAP_COLUMNS]
    assert same_bits(back.frames[others], run.frames[others])
    t = [int(x) for x in back.frames["t_ns"]]
    init = back.frames["imu_init"].tolist()
    expected = [int(i == 1 and ti - t[0] >= 15_000_000_000) for ti, i in zip(t, init, strict=True)]
    assert back.frames["imu_ba2"].tolist() == expected
    assert 0 < sum(expected) < sum(init)  # the rule decides both ways on this run
    assert back.frames["map_id"].tolist() == [0] * len(t)
    assert back.frames["map_id"].dtype == back.frames["imu_ba2"].dtype == np.int64


def test_v1_ba2_delay_boundary_is_inclusive(tmp_path):
    run = make_run(320, 1, with_gt=False)
    t = EUROC_T0_NS + np.arange(320, dtype=np.int64) * 50_000_000  # frame 300 is exactly 15 s in
    frames = run.frames.assign(t_ns=t, imu_init=np.ones(320, np.int64), imu_ba2=np.zeros(320, np.int64))
    path = logs.write_log(dataclasses.replace(run, frames=frames), tmp_path / "a.csv")
    v1_text(path)
    with pytest.warns(LogVersionWarning):
        ba2 = logs.read_log(path).frames["imu_ba2"].to_numpy()
    assert schema.V1_BA2_DELAY_S == 15.0
    assert ba2[299] == 0 and ba2[300] == 1 and ba2[:300].sum() == 0 and ba2[300:].all()


def test_v1_defaults_near_the_end_of_int64():
    t = np.array([2**63 - 20_000_000_000, 2**63 - 5_000_000_000, 2**63 - 1], dtype=np.int64)
    d = schema.v1_defaults(t, np.array([1, 1, 0]))
    assert d["imu_ba2"].tolist() == [0, 1, 0] and d["map_id"].tolist() == [0, 0, 0]
    late = np.array([2**63 - 10, 2**63 - 1], dtype=np.int64)  # t_first + 15 s is past int64
    assert schema.v1_defaults(late, np.array([1, 1]))["imu_ba2"].tolist() == [0, 0]


def test_parse_log_of_v1_bytes_warns_too(tmp_path):
    _, path = v1_run(tmp_path, n=N)
    with pytest.warns(LogVersionWarning, match="memory-name: format v1 log read with defaults"):
        logs.parse_log(path.read_bytes(), "memory-name")
    run, version = logs.read_log_version(path)  # the variant for callers that report v1 themselves
    assert version == 1 and run.frames["map_id"].eq(0).all()


def test_v1_log_is_written_back_as_the_current_version(tmp_path):
    _, path = v1_run(tmp_path)
    with pytest.warns(LogVersionWarning):
        run = logs.read_log(path)
    out = logs.write_log(run, tmp_path / "v2.csv")
    assert read_lines(out)[0].startswith("# jsve-log v3 ")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert same_bits(logs.read_log(out).frames, run.frames)


def test_v1_logs_keep_the_v1_rules(tmp_path):
    _, path = v1_run(tmp_path, n=N)
    good = path.read_bytes()
    for c in schema.VIS_COLUMNS:  # no frames without a pose in v1
        set_field(path, 8, c, "")
    set_field(path, 8, "state", "4")
    expect(
        path, LogFormatError, 8, column="vis_px", value="", reason="only gt_* fields may be empty in a v1 log"
    )
    path.write_bytes(good)
    edit_line(path, 2, read_lines(path)[1].replace("imu_init,", "imu_init,map_id,"))
    expect(path, LogFormatError, 2, column="map_id", reason="unexpected column 'map_id'")
    path.write_bytes(good)
    edit_line(path, 2, read_lines(path)[1].replace("n_extracted,n_inliers", "n_inliers,n_extracted"))
    expect(
        path, LogFormatError, 2, column="n_inliers", reason="header position 4 holds 'n_inliers', v1 expects"
    )
    path.write_bytes(good)
    set_field(path, 9, "imu_dt", "-0.05")
    expect(path, LogFormatError, 9, column="imu_dt", value="-0.05", reason="must be >= 0")


# ---------------------------------------------------------------------------------------------------
# Values a computation cannot hold, repeated metadata keys, file containers (issue 12)


@pytest.mark.parametrize(
    "column, text",
    [("vis_px", "1e300"), ("gt_pz", "-3.5e38"), ("imu_dt", "1e39"), ("vis_qw", "4e38")],
)
def test_finite_values_beyond_float32_are_refused(log, column, text):
    # float32 (what `jsve evaluate` computes in) turns these into inf: they would score as if finite.
    set_field(log, 9, column, text)
    expect(log, LogFormatError, 9, column=column, value=text, reason="beyond float32's range")


def test_the_largest_float32_is_accepted(log):
    set_field(log, 9, "vis_vy", repr(schema.FLOAT_MAX))
    set_field(log, 10, "imu_dpx", repr(-schema.FLOAT_MAX))
    frames = logs.read_log(log).frames
    assert frames["vis_vy"][6] == schema.FLOAT_MAX and frames["imu_dpx"][7] == -schema.FLOAT_MAX


@pytest.mark.parametrize("column", ["n_extracted", "n_inliers", "n_frustum"])
def test_counts_beyond_int32_are_refused(log, column):
    # int32 is what LogBatch holds: 2^32 + 1000 would wrap around to 1000 there.
    huge = str(2**32 + 1000)
    set_field(log, 9, column, huge)
    expect(log, LogFormatError, 9, column=column, value=huge, reason=f"must be <= {2**31 - 1}")


def test_a_bin_beyond_uint16_is_refused(log):
    set_field(log, 9, "n_extracted", str(10**6))
    set_field(log, 9, "bin_7", "65536")
    expect(log, LogFormatError, 9, column="bin_7", value="65536", reason="must be <= 65535")


def test_bins_whose_int64_sum_overflows_are_refused(log):
    # Two bins of 2^62 sum to 2^63, which wraps around to -2^63 in int64: the sum check alone passed it.
    set_field(log, 12, "n_extracted", str(2**62))
    set_field(log, 12, "bin_3", str(2**62))
    set_field(log, 12, "bin_4", str(2**62))
    expect(log, LogFormatError, 12, column="n_extracted", value=str(2**62), reason="must be <= 2147483647")
    set_field(log, 12, "n_extracted", "1000")
    expect(log, LogFormatError, 12, column="bin_3", value=str(2**62), reason="must be <= 65535")


def test_in_memory_runs_follow_the_same_range_rules(tmp_path):
    run = make_run(N, 3)
    frames = run.frames.assign(vis_pz=run.frames["vis_pz"].where(run.frames.index != 5, 1e300))
    with pytest.raises(LogFormatError, match=r"frame 5: column 'vis_pz' = '1e\+300': beyond float32"):
        logs.write_log(dataclasses.replace(run, frames=frames), tmp_path / "a.csv")
    assert not (tmp_path / "a.csv").exists()


@pytest.mark.parametrize(
    "meta, key",
    [
        ('{"sequence": "X", "run": 1, "fps": 20, "run": 2}', "run"),  # would change the run id
        ('{"sequence": "X", "run": 1, "fps": 20, "rule": {"kind": "sve", "kind": "inliers"}}', "kind"),
    ],
)
def test_a_repeated_metadata_key_is_refused(log, meta, key):
    edit_line(log, 1, schema.MAGIC + meta)
    err = expect(log, LogFormatError, 1, column=key, reason="appears twice")
    assert str(err).startswith(f"{log}:1: metadata key '{key}': appears twice")


def test_a_utf8_byte_order_mark_is_accepted(log, tmp_path):
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + log.read_bytes())
    back, clean = logs.read_log(bom), logs.read_log(log)
    assert same_bits(back.frames, clean.frames) and back.meta == clean.meta


def test_gzip_logs_read_the_same(log, tmp_path):
    import gzip

    packed = tmp_path / "r7.csv.gz"
    packed.write_bytes(gzip.compress(log.read_bytes()))
    back = logs.read_log(packed)
    assert same_bits(back.frames, logs.read_log(log).frames) and back.source == str(packed)
    # The rules and the line numbers are those of the decompressed text.
    set_field(log, 9, "imu_dt", "nan")
    packed.write_bytes(gzip.compress(log.read_bytes()))
    expect(packed, LogFormatError, 9, column="imu_dt", value="nan")


def test_a_truncated_gzip_log_is_incomplete_and_garbage_is_named(log, tmp_path):
    import gzip

    data = gzip.compress(log.read_bytes())
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(data[: len(data) // 2])
    expect(cut, LogIncompleteError, None, reason="incomplete: its gzip stream ends early")
    bad = tmp_path / "bad.csv.gz"
    bad.write_bytes(data[:10] + b"\x00" * 40)
    expect(bad, LogFormatError, None, reason="not a readable gzip file")


@pytest.mark.parametrize("at", [3, 10, LAST])  # after the header, mid-file, right before the end marker
def test_an_inserted_empty_line_is_named_not_an_incomplete_log(log, at):
    lines = read_lines(log)
    lines.insert(at - 1, "")  # the empty line becomes line `at`
    write_lines(log, lines)
    expect(log, LogFormatError, at, reason="empty line")


def test_an_empty_header_line_is_named(log):
    lines = read_lines(log)
    lines.insert(1, "")
    write_lines(log, lines)
    expect(log, LogFormatError, 2, reason="empty line (line 2 is the header)")


def test_a_bare_carriage_return_inside_a_row_is_named(log):
    # Arrow ends a row at a bare '\r': the message had no line ("cannot parse the rows: ... Row #6").
    lines = read_lines(log)
    lines[7] = lines[7][:40] + "\r" + lines[7][40:]
    write_lines(log, lines)
    expect(log, LogFormatError, 8, reason="a carriage return ('\\r') inside the row")
    lines[7] = "\r" + lines[7].replace("\r", "")  # at the start: Arrow read an extra row of empty fields
    write_lines(log, lines)
    expect(log, LogFormatError, 8, reason="a carriage return")


def test_a_quoted_field_is_not_a_number(log):
    # Fields are never quoted: Arrow's quoting would have read '"1.5"' as 1.5, and let a row span lines.
    set_field(log, 9, "vis_px", '"1.5"')
    expect(log, LogFormatError, 9, column="vis_px", value='"1.5"', reason="not a number")


# ---------------------------------------------------------------------------------------------------
# Fuzzing the reader (issue 12)

_FUZZ_RUN = make_run(6, 11, gt_missing=0.3, no_pose=0.3)
_FUZZ_SOURCE = "fuzz/r1.csv"
_BAD_TOKENS = (
    b"nan", b"NaN", b"inf", b"-inf", b"Infinity", b"1e400", b"-1e39", b"4e38", b"1e300", b"%d" % 2**63,
    b"%d" % 2**40, b"", b" ", b"abc", b"1.2.3", b"0x10", b"1_0", b'"1"', b"1e", b"--1", b"+-1", b"\x00",
    b"\xff", b",", b"\r",
)  # fmt: skip


def _fuzz_bytes() -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        return logs.write_log(_FUZZ_RUN, Path(folder) / "r.csv").read_bytes()


_FUZZ_BYTES = _fuzz_bytes()


_edit_kinds = st.sampled_from(
    ["delete char", "duplicate char", "replace char", "delete line", "duplicate line", "swap lines",
     "replace field", "delete field", "duplicate field", "insert line", "truncate"]
)  # fmt: skip


@st.composite
def _edited_logs(draw) -> bytes:
    """A valid log with 1 to 3 random edits, sometimes gzipped or with a UTF-8 BOM. Lines are drawn
    uniformly (hypothesis's integers lean to 0, which would edit line 1 most of the time)."""
    import gzip

    data = _FUZZ_BYTES
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(_edit_kinds)
        lines = data.split(b"\n")
        i, j = draw(st.sampled_from(range(len(lines)))), draw(st.sampled_from(range(len(lines))))
        line = bytearray(lines[i])
        if kind.endswith("char") and line:
            at = draw(st.integers(0, len(line) - 1))
            if kind == "delete char":
                del line[at]
            elif kind == "duplicate char":
                line.insert(at, line[at])
            else:
                line[at] = draw(st.sampled_from(b'0123456789,.-+eE#\n\r "x\x00\xff{}:'))
            lines[i] = bytes(line)
        elif kind == "delete line":
            del lines[i]
        elif kind == "duplicate line":
            lines.insert(i, lines[i])
        elif kind == "swap lines":
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "insert line":
            lines.insert(
                i, draw(st.sampled_from([b"", b" ", b"#", b"1,2,3", lines[j][: len(lines[j]) // 2]]))
            )
        elif kind.endswith("field"):
            fields = lines[i].split(b",")
            k = draw(st.sampled_from(range(len(fields))))
            if kind == "replace field":
                fields[k] = draw(st.sampled_from(_BAD_TOKENS))
            elif kind == "delete field":
                del fields[k]
            else:
                fields.insert(k, fields[k])
            lines[i] = b",".join(fields)
        data = b"\n".join(lines)
        if kind == "truncate":
            data = data[: draw(st.sampled_from(range(len(data) + 1)))]
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data
    if draw(st.integers(0, 3)) == 0:
        data = gzip.compress(data, mtime=0)
    return data


def _naive_frames(data: bytes) -> pd.DataFrame:
    """The rows of an accepted log read field by field with Python's int() and float(): an oracle that
    shares nothing with the reader but the column names."""
    import gzip

    if data.startswith(b"\x1f\x8b"):
        data = gzip.decompress(data)
    lines = data.removeprefix(b"\xef\xbb\xbf").decode("utf-8").rstrip().split("\n")
    header = lines[1].rstrip("\r").split(",")
    rows = [line.rstrip("\r").split(",") for line in lines[2:-1]]
    columns = {}
    for k, c in enumerate(header):
        if c in schema.INT_COLUMNS:
            columns[c] = np.array([int(r[k]) for r in rows], np.int64)
        else:
            columns[c] = np.array([float(r[k]) if r[k] else np.nan for r in rows], np.float64)
    return pd.DataFrame(columns)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(data=_edited_logs())
def test_fuzzed_logs_read_right_or_fail_with_file_and_line(data):
    """Random edits of a valid log (characters, lines and fields deleted, duplicated or replaced; nan,
    inf, huge and malformed numbers; truncation; gzip; a BOM): the reader either returns frames that are
    exactly what the text says (the original frames when the edit touched no row value) or raises
    LogFormatError naming the file and a line; never another exception, never a misread value."""
    try:
        run = logs.parse_log(data, _FUZZ_SOURCE)
    except LogFormatError as err:
        assert err.path == _FUZZ_SOURCE and str(err).startswith(_FUZZ_SOURCE), str(err)
        container = "gzip" in err.reason  # a cut or corrupt gzip stream has no line
        assert err.line is not None or container, str(err)
        return
    assert same_bits(run.frames, _naive_frames(data)), "accepted, but not what the text says"
    logs.validate_run(run)  # the in-memory rules agree with the file rules
