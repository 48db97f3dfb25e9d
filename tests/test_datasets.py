"""jsve.image._datasets: the resumable, parallel writer of disturbed EuRoC datasets and its manifest."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from jsve.image import Camera
from jsve.image import _datasets as datasets
from jsve.image import _disturb as d

W, H = 752, 480


def _write_source(root: Path, n_frames: int = 3, stereo: bool = True) -> Path:
    """A small synthetic EuRoC dataset: textured frames (or flat ones), IMU, ground truth, calibration."""
    rng = np.random.default_rng(11)
    mav0 = root / "mav0"
    for cam in ("cam0", "cam1") if stereo else ("cam0",):
        (mav0 / cam / "data").mkdir(parents=True)
        lines = ["#timestamp [ns],filename"]
        for i in range(n_frames):
            t = 1403715273262142976 + i * 50_000_000
            image = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 1.5)
            cv2.imwrite(str(mav0 / cam / "data" / f"{t}.png"), np.clip(image, 0, 255).astype(np.uint8))
            lines.append(f"{t},{t}.png")
        (mav0 / cam / "data.csv").write_text("\n".join(lines) + "\n")
        (mav0 / cam / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: camera\nrate_hz: 20\nresolution: [752, 480]\ncamera_model: pinhole\n"
            "intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\n"
            "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n"
        )
    (mav0 / "imu0").mkdir()
    (mav0 / "imu0" / "data.csv").write_text("#t,wx,wy,wz,ax,ay,az\n1403715273262142976,0,0,0,0,0,9.81\n")
    (mav0 / "state_groundtruth_estimate0").mkdir()
    (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("#t,px\n1403715273262142976,0\n")
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: test\n")
    return root


@pytest.fixture
def source(tmp_path) -> Path:
    return _write_source(tmp_path / "SEQ")


def _mtimes(folder: Path) -> dict[str, int]:
    return {p.relative_to(folder).as_posix(): p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}


def test_dataset_written_with_manifest_and_untouched_extras(source, tmp_path):
    out = tmp_path / "out"
    results = datasets.disturb_datasets(
        [source], out, ["lens_dirt", "downsample"], {"lens_dirt": [0.3], "downsample": [0.5]},
        {"downsample": {"mode": "calibration"}}, seed=4, progress=False,
    )  # fmt: skip
    assert [r.status for r in results] == ["written", "written"]
    dirt, small = (r.target for r in results)
    assert dirt == out / "SEQ" / "lens_dirt-0.3" and small == out / "SEQ" / "downsample-0.5_mode=calibration"
    for cam_index, cam in enumerate(("cam0", "cam1")):
        for t, name in datasets.read_frame_list(source / "mav0" / cam):
            original = cv2.imread(str(source / "mav0" / cam / "data" / name), cv2.IMREAD_UNCHANGED)
            written = cv2.imread(str(dirt / "mav0" / cam / "data" / name), cv2.IMREAD_UNCHANGED)
            expected = d.disturb_image(
                original, "lens_dirt", 0.3, seed=(4, cam_index), frame_seed=(4, cam_index, t)
            )
            assert np.array_equal(written, expected)
    for rel in ("mav0/imu0/data.csv", "mav0/state_groundtruth_estimate0/data.csv", "mav0/body.yaml",
                "mav0/cam0/data.csv"):  # fmt: skip
        assert (dirt / rel).read_bytes() == (source / rel).read_bytes()
    manifest = json.loads((dirt / datasets.MANIFEST_NAME).read_text())
    assert manifest["disturbance"] == "lens_dirt" and manifest["level"] == 0.3
    assert manifest["parameters"] == {"seed": 4}
    assert manifest["source"] == str(source.resolve()) and manifest["frames"] == {
        "mav0/cam0": 3,
        "mav0/cam1": 3,
    }
    assert (manifest["content_hash"], manifest["file_count"]) == datasets.content_hash(dirt)
    assert manifest["file_count"] == 2 * (3 + 2) + 3  # per camera: frames, data.csv, sensor.yaml
    camera = Camera.from_sensor_yaml(small / "mav0" / "cam0" / "sensor.yaml")
    assert (camera.width, camera.height) == (376, 240)
    np.testing.assert_allclose(
        (camera.fx, camera.fy, camera.cx, camera.cy), d.scale_intrinsics((458.654, 457.296, 367.215, 248.375),
                                                                          (W, H), (376, 240)), rtol=1e-8
    )  # fmt: skip
    assert camera.distortion[0] == pytest.approx(-0.28340811)
    frame = next((small / "mav0" / "cam0" / "data").iterdir())
    assert cv2.imread(str(frame), cv2.IMREAD_UNCHANGED).shape == (240, 376)


def test_rerun_resumes_after_a_crash(source, tmp_path):
    out = tmp_path / "out"
    levels = {"blur": [0, 5, 10], "occlusion": [100]}
    first = datasets.disturb_datasets([source], out, ["blur", "occlusion"], levels, progress=False)
    assert {r.status for r in first} == {"written"}
    finished = [out / "SEQ" / "blur-0", out / "SEQ" / "occlusion-100"]
    before = {f: _mtimes(f) for f in finished}
    # Simulate a crash: blur-5 half written (its .partial left behind), blur-10 not started.
    crashed = out / "SEQ" / "blur-5"
    crashed.rename(out / "SEQ" / "blur-5.partial")
    (out / "SEQ" / "blur-5.partial" / "mav0" / "cam0" / "data.csv").unlink()
    (out / "SEQ" / "blur-5.partial" / "junk.tmp").write_text("half")
    shutil.rmtree(out / "SEQ" / "blur-10")
    again = datasets.disturb_datasets([source], out, ["blur", "occlusion"], levels, progress=False)
    status = {r.target.name: r.status for r in again}
    assert status == {
        "blur-0": "skipped",
        "blur-5": "redone",
        "blur-10": "written",
        "occlusion-100": "skipped",
    }
    assert {f: _mtimes(f) for f in finished} == before  # finished datasets untouched
    assert not list(out.rglob("*.partial"))
    assert not (crashed / "junk.tmp").exists()
    assert [r.manifest["content_hash"] for r in again] == [r.manifest["content_hash"] for r in first]


def test_folder_without_manifest_is_not_overwritten(source, tmp_path):
    (tmp_path / "out" / "SEQ" / "blur-5").mkdir(parents=True)
    with pytest.raises(datasets.DatasetError, match="no jsve_manifest.json"):
        datasets.disturb_datasets([source], tmp_path / "out", ["blur"], {"blur": [5]}, progress=False)


def test_parallel_workers_write_the_same_datasets(tmp_path):
    source = _write_source(tmp_path / "SEQ", n_frames=2, stereo=False)
    levels = {"noise": [5], "haze": [1.0]}
    serial = datasets.disturb_datasets(
        [source], tmp_path / "a", ["noise", "haze"], levels, workers=1, progress=False
    )
    parallel = datasets.disturb_datasets(
        [source], tmp_path / "b", ["noise", "haze"], levels, workers=2, progress=False
    )
    assert [r.manifest["content_hash"] for r in serial] == [r.manifest["content_hash"] for r in parallel]


def test_not_a_dataset(tmp_path):
    with pytest.raises(datasets.DatasetError, match="no mav0"):
        datasets.make_jobs([tmp_path], tmp_path / "out")


def test_cli_levels_and_parameters(source, tmp_path, capsys):
    from jsve.cli import disturb as cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    args = parser.parse_args(
        ["disturb", str(source), "-o", str(tmp_path / "o"), "--disturbance", "motion_blur",
         "--levels", "7", "--param", "motion_blur.angle=90", "--workers", "1", "--no-progress"]
    )  # fmt: skip
    assert args.func(args) == 0
    assert "1 written" in capsys.readouterr().out
    manifest = datasets.read_manifest(tmp_path / "o" / "SEQ" / "motion_blur-7_angle=90")
    assert manifest["parameters"] == {"angle": 90, "seed": 0}
    bad = parser.parse_args(["disturb", str(source), "-o", str(tmp_path / "o"), "--param", "blur.angle=1"])
    assert bad.func(bad) == 2


def test_rerun_refuses_datasets_of_another_seed_source_or_parameters(tmp_path):
    """A finished dataset is resumed only under the key it was made under (source path and content,
    disturbance, level, parameters, seed): another seed or an edited source image stops the run before
    anything is written (StaleOutputError naming the folder and the difference); force rewrites exactly
    the stale datasets, to the bytes a clean run writes."""
    from jsve.io._resume import StaleOutputError

    source = _write_source(tmp_path / "SEQ", n_frames=2, stereo=False)
    out = tmp_path / "out"
    levels = {"noise": [5, 10]}
    datasets.disturb_datasets([source], out, ["noise"], levels, seed=0, progress=False)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(
        StaleOutputError, match=r"out holds outputs of another job \(2 datasets .*parameters.seed 0 != 1"
    ):
        datasets.disturb_datasets([source], out, ["noise"], {"noise": [5, 10, 15]}, seed=1, progress=False)
    assert not (out / "SEQ" / "noise-15").exists()
    image = next((source / "mav0" / "cam0" / "data").iterdir())
    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    pixels[0, 0] ^= 1
    image.unlink()  # a new file (the outputs hard-link the source's untouched files)
    cv2.imwrite(str(image), pixels)
    with pytest.raises(StaleOutputError, match='source_hash "sha256:[0-9a-f]+" != "sha256:[0-9a-f]+"'):
        datasets.disturb_datasets([source], out, ["noise"], levels, seed=0, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # a dataset written before the key had the source's hash
    manifest = json.loads((out / "SEQ" / "noise-5" / datasets.MANIFEST_NAME).read_text())
    del manifest["source_hash"]
    (out / "SEQ" / "noise-5" / datasets.MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(StaleOutputError, match="source_hash absent != "):
        datasets.disturb_datasets([source], out, ["noise"], {"noise": [5]}, seed=0, progress=False)
    forced = datasets.disturb_datasets([source], out, ["noise"], levels, seed=1, force=True, progress=False)
    assert [r.status for r in forced] == ["redone", "redone"]
    clean = datasets.disturb_datasets([source], tmp_path / "clean", ["noise"], levels, seed=1, progress=False)
    assert [r.manifest["content_hash"] for r in forced] == [r.manifest["content_hash"] for r in clean]
    again = datasets.disturb_datasets([source], out, ["noise"], levels, seed=1, progress=False)
    assert [r.status for r in again] == ["skipped", "skipped"]


def test_unwritable_output_is_one_error_and_leaves_nothing(source, tmp_path, monkeypatch):
    """A full disk while writing images is an OutputError naming the dataset; no .partial folder and no
    dataset are left."""
    import errno

    from jsve.io._atomic import OutputError

    def full(path, image, *args):
        raise OSError(errno.ENOSPC, "No space left on device", path)

    monkeypatch.setattr(datasets.cv2, "imwrite", full)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"cannot write .*SEQ/blur-5: No space left on device"):
        datasets.disturb_datasets([source], out, ["blur"], {"blur": [5]}, progress=False)
    assert [p.name for p in (out / "SEQ").iterdir()] == []
