"""Many tracking logs at once: find them and read them in parallel, with quarantine.

    find_logs(source)                    the sorted log files of a directory, glob or list
    read_logs(source)                    many logs, in parallel, sorted, raise or quarantine
    write_quarantine_report(result, p)   the logs set aside, as CSV

Consolidating them into one Parquet file, and reading it back, is jsve.io._parquet's.

Each log is read and validated by `jsve.io._logs.read_log` (in worker processes for large batches);
docs/log-format.md describes the batch behaviour, the quarantine report and the Parquet layout. Format
v1 logs read with `schema.v1_defaults`; a batch gives one `LogVersionWarning` for all of them.
"""

from __future__ import annotations

import collections
import glob as globlib
import logging
import math
import multiprocessing
import os
import sys
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pandas as pd
import pyarrow as pa
from tqdm.auto import tqdm

from jsve.io import _atomic as atomic
from jsve.io import _schema as schema
from jsve.io._errors import LogVersionWarning
from jsve.io._groundtruth import GroundTruth, GroundTruthSpec, apply_ground_truth, load_ground_truth
from jsve.io._log_batches import iter_parsed
from jsve.io._logs import (
    PARTIAL_SUFFIX,
    TRAILERS_KEY,
    LogFormatError,
    LogIncompleteError,
    read_log_table,
    read_log_version,
    run_from_table,
    unreadable,
)
from jsve.io._saved_trajectory import in_saved_frame
from jsve.io._schema import RunLog
from jsve.io._study_table import run_rows
from jsve.io._workers import process_pool

# The log reader's logger: read_log's warnings in worker processes are collected from it (_read_chunk)
# and re-logged here, and users configure one name for all of them.
logger = logging.getLogger(__name__)

QUARANTINE_COLUMNS = ("path", "line", "column", "reason", "message", "incomplete")
"""Columns of the quarantine report (`ReadResult.report()`, `write_quarantine_report`)."""

_V1_SHOWN = 3  # v1 logs named in the summary warning of a batch

LOG_SUFFIXES = (".csv", ".csv.gz")
"""Name endings of a log in a directory, compared without case (`.CSV` too); each also with
PARTIAL_SUFFIX (an unfinished log, reported as incomplete). A gzip log is read whatever its name
(jsve.io._text.file_bytes)."""

_SIDE_FILES = (".quarantine.csv", ".keypoints.csv", ".orbslam3.txt", ".orbslam3-euroc.txt", ".summary.json",
               ".console.txt", "orbslam3_settings.yaml")  # fmt: skip
"""jsve's own files that a directory search skips without a word: quarantine reports, keypoint side
files (jsve.io._keypoints), gzipped or not, and what `jsve frontend run` writes beside each log
(ORB-SLAM3's trajectory, the run's summary and console, scaled settings; jsve.frontend._run)."""

_SKIPPED_SHOWN = 5  # files that are not logs named in the warning of a directory search

_MIN_LOGS_PER_WORKER = 8  # below 16 logs in all, starting processes (~1 s) costs more than it saves
_MAX_WORKER_WARNINGS = 20  # warnings from worker processes re-emitted per batch, then one summary line

OnError = Literal["raise", "quarantine"]


# --------------------------------------------------------------------------------------------------
# Many logs


@dataclass(frozen=True)
class Quarantined:
    """A log that was set aside, with why.

    Attributes:
        path: the file.
        line: 1-based line of the defect, or None.
        column: column / metadata key / column range, or None.
        reason: what is wrong.
        message: the full LogFormatError message.
        incomplete: True when the log is incomplete (its writer did not finish).
    """

    path: str
    line: int | None
    column: str | None
    reason: str
    message: str
    incomplete: bool = False

    @classmethod
    def from_error(cls, err: LogFormatError) -> Quarantined:
        return cls(err.path, err.line, err.column, err.reason, str(err), isinstance(err, LogIncompleteError))


@dataclass
class ReadResult:
    """What `read_logs` returns: the valid runs in sorted path order, and every log set aside."""

    runs: list[RunLog]
    quarantined: list[Quarantined] = field(default_factory=list)

    def report(self) -> pd.DataFrame:
        """One row per quarantined log; columns QUARANTINE_COLUMNS (line as nullable Int64)."""
        df = pd.DataFrame(
            [[getattr(q, c) for c in QUARANTINE_COLUMNS] for q in self.quarantined],
            columns=list(QUARANTINE_COLUMNS),
        )
        return df.astype({"line": "Int64", "incomplete": bool})


