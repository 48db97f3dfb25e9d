"""Tests of jsve.io._logs: format v1 round trips, every malformed case, batch reading, Parquet, ground truth."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import pickle
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from logfactory import edit_line, get_field, make_run, read_lines, set_field, write_lines
from scipy.spatial.transform import Rotation, Slerp

from jsve.cli import ingest as ingest_cli
from jsve.io import _groundtruth as groundtruth
from jsve.io import _ingest as ingest
from jsve.io import _logs as logs
from jsve.io import _schema as schema
from jsve.io._logs import LogFormatError, LogIncompleteError

N = 20  # frames of the small logs below; frame i is on line i + 3, the end marker on line N + 3
LAST = N + 3


def same_bits(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Same columns, dtypes and bit patterns (so NaN == NaN and -0.0 != 0.0)."""
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return False
    return all(
        a[c].dtype == b[c].dtype
        and np.array_equal(a[c].to_numpy().view(np.int64), b[c].to_numpy().view(np.int64))
        for c in a.columns
    )


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
    run = make_run(
        400, seed, with_gt=with_gt, gt_missing=0.25, awkward_floats=True, sequence="MH_04", level=15
    )
    path = logs.write_log(run, tmp_path / "a.csv")
    back = logs.read_log(path)
    assert same_bits(back.frames, run.frames)
    assert back.meta == run.meta
    assert back.source == str(path)
    assert isinstance(back.frames.index, pd.RangeIndex)
    lines = read_lines(path)
    assert lines[0] == schema.MAGIC + json.dumps(run.meta)
    assert lines[1] == ",".join(schema.COLUMNS if with_gt else schema.REQUIRED_COLUMNS)
    assert lines[-1] == f"{schema.END_MARKER}400"
    assert len(lines) == 403
    assert not (tmp_path / "a.csv.partial").exists()


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
    values=st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=6, max_size=6),
    steps=st.lists(st.integers(0, 2**20), min_size=5, max_size=5),
)
def test_any_finite_double_and_int64_round_trips(values, steps, tmp_path_factory):
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

    monkeypatch.setattr(logs.pacsv, "write_csv", die)
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
    expect(log, LogFormatError, 1, reason="not a jsve v1 log: line 1 must start with '# jsve-log v1 '")


def test_missing_magic_line(log):
    edit_line(log, 1, None)  # the file now starts with the header
    expect(log, LogFormatError, 1, reason="found 't_ns,state,imu_init,")


def test_other_format_version(log):
    edit_line(log, 1, '# jsve-log v2 {"sequence": "X", "run": 1, "fps": 20}')
    expect(log, LogFormatError, 1, reason="unsupported format version 'v2'")


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
        reason="wrong column order: header position 4 holds 'n_inliers', v1 expects 'n_extracted'",
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
    expect(
        log, LogFormatError, 7, column=schema.COLUMNS[-3], reason="row has 95 of 98 fields (truncated row)"
    )


def test_too_many_fields(log):
    lines = read_lines(log)
    lines[8] += ",1.0"
    write_lines(log, lines)
    expect(log, LogFormatError, 9, reason="too many fields: the row has 99, v1 expects 98")


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


@pytest.mark.parametrize("column", ["vis_px", "n_frustum", "t_ns"])
def test_empty_value_outside_gt(log, column):
    set_field(log, 6, column, "")
    expect(log, LogFormatError, 6, column=column, value="", reason="only gt_* fields may be empty")


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
    for line, column, text, reason in [
        (2900, "n_inliers", "x", "not an integer"),
        (2950, "vis_px", "1.2.3", "not a number"),
        (2999, "imu_dt", "-1", "must be >= 0"),
    ]:
        path.write_bytes(good)
        set_field(path, line, column, text)
        expect(path, LogFormatError, line, column=column, value=text, reason=reason)
    path.write_bytes(good)
    lines = read_lines(path)
    lines[2700] = ",".join(lines[2700].split(",")[:50])
    write_lines(path, lines)
    expect(path, LogFormatError, 2701, column=schema.COLUMNS[50], reason="truncated row")


