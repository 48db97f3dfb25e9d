"""Where the front-end sweeps' tasks run: here, a process pool, an embedded Dask cluster or a remote one.

`jsve simulate`, `jsve disturb`, `jsve render` and `jsve frontend run` split their work into independent
tasks (a sequence's logs, a disturbed dataset, a chunk of frames, a driver run), each writing its outputs
through jsve.io._atomic (a `.partial` name renamed when complete), so a task killed anywhere leaves
nothing half-written and a re-run redoes only what is missing. `executor(workers, scheduler)` is the one
place that decides where those tasks run; every caller submits and collects with concurrent.futures
(`submit`, `as_completed`), so its progress bar and resume logic do not depend on the choice:

    local       (the default) an embedded dask.distributed LocalCluster: `workers` processes with one
                thread each, on loopback, no dashboard, logs at ERROR only
    processes   a concurrent.futures process pool (jsve.io._workers.process_pool): no Dask needed
    ADDRESS     a running Dask scheduler, `tcp://host:8786` (or `host:8786`), or the scheduler file
                (`scheduler.json`) that `dask scheduler --scheduler-file` and dask-jobqueue write:
                the cluster's workers run the tasks, however many it has (`workers` is not used)

A cluster's workers must import the same jsve (checked on connecting: its installed version) and see
the inputs and outputs under the same paths (a shared filesystem): callers hand them absolute paths.
One worker or one task without an address runs in this process (`in_process`), with no pool and no
cluster: starting a LocalCluster costs about 1.5 s (docs/scaling.md), a pool a fraction of that.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import logging
import multiprocessing
import os
import re
import threading
import uuid
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

LOCAL = "local"
PROCESSES = "processes"
DEFAULT_SCHEDULER = LOCAL
CONNECT_TIMEOUT_S = 30.0
"""Seconds to wait for a remote scheduler to answer before giving up."""

_URL = re.compile(r"^[a-z][a-z0-9+.-]*://\S+$")  # tcp://, tls://, ucx://, ws://, inproc://
_HOST_PORT = re.compile(r"^[\w.-]+:\d+$")

logger = logging.getLogger(__name__)


class SchedulerError(ValueError):
    """A --scheduler value that names no scheduler, or a cluster that cannot run jsve's tasks."""


def check_scheduler(scheduler: str | None) -> str:
    """The scheduler `scheduler` names, normalised: "local" (also for None), "processes", a Dask
    scheduler address (`host:port` becomes `tcp://host:port`) or the absolute path of a scheduler file.

    Raises:
        SchedulerError: anything else.
    """
    text = DEFAULT_SCHEDULER if scheduler is None else str(scheduler).strip()
    if text in (LOCAL, PROCESSES) or _URL.match(text):
        return text
    if text.endswith(".json"):
        if not Path(text).is_file():
            raise SchedulerError(f"--scheduler {text}: no such scheduler file")
        return str(Path(text).absolute())
    if _HOST_PORT.match(text):
        return f"tcp://{text}"
    raise SchedulerError(
        f"--scheduler {text!r}: expected local, processes, a Dask scheduler address (tcp://host:8786) "
        "or a scheduler file (scheduler.json)"
    )


def is_cluster(scheduler: str | None) -> bool:
    """Whether `scheduler` names a running Dask cluster (an address or a scheduler file)."""
    return check_scheduler(scheduler) not in (LOCAL, PROCESSES)


def in_process(workers: int, scheduler: str | None, tasks: int) -> bool:
    """Whether to run `tasks` tasks here, one after another: without a cluster address, when one worker
    is asked for or there is at most one task (a pool or a LocalCluster would only add its start-up)."""
    return not is_cluster(scheduler) and (workers <= 1 or tasks <= 1)


# The (initializer, initargs) this worker process last ran; a Dask worker outlives one sweep, so a task
# runs its sweep's initializer when the last one run here was another's.
_initialised: list[tuple[Callable, tuple]] = []
_initialising = threading.Lock()


