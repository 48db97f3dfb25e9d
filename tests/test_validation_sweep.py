"""sweeps/validate_replay.py: the order of the validation's commands (recordings, then fits on their replays,
then the rules in the loop) and the shipped config. No front-end runs here (.ci/frontend-smoke)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _sweep():
    spec = importlib.util.spec_from_file_location("validate_replay", ROOT / "sweeps" / "validate_replay.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


CONFIG = {
    "build": "B", "vocabulary": "v.txt", "settings": "s.yaml", "output": "logs", "runs": 3,
    "datasets": ["V101", "V201/blur-30"], "switch_models": ["orbslam3", "imu-coast"],
    "rules": ["orbslam3", "fit/{switch_model}/fitted_sve.json"],
    "fit": {"output": "fit", "ground_truth": {"V201": "b.csv", "V101": "a.csv"}},
}  # fmt: skip


def test_recordings_come_first_then_the_fits_then_the_rules():
    jobs = _sweep().commands(CONFIG)
    kinds = [" ".join(cmd[:2]) if cmd[1] != "frontend" else cmd[cmd.index("--rule") + 1] for cmd in jobs]
    assert kinds == [
        "record", "record",
        "jsve ingest", "jsve fit", "jsve ingest", "jsve fit",
        "orbslam3", "fit/orbslam3/fitted_sve.json", "orbslam3", "fit/imu-coast/fitted_sve.json",
    ]  # fmt: skip
    ingest, fit = jobs[4], jobs[5]
    # the fit of a switch model replays that model's recordings, each sequence with its own ground truth
    assert ingest[2] == str(Path("logs/*/*/record-imu-coast/run_*.csv"))
    assert ingest[ingest.index("--gt") :] == ["--gt", "V101=a.csv", "--gt", "V201=b.csv", "--yes"]
    assert fit[2] == ingest[ingest.index("-o") + 1] and fit[fit.index("-o") + 1] == str(Path("fit/imu-coast"))
    assert fit[fit.index("--switch-model") + 1] == "imu-coast"
    for cmd in jobs[6:]:
        model = cmd[cmd.index("--switch-model") + 1]
        assert "{switch_model}" not in cmd[cmd.index("--rule") + 1] and cmd[3:5] == ["B", "V101"]
        assert cmd[cmd.index("--runs") + 1] == "3" and model in ("orbslam3", "imu-coast")


def test_without_a_fit_table_or_recordings_only_the_rules_run():
    config = {k: v for k, v in CONFIG.items() if k != "fit"} | {"record": False, "rules": ["sve-option2"]}
    jobs = _sweep().commands(config)
    assert [cmd[cmd.index("--rule") + 1] for cmd in jobs] == ["sve-option2", "sve-option2"]


def test_the_shipped_config_names_every_step():
    config = tomllib.loads((ROOT / "sweeps" / "validation.toml").read_text())
    jobs = _sweep().commands(config)
    rules = {cmd[cmd.index("--rule") + 1] for cmd in jobs if cmd[1] == "frontend"}
    assert {"record", "orbslam3", "sve-option2", "sve-option1"} <= rules
    assert any(rule.endswith("fitted_sve.json") for rule in rules)
    fitted = [cmd for cmd in jobs if cmd[:2] == ["jsve", "fit"]]
    assert len(fitted) == len(config["switch_models"])
    sequences = {d.split("/")[-1] if "/" not in d else d.split("/")[1] for d in config["datasets"]}
    assert sequences <= set(config["fit"]["ground_truth"])  # every sequence has its ground truth
