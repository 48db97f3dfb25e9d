"""`jsve ape` and `jsve rpe` as an evo user meets them: evo's option spellings, the alignment line, every
statistic equal to evo_ape / evo_rpe (evo.main_ape.ape, evo.main_rpe.rpe: what those commands run) on
KITTI files (KITTI 00's first KITTI_POSES poses; tests/test_pose_error.py checks the library against evo on
all 4541) and on TUM files with stamps, the figure files, and result files that evo's loader and evo_res
read.

Tolerances: rel 1e-9 against evo in float64 (tests/test_pose_error.py; measured <= 5e-12), with an absolute
1e-12 for values that are 0 in exact arithmetic (KITTI 00's first poses coincide: a minimum angle error
is rounding noise on both sides). The numbers of a result file are ours exactly (JSON and .npy keep every
bit).
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit
from evo.main_ape import ape as evo_ape
from evo.main_rpe import rpe as evo_rpe
from evo.tools import file_interface

from jsve.cli import main

REL_TOL = 1e-9
ZERO_TOL = 1e-12
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")
RELATIONS = {
    "translation": metrics.PoseRelation.translation_part,
    "angle_deg": metrics.PoseRelation.rotation_angle_deg,
    "angle_rad": metrics.PoseRelation.rotation_angle_rad,
    "full": metrics.PoseRelation.full_transformation,
}
UNITS = {"f": Unit.frames, "m": Unit.meters, "d": Unit.degrees, "r": Unit.radians}


@pytest.fixture(scope="module")
def kitti(shared_data) -> tuple[str, str]:
    root = shared_data / "kitti"
    return str(root / "odometry_poses" / "00.txt"), str(root / "orbslam_estimate_00.txt")


KITTI_POSES = 800
"""The KITTI files of the statistics tests: KITTI 00's first 800 poses (558 m; 5 pairs at delta 100 m, 55
at 10 degrees, 48 at 0.2 rad), their lines copied as they are (the same digits for jsve and evo). As many
poses as the TUM files' estimate: each option is one compiled program of jsve per run length, and the
options both use are one, and evo's loops over poses stay short."""


@pytest.fixture(scope="module")
def kitti_prefix(kitti, tmp_path_factory) -> tuple[str, str]:
    folder = tmp_path_factory.mktemp("kitti")
    paths = []
    for source, name in zip(kitti, ("ref.txt", "est.txt"), strict=True):
        lines = Path(source).read_text().splitlines(keepends=True)
        assert len(lines) == 4541
        paths.append(str(folder / name))
        Path(paths[-1]).write_text("".join(lines[:KITTI_POSES]))
    return paths[0], paths[1]


@pytest.fixture(scope="module")
def tum(shared_data, tmp_path_factory) -> tuple[str, str, str]:
    """TUM files with stamps from KITTI 00's first 800 poses: the reference, the ORB-SLAM estimate 2 ms
    late, and a second estimate with noise from pose 100 on (association keeps each one's own frames)."""
    root = shared_data / "kitti"
    folder = tmp_path_factory.mktemp("tum")
    times = np.loadtxt(root / "times_00.txt")[:800]
    ref = file_interface.read_kitti_poses_file(root / "odometry_poses" / "00.txt").poses_se3[:800]
    est = np.stack(file_interface.read_kitti_poses_file(root / "orbslam_estimate_00.txt").poses_se3[:800])
    noisy = est.copy()
    noisy[:, :3, 3] += np.random.default_rng(1).normal(scale=0.3, size=(800, 3))
    paths = []
    for name, poses, stamps in (
        ("ref", ref, times),
        ("est", est, times + 0.002),
        ("noisy", noisy[100:], times[100:]),
    ):
        paths.append(str(folder / f"{name}.tum"))
        file_interface.write_tum_trajectory_file(
            paths[-1], PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps)
        )
    return paths[0], paths[1], paths[2]


