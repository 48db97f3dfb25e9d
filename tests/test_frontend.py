"""jsve.frontend: the C++ writer jsve_log.hpp, compiled and read back by jsve.io._logs.

The C++ programs live in tests/cpp/. They are compiled with the system compiler; without one the
compiled tests skip, saying so. Every log is read with jsve.io._logs.read_log, the strict reader.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsve.frontend
from jsve.cli import SUBCOMMANDS
from jsve.cli import frontend_include as cli_frontend_include
from jsve.io import LogFormatError, LogIncompleteError
from jsve.io import _schema as schema
from jsve.io._ingest import read_logs
from jsve.io._logs import read_log

CPP = Path(__file__).resolve().parent / "cpp"
CXX = shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
needs_cxx = pytest.mark.skipif(
    CXX is None, reason="no C++ compiler (g++, c++ or clang++) on PATH; the compiled tests need one"
)
STRICT = ["-Wall", "-Wextra", "-pedantic", "-Werror"]
VARIANTS = {"to_chars": [], "snprintf": ["-DJSVE_LOG_USE_SNPRINTF"]}
"""The two float formatters of the header: std::to_chars, and the snprintf("%.17g") fallback."""

N_FRAMES = 60
TWO53 = 2**53


# --------------------------------------------------------------------------------------------------
# Locating the header (no compiler needed)


def test_get_include_is_the_directory_of_the_header():
    include = Path(jsve.frontend.get_include())
    assert include.is_absolute()
    assert (include / "jsve_log.hpp").is_file()
    assert Path(jsve.frontend.header_path()) == include / "jsve_log.hpp"
    assert "#ifndef JSVE_LOG_HPP" in (include / "jsve_log.hpp").read_text()


def test_python_m_jsve_frontend_prints_the_include_directory():
    done = subprocess.run(
        [sys.executable, "-m", "jsve.frontend", "--include"], capture_output=True, text=True, check=True
    )
    assert done.stdout == jsve.frontend.get_include() + "\n"
    done = subprocess.run(
        [sys.executable, "-m", "jsve.frontend", "--header"], capture_output=True, text=True, check=True
    )
    assert done.stdout == jsve.frontend.header_path() + "\n"
    done = subprocess.run([sys.executable, "-m", "jsve.frontend"], capture_output=True, text=True)
    assert done.returncode == 2  # one of --include / --header is required


def test_cli_subcommand_prints_the_include_directory(capsys):
    assert "frontend-include" in SUBCOMMANDS
    parser = argparse.ArgumentParser(prog="jsve")
    cli_frontend_include.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["frontend-include"])
    assert args.func(args) == 0
    assert capsys.readouterr().out == jsve.frontend.get_include() + "\n"


def test_jsve_main_dispatches_frontend_include(capsys):
    missing = [n for n in SUBCOMMANDS if importlib.util.find_spec(f"jsve.cli.{n.replace('-', '_')}") is None]
    if missing:
        pytest.skip(f"subcommand modules not written yet: {missing}")
    from jsve.cli import main

    assert main(["frontend-include"]) == 0
    assert capsys.readouterr().out == jsve.frontend.get_include() + "\n"


# --------------------------------------------------------------------------------------------------
# Building the C++ programs


@pytest.fixture(scope="session")
def build(tmp_path_factory):
    """build(source, variant) -> executable, compiled once per session with the strict flags."""
    if CXX is None:
        pytest.skip("no C++ compiler (g++, c++ or clang++) on PATH")
    out_dir = tmp_path_factory.mktemp("cpp")
    built: dict[tuple[str, str], Path] = {}

    def _build(source: str, variant: str = "to_chars") -> Path:
        key = (source, variant)
        if key not in built:
            exe = out_dir / f"{Path(source).stem}_{variant}"
            cmd = [CXX, "-std=c++17", *STRICT, "-O1", *VARIANTS[variant]]
            cmd += [f"-I{jsve.frontend.get_include()}", str(CPP / source), "-o", str(exe)]
            done = subprocess.run(cmd, capture_output=True, text=True)
            assert done.returncode == 0, f"{' '.join(cmd)}\n{done.stderr}"
            built[key] = exe
        return built[key]

    return _build


def compile_strictly(source: Path, out: Path, standard: str, variant: str) -> subprocess.CompletedProcess:
    """Compile a C++ test source to an object file with STRICT plus the stricter warnings users may
    have (-Wshadow, -Wconversion, ...), at `standard`, with VARIANTS[variant]'s defines."""
    extra = ["-Wshadow", "-Wconversion", "-Wsign-conversion", "-Wold-style-cast", "-Wdouble-promotion"]
    cmd = [CXX, f"-std={standard}", *STRICT, *extra, "-O2", *VARIANTS[variant]]
    cmd += [f"-I{jsve.frontend.get_include()}", "-c", str(source), "-o", str(out)]
    return subprocess.run(cmd, capture_output=True, text=True)


