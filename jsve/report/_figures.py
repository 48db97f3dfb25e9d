"""The report's figures (matplotlib, Agg backend), written atomically and deterministically.

    heldout.png             held-out objective per rule with its interval: fitted rules per fold kind,
                            presets once
    levels.png              per disturbance level: the objective, the ATE of the runs that kept tracking,
                            the failure rate (seed Fig 7, failure-aware)
    heatmap_<family>.png    the objective over two thresholds, the others held at the fit (named in the
                            figure); presets drawn at their own parameters with their own score
    sve_levels_<dist>.png   SVE mean +- std over frames per level (seed Figs 4-6)

Lengths are in centimetres and levels carry their units (jsve.report._format).
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.patheffects as path_effects  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from jsve.core._rules import PRESETS, RULE_KINDS  # noqa: E402
from jsve.fitting._fit import fitted_rule_name
from jsve.io import _atomic as atomic  # noqa: E402
from jsve.report._derive import rule_order  # noqa: E402
from jsve.report._format import SEVERITY_FALLS_WITH_LEVEL, cm, level_axis, span_mm  # noqa: E402

PRESET_PALETTE = ("#444444", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
"""Colours of the presets, in PRESETS order (ORB-SLAM3's rule dark grey)."""
FITTED_COLORS = {"inliers": "#7f7f7f", "sve": "#d62728"}
"""Colour of each family's fitted rule, whatever the number of presets."""
RULE_COLORS = dict(zip(PRESETS, PRESET_PALETTE[: len(PRESETS)], strict=True)) | {
    fitted_rule_name(kind): FITTED_COLORS[kind] for kind in RULE_KINDS
}
"""One colour per rule (presets beyond the palette, or a new family, must choose their own: the zip is
strict)."""
OTHER_COLORS = ("#bcbd22", "#17becf", "#e377c2", "#8c564b", "#9edae5", "#c49c94")
"""Colours of other rules (rule files evaluated by name), in the order they are drawn."""
PNG_META = {"Software": None}


def rule_color(rule: str, others: list[str]) -> str:
    """A rule's colour: its own (RULE_COLORS), its family's for a fitted rule file ("fitted_sve", as
    `jsve evaluate --rule fitted_sve.json` names it), else the next of OTHER_COLORS."""
    if rule in RULE_COLORS:
        return RULE_COLORS[rule]
    family = rule.removeprefix("fitted_")
    if rule.startswith("fitted_") and family in FITTED_COLORS:
        return FITTED_COLORS[family]
    if rule not in others:
        others.append(rule)
    return OTHER_COLORS[others.index(rule) % len(OTHER_COLORS)]


FOLD_KIND_WORDS = {
    "kfold": "k-fold",
    "leave-one-sequence-out": "held-out sequence",
    "leave-one-disturbance-out": "held-out disturbance",
}
"""Short names of the fold kinds (jsve.fitting._crossval) for labels."""
FLAT_SPAN_M = 0.001
"""A heat map whose objective varies by less than this (or by less than FLAT_SHARE of its mean) is flat:
it is drawn in one colour and said to be flat, never stretched over its noise."""
FLAT_SHARE = 0.01
MIN_COLOUR_SPAN_M = 0.01
"""The colour bar of a flat heat map spans this much around its mean (centimetres stay centimetres)."""
SCORE_UNITS = {"inliers": "inliers", "sve": "SVE score"}
"""Units of each family's thresholds."""


def save(fig, path: Path) -> Path:
    """Write a figure as PNG atomically (no software version in the metadata: byte-identical reruns)."""
    try:
        with atomic.atomic_path(path) as partial:
            fig.savefig(partial, format="png", dpi=110, metadata=PNG_META)
    finally:
        plt.close(fig)
    return path


def _levels_x(levels) -> np.ndarray:
    return np.asarray(levels, np.float64)


def _orient(ax, disturbance: str) -> None:
    if disturbance in SEVERITY_FALLS_WITH_LEVEL:
        ax.invert_xaxis()


def figure_heldout(rows: pd.DataFrame, path: Path) -> Path:
    """Held-out objective (cm) with its 95 % interval, one bar per fitted rule and fold kind and one per
    preset (jsve.report._derive.heldout_rows), best at the top of each group."""
    labels, y, low, high, colors, others = [], [], [], [], [], []
    for d in rows.to_dict("records"):
        kind = FOLD_KIND_WORDS.get(d["fold_kind"], d["fold_kind"])
        labels.append(d["rule"] if d["fold_kind"] == "-" else f"{d['rule']}, {kind}")
        y.append(100 * d["mean_loss"])
        low.append(100 * d["ci_low"])
        high.append(100 * d["ci_high"])
        colors.append(rule_color(d["rule"], others))
    n = len(labels)
    fig, ax = plt.subplots(figsize=(7.2, 0.34 * n + 1.4))
    pos = np.arange(n)[::-1]
    y, low, high = np.asarray(y), np.asarray(low), np.asarray(high)
    err = np.stack([np.nan_to_num(y - low), np.nan_to_num(high - y)])
    ax.barh(pos, y, xerr=err, color=colors, capsize=3, height=0.7)
    right = np.where(np.isfinite(high), high, y)
    for p, value, end in zip(pos, y, right, strict=True):
        ax.text(end, p, f"  {value:.1f}", va="center", ha="left", fontsize=8)
    fitted = sum(1 for d in rows["fold_kind"] if d != "-")
    if 0 < fitted < n:
        ax.axhline(n - fitted - 0.5, color="#888888", lw=0.8, ls=":")
    ax.set_yticks(pos, labels, fontsize=8)
    ax.set_xlabel("held-out objective, cm (95 % CI)")
    ax.grid(alpha=0.3, axis="x")
    ax.set_xlim(0, 1.12 * float(np.nanmax(right)) if n else 1)
    fig.tight_layout()
    return save(fig, path)


def figure_levels(levels: pd.DataFrame, path: Path) -> Path:
    """Per disturbance, one line per rule over the levels: the objective (cm, failed runs at the penalty:
    what the fit minimises), the ATE RMSE of the runs that kept tracking (cm; no point where none did)
    and the share of runs that failed."""
    disturbances = [d for d in sorted(levels["disturbance"].astype(str).unique()) if d != "none"] or ["none"]
    fig, axes = plt.subplots(
        3, len(disturbances), figsize=(4.3 * len(disturbances), 8.2), squeeze=False, sharey="row"
    )
    rules, others = rule_order(levels["rule"]), []
    for j, dist in enumerate(disturbances):
        part = levels[levels["disturbance"].astype(str) == dist]
        for rule in rules:
            g = part[part["rule"] == rule].sort_values("level", key=lambda s: s.astype(float))
            x = _levels_x(g["level"])
            style = dict(marker="o", ms=3, label=rule, color=rule_color(rule, others), lw=1.2)
            if rule.startswith("fitted"):  # the study's fitted-<family>, evaluate's fitted_<family>
                style.update(lw=2.0, ls="--")
            axes[0, j].plot(x, 100 * g["objective"].to_numpy(), **style)
            tracked = np.where(g["n_tracking"].to_numpy() > 0, 100 * g["ate_tracking"].to_numpy(), np.nan)
            axes[1, j].plot(x, tracked, **style)
            axes[2, j].plot(x, 100 * g["objective_failure_rate"].to_numpy(), **style)
        axes[0, j].set_title(dist)
        axes[2, j].set_xlabel(level_axis(dist))
        for i in range(3):
            axes[i, j].grid(alpha=0.3)
            _orient(axes[i, j], dist)
    axes[0, 0].set_ylabel("objective, cm\n(failed runs at the penalty)")
    axes[1, 0].set_ylabel("ATE RMSE, cm\n(runs that kept tracking only)")
    axes[2, 0].set_ylabel("failed runs, %")
    axes[2, 0].set_ylim(-3, 103)
    handles, names = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=min(len(names), 8), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return save(fig, path)


@dataclass(frozen=True)
class Surface:
    """What a heat map shows, in numbers for the text: min, max and span of the objective (m), whether
    it is flat, and the parameters held fixed."""

    low: float
    high: float
    flat: bool
    held: dict


def surface(heat: pd.DataFrame, held: dict) -> Surface:
    low, high = float(heat["objective"].min()), float(heat["objective"].max())
    mean = float(heat["objective"].mean())
    flat = (high - low) < max(FLAT_SPAN_M, FLAT_SHARE * abs(mean))
    return Surface(low, high, flat, held)


def figure_heatmap(
    heat: pd.DataFrame,
    path: Path,
    *,
    fit: tuple[float, float, float] | None,
    presets: dict[str, tuple[float, float, float, str]],
    held: dict[str, str],
) -> tuple[Path, Surface]:
    """The objective (cm) over a grid of two thresholds of one family, the other parameters held at the
    fit (named under the title).

    Arguments:
        fit: (x, y, objective m) of the fitted rule, or None.
        presets: name -> (x, y, its own objective m, what differs in words): a preset sits on this grid
            only by its two thresholds; its other parameters are its own, so the cell under it is not
            its score. It is drawn as an open marker with its own score written beside it.
        held: the other parameters of the surface, name -> value as text.
    """
    info = surface(heat, held)
    xs, ys = np.unique(heat["x"]), np.unique(heat["y"])
    grid = heat.pivot_table(index="y", columns="x", values="objective").reindex(index=ys, columns=xs)
    grid = 100 * grid.to_numpy()
    family, x_name, y_name = (str(heat[c].iloc[0]) for c in ("family", "x_name", "y_name"))
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    if info.flat:
        mid = 100 * (info.low + info.high) / 2
        vmin, vmax = mid - 50 * MIN_COLOUR_SPAN_M, mid + 50 * MIN_COLOUR_SPAN_M
    else:
        vmin, vmax = 100 * info.low, 100 * info.high
    im = ax.pcolormesh(xs, ys, grid, shading="nearest", cmap="viridis", vmin=vmin, vmax=vmax)
    fig.colorbar(im, ax=ax, label="objective, cm (failed runs at the penalty)")
    if info.flat:
        ax.text(
            0.5,
            0.5,
            f"flat: {cm(info.low)} cm everywhere\n(it varies by {span_mm(info.high - info.low)})",
            transform=ax.transAxes,
            ha="center",
            va="center",
            fontsize=11,
            bbox=dict(boxstyle="round", fc="white", alpha=0.85),
        )
    if fit is not None:
        ax.plot([fit[0]], [fit[1]], marker="*", ms=15, mfc="#d62728", mec="white", mew=1.2, ls="none",
                label=f"fit: {cm(fit[2])} cm")  # fmt: skip
    ring = [path_effects.Stroke(linewidth=4.0, foreground="black"), path_effects.Normal()]
    for name, (x, y, score, differs) in sorted(presets.items()):
        ax.plot([x], [y], marker="o", ms=11, mfc="none", mec="white", mew=2.0, ls="none", path_effects=ring,
                label=f"{name} at its own parameters: {cm(score)} cm ({differs})")  # fmt: skip
        ax.annotate(
            f"{name}: {cm(score)} cm",
            (x, y),
            xytext=(8, 8),
            textcoords="offset points",
            fontsize=9,
            color="black",
            bbox=dict(boxstyle="round", fc="white", alpha=0.85),
        )
    unit = SCORE_UNITS.get(family, "score")
    ax.set_xlabel(f"{x_name} threshold ({unit})")
    ax.set_ylabel(f"{y_name} threshold ({unit})")
    held_text = ", ".join(f"{k} {v}" for k, v in held.items())
    ax.set_title(
        f"{family}: objective over {x_name} x {y_name}\n"
        + textwrap.fill(f"held at the fit: {held_text}", 70),
        fontsize=9,
    )
    if fit is not None or presets:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), frameon=False)
    fig.tight_layout()
    return save(fig, path), info


def figure_sve_levels(sve_levels: pd.DataFrame, disturbance: str, path: Path) -> Path:
    """SVE mean +- std over frames per level of one disturbance, one line per combination (seed Figs
    4-6)."""
    part = sve_levels[sve_levels["disturbance"] == disturbance]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    others: list[str] = []
    for name in rule_order(part["combination"]):
        g = part[part["combination"] == name].sort_values("level", key=lambda s: s.astype(float))
        x = _levels_x(g["level"])
        m, s = g["sve_mean"].to_numpy(), g["sve_std"].to_numpy()
        color = rule_color(name, others)
        ax.plot(x, m, marker="o", ms=3, label=name, color=color)
        ax.fill_between(x, m - s, m + s, alpha=0.15, color=color)
    ax.set_xlabel(level_axis(disturbance))
    ax.set_ylabel("SVE score (mean ± std over frames)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"SVE per {disturbance} level")
    ax.grid(alpha=0.3)
    _orient(ax, disturbance)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save(fig, path)
