"""Simulated studies on disk: `write_study`, parallel (jsve.io._scheduler) and resumable.

    write_study("out/", sequences=..., disturbances="seed", runs=...)   out/<seq>/<dist>-<level>/run_<k>.csv
    study_size(...)                                                     what it would write, before it does
    log_path(out, sequence, setting, run)                               where a run's log goes

A run's log is written atomically with the generator's key in its metadata; a re-run keeps the logs of
the same key, rewrites none, and stops on logs of another key (or replaces them with force).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import logging
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from jsve.io import _scheduler
from jsve.io import _schema as schema
from jsve.io._resume import differences, stop_if_stale
from jsve.sim._config import SimConfig
from jsve.sim._recording import SequenceSpec, generator_key, make_recording
from jsve.sim._simulate import Setting, _as_specs, settings, simulate_setting
from jsve.sim._trajectory import FlightProfile, euroc_file_stem

logger = logging.getLogger(__name__)


def log_path(out_dir: str | os.PathLike, sequence: str, setting: Setting, run: int) -> Path:
    """Where write_study puts a log: OUT/<sequence>/<disturbance>-<level>/run_<k>.csv."""
    return Path(out_dir) / sequence / setting.label / f"run_{run:03d}.csv"


@dataclass
class StudyResult:
    """What write_study did: logs written and skipped (already complete), seconds, and timing parts."""

    written: int = 0
    skipped: int = 0
    seconds: float = 0.0
    simulate_s: float = 0.0
    write_s: float = 0.0
    paths: list[Path] = field(default_factory=list)
    parquet: Path | None = None


@dataclass(frozen=True)
class _Job:
    spec: SequenceSpec
    todo: tuple[tuple[Setting, tuple[int, ...]], ...]  # (setting, runs still to write)
    out_dir: str
    seed: int
    config: SimConfig


def _is_complete(path: Path) -> bool:
    """A log is complete when its last line is the end marker (write_log's rename makes a finished
    file appear whole; checking the tail also rejects a file truncated by other means)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 64))
            tail = f.read().rstrip().rsplit(b"\n", 1)[-1]
        return tail.startswith(schema.END_MARKER.encode())
    except OSError:
        return False


def _run_job(job: _Job) -> tuple[int, float, float, list[str]]:
    """All pending logs of one sequence: its recording is built once, in one process. Returns (logs
    written, seconds simulating, seconds writing, the logs' paths relative to job.out_dir)."""
    from jsve.io._logs import write_log

    simulate_s = write_s = 0.0
    started = time.perf_counter()
    recording = make_recording(job.spec, job.seed, job.config)
    simulate_s += time.perf_counter() - started
    paths = []
    for setting, runs in job.todo:
        started = time.perf_counter()
        logs = simulate_setting(recording, setting, runs, job.seed, job.config)
        simulated = time.perf_counter()
        for run in logs:
            path = log_path(job.out_dir, job.spec.name, setting, run.meta["run"])
            write_log(run, path)
            paths.append(str(path.relative_to(job.out_dir)))
        simulate_s += simulated - started
        write_s += time.perf_counter() - simulated
    return len(paths), simulate_s, write_s, paths


def _init_worker() -> None:
    # Workers run the small state-machine scan only: keep them off any accelerator (one process per
    # core would otherwise each claim the GPU's memory).
    os.environ.setdefault("JAX_PLATFORMS", "cpu")


def _sequence_size(spec: SequenceSpec, flight: FlightProfile = FlightProfile()) -> float:
    """Frames of a sequence, for scheduling: the ground-truth file's lines, or a procedural flight's
    expected length (the middle of its duration range)."""
    if spec.procedural:
        return 0.5 * (flight.duration_s[0] + flight.duration_s[1]) * flight.fps
    stem = euroc_file_stem(spec.name)
    try:
        with open(Path(spec.euroc_gt) / f"{stem}_GT.txt", "rb") as f:
            return float(sum(1 for _ in f))
    except OSError:
        return 0.0


