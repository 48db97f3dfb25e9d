"""`jsve tune` end to end on the simulator's front-end (jsve.tuning): the study file, every file of the
folder and what its numbers must equal, resuming with nothing repeated, a folder of another study
refused, and a tuning killed with SIGKILL and resumed that ends as an uninterrupted one."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from jsve.io._resume import StaleOutputError
from jsve.tuning import TuneStudy, paired_difference, tune

STUDY = """
[tune]
frontend = "simulator"
family = "sve"
switch_model = "imu-coast"
train = ["proc_00:blur=25", "proc_01:occlusion=300"]
heldout = ["proc_02:blur=25"]
seeds_per_round = 2
min_seeds = 2
max_rounds = 2
verify_seeds = 3
budget = 100
design = 16
shortlist = 4
perturbations = 1
flight_s = 10.0
"""


def _study(folder: Path, text: str = STUDY) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (path := folder / "study.toml").write_text(text)
    return path


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    root = tmp_path_factory.mktemp("tune")
    study = TuneStudy.from_toml(_study(root))
    state = tune(study, root / "out", progress=False)
    return root, study, state


def test_the_study_file_names_its_errors(tmp_path):
    with pytest.raises(ValueError, match=r"study.toml: unknown key 'seeds'"):
        TuneStudy.from_toml(_study(tmp_path, STUDY + "seeds = 3\n"))
    with pytest.raises(ValueError, match="verify_seed_base 3 overlaps"):
        TuneStudy.from_toml(_study(tmp_path, STUDY + "verify_seed_base = 3\n"))
    with pytest.raises(ValueError, match="'sve-option9' is not a preset"):
        TuneStudy.from_toml(_study(tmp_path, STUDY + 'baselines = ["sve-option9"]\n'))
    with pytest.raises(ValueError, match="needs build, vocabulary, settings"):
        TuneStudy.from_toml(_study(tmp_path, STUDY.replace('"simulator"', '"orbslam3"')))


def test_paths_are_read_from_the_root_and_the_study_file(tmp_path):
    text = STUDY.replace('"simulator"', '"orbslam3"').replace('"proc_00:blur=25"', '"d/a"')
    text = text.replace('"proc_01:occlusion=300"', '"d/b"').replace('"proc_02:blur=25"', '"d/c"')
    text += 'build = "b"\nvocabulary = "voc.txt"\nsettings = "s.yaml"\n'
    study = TuneStudy.from_toml(_study(tmp_path / "sweeps", text), root=tmp_path / "data")
    assert study.train == (str(tmp_path / "data" / "d" / "a"), str(tmp_path / "data" / "d" / "b"))
    assert study.vocabulary == str(tmp_path / "data" / "voc.txt")
    assert study.settings == str(tmp_path / "sweeps" / "s.yaml")


def test_a_held_out_sequence_may_not_be_trained_on(tmp_path):
    study = TuneStudy.from_toml(_study(tmp_path, STUDY.replace("proc_02:blur=25", "proc_00:occlusion=300")))
    with pytest.raises(ValueError, match="held-out sequence proc_00 is also trained on"):
        tune(study, tmp_path / "out", progress=False)


def test_every_rule_raced_or_chosen_is_kept_and_every_run_has_one_row(tuned):
    root, study, state = tuned
    out = root / "out"
    runs = pd.read_csv(out / "runs.csv")
    assert not runs.duplicated(["candidate", "switch_model", "dataset", "seed"]).any()
    assert runs["loss_m"].notna().all() and len(runs) == state["runs_used"] <= study.budget
    raced = {c["name"] for r in state["rounds"] for c in r["candidates"]}
    assert raced <= {p.stem for p in (out / "rules").glob("*.json")}
    assert {"orbslam3", "sve-option2"} <= {p.stem for p in (out / "rules").glob("*.json")}
    assert json.loads((out / "tuned_rule.json").read_text()) == json.loads(
        (out / "rules" / f"{state['tuned']}.json").read_text()
    )
    check = runs[runs.seed >= study.verify_seed_base]
    assert len(check) == study.check_runs  # the tuned rule and both baselines on every held-out run
    assert json.loads((out / "progress.json").read_text())["phase"] == "done"


def test_the_check_is_the_paired_difference_of_the_kept_runs(tuned):
    root, study, state = tuned
    runs = pd.read_csv(root / "out" / "runs.csv")
    check = pd.read_csv(root / "out" / "check.csv")
    held = runs[runs.seed >= study.verify_seed_base].assign(
        candidate=lambda t: t.candidate + "@" + t.switch_model
    )
    for row in check[check.scope == "all held-out"].itertuples():
        again = paired_difference(held, row.rule, row.baseline)
        assert row.pairs == again["pairs"] == len(study.heldout) * study.verify_seeds
        assert row.mean_diff_m == pytest.approx(again["mean_diff_m"])


def test_the_replay_of_the_incumbents_own_logs_predicts_its_runs(tuned):
    # the simulator's run of a rule is the replay of its log: prediction and run must agree exactly,
    # so a mismatch is a defect of the pairing of predictions with runs
    root, study, state = tuned
    runs = pd.read_csv(root / "out" / "runs.csv").set_index(["candidate", "dataset", "seed"])
    pred = pd.read_csv(root / "out" / "rounds" / "0" / "predictions.csv")
    both = pred.join(runs["loss_m"], on=["candidate", "dataset", "seed"], how="inner")
    assert len(both) >= len(study.train) * study.seeds_per_round
    assert np.allclose(both["predicted_loss_m"], both["loss_m"], atol=1e-6)


def test_a_resumed_tuning_repeats_no_run_and_decides_the_same(tuned, capsys):
    root, study, state = tuned
    again = tune(study, root / "out", progress=True)
    assert "(0 made now)" in capsys.readouterr().err
    assert again["rounds"] == state["rounds"] and again["check"] == state["check"]


def test_a_folder_of_another_study_is_refused_unless_forced(tuned, tmp_path):
    root, study, _ = tuned
    other = TuneStudy.from_toml(
        _study(tmp_path, STUDY.replace("alpha", "alpha").replace("design = 16", "design = 8"))
    )
    with pytest.raises(StaleOutputError):
        tune(other, root / "out", progress=False)
    bigger = TuneStudy.from_toml(_study(tmp_path / "b", STUDY.replace("budget = 100", "budget = 120")))
    assert bigger.digest() == study.digest()  # more budget resumes the same tuning


@pytest.mark.slow
def test_a_tuning_killed_at_a_random_moment_resumes_to_the_uninterrupted_result(tuned, tmp_path):
    root, study, state = tuned
    path = _study(tmp_path)
    out = tmp_path / "out"
    command = [sys.executable, "-m", "jsve.cli", "tune", str(path), "-o", str(out), "--no-progress"]
    rng = np.random.default_rng(int(time.time()))
    target = int(rng.integers(1, state["runs_used"] - 1))
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while proc.poll() is None and len(list((out / "runs").rglob("*.summary.json"))) < target:
            time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    resumed = subprocess.run(command, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    key = ["candidate", "switch_model", "dataset", "seed"]
    mine = pd.read_csv(out / "runs.csv").drop(columns="log").sort_values(key).reset_index(drop=True)
    theirs = (
        pd.read_csv(root / "out" / "runs.csv").drop(columns="log").sort_values(key).reset_index(drop=True)
    )
    pd.testing.assert_frame_equal(mine, theirs)
    final = json.loads((out / "tune.json").read_text())
    assert final["rounds"] == state["rounds"] and final["tuned"] == state["tuned"]
    assert not list(out.rglob("*.tmp")) and not list(out.rglob("*.partial"))


def test_the_report_opens_with_the_tuned_rule_and_its_held_out_differences(tuned, tmp_path):
    from jsve.report import write_report

    root, study, state = tuned
    written = write_report(root / "out", output=tmp_path / "report")
    md = written["markdown"].read_text()
    assert md.index("## Headline") < md.index("## Held-out check") < md.index("## The race")
    assert f"Tuned **{state['tuned']}**" in md
    for baseline in ("orbslam3@orbslam3", "sve-option2@orbslam3"):
        assert f"vs `{baseline}` on {len(study.heldout) * study.verify_seeds} held-out runs" in md
    assert (tmp_path / "report" / "figures" / "check.png").is_file()
    assert "Runs spent: " + str(state["runs_used"]) in md


def test_an_unfinished_tuning_has_no_report(tuned, tmp_path):
    from jsve.report import write_report

    root, _, _ = tuned
    (tmp_path / "tune.json").write_text(json.dumps({"status": "running"}))
    with pytest.raises(ValueError, match="has not finished"):
        write_report(tmp_path)


def test_with_record_the_proposals_replay_the_record_rules_logs(tmp_path):
    study = TuneStudy.from_toml(
        _study(tmp_path, STUDY.replace("max_rounds = 2", "max_rounds = 1") + "record = true\n")
    )
    state = tune(study, tmp_path / "out", progress=False)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    recorded = runs[runs.candidate == "record"]
    assert len(recorded) == len(study.train) * study.seeds_per_round
    pred = pd.read_csv(tmp_path / "out" / "rounds" / "0" / "predictions.csv")
    assert set(zip(pred.dataset, pred.seed, strict=True)) == set(
        zip(recorded.dataset, recorded.seed, strict=True)
    )
    assert "record" not in {c["name"] for c in state["rounds"][0]["candidates"]}  # recorded, never raced


def _tune_summary():
    """analysis/tune_summary.py, imported by path: analysis/ is a folder of scripts, not a package."""
    path = Path(__file__).resolve().parents[1] / "analysis" / "tune_summary.py"
    spec = importlib.util.spec_from_file_location("analysis_tune_summary", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_pooled_summary_counts_each_run_once_and_finds_no_bias_where_a_run_is_the_replay(
    tuned, tmp_path, capsys
):
    # On the simulator a rule's run is the replay of its log, so the replay's prediction of every raced
    # candidate is its measured difference: the pooled bias is 0. Two tunings sharing one pool (a copy
    # of the folder) use every run twice and the machine made each once.
    root, study, state = tuned
    summary = _tune_summary()
    out = tmp_path / "out"
    for name in ("a", "b"):
        shutil.copytree(root / "out", out / name)
    assert summary.main([str(out), "--csv-prefix", str(tmp_path / "tables" / "tune")]) == 0
    printed = capsys.readouterr().out
    runs = pd.read_csv(root / "out" / "runs.csv")
    assert f"runs: {len(runs)} distinct over 2 tunings ({2 * len(runs)} uses)" in printed
    agreement = pd.read_csv(tmp_path / "tables" / "tune_agreement.csv")
    assert len(agreement) == 2 * len(pd.read_csv(root / "out" / "agreement.csv")) > 0
    pooled = summary.pooled_agreement(agreement)
    assert pooled["candidates"] == len(agreement)
    assert abs(pooled["bias_mean_m"]) < 1e-6 and pooled["bias_sd_m"] < 1e-6
    if agreement["predicted_diff_m"].nunique() > 1:
        assert pooled["spearman"] == pytest.approx(1.0)
    else:
        assert np.isnan(pooled["spearman"])  # undefined for a constant prediction, never 0


def test_a_finished_tuning_given_more_check_seeds_runs_those_alone(tuned, tmp_path):
    """--verify-seeds on a finished tuning: its rounds replay from its runs (the same race, the same
    tuned rule), the budget moves by the check's new runs, and only those are made: every arm on every
    held-out dataset for each new seed; the check then holds the pairs of every seed."""
    root, study, state = tuned
    shutil.copytree(root / "out", tmp_path / "out")
    wider = study.with_check_seeds(study.verify_seeds + 2)
    assert wider.budget - wider.check_runs == study.budget - study.check_runs
    again = tune(wider, tmp_path / "out", progress=False)
    assert again["rounds"] == state["rounds"] and again["tuned"] == state["tuned"]
    arms = 1 + len(study.baseline_pairs)
    assert again["runs_used"] == state["runs_used"] + 2 * arms * len(study.heldout)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    before = pd.read_csv(root / "out" / "runs.csv")
    keys = ["candidate", "switch_model", "dataset", "seed"]
    new = runs.merge(before[keys], on=keys, how="left", indicator=True).query("_merge == 'left_only'")
    assert set(new.seed) == set(wider.check_seeds) - set(study.check_seeds)
    row = next(r for r in again["check"] if r["scope"] == "all held-out")
    assert row["pairs"] == len(study.heldout) * wider.verify_seeds
    with pytest.raises(ValueError, match="verify_seeds must be >= 1"):
        study.with_check_seeds(0)
