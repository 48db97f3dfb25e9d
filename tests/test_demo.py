"""`jsve demo`, `jsve fit` and `jsve report` from the command line (small studies), and their configs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomllib

from jsve._demo import DEMO_STUDY, DemoConfig
from jsve.cli import SUBCOMMANDS, build_parser, main
from jsve.fitting._config import StudyConfig

ROOT = Path(__file__).resolve().parents[1]

TINY = """
kfold = 2
leave_one_out = ["sequence", "disturbance"]
n_boot = 50
n_local = 16
heatmap = ["imu_init", "recovery", 3]

[fit]
n_search = 32
n_starts = 1
nm_steps = 5

[demo]
sequences = 2
runs = 1
duration_s = [12.0, 12.0]
disturbances = "blur:0:50,occlusion:0:450"
"""


def test_subcommands_are_registered():
    assert {"fit", "report", "demo"} <= set(SUBCOMMANDS)
    parser = build_parser()
    for name in ("fit", "report", "demo"):
        with pytest.raises(SystemExit) as info:
            parser.parse_args([name, "--help"])
        assert info.value.code == 0


def test_configs_parse_and_unknown_keys_are_named(tmp_path):
    config = DemoConfig.from_dict(tomllib.loads(TINY))
    assert config.sequences == 2 and config.duration_s == (12.0, 12.0)
    assert config.study.fit.n_search == 32 and config.study.fit.n_starts == 1
    assert config.study.heatmap == ("imu_init", "recovery", 3)
    # the shipped configs are valid, and sweeps/demo.toml is the demo's default
    shipped = DemoConfig.from_dict(tomllib.loads((ROOT / "sweeps/demo.toml").read_text()), "sweeps/demo.toml")
    assert shipped == DemoConfig()
    StudyConfig.from_dict({k: v for k, v in tomllib.loads((ROOT / "sweeps/fit.toml").read_text()).items()})
    with pytest.raises(ValueError, match="unknown study settings \\['kfolds'\\]"):
        StudyConfig.from_dict({"kfolds": 3})
    with pytest.raises(ValueError, match="unknown \\[fit\\] settings \\['steps'\\]"):
        StudyConfig.from_dict({"fit": {"steps": 3}})
    with pytest.raises(ValueError, match="unknown \\[demo\\] settings \\['flights'\\]"):
        DemoConfig.from_dict({"demo": {"flights": 3}})
    assert DEMO_STUDY.fit.n_search >= 1024


def test_cli_errors_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("kfold = [")
    assert main(["demo", "-o", str(tmp_path / "o"), "--config", str(bad), "--no-progress"]) == 2
    assert "bad.toml" in capsys.readouterr().err
    assert main(["report", str(tmp_path)]) == 2
    assert "nothing to report" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "missing"), "-o", str(tmp_path / "o2"), "--no-progress"]) == 2


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    """A tiny demo (2 flights x 6 settings x 1 run) run from the command line, and what it printed."""
    import contextlib
    import io

    root = tmp_path_factory.mktemp("tiny")
    cfg = root / "tiny.toml"
    cfg.write_text(TINY)
    out = root / "demo"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["demo", "-o", str(out), "--config", str(cfg), "--no-progress"]) == 0
    return root, out, printed.getvalue()


@pytest.mark.slow
def test_demo_ends_with_a_human_summary_and_reports(tiny_demo, capsys):
    """The demo writes logs, every table and the report, and ends with a few lines a person reads (the
    recommended rule, its held-out objective and differences, where the report is); --json adds the
    timings as the last line (a rerun resumes: every stage is done)."""
    _, out, printed = tiny_demo
    assert (out / "logs" / "study.parquet").is_file() and (out / "report.html").is_file()
    lines = printed.strip().splitlines()
    assert lines[0].startswith("jsve demo: done in ") and lines[-1] == f"  report: {out / 'report.html'}"
    assert re.fullmatch(
        rf"  recommended: fitted-(sve|inliers) \(rule file {re.escape(str(out))}/fitted_\1\.json, .*\)",
        lines[1],
    )
    assert re.fullmatch(r"  held-out objective \(k-fold\): \d+\.\d \[\d+\.\d, \d+\.\d\] cm", lines[2])
    assert any(line.startswith("    vs orbslam3: ") for line in lines) and not printed.lstrip().startswith(
        "{"
    )
    assert (
        main(["demo", "-o", str(out), "--config", str(out.parent / "tiny.toml"), "--no-progress", "--json"])
        == 0
    )
    timings = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert timings["total"] > 0 and set(timings) >= {"simulate", "study", "report"}


def _documented_keys(table: str) -> set[str]:
    """The keys a Markdown table of docs/fitting.md documents: the `names` of each row's first cell."""
    cells = re.findall(r"^\| ([^|]+) \|", table, re.MULTILINE)
    return {key for cell in cells for key in re.findall(r"`(\w+)`", cell)}


