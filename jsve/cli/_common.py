"""What the subcommands share: the parser class, options whose choices come from the library, reading
runs, errors.

Subcommand modules use this module, never each other. Like them, it imports library code only inside
functions, and an option's choices from the library are LibraryNames, read when argparse first needs
them (a value to check, a help to print): building any parser, the full one included, imports no
library, so `jsve --help` and `jsve frontend-include` start in about 0.1 s.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args, get_origin

if TYPE_CHECKING:
    from jsve.io._ingest import OnError


def fail(command: str, message) -> int:
    """Print `jsve COMMAND: message` to stderr; returns 2, the exit status of an unusable input."""
    print(f"jsve {command}: {message}", file=sys.stderr)
    return 2


FORCE_HINT = "--force discards them and recomputes"


def guarded(command: str) -> Callable:
    """Decorator of a subcommand's `run`: the two errors of its outputs as one line and exit status 2,
    never a traceback.

    - jsve.io._atomic.OutputError (an output that cannot be written: read-only folder, full disk, a
      path of the wrong kind): `jsve COMMAND: cannot write PATH: REASON`. Commands write through
      jsve.io._atomic, which leaves no partial file (and, inside all_or_nothing, no partial set).
    - jsve.io._resume.StaleOutputError (a resumed job whose folder holds outputs of other inputs or
      another configuration): `jsve COMMAND: FOLDER holds outputs of another job (WHAT); --force ...`.

    And, wherever a command has not caught them itself, the errors of an input file
    (jsve.io._errors.LogFormatError, TrajectoryFileError: a log, a trajectory or a ground-truth file),
    whose messages name the file and line: `jsve COMMAND: FILE:LINE: ...`.
    """

    def decorate(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
        @functools.wraps(run)
        def checked(args: argparse.Namespace) -> int:
            try:
                return run(args)
            except OSError as error:
                from jsve.io._atomic import OutputError  # here: `jsve --help` imports no pandas

                if isinstance(error, OutputError):
                    return fail(command, error)
                raise
            except Exception as error:
                from jsve.io._errors import LogFormatError, TrajectoryFileError
                from jsve.io._resume import StaleOutputError

                if isinstance(error, StaleOutputError):
                    hint = FORCE_HINT if hasattr(args, "force") else "use another output folder"
                    return fail(command, f"{error}; {hint}")
                if isinstance(error, (LogFormatError, TrajectoryFileError)):
                    return fail(command, error)  # an input file's own error: it names file and line
                raise

        return checked

    return decorate


# --------------------------------------------------------------------------------------------------
# Parsers


def states_default(text: str) -> bool:
    """Whether a help text states a default: `(default: X)`, `X (default)`, `Default: X`."""
    return re.search(r"\(default\b|\bdefault:", text, re.IGNORECASE) is not None


class HelpFormatter(argparse.HelpFormatter):
    """Every option's help says its default: `(default: VALUE)` is appended where the help does not
    state one (states_default; a flag's default is `off`; an option whose default is None must say in
    words what happens without it, which tests/test_cli.py checks)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            not action.option_strings  # a positional
            or action.required
            or action.default is argparse.SUPPRESS
            or states_default(text)
        ):
            return text
        if action.nargs == 0 and not action.default:  # store_true
            return f"{text} (default: off)"
        if action.default is None or action.default == []:
            return text
        return f"{text} (default: %(default)s)"


class RawDescriptionHelpFormatter(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """HelpFormatter for a description laid out by hand (kept as written)."""


class ArgumentParser(argparse.ArgumentParser):
    """The parser of `jsve` and of each subcommand: HelpFormatter unless told otherwise."""

    def __init__(self, *args, formatter_class: type[argparse.HelpFormatter] = HelpFormatter, **kwargs):
        super().__init__(*args, formatter_class=formatter_class, **kwargs)


class LibraryValue:
    """A value that lives in the library (a default to state in a help), read when first printed: never
    when the option is registered, so building a parser imports no library and the value is never
    re-typed. Put it on the option's action and name it in the help: `action.penalty =
    LibraryValue(...)`, `help="... (default: %(penalty)s m)"`.

    Arguments:
        module: the dotted name of the module that defines it. attribute: its name there.
        scale: a factor for a number shown in another unit (1e-6: ns shown as ms).
    """

    def __init__(self, module: str, attribute: str, scale: float = 1.0):
        self.module, self.attribute, self.scale = module, attribute, scale

    @functools.cached_property
    def value(self):
        return getattr(importlib.import_module(self.module), self.attribute)

    def __str__(self) -> str:
        return f"{self.value * self.scale:g}" if isinstance(self.value, (int, float)) else str(self.value)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.module}.{self.attribute})"


