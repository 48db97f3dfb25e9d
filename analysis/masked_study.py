"""Masked ORB-SLAM3 in the real front-end (docs/masks.md, "Table I from real runs"), from the folder
sweeps/masked_study.sh wrote: Table I per sequence and scene, the paired differences masked - original,
and offline masking of the original runs (`jsve mask-logs`'s apply_masks) against masking in the loop.

    python analysis/masked_study.py OUT --data DATA [--csv docs/data/masked_runs.csv]
        [--agreement-csv docs/data/masked_offline_vs_loop.csv] [--figure docs/figures/masked_table1.png]

OUT/<scene>/<original|masked>/<SEQ>/none-0/run_<k>.*: scene "moving" (5 of 6 objects moving) or
"parked" (the same objects, all standing); DATA/<SEQ-folder>-<scene>: the rendered datasets with
their masks. Every run is scored as `jsve evaluate` scores a real run: failed when it ended in anything
but "ok", saved no trajectory, or covers less than DEFAULT_MIN_COVERAGE of its frames; its loss is the
failure penalty then, else min(ATE, penalty) with ATE that of ORB-SLAM3's saved trajectory (SE(3)
alignment, metres). Table I itself is `jsve table1` over the saved trajectories, the seed's statistics.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from jsve import ObjectiveConfig
from jsve.tuning import run_row

PENALTY_M = ObjectiveConfig().failure_penalty
MIN_COVERAGE = ObjectiveConfig().min_coverage
SCENES = ("moving", "parked")
ARMS = ("original", "masked")
DATASETS = {"V101": "V1_01", "V201": "V2_01"}
"""Sequence name in the logs -> the rendered dataset's folder stem (DATA/<stem>-<scene>)."""


def run_table(out: Path) -> pd.DataFrame:
    """One row per finished run: scene, arm, sequence, seed, outcome, coverage, ATE, failed, loss,
    events."""
    rows = []
    for path in sorted(out.glob("*/*/*/none-0/run_*.summary.json")):
        s = json.loads(path.read_text())
        if "exit_code" not in s:
            continue
        scene, arm, sequence = path.relative_to(out).parts[:3]
        row = run_row(s, PENALTY_M, MIN_COVERAGE)
        rows.append({
            "scene": scene, "arm": arm, "sequence": sequence, "seed": s["seed"], "run": path.name[4:7],
            **{k: row[k] for k in ("outcome", "coverage", "ate_m", "failed", "loss_m", "resets")},
            "maps": row["new_maps"], "loops": row["loops"], "ba2": (s.get("events") or {}).get("ba2", 0),
            "cpu_s": row["cpu_s"], "stem": str(path).removesuffix(".summary.json"),
        })  # fmt: skip
    return pd.DataFrame(rows)


