"""The lockstep study's tables (docs/frontend.md, "Lockstep runs"), from the folder sweeps/lockstep_study.sh
wrote: repeats byte for byte, distinct seeds, where a run's time goes, lockstep against paced runs, and
how two rules pair across seeds.

    python analysis/lockstep_study.py OUT [--csv docs/data/lockstep_runs.csv] \
        [--figure docs/figures/lockstep_vs_paced.png]

Every run is scored as `jsve evaluate` scores a real run: failed when it ended in anything but "ok", saved
no trajectory, or covers less than DEFAULT_MIN_COVERAGE of its frames; its loss is the failure penalty
then, else min(ATE, penalty) (the bounded loss) with ATE that of ORB-SLAM3's saved trajectory rebuilt
from the log (SE(3) alignment, metres).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from jsve import ObjectiveConfig
from jsve.tuning import run_row

DEFAULT_FAILURE_PENALTY_M = ObjectiveConfig().failure_penalty
DEFAULT_MIN_COVERAGE = ObjectiveConfig().min_coverage

REPEAT_FOLDERS = ("repeats", "rules")
"""Study folders whose rep<i> subfolders repeat the same runs (ORB-SLAM3's rule; other rules and modes)."""

RESOLVE_M = 0.05
"""The difference between two rules the pairing table sizes a study for (metres)."""


def _sha(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else None


def run_table(out: Path) -> pd.DataFrame:
    """One row per finished run under OUT/{lockstep,paced,repeats/rep<i>,rules/rep<i>}: its study, dataset,
    rule,
    seed, outcome, scores, events, time breakdown (s) and the digests of its log and trajectory."""
    rows = []
    for summary_path in sorted(out.rglob("run_*.summary.json")):
        s = json.loads(summary_path.read_text())
        if "exit_code" not in s:
            continue  # not finished
        rel = summary_path.relative_to(out).parts
        repeated = rel[0] in REPEAT_FOLDERS
        study = "/".join(rel[:2]) if repeated else rel[0]
        tail = rel[2:] if repeated else rel[1:]
        sequence, level = tail[0], tail[1]
        rule = tail[2] if len(tail) == 4 else "orbslam3-orbslam3"
        stem = summary_path.with_name(summary_path.name.removesuffix(".summary.json"))
        t = s.get("time", {})
        row = run_row(s, DEFAULT_FAILURE_PENALTY_M, DEFAULT_MIN_COVERAGE)
        rows.append({
            "study": study, "sequence": sequence, "level": level, "rule": rule, "run": stem.name,
            "mode": s.get("mode"), "seed": s.get("seed"),
            **{k: row[k] for k in ("outcome", "failed", "ate_m", "coverage", "loss_m", "resets", "loops")},
            "merges": (s.get("events") or {}).get("merge", 0), "keyframes": s.get("keyframes_at_end"),
            "wall_s": s.get("wall_seconds"), "cpu_s": t.get("cpu_s"),
            "start_s": t.get("setup_s", 0) + t.get("system_s", 0), "decode_s": t.get("decode_s"),
            "track_s": t.get("track_s"), "local_mapping_s": t.get("local_mapping_s"),
            "loop_closing_s": t.get("loop_closing_s"), "gba_s": t.get("gba_wait_s"),
            "gates_s": (t.get("settle_s", 0) - t.get("local_mapping_s", 0) - t.get("loop_closing_s", 0)
                        - t.get("gba_wait_s", 0)),
            "pace_s": t.get("pace_s"), "finish_s": t.get("finish_s"), "main_s": t.get("main_s"),
            "log_sha": _sha(stem.with_suffix(".csv")), "trajectory_sha": _sha(Path(f"{stem}.orbslam3.txt")),
        })  # fmt: skip
    return pd.DataFrame(rows)


def repeats_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Per (dataset, rule, seed) repeated under OUT/repeats: how many repeats, and how many distinct
    logs and trajectories they wrote (1 and 1: byte-identical), with the run's events."""
    rep = runs[runs.study.str.contains("/")].assign(folder=lambda r: r.study.str.split("/").str[0])
    return (
        rep.groupby(["folder", "sequence", "level", "rule", "seed"])
        .agg(
            repeats=("run", "size"),
            distinct_logs=("log_sha", "nunique"),
            distinct_trajectories=("trajectory_sha", "nunique"),
            resets=("resets", "max"),
            loops=("loops", "max"),
            ate_m=("ate_m", "first"),
            outcome=("outcome", "first"),
        )  # fmt: skip
        .reset_index()
    )


def seeds_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Per lockstep dataset and rule: runs, distinct logs among its seeds, and the events seen."""
    lock = runs[runs.study == "lockstep"]
    return (
        lock.groupby(["sequence", "level", "rule"])
        .agg(
            seeds=("seed", "nunique"),
            distinct_logs=("log_sha", "nunique"),
            runs_with_reset=("resets", lambda x: int((x > 0).sum())),
            runs_with_loop=("loops", lambda x: int((x > 0).sum())),
            failed=("failed", "sum"),
        )  # fmt: skip
        .reset_index()
    )


TIME_COLUMNS = ["start_s", "decode_s", "track_s", "local_mapping_s", "loop_closing_s", "gba_s", "gates_s",
                "pace_s", "finish_s", "wall_s", "cpu_s"]  # fmt: skip


def time_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Mean seconds per run by mode and sequence (ORB-SLAM3's rule); runs per core-hour (each batch ran one
    driver per core, so a run's wall time is the core-seconds it held) and per CPU-hour (its CPU time)."""
    own = runs[(runs.rule == "orbslam3-orbslam3") & runs.study.isin(["lockstep", "paced"])]
    table = own.groupby(["mode", "sequence"])[TIME_COLUMNS].mean()
    table["runs_per_core_hour"] = 3600.0 / table["wall_s"]  # what the machine delivered
    table["runs_per_cpu_hour"] = 3600.0 / table["cpu_s"]  # what the runs consumed
    return table.reset_index()


def gap_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Lockstep against paced runs of ORB-SLAM3's rule per dataset: failures, median ATE of the runs
    that did not fail, mean bounded loss, and a two-sided Mann-Whitney U test of the losses (the runs
    are not paired: a paced run's threads are not controlled by its seed)."""
    own = runs[(runs.rule == "orbslam3-orbslam3") & runs.study.isin(["lockstep", "paced"])]
    rows = []
    for (sequence, level), g in own.groupby(["sequence", "level"]):
        lock, paced = g[g["mode"] == "lockstep"], g[g["mode"] == "paced"]
        if lock.empty or paced.empty:
            continue
        test = stats.mannwhitneyu(lock.loss_m, paced.loss_m, alternative="two-sided")
        rows.append({
            "sequence": sequence, "level": level, "runs": f"{len(lock)} / {len(paced)}",
            "failed_lockstep": int(lock.failed.sum()), "failed_paced": int(paced.failed.sum()),
            "median_ate_lockstep_m": lock.ate_m[~lock.failed].median(),
            "median_ate_paced_m": paced.ate_m[~paced.failed].median(),
            "mean_loss_lockstep_m": lock.loss_m.mean(), "mean_loss_paced_m": paced.loss_m.mean(),
            "mann_whitney_p": test.pvalue,
        })  # fmt: skip
    return pd.DataFrame(rows)


def pairing(
    runs: pd.DataFrame, rule_a: str = "orbslam3-orbslam3", rule_b: str = "sve-option2-orbslam3"
) -> dict:
    """How two rules' lockstep losses pair across (dataset, seed): their correlation, the spread of the
    paired differences, and the runs a two-sided test at alpha 0.05 with power 0.8 needs to resolve
    RESOLVE_M: paired n = ((z_a + z_b) sd_d / delta)^2, unpaired n per rule = 2 ((z_a + z_b) sd / delta)^2."""
    lock = runs[runs.study == "lockstep"]
    a = lock[lock.rule == rule_a].set_index(["sequence", "level", "seed"]).loss_m
    b = lock[lock.rule == rule_b].set_index(["sequence", "level", "seed"]).loss_m
    both = pd.concat({"a": a, "b": b}, axis=1).dropna()
    if len(both) < 3:
        return {}
    d = both.b - both.a
    z = stats.norm.ppf(0.975) + stats.norm.ppf(0.8)
    sd = np.sqrt((both.a.var() + both.b.var()) / 2)
    wilcoxon = stats.wilcoxon(d) if (d != 0).any() else None
    return {
        "pairs": len(both), "pearson_r": stats.pearsonr(both.a, both.b)[0],
        "spearman_r": stats.spearmanr(both.a, both.b)[0], "mean_difference_m": d.mean(),
        "sd_difference_m": d.std(),
        "sd_loss_m": sd, "n_paired": int(np.ceil((z * d.std() / RESOLVE_M) ** 2)),
        "n_unpaired_per_rule": int(np.ceil(2 * (z * sd / RESOLVE_M) ** 2)),
        "wilcoxon_p": None if wilcoxon is None else wilcoxon.pvalue,
    }  # fmt: skip


def gap_figure(runs: pd.DataFrame, path: Path) -> None:
    """Every run's bounded loss by dataset, lockstep beside paced (ORB-SLAM3's rule); failures at the
    penalty, marked x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    own = runs[(runs.rule == "orbslam3-orbslam3") & runs.study.isin(["lockstep", "paced"])]
    groups = sorted(own.groupby(["sequence", "level"]).groups)
    fig, ax = plt.subplots(figsize=(9, 4))
    for i, key in enumerate(groups):
        g = own[(own.sequence == key[0]) & (own.level == key[1])]
        for j, (mode, colour) in enumerate((("lockstep", "tab:blue"), ("paced", "tab:orange"))):
            m = g[g["mode"] == mode]
            x = i + (j - 0.5) * 0.3 + np.linspace(-0.06, 0.06, max(len(m), 1))[: len(m)]
            ok = ~m.failed.to_numpy()
            ax.scatter(x[ok], m.loss_m[ok] * 100, s=14, color=colour, label=mode if i == 0 else None)
            ax.scatter(x[~ok], m.loss_m[~ok] * 100, s=24, marker="x", color=colour)
    ax.set_xticks(range(len(groups)), [f"{s}\n{lv}" for s, lv in groups])
    ax.set_yscale("log")
    ax.set_ylabel("bounded loss (cm)")
    ax.set_title("ORB-SLAM3's rule, 10 seeds: ATE of the saved trajectory; x: failed run (the penalty)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _frame_rows(log: Path) -> list[str]:
    """A log's frame rows: after its two header lines, before its trailer and end marker."""
    return [line for line in log.read_text().splitlines()[2:] if not line.startswith("#")]


def divergence_table(out: Path, rule_b: str = "sve-option2-orbslam3") -> pd.DataFrame:
    """Per (dataset, seed) run in lockstep under ORB-SLAM3's rule and `rule_b`: the first frame where the
    two logs differ and the first where their tracking state differs. Where the logs differ first in
    anything but a decision, something besides the rule (the heap the metadata leaves) set them apart."""
    rows = []
    for b in sorted((out / "lockstep").glob(f"*/*/{rule_b}/run_*.csv")):
        a = b.parent.parent / b.name
        if not a.is_file():
            continue
        lines_a, lines_b = _frame_rows(a), _frame_rows(b)
        pairs = list(zip(lines_a, lines_b, strict=False))
        first = next((k for k, (x, y) in enumerate(pairs) if x != y), None)
        state = next((k for k, (x, y) in enumerate(pairs)
                      if x.split(",", 2)[1] != y.split(",", 2)[1]), None)  # fmt: skip
        rows.append({"sequence": a.parts[-3], "level": a.parts[-2], "run": a.stem, "frames": len(lines_a),
                     "first_difference": first, "first_state_difference": state})  # fmt: skip
    return pd.DataFrame(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the study's folder (sweeps/lockstep_study.sh OUT)")
    parser.add_argument("--csv", type=Path, help="write every run's row here")
    parser.add_argument("--figure", type=Path, help="write the lockstep-against-paced figure here (PNG)")
    args = parser.parse_args()
    runs = run_table(args.out)
    if args.csv:
        runs.to_csv(args.csv, index=False)
    if args.figure:
        gap_figure(runs, args.figure)
    pd.set_option("display.width", 200)
    tables = {"Repeats": repeats_table(runs), "Seeds": seeds_table(runs),
              "Time per run (s)": time_table(runs),
              "Lockstep against paced": gap_table(runs)}  # fmt: skip
    for title, table in tables.items():
        print(f"\n## {title}\n")
        print(table.to_markdown(index=False, floatfmt=".4g") if len(table) else "(no runs)")
    print("\n## Where orbslam3 and sve-option2 runs of one seed part (lockstep)\n")
    div = divergence_table(args.out)
    print(div.to_markdown(index=False) if len(div) else "(no pairs)")
    print("\n## Pairing (lockstep, orbslam3 against sve-option2)\n")
    print(json.dumps(pairing(runs), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
