"""Tables and sections both reports share: every rule over all runs, the per-level tables and figure,
the configuration in words.

Lengths in centimetres, shares in percent (jsve.report._format); the numbers from jsve.report._derive.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from jsve.core._rules import BASELINES
from jsve.report import _derive as derive
from jsve.report import _figures as figures
from jsve.report._document import Details, Figure, Section, Sub, Table
from jsve.report._format import SEVERITY_FALLS_WITH_LEVEL, cm, cm_ci, level_axis, metres, number, percent

SWITCH_MODEL_TEXT = {
    "orbslam3": "a tracked or RECENTLY_LOST frame keeps its logged (optimised) pose, as in ORB-SLAM3 v1.0",
    "imu-coast": "a frame in RECENTLY_LOST takes the IMU prediction from the previous replayed state",
}
"""The switch models in words (docs/state-machine.md)."""
SUPPORT_TEXT = {
    "penalise": "a run whose replay needs a recorded pose the log lacks counts as failed",
    "exclude": "a run whose replay needs a recorded pose the log lacks is left out of that rule's objective",
}
"""The support policies in words (jsve.core._objective)."""
ALIGN_TEXT = {
    "se3": "SE(3)",
    "sim3": "Sim(3)",
    "posyaw": "position and yaw (4-DoF)",
    "origin": "origin",
    "none": "no",
}
"""The alignments (jsve.core._align.ALIGNERS) in words."""


def read_table(out: Path, name: str) -> pd.DataFrame | None:
    """`out/<name>.parquet`, or None where the folder lacks it."""
    path = out / f"{name}.parquet"
    return pd.read_parquet(path) if path.is_file() else None


def read_json(path: Path) -> dict:
    """A JSON file's object, {} where the file does not exist."""
    return json.loads(path.read_text()) if path.is_file() else {}


OVERVIEW_TEXT = (
    "Frames rejected: the share of frames not tracked OK; runs reaching LOST: the share of runs that lost "
    "tracking at least once. The ATE RMSE column averages only the runs that kept tracking (n of them)."
)


def rule_file(rule: str) -> str:
    """The file of a fitted rule ("fitted-sve" -> "fitted_sve.json"), a preset's name otherwise."""
    return f"fitted_{rule.removeprefix('fitted-')}.json" if rule.startswith("fitted-") else rule


def overview_table(overview: pd.DataFrame, diffs: pd.DataFrame | None = None) -> pd.DataFrame:
    """All runs, per rule: the objective, failures, coverage, switching."""
    rows = []
    for d in overview.to_dict("records"):
        row = {"rule": d["rule"], "runs": d["n_runs"]}
        if diffs is not None:
            e = diffs.set_index("rule").loc[d["rule"]]
            row["objective, cm [95 % CI]"] = cm_ci(e["mean_loss"], e["ci_low"], e["ci_high"])
            for base in BASELINES.values():
                key = f"diff_vs_{base}"
                row[f"vs {base}, cm [CI]"] = (
                    cm_ci(e[key], e[f"{key}_ci_low"], e[f"{key}_ci_high"], sign=True) if key in e else "-"
                )
        else:
            row["objective, cm"] = cm(d["objective"])
        row["failed runs"] = percent(d["failure_rate"])
        row["coverage"] = percent(d["coverage"])
        if "rejected" in d:
            row["frames rejected"] = percent(d["rejected"])
        if "reached_lost" in d:
            row["runs reaching LOST"] = percent(d["reached_lost"])
        for event, name in (("resets", "resets per run"), ("new_maps", "new maps per run")):
            if event in d:
                row[name] = number(d[event], 2)
        row["ATE RMSE of runs that kept tracking, cm"] = (
            f"{cm(d['ate_tracking'])} (n = {d['n_tracking']})" if d["n_tracking"] else "- (n = 0)"
        )
        rows.append(row)
    return pd.DataFrame(rows)


def _levels(part: pd.DataFrame, disturbance: str) -> tuple[list, dict]:
    """A disturbance's levels from mild to harsh (decreasing where severity falls with the level, as for
    downsampling) and each one's label, all with the same decimals ("1.0", "0.9", ...; "0", "50")."""
    levels = sorted(part["level"].unique(), key=float, reverse=disturbance in SEVERITY_FALLS_WITH_LEVEL)
    decimals = max((len(number(float(v), 3).partition(".")[2]) for v in levels), default=0)
    return levels, {v: f"{float(v):.{decimals}f}" for v in levels}


def _compact_levels(levels: pd.DataFrame, disturbance: str) -> pd.DataFrame:
    """One row per level, one column per rule: "objective cm (failed %)"."""
    part = levels[levels["disturbance"].astype(str) == disturbance]
    rules = derive.rule_order(part["rule"])
    rows = []
    levels_, labels = _levels(part, disturbance)
    for level in levels_:
        g = part[part["level"] == level].set_index("rule")
        row = {level_axis(disturbance): labels[level]}
        for rule in rules:
            if rule in g.index:
                r = g.loc[rule]
                row[rule] = f"{cm(r['objective'])} ({percent(r['objective_failure_rate'])})"
        rows.append(row)
    return pd.DataFrame(rows)


