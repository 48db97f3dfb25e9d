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
    from jsve.core._objective import FAILURE_DEFINITIONS, LOSSES
    from jsve.io._groundtruth import GT_FORMATS
    from jsve.io._ingest import OnError
    from jsve.io._trajectories import TRAJECTORY_FORMATS

    assert choices(["ape"], "--format") == choices(["table1"], "--format") == TRAJECTORY_FORMATS
    assert choices(["rpe"], "--format") == TRAJECTORY_FORMATS
    assert choices(["ingest"], "--gt-format") == GT_FORMATS
    for name in ("ingest", "evaluate", "fit"):
        assert choices([name], "--on-error") == get_args(OnError), name
    assert choices(["evaluate"], "--failure") == FAILURE_DEFINITIONS
    assert choices(["evaluate"], "--loss") == LOSSES


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
        "simulate": lambda: ["simulate", "-o", str(out), "--procedural", "1", "--duration", "30",
                             "--disturbances", "occlusion:450", "--runs", "1", "--workers", "1",
                             "--no-progress"],
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


# --------------------------------------------------------------------------------------------------
# Every parser, built in full: no library imported, every option documented, one spelling per concept

# Runs in a fresh interpreter: builds every subcommand's parser, as `jsve COMMAND` does for one.
BUILD_ALL = """
import json, sys
import jsve.cli
jsve.cli.build_parser()
print(json.dumps(sorted({{name.split(".")[0] for name in sys.modules}} & set({heavy!r}))))
"""

SLOW_TO_IMPORT = ("jax", "pandas", "matplotlib", "evo", "cv2", "pyarrow")
"""What `import jsve.cli` and building its parser must not import (each takes 0.2 s to over a second);
numpy (0.1 s, for `frontend vocabulary`'s options) is allowed."""


