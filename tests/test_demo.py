"""`jsve demo`, `jsve fit` and `jsve report` from the command line (small studies), and their configs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import tomllib

from jsve._demo import DEMO_STUDY, DemoConfig
from jsve.cli import SUBCOMMANDS, build_parser, main
from jsve.fitting._study import StudyConfig

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
    assert "no summary.parquet" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "missing"), "-o", str(tmp_path / "o2"), "--no-progress"]) == 2


@pytest.mark.slow
def test_demo_end_to_end_then_fit_on_its_logs(tmp_path, capsys):
    """A tiny demo (2 flights x 6 settings x 1 run) writes logs, every table and the report; `jsve fit`
    on its logs reproduces the demo's fitted SVE objective; `jsve report` re-renders the same page."""
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--config", str(cfg), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    timings = json.loads(printed.strip().splitlines()[-1])
    assert timings["total"] > 0 and "report.html" in printed
    assert (out / "logs" / "study.parquet").is_file() and (out / "report.html").is_file()
    page = (out / "report.html").read_text()
    fit_out = tmp_path / "fit"
    toml = "\n".join(line for line in TINY.split("[demo]")[0].splitlines())
    (tmp_path / "study.toml").write_text(toml)
    assert (
        main(
            [
                "fit",
                str(out / "logs" / "study.parquet"),
                "-o",
                str(fit_out),
                "--config",
                str(tmp_path / "study.toml"),
                "--no-progress",
            ]
        )
        == 0
    )
    a = json.loads((out / "fitted_sve.json").read_text())
    b = json.loads((fit_out / "fitted_sve.json").read_text())
    assert a["objective"] == pytest.approx(b["objective"], rel=1e-6)
    assert (
        main(["report", str(out), "--title", "jsve demo: fitted switching rules on a simulated study"]) == 0
    )
    assert (out / "report.html").read_text() == page


def test_demo_in_a_folder_of_another_configuration_stops_and_names_force(tmp_path, capsys, monkeypatch):
    """Logs simulated under another seed stop `jsve demo` before anything is written (one line naming
    --force, exit 2); with --force the logs are simulated again under the demo's key and the study is
    told to discard its stale stages (the fit and the report are stubbed: they have their own tests)."""
    from jsve.fitting import _study
    from jsve.report import _report
    from jsve.sim._motion import FlightProfile
    from jsve.sim._simulate import SimConfig, write_study

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
    assert main([*argv, "--force"]) == 0
    assert calls == [True]
    write_study(tmp_path / "fresh", seed=0, config=sim, **small)
    (fresh,) = (tmp_path / "fresh").rglob("*.csv")
    (log,) = (out / "logs").rglob("*.csv")
    assert log.read_bytes() == fresh.read_bytes() != before  # the demo's seed-0 log, not the old one
