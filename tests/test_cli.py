"""jsve.cli: the dispatcher lists every subcommand without importing a library, and builds only the
chosen subcommand's parser; options take their choices from the library; shared helpers."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from typing import get_args

import pytest
from logfactory import make_run, set_field

import jsve.cli
from jsve.cli import SUBCOMMANDS, main
from jsve.cli import _common as common

HEAVY = ("jax", "pandas", "numpy", "cv2", "matplotlib", "evo", "pyarrow")
"""Libraries that take from 0.1 s (numpy) to over a second (JAX) to import."""

# Runs the top-level help in a fresh interpreter and reports what it imported.
PROBE = """
import json, sys
import jsve.cli
try:
    jsve.cli.main({argv!r})
except SystemExit as exit:
    code = exit.code
else:
    code = None
loaded = sorted({{name.split(".")[0] for name in sys.modules}} & set({heavy!r}))
ours = sorted(name for name in sys.modules if name.startswith("jsve"))
print(json.dumps({{"code": code, "loaded": loaded, "jsve": ours}}))
"""


def probe(argv: list[str]) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def module(name: str):
    return importlib.import_module(f"jsve.cli.{name.replace('-', '_')}")


@pytest.mark.parametrize("argv", [["--help"], []])
def test_listing_the_subcommands_imports_no_library(argv):
    result = probe(argv)
    assert result["code"] == (0 if argv else None), result
    assert result["loaded"] == [], f"`jsve {' '.join(argv)}` imported {result['loaded']}"
    # Only the command's own package: the subcommand modules (for their HELP) and their shared helpers.
    assert all(m == "jsve" or m.startswith("jsve.cli") for m in result["jsve"]), result["jsve"]


def test_python_m_jsve_cli_help_lists_every_subcommand_with_its_summary():
    done = subprocess.run([sys.executable, "-m", "jsve.cli", "--help"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    listing = " ".join(done.stdout.split())  # argparse wraps long summaries
    for name in SUBCOMMANDS:
        assert f"{name} {module(name).HELP}" in listing, name


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_every_subcommand_help_works(name, capsys):
    with pytest.raises(SystemExit) as info:
        main([name, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: jsve {name} ")


def test_only_the_chosen_subcommand_is_built(monkeypatch):
    built = []
    original = jsve.cli._module

    def spy(name):
        mod = original(name)
        register = mod.register

        class Recording:
            HELP = mod.HELP

            @staticmethod
            def register(subparsers):
                built.append(name)
                register(subparsers)

        return Recording

    monkeypatch.setattr(jsve.cli, "_module", spy)
    with pytest.raises(SystemExit):
        main(["-v", "report", "--help"])
    assert built == ["report"]


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["no-such-command"])
    assert info.value.code == 2
    assert "invalid choice: 'no-such-command'" in capsys.readouterr().err


def test_full_parser_has_every_subcommand():
    parser = jsve.cli.build_parser()
    args = parser.parse_args(["ingest", "logs", "-o", "out.parquet"])
    assert args.func is module("ingest").run and args.on_error == "raise"


# --------------------------------------------------------------------------------------------------
# Choices come from the library


def choices(argv_prefix: list[str], option: str) -> tuple:
    parser = jsve.cli.build_parser([argv_prefix[0]])
    sub = next(a for a in parser._actions if a.dest == "command").choices[argv_prefix[0]]
    return tuple(next(a for a in sub._actions if option in a.option_strings).choices)


def test_alignment_choices_are_the_library_methods():
    from jsve.core import ALIGN_METHODS

    for name in ("ape", "table1", "evaluate"):
        assert choices([name], "--align") == tuple(ALIGN_METHODS), name


def test_format_and_error_choices_are_the_library_lists():
    from jsve.core._trajectory import SEGMENT_MODES
    from jsve.io._groundtruth import GT_FORMATS
    from jsve.io._ingest import OnError
    from jsve.io._trajectories import TRAJECTORY_FORMATS

    assert choices(["ape"], "--format") == choices(["table1"], "--format") == TRAJECTORY_FORMATS
    assert choices(["ingest"], "--gt-format") == GT_FORMATS
    for name in ("ingest", "evaluate", "fit"):
        assert choices([name], "--on-error") == get_args(OnError), name
    assert choices(["evaluate"], "--segments") == SEGMENT_MODES


# --------------------------------------------------------------------------------------------------
# Shared helpers


def test_load_runs_reports_quarantined_logs_under_the_command(tmp_path, capsys):
    from jsve.io import _logs as logs

    for i in range(3):
        logs.write_log(make_run(20, i), tmp_path / f"r{i}.csv")
    set_field(tmp_path / "r1.csv", 9, "imu_dt", "-0.05")
    runs = common.load_runs("fit", str(tmp_path), on_error="quarantine", workers=1, progress=False)
    assert [r.source for r in runs] == [str(tmp_path / "r0.csv"), str(tmp_path / "r2.csv")]
    err = capsys.readouterr().err
    assert err.startswith(f"jsve fit: quarantined {tmp_path / 'r1.csv'}:9: column 'imu_dt' = '-0.05'")


def test_n_to_align():
    assert common.n_first(-1) is None and common.n_first(200) == 200
    for bad in (0, -2):
        with pytest.raises(
            ValueError, match=rf"--n-to-align must be a positive number or -1 \(all\), got {bad}"
        ):
            common.n_first(bad)


def test_fail_names_the_command(capsys):
    assert common.fail("ape", ValueError("b.tum holds no poses")) == 2
    assert capsys.readouterr().err == "jsve ape: b.tum holds no poses\n"
