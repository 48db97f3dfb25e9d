"""SVE response and failures of the real front-end (ORB-SLAM3 v1.0 + jsve's hook) per disturbance level.

    python analysis/real_frontend_response.py LOGDIR [--markdown] [--figure response.png]

LOGDIR is `jsve frontend run`'s output (LOGDIR/<sequence>/<disturbance>-<level>/run_<k>.csv, e.g. over
`jsve render` + `jsve disturb` datasets). Per level: runs; runs in which ORB-SLAM3 itself crashed (the
driver's exit status in run_<k>.summary.json; the log stays `.partial`): failed runs, counted, never
dropped; runs that never initialised a map; runs that lost tracking once they had one (a logged
RECENTLY_LOST or LOST, or a new map); the share of frames ORB-SLAM3 tracked (OK; 0 for a crashed run);
and the mean of S_a, S_b, S_c and Option 2 over the frames where TrackLocalMap ran in the runs that
finished (jsve.core.sve_table on the logged counts). The seed's claim to compare with:
everything fails beyond blur 35.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core import sve_table
from jsve.io import read_log, schema

OK, RECENTLY_LOST, LOST = 2, 3, 4
METRICS = ("s_a_rho025", "s_b", "s_c", "sve_option2")
"""sve_table columns shown: Option 2's inputs (S_a at rho = 0.25, clamped S_b and S_c) and its score."""
LABELS = {"s_a_rho025": "S_a (rho 0.25)", "s_b": "S_b", "s_c": "S_c", "sve_option2": "Option 2"}


def run_row(log) -> dict:
    """One log's (jsve.io.RunLog) outcome and mean SVE metrics."""
    f = log.frames
    state = f["state"].to_numpy()
    tracked_once = (state == OK).any()
    after = state[np.argmax(state == OK) :] if tracked_once else state[:0]
    maps = f["map_id"].to_numpy()
    lost = bool(((after == RECENTLY_LOST) | (after == LOST)).any() or len(np.unique(maps)) > 1)
    cols = sve_table(
        f["n_extracted"].to_numpy(), f["n_inliers"].to_numpy(), f["n_frustum"].to_numpy(),
        f[list(schema.BIN_COLUMNS)].to_numpy(), n_features=log.meta.get("n_features", 1000),
    )  # fmt: skip
    ran = f["n_frustum"].to_numpy() > 0  # TrackLocalMap's SearchLocalPoints ran on the frame
    row = {
        "disturbance": log.meta.get("disturbance", "none"),
        "level": float(log.meta.get("level", 0.0)),
        "run": log.meta["run"],
        "crashed": False,
        "never_initialised": not tracked_once,
        "lost": lost,
        "tracked_share": float((state == OK).mean()),
    }
    for name in METRICS:
        values = np.asarray(cols[name], float)[ran]
        row[name] = float(values.mean()) if values.size else float("nan")
    return row


def _disturbance_of(log: Path) -> tuple[str, float]:
    """(disturbance, level) from the run's folder, OUT/<sequence>/<disturbance>-<level>[/<rule>-<model>]."""
    for folder in (log.parent, log.parent.parent):
        kind, _, level = folder.name.rpartition("-")
        try:
            return kind, float(level)
        except ValueError:
            continue
    raise ValueError(f"{log}: not under a <disturbance>-<level> folder")


def runs_table(logs: str) -> pd.DataFrame:
    """One row per run of `jsve frontend run`'s folder, from its summaries: a finished run's outcome and
    metrics from its log, a crashed run's from its dataset folder's name."""
    rows = []
    for summary in sorted(Path(logs).rglob("*.summary.json")):
        info = json.loads(summary.read_text())
        log = Path(info["log"])
        if info.get("exit_code") == 0 and log.is_file():
            rows.append(run_row(read_log(log)))
            continue
        kind, level = _disturbance_of(log)
        run = int(log.name.split("_")[-1].split(".")[0])
        rows.append({"disturbance": kind, "level": level, "run": run, "crashed": True,
                     "never_initialised": False, "lost": True, "tracked_share": 0.0})  # fmt: skip
    runs = pd.DataFrame(rows)
    runs["failed"] = runs["crashed"] | runs["never_initialised"] | runs["lost"]
    return runs


def level_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Per (disturbance, level): counts of runs and outcomes, mean tracked share and metrics."""
    g = runs.groupby(["disturbance", "level"])
    table = g.agg(
        runs=("run", "size"),
        failed=("failed", "sum"),
        crashed=("crashed", "sum"),
        never_initialised=("never_initialised", "sum"),
        lost=("lost", "sum"),
        tracked_share=("tracked_share", "mean"),
        **{name: (name, "mean") for name in METRICS},
    ).reset_index()
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", metavar="LOGDIR")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    parser.add_argument("--figure", metavar="PNG", help="write the response curves here")
    parser.add_argument("-o", "--output", metavar="CSV", help="write the per-level table here")
    args = parser.parse_args(argv)
    runs = runs_table(args.logs)
    table = level_table(runs)
    if args.output:
        table.to_csv(args.output, index=False)
    if args.markdown:
        print("| " + " | ".join(table.columns) + " |\n|" + "---|" * len(table.columns))
        for row in table.itertuples(index=False):
            print("| " + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row) + " |")
    else:
        print(table.to_string(index=False))
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        kinds = [d for d in table["disturbance"].unique() if d != "none"]
        base = table[table["disturbance"] == "none"]
        fig, axes = plt.subplots(1, len(kinds), figsize=(5 * len(kinds), 3.6), squeeze=False)
        for ax, kind in zip(axes[0], kinds, strict=True):
            part = pd.concat([base.assign(disturbance=kind), table[table["disturbance"] == kind]])
            part = part.sort_values("level")
            for name in METRICS:
                ax.plot(part["level"], part[name], marker="o", label=LABELS[name])
            ax.plot(part["level"], part["tracked_share"], "k--", marker="s", label="frames tracked (OK)")
            share = part["failed"] / part["runs"]
            ax.plot(part["level"], share, "r:", marker="x", label="runs failed (share)")
            ax.set_xlabel(
                f"{kind} level" + (" (kernel n x n px)" if kind == "blur" else " (occluder side, px)")
            )
            ax.set_ylim(0, 1.05)
            ax.set_title(f"real ORB-SLAM3 v1.0, {kind}")
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("mean over frames")
        axes[0][-1].legend(fontsize=8, loc="lower left")
        fig.tight_layout()
        fig.savefig(args.figure, dpi=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())
