"""The simulator (jsve.sim._simulate) against what it must show.

- its settings are the seed's 31 and jsve.image._disturb's grids;
- logs pass jsve.io._logs' validation through a write/read round trip, bit for bit, and are a
  deterministic function of the seed; write_study is resumable;
- monocular initialisation: a first map starts at the first frame pair with 100 level-0 matches and 1
  degree of parallax, frames before it unposed and NOT_INITIALIZED, the IMU initialised and BA2 counted
  from it; heavy blur never starts one;
- an occluder costs map inliers: its edge's keypoints and the points that emerge from behind it;
- replaying a small study with ORB-SLAM3's own rule fails more as blur grows and always at blur 50.

jsve.sim._trajectory, jsve.sim._imu and jsve.sim._vision have their own files (test_motion.py,
test_vision.py).
"""

from __future__ import annotations

import shutil
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from jsve.io import _schema as schema
from jsve.io import read_log, write_log
from jsve.io._resume import StaleOutputError
from jsve.sim import _config as sim_config
from jsve.sim import _recording as sim_recording
from jsve.sim import _simulate as sim
from jsve.sim import _study as sim_study
from jsve.sim import _trajectory as st
from jsve.sim import _vision as sv

SHORT = sim_config.SimConfig(flight=st.FlightProfile(duration_s=(25.0, 25.0)))
"""Simulator configuration with 25 s flights (500 frames) for the log-level tests."""


# ---- settings -------------------------------------------------------------------------------------


def test_seed_settings_are_the_31():
    grid = sim.settings("seed")
    assert len(grid) == 31
    by = pd.Series([s.disturbance for s in grid]).value_counts().to_dict()
    assert by == {"blur": 11, "downsample": 10, "occlusion": 10}
    assert [s.level for s in grid if s.disturbance == "blur"] == [float(v) for v in range(0, 55, 5)]
    assert [s.level for s in grid if s.disturbance == "downsample"] == [
        round(1 - 0.1 * i, 1) for i in range(10)
    ]
    assert [s.level for s in grid if s.disturbance == "occlusion"] == [float(v) for v in range(0, 500, 50)]
    assert len(sim.settings("blur:0:25,occlusion,blur:25")) == 1 + 1 + 10  # duplicates dropped
    assert sim.settings("blur=0,25,occlusion,blur=25") == sim.settings("blur:0:25,occlusion,blur:25")
    assert [(s.disturbance, s.level) for s in sim.settings("blur=10,20,none")] == [
        ("blur", 10.0),
        ("blur", 20.0),
        ("none", 0.0),
    ]
    with pytest.raises(ValueError, match="'seed' takes no levels"):
        sim.settings("seed=5")
    with pytest.raises(ValueError, match="unknown disturbance"):
        sim.settings("fog")


def test_grids_are_jsve_disturb_grids():
    disturb = pytest.importorskip("jsve.image._disturb")
    for name, grid in sim.GRIDS.items():
        levels = tuple(float(v) for v in disturb.DISTURBANCES[name].levels)
        if name == "occlusion":  # the simulator adds the undisturbed 0 to the seed's 50..450
            levels = (0.0,) + levels
        assert tuple(float(v) for v in grid) == levels, name
    assert all(sv.gaussian_blur_sigma(n) == pytest.approx(disturb.blur_sigma(n)) for n in range(0, 55, 5))


# ---- logs ------------------------------------------------------------------------------------------