def jsve_json(capsys, argv: list[str]) -> list[dict]:
    assert main([*argv, "--json"]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def evo_result(
    command: str, ref_path: str, est_path: str, fmt: str, relation: str = "translation", **options
):
    """What evo_ape / evo_rpe compute for FMT REF EST with these options (read and synchronised as they
    do: by index for kitti, associate_trajectories for tum)."""
    read = file_interface.read_kitti_poses_file if fmt == "kitti" else file_interface.read_tum_trajectory_file
    ref, est = read(ref_path), read(est_path)
    if fmt != "kitti":
        from evo.core import sync

        ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    if command == "ape":
        return evo_ape(ref, est, RELATIONS[relation], **options)
    unit = options.pop("delta_unit", "f")
    return evo_rpe(ref, est, RELATIONS[relation], delta_unit=UNITS[unit], **options)


def assert_stats(row: dict, expected: dict, what: str) -> None:
    for name in STATS:
        np.testing.assert_allclose(
            row[name], expected[name], rtol=REL_TOL, atol=ZERO_TOL, err_msg=f"{what} {name}"
        )
        if abs(expected[name]) > ZERO_TOL:
            assert abs(row[name] - expected[name]) <= REL_TOL * abs(expected[name]), f"{what} {name}"


# --------------------------------------------------------------------------------------------------
# Every statistic equal to evo's


EVO_ALIGNMENTS = {  # evo's spelling -> evo_ape's keywords
    ("-a",): dict(align=True),
    ("-a", "-s"): dict(align=True, correct_scale=True),
    ("-s",): dict(correct_scale=True),
    ("--align_origin",): dict(align_origin=True),
    ("-a", "--n_to_align", "300"): dict(align=True, n_to_align=300),
}


@pytest.mark.parametrize("relation", RELATIONS)
def test_ape_on_kitti_00_equals_evo_ape(capsys, kitti_prefix, relation):
    ref, est = kitti_prefix
    for spelling, options in EVO_ALIGNMENTS.items():
        rows = jsve_json(
            capsys, ["ape", ref, est, "--format", "kitti", "--pose_relation", relation, *spelling]
        )
        expected = evo_result("ape", ref, est, "kitti", relation, **options)
        assert_stats(rows[0], expected.stats, f"{relation} {spelling}")
        assert rows[0]["count"] == len(expected.np_arrays["error_array"]) == KITTI_POSES
        assert rows[0]["pose_relation"] == relation and not rows[0]["failed"]


RPE_OPTIONS = [  # jsve's arguments, evo_rpe's keywords
    (["--delta", "1"], dict(delta=1)),
    (["-d", "10", "-u", "f", "--all_pairs"], dict(delta=10, all_pairs=True)),
    (["--delta", "100", "--delta_unit", "m"], dict(delta=100.0, delta_unit="m")),
    (
        ["--delta", "50", "--delta-unit", "m", "--all-pairs", "-a"],
        dict(delta=50.0, delta_unit="m", all_pairs=True, align=True),
    ),
    (
        ["--delta", "10", "--delta_unit", "d", "-a", "-s"],
        dict(delta=10.0, delta_unit="d", align=True, correct_scale=True),
    ),
    (
        ["--delta", "0.2", "--delta_unit", "r", "--pairs_from_reference"],
        dict(delta=0.2, delta_unit="r", pairs_from_reference=True),
    ),
]


@pytest.mark.parametrize("relation", RELATIONS)
def test_rpe_on_kitti_00_equals_evo_rpe(capsys, kitti_prefix, relation):
    ref, est = kitti_prefix
    for argv, options in RPE_OPTIONS:
        rows = jsve_json(capsys, ["rpe", ref, est, "--format", "kitti", "-r", relation, *argv])
        expected = evo_result("rpe", ref, est, "kitti", relation, **options)
        assert_stats(rows[0], expected.stats, f"{relation} {argv}")
        assert rows[0]["count"] == len(expected.np_arrays["error_array"]) > 0


def test_tum_files_are_associated_and_equal_evo(capsys, tum):
    """Two estimates of other lengths and stamps in one call: each associated with the reference as evo
    does, then APE and RPE equal to evo's."""
    ref, est, noisy = tum
    rows = jsve_json(capsys, ["ape", ref, est, noisy, "-a", "-s", "-r", "angle_deg"])
    for row, path in zip(rows, (est, noisy), strict=True):
        assert_stats(
            row, evo_result("ape", ref, path, "tum", "angle_deg", align=True, correct_scale=True).stats, path
        )
    assert [r["count"] for r in rows] == [800, 700]
    rows = jsve_json(capsys, ["rpe", ref, est, noisy, "--delta", "20", "--delta_unit", "m", "-r", "full"])
    for row, path in zip(rows, (est, noisy), strict=True):
        assert_stats(row, evo_result("rpe", ref, path, "tum", "full", delta=20.0, delta_unit="m").stats, path)


# --------------------------------------------------------------------------------------------------
# evo's spellings and the alignment line


def printed(capsys, argv: list[str]) -> list[str]:
    assert main(argv) == 0, capsys.readouterr().err
    return capsys.readouterr().out.splitlines()


@pytest.mark.parametrize(
    ("jsve_spelling", "evo_spellings"),
    [
        (["--align", "se3"], [["-a"], ["--align"]]),
        (
            ["--align", "sim3"],
            [["-a", "-s"], ["-as"], ["--align", "--correct_scale"], ["--align", "se3", "-s"]],
        ),
        (["--align", "origin"], [["--align_origin"], ["--align-origin"]]),
        (["--align", "se3", "--n-to-align", "200"], [["-a", "--n_to_align", "200"]]),
        (["--pose-relation", "translation"], [["-r", "trans_part"], ["--pose_relation", "translation"]]),
        (["--t-max-diff", "0.005"], [["--t_max_diff", "0.005"]]),
    ],
)
def test_evo_spellings_give_jsves_result(capsys, tum, jsve_spelling, evo_spellings):
    ref, est, _ = tum
    want = jsve_json(capsys, ["ape", ref, est, *jsve_spelling])
    for spelling in evo_spellings:
        assert jsve_json(capsys, ["ape", ref, est, *spelling]) == want, spelling


def test_rpe_spellings(capsys, tum):
    ref, est, _ = tum
    want = jsve_json(
        capsys, ["rpe", ref, est, "--delta", "5", "--delta-unit", "m", "--all-pairs", "--delta-tol", "0.02"]
    )
    assert want[0]["count"] > 0
    for spelling in (
        ["-d", "5", "-u", "m", "--all_pairs", "-t", "0.02"],
        ["--delta", "5", "--delta_unit", "m", "--all_pairs", "--delta_tol", "0.02"],
    ):
        assert jsve_json(capsys, ["rpe", ref, est, *spelling]) == want, spelling
    other = jsve_json(capsys, ["rpe", ref, est, "--delta", "5", "--delta-unit", "m", "--all-pairs"])
    assert other[0]["count"] != want[0]["count"]  # the tolerance reached the pairs


@pytest.mark.parametrize(
    ("command", "argv", "title", "line"),
    [
        (
            "ape",
            [],
            "APE w.r.t. translation part (m) (with SE(3) Umeyama alignment)",
            "SE(3) Umeyama (evo -a)",
        ),
        (
            "ape",
            ["-a"],
            "APE w.r.t. translation part (m) (with SE(3) Umeyama alignment)",
            "SE(3) Umeyama (evo -a)",
        ),
        (
            "ape",
            ["-as", "-r", "angle_deg"],
            "APE w.r.t. rotation angle in degrees (deg) (with Sim(3) Umeyama alignment)",
            "Sim(3) Umeyama, with scale (evo -a -s)",
        ),
        (
            "ape",
            ["-s", "-r", "full"],
            "APE w.r.t. full transformation (unit-less) (scale corrected)",
            "scale only, Sim(3) Umeyama's scale (evo -s)",
        ),
        (
            "ape",
            ["--align_origin"],
            "APE w.r.t. translation part (m) (with origin alignment)",
            "first pose onto the reference's first pose (evo --align_origin)",
        ),
        (
            "ape",
            ["--align", "none"],
            "APE w.r.t. translation part (m) (not aligned)",
            "none (evo without -a)",
        ),
        (
            "ape",
            ["-a", "--n_to_align", "50"],
            "APE w.r.t. translation part (m) (with SE(3) Umeyama alignment) (aligned poses: 50)",
            "SE(3) Umeyama (evo -a), on the first 50 poses (evo --n_to_align 50)",
        ),
        (
            "rpe",
            [],
            "RPE w.r.t. translation part (m) for delta = 1 (frames) using consecutive pairs (not aligned)",
            "none (evo without -a)",
        ),
        (
            "rpe",
            ["-d", "2.5", "-u", "m", "--all_pairs", "-a", "-r", "angle_rad"],
            "RPE w.r.t. rotation angle in radians (rad) for delta = 2.5 (m) using all pairs "
            "(with SE(3) Umeyama alignment)",
            "SE(3) Umeyama (evo -a)",
        ),
    ],
)
def test_the_output_says_which_alignment_was_used(capsys, tum, command, argv, title, line):
    """The table is headed by evo's title (its lines joined) and the alignment line; the JSON carries the
    line in every object. jsve ape aligns SE(3) by default (evo_ape does not align without -a): the
    line says so. evo's titles come from evo_ape / evo_rpe themselves where evo has the alignment."""
    ref, est, _ = tum
    out = printed(capsys, [command, ref, est, *argv])
    assert out[0] == title and out[1] == f"aligned: {line}"
    assert out[2].split()[:2] == ["estimate", "rmse"]
    assert {r["alignment"] for r in jsve_json(capsys, [command, ref, est, *argv])} == {line}


def test_titles_are_evos(capsys, tum, tmp_path):
    """The result file's title is the one evo_ape / evo_rpe write for the same options (evo_res compares
    titles), line for line."""
    ref, est, _ = tum
    for command, argv, options in (
        (
            "ape",
            ["-a", "-s", "-r", "angle_deg", "--n_to_align", "100"],
            dict(align=True, correct_scale=True, n_to_align=100),
        ),
        ("ape", ["-s", "-r", "full"], dict(correct_scale=True)),
        ("ape", ["--align", "none"], {}),
        ("ape", ["--align_origin"], dict(align_origin=True)),
        ("rpe", ["-d", "3", "-u", "m", "--all_pairs"], dict(delta=3.0, delta_unit="m", all_pairs=True)),
        ("rpe", ["-d", "10", "-a", "-r", "angle_rad"], dict(delta=10, align=True)),
    ):
        zip_path = tmp_path / f"{command}.zip"
        printed(capsys, [command, ref, est, *argv, "--save_results", str(zip_path)])
        relation = argv[argv.index("-r") + 1] if "-r" in argv else "translation"
        expected = evo_result(command, ref, est, "tum", relation, **copy.deepcopy(options))
        assert file_interface.load_res_file(zip_path).info["title"] == expected.info["title"], argv


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-a", "--align_origin"], "--align_origin cannot be combined with -a"),
        (
            ["--align", "posyaw", "-s"],
            "-s/--correct_scale applies to Umeyama alignment (se3), not --align posyaw",
        ),
        (["-a", "--align", "origin"], "-a (evo's SE(3) alignment) contradicts --align origin"),
        (["-s", "--align_origin"], "-s with --align_origin"),
        (["-a", "--n_to_align", "0"], "--n-to-align must be a positive number or -1"),
        (["--save_plot", "figure.pdf"], "the suffix must be one of .png, .svg"),
    ],
)
def test_contradictions_are_one_line_and_exit_2(capsys, tum, tmp_path, argv, message):
    ref, est, _ = tum
    for command in ("ape", "rpe"):
        assert main([command, ref, est, *argv, "-o", str(tmp_path / "t.csv")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"jsve {command}: ") and message in err[0], err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["-d", "1.5"], "whole number of frames"), (["-d", "200", "-u", "d"], "within (0, 180]")],
)
def test_rpe_refuses_bad_deltas(capsys, tum, argv, message):
    ref, est, _ = tum
    assert main(["rpe", ref, est, *argv]) == 2
    assert message in capsys.readouterr().err


