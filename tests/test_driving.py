"""jsve.sim._driving: determinism, readers, masks = dynamic keypoints, masking helps."""

import numpy as np
import pytest

from jsve.evaluation import bootstrap_ci
from jsve.io import _schema as schema
from jsve.io import keypoints_path, read_keypoints, read_log, write_keypoints, write_log
from jsve.masks import PngMasks, apply_masks
from jsve.sim._driving import DrivingConfig, kitti_body_poses, simulate_sequence, write_png_masks

SMALL = DrivingConfig(n_frames=180)


@pytest.fixture(scope="module")
def runs():
    return simulate_sequence("DRIVE_T", 7, 2, SMALL)


def test_deterministic_under_seed(runs):
    again = simulate_sequence("DRIVE_T", 7, 2, SMALL)
    for a, b in zip(runs, again, strict=True):
        assert a.original.frames.equals(b.original.frames)
        assert a.keypoints.keypoints.equals(b.keypoints.keypoints)
        np.testing.assert_array_equal(a.masked_vis, b.masked_vis)
    other = simulate_sequence("DRIVE_T", 8, 1, SMALL)[0]
    assert not other.original.frames[list(schema.VIS_POSITION)].equals(
        runs[0].original.frames[list(schema.VIS_POSITION)]
    )
    # Runs of one sequence share the trajectory and scene but not the keypoints.
    assert runs[0].original.frames["gt_px"].equals(runs[1].original.frames["gt_px"])
    assert not runs[0].keypoints.keypoints["x"].equals(runs[1].keypoints.keypoints["x"])


def test_files_pass_readers(runs, tmp_path):
    sim = runs[0]
    log = write_log(sim.original, tmp_path / "r0.csv")
    side = write_keypoints(sim.keypoints, keypoints_path(log))
    back, kp = read_log(log), read_keypoints(side)
    # Format v2: one map, BA2 15 s in (10 fps: from frame 150; imu_init is 1 throughout), the rule.
    f = back.frames
    assert list(f.columns) == list(schema.COLUMNS) and (f["map_id"] == 0).all()
    np.testing.assert_array_equal(f["imu_ba2"], (np.arange(len(f)) >= 150).astype(np.int64))
    assert back.meta["rule"] == "orbslam3" and back.meta["switch_model"] == "orbslam3"
    np.testing.assert_array_equal(back.frames["n_extracted"], sim.original.frames["n_extracted"])
    assert len(kp.keypoints) == len(sim.keypoints.keypoints)
    masked = sim.masked()
    write_log(masked, tmp_path / "r0_masked.csv")
    assert (read_log(tmp_path / "r0_masked.csv").frames["n_extracted"] < back.frames["n_extracted"]).any()
    # The read-back pair reproduces the masked counts (apply_masks verifies the logged counts and bins).
    again = apply_masks(back, kp, sim.masks).log
    np.testing.assert_array_equal(again.frames["n_inliers"], masked.frames["n_inliers"])


def test_masks_cover_exactly_the_dynamic_keypoints(runs, tmp_path):
    sim = runs[0]
    result = apply_masks(sim.original, sim.keypoints, sim.masks)
    assert sim.dynamic.any() and (~sim.dynamic).any()
    np.testing.assert_array_equal(result.removed, sim.dynamic)
    # Static keypoints stay away from box edges: at least edge_margin px from every box.
    kp = sim.keypoints.keypoints
    frame = np.searchsorted(sim.original.frames["t_ns"].to_numpy(), kp["t_ns"].to_numpy())
    static = ~sim.dynamic
    for f in range(0, SMALL.n_frames, 10):
        sel = static & (frame == f)
        x, y = kp["x"].to_numpy()[sel], kp["y"].to_numpy()[sel]
        for x0, y0, x1, y1 in sim.scene.boxes[f]:
            inside = (x >= x0 - SMALL.edge_margin) & (x < x1 + SMALL.edge_margin)
            inside &= (y >= y0 - SMALL.edge_margin) & (y < y1 + SMALL.edge_margin)
            assert not inside.any()
    # PNG masks on disk give the same removal.
    write_png_masks(sim.scene, tmp_path / "masks")
    png = apply_masks(sim.original, sim.keypoints, PngMasks(tmp_path / "masks"))
    np.testing.assert_array_equal(png.removed, sim.dynamic)


def test_masked_vis_differs_only_through_dynamic_features():
    sim = simulate_sequence("DRIVE_N", 3, 1, DrivingConfig(n_frames=60, spawn_rate=0.0, n_initial=0))[0]
    assert not sim.dynamic.any()
    # Without objects the masked run is the original run: same draws, same inliers, no bias.
    masked = sim.masked()
    np.testing.assert_allclose(
        masked.frames[list(schema.VIS_POSITION)], sim.original.frames[list(schema.VIS_POSITION)]
    )


def test_kitti_poses_conversion(tmp_path):
    # A camera driving forward (camera z) and turning left (about camera -y) -> body x forward, yaw > 0.
    yaw = 0.1
    c, s = np.cos(yaw), np.sin(yaw)
    r_wc = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # about camera y (down) by -yaw: a left turn
    rows = [np.hstack([np.eye(3), np.zeros((3, 1))]).ravel(), np.hstack([r_wc, [[0], [0], [2.0]]]).ravel()]
    np.savetxt(tmp_path / "00.txt", np.array(rows))
    poses = kitti_body_poses(tmp_path / "00.txt")
    np.testing.assert_allclose(poses[1, :3, 3], [2.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses[1, :3, :3] @ [1, 0, 0], [np.cos(yaw), np.sin(yaw), 0.0], atol=1e-12)


def _analysis_module(name: str):
    """Import analysis/<name>.py by path: analysis/ is a folder of scripts, not a package on sys.path."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "analysis" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"analysis_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_masking_lowers_ape(x64):
    """In float64, as `python analysis/masked_driving.py` runs it."""
    study = _analysis_module("masked_driving").study

    table, per_run = study(n_runs=4, n_frames=250)
    summary = table.summary.set_index("statistic")
    assert summary.loc["rmse", "masked"] < summary.loc["rmse", "original"]
    low, high = bootstrap_ci(per_run["rmse_difference"].to_numpy(), n_boot=2000, seed=0)
    assert high < 0
