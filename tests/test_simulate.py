"""The simulator (jsve.sim._simulate) against what it must show.

- its settings are the seed's 31 and jsve.image._disturb's grids;
- logs pass jsve.io._logs' validation through a write/read round trip, bit for bit, and are a
  deterministic function of the seed; write_study is resumable;
- replaying a small study with ORB-SLAM3's own rule fails more as blur grows and always at blur 50.

jsve.sim._motion and jsve.sim._vision have their own files (test_motion.py, test_vision.py).
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
from jsve.sim import _motion as sm
from jsve.sim import _simulate as sim
from jsve.sim import _vision as sv

SHORT = sim.SimConfig(flight=sm.FlightProfile(duration_s=(25.0, 25.0)))
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
        procedural=1, disturbances="blur:0:30,occlusion:450", runs=2, seed=5, config=SHORT
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
        # Format v2: one map and a pose on every frame (full support), BA2 from 15 s after the first
        # frame where the IMU is initialised (docs/simulator.md), the rule and switch model it ran.
        assert (f["map_id"] == 0).all() and f[list(schema.VIS_COLUMNS)].notna().all(axis=None)
        t = f["t_ns"].to_numpy()
        ba2 = (f["imu_init"].to_numpy() == 1) & (t - t[0] >= 15_000_000_000)
        np.testing.assert_array_equal(f["imu_ba2"].to_numpy(), ba2.astype(np.int64))
        assert 0 < ba2.sum() < f["imu_init"].sum()  # 25 s flights: BA2 comes 15 s in
        assert run.meta["rule"] == "orbslam3" and run.meta["switch_model"] == "orbslam3"
        assert (f["n_inliers"] <= f["n_extracted"]).all() and f["n_extracted"].max() <= 1000
        assert set(np.unique(f["state"])) <= {1, 2, 3, 4}
    again = sim.simulate_study(
        procedural=1, disturbances="blur:0:30,occlusion:450", runs=2, seed=5, config=SHORT
    )
    for a, b in zip(logs, again, strict=True):
        pd.testing.assert_frame_equal(a.frames, b.frames, check_exact=True)
    other = sim.simulate_run("proc_00", "blur", 30, run=1, seed=6, config=SHORT)
    assert not other.frames["vis_px"].equals(logs[3].frames["vis_px"])
    # Runs of one setting share the recording (scene, IMU) and differ in tracking.
    a, b = logs[0].frames, logs[1].frames
    assert a["n_extracted"].equals(b["n_extracted"]) and a["imu_dpx"].iloc[200:].equals(
        b["imu_dpx"].iloc[200:]
    )
    assert not a["n_inliers"].equals(b["n_inliers"])


def test_visual_error_grows_as_tracking_weakens():
    logs = sim.simulate_study(procedural=1, disturbances="blur:0:45", runs=3, seed=2, config=SHORT)

    def error(run):
        f = run.frames
        return np.linalg.norm(
            f[list(schema.VIS_POSITION)].to_numpy() - f[list(schema.GT_POSITION)].to_numpy(), axis=1
        )

    clear = np.concatenate([error(r) for r in logs[:3]])
    blurred = np.concatenate([error(r) for r in logs[3:]])
    assert np.percentile(blurred, 99) > 3 * np.percentile(clear, 99)
    assert np.mean([r.frames["n_inliers"].mean() for r in logs[3:]]) < 0.3 * np.mean(
        [r.frames["n_inliers"].mean() for r in logs[:3]]
    )


def test_write_study_is_resumable(tmp_path):
    out = tmp_path / "study"
    first = sim.write_study(
        out, procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False
    )
    assert (first.written, first.skipped) == (4, 0)
    path = sim.log_path(out, "proc_00", sim.Setting("blur", 40.0), 1)
    original = path.read_bytes()
    path.unlink()
    stale = path.with_name(path.name + ".partial")
    stale.write_text("half a log")
    second = sim.write_study(
        out, procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False
    )
    assert (second.written, second.skipped) == (1, 3)
    assert path.read_bytes() == original and not stale.exists()


def _study(out, **kw):
    options = dict(procedural=1, disturbances="blur:0:40", runs=2, workers=1, config=SHORT, progress=False)
    return sim.write_study(out, **{**options, **kw})


def test_resume_refuses_logs_of_another_seed_or_configuration(tmp_path):
    """A folder of logs simulated under one generator key (seed, SimConfig, input files) is never
    completed under another: StaleOutputError naming the folder and the difference, the logs untouched;
    force=True replaces them with the logs a clean run under the new key writes."""
    out = tmp_path / "study"
    _study(out, runs=1)
    path = sim.log_path(out, "proc_00", sim.Setting("blur", 40.0), 0)
    before = {p: p.read_bytes() for p in out.rglob("*.csv")}
    assert read_log(path).meta["generator"] == sim.generator_key(sim.SequenceSpec("proc_00"), 0, SHORT)
    with pytest.raises(StaleOutputError, match=r"study holds outputs of another job \(2 logs .* seed 0 != 1"):
        _study(out, seed=1)  # two more runs asked for, too: nothing is written before the check
    slower = replace(SHORT, tracking=replace(SHORT.tracking, recovery_s=0.5))
    with pytest.raises(StaleOutputError, match=r"config \"[0-9a-f]+\" != \"[0-9a-f]+\""):
        _study(out, config=slower)
    with pytest.raises(StaleOutputError, match='imu_source "synthetic" != "real"'):
        _study(out, config=replace(SHORT, imu_source="real"))
    assert {p: p.read_bytes() for p in out.rglob("*.csv")} == before
    # a log of another sequence in the folder counts too (one folder, one study)
    other = sim.log_path(out, "proc_07", sim.Setting("none", 0.0), 0)
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
    spec = sim.euroc_sequences(["MH_01"], gt)[0]
    first = sim.generator_key(spec, 0, SHORT)
    copy = tmp_path / "copy"
    shutil.copytree(gt, copy)
    assert sim.generator_key(sim.euroc_sequences(["MH_01"], copy)[0], 0, SHORT) == first
    (gt / "MH01_GT.txt").write_text("#t x y z qw qx qy qz\n" + rows.replace(" 0.01 ", " 0.02 ") + "\n")
    assert sim.generator_key(spec, 0, SHORT)["inputs"] != first["inputs"]
    assert sim.generator_key(sim.SequenceSpec("proc_00"), 0, SHORT)["inputs"] == "procedural"


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
    run = read_log(sim.log_path(out, "proc_00", sim.Setting("occlusion", 450.0), 0))
    assert run.meta["frontend"] == sim.FRONTEND and run.meta["disturbance"] == "occlusion"
    assert main(["simulate", "-o", str(out), "--sequences", "MH_01"]) == 2


def test_cli_duration_sets_every_procedural_flights_length(tmp_path, capsys):
    from jsve.cli import main

    out = tmp_path / "d"
    args = ["simulate", "-o", str(out), "--procedural", "2", "--disturbances", "none", "--runs", "1"]
    assert main([*args, "--duration", "12.5", "--workers", "1", "--no-progress"]) == 0
    assert "2 logs x ~250 frames" in capsys.readouterr().err  # the size announced from the duration
    for name in ("proc_00", "proc_01"):
        assert len(read_log(sim.log_path(out, name, sim.Setting("none", 0.0), 0)).frames) == 250
    assert main([*args, "--duration", "0"]) == 2
    assert (
        main(["simulate", "-o", str(out), "--sequences", "MH_01", "--euroc-gt", ".", "--duration", "5"]) == 2
    )
    assert "--duration" in capsys.readouterr().err


# ---- replay ----------------------------------------------------------------------------------------


def test_orbslam3_fails_more_as_blur_grows():
    from jsve.core import preset
    from jsve.evaluation import evaluate
    from jsve.io import buckets

    logs = sim.simulate_study(procedural=2, disturbances="blur:0:20:35:50", runs=4, seed=0)
    table = evaluate(buckets(logs), preset("orbslam3"), rule_name="orbslam3", progress=False)
    failed = table.groupby("level")["failed"].mean()
    assert failed.loc[0] <= 0.25
    assert failed.loc[50] == 1.0
    assert failed.is_monotonic_increasing, failed.to_dict()
    # The logged state is ORB-SLAM3's own rule: a run lost tracking (an expiry to LOST, or a reset whose
    # new map waits in NOT_INITIALIZED) exactly when the replay says it did.
    lost_states = [schema.STATE_LOST, schema.STATE_NOT_INITIALIZED]
    logged = {r.run_id: bool(r.frames["state"].isin(lost_states).any()) for r in logs}
    assert 0 < sum(logged.values()) < len(logged)
    assert (table["run_id"].map(logged) == table["lost_any"]).all()
