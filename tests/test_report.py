"""jsve.fit_study and jsve.report: a small study end to end, its tables, resumption and the report.

The report's numbers must be the tables' numbers; the HTML must be self-contained; rendering twice gives
the same bytes; a rerun with the same configuration skips finished stages and changes nothing.
"""

from __future__ import annotations

import json
import re
import time

import knownanswer as ka
import numpy as np
import pandas as pd
import pytest

from jsve.fit import FitConfig, FitData
from jsve.fit_study import StudyConfig, read_table, run_study
from jsve.objective import group_weights
from jsve.report import markdown_table, write_report

SMALL = StudyConfig(fit=FitConfig(n_search=64, n_starts=1, nm_steps=10), kfold=2, leave_one_out=("sequence",),
                    n_boot=100, n_local=32, heatmap=("imu_init", "recovery", 4))  # fmt: skip


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """A study over 12 occlusion runs (3 sequences x 2 levels x 2), with the report rendered."""
    out = tmp_path_factory.mktemp("study")
    runs = ka.make_study("occlusion", range(12), n_frames=300)
    data = FitData.from_runs(runs, SMALL.objective())
    started = time.perf_counter()
    stages = run_study(data, out, SMALL, progress=False, data_description={"source": "tests/knownanswer.py"})
    first = time.perf_counter() - started
    written = write_report(out, title="test report")
    return out, data, stages, first, written


def test_study_writes_every_table_as_parquet_and_csv(study):
    out, data, stages, _, _ = study
    names = ("runs_presets", "runs", "summary", "heldout", "cv_params", "heldout_summary", "params", "heatmap",
             "sve_levels")  # fmt: skip
    for name in names:
        parquet = pd.read_parquet(out / f"{name}.parquet")
        csv = pd.read_csv(out / f"{name}.csv")
        assert len(parquet) == len(csv) > 0, name
        numeric = parquet.select_dtypes("number").columns
        np.testing.assert_allclose(csv[numeric].to_numpy(float), parquet[numeric].to_numpy(float), rtol=1e-12,
                                   equal_nan=True, err_msg=name)  # fmt: skip
    assert set(stages) == {"evaluate_presets", "fit_sve", "fit_inliers", "evaluate_fitted", "cross_validation",
                           "parameter_bootstrap", "heatmap", "sve_levels"}  # fmt: skip
    assert not list(out.glob("*.partial")) and not list(out.glob("figures/*.partial"))
    runs = read_table(out, "runs")
    assert set(runs["rule"]) == {"orbslam3", "sve-eq1", "sve-option1", "sve-option2", "fitted-sve", "fitted-inliers"}
    assert (runs.groupby("rule").size() == data.n_runs).all()


def test_fitted_objective_is_the_evaluate_tables_penalised_mean(study):
    """The fit's recorded objective equals the group-weighted mean of jsve.evaluate's per-run table with
    failed runs at the penalty (float32: 1e-5 relative)."""
    out, data, _, _, _ = study
    runs = read_table(out, "runs")
    w = group_weights(data.meta)
    for family in ("sve", "inliers"):
        rec = json.loads((out / f"fitted_{family}.json").read_text())
        table = runs[runs["rule"] == f"fitted-{family}"].set_index("run_id").loc[data.meta["run_id"]]
        loss = np.where(table["failed"], SMALL.failure_penalty, table["rmse"])
        assert rec["objective"] == pytest.approx(np.sum(w * loss) / np.sum(w), rel=1e-5)


def test_rerun_skips_finished_stages_and_changes_nothing(study):
    out, data, _, first, written = study
    before = {p.name: p.read_bytes() for p in out.glob("*.parquet")}
    started = time.perf_counter()
    run_study(data, out, SMALL, progress=False, data_description={"source": "tests/knownanswer.py"})
    assert time.perf_counter() - started < 0.25 * first
    assert {p.name: p.read_bytes() for p in out.glob("*.parquet")} == before
    # another configuration (or other data) starts from scratch
    from jsve.fit_study import Stages, fingerprint

    record = json.loads((out / "stages.json").read_text())
    assert record["key"]["config"] == fingerprint(SMALL.to_dict()) and len(record["done"]) == 8
    changed = StudyConfig(**{**SMALL.__dict__, "failure_penalty": 2.0})
    assert Stages(out, fingerprint(changed.to_dict()), record["key"]["data"]).done == {}


def test_report_is_self_contained_deterministic_and_matches_the_tables(study, tmp_path):
    out, _, _, _, written = study
    md = written["markdown"].read_text()
    page = written["html"].read_text()
    assert page.startswith("<!DOCTYPE html>") and "data:image/png;base64," in page
    assert not re.search(r'src="(?!data:)', page)  # nothing loaded from elsewhere
    for fig in ("figures/ate_levels.png", "figures/heatmap_sve.png", "figures/heldout.png",
                "figures/sve_levels_occlusion.png"):  # fmt: skip
        assert f"({fig})" in md and (out / fig).is_file()
    # numbers in the report are the tables' numbers
    heldout = read_table(out, "heldout_summary")
    row = heldout[(heldout["fold_kind"] == "kfold") & (heldout["rule"] == "fitted-sve")].iloc[0]
    assert f"{row['mean_loss']:.4g} [{row['ci_low']:.4g}, {row['ci_high']:.4g}]" in md
    params = read_table(out, "params")
    p = params[(params["family"] == "inliers") & (params["parameter"] == "imu_init")].iloc[0]
    assert f"[{p['ci_low']:.4g}, {p['ci_high']:.4g}]" in md
    # rendering again gives the same bytes
    again = write_report(out, title="test report")
    assert again["markdown"].read_text() == md and again["html"].read_text() == page
    assert (out / "figures/ate_levels.png").read_bytes() == written["figure RMS ATE and failures per level"].read_bytes()
    with pytest.raises(FileNotFoundError, match="no summary.parquet"):
        write_report(tmp_path)


def test_markdown_table_formats_numbers():
    table = pd.DataFrame({"a": [1, 2], "b": [0.123456, float("nan")], "c": ["x", "y"]})
    assert markdown_table(table).splitlines() == ["| a | b | c |", "|---|---|---|", "| 1 | 0.1235 | x |",
                                                  "| 2 | - | y |"]  # fmt: skip
