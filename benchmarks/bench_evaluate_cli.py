"""Benchmark: `jsve evaluate` end to end from Parquet, cold and warm compilation cache (issue 14, item 2).

    python benchmarks/bench_evaluate_cli.py --work /tmp/jb                     # simulate, ingest, time
    python benchmarks/bench_evaluate_cli.py --work /tmp/jb --before-tree OLD   # and an older checkout

Simulates a study (EuRoC sequences x the seed's 31 settings x --runs; 11 sequences x 1 run is 341 logs,
0.82 M frames), ingests it to Parquet (both skipped when already there), then runs
`jsve evaluate study.parquet --rule orbslam3` in fresh processes:

- before: the checkout at --before-tree (PYTHONPATH), which has no compilation cache (optional);
- cold: this checkout with JSVE_JAX_CACHE pointing at an emptied folder;
- warm: the same again, the folder now filled.

For each: XLA compilations (backend compilations minus persistent-cache hits, counted with
jax.monitoring inside the process), compilation seconds, wall time and peak RSS (/usr/bin/time -v),
and the 1-minute load average (uptime) beside it, since timings move with the machine's load while
compile counts do not. Ratios are printed against `before` (or against --before-json figures).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

EUROC = "MH_01,MH_02,MH_03,MH_04,MH_05,V1_01,V1_02,V1_03,V2_01,V2_02,V2_03"

# Runs the CLI in-process with jax.monitoring listeners; writes the counts to $BENCH_COUNTS at exit.
WRAPPER = r"""
import atexit, json, os, runpy, sys
import jax.monitoring as m
counts = {"backend_compiles": 0, "cache_hits": 0, "compile_s": 0.0}
def on_duration(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        counts["backend_compiles"] += 1
        counts["compile_s"] += duration
def on_event(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        counts["cache_hits"] += 1
m.register_event_duration_secs_listener(on_duration)
m.register_event_listener(on_event)
def dump():
    counts["compilations"] = counts["backend_compiles"] - counts["cache_hits"]
    with open(os.environ["BENCH_COUNTS"], "w") as f:
        json.dump(counts, f)
atexit.register(dump)
sys.argv = ["jsve"] + sys.argv[1:]
runpy.run_module("jsve.cli", run_name="__main__")
"""


def load() -> float:
    return os.getloadavg()[0]


def timed(cmd: list[str], env: dict[str, str]) -> dict:
    """Run `cmd` under /usr/bin/time -v; wall seconds, peak RSS (GB) and the load before it started."""
    before = load()
    proc = subprocess.run(["/usr/bin/time", "-v", *cmd], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr[-3000:]}")
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", proc.stderr)
    h, mnt, s = wall.groups()
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    return {
        "wall_s": int(h or 0) * 3600 + int(mnt) * 60 + float(s),
        "peak_rss_gb": rss / 1e6,
        "load_before": before,
        "load_after": load(),
        "stdout": proc.stdout,
    }


def evaluate(parquet: Path, tree: Path, cache: str | None, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("JSVE_JAX_CACHE", None)
    if cache is not None:
        env["JSVE_JAX_CACHE"] = cache
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        env["BENCH_COUNTS"] = f.name
    cmd = [sys.executable, "-c", WRAPPER, "evaluate", str(parquet), "--rule", "orbslam3", "--no-progress"]
    figures = timed([*cmd, "-o", str(out)], env)
    figures.update(json.loads(Path(env["BENCH_COUNTS"]).read_text()))
    os.unlink(env["BENCH_COUNTS"])
    return figures


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", type=Path, required=True, help="folder for the study, Parquet and outputs")
    p.add_argument("--sequences", default=EUROC)
    p.add_argument("--euroc-gt", default="../shared/data/euroc/groundtruth_left_cam")
    p.add_argument("--runs", type=int, default=1, help="runs per setting")
    p.add_argument("--before-tree", type=Path, help="an older checkout to time as `before`")
    p.add_argument("--before-json", type=Path, help="`before` figures saved by an earlier --json")
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args()
    tree = Path(__file__).resolve().parents[1]
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    study, parquet = work / "study", work / "study.parquet"
    if not parquet.exists():
        subprocess.run(
            ["jsve", "simulate", "-o", str(study), "--sequences", args.sequences, "--euroc-gt", args.euroc_gt,
             "--runs", str(args.runs), "--workers", "2", "--no-progress", "--yes"],
            check=True,
        )  # fmt: skip
        subprocess.run(["jsve", "ingest", str(study), "-o", str(parquet)], check=True)
    figures = {}
    if args.before_tree:
        figures["before"] = evaluate(parquet, args.before_tree.resolve(), None, work / "eval-before")
    elif args.before_json:
        figures["before"] = json.loads(args.before_json.read_text())["before"]
    cache = work / "jax-cache"
    shutil.rmtree(cache, ignore_errors=True)
    figures["cold"] = evaluate(parquet, tree, str(cache), work / "eval-cold")
    figures["warm"] = evaluate(parquet, tree, str(cache), work / "eval-warm")
    figures["cache_files"] = sum(1 for f in cache.rglob("*") if f.is_file())

    print(f"study: {parquet} ({parquet.stat().st_size / 1e6:.0f} MB)")
    print(f"{'run':<7} {'compilations':>12} {'compile s':>9} {'wall s':>7} {'peak RSS GB':>11} {'load':>9}")
    for name in ("before", "cold", "warm"):
        if name in figures:
            f = figures[name]
            print(
                f"{name:<7} {f['compilations']:>12} {f['compile_s']:>9.1f} {f['wall_s']:>7.1f} "
                f"{f['peak_rss_gb']:>11.2f} {f['load_before']:>4.1f}-{f['load_after']:<4.1f}"
            )
    print(f"cache files: {figures['cache_files']}")
    if "before" in figures:
        b = figures["before"]
        for name in ("cold", "warm"):
            f = figures[name]
            speedup, memory = b["wall_s"] / f["wall_s"], f["peak_rss_gb"] / b["peak_rss_gb"]
            print(
                f"{name} vs before: compilations {f['compilations']}/{b['compilations']}, "
                f"wall {speedup:.1f}x faster, peak RSS {memory:.2f}x"
            )
    if args.json:
        for f in figures.values():
            if isinstance(f, dict):
                f.pop("stdout", None)
        args.json.write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