def test_an_rpe_without_pairs_fails_that_estimate(capsys, tum):
    ref, est, noisy = tum
    rows = jsve_json(capsys, ["rpe", ref, est, noisy, "-d", "750"])
    assert [(r["failed"], r["failure_reason"]) for r in rows] == [
        (False, ""),
        (True, "no pose pair at this delta"),
    ]
    assert rows[1]["rmse"] is None and rows[1]["count"] == 0


# --------------------------------------------------------------------------------------------------
# posyaw


def test_posyaw_warns_on_y_down_trajectories(capsys, kitti, shared_data, tmp_path):
    ref, est = kitti
    assert main(["ape", ref, est, "--format", "kitti", "--align", "posyaw"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("moves in a plane normal to y" in e and "use --align se3" in e for e in err)
    assert err[0].startswith(f"jsve ape: warning: {ref} ") and err[1].startswith(f"jsve ape: warning: {est} ")
    assert main(["ape", ref, est, "--format", "kitti", "-a"]) == 0  # only posyaw is warned about
    assert capsys.readouterr().err == ""
    # EuRoC's world is z up: no warning
    gt = shared_data / "euroc" / "groundtruth_left_cam" / "V101_GT.txt"
    traj = file_interface.read_euroc_csv_trajectory(gt)
    copy_path = tmp_path / "v101.tum"
    file_interface.write_tum_trajectory_file(copy_path, traj)
    assert main(["ape", str(copy_path), str(copy_path), "--align", "posyaw"]) == 0
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------------------------------
# Outputs: -o, result files, figures


@pytest.mark.parametrize("command", ["ape", "rpe"])
def test_results_load_in_evo_with_our_numbers(capsys, tum, tmp_path, command):
    """--save_results writes what evo.tools.file_interface.load_res_file reads: our statistics exactly,
    evo's error array (rel 1e-9) and evo's time axis for the same options; -o writes the same table."""
    ref, est, _ = tum
    argv = [command, ref, est, "-r", "angle_deg", "-a", "-s"] + (
        ["-d", "5", "-u", "m"] if command == "rpe" else []
    )
    zip_path, csv_path = tmp_path / "r.zip", tmp_path / "t.csv"
    row = jsve_json(capsys, [*argv, "--save_results", str(zip_path), "-o", str(csv_path)])[0]
    loaded = file_interface.load_res_file(zip_path)
    assert loaded.stats == {name: row[name] for name in STATS}  # JSON keeps every bit
    options = dict(align=True, correct_scale=True) | (
        dict(delta=5.0, delta_unit="m") if command == "rpe" else {}
    )
    expected = evo_result(command, ref, est, "tum", "angle_deg", **options)
    assert set(expected.np_arrays) - {"timestamps"} == set(loaded.np_arrays)
    for name in (
        "error_array",
        "seconds_from_start",
        "distances_from_start",
        "distances",
        "alignment_transformation_sim3",
    ):
        np.testing.assert_allclose(
            loaded.np_arrays[name], expected.np_arrays[name], rtol=REL_TOL, atol=1e-9, err_msg=name
        )
    assert loaded.info == expected.info | {"ref_name": ref, "est_name": est}
    table = pd.read_csv(csv_path)
    assert table["rmse"][0] == row["rmse"] and table["count"][0] == row["count"]
    if command == "ape":  # a Sim(3) alignment's scale is a column of its own
        evo_scale = np.linalg.norm(expected.np_arrays["alignment_transformation_sim3"][:3, 0])  # |s R e_x|
        assert table["scale"][0] == row["scale"] == pytest.approx(evo_scale, rel=REL_TOL)


def test_evo_res_tabulates_our_results_beside_evos(capsys, kitti, tmp_path):
    """evo_res (evo's own command) reads a jsve result file and an evo_ape one and prints equal rows."""
    ref, est = kitti
    ours, theirs, table = tmp_path / "jsve.zip", tmp_path / "evo.zip", tmp_path / "table.csv"
    printed(capsys, ["ape", ref, est, "--format", "kitti", "-a", "--save_results", str(ours)])
    evo_bin = Path(sys.executable).with_name("evo_ape")
    done = subprocess.run(
        [str(evo_bin), "kitti", ref, est, "-a", "--save_results", str(theirs), "--no_warnings"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    done = subprocess.run(
        [
            str(evo_bin.with_name("evo_res")),
            str(ours),
            str(theirs),
            "--use_filenames",
            "--save_table",
            str(table),
            "--no_warnings",
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    rows = pd.read_csv(table, index_col=0)
    assert list(rows.index) == [str(ours), str(theirs)]
    for name in STATS:
        np.testing.assert_allclose(rows[name].iloc[0], rows[name].iloc[1], rtol=REL_TOL, err_msg=name)


def test_several_estimates_get_one_result_file_each_and_a_failed_one_none(capsys, tum, tmp_path):
    ref, est, noisy = tum
    assert main(["rpe", ref, est, noisy, "-d", "750", "--save_results", str(tmp_path / "res.zip")]) == 0
    out = capsys.readouterr()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res_est.zip"]
    assert f"jsve rpe: no result file for {noisy}: no pose pair at this delta" in out.err
    assert file_interface.load_res_file(tmp_path / "res_est.zip").info["est_name"] == est


@pytest.mark.parametrize("command", ["ape", "rpe"])
@pytest.mark.parametrize("suffix", [".png", ".svg"])
def test_save_plot_writes_a_valid_figure(capsys, tum, tmp_path, command, suffix):
    ref, est, noisy = tum
    path = tmp_path / f"figure{suffix}"
    printed(capsys, [command, ref, est, noisy, "--save_plot", str(path)])
    data = path.read_bytes()
    if suffix == ".png":
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        from matplotlib import image

        pixels = image.imread(path)
        assert pixels.ndim == 3 and pixels.shape[0] > 300 and pixels.shape[1] > 600
        assert float(np.std(pixels)) > 0.05  # something was drawn
    else:
        root = ElementTree.fromstring(data)
        assert root.tag == "{http://www.w3.org/2000/svg}svg"
        assert len(root.findall(".//{http://www.w3.org/2000/svg}path")) > 10
        assert b"Date" not in data  # the same input gives the same SVG
        again = tmp_path / "again.svg"
        printed(capsys, [command, ref, est, noisy, "--save-plot", str(again)])
        assert again.read_bytes() == data


def test_plot_without_a_display_says_so_and_goes_on(capsys, tum, monkeypatch):
    import matplotlib

    monkeypatch.setattr(matplotlib, "get_backend", lambda: "agg")
    ref, est, _ = tum
    assert main(["ape", ref, est, "--plot"]) == 0
    out = capsys.readouterr()
    assert "jsve ape: --plot needs a display" in out.err and "estimate" in out.out