def paired_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Per scene and sequence: masked - original, paired by seed, on the bounded loss (every run) and on
    ATE (pairs where both tracked): mean and median, the mean's 95 % t interval (scipy.stats.ttest_rel)
    and BCa bootstrap interval (scipy.stats.bootstrap: the losses are heavy-tailed), Wilcoxon signed-rank
    p, how often masking helped; the failures of each arm."""
    rows = []
    for (scene, sequence), g in runs.groupby(["scene", "sequence"]):
        wide = g.pivot(index="seed", columns="arm", values=["loss_m", "ate_m", "failed"]).dropna(
            subset=[("loss_m", "original"), ("loss_m", "masked")]
        )
        row = {"scene": scene, "sequence": sequence, "pairs": len(wide),
               "failed_original": int(wide[("failed", "original")].sum()),
               "failed_masked": int(wide[("failed", "masked")].sum())}  # fmt: skip
        both = ~(wide[("failed", "original")].astype(bool) | wide[("failed", "masked")].astype(bool))
        for name, a, b in (
            ("loss", wide[("loss_m", "masked")], wide[("loss_m", "original")]),
            ("ate", wide[("ate_m", "masked")][both], wide[("ate_m", "original")][both]),
        ):
            a, b = a.astype(float).to_numpy(), b.astype(float).to_numpy()
            d = a - b
            row[f"{name}_pairs"] = len(d)
            row[f"{name}_original_mean_m"] = b.mean() if len(d) else np.nan
            row[f"{name}_masked_mean_m"] = a.mean() if len(d) else np.nan
            row[f"{name}_diff_mean_m"] = d.mean() if len(d) else np.nan
            row[f"{name}_diff_median_m"] = np.median(d) if len(d) else np.nan
            if len(d) >= 2 and np.ptp(d) > 0:
                ci = stats.ttest_rel(a, b).confidence_interval(0.95)
                row[f"{name}_ci_low_m"], row[f"{name}_ci_high_m"] = ci.low, ci.high
                boot = stats.bootstrap((d,), np.mean, method="BCa", n_resamples=9999, random_state=0)
                row[f"{name}_bca_low_m"] = boot.confidence_interval.low
                row[f"{name}_bca_high_m"] = boot.confidence_interval.high
                row[f"{name}_wilcoxon_p"] = stats.wilcoxon(d).pvalue
            row[f"{name}_masked_better"] = int((d < 0).sum())
        rows.append(row)
    return pd.DataFrame(rows)


def table_one(runs: pd.DataFrame, data: Path, out: Path) -> pd.DataFrame:
    """`jsve table1` per scene and sequence over ORB-SLAM3's saved trajectories (EuRoC format, SE(3)),
    into OUT/table1/<scene>-<sequence>/; returns the summaries stacked."""
    tables = []
    for (scene, sequence), g in runs.groupby(["scene", "sequence"]):
        gt = data / f"{DATASETS[sequence]}-{scene}" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        files = {arm: [f"{s}.orbslam3-euroc.txt" for s in g[g.arm == arm].sort_values("seed").stem]
                 for arm in ARMS}  # fmt: skip
        files = {
            arm: [f for f in fs if Path(f).is_file() and Path(f).stat().st_size > 100]
            for arm, fs in files.items()
        }
        target = out / "table1" / f"{scene}-{sequence}"
        command = [sys.executable, "-m", "jsve.cli", "table1", "--ref", str(gt), "--format", "euroc",
                   "--align", "se3", "--no-plots", "-o", str(target)]  # fmt: skip
        command += ["--original", *files["original"], "--masked", *files["masked"]]
        subprocess.run(command, check=True, capture_output=True, text=True)
        summary = pd.read_csv(target / "table1.csv")
        summary.insert(0, "sequence", sequence)
        summary.insert(0, "scene", scene)
        tables.append(summary)
    return pd.concat(tables, ignore_index=True)


def offline_vs_loop(runs: pd.DataFrame, data: Path) -> pd.DataFrame:
    """Per original run: its log masked offline (apply_masks on its keypoint side file with the dataset's
    PNG masks) against the masked run of the same seed, on the frames both tracked (by stamp) and
    extracted alike (the masked run's keypoints before masking = the original run's): how many keypoints
    Algorithm 1 removed, the counts, the bins, the inliers and SVE.

    Counts and bins must agree there (ORB extraction is a function of the image and the extractor, and
    ORB-SLAM3 masks after it); inliers are what masking in the loop changes and a replay of masks cannot
    see. `<q>_change_explained`: 1 - sum (loop - offline)^2 / sum (loop - original)^2 over the frames, the
    share of the change masking made to q that offline masking predicts.
    """
    from jsve import apply_masks, read_keypoints
    from jsve.io import keypoints_path, read_log
    from jsve.masks import PngMasks

    rows = []
    for (scene, sequence, seed), g in runs.groupby(["scene", "sequence", "seed"]):
        if set(g.arm) != set(ARMS):
            continue
        stems = {arm: Path(g[g.arm == arm].stem.iloc[0]) for arm in ARMS}
        log = stems["original"].with_suffix(".csv")
        if not keypoints_path(log).is_file():
            continue
        original = read_log(log)
        masks = PngMasks(data / f"{DATASETS[sequence]}-{scene}" / "mav0" / "cam0" / "masks", classes=(1, 2))
        offline = apply_masks(original, read_keypoints(keypoints_path(log)), masks, key="t_ns")
        loop = read_log(stems["masked"].with_suffix(".csv"))
        a = _frames(offline.log, offline.n_removed)
        b = _frames(loop, _trailer(loop, "n_removed"), n_before=_trailer(loop, "n_before"))
        o = _frames(original, np.zeros(len(original.frames), int)).add_suffix("_original")
        joined = a.add_suffix("_offline").join(b.add_suffix("_loop"), how="inner").join(o, how="inner")
        tracked_both = len(joined)
        joined = joined[joined.n_before_loop == joined.n_extracted_original]  # one extractor in both runs
        bins_offline = np.stack(joined.bins_offline.to_numpy())
        bins_loop = np.stack(joined.bins_loop.to_numpy())
        row = {
            "scene": scene, "sequence": sequence, "seed": seed, "tracked_both": tracked_both,
            "frames": len(joined),
            "removed_equal": float(np.mean(joined.removed_offline == joined.removed_loop)),
            "extracted_equal": float(np.mean(joined.n_extracted_offline == joined.n_extracted_loop)),
            "bins_equal": float(np.mean(np.all(bins_offline == bins_loop, axis=1))),
            "removed_mean": float(joined.removed_loop.mean()),
            "removed_share": float(joined.removed_loop.sum() / joined.n_extracted_original.sum()),
        }  # fmt: skip
        for q in ("n_inliers", "s_a", "s_b", "s_c", "sve_option2"):
            loop_q, offline_q, original_q = (joined[f"{q}_{k}"] for k in ("loop", "offline", "original"))
            row[f"{q}_mae_offline_vs_loop"] = float(np.mean(np.abs(offline_q - loop_q)))
            change = np.sum((loop_q - original_q) ** 2)
            row[f"{q}_change_explained"] = (
                float(1 - np.sum((loop_q - offline_q) ** 2) / change) if change else np.nan
            )
        rows.append(row)
    return pd.DataFrame(rows)


def _frames(run, removed, n_before=None) -> pd.DataFrame:
    """Per tracked (OK) frame, by stamp: counts, bins, removed keypoints and the SVE metrics."""
    from jsve.core import sve_table

    f = run.frames
    bins = f[[f"bin_{k}" for k in range(64)]].to_numpy()
    sve = sve_table(f.n_extracted.to_numpy(), f.n_inliers.to_numpy(), f.n_frustum.to_numpy(), bins)
    table = pd.DataFrame({
        "n_extracted": f.n_extracted.to_numpy(), "n_inliers": f.n_inliers.to_numpy(),
        "removed": np.asarray(removed), "s_a": np.asarray(sve["s_a_original"]), "s_b": np.asarray(sve["s_b"]),
        "s_c": np.asarray(sve["s_c"]), "sve_option2": np.asarray(sve["sve_option2"]),
    }, index=f.t_ns.to_numpy())  # fmt: skip
    if n_before is not None:
        table["n_before"] = np.asarray(n_before)
    table["bins"] = list(bins)
    return table[f.state.to_numpy() == 2]


def _trailer(run, key: str) -> np.ndarray:
    """A per-frame list of the masked run's `masks` trailer, by stamp (-1 for a frame it lacks)."""
    trailer = (run.trailers or {})["masks"]
    by_stamp = dict(zip(trailer["t_ns"], trailer[key], strict=True))
    return np.array([by_stamp.get(int(t), -1) for t in run.frames.t_ns])