class LibraryNames(LibraryValue, Sequence):
    """Names that live in the library (an option's choices, a list in a help), read when argparse first
    needs them: to check a value or print a help, never when the option is registered. So building a
    parser imports no library, and the names stay the library's own, never re-typed.

    An option with LibraryNames as its choices needs a metavar (argparse would list the choices in its
    usage line when the option is added); `%(choices)s` in its help lists them; str() lists them too,
    for a list in a help text (as LibraryValue).

    Arguments:
        module: the dotted name of the module that defines them.
        attribute: the name of a tuple or dict (its keys) of names, or of a typing.Literal.
    """

    def __init__(self, module: str, attribute: str):
        super().__init__(module, attribute)

    @functools.cached_property
    def names(self) -> tuple[str, ...]:
        value = self.value
        return tuple(get_args(value) if get_origin(value) is Literal else value)

    def __getitem__(self, index):
        return self.names[index]

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __contains__(self, value) -> bool:
        return value in self.names

    def __str__(self) -> str:
        return ", ".join(self.names)


# --------------------------------------------------------------------------------------------------
# Options


def add_output_option(parser: argparse.ArgumentParser, *, metavar: str, help: str, **kwargs) -> None:
    """-o/--output, every command's spelling of what it writes (`--out`, the earlier spelling of some
    commands, still works: argparse takes a unique prefix of an option)."""
    parser.add_argument("-o", "--output", dest="output", metavar=metavar, help=help, **kwargs)


def add_force_option(parser: argparse.ArgumentParser) -> None:
    """--force: discard outputs of another job (other inputs or configuration) in the output folder
    instead of stopping (jsve.io._resume)."""
    parser.add_argument(
        "--force",
        action="store_true",
        help="the output folder holds outputs of other inputs or another configuration: discard them "
        "and recompute (without it the command stops, exit 2; it never mixes the two)",
    )


def add_align_option(parser: argparse.ArgumentParser, help: str | None = None) -> None:
    """--align, its choices jsve.core's alignment methods (default se3)."""
    parser.add_argument(
        "--align",
        choices=LibraryNames("jsve.core._align", "ALIGN_METHODS"),
        default="se3",
        metavar="METHOD",
        help=help or "alignment to the ground truth, one of %(choices)s",
    )


def add_switch_model_option(parser: argparse.ArgumentParser) -> None:
    """--switch-model: the pose of a frame in RECENTLY_LOST (jsve.core._machine.SWITCH_MODELS)."""
    parser.add_argument(
        "--switch-model",
        choices=LibraryNames("jsve.core._machine", "SWITCH_MODELS"),
        default=None,
        metavar="MODEL",
        help="orbslam3 (default): a tracked frame keeps its logged pose, as ORB-SLAM3 v1.0 does; "
        "imu-coast: a frame in RECENTLY_LOST takes the IMU prediction (docs/state-machine.md)",
    )


def add_support_option(parser: argparse.ArgumentParser) -> None:
    """--support: what the objective does with a run whose replay leaves the log's support
    (jsve.core._objective.SUPPORT_POLICIES)."""
    parser.add_argument(
        "--support",
        choices=LibraryNames("jsve.core._objective", "SUPPORT_POLICIES"),
        default=None,
        metavar="POLICY",
        help="a run whose replay needs a recorded pose the log lacks has an unknown outcome: penalise "
        "(default) scores it as failed, exclude drops the run-rule pair from the objective "
        "(docs/fitting.md)",
    )


