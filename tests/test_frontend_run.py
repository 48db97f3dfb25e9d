"""jsve frontend run without ORB-SLAM3: what a dataset is, settings for downsampled images, the runs'
plan and its resume keys. The driver itself runs in the opt-in smoke test (.ci/frontend-smoke)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from jsve.frontend._run import describe_dataset, plan, scaled_settings
from jsve.io._resume import StaleOutputError

SETTINGS = """%YAML:1.0
Camera.type: "PinHole"
Camera1.fx: 458.654
Camera1.fy: 457.296
Camera1.cx: 367.215
Camera1.cy: 248.375
Camera1.k1: -0.28340811
Camera.width: 752
Camera.height: 480
Camera.newWidth: 600
Camera.newHeight: 350
Camera.fps: 20
"""


def make_dataset(root: Path, size=(752, 480), manifest: dict | None = None, name="jsve_render.json") -> Path:
    data = root / "mav0" / "cam0" / "data"
    data.mkdir(parents=True)
    stamps = [1403715274312143104 + 50_000_000 * i for i in range(3)]
    for t in stamps:
        cv2.imwrite(str(data / f"{t}.png"), np.zeros(size[::-1], np.uint8))
    (root / "mav0" / "cam0" / "data.csv").write_text("#t,f\n" + "".join(f"{t},{t}.png\n" for t in stamps))
    (root / "mav0" / "imu0").mkdir(parents=True)
    (root / "mav0" / "imu0" / "data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n1,0,0,0,0,0,9.81\n")
    if manifest is not None:
        (root / name).write_text(json.dumps(manifest))
    return root


def make_build(root: Path) -> Path:
    root.mkdir()
    (root / "build.json").write_text(json.dumps({"hook_sha256": "ab" * 32}))
    return root


def test_datasets_are_named_by_their_manifests(tmp_path):
    rendered = make_dataset(tmp_path / "r", manifest={"trajectory": "x/V101_GT.txt"})
    assert describe_dataset(rendered).sequence == "V101"
    manifest = {"source": str(rendered), "disturbance": "blur", "level": 35}
    blurred = make_dataset(tmp_path / "b", manifest=manifest, name="jsve_manifest.json")
    d = describe_dataset(blurred)
    assert (d.sequence, d.disturbance, d.level) == ("V101", "blur", 35.0)
    with pytest.raises(ValueError, match="not a EuRoC-format dataset"):
        describe_dataset(tmp_path)


def test_settings_follow_a_downsampled_image():
    assert scaled_settings(SETTINGS, 752, 480) is None
    half = scaled_settings(SETTINGS, 376, 240)
    assert half is not None
    fs = cv2.FileStorage(half, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    assert fs.getNode("Camera1.fx").real() == pytest.approx(229.327)
    assert fs.getNode("Camera1.cy").real() == pytest.approx(124.1875)
    assert (fs.getNode("Camera.width").real(), fs.getNode("Camera.newHeight").real()) == (376, 175)
    assert fs.getNode("Camera1.k1").real() == pytest.approx(-0.28340811)  # distortion is unit-free


def test_plan_keeps_complete_logs_of_the_same_key_and_stops_at_others(tmp_path):
    build = make_build(tmp_path / "build")
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    kw = dict(runs=2, out=tmp_path / "logs", vocabulary=voc, settings=settings)
    todo, done = plan(build, [ds], **kw)
    assert [j.run for j in todo] == [0, 1] and done == []
    assert todo[0].log == tmp_path / "logs" / "V101" / "none-0" / "run_000.csv"
    key = todo[0].meta["generator"]
    todo[0].log.write_text("# jsve-log v2 " + json.dumps({"generator": key}) + "\n")
    # A complete log without its summary: the command was killed before the run finished.
    todo, done = plan(build, [ds], **kw)
    assert [j.run for j in todo] == [0, 1] and done == []
    todo[0].log.with_suffix(".summary.json").write_text(json.dumps({"exit_code": 0, "generator": key}))
    todo, done = plan(build, [ds], **kw)
    assert [j.run for j in todo] == [1] and len(done) == 1
    (ds / "mav0" / "imu0" / "data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n1,0,0,0,0,0,9.80\n")
    with pytest.raises(StaleOutputError, match="generator"):
        plan(build, [ds], **kw)
    todo, _ = plan(build, [ds], force=True, **kw)
    assert [j.run for j in todo] == [0, 1]


def test_two_datasets_of_one_identity_are_refused_not_overwritten(tmp_path):
    build = make_build(tmp_path / "build")
    a = make_dataset(tmp_path / "a", manifest={"trajectory": "V101_GT.txt"})
    b = make_dataset(tmp_path / "b", manifest={"trajectory": "other/V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    kw = dict(runs=1, out=tmp_path / "logs", vocabulary=voc, settings=settings)
    with pytest.raises(ValueError, match="would write the same logs"):
        plan(build, [a, b], **kw)
    (tmp_path / "x").mkdir()
    todo, _ = plan(build, [a, tmp_path / "x" / ".." / "a"], **kw)  # one folder named twice: planned once
    assert [j.log for j in todo] == [tmp_path / "logs" / "V101" / "none-0" / "run_000.csv"]


def test_rules_in_the_loop_become_driver_arguments_and_metadata():
    from jsve.core import preset
    from jsve.evaluation._identity import recorded_rule
    from jsve.frontend._run import driver_rule, record_rule
    from jsve.io import RunLog

    assert driver_rule("orbslam3", preset("orbslam3"), "orbslam3") == ([], "orbslam3")
    args, meta = driver_rule("orbslam3", preset("orbslam3"), "imu-coast")
    assert args == ["--rule-inliers", "15.0,50.0,50.0,10.0", "--coast"] and meta == "orbslam3"
    args, meta = driver_rule("record", record_rule(), "orbslam3")
    assert args == ["--rule-inliers", "1.0,1.0,1.0,0.0"]
    # the metadata names the rule as JSON text, which identity replay reads back as that rule
    name, rule = recorded_rule(RunLog(meta={"rule": meta}, frames=None, source="log.csv"))  # type: ignore[arg-type]
    assert name == meta and rule == record_rule()
    # the SVE family: inputs, the combination, then the thresholds; nFeatures for the authors' Eq.1
    args, meta = driver_rule("sve-option1", preset("sve-option1"), "imu-coast", n_features=1200)
    assert args[0] == "--rule-sve" and args[2:] == ["--n-features", "1200", "--coast"]
    inputs, *numbers = args[1].split(",")
    # the rule's own values (its leaves: float32 unless x64), passed exactly
    expected = np.float32([0.5, 0.5, 1.0, 1.0, 0.5, 0.1, 0.3, 0.3, 0.1])
    assert inputs == "authors-option1" and np.array_equal(np.float32([float(x) for x in numbers]), expected)
    assert recorded_rule(RunLog(meta={"rule": meta}, frames=None, source="l.csv"))[1] == preset("sve-option1")  # type: ignore[arg-type]
    args, _ = driver_rule("sve-option2", preset("sve-option2"), "orbslam3")
    assert args[1].startswith("jsve,0.5,0.5,0.0,1.0,0.25,")
    with pytest.raises(ValueError, match="log.csv: metadata 'rule' is not valid JSON"):
        recorded_rule(RunLog(meta={"rule": "{not json"}, frames=None, source="log.csv"))  # type: ignore[arg-type]


def test_metadata_reaches_the_driver_as_typed_text():
    from jsve.frontend._run import _meta_args

    meta = {"run": 3, "fps": 20.0, "image_size": [752, 480], "rule": '{"kind": "inliers"}', "seq": "007"}
    assert _meta_args(meta) == [
        "--meta", "run=3", "--meta", "fps=20.0", "--meta", "image_size=[752,480]",
        "--meta", 'rule="{"kind": "inliers"}"', "--meta", 'seq="007"',
    ]  # fmt: skip


EUROC_SETTINGS = """%YAML:1.0
Camera.width: 752
ORBextractor.nFeatures: 1200
IMU.T_b_c1: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
"""
"""ORB-SLAM3 settings with EuRoC's camera-IMU extrinsics (EuRoC_mono_inertial.yaml, IMU.T_b_c1)."""


