"""Masked vs original APE, Table I side by side, on the simulated driving scenario (jsve.sim.DrivingConfig).

    python analysis/masked_driving.py [--runs 20] [--frames 400] [--out docs/data/masked_driving.csv]

Every run is simulated once; its original log carries the visual poses of the front-end on all keypoints,
its masked log (jsve.masks.apply_masks over the keypoint side file and the box masks) the counts without
the dynamic keypoints and the simulator's stand-in for a masked re-run (same draws, no dynamic features).
Both are aligned (se3) and scored by jsve.masks.table_one; the paired difference masked - original of
per-run RMSE gets a percentile bootstrap 95% CI (jsve.evaluation.bootstrap_ci).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from jsve.core import quat_to_matrix
from jsve.evaluation import bootstrap_ci
from jsve.io import schema, write_text
from jsve.masks import PosePair, table_one, to_markdown
from jsve.sim import DrivingConfig, simulate_sequence

SEQUENCES = (("DRIVE_00", 100), ("DRIVE_01", 101))


def poses(frames: pd.DataFrame, position, quaternion) -> np.ndarray:
    out = np.tile(np.eye(4), (len(frames), 1, 1))
    out[:, :3, 3] = frames[list(position)].to_numpy()
    out[:, :3, :3] = quat_to_matrix(frames[list(quaternion)].to_numpy(), xp=np)
    return out


def pair(run) -> PosePair:
    f = run.frames
    t = (f["t_ns"].to_numpy() - f["t_ns"].iloc[0]) / 1e9
    ref = poses(f, schema.GT_POSITION, schema.GT_QUATERNION)
    est = poses(f, schema.VIS_POSITION, schema.VIS_QUATERNION)
    return PosePair(run.run_id, ref, est, t)


def study(n_runs: int, n_frames: int):
    """(TableOne, per-run paired table, dynamic keypoint share) over SEQUENCES x n_runs."""
    config = DrivingConfig(n_frames=n_frames)
    groups = {"original": [], "masked": []}
    rows = []
    for name, seed in SEQUENCES:
        for sim in simulate_sequence(name, seed, n_runs, config):
            masked = sim.masked()
            groups["original"].append(pair(sim.original))
            groups["masked"].append(pair(masked))
            o, m = sim.original.frames, masked.frames
            rows.append({
                "sequence": name, "run": sim.original.meta["run"],
                "dynamic_share": float(sim.dynamic.mean()),
                "inliers_original": float(o["n_inliers"].mean()),
                "inliers_masked": float(m["n_inliers"].mean()),
            })  # fmt: skip
    table = table_one(groups, align="se3")
    per_run = pd.DataFrame(rows)
    per = table.per_run.set_index("group")
    per_run["rmse_original"] = per.loc["original", "rmse"].to_numpy()
    per_run["rmse_masked"] = per.loc["masked", "rmse"].to_numpy()
    per_run["rmse_difference"] = per_run["rmse_masked"] - per_run["rmse_original"]
    return table, per_run


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20, help="runs per sequence")
    parser.add_argument("--frames", type=int, default=400, help="frames per sequence (10 fps)")
    parser.add_argument("--out", default="docs/data/masked_driving.csv")
    args = parser.parse_args(argv)
    # Table I is scored in float64 (equal to evo to 1e-6); set here, not at import, so that importing
    # this script (tests do) leaves the process's precision alone.
    jax.config.update("jax_enable_x64", True)
    start = time.perf_counter()
    table, per_run = study(args.runs, args.frames)
    diff = per_run["rmse_difference"].to_numpy()
    low, high = bootstrap_ci(diff, n_boot=10000, seed=0)
    print(to_markdown(table))
    print()
    print(f"runs: {len(per_run)} ({len(SEQUENCES)} sequences x {args.runs}), {args.frames} frames each")
    print(
        f"dynamic keypoints: {per_run['dynamic_share'].mean():.1%} of all; mean inliers per frame "
        f"{per_run['inliers_original'].mean():.0f} original, {per_run['inliers_masked'].mean():.0f} masked"
    )
    print(
        f"paired RMSE difference masked - original: mean {diff.mean():.4f} m, "
        f"bootstrap 95% CI [{low:.4f}, {high:.4f}] m; masked better in {(diff < 0).sum()}/{len(diff)} runs"
    )
    print(f"wall time {time.perf_counter() - start:.1f} s")
    summary = table.summary.copy()
    summary.insert(0, "kind", "table1")
    per_run.insert(0, "kind", "run")
    ci = pd.DataFrame([{"kind": "paired_difference", "statistic": "rmse_masked_minus_original",
                        "mean": diff.mean(), "ci_low": low, "ci_high": high}])  # fmt: skip
    out = pd.concat([summary, per_run, ci], ignore_index=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out, out.to_csv(index=False, float_format="%.6g"))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
