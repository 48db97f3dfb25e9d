"""Giving memory back between the stages of a long computation.

A large fit's live JAX arrays stay about the size of its data from loading to the end, yet without a
release its process grows through the search, the Nelder-Mead polishes and the cross-validation folds
to several times that. What grows is not data but what finished work leaves behind: JAX's compiled
executables (each length bucket, each subset of a halving rung, each packed polish is its own shape)
and glibc's freed heap pages, which stay with the process until trimmed. `release_memory` drops both
(the figures: docs/performance.md, `jsve fit`'s memory). JAX then compiles a shape seen before again,
which the commands' persistent compilation cache (jsve._jax_cache) turns into a read from disk.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import sys

log = logging.getLogger(__name__)

RELEASE_ABOVE_BYTES = 3 * 1024**3
"""`release_memory` drops JAX's compiled executables only when the process holds more than this
(resident): below it they are worth keeping (recompiling costs time), above it a long job would grow
past a 24 GB machine's memory."""


def resident_bytes() -> int | None:
    """The process's resident set size in bytes (Linux /proc), or None where it cannot be read."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE")


def peak_resident_bytes() -> int | None:
    """The most the process has held resident so far, in bytes (getrusage; None where unavailable)."""
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # macOS counts bytes, Linux KiB


def _trim_heap() -> bool:
    """glibc's malloc_trim(0): free heap pages back to the system; False where there is no glibc."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.malloc_trim(0))
    except (OSError, AttributeError):
        return False


ENV = "JSVE_RELEASE_MEMORY"
"""JSVE_RELEASE_MEMORY=0 (or off, false, no) turns `release_memory` off: a machine with memory to spare
keeps every executable (no compiling a shape twice); benchmarks/bench_fit_memory.py compares both."""


def release_memory(*, above_bytes: int | None = RELEASE_ABOVE_BYTES) -> dict:
    """Collect Python's garbage, drop JAX's compiled executables where the process holds more than
    `above_bytes` (None: always), and trim the heap. Results never change: only what is recomputed.
    Nothing is done where $JSVE_RELEASE_MEMORY turns it off.

    Below `above_bytes` only the young generations are collected: a full collection walks every object
    the interpreter tracks, JAX's cached jaxprs included (hundreds of thousands after a few fits; the
    cost: docs/performance.md, "The test suite"), and a process that small has nothing worth that to give
    back. Above it, a full
    collection before and after dropping the executables frees what they held.

    Returns:
        {"before": resident bytes or None, "after": ..., "cleared": whether executables were dropped}.
    """
    if os.environ.get(ENV, "1").strip().lower() in ("0", "off", "false", "no"):
        return {"before": None, "after": None, "cleared": False}
    import jax

    gc.collect(generation=1)
    before = resident_bytes()
    cleared = above_bytes is None or (before is not None and before > above_bytes)
    if cleared:
        gc.collect()
        jax.clear_caches()
        gc.collect()
    _trim_heap()
    after = resident_bytes()
    if before is not None and after is not None:
        log.debug("memory: %.2f -> %.2f GB (executables dropped: %s)", before / 1e9, after / 1e9, cleared)
    return {"before": before, "after": after, "cleared": cleared}


__all__ = ["release_memory", "resident_bytes", "peak_resident_bytes", "RELEASE_ABOVE_BYTES", "ENV"]