def test_logs_round_trip_and_are_deterministic(tmp_path):
    logs = sim.simulate_study(
        procedural=1, disturbances="blur:0:20,occlusion:450", runs=2, seed=5, config=SHORT
    )
    assert len(logs) == 6
    for run in logs:
        back = read_log(
            write_log(run, tmp_path / f"{run.meta['disturbance']}_{run.meta['level']}_{run.meta['run']}.csv")
        )
        pd.testing.assert_frame_equal(back.frames, run.frames, check_exact=True)
        assert back.meta == run.meta
        f = run.frames
        assert list(f.columns) == list(schema.COLUMNS)
        assert (f[list(schema.BIN_COLUMNS)].sum(axis=1) <= f["n_extracted"]).all()
        # Format v2: one map, a pose on every frame from its first (full support from there), BA2 from
        # 15 s after that frame where the IMU is initialised (docs/simulator.md), the rule and switch
        # model it ran.
        posed = f[list(schema.VIS_COLUMNS)].notna().all(axis=1).to_numpy()
        start = int(np.argmax(posed))
        assert (f["map_id"] == 0).all() and posed[start:].all() and not posed[:start].any()
        t = f["t_ns"].to_numpy()
        ba2 = (f["imu_init"].to_numpy() == 1) & (t - t[start] >= 15_000_000_000)
        np.testing.assert_array_equal(f["imu_ba2"].to_numpy(), ba2.astype(np.int64))
        assert 0 < ba2.sum() < f["imu_init"].sum()  # 25 s flights: BA2 comes 15 s in
        assert run.meta["rule"] == "orbslam3" and run.meta["switch_model"] == "orbslam3"
        assert (f["n_inliers"] <= f["n_extracted"]).all() and f["n_extracted"].max() <= 1000
        assert set(np.unique(f["state"])) <= {1, 2, 3, 4}
    again = sim.simulate_study(
        procedural=1, disturbances="blur:0:20,occlusion:450", runs=2, seed=5, config=SHORT
    )
    for a, b in zip(logs, again, strict=True):
        pd.testing.assert_frame_equal(a.frames, b.frames, check_exact=True)
    other = sim.simulate_run("proc_00", "blur", 20, run=1, seed=6, config=SHORT)
    assert not other.frames["vis_px"].equals(logs[3].frames["vis_px"])
    # Runs of one setting share the recording (scene, IMU) and differ in tracking.
    a, b = logs[0].frames, logs[1].frames
    assert a["n_extracted"].equals(b["n_extracted"]) and a["imu_dpx"].iloc[200:].equals(
        b["imu_dpx"].iloc[200:]
    )
    assert not a["n_inliers"].equals(b["n_inliers"])


def test_visual_error_grows_as_tracking_weakens():
    # Blur 30 is the heaviest blur at which these runs still start a map (level 0 empties beyond it):
    # the map holds less than half the inliers, and the error's tail grows with the weak tracking.
    logs = sim.simulate_study(procedural=1, disturbances="blur:0:30", runs=3, seed=2, config=SHORT)

    def error(run):
        f = run.frames
        return np.linalg.norm(
            f[list(schema.VIS_POSITION)].to_numpy() - f[list(schema.GT_POSITION)].to_numpy(), axis=1
        )

    def inliers(run):
        return run.frames.loc[run.frames["n_frustum"] > 0, "n_inliers"].mean()  # frames of a map

    clear = np.concatenate([error(r) for r in logs[:3]])
    blurred = np.concatenate([error(r) for r in logs[3:]])
    assert np.nanpercentile(blurred, 99) > 3 * np.nanpercentile(clear, 99)
    assert np.mean([inliers(r) for r in logs[3:]]) < 0.5 * np.mean([inliers(r) for r in logs[:3]])


def test_write_study_is_resumable(tmp_path):
    out = tmp_path / "study"
    first = sim_study.write_study(
        out, procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False
    )
    assert (first.written, first.skipped) == (4, 0)
    path = sim_study.log_path(out, "proc_00", sim.Setting("blur", 40.0), 1)
    original = path.read_bytes()
    path.unlink()
    stale = path.with_name(path.name + ".partial")
    stale.write_text("half a log")
    second = sim_study.write_study(
        out, procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False
    )
    assert (second.written, second.skipped) == (1, 3)
    assert path.read_bytes() == original and not stale.exists()


def _study(out, **kw):
    options = dict(procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False)
    return sim_study.write_study(out, **{**options, **kw})