@needs_cxx
@pytest.mark.parametrize("standard", ["c++17", "c++20"])
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_header_compiles_warning_free(tmp_path, variant, standard):
    """-Wall -Wextra -pedantic -Werror at -std=c++17 (and c++20), plus stricter flags users may have."""
    done = compile_strictly(CPP / "header_only.cpp", tmp_path / "h.o", standard, variant)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""


# --------------------------------------------------------------------------------------------------
# Round trip of a synthetic run


EXPECTED_META = {
    "sequence": 'MH_04 "quoted" \\ back\nline\ttab ü 漢字 \x01\x7f/end',
    "run": 7,
    "fps": 20,
    "disturbance": "blur",
    "level": 2.5,
    "sensor": "imu_monocular",
    "n_features": 1000,
    "image_size": [752, 480],
    "grid": [8, 8],
    "gravity": [0.0, 0.0, -9.81],
    "frontend": "jsve write_synthetic (test)",
    "seed": 2**40 + 3,
    "rule": "sve-option2",
    "switch_model": "orbslam3",
    "neg_zero": -0.0,
    "tiny": 5e-324,
    "big": 2**63 - 1,
    "most_negative": -(2**63),
    "awkward": [0.1, 1e-300, -0.0, 1.7976931348623157e308],
}
"""The metadata write_synthetic.cpp sets ('sequence' and 'run' are set twice: values replaced in place)."""

SPECIAL = [0.1, 1e-300, -0.0, 0.0, 5e-324, -2.5e-310, 3.4028234663852886e38, -3.4028234663852886e38,
           2.2250738585072014e-308, 9007199254740992.0, 1 / 3, 1e22, 1e23, 0.30000000000000004,
           123456789.123456789, -1.0, 1.0]  # fmt: skip
"""kSpecial of write_synthetic.cpp, as Python parses the same literals."""


def _parse_expected(path: Path, gt: bool, world: bool = False):
    """The sidecar of write_synthetic: ints and the bits of every double it wrote, and raw grids."""
    floats = list(schema.FLOAT_COLUMNS) + (list(schema.GT_COLUMNS) if gt else [])
    floats += list(schema.WORLD_COLUMNS) if world else []
    ints, bits, grids = [], [], {}
    for line in path.read_text().splitlines():
        kind, *fields = line.split()
        if kind == "G":
            grids[int(fields[0])] = np.array(fields[1:], dtype=np.int64).reshape(64, 48)
            continue
        n_int = len(schema.INT_COLUMNS)
        ints.append([int(x) for x in fields[:n_int]])
        # '-' marks a frame without ground truth: the reader gives NaN there.
        bits.append([None if x == "-" else int(x, 16) for x in fields[n_int:]])
        assert len(bits[-1]) == len(floats)
    return np.array(ints, dtype=np.int64), bits, floats, grids


