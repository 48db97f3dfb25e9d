"""jsve.evaluation._evaluate and the `jsve evaluate` / `jsve sve` commands.

The oracle for `evaluate` is the composition of its parts run one run at a time (replay of a
one-run batch, then `run_error` on that run): chunking, bucketing and padding must not change a
single number. The CLI tests check the files it writes against the library functions.
"""

from __future__ import annotations

import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from logfactory import make_run

import jsve
from jsve.cli import main as jsve_main
from jsve.evaluation import _evaluate
from jsve.evaluation._evaluate import TABLE_COLUMNS
from jsve.io._batching import meta_columns
from jsve.io._logs import write_log


@pytest.fixture(scope="module")
def runs():
    # Lengths straddle the 64-frame padding multiple so buckets and padding are exercised: three buckets
    # (jsve.buckets), of one run (exactly 64 frames), three runs (130-183, padded to 192) and two (200, 210:
    # 256). Every test compiles its computations once per bucket, so three buckets, not more.
    lengths = [150, 210, 200, 183, 64, 130]
    return [
        make_run(n, seed=10 + i, run=i, disturbance="blur" if i % 2 else "none", level=5 * (i % 3))
        for i, n in enumerate(lengths)
    ]


def _one_run_oracle(run, rule, align="se3"):
    """Replay a one-run batch and score it with run_error directly (no chunking, no buckets)."""
    batch = jsve.from_runs([run], dtype=jnp.float32).batch
    result = jax.jit(jsve.replay)(batch, rule)
    n = len(run.frames)
    # The saved trajectory: one segment, failed below the default coverage floor.
    err = jsve.run_error(
        result.position[0], result.quaternion[0], result.in_trajectory[0], jnp.zeros_like(result.segment[0]),
        batch.gt_p[0], batch.gt_q[0], batch.gt_valid[0], batch.valid[0], align=align, min_coverage=0.5,
    )  # fmt: skip
    return err, bool(result.lost_any[0]), float(np.sum(np.asarray(result.accepted[0])[:n])) / n


@pytest.mark.parametrize("rule_name", ["orbslam3", "sve-option2"])
def test_evaluate_equals_per_run_composition(runs, rule_name):
    rule = jsve.preset(rule_name)
    table = jsve.evaluate(jsve.buckets(runs), rule, rule_name=rule_name, runs_per_chunk=2, progress=False)
    assert sorted(table["run_id"]) == sorted(r.run_id for r in runs)  # every run, exactly once
    by_id = table.set_index("run_id")
    for run in runs:
        err, lost_any, accepted = _one_run_oracle(run, rule)
        row = by_id.loc[run.run_id]
        assert row["count"] == int(err.stats.count)
        if row["count"] > 0:
            # Same float32 kernels on the same frames; padding (zero weight) may reorder sums.
            np.testing.assert_allclose(row["rmse"], float(err.stats.rmse), rtol=1e-5)
        assert row["lost_any"] == lost_any
        assert row["failed"] == bool(err.failed)  # a loss of tracking fails a run only under "strict"
        np.testing.assert_allclose(row["accepted_fraction"], accepted, rtol=1e-6)
        assert row["rule"] == rule_name
        assert row["n_frames"] == len(run.frames)
    # the columns `jsve evaluate --by` is checked against before it replays anything
    assert list(table.columns) == meta_columns([r.meta for r in runs]) + list(TABLE_COLUMNS)


def test_chunk_size_does_not_change_results(runs):
    rule = jsve.preset("orbslam3")
    groups = jsve.buckets(runs)
    a = jsve.evaluate(groups, rule, runs_per_chunk=1, progress=False)
    b = jsve.evaluate(groups, rule, runs_per_chunk=64, progress=False)
    pd.testing.assert_frame_equal(a, b)