def test_errors_pickle_with_their_attributes(log):
    set_field(log, 12, "imu_dt", "-0.05")
    with pytest.raises(LogFormatError) as info:
        logs.read_log(log)
    back = pickle.loads(pickle.dumps(info.value))
    assert type(back) is LogFormatError and str(back) == str(info.value)
    assert (back.path, back.line, back.column, back.value, back.reason) == (
        str(log),
        12,
        "imu_dt",
        "-0.05",
        info.value.reason,
    )
    inc = pickle.loads(pickle.dumps(LogIncompleteError("a.csv", 3, "the log is incomplete")))
    assert type(inc) is LogIncompleteError and inc.line == 3


# ---------------------------------------------------------------------------------------------------
# Many logs


@pytest.fixture
def logdir(tmp_path) -> tuple[Path, list[str], list[str]]:
    """18 good logs in three folders and four broken ones: (dir, good paths, bad paths), sorted."""
    root = tmp_path / "logs"
    good = [
        logs.write_log(
            make_run(30 + i, i, with_gt=i % 3 != 0, sequence="MH_04"), root / f"d{i % 3}" / f"r{i:02d}.csv"
        )
        for i in range(18)
    ]
    bad = []
    p = logs.write_log(make_run(30, 100, sequence="MH_04"), root / "d0" / "r50.csv")
    set_field(p, 9, "imu_dt", "-0.05")
    bad.append(p)
    p = logs.write_log(make_run(30, 101, sequence="MH_04"), root / "d1" / "r51.csv")
    edit_line(p, 33, None)  # end marker gone
    bad.append(p)
    p = logs.write_log(make_run(30, 102, sequence="MH_04"), root / "d2" / "r52.csv")
    bad.append(p.rename(p.with_name("r52.csv.partial")))
    p = root / "notes.csv"
    p.write_text("a,b\n1,2\n")
    bad.append(p)
    (root / "README.txt").write_text("not a log, not read")
    return root, sorted(map(str, good)), sorted(map(str, bad))


def test_quarantine_lists_exactly_the_broken_logs(logdir):
    root, good, bad = logdir
    result = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == good
    assert [q.path for q in result.quarantined] == bad
    by_path = {q.path: q for q in result.quarantined}
    assert by_path[bad[0]].line == 9 and by_path[bad[0]].column == "imu_dt"
    assert [by_path[p].incomplete for p in bad] == [False, True, True, False]
    report = result.report()
    assert list(report.columns) == list(ingest.QUARANTINE_COLUMNS)
    assert report["path"].tolist() == bad
    assert report["message"].tolist() == [q.message for q in result.quarantined]


def test_quarantine_report_csv(logdir, tmp_path):
    root, _, bad = logdir
    result = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    path = ingest.write_quarantine_report(result, tmp_path / "q.csv")
    back = pd.read_csv(path)
    assert back["path"].tolist() == bad
    assert back["message"].tolist() == result.report()["message"].tolist()


def test_raise_stops_at_the_first_bad_log_in_sorted_order(logdir):
    root, _, bad = logdir
    for workers in (1, 2):
        with pytest.raises(LogFormatError) as info:
            ingest.read_logs(root, workers=workers, progress=False)
        assert info.value.path == bad[0]
        assert info.value.line == 9


def test_parallel_read_equals_serial_read(logdir):
    root, good, _ = logdir
    serial = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    parallel = ingest.read_logs(root, on_error="quarantine", workers=2, progress=False)
    assert same_runs(serial.runs, parallel.runs)
    assert serial.quarantined == parallel.quarantined
    assert len(parallel.runs) == len(good)


def test_sources_glob_list_and_file(logdir):
    root, good, _ = logdir
    by_glob = ingest.read_logs(str(root / "d1" / "r*.csv"), on_error="quarantine", workers=1, progress=False)
    in_d1 = [p for p in good if "/d1/" in p]
    assert [r.source for r in by_glob.runs] == in_d1 and len(by_glob.quarantined) == 1
    by_list = ingest.read_logs(list(reversed(in_d1)), workers=1, progress=False)
    assert [r.source for r in by_list.runs] == in_d1
    assert ingest.find_logs(good[0]) == [good[0]]
    with pytest.raises(FileNotFoundError):
        ingest.find_logs(root / "nothing-here")
    with pytest.raises(FileNotFoundError):
        ingest.find_logs(str(root / "*.nope"))


