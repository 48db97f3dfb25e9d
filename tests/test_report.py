"""jsve.fitting._study and jsve.report._report: a small study end to end, its tables, resumption and the
report (slow: compiles every stage), and the report alone from hand-made tables (fast).

The report's numbers must be the tables' numbers; the HTML must be self-contained; rendering twice gives
the same bytes; a rerun with the same configuration skips finished stages and changes nothing.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from dataclasses import replace

import knownanswer as ka
import numpy as np
import pandas as pd
import pytest

from jsve.core._rules import PRESETS
from jsve.evaluation import group_weights
from jsve.fitting._fit import FitConfig, FitData
from jsve.fitting._study import StudyConfig, data_fingerprint, fingerprint, read_table, run_study, study_files
from jsve.io._resume import StaleOutputError
from jsve.report._report import markdown_table, write_report

SMALL = StudyConfig(
    fit=FitConfig(n_search=64, n_starts=1, nm_steps=10),
    kfold=2,
    leave_one_out=("sequence",),
    n_boot=100,
    n_local=32,
    heatmap=("imu_init", "recovery", 4),
)


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


@pytest.mark.slow
def test_study_writes_every_table_as_parquet_and_csv(study):
    out, data, stages, _, _ = study
    names = (
        "runs_presets",
        "runs",
        "summary",
        "heldout",
        "cv_params",
        "heldout_summary",
        "params",
        "heatmap",
        "sve_levels",
    )
    for name in names:
        parquet = pd.read_parquet(out / f"{name}.parquet")
        csv = pd.read_csv(out / f"{name}.csv")
        assert len(parquet) == len(csv) > 0, name
        numeric = parquet.select_dtypes("number").columns
        # float32 columns are written to CSV with the shortest text that reads back as the same float32
        np.testing.assert_allclose(
            csv[numeric].to_numpy(float),
            parquet[numeric].to_numpy(float),
            rtol=1e-7,
            equal_nan=True,
            err_msg=name,
        )
    assert set(stages) == {
        "evaluate_presets",
        "fit_sve",
        "fit_inliers",
        "evaluate_fitted",
        "cross_validation",
        "parameter_bootstrap",
        "heatmap",
        "sve_levels",
    }
    assert not list(out.glob("*.partial")) and not list(out.glob("figures/*.partial"))
    runs = read_table(out, "runs")
    assert set(runs["rule"]) == {*PRESETS, "fitted-sve", "fitted-inliers"}
    assert {"orbslam3", "sve-eq1", "sve-option1", "sve-option2", "jsve-eq1"} <= set(PRESETS)
    assert (runs.groupby("rule").size() == data.n_runs).all()


@pytest.mark.slow
def test_fitted_objective_is_the_evaluate_tables_penalised_mean(study):
    """The fit's recorded objective equals the group-weighted mean of jsve.evaluation._evaluate's per-run
    table with failed runs at the penalty (float32: 1e-5 relative)."""
    out, data, _, _, _ = study
    runs = read_table(out, "runs")
    w = group_weights(data.meta)
    for family in ("sve", "inliers"):
        rec = json.loads((out / f"fitted_{family}.json").read_text())
        table = runs[runs["rule"] == f"fitted-{family}"].set_index("run_id").loc[data.meta["run_id"]]
        loss = np.where(table["failed"], SMALL.failure_penalty, table["rmse"])
        assert rec["objective"] == pytest.approx(np.sum(w * loss) / np.sum(w), rel=1e-5)


@pytest.mark.slow
def test_rerun_skips_finished_stages_and_changes_nothing(study):
    out, data, _, first, written = study
    before = {p.name: p.read_bytes() for p in out.glob("*.parquet")}
    started = time.perf_counter()
    run_study(data, out, SMALL, progress=False, data_description={"source": "tests/knownanswer.py"})
    assert time.perf_counter() - started < 0.25 * first
    assert {p.name: p.read_bytes() for p in out.glob("*.parquet")} == before
    record = json.loads((out / "stages.json").read_text())
    assert record["key"]["config"] == fingerprint(SMALL.to_dict()) and len(record["done"]) == 8


@pytest.mark.slow
def test_rerun_on_other_data_or_configuration_stops_and_force_starts_over(study, tmp_path):
    """A study folder is resumed only under its key: other logs with the same run ids and frame counts
    (one frame's inlier count changed), or another configuration, stop before anything is written
    (StaleOutputError naming the folder and what differs; the files keep their bytes). force=True deletes
    the study's files and writes the tables a clean run of the new study writes; `jsve fit` says the
    same in one line (exit 2) and takes --force."""
    out, data, _, _, _ = study
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    runs = ka.make_study("occlusion", range(12), n_frames=300)
    frames = runs[5].frames.copy()
    frames.loc[150, "n_inliers"] += 1
    runs[5] = replace(runs[5], frames=frames)
    other = FitData.from_runs(runs, SMALL.objective())
    assert (other.n_runs, other.n_frames, list(other.meta["run_id"])) == (
        data.n_runs,
        data.n_frames,
        list(data.meta["run_id"]),
    )
    assert data_fingerprint(other) != data_fingerprint(data)
    assert data_fingerprint(FitData.from_runs(ka.make_study("occlusion", range(12), n_frames=300))) == (
        data_fingerprint(data)
    )
    with pytest.raises(
        StaleOutputError, match=r"holds outputs of another job \(data: fingerprint \"[0-9a-f]+\" != "
    ):
        run_study(other, out, SMALL, progress=False, data_description={"source": "tests/knownanswer.py"})
    changed = StudyConfig(**{**SMALL.__dict__, "failure_penalty": 2.0})
    with pytest.raises(StaleOutputError, match=r"\(configuration: failure_penalty 1.0 != 2.0\)"):
        run_study(data, out, changed, progress=False)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    # every file a study and its report write is one force deletes
    assert {p for p in out.rglob("*") if p.is_file()} == set(study_files(out))

    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "notes.txt").write_text("mine")
    lean = replace(SMALL, families=("inliers",), heatmap=("imu_init", "recovery", 2), n_boot=50)
    run_study(data, copy, lean, progress=False, force=True)
    clean = tmp_path / "clean"
    run_study(data, clean, lean, progress=False)
    assert sorted(p.name for p in copy.iterdir()) == sorted([*(p.name for p in clean.iterdir()), "notes.txt"])
    for table in ("runs", "summary", "heldout", "params", "heatmap"):
        pd.testing.assert_frame_equal(read_table(copy, table), read_table(clean, table))


@pytest.mark.slow
def test_report_is_self_contained_deterministic_and_matches_the_tables(study, tmp_path):
    out, _, _, _, written = study
    md = written["markdown"].read_text()
    page = written["html"].read_text()
    assert page.startswith("<!DOCTYPE html>") and "data:image/png;base64," in page
    assert not re.search(r'src="(?!data:)', page)  # nothing loaded from elsewhere
    for fig in (
        "figures/ate_levels.png",
        "figures/heatmap_sve.png",
        "figures/heldout.png",
        "figures/sve_levels_occlusion.png",
    ):
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
    assert (out / "figures/ate_levels.png").read_bytes() == written[
        "figure RMS ATE and failures per level"
    ].read_bytes()
    with pytest.raises(FileNotFoundError, match="no summary.parquet"):
        write_report(tmp_path)


def test_markdown_table_formats_numbers():
    table = pd.DataFrame({"a": [1, 2], "b": [0.123456, float("nan")], "c": ["x", "y"]})
    assert markdown_table(table).splitlines() == [
        "| a | b | c |",
        "|---|---|---|",
        "| 1 | 0.1235 | x |",
        "| 2 | - | y |",
    ]


def _fake_study(out):
    """The tables write_report reads, made by hand (two disturbances, two rules, one family)."""
    from jsve.fitting._study import write_json, write_table

    write_json(
        {"n_runs": 8, "n_frames": 800, "balance_by": ["sequence"], "config": {"failure_penalty": 1.0}},
        out / "study.json",
    )
    rows = []
    for dist in ("blur", "occlusion"):
        for level in (0, 25, 50):
            for i, rule in enumerate(("orbslam3", "fitted-sve")):
                rows.append(
                    {
                        "disturbance": dist,
                        "level": level,
                        "rule": rule,
                        "n_runs": 2,
                        "failure_rate": 0.5 * i,
                        "mean_coverage": 1.0 - 0.1 * i,
                        "rmse_mean_nonfailed": 0.01 * (level + 1 + i),
                        "rmse_std_nonfailed": 0.001,
                        "rmse_mean_all": 0.02,
                        "rmse_std_all": 0.002,
                    }
                )
    write_table(pd.DataFrame(rows), out, "summary")
    write_table(
        pd.DataFrame(
            [
                {
                    "fold_kind": "kfold",
                    "rule": "fitted-sve",
                    "n_runs": 8,
                    "mean_loss": 0.0123456,
                    "ci_low": 0.011,
                    "ci_high": 0.0141,
                    "failure_rate": 0.0,
                    "coverage": 1.0,
                    "diff_vs_orbslam3": -0.2,
                    "diff_vs_orbslam3_ci_low": -0.3,
                    "diff_vs_orbslam3_ci_high": -0.1,
                },
                {
                    "fold_kind": "kfold",
                    "rule": "orbslam3",
                    "n_runs": 8,
                    "mean_loss": 0.2123,
                    "ci_low": 0.15,
                    "ci_high": 0.25,
                    "failure_rate": 0.25,
                    "coverage": 0.9,
                },
            ]
        ),
        out,
        "heldout_summary",
    )
    write_table(
        pd.DataFrame(
            {
                "family": "sve",
                "parameter": ["imu_init", "recovery"],
                "value": [0.06, 0.04],
                "ci_low": [0.05, 0.01],
                "ci_high": [0.0712345, 0.09],
                "boot_std": [0.01, 0.02],
                "n_boot": 100,
            }
        ),
        out,
        "params",
    )
    xs, ys = np.meshgrid(np.linspace(0, 0.6, 4), np.linspace(0, 0.6, 4))
    write_table(
        pd.DataFrame(
            {
                "family": "sve",
                "x_name": "imu_init",
                "y_name": "recovery",
                "x": xs.ravel(),
                "y": ys.ravel(),
                "objective": (xs + ys).ravel(),
                "failure_rate": 0.0,
            }
        ),
        out,
        "heatmap",
    )
    write_table(
        pd.DataFrame(
            [
                {
                    "disturbance": d,
                    "level": lv,
                    "combination": c,
                    "frames": 100,
                    "sve_mean": 0.5,
                    "sve_std": 0.1,
                }
                for d in ("blur",)
                for lv in (0, 25, 50)
                for c in ("sve-option2", "fitted-sve")
            ]
        ),
        out,
        "sve_levels",
    )
    write_json(
        {
            "params": {"imu_init": 0.06, "recovery": 0.04},
            "rule": {"kind": "sve"},
            "objective": 0.0123,
            "failure_rate": 0.0,
            "coverage": 1.0,
            "stages": [{"stage": "search", "objective": 0.013}],
        },
        out / "fitted_sve.json",
    )


def test_report_from_tables_is_deterministic_and_self_contained(tmp_path):
    _fake_study(tmp_path)
    written = write_report(tmp_path, title="fake")
    md, page = written["markdown"].read_text(), written["html"].read_text()
    assert "0.01235 [0.011, 0.0141]" in md and "-0.2 [-0.3, -0.1]" in md  # held-out row, from the table
    assert "[0.05, 0.07123]" in md  # parameter CI
    assert "| blur | " not in md and "## Per level: occlusion" in md
    for name in ("ate_levels", "heatmap_sve", "heldout", "sve_levels_blur"):
        assert (tmp_path / "figures" / f"{name}.png").is_file() and f"figures/{name}.png" in md
    assert page.count("data:image/png;base64,") == 4 and not re.search(r'src="(?!data:)', page)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    write_report(tmp_path, title="fake")
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_report_shows_switch_model_support_policy_and_support_columns(tmp_path):
    """The configuration section names the switch model and the support policy; the per-level tables carry
    the summary's support columns (changed, out of support, runs out of support) for every rule, with the
    tables' numbers; the fit section and the held-out table say how many runs left the logs' support. A
    study written before these existed renders without them ("not recorded" in the configuration)."""
    from jsve.fitting._study import write_json, write_table

    _fake_study(tmp_path)
    old = write_report(tmp_path, title="fake")["markdown"].read_text()
    assert "| switch model | not recorded |" in old and "runs out of support" not in old
    study = json.loads((tmp_path / "study.json").read_text())
    study["config"] |= {"switch_model": "imu-coast", "support": "exclude"}
    write_json(study, tmp_path / "study.json")
    summary = read_table(tmp_path, "summary")
    summary["mean_changed"] = 0.0125 * (summary["level"] + 1)
    summary["mean_unsupported"] = 0.00375 * summary["level"]
    summary["share_unsupported_runs"] = np.where(summary["rule"] == "fitted-sve", 0.5, 0.0)
    write_table(summary, tmp_path, "summary")
    heldout = read_table(tmp_path, "heldout_summary")
    heldout["unsupported"] = [0.375, 0.0]
    write_table(heldout, tmp_path, "heldout_summary")
    fitted = json.loads((tmp_path / "fitted_sve.json").read_text())
    fitted |= {"unsupported_rate": 0.25, "n_unsupported": 2, "n_excluded": 1}
    write_json(fitted, tmp_path / "fitted_sve.json")

    md = write_report(tmp_path, title="fake")["markdown"].read_text()
    assert "| switch model | imu-coast | a frame in RECENTLY_LOST takes the IMU prediction" in md
    assert (
        "| support policy | exclude | a run whose replay needs a recorded pose the log lacks is left out"
        in md
    )
    section = md.split("## Per level: occlusion")[1].split("##")[0]
    head = next(line for line in section.splitlines() if line.startswith("| level |"))
    assert head.endswith("| failure rate | coverage | changed | out of support | runs out of support |")
    # level 50, fitted-sve: changed 0.6375, out of support 0.1875, runs out of support 0.5
    assert "| 50 | fitted-sve | 2 |" in section and "| 0.6375 | 0.1875 | 0.5 |" in section
    assert "| 50 | orbslam3 | 2 |" in section and "| 0.6375 | 0.1875 | 0 |" in section
    assert "leaves the logs' support on 2 runs (weighted share 0.25); 1 run excluded" in md
    assert "| runs out of support |" in md.split("## Held-out comparison")[1].split("##")[0]
    assert "| 0.375 |" in md and "all rules support" in md