def _run_synthetic(build, tmp_path, variant, *args, env=None, name="run.csv"):
    exe = build("write_synthetic.cpp", variant)
    log, expected = tmp_path / name, tmp_path / (name + ".expected")
    done = subprocess.run(
        [str(exe), str(log), str(N_FRAMES), "--expected", str(expected), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return log, expected, done.stderr


def _assert_bitwise(run, expected: Path, gt: bool, world: bool = False):
    ints, bits, float_names, grids = _parse_expected(expected, gt, world)
    frames = run.frames
    assert len(frames) == N_FRAMES == len(ints)
    assert list(frames.columns) == list(schema.column_order(schema.FORMAT_VERSION, gt, world))
    for k, c in enumerate(schema.INT_COLUMNS):
        assert frames[c].dtype == np.int64
        np.testing.assert_array_equal(frames[c].to_numpy(), ints[:, k], err_msg=c)
    got = frames[float_names].to_numpy(dtype=np.float64)
    for i, row in enumerate(bits):
        for k, b in enumerate(row):
            if b is None:
                assert np.isnan(got[i, k]), (i, float_names[k])
            else:
                # Bitwise: -0.0 vs 0.0 and every last-digit difference count.
                assert got[i, k : k + 1].view(np.uint64)[0] == b, (i, float_names[k], got[i, k], hex(b))
    # fill_bins_from_grid agrees with an independent binning of the raw grid (bin x = col // 8,
    # bin y = row // 6, k = 8 * y + x).
    assert grids, "the sidecar holds raw grids for the first frames"
    bins = frames[list(schema.BIN_COLUMNS)].to_numpy()
    for i, grid in grids.items():
        by_bin = grid.reshape(8, 8, 8, 6).sum(axis=(1, 3))  # [bin x, bin y]
        np.testing.assert_array_equal(bins[i], by_bin.T.reshape(64))
        assert grid.sum() > 0


def _assert_meta(meta):
    assert meta == EXPECTED_META
    assert list(meta) == list(EXPECTED_META)  # insertion order, replaced keys keep their place
    assert type(meta["run"]) is int and type(meta["fps"]) is int and type(meta["level"]) is float
    assert np.signbit(meta["neg_zero"]) and np.signbit(meta["awkward"][2])
    assert meta["tiny"] == 5e-324 and meta["tiny"] > 0.0


def _assert_independent_values(frames):
    """Values fixed by write_synthetic's formulas, checked without the sidecar."""
    i = np.arange(N_FRAMES)
    state = i % 7 - 1
    has_pose = np.isin(state, [2, 3, 5]) | (i % 2 == 1)
    assert 0 < (~has_pose).sum() < N_FRAMES
    np.testing.assert_array_equal(frames[list(schema.VIS_COLUMNS)].isna().all(axis=1), ~has_pose)
    np.testing.assert_array_equal(frames[list(schema.VIS_COLUMNS)].isna().any(axis=1), ~has_pose)
    np.testing.assert_array_equal(frames["map_id"], np.where(i < 20, 0, np.where(i < 40, 3, 2**40)))
    np.testing.assert_array_equal(frames["imu_ba2"], ((i % 3 == 0) & (i >= 30)).astype(np.int64))
    t = frames["t_ns"].to_numpy()
    assert t[0] == TWO53 + 1 and t[1] == TWO53 + 2  # not representable as doubles
    expected_t = 1403636579763555584 + (np.arange(2, N_FRAMES) - 2) * 50_000_000 + np.arange(2, N_FRAMES) % 7
    np.testing.assert_array_equal(t[2:], expected_t)
    vis_px = frames["vis_px"].to_numpy()
    special = np.array([SPECIAL[i % len(SPECIAL)] for i in range(N_FRAMES)])
    assert vis_px[has_pose].view(np.uint64).tolist() == special[has_pose].view(np.uint64).tolist()
    assert has_pose[19] and has_pose[20]  # SPECIAL[2] = -0.0 and SPECIAL[3] = 0.0
    assert np.signbit(vis_px[19]) and vis_px[19] == 0.0 and not np.signbit(vis_px[20])
    np.testing.assert_array_equal(frames["state"].to_numpy(), np.arange(N_FRAMES) % 7 - 1)
    np.testing.assert_array_equal(
        frames["imu_init"].to_numpy(), (np.arange(N_FRAMES) % 3 == 0).astype(np.int64)
    )


@needs_cxx
@pytest.mark.parametrize(
    ("gt", "world"),
    [(False, False), (True, False), (False, True), (True, True)],
    ids=["no_gt", "gt", "world", "gt_world"],
)
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_round_trip_is_exact(build, tmp_path, variant, gt, world):
    args = (["--gt"] if gt else []) + (["--world"] if world else [])
    log, expected, _ = _run_synthetic(build, tmp_path, variant, *args)
    assert not Path(str(log) + ".partial").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a v2 log: no version warning
        run = read_log(log)
    assert run.source == str(log)
    assert run.has_ground_truth == gt
    assert run.has_world_frame == world
    _assert_meta(run.meta)
    _assert_bitwise(run, expected, gt, world)
    _assert_independent_values(run.frames)
    if world:
        _assert_world_values(run.frames)
    if gt:  # every fifth frame (i % 5 == 3) was written without ground truth
        missing = np.isnan(run.frames[list(schema.GT_COLUMNS)].to_numpy())
        np.testing.assert_array_equal(missing.all(axis=1), np.arange(N_FRAMES) % 5 == 3)
        assert missing.any(axis=1).sum() == missing.all(axis=1).sum()
    lines = log.read_bytes().split(b"\n")
    assert lines[-1] == b"" and lines[-2] == f"{schema.END_MARKER}{N_FRAMES}".encode()
    assert lines[0].startswith(b"# jsve-log v3 {")
    assert lines[1].startswith(b"t_ns,state,imu_init,map_id,imu_ba2,n_extracted,")
    assert lines[1] == ",".join(schema.column_order(schema.FORMAT_VERSION, gt, world)).encode()
    # Frame 0 (state -1) has no pose: ten empty fields after the bins.
    fields = lines[2].split(b",")
    k = len(schema.INT_COLUMNS)
    assert fields[k : k + 10] == [b""] * 10 and fields[k + 10] == b"0.0"  # then imu_dt


def _assert_world_values(frames):
    """The world_* of write_synthetic --world: the identity on frames 0..9, then a similarity that changes
    every 7 frames, on every frame (with or without a pose)."""
    world = frames[list(schema.WORLD_COLUMNS)].to_numpy()
    assert not np.isnan(world).any()
    np.testing.assert_array_equal(world[:10], np.tile([1.0, 0, 0, 0, 0, 0, 0, 1.0], (10, 1)))
    changed = np.flatnonzero((world[1:] != world[:-1]).any(axis=1)) + 1
    np.testing.assert_array_equal(changed, np.arange(10, N_FRAMES, 7))
    scales = frames[schema.WORLD_SCALE].to_numpy()
    assert (scales > 0).all()
    assert (
        scales[10] == 5e-324 and scales[17] == schema.FLOAT_MAX and scales[24] == 1 / 3 and scales[31] == 0.1
    )
    norms = np.linalg.norm(frames[list(schema.WORLD_QUATERNION)].to_numpy(), axis=1)
    assert np.abs(norms - 1).max() <= schema.UNIT_QUATERNION_TOLERANCE


@needs_cxx
def test_world_columns_are_last_and_need_the_option(build, tmp_path):
    """Options::world_frame decides the eight world_* columns once per log: after gt_*, or after imu_dqz."""
    for args, tail in [
        ([], b",imu_dqz"),
        (["--gt"], b",gt_qz"),
        (["--world"], b",imu_dqz," + ",".join(schema.WORLD_COLUMNS).encode()),
        (["--gt", "--world"], b",gt_qz," + ",".join(schema.WORLD_COLUMNS).encode()),
    ]:
        log, _, _ = _run_synthetic(build, tmp_path, "to_chars", *args, name="_".join(["h", *args]) + ".csv")
        header = log.read_bytes().split(b"\n")[1]
        assert header.endswith(tail), (args, header[-120:])
        rows = log.read_bytes().split(b"\n")[2:-2]
        assert all(row.count(b",") == header.count(b",") for row in rows)


@needs_cxx
def test_both_formatters_write_numbers_that_read_back_the_same(build, tmp_path):
    """to_chars (shortest) and snprintf (%.17g) write different text for the same doubles."""
    a, _, _ = _run_synthetic(build, tmp_path, "to_chars", name="a.csv")
    b, _, _ = _run_synthetic(build, tmp_path, "snprintf", name="b.csv")
    assert a.read_bytes() != b.read_bytes()
    fa, fb = read_log(a).frames, read_log(b).frames
    assert fa.to_numpy().view(np.uint64).tolist() == fb.to_numpy().view(np.uint64).tolist()


@pytest.fixture(scope="session")
def comma_locale(tmp_path_factory):
    """(env, name) of a locale whose decimal separator is a comma, built with localedef."""
    localedef = shutil.which("localedef")
    if localedef is None:
        pytest.skip("localedef not available: cannot build a locale with a decimal comma")
    root = tmp_path_factory.mktemp("locales")
    subprocess.run([localedef, "-i", "de_DE", "-f", "UTF-8", str(root / "de_DE.UTF-8")], capture_output=True)
    if not (root / "de_DE.UTF-8").exists():
        pytest.skip("localedef could not build de_DE.UTF-8 (locale sources missing)")
    return {**os.environ, "LOCPATH": str(root)}, "de_DE.UTF-8"


@needs_cxx
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_round_trip_is_exact_under_a_decimal_comma_locale(build, tmp_path, variant, comma_locale):
    env, name = comma_locale
    log, expected, stderr = _run_synthetic(
        build, tmp_path, variant, "--gt", "--world", "--locale", name, env=env
    )
    assert "decimal_point=," in stderr  # the program really ran with a decimal comma
    run = read_log(log)
    _assert_meta(run.meta)
    _assert_bitwise(run, expected, gt=True, world=True)


# --------------------------------------------------------------------------------------------------
# Runs that do not finish


def _start_and_wait_ready(cmd, timeout=30.0):
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + timeout
    line = b""
    while time.monotonic() < deadline and not line.endswith(b"\n"):
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            chunk = os.read(proc.stdout.fileno(), 64)
            if not chunk:
                break
            line += chunk
    if line != b"READY\n":
        proc.kill()
        proc.wait()
        pytest.fail(f"writer did not signal READY: {line!r} {proc.stderr.read()!r}")
    return proc


@needs_cxx
@pytest.mark.parametrize("flush", [1, 100], ids=["flush_every_frame", "flush_every_100"])
def test_killed_run_leaves_no_log_that_reads_as_complete(build, tmp_path, flush):
    exe = build("write_synthetic.cpp")
    log = tmp_path / "killed.csv"
    partial = Path(str(log) + ".partial")
    proc = _start_and_wait_ready([str(exe), str(log), "1000", "--kill-after", "7", "--flush", str(flush)])
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    proc.stdout.close()
    proc.stderr.close()

    assert not log.exists()
    assert partial.exists()
    lines = partial.read_bytes().split(b"\n")
    # Flushed every frame: line 1, the header and 7 frames reached the file; every 100: only 2 lines.
    assert len(lines) - 1 == (2 + 7 if flush == 1 else 2)
    assert lines[0].startswith(schema.MAGIC.encode())

    with pytest.raises(LogIncompleteError, match="incomplete"):
        read_log(partial)
    # Renamed by hand, the content itself still reads as incomplete (no end marker).
    renamed = tmp_path / "renamed.csv"
    shutil.copyfile(partial, renamed)
    with pytest.raises(LogIncompleteError, match="incomplete") as info:
        read_log(renamed)
    assert str(renamed) in str(info.value)
    # A directory read never takes it for a run.
    result = read_logs(tmp_path, on_error="quarantine", workers=1, progress=False)
    assert result.runs == []
    assert len(result.quarantined) == 2
    assert all(q.incomplete for q in result.quarantined)


@needs_cxx
def test_writer_destroyed_without_close_leaves_a_partial_log(build, tmp_path):
    exe = build("write_synthetic.cpp")
    log = tmp_path / "unclosed.csv"
    subprocess.run([str(exe), str(log), "5", "--no-close"], check=True, capture_output=True, timeout=60)
    assert not log.exists()
    partial = Path(str(log) + ".partial")
    assert len(partial.read_bytes().split(b"\n")) - 1 == 2 + 5  # the destructor flushed every frame
    with pytest.raises(LogIncompleteError, match="incomplete"):
        read_log(partial)


# --------------------------------------------------------------------------------------------------
# Error policy


@needs_cxx
def test_error_policy(build, tmp_path):
    exe = build("check_policy.cpp")
    done = subprocess.run([str(exe), str(tmp_path)], capture_output=True, text=True, timeout=60)
    lines = done.stdout.splitlines()
    failures = [line for line in lines if line.startswith("FAIL")]
    assert done.returncode == 0 and not failures, "\n".join(failures) + done.stderr
    passed = {line.split()[1] for line in lines if line.startswith("PASS")}
    assert len(passed) == 62, sorted(passed)
    assert {"nan_position", "repeated_stamp", "throw_policy", "no_frames", "flush_every"} <= passed
    assert {
        "negative_map_id",
        "imu_ba2_without_imu_init",
        "no_pose_in_state_2",
        "no_pose_in_state_3",
    } <= passed
    assert {"no_pose_in_state_5", "frame_without_pose", "meta_rule_int", "meta_switch_model_list"} <= passed
    assert {
        "world_non_unit_quaternion",
        "world_scale_zero",
        "world_scale_negative",
        "world_scale_negative_zero",
        "world_scale_nan",
        "world_translation_nan",
        "world_translation_inf_without_pose",
        "world_translation_beyond_float32",
        "world_quaternion_nan",
        "world_fields_ignored_without_world_frame",
        "world_frame_columns",
        "meta_camera_in_body_scalar",
        "meta_camera_in_body_six",
        "meta_camera_in_body_non_unit",
        "meta_camera_in_body_beyond_float32",
    } <= passed

    # What the writer left on disk is what the reader says it is.
    partials = sorted(tmp_path.glob("*.partial"))
    finished = sorted(tmp_path.glob("*.csv"))
    assert len(partials) == 30 and len(finished) == 11
    for p in partials:
        with pytest.raises(LogIncompleteError, match="incomplete"):
            read_log(p)
    for p in finished:
        run = read_log(p)
        t_bc = [0.5, 0.5, -0.5, 0.5, 0.1, -0.02, 0.003] if p.name == "world.csv" else None
        assert run.meta == {
            "sequence": "V1_01",
            "run": 3,
            "fps": 20.0,
            **({"camera_in_body": t_bc} if t_bc else {}),
        }
        assert run.has_world_frame == (p.name == "world.csv")
    # world_frame: written on every frame, also without a pose or ground truth.
    world = read_log(tmp_path / "world.csv").frames
    assert world[list(schema.WORLD_COLUMNS)].to_numpy().tolist() == [
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        [0.0, 1.0, 0.0, 0.0, 1.5, -2.0, 0.25, 3.0],
    ]
    assert world.loc[1, list(schema.VIS_COLUMNS + schema.GT_COLUMNS)].isna().all()
    gap = read_log(tmp_path / "gt_gap.csv").frames
    assert not np.isnan(gap.loc[0, list(schema.GT_COLUMNS)].to_numpy(dtype=float)).any()
    assert np.isnan(gap.loc[1, list(schema.GT_COLUMNS)].to_numpy(dtype=float)).all()
    # A frame without a pose reads as NaN in all ten vis_* (its NaN and non-unit values were not
    # written); the map columns are as set.
    no_pose = read_log(tmp_path / "no_pose.csv").frames
    assert no_pose[list(schema.VIS_COLUMNS)].notna().all(axis=1).tolist() == [True, False]
    assert no_pose.loc[1, list(schema.VIS_COLUMNS)].isna().all()
    assert no_pose[["state", "imu_init", "map_id", "imu_ba2"]].to_numpy().tolist() == [
        [2, 1, 7, 1],
        [4, 0, 8, 0],
    ]
    # The partial of a rejected frame holds the frames before it, never the rejected one.
    rejected = (tmp_path / "nan_position.csv.partial").read_text().splitlines()
    assert len(rejected) == 2 + 2 and rejected[-1].startswith("2000,")


@needs_cxx
def test_a_frame_the_writer_rejects_is_one_the_reader_rejects(build, tmp_path):
    """The writer's rules mirror the reader's: a log patched to contain the rejected value fails to read."""
    log, _, _ = _run_synthetic(build, tmp_path, "to_chars")
    text = log.read_text(encoding="utf-8").splitlines(keepends=True)
    columns = text[1].rstrip("\n").split(",")

    def patched(column, value, line=5):
        fields = text[line - 1].rstrip("\n").split(",")
        fields[columns.index(column)] = value
        out = tmp_path / f"patched_{column}.csv"
        out.write_text("".join(text[: line - 1] + [",".join(fields) + "\n"] + text[line:]), encoding="utf-8")
        return out

    # Line 5 is frame 2: state 1, imu_init 0, without a pose; line 6 is frame 3: state 2, with one.
    cases = [
        ("imu_dt", "-1e-9", 5),
        ("state", "6", 5),
        ("n_frustum", "-1", 5),
        ("map_id", "-1", 5),
        ("imu_ba2", "1", 5),
        ("vis_px", "nan", 6),
        ("vis_qy", "", 6),
    ]
    for column, value, line in cases:
        with pytest.raises(LogFormatError, match=f"{column}") as info:
            read_log(patched(column, value, line))
        assert f":{line}:" in str(info.value)
        assert not isinstance(info.value, LogIncompleteError)
    # The state of a pose-less frame set to OK: the reader wants the pose the writer refuses to omit.
    with pytest.raises(LogFormatError, match=r":5: column 'vis_px' = '': no pose in state 2 \(OK\)"):
        read_log(patched("state", "2", 5))


@needs_cxx
def test_a_world_frame_the_writer_rejects_is_one_the_reader_rejects(build, tmp_path):
    """world_* values the writer refuses (check_policy.cpp) fail to read when patched into a log."""
    log, _, _ = _run_synthetic(build, tmp_path, "to_chars", "--world")
    read_log(log)
    text = log.read_text(encoding="utf-8").splitlines(keepends=True)
    columns = text[1].rstrip("\n").split(",")

    def patched(changes, line):
        fields = text[line - 1].rstrip("\n").split(",")
        for column, value in changes.items():
            fields[columns.index(column)] = value
        out = tmp_path / f"patched_{'_'.join(changes)}.csv"
        out.write_text("".join(text[: line - 1] + [",".join(fields) + "\n"] + text[line:]), encoding="utf-8")
        return out

    # Line 5 is frame 2, without a pose: its world_* are written and read all the same.
    cases = [
        ({"world_s": "0.0"}, "world_s"),
        ({"world_s": "-1.0"}, "world_s"),
        ({"world_qw": "0.5"}, "world_q"),
        ({"world_ty": "nan"}, "world_ty"),
        ({"world_tz": ""}, "world_tz"),
        ({"world_tx": "1e39"}, "world_tx"),
    ]
    for changes, column in cases:
        with pytest.raises(LogFormatError, match=column) as info:
            read_log(patched(changes, 5))
        assert ":5:" in str(info.value)
        assert not isinstance(info.value, LogIncompleteError)


# --------------------------------------------------------------------------------------------------
# Benchmark script


@needs_cxx
@pytest.mark.slow
def test_benchmark_script_reports_microseconds_per_frame(tmp_path):
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_frontend_writer.py"
    out = tmp_path / "bench.json"
    subprocess.run(
        [sys.executable, str(script), "--frames", "2000", "--repeats", "2", "--json", str(out)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    results = json.loads(out.read_text())
    assert set(results["variants"]) == {"to_chars", "snprintf"}
    for r in results["variants"].values():
        assert r["frames"] == 2000 and len(r["us_per_frame"]) == 2
        assert 0 < r["min_us_per_frame"] <= r["median_us_per_frame"]
        assert 400 < r["bytes_per_frame"] < 900  # ~98 fields of EuRoC-like magnitudes
    assert results["variants"]["to_chars"]["fp_to_chars"] is True
    assert results["variants"]["snprintf"]["fp_to_chars"] is False
