"""Exact branches of a lockstep run (docs/frontend.md, "Lockstep runs"): fork the driver with every thread
parked before frame K and let the child go on under another rule. Checks that a branch under the run's
own rule to the end writes the run's log byte for byte, and prices a branch of W frames under another
rule against a full run.

    python analysis/lockstep_branches.py BUILD DATASET --vocabulary voc.txt --settings S.yaml -o OUT \\
        [--seed 3] [--at 150 300] [--frames 100] [--rule sve-option2]

Prints one row per branch point: whether the parent equals the same run without a branch (it does not:
both processes restart their workers at the fork), whether the own-rule branch equals its parent (and
the first frame where it differs), the first frame where the other rule's branch differs from the
own-rule branch, and the branch's time against a full run's.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

import pandas as pd

from jsve.frontend import canonical_paths, driver_command, driver_rule, orb_features, plan
from jsve.io import load_rules


def _first_difference(a: Path, b: Path) -> int | None:
    """The first data row (0-based frame) where two logs differ; None when one is a prefix of the other."""
    rows_a, rows_b = a.read_text().splitlines()[2:], b.read_text().splitlines()[2:]
    for k, (x, y) in enumerate(zip(rows_a, rows_b, strict=False)):
        if x != y:
            return k
    return None


def _same(a: Path, b: Path) -> bool:
    return a.read_bytes() == b.read_bytes()


def run_branch(base: list[str], out: Path, at: int, frames: int, rule: list[str]) -> dict:
    """The driver with one branch, in folder `out` (run.csv, the parent's log; brn.csv, the branch's),
    through canonical_paths as `jsve frontend run` runs it; both summaries and the wall time (s)."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [*base, "--log", str(out / "run.csv"), "--summary", str(out / "run.json"),
           "--trajectory", str(out / "run.txt")]  # fmt: skip
    if at > 0:
        cmd += ["--branch-at", str(at), "--branch-frames", str(frames), "--branch-log", str(out / "brn.csv"),
                "--branch-summary", str(out / "brn.json"), *rule]  # fmt: skip
    start = time.monotonic()
    with open(out / "console.txt", "w") as console, canonical_paths(cmd) as (cwd, canonical):
        code = subprocess.run(canonical, stdout=console, stderr=subprocess.STDOUT, cwd=cwd).returncode
    parent = json.loads((out / "run.json").read_text())
    child = json.loads((out / "brn.json").read_text()) if at > 0 else None
    return {"exit": code, "wall_s": time.monotonic() - start, "parent": parent, "branch": child}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("build", type=Path)
    p.add_argument("dataset", type=Path)
    p.add_argument("--vocabulary", type=Path, required=True)
    p.add_argument("--settings", type=Path, required=True)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--at", type=int, nargs="+", default=[150, 300])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--rule", default="sve-option2")
    args = p.parse_args()
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    [job], _ = plan(args.build, [args.dataset], runs=1, out=out / "plan", vocabulary=args.vocabulary,
                    settings=args.settings, mode="lockstep", seed=args.seed, force=True)  # fmt: skip
    command = driver_command(args.build / "bin" / "jsve_orbslam3", args.vocabulary, job)
    drop = {"--log", "--summary", "--trajectory"}
    base = [a for i, a in enumerate(command) if a not in drop and command[i - 1] not in drop]
    name, rule = load_rules([args.rule])[0]
    rule_args, _ = driver_rule(name, rule, "orbslam3", orb_features(args.settings.read_text()))
    branch_rule = [a.replace("--rule-", "--branch-rule-") for a in rule_args]
    full = run_branch(base, out / "full", 0, 0, [])
    assert full["exit"] == 0, (out / "full" / "console.txt").read_text()[-2000:]
    full_s, n = full["parent"]["time"]["main_s"], full["parent"]["frames"]
    rows = []
    for at in args.at:
        own, alt = out / f"own-{at}", out / f"alt-{at}"
        run_branch(base, own, at, n - at, [])
        other = run_branch(base, alt, at, args.frames, branch_rule)
        seconds = other["parent"]["branch"]["seconds"]
        rows.append({
            "branch_at": at,
            "parent_equals_unbranched_run": _same(own / "run.csv", out / "full" / "run.csv"),
            "own_rule_branch_equals_parent": _same(own / "brn.csv", own / "run.csv"),
            "own_rule_branch_first_difference": _first_difference(own / "brn.csv", own / "run.csv"),
            f"{name}_branch_first_difference": _first_difference(alt / "brn.csv", own / "brn.csv"),
            "full_run_s": full_s, f"{name}_branch_frames": args.frames, f"{name}_branch_s": seconds,
            "branch_share_of_full_run": seconds / full_s,
        })  # fmt: skip
    table = pd.DataFrame(rows)
    table.to_csv(out / "branches.csv", index=False)
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
