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

    for name in ("ape", "rpe", "table1", "evaluate"):
        assert choices([name], "--align") == tuple(ALIGN_METHODS), name


def test_format_and_error_choices_are_the_library_lists():
    from jsve.core._trajectory import SEGMENT_MODES
    from jsve.io._groundtruth import GT_FORMATS
    from jsve.io._ingest import OnError
    from jsve.io._trajectories import TRAJECTORY_FORMATS

    assert choices(["ape"], "--format") == choices(["table1"], "--format") == TRAJECTORY_FORMATS
    assert choices(["rpe"], "--format") == TRAJECTORY_FORMATS
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


# --------------------------------------------------------------------------------------------------
# Outputs that cannot be written: one line, exit 2, nothing left (common.guarded, jsve.io._atomic)


def _tum(path, shift: float = 0.0):
    rows = [f"{1.0 + 0.1 * k:.1f} {0.1 * k + shift} {0.02 * k} 0 0 0 0 1" for k in range(20)]
    path.write_text("\n".join(rows) + "\n")
    return str(path)


def _logs(folder, n: int = 2):
    from jsve.io import write_log

    for k in range(n):
        write_log(make_run(60, seed=k, sequence="S", run=k), folder / f"r{k}.csv")
    return str(folder)


def _dataset(root):
    import cv2
    import numpy as np

    data = root / "mav0" / "cam0" / "data"
    data.mkdir(parents=True)
    t = 1403715273262142976
    cv2.imwrite(str(data / f"{t}.png"), np.random.default_rng(0).integers(0, 255, (48, 64), np.uint8))
    (root / "mav0" / "cam0" / "data.csv").write_text(f"#t,filename\n{t},{t}.png\n")
    return str(root)


def _argv(command: str, tmp, out) -> list[str]:
    """A call of `command` that writes to `out` (its inputs made under `tmp`)."""
    ref, est = _tum(tmp / "ref.txt"), _tum(tmp / "est.txt", 0.01)
    if command in ("ingest", "evaluate", "fit"):
        logs = _logs(tmp / "logs") if not (tmp / "logs").exists() else str(tmp / "logs")
    return {
        "ingest": lambda: ["ingest", logs, "-o", str(out / "study.parquet"), "--no-progress",
                           "--workers", "1"],
        "simulate": lambda: ["simulate", "-o", str(out), "--procedural", "1", "--disturbances",
                             "occlusion:450", "--runs", "1", "--workers", "1", "--no-progress"],
        "evaluate": lambda: ["evaluate", logs, "--rule", "orbslam3", "-o", str(out), "--no-progress"],
        "ape": lambda: ["ape", ref, est, "-o", str(out / "ape.csv")],
        "rpe": lambda: ["rpe", ref, est, "-o", str(out / "rpe.csv")],
        "fit": lambda: ["fit", logs, "-o", str(out), "--no-progress", "--no-report"],
        "table1": lambda: ["table1", "--ref", ref, "--original", est, "--masked", est, "--format", "tum",
                           "-o", str(out), "--no-plots"],
        "disturb": lambda: ["disturb", _dataset(tmp / "SEQ"), "-o", str(out), "--disturbance", "blur",
                            "--levels", "5", "--workers", "1", "--no-progress"],
    }[command]()  # fmt: skip


WRITERS = ("ingest", "simulate", "evaluate", "ape", "rpe", "fit", "table1", "disturb")


def _one_error_line(capsys, command: str, path, reason: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"jsve {command}: cannot write {path}"), err
    assert err[-1].endswith(reason) and "Traceback" not in "\n".join(err), err