@pytest.mark.slow
def test_fitted_rule_files_have_the_documented_layout(tiny_demo):
    """docs/fitting.md documents every key of fitted_<family>.json and of its stages, and only keys the
    files have (the rule's part tables: their parameters named in the rows' text)."""
    _, out, _ = tiny_demo
    doc = (ROOT / "docs" / "fitting.md").read_text()
    section = doc.split("### The fitted rule files (fitted_<family>.json)\n")[1].split("\n## ")[0]
    top, stages = section.split("Each entry of `stages`")
    top_keys, stage_keys = _documented_keys(top), _documented_keys(stages)
    for family in ("sve", "inliers"):
        record = json.loads((out / f"fitted_{family}.json").read_text())
        expected = top_keys - ({"combination"} if family == "inliers" else set())
        assert set(record) == expected, (family, set(record) ^ expected)
        assert set(record["space"]) == {"kind", "free", "fixed"}
        for part in ("combination", "thresholds"):
            row = re.search(rf"^\| `{part}` \|.*$", top, re.MULTILINE).group(0)
            assert all(f"`{name}`" in row for name in record.get(part, {})), (part, row)
        for stage in record["stages"]:
            assert {"stage", "objective", "values", "seconds"} <= set(stage) <= stage_keys, stage


@pytest.mark.slow
def test_report_rerenders_the_demo_byte_for_byte(tiny_demo):
    """`jsve report DIR` without --title gives the demo's page byte for byte: the title is kept in the
    folder (report.json), the figures are deterministic."""
    _, out, _ = tiny_demo
    before = {p: p.read_bytes() for p in [out / "report.md", out / "report.html", *out.glob("figures/*.png")]}
    assert json.loads((out / "report.json").read_text())["title"].startswith("jsve demo: ")
    assert main(["report", str(out)]) == 0
    assert {p: p.read_bytes() for p in before} == before
    assert (
        "<title>jsve demo: fitted switching rules on a simulated study</title>"
        in before[out / "report.html"].decode()
    )


