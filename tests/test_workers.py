"""jsve.io._workers: the workers of jsve's process pools die with their parent, however it dies.

The oracle is the kernel's process table (/proc): after the parent of `jsve simulate --workers 2` is
killed with SIGKILL (no clean-up of its own runs), none of the processes it started may remain.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux's /proc")


def _children(pid: int) -> set[int]:
    """Processes whose parent is `pid`."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has ended; it waits only for its parent to reap it


def test_killing_simulate_kills_its_workers(tmp_path):
    command = [sys.executable, "-m", "jsve.cli", "simulate", "-o", str(tmp_path / "out"), "--procedural", "4",
               "--disturbances", "blur:0:5:10", "--runs", "2", "--workers", "2", "--no-progress"]  # fmt: skip
    parent = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        workers: set[int] = set()
        while time.monotonic() < deadline and parent.poll() is None:
            workers = {
                p for p in _children(parent.pid) if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()
            }
            if len(workers) >= 2:
                break
            time.sleep(0.1)
        assert len(workers) >= 2, "the pool's workers never started"
        time.sleep(2.0)  # into their jobs (imports done, recordings under way)
        started = _children(parent.pid)  # the workers and multiprocessing's helpers
        assert parent.poll() is None, "simulate finished before it could be killed"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and any(_alive(p) for p in started):
            time.sleep(0.05)
        assert not [p for p in started if _alive(p)], "processes outlived their killed parent"
    finally:
        if parent.poll() is None:
            parent.kill()
        for pid in _children(parent.pid):
            os.kill(pid, signal.SIGKILL)