@pytest.mark.parametrize("command", WRITERS)
def test_an_output_under_a_file_is_one_line_and_exit_2(command, tmp_path, capsys):
    """-o naming a path whose parent is a regular file (how tests running as root make a folder
    unwritable: chmod does not stop root)."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    out = blocker / "out"
    assert main(_argv(command, tmp_path, out)) == 2
    _one_error_line(capsys, command, out, "Not a directory")
    assert blocker.read_text() == "a file, not a folder"


@pytest.mark.parametrize("command", ["fit", "evaluate", "table1", "disturb"])
def test_an_output_folder_that_is_a_file_is_one_line_and_exit_2(command, tmp_path, capsys):
    out = tmp_path / "taken"
    out.write_text("mine")
    assert main(_argv(command, tmp_path, out)) == 2
    _one_error_line(capsys, command, out, "exists and is not a folder")
    assert out.read_text() == "mine"


def test_an_output_file_that_is_a_folder_is_one_line_and_exit_2(tmp_path, capsys):
    out = tmp_path / "ape.csv"
    out.mkdir()
    argv = _argv("ape", tmp_path, tmp_path)
    assert main(argv) == 2
    _one_error_line(capsys, "ape", out, "is a folder")
    assert out.is_dir() and not list(out.iterdir())


@pytest.mark.parametrize("command", WRITERS)
def test_a_full_disk_is_one_line_exit_2_and_no_partial_output(command, tmp_path, capsys, monkeypatch):
    """ENOSPC from the writer (every output's rename, jsve.io._atomic._commit; OpenCV's imwrite for
    disturb's images): one line naming the output, exit 2, and no file left in the output folder."""
    import errno

    from jsve.image import _datasets
    from jsve.io import _atomic as atomic

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "out"
    argv = _argv(command, tmp_path, out)  # the inputs, written before the disk fills
    monkeypatch.setattr(atomic, "_commit", full)
    monkeypatch.setattr(_datasets.cv2, "imwrite", full)
    assert main(argv) == 2
    _one_error_line(capsys, command, out, "No space left on device")
    assert [p for p in out.rglob("*") if p.is_file()] == []


GT_HEAD = "#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z"
GT_ROW = "{t},1.0,2.0,3.0,1.0,0.0,0.0,0.0"
BAD_GT = {
    # what the --gt file holds -> what the one line says
    "nan": ("1403715274312143104,1.0,nan,3.0,1,0,0,0", "gt.csv:4: column 'p_y' = 'nan': NaN or inf"),
    "zero quaternion": ("1403715274312143104,1,2,3,0,0,0,0", "gt.csv:4: columns 'q_w..q_z' = '0 0 0 0'"),
    "stamps back": ("1403715274000000000,1,2,3,1,0,0,0", "gt.csv: timestamps not strictly increasing"),
    "not text": (
        b"\x80\xff\x00".decode("latin-1"),
        "gt.csv: not a readable euroc ground-truth file: not UTF-8",
    ),
}


@pytest.mark.parametrize("defect", BAD_GT)
@pytest.mark.parametrize("mode", ["raise", "quarantine"])
def test_a_bad_value_in_the_gt_file_is_one_line_and_exit_2(defect, mode, tmp_path, capsys):
    """A --gt file with a value jsve refuses is that file's one-line error, before any log is read:
    never a traceback, never a quarantined log, nothing written."""
    logs = tmp_path / "logs"
    logs.mkdir()
    from jsve.io import write_log

    for k in range(2):
        write_log(make_run(30, seed=k, with_gt=False, sequence="S", run=k), logs / f"r{k}.csv")
    row, reason = BAD_GT[defect]
    gt = tmp_path / "gt.csv"
    rows = [GT_ROW.format(t=1403715274212143104 + k * 50_000_000) for k in range(2)] + [row]
    gt.write_bytes("\n".join([GT_HEAD, *rows, ""]).encode("latin-1"))
    argv = ["ingest", str(logs), "-o", str(tmp_path / "s.parquet"), "--gt", str(gt), "--on-error", mode]
    assert main([*argv, "--no-progress", "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jsve ingest: --gt: {tmp_path / reason}"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.csv", "logs"]


def test_guarded_turns_an_input_files_error_into_one_line(capsys):
    """Wherever a command lets a log's or a trajectory file's error through, it is one line and exit 2;
    other errors stay tracebacks (they are jsve's bugs)."""
    import argparse

    from jsve.io._errors import LogFormatError, TrajectoryFileError

    def raising(error):
        @common.guarded("ingest")
        def run(args):
            raise error

        return run(argparse.Namespace())

    assert raising(TrajectoryFileError.at("gt.txt", 7, "NaN or inf is not allowed", "p_x", "nan")) == 2
    assert (
        capsys.readouterr().err == "jsve ingest: gt.txt:7: column 'p_x' = 'nan': NaN or inf is not allowed\n"
    )
    assert raising(LogFormatError("r.csv", 3, "imu_dt is negative")) == 2
    assert capsys.readouterr().err == "jsve ingest: r.csv:3: imu_dt is negative\n"
    with pytest.raises(KeyError):
        raising(KeyError("a bug"))


def test_a_missing_gt_file_is_the_gt_files_error_and_nothing_is_quarantined(tmp_path, capsys):
    logs = tmp_path / "logs"
    logs.mkdir()
    from jsve.io import write_log

    for k in range(2):
        write_log(make_run(30, seed=k, with_gt=False, sequence="S", run=k), logs / f"r{k}.csv")
    missing = tmp_path / "V101_GT.txt"
    out = tmp_path / "study.parquet"
    for mode in ("raise", "quarantine"):
        argv = [
            "ingest",
            str(logs),
            "-o",
            str(out),
            "--gt",
            str(missing),
            "--on-error",
            mode,
            "--no-progress",
        ]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            f"jsve ingest: --gt: {missing}: cannot read the ground-truth file: No such file or directory"
        ]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["logs"]