def test_resume_refuses_logs_of_another_seed_or_configuration(tmp_path):
    """A folder of logs simulated under one generator key (seed, SimConfig, input files) is never
    completed under another: StaleOutputError naming the folder and the difference, the logs untouched;
    force=True replaces them with the logs a clean run under the new key writes."""
    out = tmp_path / "study"
    _study(out, runs=1)
    path = sim_study.log_path(out, "proc_00", sim.Setting("blur", 40.0), 0)
    before = {p: p.read_bytes() for p in out.rglob("*.csv")}
    assert read_log(path).meta["generator"] == sim_recording.generator_key(
        sim_recording.SequenceSpec("proc_00"), 0, SHORT
    )
    with pytest.raises(StaleOutputError, match=r"study holds outputs of another job \(2 logs .* seed 0 != 1"):
        _study(out, seed=1)  # two more runs asked for, too: nothing is written before the check
    slower = replace(SHORT, tracking=replace(SHORT.tracking, recovery_s=0.5))
    with pytest.raises(StaleOutputError, match=r"config \"[0-9a-f]+\" != \"[0-9a-f]+\""):
        _study(out, config=slower)
    with pytest.raises(StaleOutputError, match='imu_source "synthetic" != "real"'):
        _study(out, config=replace(SHORT, imu_source="real"))
    assert {p: p.read_bytes() for p in out.rglob("*.csv")} == before
    # a log of another sequence in the folder counts too (one folder, one study)
    other = sim_study.log_path(out, "proc_07", sim.Setting("none", 0.0), 0)
    other.parent.mkdir(parents=True)
    other.write_bytes(path.read_bytes().replace(b'"generator": {"seed": 0', b'"generator": {"seed": 5', 1))
    with pytest.raises(StaleOutputError, match="proc_07/none-0/run_000.csv: seed 5 != 0"):
        _study(out)
    other.unlink()
    # a log written before the key existed
    legacy = path.read_bytes().replace(b', "generator": ', b', "was": ', 1)
    path.write_bytes(legacy)
    with pytest.raises(StaleOutputError, match="no generator key"):
        _study(out, runs=1)
    forced = _study(out, seed=1, force=True)
    assert (forced.written, forced.skipped) == (4, 0)
    clean = _study(tmp_path / "clean", seed=1)
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*.csv")} == {
        p.relative_to(tmp_path / "clean"): p.read_bytes() for p in (tmp_path / "clean").rglob("*.csv")
    }
    assert (clean.written, _study(out, seed=1).skipped) == (4, 4)


def test_the_generator_key_covers_the_input_files(tmp_path):
    """An EuRoC sequence's key changes with its ground-truth file's content, not with its path or
    modification time alone."""
    gt = tmp_path / "gt"
    gt.mkdir()
    rows = "\n".join(f"{1403636580000000000 + k * 50_000_000} {k * 0.01} 0 0 1 0 0 0" for k in range(5))
    (gt / "MH01_GT.txt").write_text("#t x y z qw qx qy qz\n" + rows + "\n")
    spec = sim_recording.euroc_sequences(["MH_01"], gt)[0]
    first = sim_recording.generator_key(spec, 0, SHORT)
    copy = tmp_path / "copy"
    shutil.copytree(gt, copy)
    assert sim_recording.generator_key(sim_recording.euroc_sequences(["MH_01"], copy)[0], 0, SHORT) == first
    (gt / "MH01_GT.txt").write_text("#t x y z qw qx qy qz\n" + rows.replace(" 0.01 ", " 0.02 ") + "\n")
    assert sim_recording.generator_key(spec, 0, SHORT)["inputs"] != first["inputs"]
    assert (
        sim_recording.generator_key(sim_recording.SequenceSpec("proc_00"), 0, SHORT)["inputs"] == "procedural"
    )


