"""Run the real front-end for the replay's validation (issue 11): every rule of the config in ORB-SLAM3's
loop under every switch model, and `record`-mode recordings, N runs per dataset.

    python sweeps/validate_replay.py sweeps/validation.toml [--dry-run]

Each (rule, switch model) is one `jsve frontend run` over all datasets (parallel, resumable: runs already
complete under the same key are kept, so a stopped sweep continues where it stopped; runs of another key
stop it). Then `python analysis/replay_vs_rerun.py OUTPUT --ground-truth SEQ=GT ...` compares every
recording's replay with the re-runs. The config format is in sweeps/validation.toml.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import tomllib


def commands(config: dict) -> list[list[str]]:
    """The `jsve frontend run` command lines of a config, one per (rule, switch model), record last."""
    base = ["jsve", "frontend", "run", config["build"], *config["datasets"],
            "--vocabulary", config["vocabulary"], "--settings", config["settings"],
            "--runs", str(config.get("runs", 5)), "--workers", str(config.get("workers", 2)),
            "-o", config["output"]]  # fmt: skip
    if config.get("no_wait", False):
        base.append("--no-wait")
    jobs = []
    for model in config.get("switch_models", ["orbslam3"]):
        for rule in config.get("rules", ["orbslam3"]):
            jobs.append([*base, "--rule", rule, "--switch-model", model])
        if config.get("record", True):
            jobs.append([*base, "--rule", "record", "--switch-model", model])
    return jobs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--dry-run", action="store_true", help="print the commands and exit")
    args = parser.parse_args(argv)
    config = tomllib.loads(args.config.read_text())
    jobs = commands(config)
    for k, cmd in enumerate(jobs, 1):
        print(f"[{k}/{len(jobs)}] {' '.join(cmd)}", flush=True)
        if args.dry_run:
            continue
        start = time.monotonic()
        done = subprocess.run(cmd)
        print(f"[{k}/{len(jobs)}] exit {done.returncode} after {time.monotonic() - start:.0f} s", flush=True)
        if done.returncode not in (0, 1):  # 1: some runs failed (counted); anything else stops the sweep
            return done.returncode
    return 0


if __name__ == "__main__":
    sys.exit(main())
