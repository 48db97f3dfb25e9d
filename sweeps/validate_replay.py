"""Run the real front-end for the replay's validation (issue 11): recordings in `record` mode, a rule
fitted on their replays, then every rule of the config in ORB-SLAM3's loop under every switch model.

    python sweeps/validate_replay.py sweeps/validation.toml [--dry-run]

Steps, in order (the config format is in sweeps/validation.toml):

1. `record` runs of every dataset under each switch model (the logs that support every stricter rule);
2. with a `[fit]` table: per switch model, `jsve ingest` of those recordings (each sequence with its own
   ground truth) and `jsve fit` on them, so that a rule named `fit/{switch_model}/fitted_sve.json`
   exists before it is run;
3. each rule in the loop under each switch model.

Every step is one `jsve` command: runs are parallel and resumable (runs already complete under the same
key are kept, so a stopped sweep continues where it stopped; runs of another key stop it), ingest and
fit resume their own outputs (the recordings are ingested afresh each time, and `jsve fit` resumes only
a study of the same data and configuration). Then
`python analysis/replay_vs_rerun.py OUTPUT --ground-truth SEQ=GT ...` compares every recording's
replay with the re-runs.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import tomllib


def run_command(config: dict, rule: str, model: str) -> list[str]:
    """`jsve frontend run` of every dataset with `rule` in the loop under switch model `model`."""
    cmd = ["jsve", "frontend", "run", config["build"], *config["datasets"],
           "--vocabulary", config["vocabulary"], "--settings", config["settings"],
           "--runs", str(config.get("runs", 5)), "--workers", str(config.get("workers", 2)),
           "-o", config["output"],
           "--rule", rule.format(switch_model=model), "--switch-model", model]  # fmt: skip
    if config.get("no_wait", False):
        cmd.append("--no-wait")
    return cmd


def fit_commands(config: dict, model: str) -> list[list[str]]:
    """`jsve ingest` of the `record` runs under `model` and `jsve fit` on them (config's [fit] table)."""
    fit = config["fit"]
    root = Path(fit.get("output", "fit"))
    folder = root / model
    recordings = str(Path(config["output"]) / "*" / "*" / f"record-{model}" / "run_*.csv")
    truth = [arg for seq, path in sorted(fit["ground_truth"].items()) for arg in ("--gt", f"{seq}={path}")]
    parquet = str(root / f"recordings-{model}.parquet")
    ingest = ["jsve", "ingest", recordings, "-o", parquet, *truth, "--yes"]
    study = ["jsve", "fit", parquet, "-o", str(folder), "--switch-model", model]
    if "config" in fit:
        study += ["--config", fit["config"]]
    return [ingest, study]


def commands(config: dict) -> list[list[str]]:
    """Every command of the sweep in order: recordings, fits, then the rules in the loop."""
    models = config.get("switch_models", ["orbslam3"])
    jobs = [run_command(config, "record", m) for m in models] if config.get("record", True) else []
    if "fit" in config:
        jobs += [cmd for m in models for cmd in fit_commands(config, m)]
    jobs += [run_command(config, rule, m) for m in models for rule in config.get("rules", ["orbslam3"])]
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
        if cmd[:2] == ["jsve", "ingest"]:  # re-ingested every time (seconds): never a stale table
            Path(cmd[cmd.index("-o") + 1]).parent.mkdir(parents=True, exist_ok=True)
        start = time.monotonic()
        done = subprocess.run(cmd)
        print(f"[{k}/{len(jobs)}] exit {done.returncode} after {time.monotonic() - start:.0f} s", flush=True)
        frontend_run = cmd[:3] == ["jsve", "frontend", "run"]
        if done.returncode != 0 and not (frontend_run and done.returncode == 1):
            return done.returncode  # 1 from a front-end run: some runs failed (counted); the rest stops
    return 0


if __name__ == "__main__":
    sys.exit(main())
