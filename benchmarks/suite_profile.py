"""Where the test suite's time goes: a pytest plugin recording, per test, its wall time, its worker and
jax.monitoring's compile events, and a summary of those records per file or per test.

    JSVE_SUITE_PROFILE=DIR PYTHONPATH=benchmarks pytest -p suite_profile      # record (one file a worker)
    python benchmarks/suite_profile.py DIR                                     # per file, slowest first
    python benchmarks/suite_profile.py DIR --by test --top 40
    python benchmarks/suite_profile.py DIR --by program                        # per jitted function
    python benchmarks/suite_profile.py DIR --against OLD_DIR                   # per file, two recordings

Per test (setup, call and teardown together): wall seconds, XLA's backend compile seconds and programs
(/jax/core/compile/backend_compile_duration), tracing and lowering seconds, the garbage collector's
seconds, its compile seconds and programs per jitted function (the name jax compiles it under, e.g.
jit(_compiled_scan_sums)), and its start and end (seconds since the earliest start of the recording).
The summary's first lines are each worker's busy time, the time its last test ended, and its compile
totals: a large gap between the workers' last ends is a tail of the load balance; similar compile
counts with very different compile seconds mean the machine's speed changed between the recordings.
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import os
import sys
import time
from pathlib import Path

import pytest

COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
ENV = "JSVE_SUITE_PROFILE"

_events: dict[str, list[float]] = {}
_programs: dict[str, list[float]] = {}
_gc = {"total": 0.0, "since": None}
_records: list[dict] = []


def _on_duration(event: str, duration: float, *, fun_name: str = "", **_) -> None:
    for table, key in ((_events, event), (_programs, fun_name if event == COMPILE else None)):
        if key is not None:
            total = table.setdefault(key, [0.0, 0])
            total[0] += duration
            total[1] += 1


def _on_gc(phase: str, _info) -> None:
    if phase == "start":
        _gc["since"] = time.perf_counter()
    elif _gc["since"] is not None:
        _gc["total"] += time.perf_counter() - _gc["since"]
        _gc["since"] = None


def pytest_configure(config) -> None:
    import jax.monitoring

    if not os.environ.get(ENV):
        raise RuntimeError(f"suite_profile records into ${ENV}: set it to a folder")
    jax.monitoring.register_event_duration_secs_listener(_on_duration)
    gc.callbacks.append(_on_gc)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _events.clear()
    _programs.clear()
    gc_before, start = _gc["total"], time.time()
    yield
    _records.append(
        {"test": item.nodeid, "start": start, "end": time.time(), "gc_s": _gc["total"] - gc_before,
         "events": {k: list(v) for k, v in _events.items()},
         "programs": {k: list(v) for k, v in _programs.items()}}
    )  # fmt: skip


def pytest_sessionfinish(session) -> None:
    if not _records:
        return
    folder = Path(os.environ[ENV])
    folder.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (folder / f"{worker}.json").write_text(json.dumps(_records))


def load(folder: Path) -> list[dict]:
    """Every record of a recording, each with its worker."""
    rows = []
    for path in sorted(Path(folder).glob("*.json")):
        rows += [{**r, "worker": path.stem} for r in json.loads(path.read_text())]
    if not rows:
        raise SystemExit(f"{folder}: no recording (run pytest -p suite_profile with {ENV}={folder})")
    return rows


def _event(row: dict, name: str) -> tuple[float, int]:
    s, n = row["events"].get(name, (0.0, 0))
    return float(s), int(n)


def totals(rows: list[dict], by: str) -> dict[str, dict]:
    """Per file (by="file") or per test: wall, compile seconds and programs, tracing, lowering, gc."""
    out: dict[str, dict] = collections.defaultdict(lambda: collections.Counter())
    for r in rows:
        key = r["test"].split("::")[0] if by == "file" else r["test"]
        t = out[key]
        t["wall_s"] += r["end"] - r["start"]
        t["compile_s"] += _event(r, COMPILE)[0]
        t["programs"] += _event(r, COMPILE)[1]
        t["trace_s"] += _event(r, TRACE)[0]
        t["lower_s"] += _event(r, LOWER)[0]
        t["gc_s"] += r["gc_s"]
    return out


def by_program(rows: list[dict]) -> dict[str, dict]:
    """Per jitted function: compile seconds, programs, and the test files that compiled it."""
    out: dict[str, dict] = collections.defaultdict(lambda: {"compile_s": 0.0, "programs": 0, "files": set()})
    for r in rows:
        for name, (s, n) in r.get("programs", {}).items():
            t = out[name]
            t["compile_s"] += s
            t["programs"] += n
            t["files"].add(r["test"].split("::")[0])
    return out


def _print_programs(rows: list[dict], top: int) -> None:
    table = by_program(rows)
    if not table:
        raise SystemExit("this recording has no compile times per function (recorded by an older plugin)")
    print(f"{'':60} {'compile s':>9} {'programs':>8} {'files':>5}")
    for name, t in sorted(table.items(), key=lambda kv: -kv[1]["compile_s"])[:top]:
        print(f"{name[-60:]:60} {t['compile_s']:9.1f} {t['programs']:8d} {len(t['files']):5d}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--by", choices=("file", "test", "program"), default="file")
    parser.add_argument("--top", type=int, default=30)
    parser.add_argument("--against", type=Path, help="an earlier recording: its wall and compile beside")
    args = parser.parse_args(argv)
    rows = load(args.folder)
    t0 = min(r["start"] for r in rows)
    for worker in sorted({r["worker"] for r in rows}):
        mine = [r for r in rows if r["worker"] == worker]
        busy = sum(r["end"] - r["start"] for r in mine)
        last = max(r["end"] for r in mine) - t0
        seconds, programs = (sum(c) for c in zip(*(_event(r, COMPILE) for r in mine), strict=True))
        print(f"{worker}: {len(mine)} tests, busy {busy:.0f} s, last end {last:.0f} s, "
              f"compile {seconds:.0f} s over {programs} programs")  # fmt: skip
    if args.by == "program":
        _print_programs(rows, args.top)
        return 0
    now = totals(rows, args.by)
    before = totals(load(args.against), args.by) if args.against else {}
    print(f"{'':60} {'wall s':>7} {'compile s':>9} {'programs':>8} {'trace s':>7} {'lower s':>7} {'gc s':>5}"
          + ("   earlier wall / compile s / programs" if before else ""))  # fmt: skip
    for key, t in sorted(now.items(), key=lambda kv: -kv[1]["wall_s"])[: args.top]:
        line = (f"{key[-60:]:60} {t['wall_s']:7.1f} {t['compile_s']:9.1f} {t['programs']:8d} "
                f"{t['trace_s']:7.1f} {t['lower_s']:7.1f} {t['gc_s']:5.1f}")  # fmt: skip
        if key in before:
            b = before[key]
            line += f"   {b['wall_s']:7.1f} / {b['compile_s']:6.1f} / {b['programs']:5d}"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