def add_scoring_options(parser: argparse.ArgumentParser) -> None:
    """--failure, --min-coverage and --loss: what fails a run and what a tracked run costs
    (jsve.core._objective; docs/state-machine.md, "Scoring a run")."""
    parser.add_argument(
        "--failure",
        default="coverage",
        choices=LibraryNames("jsve.core._objective", "FAILURE_DEFINITIONS"),
        metavar="DEF",
        help="what fails a run: coverage (its saved trajectory covers less than --min-coverage of the "
        "frames, as the field counts failures) or strict (also any loss of tracking: a reset, an expiry, "
        "a new map); %(choices)s",
    )
    coverage = parser.add_argument(
        "--min-coverage",
        type=float,
        metavar="C",
        help="share of the frames with ground truth (0 to 1) the saved trajectory must cover, else the run "
        "failed (default: %(coverage)s)",
    )
    coverage.coverage = LibraryValue("jsve.core._objective", "DEFAULT_MIN_COVERAGE")
    parser.add_argument(
        "--loss",
        default="bounded",
        choices=LibraryNames("jsve.core._objective", "LOSSES"),
        metavar="LOSS",
        help="a tracked run's loss: bounded (its ATE capped at the failure penalty: a diverged run costs "
        "what a failed one costs) or raw (its ATE); %(choices)s",
    )


def add_on_error_option(parser: argparse.ArgumentParser) -> None:
    """--on-error: what a batch read does with a bad log (jsve.io._ingest.OnError)."""
    parser.add_argument(
        "--on-error",
        choices=LibraryNames("jsve.io._ingest", "OnError"),
        default="raise",
        metavar="MODE",
        help="raise: stop at the first bad log (exit 2); quarantine: set bad logs aside, list them on "
        "stderr and go on with the others",
    )


def add_trajectory_options(parser: argparse.ArgumentParser, *, default_format: str) -> None:
    """--format, --n-to-align and --t-max-diff: how trajectory files are read and paired
    (jsve.io._trajectories)."""
    parser.add_argument(
        "--format",
        choices=LibraryNames("jsve.io._trajectories", "TRAJECTORY_FORMATS"),
        default=default_format,
        metavar="FORMAT",
        help="file format: %(choices)s (default: %(default)s)",
    )
    parser.add_argument(
        "--n-to-align",
        "--n_to_align",
        dest="n_to_align",
        type=int,
        default=-1,
        metavar="N",
        help="align on the first N associated poses only (evo's --n_to_align; default -1: all)",
    )
    parser.add_argument(
        "--t-max-diff",
        "--t_max_diff",
        dest="t_max_diff",
        type=float,
        default=0.01,
        metavar="S",
        help="largest time difference in seconds for associating poses (tum, euroc; evo's --t_max_diff; "
        "default 0.01)",
    )


def n_first(n_to_align: int) -> int | None:
    """--n-to-align as `n_first` of jsve's alignment: None for -1 (all poses).

    Raises:
        ValueError: 0 or below -1.
    """
    if n_to_align == 0 or n_to_align < -1:
        raise ValueError(f"--n-to-align must be a positive number or -1 (all), got {n_to_align}")
    return None if n_to_align == -1 else n_to_align


def add_workers_option(
    parser: argparse.ArgumentParser, what: str = "processes reading the logs", *, default: int | None = None
) -> None:
    """--workers N: how many processes; default None: one per core."""
    parser.add_argument(
        "--workers",
        type=int,
        default=(os.cpu_count() or 1) if default is None else default,
        metavar="N",
        help=f"{what} (default: {'all cores' if default is None else default})",
    )


def add_progress_option(parser: argparse.ArgumentParser) -> None:
    """--no-progress: no progress bar (on stderr)."""
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def add_yes_option(parser: argparse.ArgumentParser) -> None:
    """--yes: write even when the size estimate (announce_size) exceeds the free disk space."""
    parser.add_argument(
        "--yes",
        action="store_true",
        help="write even when the estimated output is larger than the free space on its disk (without "
        "it the command stops before writing, exit 2)",
    )


