"""SVE response and failures of the real front-end (ORB-SLAM3 v1.0 + jsve's hook) per disturbance level.

    python analysis/real_frontend_response.py LOGDIR [--simulated SIMDIR] [--markdown] [--figure response.png]

LOGDIR is `jsve frontend run`'s output (LOGDIR/<sequence>/<disturbance>-<level>/run_<k>.csv, e.g. over
`jsve render` + `jsve disturb` datasets). Per level: runs; runs in which ORB-SLAM3 itself crashed (the
driver's exit status in run_<k>.summary.json; the log stays `.partial`): failed runs, counted, never
dropped; runs that never initialised a map; runs that lost tracking once they had one (a logged
RECENTLY_LOST or LOST, or a new map); the share of frames ORB-SLAM3 tracked (OK; 0 for a crashed run);
and the mean of S_a, S_b, S_c and Option 2 over the frames where TrackLocalMap ran in the runs that
finished (jsve.core.sve_table on the logged counts). The seed's claim to compare with:
everything fails beyond blur 35.

SIMDIR (optional) is a `jsve simulate` study of the same sequence and levels: its logs go through the
same per-run and per-level rules, and the figure draws them beside the real front-end's (dashed), so
the simulator's vision model is compared with the real front-end on the same disturbances.
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
        log = summary.parent / Path(info["log"]).name  # the summary's path may be relative to where it ran
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


def simulated_runs_table(study: str) -> pd.DataFrame:
    """One row per log of a `jsve simulate` study folder (the same rules as `run_row`; a simulated run
    never crashes)."""
    paths = sorted(p for p in Path(study).rglob("*.csv") if p.name.startswith("run"))
    if not paths:
        raise SystemExit(f"{study}: no simulator logs (run_*.csv)")
    runs = pd.DataFrame([run_row(read_log(p)) for p in paths])
    # The simulator writes the undisturbed runs as a level of a disturbance (blur 0): the baseline.
    base = runs["level"] == runs["disturbance"].map(BASE_LEVEL)
    runs.loc[base, ["disturbance", "level"]] = ["none", 0.0]
    runs["failed"] = runs["crashed"] | runs["never_initialised"] | runs["lost"]
    return runs


BASE_LEVEL = {"blur": 0.0, "occlusion": 0.0, "downsample": 1.0}
"""The level of each disturbance that is the undisturbed sequence (plotted from the `none` runs)."""

AXIS = {"blur": "blur (Gaussian kernel n x n px)", "occlusion": "occlusion (occluder side, px)",
        "downsample": "downsampling (scale factor)"}  # fmt: skip


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
    parser.add_argument("--simulated", metavar="SIMDIR", help="a jsve simulate study to draw beside")
    parser.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    parser.add_argument("--figure", metavar="PNG", help="write the response curves here")
    parser.add_argument("-o", "--output", metavar="CSV", help="write the per-level table here")
    args = parser.parse_args(argv)
    table = level_table(runs_table(args.logs)).assign(source="real")
    if args.simulated:
        table = pd.concat(
            [table, level_table(simulated_runs_table(args.simulated)).assign(source="simulator")]
        )
    if args.output:
        table.to_csv(args.output, index=False)
    if args.markdown:
        print("| " + " | ".join(table.columns) + " |\n|" + "---|" * len(table.columns))
        for row in table.itertuples(index=False):
            print("| " + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row) + " |")
    else:
        print(table.to_string(index=False))
    if args.figure:
        plot(table, args.figure)
    return 0


def plot(table: pd.DataFrame, path: str) -> None:
    """One panel per disturbance: mean S_a, S_b, S_c, Option 2, frames tracked and failed runs per level,
    the real front-end solid, the simulator dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [d for d in BASE_LEVEL if d in set(table["disturbance"])]
    fig, axes = plt.subplots(1, len(kinds), figsize=(5.2 * len(kinds), 4.0), squeeze=False)
    colours = dict(
        zip([*METRICS, "tracked_share", "failed_share"], plt.get_cmap("tab10").colors, strict=False)
    )
    labels = {
        **LABELS,
        "tracked_share": "frames tracked (OK)",
        "failed_share": "runs that lost tracking or never started (share)",
    }
    for ax, kind in zip(axes[0], kinds, strict=True):
        for source, style in (("real", "-"), ("simulator", "--")):
            own = table[table["source"] == source]
            base = own[own["disturbance"] == "none"].assign(disturbance=kind, level=BASE_LEVEL[kind])
            part = pd.concat([base, own[own["disturbance"] == kind]]).sort_values("level")
            if part.empty:
                continue
            part = part.assign(failed_share=part["failed"] / part["runs"])
            for name in [*METRICS, "tracked_share", "failed_share"]:
                ax.plot(part["level"], part[name], style, color=colours[name], marker="o", ms=3,
                        label=f"{labels[name]} ({source})")  # fmt: skip
        ax.set_xlabel(AXIS[kind])
        if kind == "downsample":
            ax.invert_xaxis()  # from the full image (1.0) to the smallest
        ax.set_ylim(-0.02, 1.05)
        ax.set_title(f"{kind}: real ORB-SLAM3 v1.0 (solid) vs simulator (dashed)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean over frames / share of runs")
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=4, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
