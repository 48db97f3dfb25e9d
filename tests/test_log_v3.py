"""Format v3: the keyframe columns and trailers, written by the C++ header and by jsve, read back; and
ORB-SLAM3's saved trajectory rebuilt from a trailer (synthetic keyframes, 4x4 matrices as the oracle:
the real front-end's own files are the oracle in test_real_frontend.py)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from test_frontend import build, needs_cxx  # noqa: F401 - the session fixture that compiles tests/cpp

from jsve.io import LogFormatError
from jsve.io import _schema as schema
from jsve.io._logs import parse_log, read_log, write_log
from jsve.io._saved_trajectory import event_counts, saved_map_id, saved_trajectory
from jsve.io._schema import RunLog

# --------------------------------------------------------------------------------------------------
# The C++ writer


@needs_cxx
def test_header_writes_the_keyframe_columns_and_a_trailer_that_jsve_reads_back(build, tmp_path):  # noqa: F811
    exe = build("write_keyframes.cpp")
    log = tmp_path / "kf.csv"
    done = subprocess.run([str(exe), str(log)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    run = read_log(log)
    assert log.read_text().startswith("# jsve-log v3 ")
    assert list(run.frames.columns) == list(schema.column_order(3, False, False, True))
    f = run.frames
    np.testing.assert_array_equal(f["events"], [1, 2, 4, 8, 16, 0])
    np.testing.assert_array_equal(f["ref_kf"], [10, 11, 12, -1, 14, 15])
    np.testing.assert_array_equal(f["traj"], [1, 0, 1, 0, 1, 0])
    assert f.loc[3, list(schema.REL_COLUMNS)].isna().all()  # no keyframe: rel_* empty
    k = np.array([0, 1, 2, 4, 5])
    np.testing.assert_array_equal(f.loc[k, "rel_px"], k)
    np.testing.assert_allclose(f.loc[k, "rel_qz"], np.sin(0.1 * k), rtol=0, atol=0)
    assert run.trailers == {"demo": {"x": [1, 2]}}
    refused = dict(line.split(" ", 1) for line in done.stdout.splitlines())
    assert refused == {
        "traj_without_ref": "value out of range",
        "unknown_event": "value out of range",
        "rel_not_unit": "value out of range",
        "frame_after_trailer": "value out of range",
        "bad_trailer_key": "value out of range",
        "multiline_trailer": "value out of range",
    }


@needs_cxx
def test_a_log_continued_in_a_forked_child_keeps_the_rows_before_the_fork(build, tmp_path):  # noqa: F811
    exe = build("write_branch.cpp")
    parent, child = tmp_path / "parent.csv", tmp_path / "branch.csv"  # one length: no allocation
    done = subprocess.run([str(exe), str(parent), str(child)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["exists file exists", "length I/O error", "child 0"]
    a, b = read_log(parent).frames, read_log(child).frames
    np.testing.assert_array_equal(a["n_inliers"], [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(b["n_inliers"], [0, 1, 2, 103, 104, 105])
    head = parent.read_text().splitlines()[:5]  # magic, header, the three rows before the fork
    assert child.read_text().splitlines()[:5] == head
    assert not Path(f"{parent}.partial").exists() and not Path(f"{child}.partial").exists()


# --------------------------------------------------------------------------------------------------
# jsve's writer and reader


def _v3_run(n: int = 5, trailers: dict | None = None) -> RunLog:
    frames = {c: np.zeros(n, np.int64) for c in schema.INT_COLUMNS}
    frames["t_ns"] = np.arange(n, dtype=np.int64) * 50_000_000 + 10**18
    frames["state"] = np.full(n, 2)
    frames["n_extracted"] = np.full(n, 100)
    for c in schema.FLOAT_COLUMNS:
        frames[c] = np.zeros(n)
    for c in ("vis_qw", "imu_dqw"):
        frames[c] = np.ones(n)
    frames["events"] = np.resize([0, 4, 0, 16, 32], n)
    frames["traj"] = np.resize([1, 1, 0, 1, 0], n)
    frames["ref_kf"] = np.resize([0, 0, -1, 1, 2], n)
    for c in schema.REL_COLUMNS:
        value = 1.0 if c == "rel_qw" else 0.0 if c in schema.REL_QUATERNION else 0.25
        frames[c] = np.where(frames["ref_kf"] >= 0, value, np.nan)
    df = pd.DataFrame(frames)[list(schema.column_order(3, False, False, True))]
    return RunLog({"sequence": "S", "run": 0, "fps": 20}, df, "<v3>", trailers)


def test_write_log_and_read_log_round_trip_keyframe_columns_and_trailers(tmp_path):
    run = _v3_run(trailers={"orbslam3": {"maps": {"id": [0], "keyframes": [3]}}, "note": [1.5, None]})
    path = write_log(run, tmp_path / "r.csv")
    back = read_log(path)
    pd.testing.assert_frame_equal(back.frames, run.frames)
    assert back.trailers == run.trailers
    assert event_counts(back) == {**dict.fromkeys(schema.EVENTS, 0), "new_map": 1, "loop": 1, "imu_init": 1}


def _text(run: RunLog, tmp_path) -> str:
    return write_log(run, tmp_path / "r.csv").read_text()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("\n1000000000050000000,", "\n1000000000050000000,", 1), None),
        (lambda t: t.replace(",1,0,0.25,", ",1,-1,0.25,", 1), "traj"),
        (lambda t: t.replace(",0,1,0,0.25,", ",512,1,0,0.25,", 1), "events"),
        (lambda t: t.replace(",-1,,,,,,,", ",-1,0.25,,,,,,", 1), "rel_px"),
        (lambda t: t.replace("# jsve-log v3 ", "# jsve-log v2 ", 1), "keyframe columns are format v3"),
        (lambda t: t.replace("# jsve-log end", '# jsve-log trailer x {"a":\n# jsve-log end'), "not JSON"),
        (lambda t: t.replace("# jsve-log end", "# jsve-log trailer x 1\n# jsve-log trailer x 2\n# jsve-log end"),  # noqa: E501
         "more than once"),
    ],
)  # fmt: skip
def test_the_reader_names_the_line_of_a_bad_keyframe_field_or_trailer(tmp_path, edit, message):
    text = edit(_text(_v3_run(), tmp_path))
    if message is None:  # the unedited text reads
        assert parse_log(text.encode(), "x.csv").frames["ref_kf"].tolist() == [0, 0, -1, 1, 2]
        return
    with pytest.raises(LogFormatError, match=message) as error:
        parse_log(text.encode(), "x.csv")
    assert str(error.value).startswith("x.csv:")


# --------------------------------------------------------------------------------------------------
# The saved trajectory of a trailer


def _matrix(q_wxyz, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.roll(q_wxyz, -1)).as_matrix()
    m[:3, 3] = t
    return m


def _seven(m: np.ndarray) -> list[float]:
    q = np.roll(Rotation.from_matrix(m[:3, :3]).as_quat(), 1)
    return [*q, *m[:3, 3]]


def _random_pose(rng) -> np.ndarray:
    return _matrix(np.roll(Rotation.random(random_state=rng).as_quat(), 1), rng.normal(size=3))


def test_saved_trajectory_follows_save_trajectory_euroc_on_synthetic_keyframes():
    """Keyframes 0-2 in map 0, 3-5 in map 1 (the bigger: saved), keyframe 4 culled (bad, parent 3); the
    oracle poses each frame as T_b0^-1 T_wb from 4x4 matrices, independently of jsve's composition."""
    rng = np.random.default_rng(7)
    t_bc = _random_pose(rng)
    t_cw = {k: _random_pose(rng) for k in range(6)}
    t_cp4 = _random_pose(rng)  # keyframe 4's pose relative to its parent when it was culled
    maps = {0: [0, 1, 2], 1: [3, 4, 5]}
    refs = [0, 3, 4, 5, 1, 5, 3]  # entry k's reference keyframe
    lost = [0, 0, 0, 0, 0, 1, 0]
    rows = [1, 2, 4, 5, 6, 8, 9]
    t_cr = [_random_pose(rng) for _ in refs]
    keyframes = {
        "id": list(range(6)), "map_id": [0, 0, 0, 1, 1, 1], "bad": [0, 0, 0, 0, 1, 0],
        "parent": [-1, 0, 1, -1, 3, 3], "t_cw": [_seven(t_cw[k]) for k in range(6)],
        "t_cp": [_seven(t_cp4 if k == 4 else np.eye(4)) for k in range(6)],
    }  # fmt: skip
    trailer = {
        "t_bc": _seven(t_bc),
        "maps": {"id": [0, 1], "keyframes": [3, 4]},
        "keyframes": keyframes,
        "trajectory": {"row": rows, "ref_kf": refs, "lost": lost, "t_cr": [_seven(m) for m in t_cr]},
    }
    run = _v3_run(10, trailers={"orbslam3": json.loads(json.dumps(trailer))})
    saved = saved_trajectory(run)
    assert saved is not None and saved.saved_map == 1
    t_wb0 = np.linalg.inv(t_cw[3]) @ np.linalg.inv(t_bc)  # the saved map's lowest keyframe, as a body
    expected, kept = [], []
    for k, (row, ref) in enumerate(zip(rows, refs, strict=True)):
        if lost[k] or ref not in maps[1]:
            continue
        t_rw = (t_cp4 @ t_cw[3]) if ref == 4 else t_cw[ref]  # the culled keyframe: its parent's pose
        t_wb = np.linalg.inv(t_bc @ t_cr[k] @ t_rw)
        expected.append(np.linalg.inv(t_wb0) @ t_wb)
        kept.append(row)
    np.testing.assert_array_equal(saved.rows, kept)
    got = np.stack([_matrix(p[:4], p[4:]) for p in saved.pose])
    np.testing.assert_allclose(got, np.stack(expected), atol=1e-12)
    world = np.stack([_matrix(p[:4], p[4:]) for p in saved.world_pose])
    np.testing.assert_allclose(world, t_wb0 @ np.stack(expected), atol=1e-12)
    assert saved.coverage == len(kept) / 10