def test_building_every_parser_imports_no_library():
    """Registering every subcommand's options reads nothing from the library: choices and defaults that
    live there are LibraryNames / LibraryValue, read when a value is checked or a help printed. Then
    `jsve --help`, `jsve frontend-include` and each `jsve COMMAND` start without JAX (README: timings)."""
    done = subprocess.run(
        [sys.executable, "-c", BUILD_ALL.format(heavy=SLOW_TO_IMPORT)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []


def test_library_choices_are_checked_when_parsing(capsys):
    parser = jsve.cli.build_parser(["evaluate"])
    assert parser.parse_args(["evaluate", "logs", "--align", "sim3"]).align == "sim3"
    with pytest.raises(SystemExit):
        parser.parse_args(["evaluate", "logs", "--align", "sim4"])
    assert "argument --align: invalid choice: 'sim4' (choose from 'se3', 'sim3'" in capsys.readouterr().err


def test_library_names_and_values_are_the_librarys():
    from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M
    from jsve.core._pose_error import POSE_RELATIONS
    from jsve.io._groundtruth import DEFAULT_MAX_GAP_NS

    relations = common.LibraryNames("jsve.core._pose_error", "POSE_RELATIONS")  # a dict: its keys
    assert tuple(relations) == tuple(POSE_RELATIONS) and "angle_deg" in relations and len(relations) == 4
    assert str(relations) == ", ".join(POSE_RELATIONS)
    assert str(common.LibraryValue("jsve.core._objective", "DEFAULT_FAILURE_PENALTY_M")) == (
        f"{DEFAULT_FAILURE_PENALTY_M:g}"
    )
    assert str(common.LibraryValue("jsve.io._groundtruth", "DEFAULT_MAX_GAP_NS", scale=1e-6)) == (
        f"{DEFAULT_MAX_GAP_NS / 1e6:g}"
    )


def parsers(parser=None, path=("jsve",)):
    """(command path, parser) of jsve and every subcommand, nested ones (frontend build) included."""
    import argparse

    parser = parser or jsve.cli.build_parser()
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from parsers(sub, (*path, name))


def options(parser):
    """The actions of a parser a user sees: all but -h, the subcommand list and hidden aliases (help
    argparse.SUPPRESS, test_hidden_options_are_aliases_of_visible_ones)."""
    import argparse

    return [
        a
        for a in parser._actions
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
        and a.help != argparse.SUPPRESS
    ]


def test_hidden_options_are_aliases_of_visible_ones():
    """An option hidden from the help (argparse.SUPPRESS) is only an earlier spelling kept so that old
    commands work: it sets the destination of a visible option, with the same type."""
    import argparse

    hidden = {}
    for path, parser in parsers():
        visible = {a.dest: a for a in options(parser)}
        for action in parser._actions:
            if action.help == argparse.SUPPRESS and action.option_strings:
                twin = visible.get(action.dest)
                assert twin is not None and twin.type is action.type, (path, action.option_strings)
                hidden[" ".join(path), action.option_strings[-1]] = twin.option_strings[-1]
    assert hidden == {("jsve demo", "--sequences"): "--flights"}


def test_demo_counts_flights_and_still_reads_the_earlier_sequences():
    parser = jsve.cli.build_parser(["demo"])
    assert parser.parse_args(["demo", "--flights", "2"]).flights == 2
    assert parser.parse_args(["demo", "--sequences", "2"]).flights == 2  # a command from before --flights
    assert parser.parse_args(["demo"]).flights is None  # --config's, else DemoConfig's
    demo = dict(parsers(parser))["jsve", "demo"]
    assert "--flights N" in demo.format_help() and "--sequences" not in demo.format_help()


def _help_gap(parser, action) -> str | None:
    """What a (sub)command's option lacks: a help, or (when it is optional) a stated default."""
    if not (action.help or "").strip():
        return "no help"
    shown = parser._get_formatter()._get_help_string(action)  # with the default appended, as printed
    required = action.required or "required" in shown.lower()
    if action.option_strings and not required and not common.states_default(shown):
        return f"no default stated in {shown!r}"
    return None


def test_every_option_has_a_help_and_states_its_default():
    """`jsve COMMAND --help` explains every option and shows its default: a value argparse fills in,
    or words for an option whose default is None ("default: print the summary only")."""
    gaps = {}
    for path, parser in parsers():
        for action in options(parser):
            key = (" ".join(path), (action.option_strings or [action.dest])[-1])
            gap = _help_gap(parser, action)
            if gap:
                gaps[key] = gap
    assert not gaps, gaps


def test_the_help_formatter_appends_defaults_once():
    parser = common.ArgumentParser(prog="x")
    parser.add_argument("--runs", type=int, default=10, help="runs per setting")
    parser.add_argument("--flag", action="store_true", help="a flag")
    parser.add_argument("--said", default=3, help="stated (default: three)")
    parser.add_argument("--none", help="no value")
    text = " ".join(parser.format_help().split())
    assert "runs per setting (default: 10)" in text and "a flag (default: off)" in text
    assert "stated (default: three) --none" in text and "no value" in text and "(default: None)" not in text


WRITES_OUTPUT = {
    # every command that writes files -> what it writes with -o/--output
    "jsve ingest": "the Parquet file",
    "jsve sve": "the CSV (default: standard output)",
    "jsve evaluate": "the tables",
    "jsve check": "the per-log table",
    "jsve ape": "the per-estimate table",
    "jsve rpe": "the per-estimate table",
    "jsve frontend build": "the build folder",
    "jsve frontend run": "the log folder",
    "jsve frontend vocabulary": "the vocabulary",
    "jsve disturb": "the datasets",
    "jsve measure": "the tables",
    "jsve table1": "the report",
    "jsve mask-logs": "the masked logs",
    "jsve simulate": "the logs",
    "jsve render": "the dataset",
    "jsve fit": "the study",
    "jsve demo": "the study and report",
    "jsve report": "the report (default: into the folder it reads)",
}


def test_every_writer_takes_dash_o_and_output_and_no_other_spelling():
    seen = set()
    for path, parser in parsers():
        command = " ".join(path)
        spellings = {s for a in options(parser) for s in a.option_strings}
        if command in WRITES_OUTPUT:
            seen.add(command)
            assert {"-o", "--output"} <= spellings, command
        if "-o" in spellings:  # one option, both spellings, the same destination
            action = parser._option_string_actions["-o"]
            assert parser._option_string_actions["--output"] is action, command
    assert seen == set(WRITES_OUTPUT), set(WRITES_OUTPUT) - seen


def test_the_earlier_out_spelling_still_works():
    """`--out` was simulate's, disturb's, render's, measure's and frontend's spelling: argparse takes it
    as the unique prefix of --output."""
    parser = jsve.cli.build_parser(["simulate", "frontend"])
    assert parser.parse_args(["simulate", "--out", "study"]).output == "study"
    argv = ["frontend", "build", "--orbslam3", "o", "--out", "b"]
    assert parser.parse_args(argv).output == "b"
    for spelling in ("-o", "--output", "--out"):  # --out was vocabulary's own spelling
        argv = ["frontend", "vocabulary", "images", spelling, "voc.txt"]
        assert parser.parse_args(argv).output == "voc.txt"


def test_sequences_names_sequences_everywhere():
    """--sequences is one thing in every command: comma-separated sequence names (a string). (`jsve demo
    --sequences N`, which counted flights, is a hidden alias of --flights.)"""
    found = {}
    for path, parser in parsers():
        for action in options(parser):
            if "--sequences" in action.option_strings:
                found[" ".join(path)] = action.type in (None, str) and "name" in action.help
    assert found.pop("jsve simulate")
    assert all(found.values()), found


# --------------------------------------------------------------------------------------------------
# Size estimates before writing


def test_announce_size_says_the_estimate_and_stops_before_filling_the_disk(tmp_path, capsys, monkeypatch):
    import collections

    Usage = collections.namedtuple("Usage", "total used free")
    out = tmp_path / "study"
    out.mkdir()
    (out / "done.csv").write_bytes(b"x" * 1000)  # a resumed job keeps this: 1 kB less to write
    monkeypatch.setattr(common.shutil, "disk_usage", lambda path: Usage(10**12, 0, 5 * 10**9))
    assert common.announce_size("simulate", out, 4.6e9, "3410 logs", yes=False) is None
    err = capsys.readouterr().err
    assert (
        err
        == f"jsve simulate: about 4.6 GB to write to {out} (3410 logs; 1.0 kB there already), 5.0 GB free\n"
    )
    # more than the free space: one line, exit 2, unless --yes
    assert common.announce_size("simulate", out / "sub", 6e9, "many logs", yes=False) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (
        f"jsve simulate: about 6.0 GB to write but 5.0 GB free on the disk of {out / 'sub'}; free space, "
        "choose another -o, or pass --yes to write anyway"
    )
    assert common.announce_size("simulate", out / "sub", 6e9, "many logs", yes=True) is None
    assert [common.format_bytes(n) for n in (512, 42e3, 1.26e6, 12.4e9)] == [
        "512 B",
        "42 kB",
        "1.3 MB",
        "12 GB",
    ]


def test_simulate_estimates_its_logs_within_a_quarter(tmp_path, capsys):
    """The printed estimate (frames of each sequence x LOG_BYTES_PER_FRAME) is what the logs weigh, to
    a quarter: enough to plan the disk (a procedural flight's length varies about its expected one)."""
    import re

    argv = ["simulate", "-o", str(tmp_path / "s"), "--procedural", "2", "--disturbances", "blur=0,30",
            "--runs", "1", "--workers", "1", "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if "to write to" in x)
    assert "(4 logs x ~2600 frames x ~515 B)" in line
    estimate = float(re.search(r"about ([\d.]+) MB", line).group(1)) * 1e6
    written = sum(p.stat().st_size for p in (tmp_path / "s").rglob("*.csv"))
    assert abs(estimate / written - 1) < 0.25, (estimate, written)


def test_ingest_estimates_its_parquet_file_within_a_half(tmp_path, capsys):
    import re

    from jsve.io import write_log

    logs = tmp_path / "logs"
    logs.mkdir()
    for k in range(3):
        write_log(make_run(400, seed=k, sequence="S", run=k), logs / f"r{k}.csv")
    out = tmp_path / "study.parquet"
    assert main(["ingest", str(logs), "-o", str(out), "--no-progress", "--workers", "1"]) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if "to write to" in x)
    estimate = float(re.search(r"about ([\d.]+) kB", line).group(1)) * 1e3
    # logfactory's logs compress less than simulated ones (random numbers): a half, not a quarter
    assert abs(estimate / out.stat().st_size - 1) < 0.5, (estimate, out.stat().st_size)


# --------------------------------------------------------------------------------------------------
# --disturbances NAME=LEVELS


def test_disturb_reads_levels_in_the_disturbances_spec_and_the_earlier_options():
    import argparse

    from jsve.cli import disturb

    known = ["blur", "occlusion", "noise"]

    def parse(**options):
        return disturb._disturbances(
            argparse.Namespace(**{"disturbances": None, "disturbance": None, "levels": None, **options}),
            known,
        )

    assert parse(disturbances="blur=5,15,occlusion") == (["blur", "occlusion"], {"blur": [5.0, 15.0]})
    assert parse(disturbances="blur=5,blur=5,25") == (["blur"], {"blur": [5.0, 25.0]})
    assert parse(disturbance="blur,occlusion", levels=["blur=5,15"]) == (
        ["blur", "occlusion"],
        {"blur": [5, 15]},
    )
    assert parse() == (known, {})
    with pytest.raises(ValueError, match="--disturbances replaces --disturbance and --levels"):
        parse(disturbances="blur", levels=["5"])
    with pytest.raises(ValueError, match="unknown disturbance 'fog'"):
        parse(disturbances="fog=3")