def test_duplicate_run_ids_name_both_files(tmp_path):
    a = logs.write_log(make_run(N, 1, sequence="V101"), tmp_path / "a.csv")
    b = logs.write_log(make_run(N, 1, sequence="V101"), tmp_path / "b.csv")
    with pytest.raises(LogFormatError) as info:
        ingest.read_logs(tmp_path, workers=1, progress=False)
    assert info.value.path == str(b) and str(a) in str(info.value)
    assert "duplicate run id: 'V101/none-0/1'" in str(info.value)
    result = ingest.read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == [str(a)]
    assert [q.path for q in result.quarantined] == [str(b)]


def test_unreadable_paths_are_quarantined_not_lost(tmp_path):
    good = logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    gone = tmp_path / "gone.csv"
    result = ingest.read_logs([good, gone], on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in result.runs] == [str(good)]
    (q,) = result.quarantined
    assert q.path == str(gone) and "cannot read the file" in q.message
    empty = ingest.ReadResult(runs=result.runs).report()
    assert list(empty.columns) == list(ingest.QUARANTINE_COLUMNS) and len(empty) == 0


def test_progress_bar_goes_to_stderr(tmp_path, capsys):
    for i in range(3):
        logs.write_log(make_run(N, i), tmp_path / f"r{i}.csv")
    ingest.read_logs(tmp_path, workers=1, progress=True)
    captured = capsys.readouterr()
    assert captured.out == "" and "3/3" in captured.err
    ingest.read_logs(tmp_path, workers=1, progress=False)
    assert capsys.readouterr().err == ""


def test_on_error_is_checked(logdir):
    with pytest.raises(ValueError, match="on_error"):
        ingest.read_logs(logdir[0], on_error="skip", progress=False)


# ---------------------------------------------------------------------------------------------------
# Parquet


def test_ingest_and_read_parquet_round_trip(logdir, tmp_path):
    root, good, bad = logdir
    out = tmp_path / "study.parquet"
    summary = ingest.ingest(root, out, on_error="quarantine", workers=2, progress=False)
    expected = ingest.read_logs(root, on_error="quarantine", workers=1, progress=False)
    assert summary.n_runs == len(good) and summary.n_frames == sum(len(r.frames) for r in expected.runs)
    assert [q.path for q in summary.quarantined] == bad
    assert summary.quarantine_report == tmp_path / "study.quarantine.csv"
    assert pd.read_csv(summary.quarantine_report)["path"].tolist() == bad
    assert same_runs(ingest.read_parquet(out), expected.runs)
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())

    pf = pq.ParquetFile(out)
    assert pf.schema_arrow.names[:2] == ["run_id", "frame"]
    assert pf.schema_arrow.names[2:] == list(schema.COLUMNS)
    assert str(pf.schema_arrow.field("frame").type) == "int32"
    assert str(pf.schema_arrow.field("run_id").type).startswith("dictionary<values=string")
    entries = json.loads(pf.metadata.metadata[b"jsve.runs"])
    assert [e["run_id"] for e in entries] == [r.run_id for r in expected.runs]
    assert [e["meta"] for e in entries] == [r.meta for r in expected.runs]
    table = pq.read_table(out, columns=["run_id", "frame", "t_ns"])
    first = expected.runs[0]
    assert table.column("run_id")[0].as_py() == first.run_id
    assert table.column("t_ns").to_numpy()[: len(first.frames)].tolist() == first.frames["t_ns"].tolist()


def test_ingest_raise_writes_nothing(logdir, tmp_path):
    out = tmp_path / "study.parquet"
    with pytest.raises(LogFormatError):
        ingest.ingest(logdir[0], out, workers=1, progress=False)
    assert list(tmp_path.iterdir()) == [logdir[0]]


def test_ingest_without_bad_logs_writes_no_report(tmp_path):
    for i in range(3):
        logs.write_log(make_run(N, i), tmp_path / "logs" / f"r{i}.csv")
    out = tmp_path / "out" / "s.parquet"
    stale = out.with_suffix(".quarantine.csv")
    stale.parent.mkdir()
    stale.write_text("path\nold.csv\n")
    summary = ingest.ingest(tmp_path / "logs", out, on_error="quarantine", workers=1, progress=False)
    assert summary.quarantine_report is None and summary.n_runs == 3
    assert not stale.exists()  # a report from an earlier ingest would describe other logs


