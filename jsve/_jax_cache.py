"""JAX's persistent compilation cache in a user cache folder, so a second `jsve` run compiles nothing.

The commands that compute (evaluate, fit, demo, check, tune) call `enable_compilation_cache()` before their
first JAX computation. The folder is $JSVE_JAX_CACHE when set, else $XDG_CACHE_HOME/jsve/jax (default
~/.cache/jsve/jax); JSVE_JAX_CACHE=0 (or off, false, no, none, or empty) turns the cache off. Entries are
keyed by JAX on the computation, shapes, flags, JAX version and device, so a stale entry is never used;
deleting the folder is always safe.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

ENV = "JSVE_JAX_CACHE"
OFF = ("", "0", "off", "false", "no", "none")

logger = logging.getLogger(__name__)


def cache_dir() -> Path | None:
    """The cache folder the environment asks for, or None when JSVE_JAX_CACHE turns the cache off."""
    value = os.environ.get(ENV)
    if value is not None:
        return None if value.strip().lower() in OFF else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jsve" / "jax"


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent compilation cache at `cache_dir()` (every computation, however quick to
    compile), and return the folder; None when turned off or when the folder cannot be created (the
    run then compiles as without a cache)."""
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        logger.warning("compilation cache off: cannot create %s (%s)", path, err)
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(path))
    # JAX's default skips computations compiled in under 1 s; jsve's small ones add up to seconds.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
