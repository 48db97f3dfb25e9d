"""Many tracking logs at once: find, read in parallel with quarantine, and consolidate into Parquet.

    find_logs(source)                    the sorted log files of a directory, glob or list
    read_logs(source)                    many logs, in parallel, sorted, raise or quarantine
    write_quarantine_report(result, p)   the logs set aside, as CSV
    ingest(source, out)                  many logs -> one Parquet file;  read_parquet(out) -> RunLogs
    load_runs(source)                    a Parquet file from `ingest`, or logs as read_logs takes them

Each log is read and validated by `jsve.io._logs.read_log` (in worker processes for large batches);
docs/log-format.md describes the batch behaviour, the quarantine report and the Parquet layout. Format
v1 logs read with `schema.v1_defaults`; a batch gives one `LogVersionWarning` for all of them.
"""

from __future__ import annotations

import collections
import glob as globlib
import json
import logging
import math
import multiprocessing
import os
import sys
import warnings
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
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
    with_v1_defaults,
)
from jsve.io._saved_trajectory import SAVED_COLUMN, in_saved_frame
from jsve.io._schema import RunLog
from jsve.io._stream import (
    PARQUET_FORMAT_KEY,
    PARQUET_FORMAT_VERSION,
    PARQUET_RUNS_KEY,
    check_run_rows,
    open_study,
)
from jsve.io._study_table import PARQUET_SCHEMA, PARQUET_WRITE_OPTIONS, row_group, run_rows
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

_ROW_GROUP_ROWS = 262_144  # Parquet row group target: ~70 runs of 3,600 frames, ~200 MB in memory
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
class _LogRows:
    """One valid log as `ingest` writes it: its entry in the file's run list, and its rows in the
    study layout (jsve.io._study_table.run_rows; without run_id)."""

    entry: dict
    rows: pa.Table

    @property
    def run_id(self) -> str:
        return self.entry["run_id"]


def _read_rows_one(path: str, ground_truth) -> tuple[_LogRows, int] | LogFormatError:
    """`_read_one` for `ingest`: (the log's rows, format version) or the error."""
    try:
        return _log_rows(path, *read_log_table(path), ground_truth)
    except LogFormatError as e:
        return e
    except OSError as e:
        return unreadable(path, e)


def _log_rows(path: str, meta: dict, version: int, table: pa.Table, ground_truth) -> tuple[_LogRows, int]:
    """(_LogRows, version) of a parsed log (read_log_table). A v2 log without ground truth to associate
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
    return _LogRows(entry, run_rows(columns, table.num_rows)), version


def _iter_rows_batched(paths: list[str], *, threads: int, progress: bool, stop_on_error: bool):
    """(path, (_LogRows, version) | LogFormatError) in path order: `_iter_read` with reader=_read_rows_one,
    for logs without ground truth to associate, read in batches parsed as one (jsve.io._log_batches)
    on Arrow's threads in this process: nothing is pickled between processes."""
    bar = tqdm(total=len(paths), disable=not progress, file=sys.stderr, unit="log", desc="reading logs")
    try:
        parsed = iter_parsed(paths, threads=threads, stop_on_error=stop_on_error, on_batch=bar.update)
        for path, result in parsed:
            yield path, result if isinstance(result, LogFormatError) else _log_rows(path, *result, None)
    finally:
        bar.close()


def _warn_v1(paths: list[str], stacklevel: int) -> None:
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
    """Worker: read a chunk of logs with `reader` (_read_one or _read_rows_one); warnings are returned
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
    """(path, reader's result: (RunLog or _LogRows, version) | LogFormatError) in the order of `paths`,
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


def _good_runs(
    paths, *, on_error: OnError, workers, progress, ground_truth, quarantined: list, reader=_read_one
) -> Iterator[tuple]:
    """(valid run, its format version) in path order, each run a RunLog (or _LogRows with
    reader=_read_rows_one); bad logs raise (on_error='raise') or go to `quarantined`."""
    if on_error not in ("raise", "quarantine"):
        raise ValueError(f"on_error must be 'raise' or 'quarantine', got {on_error!r}")
    seen: dict[str, str] = {}
    if reader is _read_rows_one and ground_truth is None:
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
    return _read_logs(source, on_error, workers, progress, ground_truth, stacklevel=3)


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


def _read_logs(source, on_error, workers, progress, ground_truth, *, stacklevel: int) -> ReadResult:
    paths = find_logs(source)
    check_ground_truth(ground_truth)
    quarantined: list[Quarantined] = []
    read = list(
        _good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
        )
    )
    runs = [run for run, _ in read]
    _warn_v1([run.source for run, version in read if version == 1], stacklevel)
    return ReadResult(runs=runs, quarantined=quarantined)


