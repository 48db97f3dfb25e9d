"""What the subcommands share: options whose choices come from the library, reading runs, errors.

Subcommand modules use this module, never each other. Like them, it imports library code only inside
functions, so that `jsve --help` stays free of JAX and pandas: a `register()` that calls an `add_*`
helper pays for the import of the constants its choices come from, and only when its command runs.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

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
# Options


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
    from jsve.core import ALIGN_METHODS

    parser.add_argument("--align", choices=tuple(ALIGN_METHODS), default="se3", help=help)


def add_switch_model_option(parser: argparse.ArgumentParser) -> None:
    """--switch-model: the pose of a frame in RECENTLY_LOST (jsve.core._machine.SWITCH_MODELS)."""
    from jsve.core._machine import SWITCH_MODELS

    parser.add_argument(
        "--switch-model",
        choices=SWITCH_MODELS,
        default=None,
        help="orbslam3 (default): a tracked frame keeps its logged pose, as ORB-SLAM3 v1.0 does; "
        "imu-coast: a frame in RECENTLY_LOST takes the IMU prediction (docs/state-machine.md)",
    )


def add_support_option(parser: argparse.ArgumentParser) -> None:
    """--support: what the objective does with a run whose replay leaves the log's support
    (jsve.core._objective.SUPPORT_POLICIES)."""
    from jsve.core._objective import SUPPORT_POLICIES

    parser.add_argument(
        "--support",
        choices=SUPPORT_POLICIES,
        default=None,
        help="a run whose replay needs a recorded pose the log lacks has an unknown outcome: penalise "
        "(default) scores it as failed, exclude drops the run-rule pair from the objective "
        "(docs/fitting.md)",
    )


def add_segments_option(parser: argparse.ArgumentParser) -> None:
    """--segments: which map segment of a run is scored (jsve.core._trajectory.run_error)."""
    from jsve.core._trajectory import SEGMENT_MODES

    parser.add_argument(
        "--segments",
        default="largest",
        choices=SEGMENT_MODES,
        help="which map segment of a run is scored (default: largest)",
    )


def on_error_choices() -> tuple[str, ...]:
    """What a batch read does with a bad log: jsve.io's OnError ("raise", "quarantine")."""
    from typing import get_args

    from jsve.io._ingest import OnError

    return get_args(OnError)


def add_trajectory_options(parser: argparse.ArgumentParser, *, default_format: str) -> None:
    """--format, --n-to-align and --t-max-diff: how trajectory files are read and paired
    (jsve.io._trajectories)."""
    from jsve.io._trajectories import TRAJECTORY_FORMATS

    parser.add_argument(
        "--format",
        choices=TRAJECTORY_FORMATS,
        default=default_format,
        help=f"file format (default: {default_format})",
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


# --------------------------------------------------------------------------------------------------
# Inputs


def load_runs(command: str, source: str, *, on_error: OnError, workers: int | None, progress: bool):
    """The runs of LOGS (a Parquet file from `jsve ingest`, or logs on disk), each quarantined log
    reported on stderr as `jsve COMMAND: quarantined <message>`.

    Raises:
        LogFormatError, OSError: as jsve.io.load_runs.
    """
    from jsve.io._ingest import load_runs as read

    result = read(source, on_error=on_error, workers=workers, progress=progress)
    for q in result.quarantined:
        print(f"jsve {command}: quarantined {q.message}", file=sys.stderr)
    return result.runs