def test_a_pass_gives_memory_back_where_the_frame_length_changes(runs, monkeypatch):
    """evaluate_rules drops JAX's executables (jsve._memory.release_memory) where the next bucket has
    another frame length and the process holds too much, never between two buckets of one length and
    never when it holds little; the results are those of a pass that keeps everything."""

    rules = [("orbslam3", jsve.preset("orbslam3")), ("sve-option2", jsve.preset("sve-option2"))]
    groups = jsve.buckets(runs)
    lengths = [g.batch.n_frames for g in groups]
    assert len(set(lengths)) >= 2
    stream = groups + groups[-1:]  # the last length twice in a row: no release between them
    kept = _evaluate.evaluate_rules(stream, rules, progress=False)
    released = []
    monkeypatch.setattr(_evaluate, "release_memory", lambda: released.append(1))
    monkeypatch.setattr(_evaluate, "_holds_too_much", lambda: True)
    again = _evaluate.evaluate_rules(stream, rules, progress=False)
    stream_lengths = [g.batch.n_frames for g in stream]
    changes = sum(a != b for a, b in zip(stream_lengths, stream_lengths[1:], strict=False))
    assert len(released) == changes >= 1
    pd.testing.assert_frame_equal(again, kept)
    monkeypatch.setattr(_evaluate, "_holds_too_much", lambda: False)
    released.clear()
    _evaluate.evaluate_rules(stream, rules, progress=False)
    assert released == []


def test_accept_all_rule_scores_the_visual_estimate(runs):
    """With thresholds that accept every frame the replay is the logged visual trajectory, so the
    APE must equal evo-style scoring of vis_* against gt_* (here: jsve.align + ape_statistics)."""
    rule = jsve.InlierRule(jsve.Thresholds(imu_init=-1, not_init=-1, reloc=-1, recovery=-1))
    table = jsve.evaluate(jsve.buckets(runs), rule, progress=False).set_index("run_id")
    for run in runs:
        f = run.frames
        est = jnp.asarray(f[["vis_px", "vis_py", "vis_pz"]].to_numpy(), jnp.float32)
        ref = jnp.asarray(f[["gt_px", "gt_py", "gt_pz"]].to_numpy(), jnp.float32)
        mask = jnp.ones(len(f), bool)
        aligned, _, _ = jsve.align(est, ref, mask, method="se3")
        stats = jsve.ape_statistics(aligned, ref, mask)
        row = table.loc[run.run_id]
        assert row["accepted_fraction"] == 1.0 and not row["lost_any"] and row["coverage"] == 1.0
        np.testing.assert_allclose(row["rmse"], float(stats.rmse), rtol=1e-5)


@pytest.fixture(scope="module")
def log_dir(runs, tmp_path_factory):
    folder = tmp_path_factory.mktemp("logs")
    for run in runs:
        write_log(run, folder / f"{run.run_id.replace('/', '_')}.csv")
    return folder


def test_cli_evaluate_writes_tables_matching_the_library(runs, log_dir, tmp_path, capsys):
    out = tmp_path / "out"
    code = jsve_main(["evaluate", str(log_dir), "--rule", "orbslam3", "--rule", "sve-option2", "-o", str(out),
                      "--no-progress", "--by", "disturbance,rule"])  # fmt: skip
    assert code == 0
    per_run = pd.read_parquet(out / "runs.parquet")
    summary = pd.read_csv(out / "summary.csv")
    assert len(per_run) == 2 * len(runs)
    assert set(summary["rule"]) == {"orbslam3", "sve-option2"}
    lib = jsve.evaluate(jsve.buckets(runs), jsve.preset("orbslam3"), rule_name="orbslam3", progress=False)
    cli = per_run[per_run["rule"] == "orbslam3"].set_index("run_id").loc[lib["run_id"]]
    np.testing.assert_allclose(cli["rmse"].to_numpy(), lib["rmse"].to_numpy(), rtol=1e-6)
    # The on-screen summary lists every (disturbance, rule) group, then the failed runs of each rule
    # per failure_reason: the counts of runs.parquet's rows.
    printed, failures = capsys.readouterr().out.split("\n\nfailed runs by failure_reason:\n")
    assert printed.count("sve-option2") == summary["rule"].eq("sve-option2").sum()
    header, *lines = failures.splitlines()
    assert header.split() == ["rule", "n_runs", "failure_reason"]
    shown = [tuple(line.split(maxsplit=2)) for line in lines]
    failed = per_run[per_run["failed"]]
    expected = failed.groupby(["rule", "failure_reason"]).size()
    assert sorted(shown) == sorted((r, str(n), why) for (r, why), n in expected.items())
    assert sum(int(n) for _, n, _ in shown) == summary["n_failed"].sum() > 0
    assert not list(out.glob("*.partial"))
    # The summary leads with the objective the fit minimises, then failures and coverage; never the mean
    # ATE over all runs (a failed run's tracked part), only the ATE of the runs that did not fail.
    table, legend = printed.split("\n\n")
    header, *rows = table.splitlines()
    assert header.split()[:5] == ["disturbance", "rule", "runs", "objective", "m"]
    assert (
        "ATE ok m" in header and "rmse_mean_all" not in printed and legend.startswith("objective: the mean")
    )
    pattern = re.compile(
        r"^(\S+)\s+(\S+)\s+(\d+)\s+([\d.]+)\s+(\d+) %\s+(\d+) %\s+(\d+) %\s+([\d.]+|-)\s+(\d+)"
    )
    seen = {}
    for row in rows:
        disturbance, rule, n_runs, objective, failed, _, coverage, ate_ok, n_ok = pattern.match(row).groups()
        seen[disturbance, rule] = (int(n_runs), float(objective), int(failed), int(n_ok))
    for r in summary.itertuples():
        n_runs, objective, failed, n_ok = seen[str(r.disturbance), r.rule]
        assert (n_runs, n_ok) == (r.n_runs, r.n_runs - r.n_failed)
        assert objective == pytest.approx(r.objective, abs=5e-5) and failed == round(100 * r.failure_rate)
        charged = per_run[(per_run["disturbance"] == r.disturbance) & (per_run["rule"] == r.rule)]
        loss = np.where(charged["failed"] | (charged["unsupported_fraction"] > 0), 1.0, charged["rmse"])
        assert r.objective == pytest.approx(loss.mean(), rel=1e-12)  # 1 m, the default penalty


