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
    imu, ba2 = f["imu_init"].to_numpy().astype(bool), f["imu_ba2"].to_numpy().astype(bool)
    before, between = ok & ~imu, ok & imu & ~ba2
    assert _ate(p[before], g[before], scale=True) < 0.03
    assert _ate(p[between], g[between]) < 0.1
    # the jump at the IMU's initialisation: one step of the log against ground truth's
    k = int(np.argmax(imu))
    assert np.linalg.norm(p[k] - p[k - 1]) > 20 * np.linalg.norm(g[k] - g[k - 1])


@pytest.mark.xfail(
    strict=True,
    reason="the replay aligns a map's online poses as one segment across the "
    "world-frame changes of IMU initialisation and BA2 (no log column marks them yet)",
)
def test_the_replayed_stock_rule_scores_the_logged_poses_in_centimetres(run):
    from jsve.core import preset
    from jsve.evaluation._evaluate import evaluate

    row = evaluate([from_runs([run])], preset("orbslam3"), progress=False).iloc[0]
    assert row["rmse"] < 0.2


def test_orbslam3s_own_trajectory_scores_as_evo_scores_it(files, x64):
    evo_file = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    from jsve.core._pose_error import batched_pose_error
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
