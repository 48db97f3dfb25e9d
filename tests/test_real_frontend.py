"""A log from the real compiled front-end (ORB-SLAM3 v1.0 with jsve's hook; tests/data/orbslam3_v101,
made by `jsve frontend run`): it reads, its identity replay reproduces ORB-SLAM3's logged states on
every frame, its inertial stages are where ORB-SLAM3 puts them, and scoring it agrees with evo."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from jsve.evaluation._identity import identity_table
from jsve.io._batching import from_runs
from jsve.io._groundtruth import GroundTruth
from jsve.io._logs import read_log

DATA = Path(__file__).parent / "data" / "orbslam3_v101"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("real")
    paths = {}
    for name in ("groundtruth.csv", "run_000.orbslam3-euroc.txt"):
        with gzip.open(DATA / f"{name}.gz", "rb") as src, open(out / name, "wb") as dst:
            shutil.copyfileobj(src, dst)
        paths[name] = out / name
    return paths


@pytest.fixture(scope="module")
def run(files):
    return read_log(DATA / "run_000.csv.gz", ground_truth=GroundTruth(files["groundtruth.csv"], fmt="euroc"))


def test_the_real_log_reads_with_orbslam3s_stages(run):
    f = run.frames
    assert run.meta["frontend"] == "ORB-SLAM3 v1.0 + jsve hook" and len(f) == 700
    states = f["state"].to_numpy()
    first_ok = int(np.argmax(states == 2))
    # NOT_INITIALIZED until the monocular map, then tracked; no loss on the undisturbed sequence
    assert set(states[:first_ok]) == {1} and (states[first_ok:] == 2).mean() == 1.0
    imu = f["imu_init"].to_numpy().astype(bool)
    ba2 = f["imu_ba2"].to_numpy().astype(bool)
    first_imu, first_ba2 = int(np.argmax(imu)), int(np.argmax(ba2))
    # ORB-SLAM3 initialises the IMU a couple of seconds after the map, BA2 after ~15 s of keyframes
    assert first_ok < first_imu < first_ba2 and imu[first_imu:].all() and ba2[first_ba2:].all()
    assert 1.0 < (first_imu - first_ok) / 20.0 < 5.0 and 10.0 < (first_ba2 - first_imu) / 20.0 < 25.0
    # the hook's counts: inliers only where TrackLocalMap ran, never more than the keypoints
    inl = f["n_inliers"].to_numpy()
    assert (inl[:first_ok] == 0).all() and (inl[first_ok + 1 :] > 15).all()
    assert (inl <= f["n_extracted"].to_numpy()).all()
    assert run.has_ground_truth


def test_identity_replay_reproduces_every_logged_state(run):
    table = identity_table([run])
    assert table["agreement"].iloc[0] == 1.0 and not table["flagged"].iloc[0]


def test_the_replayed_stock_rule_covers_what_orbslam3_tracked(run):
    from jsve.core import preset
    from jsve.evaluation._evaluate import evaluate

    row = evaluate([from_runs([run])], preset("orbslam3"), progress=False).iloc[0]
    assert not row["failed"] and row["accepted_fraction"] > 0.85 and not row["lost_any"]
    # the frames ORB-SLAM3 tracked, less one at the ends of the ground truth or the map's start
    assert row["coverage"] == pytest.approx((run.frames["state"] == 2).mean(), abs=3 / 700)


def _ate(p, g, scale=False):
    """Umeyama-aligned position RMSE (m) of p against g, rows of 3."""
    a, b = p - p.mean(0), g - g.mean(0)
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    k = (s * np.diag(d)).sum() / (a**2).sum() if scale else 1.0
    return float(np.sqrt(((b - k * (u @ d @ vt @ a.T).T) ** 2).sum(1).mean()))


def test_the_logged_online_poses_change_world_frame_at_imu_initialisation(run):
    """What the real log taught: ORB-SLAM3 re-expresses the map (gravity, scale) when it initialises
    the IMU, with no new map id, so the online poses before and after are in different frames. Each
    part alone matches the ground truth (the monocular part up to scale)."""
    f = run.frames
    p, g = f[["vis_px", "vis_py", "vis_pz"]].to_numpy(), f[["gt_px", "gt_py", "gt_pz"]].to_numpy()
    ok = (f["state"].to_numpy() == 2) & np.isfinite(g).all(1)
    imu = f["imu_init"].to_numpy().astype(bool)
    before = ok & ~imu
    assert _ate(p[before], g[before], scale=True) < 0.03
    # the jump at the IMU's initialisation: one step of the log against ground truth's
    k = int(np.argmax(imu))
    assert np.linalg.norm(p[k] - p[k - 1]) > 20 * np.linalg.norm(g[k] - g[k - 1])


def _steps(p):
    return np.linalg.norm(np.diff(p, axis=0), axis=1)


def test_the_hooks_world_columns_put_a_map_in_one_world_frame(run):
    """The hook logs each re-expression (world_*: ApplyScaledRotation and the inertial BA after it, at
    IMU initialisation, BA1, BA2 and scale refinement); undone (jsve.io._world), the online poses of
    the map move as the ground truth does, with no jump."""
    from jsve.io._world import in_one_world_frame

    f = run.frames
    assert run.has_world_frame and "camera_in_body" in run.meta
    s = f["world_s"].to_numpy()
    changes = np.flatnonzero(np.diff(s) != 0) + 1
    first_imu = int(np.argmax(f["imu_init"].to_numpy()))
    first_ba2 = int(np.argmax(f["imu_ba2"].to_numpy()))
    # a change where the IMU is initialised and one where BA2 ran (the frame the hook saw it on)
    assert np.abs(changes - first_imu).min() <= 2 and np.abs(changes - first_ba2).min() <= 10
    assert (s[: changes[0]] == 1.0).all()
    g = f[["gt_px", "gt_py", "gt_pz"]].to_numpy()
    posed = (f["state"].to_numpy() == 2) & np.isfinite(g).all(1)
    raw = f[["vis_px", "vis_py", "vis_pz"]].to_numpy()
    one = in_one_world_frame(run).frames[["vis_px", "vis_py", "vis_pz"]].to_numpy()
    k = np.flatnonzero(posed[1:] & posed[:-1])
    jump = _steps(raw)[k] > 3 * _steps(g)[k] + 0.05
    assert jump.sum() >= 1  # the raw log does jump
    assert not (_steps(one)[k] > 3 * _steps(g)[k] + 0.05).any()


def test_the_replayed_stock_rule_scores_the_logged_poses_in_centimetres(run, files):
    """Replayed under its own rule, the log's online poses (in one world frame) score as ORB-SLAM3's
    own saved trajectory does, within a few centimetres (the saved one is refined by later BA)."""
    from jsve.core import preset
    from jsve.evaluation._evaluate import evaluate

    row = evaluate([from_runs([run])], preset("orbslam3"), progress=False).iloc[0]
    own = np.loadtxt(files["run_000.orbslam3-euroc.txt"], delimiter=",", comments="#")
    gt = np.loadtxt(files["groundtruth.csv"], delimiter=",", comments="#")
    common, i, j = np.intersect1d(own[:, 0].astype(np.int64), gt[:, 0].astype(np.int64), return_indices=True)
    own_ate = _ate(own[i, 1:4], gt[j, 1:4])
    assert not row["failed"] and row["rmse"] < 0.12
    assert abs(row["rmse"] - own_ate) < 0.04, (row["rmse"], own_ate)


def test_orbslam3s_own_trajectory_scores_as_evo_scores_it(files, x64):
    evo_file = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    from jsve.core._pose_error_batch import batched_pose_error
    from jsve.io._trajectories import read_pose_pairs, stack_pose_pairs

    ref = evo_file.read_euroc_csv_trajectory(str(files["groundtruth.csv"]))
    est = evo_file.read_euroc_csv_trajectory(str(files["run_000.orbslam3-euroc.txt"]))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref, correct_scale=False)
    evo_ape = metrics.APE(metrics.PoseRelation.translation_part)
    evo_ape.process_data((ref, est))
    expected = evo_ape.get_statistic(metrics.StatisticsType.rmse)
    assert 0.01 < expected < 0.3
    pairs = read_pose_pairs(files["groundtruth.csv"], [files["run_000.orbslam3-euroc.txt"]], "euroc")
    errors, _ = batched_pose_error(*stack_pose_pairs(pairs), align="se3")
    np.testing.assert_allclose(float(np.asarray(errors.stats.rmse)[0]), expected, rtol=1e-9)
