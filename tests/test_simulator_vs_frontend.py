"""analysis/simulator_vs_frontend.py: the re-runs rebuilt from their summaries, the per-level comparison on
a hand-made table with a known tau, regret@1 and failure agreement, the simulated runs' first maps, and
the two scenes it simulates."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from jsve.evaluation import run_loss
from jsve.sim import RENDERED_TEXTURE_SCALE, ImuNoise, SceneProfile, settings


def _script():
    """analysis/simulator_vs_frontend.py, imported by path (analysis/ is a folder of scripts)."""
    path = Path(__file__).resolve().parents[1] / "analysis" / "simulator_vs_frontend.py"
    spec = importlib.util.spec_from_file_location("analysis_simulator_vs_frontend", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


svf = _script()
RULES = ("orbslam3", "sve-option2", "sve-option1")


def _real(level: float, losses, failed=(0.0, 0.0, 0.0)) -> pd.DataFrame:
    """Re-run summaries of the three rules at (V101, blur, level) under switch model orbslam3."""
    return pd.DataFrame(
        {"sequence": "V101", "disturbance": "blur", "level": level, "rule": RULES, "switch_model": "orbslam3",
         "reruns": 5, "rerun_loss": losses, "rerun_q05": losses, "rerun_q95": losses,
         "rerun_failed": failed, "rerun_coverage": 0.8}
    )  # fmt: skip


def _sim(level: float, losses: dict, failed: dict | None = None) -> pd.DataFrame:
    """Two simulated runs per rule at (V101, blur, level), both replayed under every rule: run k of rule r
    has loss losses[r][k] (NaN RMSE where failed[r][k])."""
    rows = []
    for rule, values in losses.items():
        for k, loss in enumerate(values):
            bad = bool(failed and failed[rule][k])
            rows.append({"sequence": "V101", "disturbance": "blur", "level": level, "rule": rule,
                         "switch_model": "orbslam3", "run_id": f"V101/blur-{level:g}/{k}",
                         "rmse": np.nan if bad else loss, "failed": bad, "coverage": 0.0 if bad else 1.0,
                         "accepted_fraction": 0.0 if bad else 1.0})  # fmt: skip
    return pd.DataFrame(rows)


def test_pseudo_reruns_keep_the_mean_loss_and_the_failure_share():
    real = _real(20.0, [0.6, 1.0, 0.05], failed=[0.4, 1.0, 0.0])
    pseudo = svf.pseudo_reruns(real)
    g = pseudo.assign(loss=run_loss(pseudo)).groupby("rule")
    assert (g.size() == 5).all()
    for rule, loss, share in zip(RULES, [0.6, 1.0, 0.05], [0.4, 1.0, 0.0], strict=True):
        assert g["loss"].mean()[rule] == pytest.approx(loss, abs=1e-12)
        assert g["failed"].mean()[rule] == pytest.approx(share, abs=1e-12)
    # orbslam3: 2 failed re-runs at the 1 m penalty, so the other 3 carry (3 - 2) / 3 m each
    ok = pseudo[(pseudo["rule"] == "orbslam3") & ~pseudo["failed"]]["rmse"]
    np.testing.assert_allclose(ok, 1.0 / 3.0, atol=1e-12)


def test_compare_gives_the_known_tau_regret_and_failure_agreement():
    # Level 20: the simulator ranks orbslam3 < sve-option2 < sve-option1, the re-runs the reverse.
    # Level 25: the simulator ties every rule, so its pick is one at random.
    sim = pd.concat([
        _sim(20.0, {"orbslam3": [0.1, 0.1], "sve-option2": [0.2, 0.2], "sve-option1": [0.3, 1.0]},
             failed={"orbslam3": [0, 0], "sve-option2": [0, 0], "sve-option1": [0, 1]}),
        _sim(25.0, {r: [0.05, 0.05] for r in RULES}),
    ])  # fmt: skip
    real = pd.concat([_real(20.0, [0.5, 0.3, 0.1], failed=[0.4, 0.0, 0.0]), _real(25.0, [0.2, 0.4, 0.6])])
    c = svf.compare(sim, real, n_boot=200, seed=0)
    levels = c.levels.set_index("level")
    assert levels.loc[20.0, "tau"] == pytest.approx(-1.0)
    assert levels.loc[20.0, "replay_best"] == "orbslam3" and levels.loc[20.0, "rerun_best"] == "sve-option1"
    assert levels.loc[20.0, "regret_at_1"] == pytest.approx(0.5 - 0.1)
    assert levels.loc[20.0, "chance_regret"] == pytest.approx((0.5 + 0.3 + 0.1) / 3 - 0.1)
    assert np.isnan(levels.loc[25.0, "tau"])
    assert levels.loc[25.0, "regret_at_1"] == pytest.approx((0.2 + 0.4 + 0.6) / 3 - 0.2)
    rules = c.rules.set_index(["level", "rule"])
    # orbslam3 never fails in the simulator, in 2 of 5 re-runs: a random re-run agrees 3 times in 5
    assert rules.loc[(20.0, "orbslam3"), "failure_agreement"] == pytest.approx(0.6)
    # sve-option1 fails in one of two simulated runs, never in the re-runs: agreement 1/2
    assert rules.loc[(20.0, "sve-option1"), "failure_agreement"] == pytest.approx(0.5)
    assert rules.loc[(20.0, "sve-option1"), "sim_loss"] == pytest.approx(0.65)
    assert rules.loc[(20.0, "sve-option1"), "sim_failed"] == pytest.approx(0.5)
    assert rules.loc[(20.0, "sve-option1"), "real_loss"] == pytest.approx(0.1)
    pool = svf.pooled(c, n_boot=200, seed=0).set_index("levels")
    assert pool.loc["all", "regret_at_1"] == pytest.approx((0.4 + 0.2) / 2)
    assert pool.loc["all", "units_tau"] == 1
    low, high = pool.loc["all", ["regret_at_1_low", "regret_at_1_high"]]
    assert low <= 0.3 <= high


def test_a_level_where_every_real_run_failed_is_left_out_of_the_informative_pool():
    ranked = {"orbslam3": [0.1, 0.1], "sve-option2": [0.2, 0.2], "sve-option1": [0.3, 0.3]}
    sim = pd.concat([_sim(20.0, ranked), _sim(30.0, ranked)])
    real = pd.concat([_real(20.0, [0.5, 0.3, 0.1]), _real(30.0, [1.0, 1.0, 1.0], failed=[1.0, 1.0, 1.0])])
    c = svf.compare(sim, real, n_boot=100, seed=0)
    assert c.levels.set_index("level")["real_rules_differ"].to_dict() == {20.0: True, 30.0: False}
    pool = svf.pooled(c, n_boot=100, seed=0).set_index("levels")
    assert pool.loc["all", "units_regret_at_1"] == 2
    assert pool.loc["all", "regret_at_1"] == pytest.approx(0.4 / 2)  # regret 0 at level 30
    assert pool.loc["real rules differ", "units_regret_at_1"] == 1
    assert pool.loc["real rules differ", "regret_at_1"] == pytest.approx(0.4)


def test_first_maps_are_the_first_posed_frames():
    def log(sequence, level, run, start):
        posed = [0.0] * 5 if start is not None else []
        frames = pd.DataFrame({"vis_px": [np.nan] * (start if start is not None else 10) + posed})
        return SimpleNamespace(meta={"sequence": sequence, "disturbance": "blur", "level": level, "run": run},
                               frames=frames)  # fmt: skip

    logs = [
        log("V1_01", 20, 0, 80),
        log("V1_01", 20, 1, 90),
        log("V2_01", 20, 0, None),
        log("V2_01", 20, 1, 3),
    ]
    table = svf.first_maps(logs).set_index("sequence")
    assert table.loc["V101", "sim_first_map"] == 85 and table.loc["V101", "sim_started"] == 1.0
    # a run that never posed a frame is left out of the mean, and counted in the share
    assert table.loc["V201", "sim_first_map"] == 3 and table.loc["V201", "sim_started"] == 0.5


def test_the_rendered_scene_is_the_renders():
    """The real front-end ran on `jsve render`'s images: the simulator's rendered scene has their texture
    (fitted) and their 8 ms exposure; the camera-image scene is the default."""
    rendered, camera = svf.VARIANTS[svf.RENDERED], svf.VARIANTS[svf.CAMERA]
    assert rendered.scene.texture_scale == RENDERED_TEXTURE_SCALE
    assert rendered.scene.exposure_s == 0.008 and camera.scene == SceneProfile()
    assert rendered.imu == camera.imu == ImuNoise.datasheet()


def test_settings_spec_is_read_back_by_the_simulator():
    real = pd.concat([_real(20.0, [0.1] * 3), _real(35.0, [0.1] * 3)])
    real = pd.concat([real, real.assign(disturbance="none", level=0.0), real.assign(disturbance="occlusion")])
    got = {(s.disturbance, s.level) for s in settings(svf.settings_spec(real))}
    assert got == {("blur", 20.0), ("blur", 35.0), ("none", 0.0), ("occlusion", 20.0), ("occlusion", 35.0)}