LOG_BYTES_PER_FRAME = 515
"""Bytes of a simulated log per frame, ground-truth columns included (the size of the logs of a
procedural flight under blur and occlusion), for study_size."""


def study_size(
    sequences: Sequence[str] | str | None = None,
    *,
    procedural: int | None = None,
    euroc_gt: str | os.PathLike | None = None,
    disturbances: str | Iterable[str] = "seed",
    runs: int | Sequence[int] = 10,
    flight: FlightProfile = FlightProfile(),
) -> tuple[int, float, float]:
    """What write_study would write, before it writes: (logs, mean frames per log, estimated bytes).

    Frames come from each sequence's ground-truth file (a procedural flight's expected length under
    `flight`, SimConfig.flight), bytes from LOG_BYTES_PER_FRAME. Other arguments as write_study.
    """
    specs = _as_specs(sequences, euroc_gt, procedural)
    n_runs = runs if isinstance(runs, int) else len(runs)
    per_sequence = len(settings(disturbances)) * n_runs
    logs = len(specs) * per_sequence
    frames = sum(_sequence_size(spec, flight) for spec in specs) * per_sequence
    return logs, frames / max(logs, 1), frames * LOG_BYTES_PER_FRAME


def _recorded_generator(path: Path) -> dict | None:
    """The `generator` metadata of a log's line 1 (None when it has none or the line is unreadable)."""
    try:
        with open(path, "rb") as f:
            line = f.readline(1 << 20)
        meta = json.loads(line[line.index(b"{") :])
    except (OSError, ValueError):
        return None
    return meta.get("generator") if isinstance(meta, dict) else None


def _stale_logs(out_dir: Path, keys: dict[str, dict]) -> list[tuple[Path, str]]:
    """(log, what differs) for every complete log under out_dir whose generator is not the job's: for
    the job's sequences the whole key (keys[name]), for others all but the input files (a folder holds
    one study: one seed, model and configuration)."""
    if not out_dir.is_dir():
        return []
    some = next(iter(keys.values()))
    stale = []
    for path in sorted(out_dir.glob("*/*/run_*.csv")):
        if not _is_complete(path):
            continue  # rewritten anyway
        expected = keys.get(path.parent.parent.name)
        recorded = _recorded_generator(path) or {}
        if expected is None:
            recorded = {k: v for k, v in recorded.items() if k != "inputs"}
            expected = {k: v for k, v in some.items() if k != "inputs"}
        if recorded != expected:
            stale.append((path, differences(recorded, expected) if recorded else "no generator key"))
    return stale