def _call(initializer: Callable | None, initargs: tuple, function: Callable, *args):
    """function(*args) on a Dask worker, after initializer(*initargs) once per worker process (what a
    process pool's initializer does; a Dask worker has none per job)."""
    if initializer is not None:
        with _initialising:
            if _initialised != [(initializer, initargs)]:
                initializer(*initargs)
                _initialised[:] = [(initializer, initargs)]
    return function(*args)


def _name(function: Callable) -> str:
    while isinstance(function, functools.partial):
        function = function.func
    return getattr(function, "__name__", "task").strip("_")


class _DaskExecutor(concurrent.futures.Executor):
    """A Dask client's executor (Client.get_executor) that runs a worker initializer before tasks.

    Tasks are impure (they write files): never deduplicated by their arguments, never cached.
    """

    def __init__(self, client, initializer: Callable | None, initargs: tuple):
        self._inner = client.get_executor(pure=False)
        self._initializer, self._initargs = initializer, initargs

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        if kwargs:
            raise TypeError(
                "jsve's tasks take positional arguments only (bind others with functools.partial)"
            )
        key = f"jsve_{_name(fn)}-{uuid.uuid4().hex}"  # the dashboard groups tasks by "jsve_run_job"
        return self._inner.submit(_call, self._initializer, self._initargs, fn, *args, key=key)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait and not cancel_futures)


def _check_workers(client, where: str) -> None:
    """Fail early, with one line, when the cluster has no workers or its workers run another jsve."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("jsve")
    except PackageNotFoundError:  # running from a checkout: nothing to compare with
        return
    try:
        theirs = client.run(version, "jsve")
    except PackageNotFoundError as error:
        raise SchedulerError(
            f"{where}: a worker cannot find jsve ({error}); install jsve on every worker"
        ) from error
    if not theirs:
        logger.warning("%s: no workers yet; the tasks wait for some to join", where)
    other = {address: v for address, v in theirs.items() if v != ours}
    if other:
        raise SchedulerError(
            f"{where}: workers run another jsve ({', '.join(f'{a}: {v}' for a, v in sorted(other.items()))}; "
            f"this is {ours}): install the same jsve on every worker"
        )


@contextlib.contextmanager
def _quiet(name: str, level: int = logging.ERROR):
    """Raise logger `name`'s level for the block: an embedded cluster's scheduler and nannies run in this
    process, and their INFO lines (workers starting, connections) would reach jsve's own log handler."""
    log = logging.getLogger(name)
    before = log.level
    log.setLevel(max(level, log.getEffectiveLevel()))
    try:
        yield
    finally:
        log.setLevel(before)


@contextlib.contextmanager
def _environment_kept():
    """Undo, on leaving, what the block set in os.environ: Dask's nannies set variables (PYTHONHASHSEED)
    in the process that runs them, which later subprocesses of this one would inherit."""
    before = dict(os.environ)
    try:
        yield
    finally:
        for name in set(os.environ) - set(before):
            del os.environ[name]
        os.environ.update({k: v for k, v in before.items() if os.environ.get(k) != v})