def test_cli_evaluate_rule_file_round_trip(runs, log_dir, tmp_path):
    rule = jsve.preset("sve-eq1")
    path = tmp_path / "eq1.json"
    path.write_text(json.dumps(jsve.rule_to_dict(rule)))
    out = tmp_path / "o"
    assert jsve_main(["evaluate", str(log_dir), "--rule", str(path), "-o", str(out), "--no-progress"]) == 0
    from_file = pd.read_csv(out / "runs.csv").set_index("run_id")
    lib = jsve.evaluate(jsve.buckets(runs), rule, progress=False).set_index("run_id")
    np.testing.assert_allclose(from_file.loc[lib.index, "rmse"], lib["rmse"], rtol=1e-6)
    assert set(from_file["rule"]) == {"eq1"}


def test_cli_evaluate_records_its_settings_and_rules_for_the_report(runs, log_dir, tmp_path):
    """`jsve evaluate -o` writes evaluation.json: the penalty, support policy, alignment, switch model and
    every rule it scored with (a rule file's parameters too), which `jsve report DIR` then scores and
    names instead of jsve's defaults."""
    from jsve.core._rules import rule_from_dict, rule_params
    from jsve.evaluation import read_evaluation_record

    rule = jsve.preset("sve-eq1")
    path = tmp_path / "eq1.json"
    path.write_text(json.dumps(jsve.rule_to_dict(rule)))
    out = tmp_path / "o"
    argv = ["evaluate", str(log_dir), "--rule", "orbslam3", "--rule", str(path), "-o", str(out),
            "--no-progress", "--failure-penalty", "0.25", "--support", "exclude", "--align", "sim3",
            "--switch-model", "imu-coast", "--min-coverage", "0.5", "--n-to-align", "40",
            "--by", "disturbance,rule"]  # fmt: skip
    assert jsve_main(argv) == 0
    record = read_evaluation_record(out)
    assert (record.failure_penalty, record.support, record.align, record.switch_model) == (
        0.25, "exclude", "sim3", "imu-coast",
    )  # fmt: skip
    assert (record.min_coverage, record.n_to_align, record.by, record.logs) == (
        0.5, 40, ("disturbance", "rule"), str(log_dir),
    )  # fmt: skip
    assert [(r.name, r.file) for r in record.rules] == [("orbslam3", None), ("eq1", str(path))]
    back = rule_from_dict(record.rules[1].rule)
    assert {k: float(v) for k, v in rule_params(back).items()} == pytest.approx(
        {k: float(v) for k, v in rule_params(rule).items()}
    )
    assert back.combination.inputs == rule.combination.inputs == "authors-eq1"
    assert jsve_main(["report", str(out)]) == 0
    md = (out / "report.md").read_text()
    assert "a failed run charged 0.25 m, a run out of the log's support left out" in md
    assert "under the switch model `imu-coast` and Sim(3) alignment" in md
    assert "| eq1 | " + str(path) + " | sve |" in md and "inputs authors-eq1" in md