# --------------------------------------------------------------------------------------------------
# Output size


def plural(n: int, word: str) -> str:
    """`1 log`, `3 logs`."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def format_bytes(n: float) -> str:
    """Bytes in decimal units with two or three digits: 512 B, 42 kB, 1.3 MB, 4.6 GB."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            value = n / scale
            return f"{value:.1f} {unit}" if value < 10 else f"{value:.0f} {unit}"
    return f"{n:.0f} B"


def _bytes_under(path: Path) -> int:
    """Bytes of the files at or under path (0 when it does not exist)."""
    if path.is_file():
        return path.stat().st_size
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except OSError:
                pass  # removed while we walk
    return total


def _free_bytes(path: Path) -> int:
    """Free bytes on the file system that path is (or would be) on: its nearest existing ancestor's."""
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def announce_size(
    command: str, output: str | os.PathLike, total: float, detail: str, *, yes: bool
) -> int | None:
    """Say on stderr how much COMMAND is about to write, before it writes; stop when it cannot fit.

    The line reads `jsve COMMAND: about 4.6 GB to write to OUT (DETAIL; 1.2 GB there already), 38 GB free`.
    Bytes already at or under `output` (a resumed job keeps its finished outputs) are taken off the
    estimate; when the rest exceeds the free space of output's disk the command stops (exit 2) unless
    `yes`, so that a study never fills the disk half-way.

    Arguments:
        output: the file or folder the command writes. total: estimated bytes of the whole output.
        detail: how total was estimated, e.g. "3400 logs x ~2600 frames x ~520 B".
        yes: --yes, write anyway.
    Returns:
        None to go on, or 2 (after printing why).
    """
    output = Path(output)
    there = _bytes_under(output) if output.exists() else 0
    to_write = max(0.0, total - there)
    free = _free_bytes(output)
    already = f"; {format_bytes(there)} there already" if there else ""
    print(
        f"jsve {command}: about {format_bytes(to_write)} to write to {output} ({detail}{already}), "
        f"{format_bytes(free)} free",
        file=sys.stderr,
    )
    if to_write > free and not yes:
        return fail(
            command,
            f"about {format_bytes(to_write)} to write but {format_bytes(free)} free on the disk of {output}; "
            "free space, choose another -o, or pass --yes to write anyway",
        )
    return None


# --------------------------------------------------------------------------------------------------
# Closing lines


def print_study_summary(header: str, out_dir: str | os.PathLike, *, report: bool = True) -> None:
    """The few lines `jsve demo` and `jsve fit` end with, for a person to read: a header (`jsve demo:
    done in 247 s`), then, indented, the study's headline (jsve.report._report.summary_lines: the
    recommended rule and its file, its held-out objective and differences to the baselines, how often it
    switches, where the report is).

    Arguments:
        report: whether the report was written (`jsve fit --no-report`: the last line says how to write it).
    """
    from jsve.report._report import summary_lines

    print(header)
    for line in summary_lines(out_dir, report=report):
        print(f"  {line}")


# --------------------------------------------------------------------------------------------------
# Inputs


def load_runs(command: str, source: str, *, on_error: OnError, workers: int | None, progress: bool):
    """The runs of LOGS (a Parquet file from `jsve ingest`, or logs on disk), each quarantined log
    reported on stderr as `jsve COMMAND: quarantined <message>`.

    Raises:
        LogFormatError, OSError: as jsve.io.load_runs.
    """
    from jsve.io._parquet import load_runs as read

    result = read(source, on_error=on_error, workers=workers, progress=progress)
    for q in result.quarantined:
        print(f"jsve {command}: quarantined {q.message}", file=sys.stderr)
    return result.runs


def use_all_cores() -> None:
    """Ask XLA for one CPU device per core, so that jsve.fitting's `search` runs its calls on every
    core. Effective only before JAX's backend starts, and only when XLA_FLAGS does not set a device
    count already. For the command line and scripts (it changes the process's environment): a library
    user decides this for their own process."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_force_host_platform_device_count={os.cpu_count() or 1}".strip()
        )