def test_the_saved_map_is_the_first_with_most_keyframes_and_none_without_keyframes():
    assert saved_map_id({"id": [2, 0, 1], "keyframes": [5, 5, 3]}) == 0
    assert saved_map_id({"id": [0, 1], "keyframes": [0, 0]}) is None


def test_a_log_without_the_trailer_cannot_give_a_saved_trajectory():
    with pytest.raises(LogFormatError, match="no 'orbslam3' trailer"):
        saved_trajectory(_v3_run())


def test_the_headers_event_bits_are_the_schemas():
    """jsve_log.hpp's jsve::Event and schema.EVENTS name the same bits (the writer and the reader share
    one schema): kEventResetAll is "reset_all", 1u << 1, and so on."""
    import re

    import jsve.frontend

    text = Path(jsve.frontend.header_path()).read_text()
    found = {
        re.sub(r"(?<!^)([A-Z])", r"_\1", name).lower(): 1 << int(shift)
        for name, shift in re.findall(r"kEvent(\w+) = 1u << (\d+),", text)
    }
    assert found == schema.EVENTS
    assert f"kEventMask = (1u << {len(schema.EVENTS)}) - 1" in text


@pytest.mark.parametrize(
    ("broken", "message"),
    [
        (lambda t: t.pop("maps"), "'maps' must be an object with id, keyframes"),
        (lambda t: t["keyframes"]["bad"].pop(), "'keyframes' columns differ in length"),
        (lambda t: t.update(t_bc=[1.0, 0.0]), "'t_bc' must be 7 numbers"),
        (lambda t: t["trajectory"].update(t_cr=[[1.0, 0.0, 0.0]]), "'trajectory.t_cr' must hold poses of 7"),
    ],
)
def test_a_malformed_trailer_is_refused_naming_the_log_and_field(broken, message):
    trailer = {
        "t_bc": [1.0, 0, 0, 0, 0, 0, 0],
        "maps": {"id": [0], "keyframes": [1]},
        "keyframes": {"id": [0], "map_id": [0], "bad": [0], "parent": [-1], "t_cw": [[1.0, 0, 0, 0, 0, 0, 0]],
                      "t_cp": [[1.0, 0, 0, 0, 0, 0, 0]]},
        "trajectory": {"row": [0], "ref_kf": [0], "lost": [0], "t_cr": [[1.0, 0, 0, 0, 0, 0, 0]]},
    }  # fmt: skip
    assert saved_trajectory(_v3_run(trailers={"orbslam3": json.loads(json.dumps(trailer))})) is not None
    broken(trailer)
    with pytest.raises(LogFormatError, match=message) as error:
        saved_trajectory(_v3_run(trailers={"orbslam3": trailer}))
    assert str(error.value).startswith("<v3>")