@contextlib.contextmanager
def _dask_client(scheduler: str, workers: int):
    """A connected distributed.Client: to an embedded LocalCluster ("local") or to a running scheduler."""
    try:
        import distributed
    except ImportError as error:
        raise SchedulerError(
            f"--scheduler {scheduler} needs dask.distributed ({error}): pip install 'dask[distributed]', "
            "or use --scheduler processes"
        ) from error
    if scheduler == LOCAL:
        import dask

        with _quiet("distributed"), _environment_kept():
            # One single-threaded process per worker, as a process pool; memory_limit 0: no Dask memory
            # management (the pool has none; a worker's memory is the operating system's to limit). The
            # scheduler's HTTP routes always start: on a free loopback port, without the dashboard.
            # No pre-spawn environment, so a worker's is a pool worker's: Dask's one (one BLAS thread,
            # MALLOC_TRIM_THRESHOLD_=65536, which also turns off glibc's adaptive mmap threshold) makes
            # the simulator's tasks markedly slower, and the nannies set it here too.
            with dask.config.set({"distributed.nanny.pre-spawn-environ": {}}):
                cluster = distributed.LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=":0",
                    scheduler_kwargs={"dashboard": False},
                    memory_limit=0,
                    silence_logs=logging.ERROR,
                )
            try:
                with distributed.Client(cluster) as client:
                    yield client
            finally:
                cluster.close()
        return
    is_file = scheduler.endswith(".json")
    try:
        client = distributed.Client(
            None if is_file else scheduler,
            scheduler_file=scheduler if is_file else None,
            timeout=CONNECT_TIMEOUT_S,
        )
    except OSError as error:  # distributed's connection timeout is an OSError
        raise SchedulerError(f"--scheduler {scheduler}: cannot connect ({error})") from error
    with client:
        _check_workers(client, f"--scheduler {scheduler}")
        yield client


@contextlib.contextmanager
def executor(
    workers: int,
    scheduler: str | None = None,
    *,
    initializer: Callable | None = None,
    initargs: tuple = (),
    threads: bool = False,
) -> Iterator[concurrent.futures.Executor]:
    """A concurrent.futures.Executor for `scheduler` (see the module docstring), shut down on leaving.

    Arguments:
        workers: processes of a local pool or LocalCluster (a remote cluster has its own).
        scheduler: "local" (default, also None), "processes" or a Dask scheduler address or file.
        initializer, initargs: run once in each worker process before its first task (on a Dask
            worker, before the first task of this call's kind). Functions and arguments must pickle.
        threads: run locally in threads of this process, for tasks that only wait on a subprocess
            (`jsve frontend run`'s drivers): "local" and "processes" then both mean a thread pool.

    Leaving on an exception cancels the tasks not yet started (a LocalCluster's workers are stopped;
    their outputs are `.partial` files the next run redoes).

    Raises:
        SchedulerError: an unusable `scheduler`, or a cluster whose workers run another jsve.
    """
    scheduler = check_scheduler(scheduler)
    workers = max(1, int(workers))
    if threads and scheduler in (LOCAL, PROCESSES):
        pool: concurrent.futures.Executor = concurrent.futures.ThreadPoolExecutor(
            workers, initializer=initializer, initargs=initargs
        )
        with _shut_down(pool):
            yield pool
        return
    if scheduler == LOCAL:
        try:
            import distributed  # noqa: F401
        except ImportError as error:  # the no-dependency fallback
            warnings.warn(
                f"dask.distributed is not installed ({error}): running on a process pool instead "
                "(--scheduler processes)",
                stacklevel=3,
            )
            scheduler = PROCESSES
    if scheduler == PROCESSES:
        from jsve.io._workers import process_pool

        # spawn: jsve never forks a process that may hold JAX's or OpenCV's threads
        pool = process_pool(workers, multiprocessing.get_context("spawn"), initializer, initargs)
        with _shut_down(pool):
            yield pool
        return
    with _dask_client(scheduler, workers) as client:
        pool = _DaskExecutor(client, initializer, initargs)
        with _shut_down(pool):
            yield pool


@contextlib.contextmanager
def _shut_down(pool: concurrent.futures.Executor):
    try:
        yield
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def absolute(path: str | os.PathLike) -> str:
    """`path` as a cluster's worker must see it: absolute (a worker's working folder is its own)."""
    return os.path.abspath(os.fspath(path))


__all__ = [
    "LOCAL",
    "PROCESSES",
    "DEFAULT_SCHEDULER",
    "SchedulerError",
    "check_scheduler",
    "is_cluster",
    "in_process",
    "executor",
    "absolute",
]