def figure(runs: pd.DataFrame, paired: pd.DataFrame, path: Path) -> None:
    """Per scene and sequence, each seed's bounded loss without and with masks (a line per seed), and the
    mean paired difference with its 95 % interval in the title."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    groups = list(runs.groupby(["scene", "sequence"]))
    fig = Figure(figsize=(3.0 * len(groups), 3.6), layout="constrained")
    axes = fig.subplots(1, len(groups), sharey=True, squeeze=False)[0]
    axes[0].set_yscale("log")
    for ax, ((scene, sequence), g) in zip(axes, groups, strict=True):
        wide = g.pivot(index="seed", columns="arm", values="loss_m") * 100
        for _, row in wide.iterrows():
            ax.plot([0, 1], [row["original"], row["masked"]], color="0.6", marker="o", markersize=3, lw=0.8)
        ax.plot([0, 1], [wide["original"].mean(), wide["masked"].mean()], color="C3", marker="s", lw=2)
        p = paired[(paired.scene == scene) & (paired.sequence == sequence)].iloc[0]
        ci = f"BCa [{100 * p.loss_bca_low_m:+.2f}, {100 * p.loss_bca_high_m:+.2f}]"
        mean = f"{100 * p.loss_diff_mean_m:+.2f} cm"
        ax.set_title(f"{sequence}, {scene}: {mean}\n{ci}, p = {p.loss_wilcoxon_p:.2g}", fontsize=9)
        ax.set_xticks([0, 1], ["original", "masked"])
        ax.set_xlim(-0.3, 1.3)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("bounded loss per run, cm")
    fig.suptitle(
        "ORB-SLAM3 without and with masks in the loop, paired by seed (masked - original)", fontsize=10
    )
    fig.savefig(path, dpi=120)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("out", type=Path)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--csv", type=Path)
    parser.add_argument("--agreement-csv", type=Path)
    parser.add_argument("--paired-csv", type=Path)
    parser.add_argument("--table1-csv", type=Path)
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    runs = run_table(args.out)
    pd.set_option("display.width", 200)
    pd.set_option("display.max_columns", 40)
    print(runs.groupby(["scene", "sequence", "arm"]).agg(runs=("seed", "size"), failed=("failed", "sum"),
          ate_median_m=("ate_m", "median"), loss_mean_m=("loss_m", "mean"), resets=("resets", "sum"),
          cpu_s=("cpu_s", "mean")).to_markdown(floatfmt=".4f"))  # fmt: skip
    print()
    paired = paired_table(runs)
    print(paired.T.to_markdown(floatfmt=".4g"))
    print()
    t1 = table_one(runs, args.data, args.out)
    print(t1.to_markdown(index=False, floatfmt=".4f"))
    print()
    agreement = offline_vs_loop(runs, args.data)
    print(agreement.to_markdown(index=False, floatfmt=".3f"))
    if args.csv:
        runs.drop(columns="stem").to_csv(args.csv, index=False)
    if args.agreement_csv:
        agreement.to_csv(args.agreement_csv, index=False)
    if args.paired_csv:
        paired.to_csv(args.paired_csv, index=False)
    if args.table1_csv:
        t1.to_csv(args.table1_csv, index=False)
    if args.figure:
        figure(runs, paired, args.figure)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