def test_settings_give_the_feature_count_and_the_camera_in_the_body():
    from scipy.spatial.transform import Rotation

    from jsve.frontend._run import camera_in_body, orb_features

    assert orb_features(EUROC_SETTINGS) == 1200
    assert orb_features("%YAML:1.0\nCamera.width: 752\n") == 1000
    pose = camera_in_body(EUROC_SETTINGS)
    assert pose is not None and camera_in_body("%YAML:1.0\nCamera.width: 752\n") is None
    rot = Rotation.from_quat(pose[1:4] + pose[:1]).as_matrix()
    expected = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422],
                         [0.999557249008, 0.0149672133247, 0.025715529948],
                         [-0.0257744366974, 0.00375618835797, 0.999660727178]])  # fmt: skip
    np.testing.assert_allclose(rot, expected, atol=2e-6)  # EuRoC's matrix is orthonormal to ~1e-6
    np.testing.assert_allclose(pose[4:], [-0.0216401454975, -0.064676986768, 0.00981073058949], rtol=1e-6)


def test_a_finished_failed_attempt_is_kept_a_killed_one_is_run_again(tmp_path):
    # A crash of a non-deterministic front-end is an outcome: re-running it until it succeeds would
    # bias the failure rate. An attempt without a summary was killed, not finished: it runs again.
    build = make_build(tmp_path / "build")
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    kw = dict(runs=3, out=tmp_path / "logs", vocabulary=voc, settings=settings)
    todo, _ = plan(build, [ds], **kw)
    key = todo[0].meta["generator"]
    crashed, killed, legacy = (j.log for j in todo)
    crashed.with_suffix(".summary.json").write_text(json.dumps({"exit_code": -11, "generator": key}))
    killed.with_name(killed.name + ".partial").write_text("# jsve-log v2 " + json.dumps({"generator": key}))
    # A summary written before summaries carried the key: the partial log's header names it.
    legacy.with_name(legacy.name + ".partial").write_text("# jsve-log v2 " + json.dumps({"generator": key}))
    legacy.with_suffix(".summary.json").write_text(json.dumps({"exit_code": 1}))
    todo, done = plan(build, [ds], **kw)
    assert [j.log for j in todo] == [killed] and done == [crashed, legacy]
    todo, done = plan(build, [ds], retry_failed=True, **kw)
    assert [j.log for j in todo] == [crashed, killed, legacy] and done == []
    # A failed attempt under another key (new inputs) is no outcome of this run.
    crashed.with_suffix(".summary.json").write_text(json.dumps({"exit_code": -11, "generator": "other"}))
    todo, _ = plan(build, [ds], **kw)
    assert [j.log for j in todo] == [crashed, killed]


