"""Real ORB-SLAM3 runs (tests/data/orbslam3_v3, format-v3 logs of the hooked ORB-SLAM3 v1.0 with the
trajectory ORB-SLAM3 itself saved): jsve rebuilds that trajectory from the log alone, its score of a log
under the log's own rule equals `jsve ape` (= evo) of ORB-SLAM3's saved file, events are counted and
failures follow the coverage of the saved trajectory. The oracle is ORB-SLAM3's own output."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jsve.core import ObjectiveConfig, preset
from jsve.core._objective import run_losses
from jsve.core._replay import batch_features
from jsve.core._rules import InlierRule, Thresholds
from jsve.evaluation import identity_table, own_rule_table
from jsve.evaluation._evaluate import LOST_REASON
from jsve.fitting._kernel import prepare, search_chunk
from jsve.io import euroc_ate, event_counts, from_runs, in_saved_frame, read_log, saved_trajectory
from jsve.io._groundtruth import GroundTruth
from jsve.io._trajectories import read_trajectory

DATA = Path(__file__).parent / "data" / "orbslam3_v3"
FIXTURES = ("undisturbed", "reset_at_init", "loop_closure", "rule_in_loop", "imu_coast", "never_initialised")
SAVED = FIXTURES[:-1]  # never_initialised: ORB-SLAM3 built no map, saved no trajectory


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("orbslam3_v3")
    for path in DATA.glob("*.gz"):
        with gzip.open(path, "rb") as src, open(out / path.name.removesuffix(".gz"), "wb") as dst:
            shutil.copyfileobj(src, dst)
    return out


@pytest.fixture(scope="module")
def runs(files) -> dict:
    return {
        name: read_log(DATA / f"{name}.csv.gz", ground_truth=GroundTruth(files / f"{name}.groundtruth.csv"))
        for name in FIXTURES
    }


def test_the_fixtures_hold_the_events_they_are_named_for(runs):
    events = {name: event_counts(run) for name, run in runs.items()}
    assert events["undisturbed"]["reset"] == 0 and events["undisturbed"]["ba2"] == 1
    assert events["reset_at_init"]["reset"] >= 2  # "Not enough motion for initializing. Reseting..."
    assert events["loop_closure"]["loop"] == 1
    states = runs["rule_in_loop"].frames["state"].to_numpy()
    assert (states == 3).any() and events["rule_in_loop"]["reset"] > 0  # RECENTLY_LOST, resets
    assert runs["rule_in_loop"].meta["rule_name"] == "harsh"
    assert runs["imu_coast"].meta["switch_model"] == "imu-coast"
    assert (runs["never_initialised"].frames["state"] == 1).all()


@pytest.mark.parametrize("name", SAVED)
def test_the_rebuilt_trajectory_is_the_one_orbslam3_saved(runs, files, name):
    """Pose by pose: the same frames and, to float32 arithmetic and 9 printed decimals, the same poses."""
    saved = saved_trajectory(runs[name])
    file = read_trajectory(files / f"{name}.orbslam3-euroc.txt", "euroc")
    assert len(saved.rows) == file.num_poses
    # SaveTrajectoryEuRoC prints 1e9 x a double stamp in seconds: within 1 us of the frame's
    np.testing.assert_allclose(saved.t_ns * 1e-9, file.timestamps, rtol=0, atol=1e-6)
    # 1e-5 m: ORB-SLAM3 composes three or four SE3f (float32, eps 1.2e-7) poses metres from the origin
    # (2.6e-6 m at most on these runs); jsve composes the same float32 values in float64
    np.testing.assert_allclose(saved.pose[:, 4:], file.positions_xyz, rtol=0, atol=1e-5)
    q, q_file = saved.pose[:, :4], file.orientations_quat_wxyz
    q = q * np.sign(np.sum(q * q_file, axis=1))[:, None]
    np.testing.assert_allclose(q, q_file, rtol=0, atol=1e-5)


@pytest.mark.parametrize("name", SAVED)
def test_a_log_scored_under_its_own_rule_equals_jsve_ape_of_the_saved_file(runs, files, name, x64):
    """The number a SLAM researcher reports (evo_ape -a on ORB-SLAM3's file) is jsve's, to 1e-6 m."""
    row = own_rule_table([runs[name]], min_coverage=0.0).iloc[0]
    expected, n = euroc_ate(files / f"{name}.groundtruth.csv", files / f"{name}.orbslam3-euroc.txt")
    assert row["rmse"] == pytest.approx(expected, abs=1e-6)
    assert row["count"] == n and not row["failed"]
    # and evo itself, as `evo_ape euroc GT EST -a` computes it
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_euroc_csv_trajectory(str(files / f"{name}.groundtruth.csv"))
    est = file_interface.read_euroc_csv_trajectory(str(files / f"{name}.orbslam3-euroc.txt"))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert row["rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)


@pytest.mark.parametrize("name", FIXTURES)
def test_identity_replay_reproduces_every_logged_state(runs, name):
    """Every state, but for the frames where Track() returned early after LocalMapping flagged a bad IMU
    initialisation (the hook logs them LOST, the machine a reset: docs/frontend.md), one per reset of
    the stationary start."""
    row = identity_table([runs[name]]).iloc[0]
    if name != "reset_at_init":
        assert row["agreement"] == 1.0
        return
    states = runs[name].frames["state"].to_numpy()
    early = np.flatnonzero((states[1:] == 4) & (states[:-1] == 2)) + 1
    assert len(early) == 3 and row["first_mismatch"] == early[0]
    assert row["agreement"] == pytest.approx(1 - len(early) / len(states))


def test_frames_tracked_in_the_saved_map_are_the_saved_frames(runs):
    """in_saved marks exactly the frames ORB-SLAM3 saved among those it ended in OK or RECENTLY_LOST."""
    for name in SAVED:
        run = runs[name]
        f = in_saved_frame(run).frames
        tracked = f["state"].isin([2, 3]).to_numpy() & np.isfinite(f["vis_px"].to_numpy())
        np.testing.assert_array_equal(
            np.flatnonzero(tracked & (f["in_saved"] == 1)), saved_trajectory(run).rows
        )


def test_a_run_fails_by_its_coverage_not_by_its_resets(runs):
    """The stationary start: ORB-SLAM3 reset its map three times and saved 26 % of the frames. Under the
    default floor (half the frames) the run failed for its coverage; with a lower floor it is tracked at
    its saved trajectory's ATE; under "strict" every reset is a failure."""
    run = [runs["reset_at_init"]]
    default = own_rule_table(run).iloc[0]
    assert default["failed"] and default["coverage"] == pytest.approx(317 / 1200)
    assert "coverage" in default["failure_reason"] and LOST_REASON not in default["failure_reason"]
    assert default["resets"] == 3
    low = own_rule_table(run, min_coverage=0.2).iloc[0]
    assert not low["failed"] and low["rmse"] == pytest.approx(default["rmse"])
    strict = own_rule_table(run, min_coverage=0.2, failure="strict").iloc[0]
    assert strict["failed"] and LOST_REASON in strict["failure_reason"]
    loop = own_rule_table([runs["loop_closure"]]).iloc[0]
    assert not loop["failed"] and loop["resets"] == 2  # resets at initialisation, then a loop closure
    never = own_rule_table([runs["never_initialised"]]).iloc[0]
    assert never["failed"] and never["coverage"] == 0 and np.isnan(never["rmse"])


def test_the_loss_is_bounded_by_the_penalty_unless_raw(runs, x64):
    batch = from_runs([runs["loop_closure"]], dtype=jnp.float64).batch
    rule = preset("orbslam3")
    raw = run_losses(batch, rule, config=ObjectiveConfig(failure_penalty=0.01, loss="raw"))
    bounded = run_losses(batch, rule, config=ObjectiveConfig(failure_penalty=0.01))
    assert float(raw.rmse[0]) == pytest.approx(0.0215, abs=5e-4) and not bool(raw.failed[0])
    assert float(raw.loss[0]) == float(raw.rmse[0]) and float(bounded.loss[0]) == pytest.approx(0.01)


@pytest.mark.parametrize("switch_model", ["orbslam3", "imu-coast"])
def test_the_search_kernel_scores_real_runs_as_the_replay_objective_does(runs, switch_model, x64):
    """Stricter rules than the recorded ones reset, expire and start maps of their own on real logs: the
    kernel's per-map sums give the objective of run_losses (replay + in_trajectory + alignment)."""
    chosen = [runs[n] for n in ("undisturbed", "reset_at_init", "loop_closure", "rule_in_loop", "imu_coast")]
    batch = from_runs(chosen, dtype=jnp.float64).batch
    features = batch_features(batch)
    th = np.array([[15, 50, 50, 10], [60, 120, 100, 10], [150, 200, 150, 120], [300, 300, 300, 300]], float)
    rules = InlierRule(Thresholds(*(jnp.asarray(th[:, k]) for k in range(4))))
    config = ObjectiveConfig(switch_model=switch_model, min_coverage=0.3)
    kernel = search_chunk(prepare(batch, features), rules, config)
    for s in range(len(th)):
        one = InlierRule(Thresholds(*(jnp.asarray(th[s, k]) for k in range(4))))
        ref = run_losses(batch, one, features, config)
        np.testing.assert_array_equal(np.asarray(kernel.failed[s]), np.asarray(ref.failed))
        np.testing.assert_allclose(np.asarray(kernel.coverage[s]), np.asarray(ref.coverage), atol=1e-12)
        # 1e-9 m: the kernel's alignment from sums against the replay's over points, in float64
        np.testing.assert_allclose(np.asarray(kernel.loss[s]), np.asarray(ref.loss), atol=1e-9)
    # the thresholds exercise what they are meant to: failures and tracked runs both
    assert np.asarray(kernel.failed).any() and not np.asarray(kernel.failed).all()


def test_euroc_ate_computes_in_float64_in_its_own_thread_only(files, monkeypatch):
    # `jsve frontend run --workers N` scores runs from N threads: a process-wide float64 switch, turned
    # off by one thread while another traced, crashed a run; the switch must hold in the caller alone.
    import threading

    import jax

    import jsve.core._pose_error_batch as pose_error

    seen = {}
    real = pose_error.batched_ape

    def spy(*args, **kwargs):
        seen["caller"] = jax.numpy.zeros(()).dtype
        other = threading.Thread(target=lambda: seen.update(other=jax.numpy.zeros(()).dtype))
        other.start()
        other.join()
        return real(*args, **kwargs)

    monkeypatch.setattr(pose_error, "batched_ape", spy)
    name = SAVED[0]
    with jax.enable_x64(False):
        euroc_ate(files / f"{name}.groundtruth.csv", files / f"{name}.orbslam3-euroc.txt")
    assert seen == {"caller": np.float64, "other": np.float32}
