"""jsve.fitting._study and jsve.report: a small study end to end, its tables, resumption and the report
(slow: compiles every stage), and the report alone from hand-made tables with known answers (fast).

The report's numbers must be the tables' numbers: its headline first, failure-aware (a failed run at the
penalty, never averaged over the part it tracked), presets once, heat maps honest about what they hold
and whether they are flat, parameters flagged where the data cannot pin them; the HTML self-contained;
rendering twice gives the same bytes and keeps the title.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from dataclasses import replace
from pathlib import Path

import knownanswer as ka
import numpy as np
import pandas as pd
import pytest

from jsve.core._rules import PRESETS
from jsve.evaluation import group_weights
from jsve.fitting._config import StudyConfig
from jsve.fitting._data import FitData
from jsve.fitting._fit import FitConfig
from jsve.fitting._stages import data_fingerprint, fingerprint, read_table, study_files
from jsve.fitting._study import run_study
from jsve.io._resume import StaleOutputError
from jsve.report import _format as fmt
from jsve.report._report import write_report

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
        "fit_sve",
        "fit_inliers",
        "evaluate",
        "cross_validation",
        "parameter_bootstrap",
        "heatmap",
    }
    assert not list(out.glob("*.partial")) and not list(out.glob("figures/*.partial"))
    runs = read_table(out, "runs")
    assert set(runs["rule"]) == {*PRESETS, "fitted-sve", "fitted-inliers"}
    assert {"orbslam3", "sve-eq1", "sve-option1", "sve-option2", "jsve-eq1"} <= set(PRESETS)
    assert (runs.groupby("rule").size() == data.n_runs).all()
    # the presets' held-out rows are the evaluation's objective terms of the same runs (one pass)
    heldout = read_table(out, "heldout")
    for rule in PRESETS:
        rows = heldout[heldout["rule"] == rule].merge(runs[runs["rule"] == rule], on="run_id")
        assert len(rows) == len(heldout[heldout["rule"] == rule]) > 0
        np.testing.assert_allclose(rows["loss"], rows["objective_loss"], rtol=1e-7)
        np.testing.assert_array_equal(rows["failed_x"], rows["objective_failed"])


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
    assert record["key"]["config"] == fingerprint(SMALL.to_dict()) and len(record["done"]) == 6


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
        "figures/levels.png",
        "figures/heatmap_sve.png",
        "figures/heatmap_inliers.png",
        "figures/heldout.png",
        "figures/sve_levels_occlusion.png",
    ):
        assert f"({fig})" in md and (out / fig).is_file()
    assert md.index("## Headline") < md.index("## Figures") < md.index("## Held-out comparison")
    # numbers in the report are the tables' numbers, in centimetres
    heldout = read_table(out, "heldout_summary")
    row = heldout[(heldout["fold_kind"] == "kfold") & (heldout["rule"] == "fitted-sve")].iloc[0]
    cm = lambda m: f"{100 * m:.1f}"  # noqa: E731
    assert f"| {cm(row['mean_loss'])} [{cm(row['ci_low'])}, {cm(row['ci_high'])}] |" in md
    params = read_table(out, "params")
    p = params[(params["family"] == "inliers") & (params["parameter"] == "imu_init")].iloc[0]
    assert f"| [{p['ci_low']:.1f}, {p['ci_high']:.1f}] | [0.0, 100.0] | 15.0 |" in md  # 0.5 % of the range
    # rendering again gives the same bytes, title kept in report.json
    again = write_report(out)
    assert again["markdown"].read_text() == md and again["html"].read_text() == page
    assert json.loads((out / "report.json").read_text()) == {"title": "test report"}
    assert (out / "figures/levels.png").read_bytes() == written["figure levels.png"].read_bytes()
    with pytest.raises(FileNotFoundError, match="nothing to report"):
        write_report(tmp_path)


# ---------------------------------------------------------------------------------------------------
# The report from tables made by hand (fast): known answers


def test_numbers_are_never_scientific_and_shares_read_as_percent():
    assert fmt.number(1e-5) == "0.00001" and fmt.number(0.123456) == "0.1235" and fmt.number(3.0) == "3"
    assert fmt.number(223200) == "223,200" and fmt.number(float("nan")) == "-"
    assert fmt.cm(0.039030) == "3.9" and fmt.cm(-0.0004) == "0.0" and fmt.cm(-0.0117, sign=True) == "-1.2"
    assert fmt.cm_ci(0.0117, 0.0, 0.0273, sign=True) == "+1.2 [0.0, +2.7]"
    assert [fmt.percent(x) for x in (0, 1, 0.108, 0.0005, 0.00005)] == [
        "0 %",
        "100 %",
        "10.8 %",
        "0.05 %",
        "< 0.01 %",
    ]
    assert fmt.decimals_for(0.6) == 3 and fmt.decimals_for(8.0) == 2 and fmt.decimals_for(200.0) == 1
    assert fmt.fixed(-0.0001, 3) == "0.000"


def test_markdown_table_aligns_words_left_and_numbers_right():
    table = pd.DataFrame(
        {"a": [1, 2], "b": [0.123456, float("nan")], "c": ["x", "y"], "d": ["3.9 [3.3, 4.6]", "-"]}
    )
    assert fmt.markdown_table(table).splitlines() == [
        "| a | b | c | d |",
        "|---:|---:|:---|---:|",
        "| 1 | 0.1235 | x | 3.9 [3.3, 4.6] |",
        "| 2 | - | y | - |",
    ]
    cells = fmt.html_table(table)
    assert '<td class="w">x</td>' in cells and '<td class="n">0.1235</td>' in cells


def test_every_disturbance_has_a_level_axis_with_its_unit():
    from jsve.image._disturb import DISTURBANCES

    assert set(fmt.DISTURBANCE_AXES) == set(DISTURBANCES)
    assert fmt.level_axis("blur") == "blur kernel n (n x n px)"
    assert fmt.level_axis("downsample") == "downsampling scale factor s (image scaled by s)"
    assert fmt.level_axis("occlusion") == "occluder side n (n x n px square)"


def test_every_parameter_has_words():
    from jsve.core._rules import RULE_KINDS, param_names
    from jsve.report._study_report import PARAMETER_TEXT

    names = {n for kind in RULE_KINDS for n in param_names(kind)} | {"weight_a", "weight_b", "weight_c"}
    assert names <= set(PARAMETER_TEXT)


RULES = ("fitted-sve", "orbslam3", "sve-option2")
"""The rules of the hand-made study."""


def _run(sequence, disturbance, level, rule, rmse, failed=False, accepted=1.0, unsupported=0.0):
    return {
        "run_id": f"{sequence}/{disturbance}-{level}/0",
        "sequence": sequence,
        "disturbance": disturbance,
        "level": float(level),
        "run": 0,
        "rule": rule,
        "switch_model": "orbslam3",
        "rmse": rmse,
        "mean": rmse,
        "sse": rmse * rmse * 100,
        "count": 100,
        "coverage": 0.8 if failed else 1.0,
        "failed": failed,
        "failure_reason": "lost tracking (a reset, an expiry to LOST or a recorded map loss)"
        if failed
        else "",
        "accepted_fraction": accepted,
        "changed_fraction": 0.0,
        "unsupported_fraction": unsupported,
        "lost_any": failed,
    }


def _runs() -> pd.DataFrame:
    """Two sequences x (blur 0, 50; occlusion 0, 450) x the three rules. At blur 50 orbslam3 fails both runs
    after tracking part of them at 5 cm; fitted-sve keeps tracking at 20 and 30 cm."""
    rows = []
    for seq in ("s1", "s2"):
        for dist, harsh in (("blur", 50), ("occlusion", 450)):
            for rule in RULES:
                rows.append(_run(seq, dist, 0, rule, 0.02))
            rows.append(_run(seq, dist, harsh, "fitted-sve", {"s1": 0.2, "s2": 0.3}[seq], accepted=0.9999))
            if dist == "blur":
                rows.append(_run(seq, dist, harsh, "orbslam3", 0.05, failed=True, accepted=0.9))
                rows.append(_run(seq, dist, harsh, "sve-option2", 0.03, failed=seq == "s1", accepted=0.96))
            else:
                rows.append(
                    _run(seq, dist, harsh, "orbslam3", {"s1": 0.03, "s2": 0.04}[seq], failed=seq == "s1")
                )
                rows.append(_run(seq, dist, harsh, "sve-option2", 0.03))
    return pd.DataFrame(rows)


def _heldout_row(kind, rule, mean, **diffs):
    row = {
        "fold_kind": kind,
        "rule": rule,
        "n_runs": 8,
        "mean_loss": mean,
        "ci_low": mean - 0.01,
        "ci_high": mean + 0.01,
        "failure_rate": 0.0,
        "coverage": 1.0,
        "unsupported": 0.0,
    }
    for base, (d, lo, hi) in diffs.items():
        row |= {f"diff_vs_{base}": d, f"diff_vs_{base}_ci_low": lo, f"diff_vs_{base}_ci_high": hi}
    return row


SVE_SPACE = {"w_a": [0.0, 1.0], "imu_init": [0.0, 0.6], "recovery": [0.0, 0.6]}
INLIER_SPACE = {
    "imu_init": [0.0, 100.0],
    "not_init": [0.0, 200.0],
    "reloc": [0.0, 200.0],
    "recovery": [0.0, 100.0],
}


def _fake_study(out):
    """Every table write_report reads, made by hand with known answers."""
    from jsve.fitting._stages import write_json, write_table

    config = {
        "failure_penalty": 1.0,
        "align": "se3",
        "min_coverage": 0.0,
        "switch_model": "orbslam3",
        "support": "penalise",
        "families": ["sve", "inliers"],
        "kfold": 2,
        "leave_one_out": ["sequence"],
        "n_boot": 100,
        "level": 0.95,
        "fit": {"design": "sobol", "n_search": 64, "n_starts": 1, "nm_steps": 10, "relaxed": False},
    }
    write_json(
        {
            "n_runs": 8,
            "n_frames": 800,
            "balance_by": ["sequence", "disturbance", "level"],
            "config": config,
            "data": {"source": "jsve simulator (hand-made)"},
        },
        out / "study.json",
    )
    write_table(_runs(), out, "runs")
    oslam, option2 = ("orbslam3", "sve-option2")
    rows = []
    for kind in ("kfold", "leave-one-sequence-out"):
        # fitted-inliers has the lower k-fold objective, fitted-sve the lower worst case: sve is recommended
        sve, inl = (0.03, 0.025) if kind == "kfold" else (0.05, 0.08)
        rows += [
            _heldout_row(
                kind, "fitted-sve", sve, **{oslam: (sve - 0.39, -0.5, -0.2), option2: (-0.012, -0.027, 0.0)}
            ),
            _heldout_row(
                kind, "fitted-inliers", inl, **{oslam: (inl - 0.39, -0.5, -0.2), option2: (0.01, 0.002, 0.03)}
            ),
            _heldout_row(kind, oslam, 0.39, **{option2: (0.3, 0.2, 0.4)}) | {"failure_rate": 0.375},
            _heldout_row(kind, option2, 0.09, **{oslam: (-0.3, -0.4, -0.2)}) | {"failure_rate": 0.125},
        ]
    write_table(pd.DataFrame(rows), out, "heldout_summary")
    write_table(
        pd.DataFrame(
            {
                "family": ["sve"] * 4 + ["inliers"] * 4,
                "parameter": [
                    "w_a",
                    "imu_init",
                    "recovery",
                    "weight_a",
                    "imu_init",
                    "not_init",
                    "reloc",
                    "recovery",
                ],
                "value": [0.5, 0.6, 0.04, 0.5, 2.7, 40.2, 3.2, 3.4],
                "ci_low": [0.1, 0.55, 0.03, 0.1, 0.7, 38.0, 0.4, 6.1],
                "ci_high": [0.9, 0.6, 0.05, 0.9, 6.2, 42.0, 10.8, 14.2],
                "boot_std": 0.01,
                "n_boot": 100,
            }
        ),
        out,
        "params",
    )
    xs, ys = np.meshgrid(np.linspace(0, 0.6, 4), np.linspace(0, 0.6, 4))
    ix, iy = np.meshgrid(np.linspace(0, 100, 4), np.linspace(0, 100, 4))
    heat = [
        # SVE: flat, 3.9 cm +- 0.02 mm; inliers: 4 to 24 cm along imu_init
        {"family": "sve", "x_name": "imu_init", "y_name": "recovery", "x": xs.ravel(), "y": ys.ravel(),
         "objective": 0.039 + 2e-5 * xs.ravel(), "failure_rate": 0.0},
        {"family": "inliers", "x_name": "imu_init", "y_name": "recovery", "x": ix.ravel(), "y": iy.ravel(),
         "objective": 0.04 + 0.002 * ix.ravel(), "failure_rate": 0.0},
    ]  # fmt: skip
    write_table(pd.concat([pd.DataFrame(h) for h in heat], ignore_index=True), out, "heatmap")
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
                for d in ("blur", "occlusion")
                for lv in (0.0, 50.0)
                for c in ("sve-option2", "fitted-sve")
            ]
        ),
        out,
        "sve_levels",
    )
    for family, params, space in (
        ("sve", {"w_a": 0.5, "imu_init": 0.6, "recovery": 0.04}, SVE_SPACE),
        ("inliers", {"imu_init": 2.7, "not_init": 40.2, "reloc": 3.2, "recovery": 3.4}, INLIER_SPACE),
    ):
        write_json(
            {
                "kind": family,
                "family": family,
                "params": params,
                "space": {"kind": family, "free": space, "fixed": {}},
                "objective": 0.0312,
                "failure_rate": 0.0,
                "coverage": 1.0,
                "stages": [
                    {"stage": "search", "objective": 0.033, "seconds": 1.5},
                    {"stage": "nelder_mead_0", "objective": 0.0312, "seconds": 7.25, "simplexes": 2},
                    {"stage": "nelder_mead_1", "objective": 0.0315, "seconds": 7.25, "simplexes": 2},
                ],
            },
            out / f"fitted_{family}.json",
        )


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    """The hand-made study with its report rendered once: (folder, markdown, html) for the tests that
    only read them; a test that changes the study copies the folder first."""
    out = tmp_path_factory.mktemp("fake")
    _fake_study(out)
    written = write_report(out, title="fake")
    return out, written["markdown"].read_text(), written["html"].read_text()


def _section(md: str, heading: str) -> str:
    return md.split(f"## {heading}\n")[1].split("\n## ")[0]


def test_stage_seconds_of_simplexes_in_lockstep_are_marked_shared(fake):
    """Nelder-Mead runs moved in lockstep record the lockstep's wall time each: the stage table says the
    time is theirs together, so no reader adds it up twice."""
    _, md, _ = fake
    assert md.count("| 7.2 (all 2 simplexes) |") == 4  # two stages of each family's table
    assert "| 1.5 |" in md


def test_headline_comes_first_and_says_what_the_tables_say(fake):
    _, md, _ = fake
    assert md.startswith("# fake\n\n## Headline\n")
    head = _section(md, "Headline")
    assert (
        "The SVE rule (3 free parameters: w_a, imu_init, recovery) and ORB-SLAM3's inlier rule (4 free"
        in head
    )
    # sve's worst fold kind (5.0 cm) beats inliers' (8.0 cm), although inliers wins k-fold
    assert "**Recommended: `fitted-sve`**" in head and "`jsve evaluate LOGS --rule fitted_sve.json`" in head
    assert "it scores 3.0 [2.0, 4.0] cm: better than `orbslam3` by 36.0 cm (95 % CI 20.0 to 50.0)" in head
    assert "not clearly different from `sve-option2` (-1.2 cm, 95 % CI -2.7 to 0.0: it contains 0)" in head
    # switching, from runs: fitted-sve rejects 0.01 % of frames in 4 of 8 runs (0.005 %), orbslam3 10 % in 2
    assert "`fitted-sve` rejects < 0.01 % of frames and 0 % of runs reach LOST" in head
    assert "(`orbslam3` 2.5 % and 37.5 %; `sve-option2` 1.0 % and 12.5 %)" in head
    assert "Simulated data" in head and "Switch model `orbslam3`" in head and "Support: none of" in head
    assert "of `orbslam3`'s 39.0 cm, 37.5 cm is the penalty of its failed runs (37.5 % of runs at 1 m" in head
    assert "practically never switches" in head
    assert "2 parameters of `fitted-sve` flagged (at a bound, not identified)" in head


def test_tables_are_failure_aware_and_presets_appear_once(fake):
    _, md, page = fake
    held = _section(md, "Held-out comparison")
    assert held.count("| orbslam3 |") == 1 and held.count("| fitted-sve |") == 2
    assert "| orbslam3 | (not fitted) | 8 | 39.0 [38.0, 40.0] | 37.5 % |" in held
    # blur 50: orbslam3 failed both runs after tracking part of them at 5 cm: the objective is the penalty,
    # and no mean over all runs shows 5 cm
    levels = _section(md, "Per level")
    head = "| blur kernel n (n x n px) | fitted-sve | orbslam3 | sve-option2 |"
    assert head in levels
    assert "| 50 | 25.0 (0 %) | 100.0 (100 %) | 51.5 (50.0 %) |" in levels
    assert "| 50 | orbslam3 | 2 | 100.0 | 100 % | 80.0 % | - (n = 0) |" in levels
    assert "| 450 | orbslam3 | 2 | 52.0 | 50.0 % | 90.0 % | 4.0 (n = 1) |" in levels
    assert (
        "ATE RMSE, m (all runs)" not in md
        and "5.0" not in levels.split("| 50 | orbslam3 |")[1].split("\n")[0]
    )
    overall = _section(md, "All runs, per rule")
    assert "| orbslam3 | 8 | 39.0 | 37.5 % | 92.5 % | 2.5 % | 37.5 % | 2.4 (n = 5) |" in overall
    # words left, numbers right; the long tables collapsed
    assert "<details><summary>blur: every rule and level in detail</summary>" in page
    assert '<td class="w">orbslam3</td>' in page and '<td class="n">39.0</td>' in page


def test_heat_maps_say_what_is_held_and_when_they_are_flat(fake):
    _, md, _ = fake
    figs = _section(md, "Figures")
    sve = figs.split("### Objective over two thresholds: sve")[1].split("###")[0]
    inl = figs.split("### Objective over two thresholds: inliers")[1].split("###")[0]
    assert "other 1 parameter held at the fit (w_a 0.500)" in sve
    assert "The surface is flat: 3.9 cm everywhere (it varies by 0.01 mm)" in sve
    # presets at their own score (runs: sve-option2 0.09 m overall), not the cell under them
    assert "`sve-option2` is drawn at its thresholds with its own score, 14.6 cm" in sve
    assert "held at the fit (not_init 40.2, reloc 3.2)" in inl and "It spans 4.0 to 24.0 cm" in inl
    assert "`orbslam3` is drawn at its thresholds with its own score, 39.0 cm (not_init 50, reloc 50)" in inl
    assert "flat" not in inl


def test_parameters_flag_what_the_data_cannot_say(fake):
    _, md, _ = fake
    params = _section(md, "Fitted parameters")
    rows = {line.split(" | ")[0].strip("| "): line for line in params.splitlines() if line.startswith("| ")}
    assert "not identified: its 95 % interval spans 80 % of the search range" in rows["w_a"]
    assert "at a bound: the upper bound" in params.split("| imu_init |")[1].split("\n")[0]
    assert "weight_a" not in rows and "sve's weight_a is w_a" in params  # the duplicate row, once
    inliers = params.split("### inliers")[1]
    lines = {line.split(" | ")[0].strip("| "): line for line in inliers.splitlines() if line.startswith("| ")}
    assert "| >= 3 inliers | implausible: below 10 inliers" in lines["imu_init"]
    assert "| >= 41 inliers | -" in lines["not_init"]  # score < 40.2 fails counts up to 40
    assert "| >= 4 inliers | outside its interval" in lines["recovery"]  # recovery: score > 3.4 from 4 on


def test_parameter_intervals_say_what_the_refits_chose_from(fake, tmp_path):
    """With a local design the refits chose from it and the search; without one (the default study's
    n_local 0: `local` is 1, the fit alone) the report says the intervals are only as fine as the search's
    settings, and how to get finer ones."""
    from jsve.fitting._stages import read_table, write_table

    folder, md, _ = fake
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True)
    assert "the best setting of the search and a dense local design" in _section(md, "Fitted parameters")
    params = read_table(tmp_path, "params")
    write_table(params.assign(local=1, local_scored=1, race="1"), tmp_path, "params")
    section = _section(write_report(tmp_path, title="fake")["markdown"].read_text(), "Fitted parameters")
    assert "dense local design" not in section
    assert "under halving its last rung's survivors, and the fit; no local design" in section
    assert "`jsve fit --thorough` adds 1,024 settings around the fit" in section


def test_configuration_is_written_as_sentences(fake):
    _, md, _ = fake
    method = _section(md, "Method")
    assert "coverage below 0" not in md and "there is no coverage floor" in method
    assert "a failed run charged 1 m" in method and "Switch model `orbslam3`: a tracked" in method
    assert "Cross-validation: 2-fold and leave-one-sequence-out" in method


def test_report_is_deterministic_and_keeps_its_title(fake, tmp_path):
    folder, _, page = fake
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True)
    assert page.count("data:image/png;base64,") == 6 and not re.search(r'src="(?!data:)', page)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    write_report(tmp_path)  # no title: the kept one
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert "<title>fake</title>" in page


def test_jsve_report_dash_o_writes_the_same_page_elsewhere_and_only_reads_the_study(tmp_path, capsys):
    """`jsve report DIR -o OUT` writes the report DIR would hold into OUT, byte for byte (figures linked
    relative to OUT, the title DIR keeps), and leaves DIR as it was; a --title is kept in OUT."""
    from jsve.cli import main

    study, elsewhere = tmp_path / "study", tmp_path / "elsewhere"
    _fake_study(study)
    write_report(study, title="fake")
    before = {p.relative_to(study): p.read_bytes() for p in study.rglob("*") if p.is_file()}
    assert main(["report", str(study), "-o", str(elsewhere)]) == 0
    assert capsys.readouterr().out == (
        f"jsve report: {elsewhere / 'report.html'} (6 figures; Markdown: {elsewhere / 'report.md'})\n"
    )
    after = {p.relative_to(study): p.read_bytes() for p in study.rglob("*") if p.is_file()}
    assert after == before  # the study folder is only read
    report = {p.relative_to(elsewhere): p.read_bytes() for p in elsewhere.rglob("*") if p.is_file()}
    assert set(report) == {
        p for p in before if p.name.startswith("report.") or p.parent.name == "figures"
    } - {Path("report.json")}
    assert all(report[p] == before[p] for p in report)
    assert main(["report", str(study), "--output", str(elsewhere), "--title", "other"]) == 0
    assert json.loads((elsewhere / "report.json").read_text()) == {"title": "other"}
    assert "<title>other</title>" in (elsewhere / "report.html").read_text()
    assert json.loads((study / "report.json").read_text()) == {"title": "fake"}


def test_report_of_an_older_study_without_support_columns(tmp_path):
    """A study written before the support columns and the configuration's switch model and support policy
    existed renders without them."""
    from jsve.fitting._stages import write_json, write_table

    _fake_study(tmp_path)
    runs = read_table(tmp_path, "runs").drop(columns=["unsupported_fraction", "changed_fraction"])
    write_table(runs, tmp_path, "runs")
    write_table(
        read_table(tmp_path, "heldout_summary").drop(columns=["unsupported"]), tmp_path, "heldout_summary"
    )
    study = json.loads((tmp_path / "study.json").read_text())
    del study["config"]["switch_model"], study["config"]["support"]
    write_json(study, tmp_path / "study.json")
    md = write_report(tmp_path, title="fake")["markdown"].read_text()
    assert "runs out of support" not in md and "frames changed" not in md


def test_report_of_an_evaluate_folder(tmp_path):
    """`jsve evaluate -o` writes runs.parquet (and no study.json): the report scores every rule as the fit
    would, pairs the differences over runs, and keeps the per-level tables and figure."""
    from jsve.io import _atomic as atomic

    runs = _runs()
    atomic.write_table(runs, tmp_path / "runs.parquet")
    written = write_report(tmp_path)
    md = written["markdown"].read_text()
    assert md.startswith("# jsve evaluation report\n\n## Headline\n")
    head = _section(md, "Headline")
    # losses, sve-option2: 0.02 x 4, 1, 0.03 x 3 -> 0.14625 m; fitted-sve: 0.02 x 4, 0.2, 0.3 x 2 -> 0.135 m
    assert "**Lowest objective: `fitted-sve`**, 13.5 [" in head
    assert (
        "3 rules (`fitted-sve`, `orbslam3` and `sve-option2`) replayed by `jsve evaluate` on 8 runs" in head
    )
    overall = _section(md, "All runs, per rule")
    assert "| sve-option2 | 8 | 14.6 [" in overall and "| orbslam3 | 8 | 39.0 [" in overall
    assert "| lost tracking (a reset, an expiry to LOST or a recorded map loss) |" in _section(
        md, "Why runs failed"
    )
    assert "| 50 | 25.0 (0 %) | 100.0 (100 %) | 51.5 (50.0 %) |" in _section(md, "Per level")
    assert (tmp_path / "figures" / "levels.png").is_file()
    assert not (tmp_path / "report.json").exists()  # no title given: none kept
    # Without evaluation.json (a folder of an earlier jsve) the report says it assumes the defaults.
    assert "This folder has no evaluation.json" in _section(md, "Method")


def test_report_of_an_evaluate_folder_scores_as_evaluate_recorded(tmp_path):
    """The settings `jsve evaluate -o` records in evaluation.json, not jsve's defaults, score the rules
    and are shown: a penalty of 0.5 m reorders the rules, the alignment, switch model and support policy
    are named, every rule is listed with where it came from and its parameters."""
    from jsve.core._rules import preset, rule_to_dict
    from jsve.evaluation import EvaluationRecord, RuleRecord, write_evaluation_record
    from jsve.io import _atomic as atomic

    atomic.write_table(_runs(), tmp_path / "runs.parquet")
    fitted = {
        "kind": "inliers",
        "thresholds": {"imu_init": 7.5, "not_init": 30.0, "reloc": 30.0, "recovery": 5.0},
    }
    record = EvaluationRecord(
        align="sim3",
        switch_model="imu-coast",
        failure_penalty=0.5,
        support="penalise",
        min_coverage=0.25,
        logs="study.parquet",
        rules=(
            RuleRecord("fitted-sve", "fit/fitted_sve.json", fitted),
            RuleRecord("orbslam3", None, rule_to_dict(preset("orbslam3"))),
            RuleRecord("sve-option2", None, rule_to_dict(preset("sve-option2"))),
        ),
    )
    write_evaluation_record(record, tmp_path)
    md = write_report(tmp_path)["markdown"].read_text()
    head = _section(md, "Headline")
    # sve-option2: 0.02 x 4, 0.5 (the failed run), 0.03 x 3 -> 0.08375 m; fitted-sve keeps 0.135 m
    assert "**Lowest objective: `sve-option2`**, 8.4 [" in head, head
    assert "under the switch model `imu-coast` and Sim(3) alignment" in head
    assert "charged 0.5 m" in head and "1 m" not in head
    assert "| sve-option2 | 8 | 8.4 [" in _section(md, "All runs, per rule")
    method = _section(md, "Method")
    assert "after Sim(3) alignment, capped at 0.5 m; a failed run charged 0.5 m" in method
    assert "its saved trajectory covers fewer than 25.0 % of its frames with ground truth" in method
    assert "Resets, new maps and loop closures are events, not failures" in method
    assert "Switch model `imu-coast`" in method and "Support policy `penalise`" in method
    assert (
        "| fitted-sve | fit/fitted_sve.json | inliers | imu_init 7.5, not_init 30, reloc 30, recovery 5 | - |"
        in method
    )
    assert "| orbslam3 | preset | inliers | imu_init 15, not_init 50, reloc 50, recovery 10 | - |" in method
    assert "w_a 0.5, u_b 0.5, p 0, q 1, rho 0.25" in method
    # "exclude" leaves sve-option2's run out of support out of its mean instead of charging it
    write_evaluation_record(replace(record, support="exclude"), tmp_path)
    md = write_report(tmp_path)["markdown"].read_text()
    assert "a run out of the log's support left out of its rule's mean" in _section(md, "Headline")
    assert "Support policy `exclude`" in _section(md, "Method")
    (tmp_path / "evaluation.json").write_text('{"penalty": 2}')  # not a record: named, never misread
    with pytest.raises(ValueError, match=r"evaluation.json: unknown keys \['penalty'\]"):
        write_report(tmp_path)


def _with_changed(out: Path, changed: float) -> None:
    """The fake study with fitted-sve's replays changing `changed` of the recordings' decisions."""
    _fake_study(out)
    runs = pd.read_parquet(out / "runs.parquet")
    runs.loc[runs["rule"] == "fitted-sve", "changed_fraction"] = changed
    runs.to_parquet(out / "runs.parquet")


def test_the_report_says_whether_the_fitted_rule_stays_where_replays_were_validated(tmp_path):
    from jsve.evaluation import REPLAY_TRUSTED_CHANGED_SHARE
    from jsve.report._report import trust_warnings

    inside, outside = tmp_path / "inside", tmp_path / "outside"
    _with_changed(inside, 0.0)
    _with_changed(outside, 0.05)
    assert trust_warnings(inside) == []
    assert (
        "changes 0 % of the recordings' decisions, within the 0.1 % up to which replays under switch "
        "model `orbslam3` agreed" in _section(write_report(inside)["markdown"].read_text(), "Headline")
    )
    (line,) = trust_warnings(outside)
    assert line.startswith("`fitted-sve` changes 5.0 % of the recordings' decisions, more than the 0.1 %")
    assert line in _section(write_report(outside)["markdown"].read_text(), "Headline")
    # the threshold decides: 5 % is inside a region that reaches 10 %
    assert trust_warnings(outside, threshold=0.1) == [] and REPLAY_TRUSTED_CHANGED_SHARE["orbslam3"] < 0.05


def test_the_trust_region_is_that_of_the_study_switch_model(tmp_path):
    """A study replayed under `imu-coast` is judged by that model's region (1 %), not stock ORB-SLAM3's."""
    import json

    from jsve.report._report import trust_warnings

    out = tmp_path / "coast"
    _with_changed(out, 0.005)
    assert len(trust_warnings(out)) == 1  # beyond `orbslam3`'s 0.1 %
    study = json.loads((out / "study.json").read_text())
    study["config"]["switch_model"] = "imu-coast"
    (out / "study.json").write_text(json.dumps(study))
    assert trust_warnings(out) == []
    assert "within the 1.0 % up to which replays under switch model `imu-coast` agreed" in _section(
        write_report(out)["markdown"].read_text(), "Headline"
    )


@pytest.mark.parametrize("changed", [0.0, 0.05])
def test_jsve_fit_warns_when_a_fitted_rule_leaves_the_trust_region(tmp_path, monkeypatch, capsys, changed):
    """jsve fit's own path, with the study itself replaced by the hand-made one (the fit is not the test)."""
    from logfactory import make_run

    import jsve.fitting._study as study
    from jsve.cli import main
    from jsve.io import write_log

    for k in range(2):
        write_log(make_run(60, seed=k, sequence="S", run=k), tmp_path / "logs" / f"r{k}.csv")
    monkeypatch.setattr(study, "run_study", lambda data, out, config, **kw: _with_changed(Path(out), changed))
    out = tmp_path / "study"
    assert main(["fit", str(tmp_path / "logs"), "-o", str(out), "--no-progress", "--no-report"]) == 0
    warnings = [
        line for line in capsys.readouterr().err.splitlines() if line.startswith("jsve fit: warning:")
    ]
    assert len(warnings) == (1 if changed > 0.001 else 0)
    if warnings:
        assert "`fitted-sve` changes 5.0 %" in warnings[0]


def test_a_heatmap_on_a_subset_of_the_runs_says_so():
    """StudyConfig.heatmap_runs: a surface scored on fewer runs than the study's is named as such."""
    from jsve.report._study_report import _heatmap_subset_note

    def table(scored, weighted):
        return pd.DataFrame({"objective": [0.1, 0.2], "n_runs": scored, "n_weighted": weighted})

    note = _heatmap_subset_note(table(512, 3410))
    assert "512 of the 3,410 runs" in note and "estimate" in note
    assert _heatmap_subset_note(table(40, 40)) == ""
    assert _heatmap_subset_note(pd.DataFrame({"objective": [0.1]})) == ""  # written before heatmap_runs