def load_runs(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    on_error: OnError = "raise",
    workers: int | None = None,
    progress: bool = True,
    ground_truth: GroundTruthSpec | None = None,
) -> ReadResult:
    """The runs of a Parquet file written by `ingest`, or of logs on disk: what `jsve evaluate` and
    `jsve fit` accept as LOGS.

    Arguments:
        source: a `.parquet` file (read with `read_parquet`), else logs as `read_logs` takes them.
        on_error, workers, progress, ground_truth: as in `read_logs`; unused for a Parquet file, whose
            runs were validated (and given their ground truth) when it was written.

    Returns:
        ReadResult; nothing is quarantined from a Parquet file.
    """
    if isinstance(source, (str, os.PathLike)) and Path(source).name.endswith(".parquet"):
        return ReadResult(runs=_read_parquet(source, stacklevel=3))
    return _read_logs(source, on_error, workers, progress, ground_truth, stacklevel=3)


# --------------------------------------------------------------------------------------------------
# Parquet


@dataclass(frozen=True)
class IngestSummary:
    """What `ingest` did.

    Attributes:
        out_path: the Parquet file written.
        n_runs: runs written.
        n_frames: frames (rows) written.
        quarantined: logs set aside (on_error='quarantine').
        quarantine_report: the CSV report written, or None when nothing was quarantined.
    """

    out_path: Path
    n_runs: int
    n_frames: int
    quarantined: list[Quarantined]
    quarantine_report: Path | None

    def line(self) -> str:
        """A one-line summary for people."""
        text = (
            f"ingested {self.n_runs} runs, {self.n_frames} frames -> {self.out_path}; "
            f"quarantined {len(self.quarantined)}"
        )
        if self.quarantine_report is not None:
            text += f" (report: {self.quarantine_report})"
        return text


class _BackgroundWrites:
    """Row groups written on a thread of their own, one at a time, while the next logs are read (Arrow
    encodes without the GIL); an error of a write is raised by the next `write` or `wait`."""

    def __init__(self, writer: pq.ParquetWriter):
        self._writer = writer
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="jsve-parquet")
        self._pending: Future | None = None

    def write(self, table: pa.Table) -> None:
        self.wait()  # at most one row group in flight: memory stays at two row groups
        self._pending = self._pool.submit(self._writer.write_table, table)

    def wait(self) -> None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()

    def __enter__(self) -> _BackgroundWrites:
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None:
                self.wait()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


def default_quarantine_report_path(out_path: str | os.PathLike) -> Path:
    """`OUT.quarantine.csv` beside `OUT.parquet`."""
    return Path(out_path).with_suffix(".quarantine.csv")