@pytest.mark.slow
def test_headline_numbers_rederived_from_the_tables(tiny_demo):
    """Every number of the demo's headline, recomputed here from the per-run tables without the report's
    code: the recommended rule (lowest worst-fold held-out objective), its held-out objective and paired
    differences (jsve.fitting.compare over heldout.parquet), the frames it rejects and the runs that reach
    LOST (runs.parquet, weighted as the fit weighs runs)."""
    from jsve.evaluation import group_weights
    from jsve.fitting import compare

    _, out, _ = tiny_demo
    md = (out / "report.md").read_text()
    head = md.split("## Headline\n")[1].split("\n## ")[0]
    study = json.loads((out / "study.json").read_text())
    heldout = pd.read_parquet(out / "heldout.parquet")
    summary = compare(heldout, n_boot=study["config"]["n_boot"], level=study["config"]["level"], seed=0)
    pd.testing.assert_frame_equal(
        summary, pd.read_parquet(out / "heldout_summary.parquet"), check_dtype=False
    )
    fitted = summary[summary["rule"].str.startswith("fitted-")]
    worst = fitted.groupby("rule")["mean_loss"].max().round(6)
    kfold = fitted[fitted["fold_kind"] == "kfold"].set_index("rule")["mean_loss"].round(6)
    order = sorted(worst.index, key=lambda r: (worst[r], kfold[r], r != "fitted-inliers"))
    rule = order[0]
    assert f"**Recommended: `{rule}`**" in head
    row = summary[(summary["fold_kind"] == "kfold") & (summary["rule"] == rule)].iloc[0]
    cm = lambda m: f"{100 * m:.1f}".replace("-0.0", "0.0")  # noqa: E731
    assert f"it scores {cm(row['mean_loss'])} [{cm(row['ci_low'])}, {cm(row['ci_high'])}] cm" in head
    for base in ("orbslam3", "sve-option2"):
        d, lo, hi = (row[f"diff_vs_{base}{s}"] for s in ("", "_ci_low", "_ci_high"))
        if hi < 0:
            assert f"better than `{base}` by {cm(-d)} cm (95 % CI {cm(-hi)} to {cm(-lo)})" in head
        elif lo > 0:
            assert f"worse than `{base}` by {cm(d)} cm (95 % CI {cm(lo)} to {cm(hi)})" in head
        else:
            assert f"not clearly different from `{base}`" in head
    runs = pd.read_parquet(out / "runs.parquet")
    shares = {}
    for name, g in runs.groupby("rule"):
        w = group_weights(g, study["balance_by"])
        rejected = 1 - np.sum(w * g["accepted_fraction"]) / np.sum(w)
        lost = np.sum(w * g["lost_any"]) / np.sum(w)
        shares[name] = (rejected, lost)

    def pct(x):
        p = 100 * x
        return "0 %" if p == 0 else "< 0.01 %" if p < 0.01 else f"{p:.2f} %" if p < 0.1 else f"{p:.1f} %"

    r, lost = shares[rule]
    assert f"`{rule}` rejects {pct(r)} of frames and {pct(lost)} of runs reach LOST" in head
    r, lost = shares["orbslam3"]
    assert f"`orbslam3` {pct(r)} and {pct(lost)}" in head


@pytest.mark.slow
def test_fitted_rule_files_work_with_evaluate_and_the_front_end(tiny_demo):
    """`jsve evaluate LOGS --rule fitted_<family>.json` takes the study's file as it is and replays the same
    rule the study evaluated (the same runs fail, the same RMSE); the front-end's rule option reads it
    too (the driver's --rule-* arguments carry the fitted numbers); `jsve report` reads the evaluate
    folder."""
    from jsve.frontend._run import driver_rule
    from jsve.io import load_rules

    root, out, _ = tiny_demo
    evaluated = root / "evaluated"
    files = [str(out / "fitted_sve.json"), str(out / "fitted_inliers.json")]
    argv = ["evaluate", str(out / "logs" / "study.parquet"), "--rule", files[0], "--rule", files[1]]
    assert main([*argv, "--rule", "orbslam3", "-o", str(evaluated), "--no-progress"]) == 0
    mine = pd.read_parquet(evaluated / "runs.parquet")
    study = pd.read_parquet(out / "runs.parquet")
    for family in ("sve", "inliers"):
        a = mine[mine["rule"] == f"fitted_{family}"].set_index("run_id").sort_index()
        b = study[study["rule"] == f"fitted-{family}"].set_index("run_id").loc[a.index]
        assert len(a) == len(b) > 0 and (a["failed"] == b["failed"]).all()
        np.testing.assert_allclose(a["rmse"], b["rmse"], rtol=1e-6)  # both float32 replays of one rule
    (name, rule), (_, inliers) = load_rules(files)
    assert name == "fitted_sve"
    args, _ = driver_rule("fitted_inliers", inliers, "orbslam3")
    thresholds = json.loads((out / "fitted_inliers.json").read_text())["thresholds"]
    expected = [thresholds[k] for k in ("imu_init", "not_init", "reloc", "recovery")]
    assert args[0] == "--rule-inliers" and [float(x) for x in args[1].split(",")] == pytest.approx(expected)
    assert driver_rule("fitted_sve", rule, "orbslam3")[0][0] == "--rule-sve"
    assert main(["report", str(evaluated)]) == 0
    page = (evaluated / "report.md").read_text()
    assert page.startswith("# jsve evaluation report") and "`fitted_sve`" in page