def write_quarantine_report(result: ReadResult | Sequence[Quarantined], path: str | os.PathLike) -> Path:
    """Write the quarantine report (one row per quarantined log) as CSV, atomically.

    Arguments:
        result: a ReadResult, or the list of Quarantined entries.
        path: destination CSV.
    """
    if not isinstance(result, ReadResult):
        result = ReadResult(runs=[], quarantined=list(result))
    return atomic.write_table(result.report(), path)


def find_logs(source: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str]:
    """The log files of `source`, sorted.

    Arguments:
        source: a directory (searched recursively for `*.csv` and `*.csv.gz` in any case, and both
            with `.partial`, skipping jsve's own `*.quarantine.csv` reports and `*.keypoints.csv` side
            files; any other file is named in one warning), a single file, a glob pattern ('**'
            recursive), or a list of paths (taken as given).

    Raises:
        FileNotFoundError: the path does not exist or the pattern matches nothing.
    """
    if isinstance(source, (str, os.PathLike)):
        text = os.fspath(source)
        path = Path(text)
        if path.is_dir():
            files = _logs_in(path)
        elif path.exists():
            files = [text]
        elif any(ch in text for ch in "*?["):
            files = [p for p in globlib.glob(text, recursive=True) if os.path.isfile(p)]
            if not files:
                raise FileNotFoundError(f"no files match {text!r}")
        else:
            raise FileNotFoundError(f"no such file or directory: {text!r}")
    else:
        files = [os.fspath(p) for p in source]
    return sorted(set(files))


def is_log_name(name: str) -> bool:
    """Whether a file name is a log's in a directory search: `*.csv` or `*.csv.gz` (any case), or either
    with PARTIAL_SUFFIX, and not one of jsve's side files (`*.quarantine.csv`, `*.keypoints.csv`)."""
    name = name.lower().removesuffix(PARTIAL_SUFFIX)
    return name.endswith(LOG_SUFFIXES) and not name.removesuffix(".gz").endswith(_SIDE_FILES)


def _logs_in(folder: Path) -> list[str]:
    """The logs under `folder` (recursive); the other files are named in one warning, never dropped
    without a word (a log archived under a name the search does not know would be lost)."""
    logs, others = [], []
    for p in folder.rglob("*"):
        if not p.is_file():
            continue
        if is_log_name(p.name):
            logs.append(os.fspath(p))
        elif not p.name.lower().removesuffix(".gz").endswith(_SIDE_FILES):
            others.append(os.fspath(p.relative_to(folder)))
    if others:
        others.sort()
        shown = ", ".join(others[:_SKIPPED_SHOWN])
        more = f" and {len(others) - _SKIPPED_SHOWN} more" if len(others) > _SKIPPED_SHOWN else ""
        what = "1 file that is not a log" if len(others) == 1 else f"{len(others)} files that are not logs"
        logger.warning("%s: skipped %s (a log is named *.csv or *.csv.gz): %s%s", folder, what, shown, more)
    return logs


def _read_one(path: str, ground_truth) -> tuple[RunLog, int] | LogFormatError:
    """(run, format version) or the error; v1 logs are reported by the caller, once per batch."""
    try:
        return read_log_version(path, ground_truth=ground_truth)
    except LogFormatError as e:
        return e
    except OSError as e:
        return unreadable(path, e)


@dataclass(frozen=True)
class LogRows:
    """One valid log as `ingest` writes it: its entry in the file's run list, and its rows in the
    study layout (jsve.io._study_table.run_rows; without run_id)."""

    entry: dict
    rows: pa.Table

    @property
    def run_id(self) -> str:
        return self.entry["run_id"]


def read_rows_one(path: str, ground_truth) -> tuple[LogRows, int] | LogFormatError:
    """`_read_one` for `ingest`: (the log's rows, format version) or the error."""
    try:
        return _log_rows(path, *read_log_table(path), ground_truth)
    except LogFormatError as e:
        return e
    except OSError as e:
        return unreadable(path, e)


def _log_rows(path: str, meta: dict, version: int, table: pa.Table, ground_truth) -> tuple[LogRows, int]:
    """(LogRows, version) of a parsed log (read_log_table). A v2 log without ground truth to associate
    goes from Arrow's parse to the layout with no pandas frame."""
    saved = TRAILERS_KEY in (table.schema.metadata or {}) and schema.KEYFRAME_COLUMNS[0] in table.column_names
    if version >= 2 and ground_truth is None and not saved:
        columns = {c: table.column(c) for c in table.column_names}
    else:
        run = run_from_table(meta, version, table, path)
        if ground_truth is not None:
            run = apply_ground_truth(run, ground_truth)  # adds gt_* and their metadata
        if saved:  # the saved trajectory's poses and in_saved (jsve.io._saved_trajectory)
            run = in_saved_frame(run)
        meta, columns = run.meta, {c: run.frames[c].to_numpy() for c in run.frames.columns}
    entry = {
        "run_id": schema.run_id(meta),
        "source": path,
        "meta": meta,
        "n_frames": table.num_rows,
        "has_ground_truth": all(c in columns for c in schema.GT_COLUMNS),
        "has_world_frame": all(c in columns for c in schema.WORLD_COLUMNS),
        # map_id / imu_ba2 of a v1 log are schema.v1_defaults, not recorded values.
        "log_version": version,
    }
    return LogRows(entry, run_rows(columns, table.num_rows)), version


