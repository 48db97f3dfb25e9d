"""Tests of jsve.io._keypoints: keypoint side files (format v1), round trips, every malformed case, joins."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from logfactory import make_run, read_lines, same_bits, write_lines

from jsve.io import _ingest as ingest
from jsve.io import _keypoints as kpio
from jsve.io import _logs as logs
from jsve.io._keypoints import KeypointLog
from jsve.io._logs import LogFormatError, LogIncompleteError

META = {"sequence": "SYN", "run": 3, "image_size": [752, 480], "disturbance": "none", "level": 0}


def make_keypoints(n: int = 30, seed: int = 0, t0: int = 1_403_715_274_312_143_104, **meta) -> KeypointLog:
    """n keypoints over a few frames (stamps t0 + k * 50 ms), with awkward floats in the first rows."""
    rng = np.random.default_rng(seed)
    frame = np.sort(rng.integers(0, 5, size=n))
    x = rng.uniform(0, 752, n)
    awkward = [-0.0, 5e-324, 0.1, 751.99999999999989]  # values a careless writer would not round-trip
    x[: min(n, 4)] = awkward[: min(n, 4)]
    frames = pd.DataFrame(
        {
            "t_ns": t0 + frame * 50_000_000,
            "x": x,
            "y": rng.uniform(0, 480, n),
            "ux": rng.uniform(-5, 757, n),
            "uy": rng.uniform(-5, 485, n),
            "octave": rng.integers(0, 8, n),
            "inlier": rng.integers(0, 2, n),
        }
    )
    return KeypointLog({**META, **meta}, frames)


@pytest.fixture
def kp_file(tmp_path) -> Path:
    """A valid side file of 30 keypoints: keypoint r on line r + 3, the end marker on line 33."""
    return kpio.write_keypoints(make_keypoints(), tmp_path / "r3.keypoints.csv")


def expect(path, exc, line, needle) -> LogFormatError:
    """read_keypoints(path) raises exactly `exc` at `line` (None: no line), its message containing needle."""
    with pytest.raises(LogFormatError) as info:
        kpio.read_keypoints(path)
    err = info.value
    assert type(err) is exc, str(err)
    assert err.line == line, str(err)
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert str(err).startswith(prefix), str(err)
    assert needle in str(err), str(err)
    return err


def set_text(path, line: int, column: str, text: str) -> None:
    lines = read_lines(path)
    fields = lines[line - 1].split(",")
    fields[kpio.COLUMNS.index(column)] = text
    lines[line - 1] = ",".join(fields)
    write_lines(path, lines)


# --------------------------------------------------------------------------------------------------
# Round trips


def test_round_trip_is_bit_exact(tmp_path):
    kp = make_keypoints(200, seed=7)
    path = kpio.write_keypoints(kp, tmp_path / "a.keypoints.csv")
    back = kpio.read_keypoints(path)
    assert back.meta == kp.meta
    assert back.source == str(path)
    assert same_bits(back.keypoints, kp.keypoints)
    lines = read_lines(path)
    assert lines[0].startswith(kpio.MAGIC) and json.loads(lines[0][len(kpio.MAGIC) :]) == kp.meta
    assert lines[1] == ",".join(kpio.COLUMNS)
    assert lines[-1] == f"{kpio.END_MARKER}200"
    assert not list(tmp_path.glob("*.partial"))


def test_a_run_without_keypoints_round_trips(tmp_path):
    empty = make_keypoints(0)
    back = kpio.read_keypoints(kpio.write_keypoints(empty, tmp_path / "e.keypoints.csv"))
    assert len(back.keypoints) == 0 and list(back.keypoints.columns) == list(kpio.COLUMNS)
    assert back.keypoints["t_ns"].dtype == np.int64 and back.keypoints["x"].dtype == np.float64


def test_image_bounds_default_to_the_image(tmp_path):
    assert make_keypoints().image_bounds == (0.0, 752.0, 0.0, 480.0)
    bounded = make_keypoints(image_bounds=[-3.5, 755.25, -2, 482])
    assert bounded.image_bounds == (-3.5, 755.25, -2.0, 482.0)
    back = kpio.read_keypoints(kpio.write_keypoints(bounded, tmp_path / "b.keypoints.csv"))
    assert back.image_bounds == bounded.image_bounds


def test_keypoints_path():
    assert kpio.keypoints_path("runs/r7.csv") == Path("runs/r7.keypoints.csv")
    assert kpio.keypoints_path(Path("/a/b/MH_04-blur-15-7.csv")) == Path("/a/b/MH_04-blur-15-7.keypoints.csv")
    assert kpio.keypoints_path("runs/r7") == Path("runs/r7.keypoints.csv")


def test_directory_searches_skip_side_files(tmp_path):
    run = make_run(10, seed=3)
    logs.write_log(run, tmp_path / "r3.csv")
    kpio.write_keypoints(make_keypoints(), kpio.keypoints_path(tmp_path / "r3.csv"))
    (tmp_path / "r4.keypoints.csv.partial").write_text("half")
    assert ingest.find_logs(tmp_path) == [str(tmp_path / "r3.csv")]
    assert [r.run_id for r in ingest.read_logs(tmp_path, progress=False).runs] == [run.run_id]


# --------------------------------------------------------------------------------------------------
# Malformed files: every message names the file and line


def test_empty_file_is_incomplete(tmp_path):
    path = tmp_path / "x.keypoints.csv"
    path.write_bytes(b"")
    expect(path, LogIncompleteError, 1, "empty file")


def test_partial_name_is_incomplete(tmp_path, kp_file):
    partial = kp_file.with_name(kp_file.name + ".partial")
    kp_file.rename(partial)
    expect(partial, LogIncompleteError, None, "has not finished")


@pytest.mark.parametrize(
    "line1, needle",
    [
        ("t_ns,x,y,ux,uy,octave,inlier", "not a jsve keypoint file"),
        ('# jsve-keypoints v2 {"sequence": "S"}', "unsupported keypoint format version 'v2'"),
        ('# jsve-log v1 {"sequence": "S", "run": 1, "fps": 20}', "not a jsve keypoint file"),
        ('# jsve-keypoints v1 {"sequence": "S", "run": 3', "metadata is not valid JSON"),
        (
            '# jsve-keypoints v1 {"sequence": "S", "image_size": [752, 480]}',
            "metadata key 'run': required key",
        ),
        ('# jsve-keypoints v1 {"sequence": "S", "run": "3", "image_size": [752, 480]}', "must be an integer"),
        ('# jsve-keypoints v1 {"sequence": "S", "run": 3, "image_size": [752]}', "'image_size'"),
        ('# jsve-keypoints v1 {"sequence": "S", "run": 3, "image_size": [0, 480]}', "[width, height]"),
        (
            '# jsve-keypoints v1 {"sequence": "S", "run": 3, "image_size": [752, 480], '
            '"image_bounds": [5, 1, 0, 480]}',
            "min < max",
        ),
        ('# jsve-keypoints v1 {"sequence": "S", "run": 3, "image_size": [752, 480], "level": NaN}', "finite"),
    ],
)
def test_bad_metadata_line(kp_file, line1, needle):
    lines = read_lines(kp_file)
    lines[0] = line1
    write_lines(kp_file, lines)
    expect(kp_file, LogFormatError, 1, needle)


def test_bad_header(kp_file):
    lines = read_lines(kp_file)
    lines[1] = "t_ns,x,y,octave,ux,uy,inlier"
    write_lines(kp_file, lines)
    err = expect(kp_file, LogFormatError, 2, "wrong header")
    assert err.column == "octave"


def test_missing_end_marker_is_incomplete(kp_file):
    lines = read_lines(kp_file)
    write_lines(kp_file, lines[:-3])  # the writer died after keypoint 28
    expect(kp_file, LogIncompleteError, 30, "without the end marker")


def test_count_that_disagrees_is_incomplete(kp_file):
    lines = read_lines(kp_file)
    del lines[10]
    write_lines(kp_file, lines)
    expect(kp_file, LogIncompleteError, 32, "says 30 keypoints but the file has 29 rows")


@pytest.mark.parametrize(
    "line, column, text, needle",
    [
        (9, "x", "abc", "column 'x' = 'abc': not a number"),
        (12, "octave", "1.5", "column 'octave' = '1.5': not an integer"),
        (14, "t_ns", "99999999999999999999", "out of the int64 range"),
        (15, "uy", "", "column 'uy' = '': empty value"),
        (7, "y", "nan", "column 'y' = 'nan': NaN or inf is not allowed"),
        (8, "ux", "-inf", "NaN or inf is not allowed"),
        (20, "octave", "-1", "column 'octave' = '-1': must be >= 0"),
        (21, "inlier", "2", "column 'inlier' = '2': must be 0 or 1"),
        (25, "t_ns", "1403715274312143104", "t_ns must not decrease"),
    ],
)
def test_bad_field(kp_file, line, column, text, needle):
    set_text(kp_file, line, column, text)
    err = expect(kp_file, LogFormatError, line, needle)
    assert err.column == column


def test_first_of_several_defects_is_reported(kp_file):
    set_text(kp_file, 20, "inlier", "5")
    set_text(kp_file, 11, "octave", "-2")
    expect(kp_file, LogFormatError, 11, "'octave' = '-2'")


@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda fields: fields[:5], "column 'octave': missing: the row has 5 of 7 fields (truncated row)"),
        (lambda fields: fields + ["1"], "too many fields: the row has 8, expected 7"),
        (lambda fields: [""], "empty line"),
    ],
)
def test_wrong_number_of_fields(kp_file, edit, needle):
    lines = read_lines(kp_file)
    lines[16] = ",".join(edit(lines[16].split(",")))
    write_lines(kp_file, lines)
    expect(kp_file, LogFormatError, 17, needle)


def test_writer_refuses_invalid_keypoints_and_leaves_nothing(tmp_path):
    kp = make_keypoints()
    kp.keypoints.loc[12, "inlier"] = 3
    with pytest.raises(
        LogFormatError, match=r"<memory>: column 'inlier' = '3': must be 0 or 1 \(keypoint row 12\)"
    ):
        kpio.write_keypoints(kp, tmp_path / "bad.keypoints.csv")
    assert list(tmp_path.iterdir()) == []
    wrong = KeypointLog(META, make_keypoints().keypoints.drop(columns="ux"))
    with pytest.raises(LogFormatError, match="missing \\['ux'\\]"):
        kpio.validate_keypoints(wrong)


# --------------------------------------------------------------------------------------------------
# Joining keypoints with their log


def test_frame_of_keypoints_and_unknown_stamps(kp_file):
    kp = kpio.read_keypoints(kp_file)
    t0 = int(kp.keypoints["t_ns"].iloc[0])
    frames = t0 + np.arange(6, dtype=np.int64) * 50_000_000
    expected = (kp.keypoints["t_ns"].to_numpy() - t0) // 50_000_000
    np.testing.assert_array_equal(kpio.frame_of_keypoints(kp, frames), expected)
    # A log lacking the frame of keypoint 17 (line 20): the message points at that keypoint's line.
    missing = int(kp.keypoints["t_ns"].iloc[17])
    first = int(np.argmax(kp.keypoints["t_ns"].to_numpy() == missing))
    with pytest.raises(LogFormatError) as info:
        kpio.frame_of_keypoints(kp, frames[frames != missing], "logs/r3.csv")
    assert str(info.value).startswith(
        f"{kp_file}:{first + 3}: column 't_ns' = '{missing}': no frame of logs/r3.csv"
    )


def test_side_file_of_another_run_is_refused():
    run = make_run(5, seed=3, image_size=[752, 480])
    kpio.check_matches_log(make_keypoints(sequence="SYN", run=3), run)
    with pytest.raises(LogFormatError, match="metadata key 'run' = '4': does not match the log's run 3"):
        kpio.check_matches_log(make_keypoints(run=4), run)
    with pytest.raises(LogFormatError, match="'level' = '15': does not match the log's level 0"):
        kpio.check_matches_log(make_keypoints(level=15), run)
    with pytest.raises(LogFormatError, match="image_size"):
        kpio.check_matches_log(make_keypoints(image_size=[1241, 376]), run)