def test_cli(tmp_path, capsys):
    from jsve.cli import main

    out = tmp_path / "cli"
    assert (
        main(
            [
                "simulate",
                "-o",
                str(out),
                "--procedural",
                "1",
                "--duration",
                "30",
                "--disturbances",
                "occlusion:450",
                "--runs",
                "1",
                "--workers",
                "1",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "1 logs written" in capsys.readouterr().out
    run = read_log(sim_study.log_path(out, "proc_00", sim.Setting("occlusion", 450.0), 0))
    assert run.meta["frontend"] == sim_config.FRONTEND and run.meta["disturbance"] == "occlusion"
    assert main(["simulate", "-o", str(out), "--sequences", "MH_01"]) == 2


def test_cli_duration_sets_every_procedural_flights_length(tmp_path, capsys):
    from jsve.cli import main

    out = tmp_path / "d"
    args = ["simulate", "-o", str(out), "--procedural", "2", "--disturbances", "none", "--runs", "1"]
    assert main([*args, "--duration", "12.5", "--workers", "1", "--no-progress"]) == 0
    assert "2 logs x ~250 frames" in capsys.readouterr().err  # the size announced from the duration
    for name in ("proc_00", "proc_01"):
        assert len(read_log(sim_study.log_path(out, name, sim.Setting("none", 0.0), 0)).frames) == 250
    assert main([*args, "--duration", "0"]) == 2
    assert (
        main(["simulate", "-o", str(out), "--sequences", "MH_01", "--euroc-gt", ".", "--duration", "5"]) == 2
    )
    assert "--duration" in capsys.readouterr().err


# ---- the first map -----------------------------------------------------------------------------------


def _first_map(n_level0=217.0, p_match=0.6, z=0.0, n_keys=1000, speed=0.01, moves_from=30, F=80, **changes):
    """first_map_frame on a made-up flight: 20 fps, a camera at rest until frame `moves_from`, then
    `speed` m per frame along x, 3 m from the scene; every frame `n_keys` keypoints, `n_level0` of them
    at level 0, each matched with probability p_match; one run whose match draws are all `z`."""
    k = np.arange(F)
    camera = np.zeros((F, 3))
    camera[:, 0] = speed * np.maximum(k - moves_from, 0)
    columns = dict(n_keys=np.full(F, n_keys), n_level0=np.full(F, n_level0), p_match=np.full(F, p_match),
                   camera_p=camera, depth=np.full(F, 3.0), t=k / 20.0, z=np.full((1, F), z))  # fmt: skip
    columns.update(changes)
    return int(sim.first_map_frame(**columns)[0])


def test_the_first_map_waits_for_matches_and_parallax():
    """Known answers of Tracking::MonocularInitialization's rules. 1 degree at 3 m is a 5.24 cm
    baseline: 6 frames of motion at 1 cm a frame."""
    # Frame 0 is the reference; at rest its pairs match but have no parallax. The reference is dropped at
    # frame 22, whose previous frame is more than 1 s after it (t[21] - t[0] = 1.05 s); frame 23 is the
    # next, and the camera, moving from frame 30, is 6 cm from it at frame 36.
    assert _first_map() == 36
    # Moving from the start: frame 0's pair with frame 6 has the parallax.
    assert _first_map(moves_from=0) == 6
    # Too few matches (217 x 0.4 = 87 < 100): every pair drops its reference; never a map.
    assert _first_map(p_match=0.4) == sim.NEVER
    # The same with unlucky draws: 130.2 - 3 x 7.2 < 100.
    assert _first_map(z=-5.0) == sim.NEVER
    # Fewer than 100 level-0 keypoints: no pair can reach 100 matches.
    assert _first_map(n_level0=99.0) == sim.NEVER
    # A frame of 100 keypoints or fewer drops the reference: frames 33-35 do, so frame 36 becomes the
    # reference, and frame 42 is 6 cm further.
    poor = np.full(80, 1000)
    poor[33:36] = 100
    assert _first_map(n_keys=poor) == 42
    # 1.5 degrees of parallax needs 7.85 cm: frame 38 (8 cm).
    tracking = replace(sim_config.TrackingParams(), init_parallax_deg=1.5)
    assert _first_map(tracking=tracking) == 38


def test_frames_before_the_first_map_have_no_pose_and_no_map():
    logs = sim.simulate_study(procedural=2, disturbances="none", runs=3, seed=1, config=SHORT)
    for run in logs:
        f = run.frames
        posed = f["vis_px"].notna().to_numpy()
        start = int(np.argmax(posed))
        assert posed.any() and start > 0  # the camera must move before a map can start
        before, after = f.iloc[:start], f.iloc[start:]
        assert (before["state"] == schema.STATE_NOT_INITIALIZED).all()
        assert (before[["n_inliers", "n_frustum", "imu_init", "imu_ba2"]] == 0).all(axis=None)
        assert (after["state"].iloc[0] == schema.STATE_OK) and (after["n_inliers"] > 0).all()
        # The IMU is initialised 2 to 3.5 s into the map (TrackingParams.imu_init_s).
        t = (f["t_ns"].to_numpy() - f["t_ns"].iloc[0]) / 1e9
        delay = t[int(np.argmax(f["imu_init"].to_numpy() == 1))] - t[start]
        assert 2.0 - 0.05 <= delay <= 3.5 + 0.05


def test_heavy_blur_never_starts_a_map():
    """At blur 40 the camera images keep no level-0 keypoints (docs/data/simulator_octaves.csv: 0 of 217)
    so no run initialises: every frame NOT_INITIALIZED and unposed, and every rule's replay fails."""
    from jsve.core import preset
    from jsve.evaluation import evaluate
    from jsve.io import buckets

    logs = sim.simulate_study(procedural=1, disturbances="blur=40", runs=2, seed=0, config=SHORT)
    for run in logs:
        assert (run.frames["state"] == schema.STATE_NOT_INITIALIZED).all()
        assert run.frames["vis_px"].isna().all() and (run.frames["n_inliers"] == 0).all()
    for rule in ("orbslam3", "sve-option2"):
        table = evaluate(buckets(logs), preset(rule), rule_name=rule, progress=False)
        assert table["failed"].all() and (table["coverage"] == 0).all()


def test_an_occluder_costs_map_inliers():
    """The edge's keypoints (static) are never inliers, and the points that emerge from behind the
    occluder have no map point yet: the share falls with the occluder's size and with image speed."""
    recording = sim_recording.make_recording(sim_recording.SequenceSpec("proc_00"), 0, SHORT)
    share = {}
    for side in (0, 200, 350):
        deg = sv.degradation("occlusion" if side else "none", side)
        counts = sv.extract(recording.scene, deg)
        share[side] = sim.occluder_map_share(recording, counts, deg, SHORT.tracking)
        assert counts.border.sum(axis=1).max() == (0 if side == 0 else counts.border.sum(axis=1).max())
    assert (share[0] == 1.0).all()
    assert 1.0 > share[200].mean() > share[350].mean() > 0.5
    speed = np.linalg.norm(recording.omega[:, :2], axis=1)
    fast, slow = speed > np.quantile(speed, 0.8), speed < np.quantile(speed, 0.2)
    assert share[350][fast].mean() < share[350][slow].mean()
    still = replace(SHORT.tracking, map_lifetime_s=0.0)
    deg = sv.degradation("occlusion", 350)
    assert (sim.occluder_map_share(recording, sv.extract(recording.scene, deg), deg, still) == 1.0).all()
    logs = sim.simulate_study(procedural=1, disturbances="none,occlusion=350", runs=2, seed=0, config=SHORT)

    def ratio(run):
        f = run.frames[run.frames["n_frustum"] > 0]
        return (f["n_inliers"] / f["n_extracted"]).mean()

    assert np.mean([ratio(r) for r in logs[2:]]) < 0.75 * np.mean([ratio(r) for r in logs[:2]])


# ---- replay ----------------------------------------------------------------------------------------


def test_orbslam3_fails_more_as_blur_grows():
    from jsve.core import preset
    from jsve.evaluation import evaluate
    from jsve.io import buckets

    logs = sim.simulate_study(procedural=2, disturbances="blur:0:20:30:50", runs=4, seed=0)
    table = evaluate(buckets(logs), preset("orbslam3"), rule_name="orbslam3", progress=False)
    failed = table.groupby("level")["failed"].mean()
    assert failed.loc[0] <= 0.25
    assert failed.loc[50] == 1.0
    assert failed.is_monotonic_increasing, failed.to_dict()
    # The logged state is ORB-SLAM3's own rule: a run lost tracking (an expiry to LOST, or a reset whose
    # new map waits in NOT_INITIALIZED) after its first map exactly when the replay says it did.
    lost_states = [schema.STATE_LOST, schema.STATE_NOT_INITIALIZED]

    def lost(run):
        posed = run.frames["vis_px"].notna().to_numpy()
        return posed.any() and bool(run.frames["state"].iloc[int(np.argmax(posed)) :].isin(lost_states).any())

    logged = {r.run_id: lost(r) for r in logs}
    assert 0 < sum(logged.values()) < len(logged)
    assert (table["run_id"].map(logged) == table["lost_any"]).all()