def ingest(
    source: str | os.PathLike | Sequence[str | os.PathLike],
    out_path: str | os.PathLike,
    *,
    on_error: OnError = "raise",
    workers: int | None = None,
    progress: bool = True,
    ground_truth: GroundTruthSpec | None = None,
    quarantine_report: str | os.PathLike | None = None,
) -> IngestSummary:
    """Validate many logs (optionally associating ground truth) and consolidate them into one Parquet file.

    The file (layout PARQUET_SCHEMA) holds one row per frame: `run_id` (dictionary-encoded string),
    `frame` (int32, 0-based), then the v2 columns (v1 logs with their defaults); runs are contiguous,
    in sorted path order. The schema's key-value metadata holds b'jsve.runs': a JSON list of {run_id,
    source, meta, n_frames, has_ground_truth, has_world_frame, log_version}, one per run in file order, and
    b'jsve.format' = b'2'. Logs are streamed (row groups of ~260k frames), so memory stays flat. The
    file is written as `<out>.partial` and renamed when complete.

    Arguments:
        source: logs (see `find_logs`).
        out_path: the Parquet file.
        on_error, workers, progress, ground_truth: as in `read_logs`.
        quarantine_report: CSV path for the report of quarantined logs; default `OUT.quarantine.csv`
            beside the output. Written only when logs were quarantined (a stale report at the default
            path is removed).

    Returns:
        IngestSummary.

    Raises:
        LogFormatError: the first bad log, with on_error='raise' (nothing is written); a ground-truth
            file that cannot be read, whatever on_error (check_ground_truth; nothing is written).
        FileNotFoundError: no logs in `source`.
        OutputError: the Parquet file or the report cannot be written (nothing is left of them).

    Warns:
        LogVersionWarning: once, when v1 logs were read (see `read_logs`).
    """
    paths = find_logs(source)
    if not paths:
        raise FileNotFoundError(
            f"no tracking logs (*.csv, *.csv.gz, with or without .partial) in {os.fspath(source)!r}"
        )
    check_ground_truth(ground_truth)
    out = Path(out_path)
    quarantined: list[Quarantined] = []
    v1: list[str] = []
    entries = []
    n_frames = 0
    with (
        atomic.atomic_path(out) as tmp,
        pq.ParquetWriter(tmp, PARQUET_SCHEMA, **PARQUET_WRITE_OPTIONS) as writer,
        _BackgroundWrites(writer) as background,
    ):
        batch: list[_LogRows] = []
        batch_rows = 0
        runs = _good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
            reader=_read_rows_one,
        )
        for run, version in runs:
            if version == 1:
                v1.append(run.entry["source"])
            entries.append(run.entry)
            n_frames += run.entry["n_frames"]
            batch.append(run)
            batch_rows += run.entry["n_frames"]
            if batch_rows >= _ROW_GROUP_ROWS:
                background.write(row_group([r.run_id for r in batch], [r.rows for r in batch]))
                batch, batch_rows = [], 0
        if batch:
            background.write(row_group([r.run_id for r in batch], [r.rows for r in batch]))
        background.wait()
        writer.add_key_value_metadata(
            {
                PARQUET_RUNS_KEY: json.dumps(entries, allow_nan=False),
                PARQUET_FORMAT_KEY: str(PARQUET_FORMAT_VERSION),
            }
        )

    _warn_v1(v1, 2)
    default_report = default_quarantine_report_path(out)
    report = Path(quarantine_report) if quarantine_report is not None else default_report
    if quarantined:
        write_quarantine_report(quarantined, report)
        logger.warning("%d logs quarantined; see %s", len(quarantined), report)
    else:
        if quarantine_report is None and default_report.exists():
            logger.info("removing the stale quarantine report %s", default_report)
            default_report.unlink()
        report = None
    return IngestSummary(out, len(entries), n_frames, quarantined, report)


def read_parquet(path: str | os.PathLike) -> list[RunLog]:
    """Restore the runs of a Parquet file written by `ingest`, exactly (ints exact, floats bitwise).

    A file ingested before format v2 (`jsve.format` "1": no map_id / imu_ba2 columns) is read with
    `schema.v1_defaults` for every run and one `LogVersionWarning` naming the file.

    Returns:
        RunLogs in file order, with the metadata and source recorded at ingest; runs ingested without
        ground truth have no gt_* columns.

    Raises:
        LogFormatError: not a jsve Parquet file, a format version this reader does not know, or rows
            that disagree with its run list.
    """
    return _read_parquet(path, stacklevel=3)


def _read_parquet(path: str | os.PathLike, *, stacklevel: int) -> list[RunLog]:
    study = open_study(path)
    source, version, entries = study.path, study.version, study.entries
    table = pq.ParquetFile(source).read()
    check_run_rows(study, table, first_run=0, stop_run=study.n_runs)
    offsets = np.concatenate([[0], np.cumsum(study.lengths)])
    required = schema.required_columns(version)
    world = [c for c in schema.WORLD_COLUMNS if c in table.column_names]
    columns = {c: table.column(c).to_numpy() for c in required + schema.GT_COLUMNS + tuple(world)}
    saved = (
        table.column(SAVED_COLUMN).to_numpy(zero_copy_only=False).astype(np.float64)
        if SAVED_COLUMN in table.column_names
        else None
    )
    runs = []
    for e, start, stop in zip(entries, offsets[:-1], offsets[1:], strict=True):
        has_world = bool(e.get("has_world_frame", False))
        names = schema.column_order(version, e["has_ground_truth"], has_world)
        frames = pd.DataFrame({c: columns[c][start:stop].copy() for c in names}, columns=list(names))
        if version == 1:
            frames = with_v1_defaults(frames)
        if saved is not None and not np.isnan(saved[start]):  # poses of the saved trajectory's frame
            frames[SAVED_COLUMN] = saved[start:stop].astype(np.int64)
        runs.append(RunLog(meta=e["meta"], frames=frames, source=e["source"]))
    if version == 1:
        warnings.warn(
            f"{source}: jsve Parquet file of format 1 (ingested before format v2): its {len(runs)} runs "
            f"read with the v1 defaults {schema.V1_DEFAULTS_TEXT} (docs/log-format.md, 'Reading v1 "
            "logs: defaults'); ingest the logs again to write format 2",
            LogVersionWarning,
            stacklevel=stacklevel,
        )
    return runs