def _detailed_levels(levels: pd.DataFrame, disturbance: str) -> pd.DataFrame:
    part = levels[levels["disturbance"].astype(str) == disturbance]
    rules = derive.rule_order(part["rule"])
    rows = []
    levels_, labels = _levels(part, disturbance)
    for level in levels_:
        g = part[part["level"] == level].set_index("rule")
        for rule in rules:
            if rule not in g.index:
                continue
            r = g.loc[rule]
            n = int(r["n_tracking"])
            spread = f" ± {cm(r['rmse_std_nonfailed'])}" if n > 1 else ""
            tracked = f"{cm(r['ate_tracking'])}{spread} (n = {n})" if n else "- (n = 0)"
            row = {
                level_axis(disturbance): labels[level],
                "rule": rule,
                "runs": int(r["n_runs"]),
                "objective, cm": cm(r["objective"]),
                "failed runs": percent(r["objective_failure_rate"]),
                "coverage": percent(r["coverage"]),
                "ATE RMSE of runs that kept tracking, cm (mean ± sd, n)": tracked,
            }
            for key, head in (
                ("mean_changed", "frames changed"),
                ("mean_unsupported", "frames out of support"),
                ("share_unsupported_runs", "runs out of support"),
            ):
                if key in r:
                    row[head] = percent(r[key])
            rows.append(row)
    return pd.DataFrame(rows)


LEVELS_TEXT = (
    "Per level, each rule's objective as the fit scores it (mean per-run ATE RMSE with every failed run "
    "at the penalty) and, in brackets, the share of runs that failed (reached LOST, a degenerate "
    "alignment, too few frames, or out of the log's support under the penalise policy). The ATE of the "
    "runs that kept tracking alone is in the collapsed table: it is never an average over failed runs."
)
SUPPORT_COLUMNS_TEXT = (
    "Frames changed: the mean share of frames whose replayed state differs from the logged one; frames "
    "out of support: where the replay needs a recorded pose the log lacks; runs out of support: runs with "
    "any such frame."
)


def level_sections(levels: pd.DataFrame | None, fig_dir: Path) -> tuple[list, Section | None]:
    """The levels figure block and the per-level section (compact tables open, details collapsed)."""
    if levels is None or levels.empty:
        return [], None
    path = figures.figure_levels(levels, fig_dir / "levels.png")
    figure_blocks = [
        Sub("Per disturbance level"),
        "Top: the objective (failed runs at the penalty), what the fit minimises. Middle: the ATE RMSE of "
        "the runs that kept tracking only (no point where every run failed). Bottom: the share of runs "
        "that failed. Fitted rules dashed.",
        Figure(path, "objective, ATE of tracking runs and failures per level"),
    ]
    blocks: list = [LEVELS_TEXT]
    support_text = (SUPPORT_COLUMNS_TEXT,) if "mean_changed" in levels else ()
    for dist in sorted(levels["disturbance"].astype(str).unique()):
        blocks += [
            Sub(f"{dist}: objective, cm (failed runs)"),
            Table(_compact_levels(levels, dist)),
            Details(
                f"{dist}: every rule and level in detail",
                (*support_text, Table(_detailed_levels(levels, dist))),
            ),
        ]
    return figure_blocks, Section("Per level", blocks)


def has_levels(runs: pd.DataFrame) -> bool:
    return {"disturbance", "level"} <= set(runs.columns)


def scoring_bullets(
    scoring: derive.Scoring,
    *,
    align: str,
    min_coverage: float,
    switch_model: str | None,
    support: str | None,
) -> list[str]:
    """How runs were scored, in sentences (the Method of both reports): the objective with its alignment,
    penalty and what fails a run, the run weighting, the switch model and the support policy (each left
    out where None: a folder written before the setting was recorded).

    Arguments:
        scoring: the penalty (metres) and weighting. align: jsve.core._align's method name.
        min_coverage: the coverage floor, a share of frames (0: none).
    """
    strict = scoring.failure == "strict"
    fails = "its alignment is degenerate or fewer than 3 frames are evaluated"
    if strict:
        fails = "loses tracking once (a reset, an expiry to LOST or a new map), " + fails
    if min_coverage > 0:
        share = percent(min_coverage)
        fails += f", or its saved trajectory covers fewer than {share} of its frames with ground truth"
    cap = f", capped at {metres(scoring.penalty)}" if scoring.loss == "bounded" else " (raw, uncapped)"
    items = [
        f"Objective: the mean per-run ATE RMSE of the trajectory the front-end saves, after "
        f"{ALIGN_TEXT.get(align, align)} alignment{cap}; a failed run charged {metres(scoring.penalty)}. "
        f"A run fails when {'it ' if strict else ''}{fails}"
        + ("; there is no coverage floor." if min_coverage <= 0 else ".")
        + ("" if strict else " Resets, new maps and loop closures are events, not failures."),
        (
            f"Runs weighted so that every ({', '.join(scoring.balance_by)}) group counts equally."
            if scoring.balance_by
            else "Every run weighs the same."
        ),
    ]
    if switch_model:
        model = SWITCH_MODEL_TEXT.get(switch_model, "")
        items.append(f"Switch model `{switch_model}`: {model} (docs/state-machine.md).")
    if support:
        items.append(f"Support policy `{support}`: {SUPPORT_TEXT.get(support, '')}.")
    return items
