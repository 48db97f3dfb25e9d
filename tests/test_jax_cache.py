"""jsve._jax_cache: where the persistent compilation cache lives, and that a second `jsve evaluate`
compiles nothing (every computation of the first is found in the cache)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from logfactory import make_run

from jsve._jax_cache import ENV, cache_dir
from jsve.io import write_log


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c"
    for off in ("0", "off", "OFF", " false ", "", "none"):
        monkeypatch.setenv(ENV, off)
        assert cache_dir() is None
    monkeypatch.delenv(ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "jsve" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "jsve" / "jax"


def _evaluate(logs: Path, out: Path, cache: Path) -> str:
    env = dict(os.environ, **{ENV: str(cache)})
    cmd = [sys.executable, "-m", "jsve.cli", "evaluate", str(logs), "--rule", "orbslam3", "--rule",
           "sve-option2", "-o", str(out), "--no-progress"]  # fmt: skip
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return (out / "runs.csv").read_text()


def _entries(cache: Path) -> set[str]:
    return {str(p.relative_to(cache)) for p in cache.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_second_evaluate_compiles_nothing(tmp_path):
    # Runs of three lengths in two ladder rungs: several shapes, every one of them cached by the first run.
    logs = tmp_path / "logs"
    logs.mkdir()
    for k, n in enumerate([150, 160, 400, 410]):
        write_log(make_run(n, seed=k, sequence="MH_01", run=k), logs / f"run_{k}.csv")
    cache = tmp_path / "jax-cache"
    first = _evaluate(logs, tmp_path / "first", cache)
    written = _entries(cache)
    assert written, "the first run wrote no compiled computation into the cache"
    second = _evaluate(logs, tmp_path / "second", cache)
    # JAX writes every computation it compiles (jsve sets no minimum compile time or size), so an
    # unchanged folder means the second run compiled nothing, only read.
    assert _entries(cache) == written
    assert second == first