def test_read_parquet_rejects_other_parquet(tmp_path):
    path = tmp_path / "x.parquet"
    pd.DataFrame({"a": [1, 2]}).to_parquet(path)
    with pytest.raises(LogFormatError, match="not a jsve Parquet file"):
        ingest.read_parquet(path)


# ---------------------------------------------------------------------------------------------------
# Ground truth


def euroc_gt(shared_data) -> tuple[Path, np.ndarray, np.ndarray]:
    """V101 left-camera ground truth: (path, int64 ns stamps, [n, 7] p xyz + q wxyz), parsed with numpy."""
    path = shared_data / "euroc" / "groundtruth_left_cam" / "V101_GT.txt"
    text = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    stamps = np.array([int(line.split(",")[0].split(".")[0]) for line in text], dtype=np.int64)
    values = np.array([[float(v) for v in line.split(",")[1:8]] for line in text])
    return path, stamps, values


def with_stamps(t_ns: np.ndarray, seed: int = 0, **meta) -> schema.RunLog:
    run = make_run(len(t_ns), seed, with_gt=False, **meta)
    return dataclasses.replace(run, frames=run.frames.assign(t_ns=np.asarray(t_ns, dtype=np.int64)))


def test_euroc_exact_stamps_take_the_file_values(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    run = with_stamps(stamps[100:400])
    out = groundtruth.associate_ground_truth(run, path, "euroc")
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    # Positions are the file's doubles; quaternions are normalised (the file has ~10 digits).
    np.testing.assert_allclose(gt[:, :3], values[100:400, :3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(gt[:, 3:], values[100:400, 3:], rtol=0, atol=1e-9)
    assert out.meta["gt_missing_frames"] == 0 and out.meta["gt_source"] == str(path)
    assert same_bits(out.frames[list(schema.REQUIRED_COLUMNS)], run.frames)
    logs.validate_run(out)  # a valid v1 run, ready to write


def test_euroc_interpolation_midpoints(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    k = np.arange(200, 500)
    t = stamps[k] + (stamps[k + 1] - stamps[k]) // 2  # half a period later
    out = groundtruth.associate_ground_truth(with_stamps(t), path)
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    alpha = (t - stamps[k]) / (stamps[k + 1] - stamps[k])
    assert np.allclose(alpha, 0.5, atol=1e-8)
    p = values[k, :3] + alpha[:, None] * (values[k + 1, :3] - values[k, :3])
    np.testing.assert_allclose(gt[:, :3], p, rtol=0, atol=1e-9)
    # Oracle: scipy's Slerp (xyzw), between the two neighbouring samples.
    for i in range(0, len(k), 37):
        key = Rotation.from_quat(values[[k[i], k[i] + 1]][:, [4, 5, 6, 3]])
        q = Slerp([0.0, 1.0], key)([alpha[i]]).as_quat()[0][[3, 0, 1, 2]]
        assert min(np.abs(gt[i, 3:] - q).max(), np.abs(gt[i, 3:] + q).max()) < 1e-9


def test_int64_stamps_resolve_nanoseconds(shared_data):
    # 100 ns after a sample: evo's float seconds (spacing ~240 ns at 1.4e9 s) cannot tell it apart.
    path, stamps, values = euroc_gt(shared_data)
    t = stamps[300:310] + 100
    gt = groundtruth.associate_ground_truth(with_stamps(t), path).frames[list(schema.GT_POSITION)].to_numpy()
    alpha = 100 / (stamps[301:311] - stamps[300:310])
    expected = values[300:310, :3] + alpha[:, None] * (values[301:311, :3] - values[300:310, :3])
    np.testing.assert_allclose(gt, expected, rtol=0, atol=1e-12)
    assert not np.allclose(gt, values[300:310, :3], rtol=0, atol=1e-12)


def test_frames_outside_the_span_are_counted_and_warned(shared_data, caplog):
    path, stamps, values = euroc_gt(shared_data)
    t = np.concatenate([stamps[0] - np.array([3, 2, 1]) * 50_000_000, stamps[:50], stamps[-1] + [1, 2]])
    with caplog.at_level(logging.WARNING, logger="jsve.io._logs"):
        out = groundtruth.associate_ground_truth(with_stamps(t), path)
    missing = out.frames["gt_px"].isna().to_numpy()
    assert missing.tolist() == [True] * 3 + [False] * 50 + [True] * 2
    assert out.frames.loc[missing, list(schema.GT_COLUMNS)].isna().all(axis=None)
    assert out.meta["gt_missing_frames"] == 5
    assert any("5 of 55 frames have no ground truth" in r.getMessage() for r in caplog.records)


def test_gaps_wider_than_max_gap_are_not_interpolated(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    t = np.sort(np.concatenate([stamps[10:20], stamps[10:19] + 25_000_000]))
    out = groundtruth.associate_ground_truth(with_stamps(t), path, max_gap_ns=40_000_000)  # samples are 50 ms apart
    missing = out.frames["gt_px"].isna().to_numpy()
    assert np.array_equal(missing, ~np.isin(t, stamps))
    assert out.meta["gt_missing_frames"] == 9


def test_nearest_sample_without_interpolation(shared_data):
    path, stamps, values = euroc_gt(shared_data)
    t = np.concatenate([stamps[40:45] + 10_000_000, stamps[45:50] + 40_000_000])
    out = groundtruth.associate_ground_truth(with_stamps(t), path, interpolate=False)
    np.testing.assert_array_equal(
        out.frames[list(schema.GT_POSITION)].to_numpy(),
        np.concatenate([values[40:45, :3], values[46:51, :3]]),
    )


def test_tum_equals_euroc(shared_data, tmp_path):
    path, stamps, values = euroc_gt(shared_data)
    tum = tmp_path / "gt.tum"
    lines = [
        f"{t // 10**9}.{t % 10**9:09d} " + " ".join(repr(float(v)) for v in (*row[:3], *row[4:], row[3]))
        for t, row in zip(stamps[:300], values[:300], strict=True)
    ]
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    run = with_stamps(np.concatenate([stamps[5:100], stamps[100:200] + 12_345_678]))
    a = groundtruth.associate_ground_truth(run, path, "euroc")
    b = groundtruth.associate_ground_truth(run, tum, "tum")
    assert same_bits(a.frames, b.frames)


def test_kitti_by_frame_index(shared_data):
    path = shared_data / "kitti" / "odometry_poses" / "04.txt"
    poses = np.loadtxt(path).reshape(-1, 3, 4)
    n = len(poses) + 3
    out = groundtruth.associate_ground_truth(with_stamps(np.arange(n) * 100_000_000), path, "kitti")
    gt = out.frames[list(schema.GT_COLUMNS)].to_numpy()
    np.testing.assert_array_equal(gt[: len(poses), :3], poses[:, :, 3])
    rot = Rotation.from_quat(gt[: len(poses), [4, 5, 6, 3]]).as_matrix()
    # KITTI stores 7 significant digits, so its matrices are orthonormal to ~1e-6.
    np.testing.assert_allclose(rot, poses[:, :, :3], atol=5e-6)
    assert np.isnan(gt[len(poses) :]).all() and out.meta["gt_missing_frames"] == 3


def test_kitti_with_times_file(shared_data):
    path = shared_data / "kitti" / "odometry_poses" / "00.txt"
    times = shared_data / "kitti" / "times_00.txt"
    t_ns = np.array([round(float(s) * 1e9) for s in times.read_text().split()], dtype=np.int64)
    poses = np.loadtxt(path).reshape(-1, 3, 4)
    run = with_stamps(np.concatenate([t_ns[10:20], (t_ns[20:30] + t_ns[21:31]) // 2]))
    out = groundtruth.associate_ground_truth(run, path, "kitti", kitti_times=times)
    p = out.frames[list(schema.GT_POSITION)].to_numpy()
    np.testing.assert_array_equal(p[:10], poses[10:20, :, 3])
    np.testing.assert_allclose(p[10:], (poses[20:30, :, 3] + poses[21:31, :, 3]) / 2, atol=1e-6)


def test_ground_truth_when_reading(shared_data, tmp_path):
    path, stamps, _ = euroc_gt(shared_data)
    plain = logs.write_log(with_stamps(stamps[:40], 1, sequence="V101"), tmp_path / "a.csv")
    own = make_run(40, 2, sequence="V101")
    logs.write_log(own, tmp_path / "b.csv")
    spec = {"V101": groundtruth.GroundTruth(path, "euroc")}
    result = ingest.read_logs(tmp_path, ground_truth=spec, workers=1, progress=False)
    a, b = result.runs
    assert a.has_ground_truth and a.meta["gt_missing_frames"] == 0
    assert same_bits(b.frames, own.frames)  # a log's own ground truth is kept
    single = logs.read_log(plain, ground_truth=path)
    assert same_bits(single.frames, a.frames)


def test_ground_truth_arguments_are_checked(shared_data):
    with pytest.raises(ValueError, match="fmt"):
        groundtruth.GroundTruth("x.txt", "csv")
    with pytest.raises(ValueError, match="kitti_times"):
        groundtruth.GroundTruth("x.txt", "euroc", kitti_times="t.txt")
    with pytest.raises(FileNotFoundError):
        groundtruth.associate_ground_truth(make_run(5, 0), shared_data / "no-such-file.txt")


# ---------------------------------------------------------------------------------------------------
# CLI


def cli(argv: list[str]) -> int:
    """`jsve ingest ...` through the subcommand's own parser (the other subcommands are not needed)."""
    parser = argparse.ArgumentParser(prog="jsve")
    ingest_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_ingest(logdir, tmp_path, capsys):
    root, good, bad = logdir
    out = tmp_path / "s.parquet"
    assert cli(["ingest", str(root), "-o", str(out), "--workers", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{bad[0]}:9: column 'imu_dt' = '-0.05': must be >= 0" in err and not out.exists()

    report = tmp_path / "bad.csv"
    argv = [
        "ingest",
        str(root),
        "-o",
        str(out),
        "--on-error",
        "quarantine",
        "--quarantine-report",
        str(report),
    ]
    assert cli([*argv, "--workers", "1", "--no-progress"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.search(rf"ingested {len(good)} runs, \d+ frames -> .*; quarantined {len(bad)}", line)
    assert len(ingest.read_parquet(out)) == len(good) and pd.read_csv(report)["path"].tolist() == bad


def test_cli_ingest_with_ground_truth(shared_data, tmp_path, capsys):
    path, stamps, _ = euroc_gt(shared_data)
    logs.write_log(with_stamps(stamps[:30], 1, sequence="V101"), tmp_path / "logs" / "a.csv")
    out = tmp_path / "s.parquet"
    argv = ["ingest", str(tmp_path / "logs"), "-o", str(out), "--gt", str(path), "--gt-format", "euroc"]
    assert cli([*argv, "--no-progress"]) == 0
    (run,) = ingest.read_parquet(out)
    assert run.has_ground_truth and run.meta["gt_missing_frames"] == 0


def test_cli_usage_errors(tmp_path):
    with pytest.raises(SystemExit):
        cli(["ingest", str(tmp_path), "-o", "x.parquet", "--quarantine-report", "q.csv"])
    with pytest.raises(SystemExit):
        cli(["ingest", str(tmp_path), "-o", "x.parquet", "--gt", "a.txt", "--kitti-times", "t.txt"])


def test_cli_is_registered_with_the_dispatcher():
    from jsve import cli as jsve_cli

    assert "ingest" in jsve_cli.SUBCOMMANDS
    try:
        parser = jsve_cli.build_parser()
    except ImportError as e:  # another subcommand's module is not written yet
        pytest.skip(f"jsve CLI dispatcher cannot import every subcommand yet: {e}")
    args = parser.parse_args(["ingest", "logs", "-o", "out.parquet"])
    assert args.func is ingest_cli.run and args.on_error == "raise"


def test_no_logs_is_an_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError):
        ingest.ingest(tmp_path / "empty", tmp_path / "s.parquet", progress=False)
    assert cli(["ingest", str(tmp_path / "empty"), "-o", str(tmp_path / "s.parquet"), "--no-progress"]) == 2


def test_partial_files_are_never_skipped(tmp_path):
    logs.write_log(make_run(N, 1), tmp_path / "a.csv")
    os.rename(logs.write_log(make_run(N, 2), tmp_path / "b.csv"), tmp_path / "b.csv.partial")
    result = ingest.read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert [q.path for q in result.quarantined] == [str(tmp_path / "b.csv.partial")]
    assert result.quarantined[0].incomplete and "incomplete" in result.quarantined[0].message