def write_study(
    out_dir: str | os.PathLike,
    sequences: Sequence[str] | str | None = None,
    *,
    procedural: int | None = None,
    euroc_gt: str | os.PathLike | None = None,
    disturbances: str | Iterable[str] = "seed",
    runs: int | Sequence[int] = 10,
    seed: int = 0,
    workers: int | None = None,
    config: SimConfig = SimConfig(),  # noqa: B008
    progress: bool = True,
    parquet: bool = False,
    force: bool = False,
    scheduler: str | None = None,
) -> StudyResult:
    """Simulate a study and write one format-v3 log per run under out_dir (see log_path).

    Resumable: a complete log is kept when it was simulated under the same generator key (generator_key:
    seed, model, SimConfig, input files' content; recorded in its metadata), so a re-run after an
    interruption finishes the rest (jsve.io._logs.write_log writes `.partial` files and renames them,
    and stale ones are removed). A folder that holds a log of another key (another seed, --imu,
    configuration or ground truth; or a log written before the key existed) is never mixed with new
    logs: StaleOutputError, unless force=True, which deletes those logs (and out_dir/study.parquet)
    and simulates them again where the study includes them.
    Parallel: one task per sequence (its recording built once), longest first, run where `scheduler`
    says (jsve.io._scheduler: "local", the default, an embedded Dask LocalCluster of `workers` processes,
    default all cores; "processes", a process pool; or a Dask scheduler's address, whose workers must
    see out_dir and the ground truth under the same absolute paths); one worker or one sequence runs
    in this process. The progress bar advances as sequences finish. parquet=True then consolidates
    all logs into out_dir/study.parquet with jsve.io._logs.ingest.

    Raises:
        StaleOutputError: out_dir holds logs of another generator key (and force is False).
        OutputError: out_dir or a log cannot be written.
        SchedulerError: `scheduler` names no scheduler, or its workers run another jsve.
    """
    from tqdm.auto import tqdm

    from jsve.io import _atomic as atomic

    started = time.perf_counter()
    scheduler = _scheduler.check_scheduler(scheduler)  # a wrong value fails before any work
    out_dir = Path(out_dir)
    specs = _as_specs(sequences, euroc_gt, procedural)
    grid = settings(disturbances)
    run_ids = list(range(runs)) if isinstance(runs, int) else list(runs)
    keys = {spec.name: generator_key(spec, seed, config) for spec in specs}
    stale = _stale_logs(out_dir, keys)
    if not force:
        stop_if_stale(out_dir, stale, "logs simulated under another generator key")
    redo = {path for path, _ in stale}
    result = StudyResult()
    jobs = []
    for spec in specs:
        todo = []
        for setting in grid:
            paths = {r: log_path(out_dir, spec.name, setting, r) for r in run_ids}
            runs_left = tuple(r for r in run_ids if paths[r] in redo or not _is_complete(paths[r]))
            result.skipped += len(run_ids) - len(runs_left)
            if runs_left:
                todo.append((setting, runs_left))
        if todo:
            # Absolute paths: a cluster's worker does not share this process's working folder.
            folders = {f: getattr(spec, f) for f in ("euroc_gt", "timestamps", "imu") if getattr(spec, f)}
            worker_spec = dataclasses.replace(spec, **{f: _scheduler.absolute(v) for f, v in folders.items()})
            jobs.append(_Job(worker_spec, tuple(todo), _scheduler.absolute(out_dir), int(seed), config))
    partials = list(out_dir.rglob("*.partial")) if out_dir.is_dir() else []
    if jobs or stale or partials or parquet:
        atomic.check_writable(out_dir)  # before any work: a folder that cannot take the logs fails now
    deleted = [*redo, *([out_dir / "study.parquet"] if stale else []), *partials]
    for path in deleted:
        try:
            path.unlink(missing_ok=True)
        except OSError as error:
            raise atomic.output_error(error, path) from error
    if stale:
        logger.info("%s: %d logs of another generator key deleted (force)", out_dir, len(stale))
    # One job per sequence (each recording built once), the biggest first so that the processes
    # finish together (longest-processing-time-first scheduling).
    jobs.sort(key=lambda j: -sum(len(r) for _, r in j.todo) * _sequence_size(j.spec))
    workers = workers or os.cpu_count() or 1
    total = sum(len(r) for j in jobs for _, r in j.todo)
    outcomes = []
    with tqdm(total=total, desc="simulate", unit="log", disable=not progress) as bar:
        if _scheduler.in_process(workers, scheduler, len(jobs)):
            for job in jobs:
                outcomes.append(_run_job(job))
                bar.update(outcomes[-1][0])
        else:
            with _scheduler.executor(min(workers, len(jobs)), scheduler, initializer=_init_worker) as pool:
                futures = [pool.submit(_run_job, job) for job in jobs]
                for future in concurrent.futures.as_completed(futures):
                    outcomes.append(future.result())
                    bar.update(outcomes[-1][0])
    for n, sim_s, write_s, paths in outcomes:
        result.written += n
        result.simulate_s += sim_s
        result.write_s += write_s
        result.paths.extend(out_dir / p for p in paths)
    if parquet:
        from jsve.io._parquet import ingest

        result.parquet = out_dir / "study.parquet"
        ingest(str(out_dir), result.parquet, workers=workers, progress=progress)
    result.seconds = time.perf_counter() - started
    return result


__all__ = ["write_study", "log_path", "StudyResult", "study_size", "LOG_BYTES_PER_FRAME"]