def test_sensor_masks_and_keypoints_reach_the_driver_and_the_runs_key(tmp_path):
    from jsve.frontend._run import driver_command

    build = make_build(tmp_path / "build")
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    kw = dict(runs=1, out=tmp_path / "logs", vocabulary=voc, settings=settings)
    (plain,), _ = plan(build, [ds], **kw)
    command = driver_command(Path("driver"), voc, plain)
    assert not {"--sensor", "--masks", "--keypoints"} & set(command)  # a default run's command as before
    assert plain.meta["sensor"] == "imu_monocular"
    with pytest.raises(
        ValueError, match=r"ds/mav0/cam0/masks/1403715274312143104\.png: no mask \(3 of the 3"
    ):
        plan(build, [ds], masks=True, **kw)
    masks = ds / "mav0" / "cam0" / "masks"
    masks.mkdir()
    for image in sorted((ds / "mav0" / "cam0" / "data").iterdir())[:2]:
        cv2.imwrite(str(masks / image.name), np.zeros((480, 752), np.uint16))
    with pytest.raises(ValueError, match=r"1403715274412143104\.png: no mask \(1 of the 3"):
        plan(build, [ds], masks=True, **kw)
    cv2.imwrite(str(masks / "1403715274412143104.png"), np.zeros((480, 752), np.uint16))
    (job,), _ = plan(build, [ds], sensor="monocular", masks=True, keypoints=True, **kw)
    assert driver_command(Path("driver"), voc, job)[-4:] == [
        "--sensor",
        "monocular",
        "--masks",
        "--keypoints",
    ]
    assert job.meta["sensor"] == "monocular" and "camera_in_body" not in job.meta
    keys = {plain.meta["generator"], job.meta["generator"]}
    for options in ({"sensor": "monocular"}, {"masks": True}, {"keypoints": True}):
        (other,), _ = plan(build, [ds], force=True, **options, **kw)
        keys.add(other.meta["generator"])
    assert len(keys) == 5  # each option makes runs of their own key
    cv2.imwrite(str(masks / "1403715274412143104.png"), np.full((480, 752), 1001, np.uint16))
    (changed,), _ = plan(build, [ds], force=True, masks=True, **kw)
    assert changed.meta["generator"] not in keys  # another mask, another run