@pytest.mark.slow
def test_fit_on_the_demo_logs_reproduces_its_fit(tiny_demo, capsys):
    """`jsve fit` on the demo's logs with the demo's study settings reproduces its fitted objective, and
    ends with the demo's closing lines (jsve.report._report.summary_lines)."""
    from jsve.report._report import summary_lines

    root, out, _ = tiny_demo
    fit_out = root / "fit"
    (root / "study.toml").write_text(TINY.split("[demo]")[0])
    argv = [
        "fit",
        str(out / "logs" / "study.parquet"),
        "-o",
        str(fit_out),
        "--config",
        str(root / "study.toml"),
    ]
    assert main([*argv, "--no-progress"]) == 0
    a = json.loads((out / "fitted_sve.json").read_text())
    b = json.loads((fit_out / "fitted_sve.json").read_text())
    assert a["objective"] == pytest.approx(b["objective"], rel=1e-6)
    # It ends as the demo does: a header, then the headline in a few indented lines, not a bare path.
    # (The rerun resumes every stage.)
    capsys.readouterr()
    assert main([*argv, "--no-progress"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert re.fullmatch(r"jsve fit: fitted and reported in \d+ s", lines[0]), lines
    assert lines[1:] == [f"  {line}" for line in summary_lines(fit_out)]
    assert re.fullmatch(r"  recommended: fitted-(sve|inliers) \(rule file .*/fitted_\1\.json, .*\)", lines[1])
    assert any(line.startswith("    vs sve-option2: ") for line in lines)
    assert lines[-1] == f"  report: {fit_out / 'report.html'}"
    assert main([*argv, "--no-progress", "--no-report"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("jsve fit: fitted in ")
    assert lines[-1] == f"  report: not written (`jsve report {fit_out}` writes it)"


def test_demo_in_a_folder_of_another_configuration_stops_and_names_force(tmp_path, capsys, monkeypatch):
    """Logs simulated under another seed stop `jsve demo` before anything is written (one line naming
    --force, exit 2); with --force the logs are simulated again under the demo's key and the study is
    told to discard its stale stages (the fit and the report are stubbed: they have their own tests)."""
    from jsve.fitting import _study
    from jsve.report import _report
    from jsve.sim._config import SimConfig
    from jsve.sim._study import write_study
    from jsve.sim._trajectory import FlightProfile

    out = tmp_path / "demo"
    small = dict(procedural=1, disturbances="blur:0", runs=1, workers=1, progress=False)
    sim = SimConfig(flight=FlightProfile(duration_s=(6.0, 6.0)))
    write_study(out / "logs", seed=1, config=sim, **small)
    (log,) = (out / "logs").rglob("*.csv")
    before = log.read_bytes()
    cfg = tmp_path / "small.toml"
    cfg.write_text(TINY.replace("sequences = 2", "sequences = 1").replace("12.0, 12.0", "6.0, 6.0")
                   .replace('"blur:0:50,occlusion:0:450"', '"blur:0"'))  # fmt: skip
    argv = ["demo", "-o", str(out), "--config", str(cfg), "--seed", "0", "--workers", "1", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jsve demo: {out / 'logs'} holds outputs of another job")
    assert "--force" in err[0]
    assert log.read_bytes() == before and sorted(p.name for p in out.iterdir()) == ["logs"]

    calls = []
    monkeypatch.setattr(_study, "run_study", lambda *a, **kw: calls.append(kw["force"]) or {})
    monkeypatch.setattr(_report, "write_report", lambda *a, **kw: None)
    monkeypatch.setattr(_report, "summary_lines", lambda out, **kw: [f"report: {out}"])
    assert main([*argv, "--force"]) == 0
    assert calls == [True]
    write_study(tmp_path / "fresh", seed=0, config=sim, **small)
    (fresh,) = (tmp_path / "fresh").rglob("*.csv")
    (log,) = (out / "logs").rglob("*.csv")
    assert log.read_bytes() == fresh.read_bytes() != before  # the demo's seed-0 log, not the old one