def test_cli_evaluate_errors(log_dir, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"kind": "sve",\n "thresholds": }')
    assert jsve_main(["evaluate", str(log_dir), "--rule", str(bad), "--no-progress"]) == 2
    assert f"{bad}:2: not valid JSON" in capsys.readouterr().err
    incomplete = tmp_path / "incomplete.json"
    incomplete.write_text(json.dumps({"kind": "inliers", "thresholds": {"imu_init": 15}}))
    assert jsve_main(["evaluate", str(log_dir), "--rule", str(incomplete), "--no-progress"]) == 2
    assert "lacks key 'not_init'" in capsys.readouterr().err
    assert jsve_main(["evaluate", str(log_dir), "--rule", "no-such-preset", "--no-progress"]) == 2
    assert "neither a preset" in capsys.readouterr().err


def test_cli_evaluate_refuses_an_unknown_by_key_before_replaying(log_dir, monkeypatch, capsys):
    """The --by keys are checked against the table's columns (the logs' metadata and what evaluate
    writes) before any rule is replayed: a typo costs nothing."""
    monkeypatch.setattr(_evaluate, "evaluate_rules", lambda *a, **k: pytest.fail("evaluated before refusing"))
    argv = ["evaluate", str(log_dir), "--rule", "orbslam3", "--by", "disturbance,weather", "--no-progress"]
    assert jsve_main(argv) == 2
    err = capsys.readouterr().err
    assert "--by keys ['weather'] are not metadata of these logs" in err
    assert "disturbance" in err.split("known:")[1] and "rule" in err.split("known:")[1]


def test_cli_evaluate_refuses_logs_without_ground_truth(tmp_path, capsys):
    write_log(make_run(120, seed=3, with_gt=False), tmp_path / "r.csv")
    assert jsve_main(["evaluate", str(tmp_path), "--no-progress"]) == 2
    assert "no ground truth" in capsys.readouterr().err


def test_cli_sve_matches_sve_table(runs, log_dir, tmp_path):
    run = runs[3]
    log = log_dir / f"{run.run_id.replace('/', '_')}.csv"
    out = tmp_path / "sve.csv"
    assert jsve_main(["sve", str(log), "-o", str(out)]) == 0
    table = pd.read_csv(out)
    f = run.frames
    bins = f[list(jsve.io.schema.BIN_COLUMNS)].to_numpy()
    counts = (f[name].to_numpy() for name in ("n_extracted", "n_inliers", "n_frustum"))  # arrays, as the CLI
    expected = jsve.sve_table(*counts, bins, n_features=run.meta["n_features"])
    assert table["t_ns"].tolist() == f["t_ns"].tolist()  # int64 stamps exact
    for name, values in expected.items():
        np.testing.assert_allclose(table[name], np.asarray(values), rtol=1e-6, atol=1e-7, err_msg=name)


def test_cli_sve_bad_log(tmp_path, capsys):
    path = tmp_path / "empty.csv"
    path.write_text("")
    assert jsve_main(["sve", str(path)]) == 2
    assert str(path) in capsys.readouterr().err


def test_evaluate_batch_checks_the_rule_on_the_host(runs):
    # The compiled computation carries no traced check (it would keep it out of JAX's persistent cache),
    # so a combination made undefined behind the constructor's back is refused before compiling.
    import equinox as eqx

    from jsve.evaluation._evaluate import evaluate_batch

    batch = jsve.from_runs(runs[:2]).batch
    bad = eqx.tree_at(lambda r: r.combination.p, jsve.preset("sve-option1"), jnp.asarray(0.5))
    with pytest.raises(ValueError, match=r"needs p = 1, got 0\.5"):
        evaluate_batch(batch, bad)
    assert evaluate_batch(batch, jsve.preset("sve-option1")).failed.shape == (2,)