def test_a_monocular_run_takes_orbslam3s_own_rule_only(tmp_path):
    from jsve.core import preset

    build = make_build(tmp_path / "build")
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    kw = dict(runs=1, out=tmp_path / "logs", vocabulary=voc, settings=settings, sensor="monocular")
    with pytest.raises(ValueError, match="monocular run tracks with ORB-SLAM3's own rule only"):
        plan(build, [ds], rule=("sve-option2", preset("sve-option2")), **kw)
    with pytest.raises(ValueError, match="monocular run tracks with ORB-SLAM3's own rule only"):
        plan(build, [ds], switch_model="imu-coast", **kw)
    with pytest.raises(ValueError, match="sensor 'stereo': expected one of imu-monocular, monocular"):
        plan(build, [ds], **{**kw, "sensor": "stereo"})


def test_frontend_run_refuses_a_monocular_rule_and_missing_masks_before_running(tmp_path, capsys):
    from jsve.cli import main

    build = make_build(tmp_path / "build")
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    common = ["frontend", "run", str(build), str(ds), "--vocabulary", str(voc), "--settings", str(settings)]
    out = ["-o", str(tmp_path / "logs"), "--no-progress"]
    assert main([*common, "--sensor", "monocular", "--rule", "sve-option2", *out]) == 2
    assert "own rule only" in capsys.readouterr().err
    assert main([*common, "--masks", *out]) == 2
    assert "no mask (3 of the 3 images have none)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main([*common, "--sensor", "stereo", *out])
    assert exit_.value.code == 2


DRIVER = Path(os.environ.get("JSVE_FRONTEND_BUILD", Path.home() / ".cache" / "jsve" / "orbslam3")) / "bin"
DRIVER = DRIVER / "jsve_orbslam3"
"""The driver of a `jsve frontend build` (JSVE_FRONTEND_BUILD, else .ci/frontend-smoke's default folder)."""


@pytest.mark.skipif(not DRIVER.is_file(), reason=f"no jsve frontend build at {DRIVER} (.ci/frontend-smoke)")
@pytest.mark.parametrize(
    "extra, message",
    [
        (["--sensor", "stereo"], "--sensor wants imu-monocular or monocular, got 'stereo'"),
        (["--sensor", "monocular", "--rule-inliers", "15,50,50,10"], "need --sensor imu-monocular"),
        (["--lockstep", "--keypoints", "--branch-at", "2", "--branch-frames", "1", "--branch-log", "BRANCH"],
         "--keypoints does not go with --branch-at"),
        (["--masks"], "--masks: no mask "),
    ],
)  # fmt: skip
def test_the_driver_refuses_bad_arguments_and_missing_masks_before_it_runs(tmp_path, extra, message):
    ds = make_dataset(tmp_path / "ds")
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    log = tmp_path / "a" / "run.csv"
    log.parent.mkdir()
    command = [str(DRIVER), "--vocabulary", str(voc), "--settings", str(settings), "--sequence", str(ds)]
    command += ["--log", str(log), "--meta", "sequence=V101", "--meta", "run=0", "--meta", "fps=20.0"]
    extra = [str(tmp_path / "b" / "run.csv") if x == "BRANCH" else x for x in extra]  # as long as the log
    done = subprocess.run(command + extra, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr, done.stderr
    if extra == ["--masks"]:  # the first image's mask, named
        assert f"{ds}/mav0/cam0/masks/1403715274312143104.png" in done.stderr
    assert not list(log.parent.iterdir())  # no log, not even a partial one
