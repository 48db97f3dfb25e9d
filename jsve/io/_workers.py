"""Worker processes that die with the process that started them.

jsve's process pools (reading many logs, measure, and simulate, disturb and render under `--scheduler
processes`: jsve.io._scheduler decides where a sweep's tasks run) use `process_pool`, whose workers
end when their parent ends, however it ends: a parent killed with SIGKILL runs no clean-up, and
concurrent.futures' workers would otherwise go on with their jobs (writing files for seconds) and
then wait forever, idle, holding their memory.

Two mechanisms, because neither is enough alone:
- Linux: prctl(PR_SET_PDEATHSIG, SIGKILL) (prctl(2)): the kernel kills the worker the moment its
  parent exits, even while the worker runs C code that holds the GIL. Its parent is the process that
  started it under the spawn method, but a forkserver's server under forkserver.
- Everywhere: a daemon thread waiting on multiprocessing's parent sentinel (a pipe the process that
  asked for the worker holds open; under forkserver too), which ends the worker with os._exit when
  the parent is gone, and at once when it died before the worker's initializer ran.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
from collections.abc import Callable

_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_ORPHAN_EXIT = 70  # exit status of a worker whose parent is gone (EX_SOFTWARE)


def _watch(sentinel) -> None:
    multiprocessing.connection.wait([sentinel])  # returns when the parent's end of the pipe closes
    os._exit(_ORPHAN_EXIT)


def die_with_parent() -> None:
    """Make this worker process (started by multiprocessing) end when the process that started it
    ends; a no-op in a process multiprocessing did not start."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no libc to load: the watcher thread alone
            pass
    parent = multiprocessing.parent_process()
    if parent is None or parent.sentinel is None:
        return
    threading.Thread(target=_watch, args=(parent.sentinel,), name="jsve-parent-watch", daemon=True).start()


def _initialize(initializer: Callable | None, initargs: tuple) -> None:
    die_with_parent()
    if initializer is not None:
        initializer(*initargs)


def process_pool(
    workers: int, mp_context, initializer: Callable | None = None, initargs: tuple = ()
) -> concurrent.futures.ProcessPoolExecutor:
    """A ProcessPoolExecutor whose workers die with their parent (see the module docstring).

    Arguments:
        workers: processes. mp_context: a multiprocessing context (spawn or forkserver: jsve never forks
            a process that may hold JAX's threads).
        initializer, initargs: run in each worker after it is tied to its parent.
    """
    return concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=mp_context, initializer=_initialize, initargs=(initializer, initargs)
    )


__all__ = ["process_pool", "die_with_parent"]
