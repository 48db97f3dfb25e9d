"""The consolidated Parquet study, written and read whole.

    ingest(source, out)      many logs -> one Parquet file (validated, streamed in row groups, atomic)
    read_parquet(out)        the file -> RunLogs, exactly as ingested
    load_runs(source)        a Parquet file from `ingest`, or logs as jsve.io._ingest.read_logs takes them

The layout is jsve.io._study_table's; reading a study in bounded memory, chunk by chunk, is
jsve.io._stream's. docs/log-format.md describes the file for people.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from jsve.io import _atomic as atomic
from jsve.io import _schema as schema
from jsve.io._errors import LogVersionWarning
from jsve.io._groundtruth import GroundTruthSpec
from jsve.io._ingest import (
    LogRows,
    OnError,
    Quarantined,
    ReadResult,
    check_ground_truth,
    find_logs,
    good_runs,
    logger,
    read_logs_at,
    read_rows_one,
    warn_v1_logs,
    write_quarantine_report,
)
from jsve.io._logs import (
    with_v1_defaults,
)
from jsve.io._saved_trajectory import SAVED_COLUMN
from jsve.io._schema import RunLog
from jsve.io._stream import (
    PARQUET_FORMAT_KEY,
    PARQUET_FORMAT_VERSION,
    PARQUET_RUNS_KEY,
    check_run_rows,
    open_study,
)
from jsve.io._study_table import PARQUET_SCHEMA, PARQUET_WRITE_OPTIONS, row_group

_ROW_GROUP_ROWS = 262_144  # Parquet row group target: ~70 runs of 3,600 frames, ~200 MB in memory


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
        batch: list[LogRows] = []
        batch_rows = 0
        runs = good_runs(
            paths,
            on_error=on_error,
            workers=workers,
            progress=progress,
            ground_truth=ground_truth,
            quarantined=quarantined,
            reader=read_rows_one,
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

    warn_v1_logs(v1, 2)
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
    return read_logs_at(source, on_error, workers, progress, ground_truth, stacklevel=3)


__all__ = ["IngestSummary", "default_quarantine_report_path", "ingest", "read_parquet", "load_runs"]
