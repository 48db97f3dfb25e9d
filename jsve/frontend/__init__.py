"""The compiled front-end boundary: `jsve_log.hpp`, a header-only C++17 writer of log format v3.

A front-end (ORB-SLAM3 with the hooks of docs/frontend.md, or any other) includes the header and
writes one format-v3 log per run; jsve reads it with `jsve.io._logs.read_log`. Compile with

    g++ -std=c++17 -I"$(jsve frontend-include)" ...        # or: python -m jsve.frontend --include
"""

from __future__ import annotations

from pathlib import Path

DEFAULT_GATE_TIMEOUT_S = 120.0
"""How long a lockstep run of `jsve frontend run` waits for LocalMapping or LoopClosing to park after a
frame before it ends as outcome "gate_timeout" (a global BA of a few hundred keyframes takes seconds)."""

HEADER_NAME = "jsve_log.hpp"
"""File name of the header inside `get_include()`."""


def get_include() -> str:
    """Directory holding `jsve_log.hpp`, for a compiler's `-I` (like `numpy.get_include()`).

    Returns:
        Absolute path of the directory, as a string.
    """
    return str(Path(__file__).resolve().parent)


def header_path() -> str:
    """Absolute path of `jsve_log.hpp` itself."""
    return str(Path(get_include()) / HEADER_NAME)


_RUN_NAMES = ("MODES", "plan", "run_all", "canonical_paths", "driver_command", "driver_rule", "orb_features")
"""`jsve frontend run`'s building blocks (jsve.frontend._run), loaded on first use: importing this package
stays as light as the header's path needs."""


def __getattr__(name: str):
    if name in _RUN_NAMES:
        from jsve.frontend import _run

        return getattr(_run, name)
    raise AttributeError(f"module 'jsve.frontend' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_RUN_NAMES])