def _iter_rows_batched(paths: list[str], *, threads: int, progress: bool, stop_on_error: bool):
    """(path, (LogRows, version) | LogFormatError) in path order: `_iter_read` with reader=read_rows_one,
    for logs without ground truth to associate, read in batches parsed as one (jsve.io._log_batches)
    on Arrow's threads in this process: nothing is pickled between processes."""
    bar = tqdm(total=len(paths), disable=not progress, file=sys.stderr, unit="log", desc="reading logs")
    try:
        parsed = iter_parsed(paths, threads=threads, stop_on_error=stop_on_error, on_batch=bar.update)
        for path, result in parsed:
            yield path, result if isinstance(result, LogFormatError) else _log_rows(path, *result, None)
    finally:
        bar.close()


def warn_v1_logs(paths: list[str], stacklevel: int) -> None:
    """One LogVersionWarning for every v1 log of a batch: how many, which defaults, the first few."""
    if not paths:
        return
    shown = ", ".join(paths[:_V1_SHOWN])
    more = f" and {len(paths) - _V1_SHOWN} more" if len(paths) > _V1_SHOWN else ""
    noun = "log" if len(paths) == 1 else "logs"
    warnings.warn(
        f"{len(paths)} v1 {noun} read with defaults: {schema.V1_DEFAULTS_TEXT} ({shown}{more}; "
        "docs/log-format.md, 'Reading v1 logs: defaults')",
        LogVersionWarning,
        stacklevel=stacklevel + 1,
    )


class _Collect(logging.Handler):
    def __init__(self, records: list):
        super().__init__(logging.WARNING)
        self.records = records

    def emit(self, record: logging.LogRecord) -> None:
        record.msg, record.args, record.exc_info = record.getMessage(), None, None
        self.records.append(record)


def _read_chunk(paths: list[str], ground_truth, stop_on_error: bool, reader=_read_one):
    """Worker: read a chunk of logs with `reader` (_read_one or read_rows_one); warnings are returned
    to the parent to be logged there."""
    records: list = []
    handler = _Collect(records)
    logger.addHandler(handler)
    propagate, logger.propagate = logger.propagate, False
    try:
        out = []
        for p in paths:
            result = reader(p, ground_truth)
            out.append((p, result))
            if stop_on_error and isinstance(result, LogFormatError):
                break
        return out, records
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _mp_context():
    # Not fork: the parent may hold JAX's (or Arrow's) threads, and fork with threads can deadlock.
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["jsve.io._ingest"])
        return ctx
    return multiprocessing.get_context("spawn")


def _iter_read(
    paths: list[str],
    *,
    workers: int | None,
    progress: bool,
    ground_truth,
    stop_on_error: bool,
    reader=_read_one,
):
    """(path, reader's result: (RunLog or LogRows, version) | LogFormatError) in the order of `paths`,
    read in parallel chunks."""
    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    bar = tqdm(total=len(paths), disable=not progress, file=sys.stderr, unit="log", desc="reading logs")
    try:
        if workers == 1 or len(paths) < _MIN_LOGS_PER_WORKER * 2:
            for p in paths:
                result = reader(p, ground_truth)
                bar.update(1)
                yield p, result
            return
        chunk = max(1, min(16, math.ceil(len(paths) / (4 * workers))))
        chunks = iter([paths[i : i + chunk] for i in range(0, len(paths), chunk)])
        executor = process_pool(min(workers, len(paths)), _mp_context())
        try:
            pending = collections.deque()
            # A bounded window of chunks in flight keeps memory flat however many logs there are.
            for c in chunks:
                pending.append(executor.submit(_read_chunk, c, ground_truth, stop_on_error, reader))
                if len(pending) >= 2 * workers:
                    break
            n_warnings = 0
            while pending:
                out, records = pending.popleft().result()
                for record in records:
                    n_warnings += 1
                    if n_warnings <= _MAX_WORKER_WARNINGS:
                        logger.handle(record)
                nxt = next(chunks, None)
                if nxt is not None:
                    pending.append(executor.submit(_read_chunk, nxt, ground_truth, stop_on_error, reader))
                for p, result in out:
                    bar.update(1)
                    yield p, result
            if n_warnings > _MAX_WORKER_WARNINGS:
                logger.warning("... and %d more warnings like these", n_warnings - _MAX_WORKER_WARNINGS)
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()


