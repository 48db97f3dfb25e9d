"""Threshold report of a fitting study: Markdown, a self-contained HTML page, and figures.

`write_report(out_dir)` reads the tables that jsve.fitting._study wrote to `out_dir` (every number of the
report is in one of them, as Parquet and CSV) and writes

    report.md      tables and figures/*.png
    report.html    the same page with the figures embedded (base64 PNG): one file to share
    figures/       sve_levels_<disturbance>.png (seed Figs 4-6), ate_levels.png (Fig 7),
                   heatmap_<family>.png (objective over the two main thresholds), heldout.png

Rendering is deterministic: the same tables give byte-identical files (matplotlib's Agg backend, no
timestamps, fixed ordering). Every file is written through jsve.io's atomic writers (`<name>.partial`,
then a rename), so a killed render leaves no half-written report under its final name.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from jsve.core._rules import BASELINES, PRESETS, RULE_KINDS, preset  # noqa: E402
from jsve.fitting import fitted_rule_name  # noqa: E402
from jsve.io import _atomic as atomic  # noqa: E402

log = logging.getLogger(__name__)

RULE_ORDER = PRESETS + tuple(fitted_rule_name(kind) for kind in RULE_KINDS)
"""The presets, then the fitted families ("fitted-<family>", jsve.fitting.fitted_rule_name)."""
PRESET_PALETTE = ("#444444", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
"""Colours of the presets, in PRESETS order (ORB-SLAM3's rule dark grey)."""
FITTED_COLORS = {"inliers": "#7f7f7f", "sve": "#d62728"}
"""Colour of each family's fitted rule, whatever the number of presets."""
RULE_COLORS = dict(zip(PRESETS, PRESET_PALETTE[: len(PRESETS)], strict=True)) | {
    fitted_rule_name(kind): FITTED_COLORS[kind] for kind in RULE_KINDS
}
"""One colour per rule of RULE_ORDER (presets beyond the palette, or a new family, must choose their own:
the zip is strict)."""
PNG_META = {"Software": None}


# ---------------------------------------------------------------------------------------------------
# Small helpers


def _fmt(x, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.{digits}g}"
    return str(x)


def markdown_table(table: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table of a DataFrame (numbers to 4 significant digits)."""
    head = "| " + " | ".join(map(str, table.columns)) + " |"
    rule = "|" + "|".join("---" for _ in table.columns) + "|"
    rows = ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join([head, rule, *rows])


def _html_cell(value) -> str:
    """A table cell: numbers right-aligned (the page's default), words left-aligned, and short words
    (rule names, settings) kept on one line."""
    text = _fmt(value)
    if isinstance(value, str):
        kind = "w" if len(text) <= 24 else "t"
        return f'<td class="{kind}">{html.escape(text)}</td>'
    return f"<td>{html.escape(text)}</td>"


def html_table(table: pd.DataFrame) -> str:
    cells = "".join(f"<th>{html.escape(str(c))}</th>" for c in table.columns)
    body = "".join(
        "<tr>" + "".join(_html_cell(v) for v in row) + "</tr>" for row in table.itertuples(index=False)
    )
    return f"<table><thead><tr>{cells}</tr></thead><tbody>{body}</tbody></table>"


def _rules(present) -> list[str]:
    present = list(dict.fromkeys(present))
    return [r for r in RULE_ORDER if r in present] + sorted(r for r in present if r not in RULE_ORDER)


def _pm(mean, std) -> str:
    return f"{_fmt(mean)} ± {_fmt(std)}"


def _ci(mean, low, high) -> str:
    return f"{_fmt(mean)} [{_fmt(low)}, {_fmt(high)}]"


def _save(fig, path: Path) -> Path:
    try:
        with atomic.atomic_path(path) as partial:
            fig.savefig(partial, format="png", dpi=110, metadata=PNG_META)
    finally:
        plt.close(fig)
    return path


def _level_sort(levels) -> list:
    return sorted(levels, key=lambda v: float(v))


# ---------------------------------------------------------------------------------------------------
# Figures


def figure_sve_levels(sve_levels: pd.DataFrame, disturbance: str, path: Path) -> Path:
    """SVE mean +- std per level of one disturbance, one line per combination (seed Figs 4-6)."""
    part = sve_levels[sve_levels["disturbance"] == disturbance]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for name in _rules(part["combination"]):
        g = part[part["combination"] == name].sort_values("level", key=lambda s: s.astype(float))
        x = g["level"].astype(float).to_numpy()
        m, s = g["sve_mean"].to_numpy(), g["sve_std"].to_numpy()
        color = RULE_COLORS.get(name)
        ax.plot(x, m, marker="o", ms=3, label=name, color=color)
        ax.fill_between(x, m - s, m + s, alpha=0.15, color=color)
    ax.set_xlabel(f"{disturbance} level")
    ax.set_ylabel("SVE (mean ± std over frames)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"SVE per {disturbance} level")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def figure_ate_levels(summary: pd.DataFrame, path: Path) -> Path:
    """Per disturbance: mean RMS ATE of the runs that kept tracking (top) and failure rate (bottom) per
    level, one line per rule (seed Fig 7)."""
    disturbances = [d for d in sorted(summary["disturbance"].astype(str).unique()) if d != "none"] or ["none"]
    fig, axes = plt.subplots(
        2, len(disturbances), figsize=(4.2 * len(disturbances), 5.6), squeeze=False, sharey="row"
    )
    for j, dist in enumerate(disturbances):
        part = summary[summary["disturbance"].astype(str) == dist]
        for rule in _rules(part["rule"]):
            g = part[part["rule"] == rule].sort_values("level", key=lambda s: s.astype(float))
            x = g["level"].astype(float).to_numpy()
            axes[0, j].plot(
                x, g["rmse_mean_nonfailed"], marker="o", ms=3, label=rule, color=RULE_COLORS.get(rule)
            )
            axes[1, j].plot(x, g["failure_rate"], marker="o", ms=3, label=rule, color=RULE_COLORS.get(rule))
        axes[0, j].set_title(dist)
        axes[1, j].set_xlabel(f"{dist} level")
        for i in range(2):
            axes[i, j].grid(alpha=0.3)
    axes[0, 0].set_ylabel("RMS ATE, m (runs that kept tracking)")
    axes[1, 0].set_ylabel("failure rate")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path)


def figure_heatmap(heat: pd.DataFrame, path: Path, marks: dict[str, tuple[float, float]]) -> Path:
    """The objective over the grid of two thresholds, with marked points (the fit, a preset)."""
    xs, ys = np.unique(heat["x"]), np.unique(heat["y"])
    grid = (
        heat.pivot_table(index="y", columns="x", values="objective").reindex(index=ys, columns=xs).to_numpy()
    )
    fig, ax = plt.subplots(figsize=(5.6, 4.6))
    im = ax.pcolormesh(xs, ys, grid, shading="nearest", cmap="viridis")
    fig.colorbar(im, ax=ax, label="objective, m (penalised mean ATE)")
    for (label, (x, y)), marker in zip(sorted(marks.items()), ("*", "o", "s", "^"), strict=False):
        ax.plot([x], [y], marker=marker, ms=11, mfc="none", mec="white", mew=1.8, ls="none", label=label)
    ax.set_xlabel(str(heat["x_name"].iloc[0]))
    ax.set_ylabel(str(heat["y_name"].iloc[0]))
    ax.set_title(f"{heat['family'].iloc[0]}: objective over two thresholds")
    if marks:
        ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def figure_heldout(summary: pd.DataFrame, path: Path) -> Path:
    """Held-out mean loss with its bootstrap CI per rule, one panel per fold kind."""
    kinds = list(dict.fromkeys(summary["fold_kind"]))
    fig, axes = plt.subplots(1, len(kinds), figsize=(4.0 * len(kinds), 3.6), squeeze=False, sharey=True)
    for j, kind in enumerate(kinds):
        part = summary[summary["fold_kind"] == kind].set_index("rule")
        rules = _rules(part.index)
        y = part.loc[rules, "mean_loss"].to_numpy()
        err = np.stack([y - part.loc[rules, "ci_low"].to_numpy(), part.loc[rules, "ci_high"].to_numpy() - y])
        axes[0, j].bar(
            range(len(rules)), y, yerr=err, capsize=3, color=[RULE_COLORS.get(r, "#999") for r in rules]
        )
        axes[0, j].set_xticks(range(len(rules)), rules, rotation=45, ha="right", fontsize=8)
        axes[0, j].set_title(kind, fontsize=9)
        axes[0, j].grid(alpha=0.3, axis="y")
    axes[0, 0].set_ylabel("held-out objective, m")
    fig.tight_layout()
    return _save(fig, path)


# ---------------------------------------------------------------------------------------------------
# The report


def _read(out: Path, name: str) -> pd.DataFrame | None:
    path = out / f"{name}.parquet"
    return pd.read_parquet(path) if path.is_file() else None


SWITCH_MODEL_TEXT = {
    "orbslam3": "a tracked or RECENTLY_LOST frame keeps its logged (optimised) pose, as ORB-SLAM3 v1.0",
    "imu-coast": "a frame in RECENTLY_LOST takes the IMU prediction from the previous replayed state",
}
"""The switch models in words (docs/state-machine.md)."""
SUPPORT_TEXT = {
    "penalise": "a run whose replay needs a recorded pose the log lacks counts as failed (the penalty)",
    "exclude": "a run whose replay needs a recorded pose the log lacks is left out of that rule's objective",
}
"""The support policies in words (jsve.core._objective)."""


def _config_view(study: dict) -> pd.DataFrame:
    """The study's configuration as (setting, value, meaning) rows; "not recorded" for a setting an older
    study.json lacks."""
    cfg = study.get("config", {})
    fit = cfg.get("fit", {})
    missing = "not recorded"

    def get(key, table=cfg):
        return table.get(key, missing)

    model, support = get("switch_model"), get("support")
    rows = [
        ("switch model", model, SWITCH_MODEL_TEXT.get(model, "")),
        ("support policy", support, SUPPORT_TEXT.get(support, "")),
        ("alignment", get("align"), "before the ATE RMSE (jsve.core.align)"),
        ("failure penalty, m", get("failure_penalty"), "the loss of a failed run"),
        ("coverage floor", get("min_coverage"), "runs below it fail"),
        ("run weighting", ", ".join(study.get("balance_by", [])) or "none", "each group counts equally"),
        ("families", ", ".join(get("families")) if "families" in cfg else missing, "rule families fitted"),
        ("search", f"{get('design', fit)}, {get('n_search', fit)} settings", "plus the presets"),
        ("k-fold", get("kfold"), "folds of the k-fold cross-validation"),
        ("bootstrap resamples", get("n_boot"), f"{get('level')} intervals"),
    ]
    return pd.DataFrame(rows, columns=["setting", "value", "meaning"])


def _heldout_view(summary: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for d in summary.to_dict("records"):
        row = {
            "fold kind": d["fold_kind"],
            "rule": d["rule"],
            "runs": d["n_runs"],
            "held-out objective, m [95% CI]": _ci(d["mean_loss"], d["ci_low"], d["ci_high"]),
            "failure rate": d["failure_rate"],
            "coverage": d["coverage"],
        }
        if "unsupported" in d:
            row["runs out of support"] = d["unsupported"]
        for base in BASELINES.values():
            key = f"diff_vs_{base}"
            present = key in d and pd.notna(d[key])
            row[f"vs {base}, m [CI]"] = (
                _ci(d[key], d[f"{key}_ci_low"], d[f"{key}_ci_high"]) if present else "-"
            )
        rows.append(row)
    return pd.DataFrame(rows)


def _params_view(params: pd.DataFrame) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "family": params["family"],
            "parameter": params["parameter"],
            "fitted": params["value"],
            "95% CI": [
                f"[{_fmt(a)}, {_fmt(b)}]" for a, b in zip(params["ci_low"], params["ci_high"], strict=True)
            ],
            "bootstrap std": params["boot_std"],
        }
    )


SUPPORT_COLUMNS = {
    "mean_changed": "changed",
    "mean_unsupported": "out of support",
    "share_unsupported_runs": "runs out of support",
}
"""The summary's support columns (jsve.evaluation.aggregate) and their headings in the per-level tables:
the mean share of frames whose replayed state differs from the logged one, the mean share of frames
where the replay needs a recorded pose the log lacks, and the share of runs with any such frame."""


def _levels_view(summary: pd.DataFrame, disturbance: str) -> pd.DataFrame:
    part = summary[summary["disturbance"].astype(str) == disturbance]
    rows = []
    for level in _level_sort(part["level"].unique()):
        for rule in _rules(part["rule"]):
            g = part[(part["level"] == level) & (part["rule"] == rule)]
            if g.empty:
                continue
            r = g.iloc[0]
            row = {
                "level": level,
                "rule": rule,
                "runs": int(r["n_runs"]),
                "ATE RMSE, m (mean ± std, runs that kept tracking)": _pm(
                    r["rmse_mean_nonfailed"], r["rmse_std_nonfailed"]
                ),
                "ATE RMSE, m (all runs)": _pm(r["rmse_mean_all"], r["rmse_std_all"]),
                "failure rate": r["failure_rate"],
                "coverage": r["mean_coverage"],
            }
            row.update({head: r[key] for key, head in SUPPORT_COLUMNS.items() if key in r})
            rows.append(row)
    return pd.DataFrame(rows)


def write_report(out_dir: str | os.PathLike, *, title: str = "jsve threshold report") -> dict[str, Path]:
    """Render report.md, report.html and the figures from a study folder's tables.

    Returns:
        Paths of what was written, by name.
    """
    out = Path(out_dir)
    study = json.loads((out / "study.json").read_text()) if (out / "study.json").is_file() else {}
    summary, heldout_summary = _read(out, "summary"), _read(out, "heldout_summary")
    params, heat, sve_levels = _read(out, "params"), _read(out, "heatmap"), _read(out, "sve_levels")
    fitted = {
        p.stem.removeprefix("fitted_"): json.loads(p.read_text()) for p in sorted(out.glob("fitted_*.json"))
    }
    if summary is None:
        raise FileNotFoundError(f"{out}: no summary.parquet; run `jsve fit` (or `jsve demo`) into it first")
    figures: dict[str, Path] = {}
    fig_dir = out / "figures"
    if sve_levels is not None:
        for dist in sorted(sve_levels["disturbance"].astype(str).unique()):
            if dist != "none":
                figures[f"SVE per {dist} level"] = figure_sve_levels(
                    sve_levels, dist, fig_dir / f"sve_levels_{dist}.png"
                )
    if {"disturbance", "level"} <= set(summary.columns):
        figures["RMS ATE and failures per level"] = figure_ate_levels(summary, fig_dir / "ate_levels.png")
    if heat is not None:
        for family, g in heat.groupby("family", sort=True):
            x_name, y_name = g["x_name"].iloc[0], g["y_name"].iloc[0]
            marks = {}
            if family in fitted:
                p = fitted[family]["params"]
                marks["fitted"] = (p[x_name], p[y_name])
            base = BASELINES[str(family)]
            th = preset(base).thresholds
            marks[base] = (float(getattr(th, x_name)), float(getattr(th, y_name)))
            figures[f"Objective over {x_name} x {y_name} ({family})"] = figure_heatmap(
                g, fig_dir / f"heatmap_{family}.png", marks
            )
    if heldout_summary is not None:
        figures["Held-out objective per rule"] = figure_heldout(heldout_summary, fig_dir / "heldout.png")

    sections: list[tuple[str, str, object]] = []  # (heading, text, table or figure path)
    cfg = study.get("config", {})
    facts = study.get("data", {})
    intro = (
        f"{study.get('n_runs', '?')} runs, {study.get('n_frames', '?')} frames. Objective: mean per-run ATE "
        f"RMSE after {cfg.get('align', 'se3')} alignment, a failed run (LOST, degenerate alignment or "
        f"coverage below {cfg.get('min_coverage', 0)}) costs {cfg.get('failure_penalty', '?')} m; runs "
        f"weighted so that each group of {', '.join(study.get('balance_by', [])) or 'runs'} counts equally."
    )
    if facts:
        intro += " Data: " + ", ".join(f"{k} = {v}" for k, v in facts.items()) + "."
    sections.append(("Study", intro, None))
    sections.append(
        (
            "Configuration",
            "How every rule was replayed and scored (study.json). The switch model decides the pose of a "
            "frame the rule rejects; the support policy, what the objective does with a run whose "
            "replay leaves the log's support (docs/state-machine.md, docs/fitting.md).",
            _config_view(study),
        )
    )
    if heldout_summary is not None:
        text = (
            "Each run is held out once per fold kind; fitted rules are refitted without it. Bootstrap "
            "95% intervals over runs; differences are paired (negative: the rule beats the baseline)."
        )
        if cfg.get("support") == "exclude":
            text += (
                " Support policy exclude: every rule is scored on the held-out runs all rules support "
                "(runs); runs out of support is each rule's share of all held-out runs."
            )
        sections.append(("Held-out comparison", text, _heldout_view(heldout_summary)))
    if params is not None:
        sections.append(
            (
                "Fitted parameters",
                "Fitted on all runs; 95% intervals from refits on bootstrap resamples of the runs "
                "(best setting of the search and a dense local design under each resample's weights).",
                _params_view(params),
            )
        )
    for family, rec in fitted.items():
        stages = pd.DataFrame(
            [
                {
                    "stage": s["stage"],
                    "objective, m": s["objective"],
                    "seconds": s.get("seconds", float("nan")),
                }
                for s in rec["stages"]
            ]
        )
        text = (
            f"Rule: `{json.dumps(rec['rule'], sort_keys=True)}`; objective {_fmt(rec['objective'])} m, "
            f"failure rate {_fmt(rec['failure_rate'])}, coverage {_fmt(rec['coverage'])}."
        )
        if "n_unsupported" in rec:
            runs = lambda n: f"{n} run" + ("" if n == 1 else "s")  # noqa: E731
            text += (
                f" The rule's replay leaves the logs' support on {runs(rec['n_unsupported'])} (weighted "
                f"share {_fmt(rec['unsupported_rate'])}); {runs(rec['n_excluded'])} excluded from the "
                "objective."
            )
        sections.append((f"Fit of the {family} family", text, stages))
    if {"disturbance", "level"} <= set(summary.columns):
        for dist in sorted(summary["disturbance"].astype(str).unique()):
            text = "ATE RMSE in metres; failure rate and coverage per rule."
            if "mean_changed" in summary.columns:
                text += (
                    " Support (shares, mean over runs): changed, frames whose replayed state differs from "
                    "the logged one; out of support, frames where the replay needs a recorded pose the log "
                    "lacks (they count as without an estimate here); runs out of support, runs with any "
                    "such frame (the objective applies the support policy to them)."
                )
            sections.append((f"Per level: {dist}", text, _levels_view(summary, dist)))
    for name, path in figures.items():
        sections.append((name, "", path))

    md = [f"# {title}", ""]
    body = []
    for heading, text, obj in sections:
        md += [f"## {heading}", ""]
        body.append(f"<h2>{html.escape(heading)}</h2>")
        if text:
            md += [text, ""]
            body.append(f"<p>{html.escape(text)}</p>")
        if isinstance(obj, pd.DataFrame):
            md += [markdown_table(obj), ""]
            body.append(html_table(obj))
        elif isinstance(obj, Path):
            rel = obj.relative_to(out).as_posix()
            md += [f"![{heading}]({rel})", ""]
            data = base64.b64encode(obj.read_bytes()).decode("ascii")
            body.append(f'<img alt="{html.escape(heading)}" src="data:image/png;base64,{data}">')
    md.append("Every number above is in the study folder's tables (Parquet and CSV); see docs/report.md.")
    style = (
        "body{font-family:sans-serif;max-width:70em;margin:2em auto;padding:0 1em}"
        "table{border-collapse:collapse;margin:1em 0;font-size:90%}td,th{border:1px solid #ccc;"
        "padding:2px 6px;text-align:right}th{background:#f4f4f4}td.t,td.w{text-align:left}"
        "td.w{white-space:nowrap}img{max-width:100%}"
    )
    page = (
        f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{style}</style></head><body><h1>{html.escape(title)}</h1>\n"
        + "\n".join(body)
        + "\n<p>Every number above is in the study folder's tables (Parquet and CSV).</p></body></html>\n"
    )
    written = {"markdown": out / "report.md", "html": out / "report.html"}
    for key, text in (("markdown", "\n".join(md) + "\n"), ("html", page)):
        atomic.write_text(written[key], text)
    written.update({f"figure {k}": v for k, v in figures.items()})
    return written
