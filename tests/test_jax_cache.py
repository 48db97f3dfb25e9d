"""jsve._jax_cache: where the persistent compilation cache lives, and that a second `jsve evaluate`
compiles nothing (every computation of the first is found in the cache)."""

from __future__ import annotations

import json
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


# `jsve ...` in a fresh process that prints how many computations XLA compiled and how many of them JAX
# found in its persistent cache (jax.monitoring's events), as JSON on its last line.
COUNTING = """
import json, sys
import jax.monitoring as monitoring
counts = {"compiled": 0, "from_cache": 0}
def on_duration(event, duration, **kwargs):
    counts["compiled"] += event == "/jax/core/compile/backend_compile_duration"
def on_event(event, **kwargs):
    counts["from_cache"] += event == "/jax/compilation_cache/cache_hits"
monitoring.register_event_duration_secs_listener(on_duration)
monitoring.register_event_listener(on_event)
from jsve.cli import main
code = main(sys.argv[1:])
print(json.dumps(counts))
sys.exit(code)
"""


def _evaluate(logs: Path, out: Path, cache: Path) -> tuple[str, dict]:
    env = dict(os.environ, **{ENV: str(cache)})
    cmd = [sys.executable, "-c", COUNTING, "evaluate", str(logs), "--rule", "orbslam3", "--rule",
           "sve-option1", "-o", str(out), "--no-progress"]  # fmt: skip
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return (out / "runs.csv").read_text(), json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_second_evaluate_compiles_nothing(tmp_path):
    # Runs in two ladder rungs and two rules (sve-option1: the authors' inputs, whose traced check is a
    # host callback that would keep the computation out of the cache): several computations, every one
    # of them compiled by the first run and read back by the second.
    logs = tmp_path / "logs"
    logs.mkdir()
    for k, n in enumerate([150, 160, 400, 410]):
        write_log(make_run(n, seed=k, sequence="MH_01", run=k), logs / f"run_{k}.csv")
    cache = tmp_path / "jax-cache"
    first, cold = _evaluate(logs, tmp_path / "first", cache)
    assert cold["compiled"] > 0 and cold["from_cache"] == 0, cold
    second, warm = _evaluate(logs, tmp_path / "second", cache)
    assert warm["compiled"] == warm["from_cache"] == cold["compiled"], (cold, warm)
    assert second == first
