"""Rules run in the loop as a Scorer (jsve.tuning._frontend): the bounded loss of a finished run, names
that follow the rule, and the ORB-SLAM3 front-end's runs (a stand-in driver with the real driver's
options and files, as in test_frontend_resume): where each run goes, the seed and rule it is given, and
that a run in the pool is found again, never repeated."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_frontend_resume import make_fake_build
from test_frontend_run import SETTINGS, make_dataset

from jsve.core._rules import preset, rule_from_dict, rule_to_dict
from jsve.tuning._frontend import (
    Candidate,
    FrontendScorer,
    Instance,
    OrbSlam3Frontend,
    Request,
    candidate_name,
    parse_setting,
    run_row,
)


def test_a_tracked_run_costs_its_ate_capped_at_the_penalty():
    ok = {"outcome": "ok", "saved_coverage": 0.9, "ate_from_log_m": 0.031, "events": {"reset": 1, "loop": 2}}
    row = run_row(ok, penalty_m=1.0, min_coverage=0.5)
    assert (row["failed"], row["loss_m"], row["resets"], row["loops"]) == (False, 0.031, 1, 2)
    assert run_row({**ok, "ate_from_log_m": 3.2}, 1.0, 0.5)["loss_m"] == 1.0  # diverged: what a failure costs


@pytest.mark.parametrize(
    "summary",
    [
        {"outcome": "SIGSEGV", "saved_coverage": 0.9, "ate_from_log_m": 0.03},  # crashed after saving
        {"outcome": "ok", "saved_coverage": 0.3, "ate_from_log_m": 0.01},  # saved too little
        {"outcome": "ok", "saved_coverage": None, "ate_from_log_m": None},  # saved nothing
        {"outcome": "ok", "saved_trajectory_error": "run_000.csv: bad"},  # nothing jsve could score
        {},  # no summary at all
    ],
)
def test_a_run_without_a_scored_trajectory_fails_and_costs_the_penalty(summary):
    row = run_row(summary, penalty_m=1.0, min_coverage=0.5)
    assert row["failed"] and row["loss_m"] == 1.0


def test_presets_keep_their_names_and_other_rules_are_named_by_content():
    assert candidate_name(preset("sve-option2")) == "sve-option2"
    spec = rule_to_dict(preset("sve-option2"))
    spec["thresholds"]["imu_init"] = 0.07
    name = candidate_name(rule_from_dict(spec))
    assert name.startswith("sve-") and len(name) == 12
    assert candidate_name(rule_from_dict(json.loads(json.dumps(spec)))) == name
    spec["thresholds"]["imu_init"] = 0.071
    assert candidate_name(rule_from_dict(spec)) != name


def test_simulator_datasets_are_sequence_and_setting():
    assert parse_setting("proc_00") == ("proc_00", "none", 0.0)
    assert parse_setting("proc_01:blur=25") == ("proc_01", "blur", 25.0)
    with pytest.raises(ValueError, match="proc_01:blur"):
        parse_setting("proc_01:blur")


@pytest.fixture
def loop(tmp_path, monkeypatch):
    """A stand-in build, one dataset, a vocabulary and settings; the driver's starts go to a ledger."""
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    ledger = tmp_path / "ledger.txt"
    monkeypatch.setenv("FAKE_LEDGER", str(ledger))
    frontend = OrbSlam3Frontend(tmp_path / "pool", make_fake_build(tmp_path / "build"), voc, settings,
                                check_base=1000, workers=2)  # fmt: skip
    return frontend, str(ds), ledger


def _starts(ledger):
    return [line.split()[1] for line in ledger.read_text().splitlines() if line.startswith("start")]


def test_each_run_goes_to_its_rule_model_and_seed_and_is_made_once(loop):
    frontend, ds, ledger = loop
    instances = [Instance(ds, 0), Instance(ds, 2), Instance(ds, 1001)]
    rows = []
    scorer = FrontendScorer(frontend, instances, "imu-coast", 1.0, 0.5, rows.append)
    result = scorer.score_candidates([Candidate.preset("orbslam3"), Candidate.preset("sve-option2")])
    assert result.loss.shape == (2, 3)
    assert len(_starts(ledger)) == 6
    made = {p.relative_to(frontend.pool).as_posix(): json.loads(p.read_text())["seed"]
            for p in frontend.pool.rglob("run_*.summary.json")}  # fmt: skip
    level = "V101/none-0"
    assert made == {
        f"seeds-0/{level}/{rule}-imu-coast/run_{k:03d}.summary.json": k
        for rule in ("orbslam3", "sve-option2")
        for k in (0, 2)
    } | {
        f"seeds-1000/{level}/{rule}-imu-coast/run_001.summary.json": 1001
        for rule in ("orbslam3", "sve-option2")
    }
    # the stand-in saves no trajectory: every run fails and costs the penalty, none is dropped
    assert result.failed.all() and np.all(result.loss == 1.0) and len(rows) == 6
    again = FrontendScorer(frontend, instances, "imu-coast", 1.0, 0.5)
    again.score_candidates([Candidate.preset("sve-option2")], runs=[0, 2])
    assert len(_starts(ledger)) == 6  # found in the pool
    assert again.meter.setting_runs == 2


def test_stock_orbslam3_runs_without_rule_arguments_in_the_level_folder(loop, monkeypatch):
    frontend, ds, ledger = loop
    stock = Request(Candidate.preset("orbslam3"), "orbslam3", Instance(ds, 1))
    job, _ = frontend._plan(stock)
    assert job.rule_args == () and job.seed == 1
    coasting, _ = frontend._plan(Request(Candidate.preset("orbslam3"), "imu-coast", Instance(ds, 1)))
    assert coasting.rule_args[0] == "--rule-inliers" and coasting.rule_args[-1] == "--coast"
    FrontendScorer(frontend, [Instance(ds, 1)], "orbslam3", 1.0, 0.5).score_candidates(
        [Candidate.preset("orbslam3")]
    )
    assert len(_starts(ledger)) == 1
    (summary,) = frontend.pool.rglob("run_*.summary.json")
    assert summary == frontend.pool / "seeds-0" / "V101" / "none-0" / "run_001.summary.json"