def good_runs(
    paths, *, on_error: OnError, workers, progress, ground_truth, quarantined: list, reader=_read_one
) -> Iterator[tuple]:
    """(valid run, its format version) in path order, each run a RunLog (or LogRows with
    reader=read_rows_one); bad logs raise (on_error='raise') or go to `quarantined`."""
    if on_error not in ("raise", "quarantine"):
        raise ValueError(f"on_error must be 'raise' or 'quarantine', got {on_error!r}")
    seen: dict[str, str] = {}
    if reader is read_rows_one and ground_truth is None:
        results = _iter_rows_batched(
            paths,
            threads=(os.cpu_count() or 1) if workers is None else int(workers),
            progress=progress,
            stop_on_error=on_error == "raise",
        )
    else:
        results = _iter_read(
            paths,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            stop_on_error=on_error == "raise",
            reader=reader,
        )
    for path, result in results:
        version = None
        if not isinstance(result, LogFormatError):
            result, version = result
        if not isinstance(result, LogFormatError) and result.run_id in seen:
            result = LogFormatError(
                path,
                1,
                f"duplicate run id: '{result.run_id}' is also the run id of {seen[result.run_id]} "
                "(sequence/disturbance-level/run must be unique)",
            )
        if isinstance(result, LogFormatError):
            if on_error == "raise":
                results.close()
                raise result
            quarantined.append(Quarantined.from_error(result))
            continue
        seen[result.run_id] = path
        yield result, version


def read_logs(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    on_error: OnError = "raise",
    workers: int | None = None,
    progress: bool = True,
    ground_truth: GroundTruthSpec | None = None,
) -> ReadResult:
    """Read and validate many logs in parallel.

    Arguments:
        source: a directory (recursive `*.csv`, `*.csv.gz` and both with `.partial`), a glob, a file
            or a list of paths (see `find_logs`). `.partial` files are always reported as incomplete,
            never skipped.
        on_error: "raise" stops at the first bad log in sorted path order with its LogFormatError;
            "quarantine" sets bad logs aside in ReadResult.quarantined (nothing is dropped silently).
        workers: processes (default os.cpu_count()); 1, or fewer than 16 logs, reads in this process.
            Processes start with multiprocessing's "forkserver" method (not fork: the caller may hold
            JAX's threads), so a script that calls this needs the usual `if __name__ == "__main__":`.
        progress: tqdm progress bar on stderr.
        ground_truth: associated with logs that carry none (see `read_log`); must be picklable.

    Returns:
        ReadResult(runs in sorted path order, quarantined). A run id (RunLog.run_id) met a second time
        is an error naming both files (the later file is the one raised or quarantined).

    Warns:
        LogVersionWarning: once, when v1 logs were read (how many, the defaults used, the first few
            paths), instead of one warning per log.
    """
    return read_logs_at(source, on_error, workers, progress, ground_truth, stacklevel=3)


def check_ground_truth(spec: GroundTruthSpec | None) -> None:
    """Read every ground-truth file of `spec` once, in this process, before any log is read: a missing or
    malformed file is that file's error, never blamed on each log (or quarantining every log).

    Raises:
        LogFormatError: `GT_FILE: cannot read the ground-truth file: REASON`, or the reader's error naming
            the file's line.
    """
    if spec is None:
        return
    specs = list(spec.values()) if isinstance(spec, Mapping) else [spec]
    for gt in specs:
        gt = gt if isinstance(gt, GroundTruth) else GroundTruth(os.fspath(gt))
        try:
            load_ground_truth(gt.path, gt.fmt, kitti_times=gt.kitti_times)
        except OSError as e:
            name = e.filename if e.filename is not None else gt.path
            raise LogFormatError(
                os.fspath(name), None, f"cannot read the ground-truth file: {e.strerror or e}"
            ) from None


def read_logs_at(source, on_error, workers, progress, ground_truth, *, stacklevel: int) -> ReadResult:
    """read_logs, its warnings attributed `stacklevel` frames up (to the caller of the public function
    that calls this one)."""
    paths = find_logs(source)
    check_ground_truth(ground_truth)
    quarantined: list[Quarantined] = []
    read = list(
        good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
        )
    )
    runs = [run for run, _ in read]
    warn_v1_logs([run.source for run, version in read if version == 1], stacklevel)
    return ReadResult(runs=runs, quarantined=quarantined)
