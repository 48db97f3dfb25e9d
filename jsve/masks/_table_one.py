"""Table I of the seed paper: APE statistics of two sets of runs side by side (masked vs original), plots.

The seed (Masked ORB-SLAM3 on KITTI odometry) reports APE RMSE, mean, median, std, min, max and SSE for
the masked and the original system, an APE-over-time plot and the error distribution. This module makes
that report for any sets of estimates against their references:

    pairs = {"original": read_pose_pairs(ref, originals, "kitti"), "masked": [PosePair(...), ...]}
    table = table_one(pairs, align="se3")          # statistics: jsve.core._trajectory (evo's definitions)
    write_report(table, "out/")                    # Markdown + CSV, PNG/SVG plots, aligned KITTI poses

Pose pairs are read and padded by jsve.io._trajectories and scored by
jsve.core._pose_error.batched_pose_error (as `jsve ape` scores them: one compiled kernel per table);
per-run tables from jsve.evaluation._aggregate.
Compute in float64 (`jax_enable_x64`) to match evo to 1e-6; `jsve table1` does. Plots use matplotlib
without pyplot (Agg for PNG); the density is a Gaussian KDE written in numpy (Scott's bandwidth, as
scipy's default). Files are written atomically (jsve.io._atomic).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from jsve.core._pose_error_batch import batched_pose_error
from jsve.core._trajectory import AlignMethod, Transform
from jsve.evaluation._aggregate import per_run_table
from jsve.io import _atomic as atomic
from jsve.io._trajectories import PosePair, stack_pose_pairs

STATISTICS: tuple[str, ...] = ("rmse", "mean", "median", "std", "min", "max", "sse")
"""The rows of Table I, in the seed's order (metres; sse in square metres)."""

STAT_LABELS = {
    "rmse": "RMSE",
    "mean": "mean",
    "median": "median",
    "std": "std",
    "min": "min",
    "max": "max",
    "sse": "SSE (m^2)",
}

PLOT_FORMATS: tuple[str, ...] = ("png", "svg")

_KDE_CHUNK = 1 << 22  # samples x points evaluated at once (32 MiB of float64)


@dataclass(frozen=True)
class ScoredRun:
    """One estimate after alignment.

    Attributes:
        group: its set ("original", "masked", ...).
        name: the PosePair's name.
        t: [T] seconds (or pose index when the pair had no stamps; see `timed`).
        timed: whether t is in seconds.
        ref: [T, 4, 4] reference poses.
        aligned: [T, 4, 4] estimated poses mapped into the reference frame (rotation R R_i, position
            s R p_i + t, as evo's align).
        errors: [T] APE of the translation part, metres.
        transform: the alignment (estimate -> reference).
    """

    group: str
    name: str
    t: np.ndarray
    timed: bool
    ref: np.ndarray
    aligned: np.ndarray
    errors: np.ndarray
    transform: Transform


@dataclass(frozen=True)
class TableOne:
    """Table I and what it was made of.

    Attributes:
        groups: the sets, in column order (the first is the baseline of `change_percent`).
        align: the alignment method.
        per_run: one row per estimate: group, name, rmse, mean, median, std, min, max, sse, count,
            coverage, n_segments, failed, failure_reason, scale (jsve.evaluation._aggregate.per_run_table's
            columns).
        summary: one row per statistic (STATISTICS): for each group its value (the mean over the group's
            runs), `<group>_std` (over runs, ddof 1; NaN for a single run), and `change_percent` of the
            second group against the first when there are two.
        runs: the aligned runs, in per_run's order.
    """

    groups: tuple[str, ...]
    align: str
    per_run: pd.DataFrame
    summary: pd.DataFrame
    runs: list[ScoredRun]


# --------------------------------------------------------------------------------------------------
# Table I


def table_one(
    groups: Mapping[str, Sequence[PosePair]],
    *,
    align: AlignMethod = "se3",
    n_first: int | None = None,
) -> TableOne:
    """Score every estimate against its reference and lay out Table I.

    Arguments:
        groups: set name -> its estimates, e.g. {"original": [...], "masked": [...]}; the order of the
            mapping is the order of the columns, the first set the baseline.
        align: "se3" (evo_ape --align), "sim3" (--align --correct_scale), "posyaw", "origin", "none".
        n_first: align on the first n_first poses only (evo's --n_to_align); None: all.

    Returns:
        TableOne. Float precision follows JAX's: enable jax_enable_x64 for float64 (evo's).
    """
    if not groups or any(len(pairs) == 0 for pairs in groups.values()):
        raise ValueError("every group needs at least one estimate")
    labelled = [(group, pair) for group, pairs in groups.items() for pair in pairs]
    errors, transforms = batched_pose_error(
        *stack_pose_pairs([pair for _, pair in labelled]), align=align, n_first=n_first
    )
    aligned = _aligned_poses([pair for _, pair in labelled], transforms)
    runs = []
    for i, ((group, pair), poses) in enumerate(zip(labelled, aligned, strict=True)):
        timed = pair.t is not None
        t = np.asarray(pair.t, np.float64) if timed else np.arange(len(pair.ref), dtype=np.float64)
        per_pose = np.linalg.norm(poses[:, :3, 3] - pair.ref[:, :3, 3], axis=1)
        transform = jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], transforms)
        runs.append(ScoredRun(group, pair.name, t, timed, pair.ref, poses, per_pose, transform))
    meta = pd.DataFrame({"group": [g for g, _ in labelled], "name": [p.name for _, p in labelled]})
    per_run = per_run_table(errors, meta)
    per_run["scale"] = np.asarray(transforms.scale, np.float64)
    return TableOne(tuple(groups), align, per_run, summary_table(per_run, tuple(groups)), runs)


def _aligned_poses(pairs: Sequence[PosePair], transforms: Transform) -> list[np.ndarray]:
    """[T_i, 4, 4] per pair: the estimated poses mapped into the reference frame by their transform."""
    rotation = np.asarray(transforms.rotation, np.float64)
    translation = np.asarray(transforms.translation, np.float64)
    scale = np.asarray(transforms.scale, np.float64)
    aligned = []
    for i, pair in enumerate(pairs):
        poses = pair.est.copy()
        # As evo's PosePath3D.align: positions s R p + t, orientations R R_i.
        poses[:, :3, :3] = rotation[i] @ pair.est[:, :3, :3]
        poses[:, :3, 3] = scale[i] * pair.est[:, :3, 3] @ rotation[i].T + translation[i]
        aligned.append(poses)
    return aligned


def summary_table(per_run: pd.DataFrame, groups: Sequence[str]) -> pd.DataFrame:
    """Table I from a per-run table: one row per statistic, one column per group (mean over its runs),
    `<group>_std` across runs (ddof 1), `<group>_runs`, and change_percent = 100 (second - first) / first
    when there are two groups."""
    missing = sorted(set(STATISTICS) - set(per_run.columns))
    if missing:
        raise ValueError(f"per_run lacks columns {missing}")
    table = pd.DataFrame({"statistic": list(STATISTICS)})
    for group in groups:
        part = per_run[per_run["group"] == group]
        if part.empty:
            raise ValueError(f"no run in group {group!r}")
        table[group] = [part[s].mean() for s in STATISTICS]
        table[f"{group}_std"] = [part[s].std(ddof=1) if len(part) > 1 else np.nan for s in STATISTICS]
        table[f"{group}_runs"] = len(part)
    if len(groups) == 2:
        first, second = table[groups[0]], table[groups[1]]
        table["change_percent"] = np.where(
            first != 0, 100.0 * (second - first) / first.where(first != 0, 1.0), np.nan
        )
    return table


def to_markdown(table: TableOne, digits: int = 4) -> str:
    """Table I as a Markdown table (metres, `digits` decimals; mean +- std over runs when a group has
    several), with the alignment and any failed runs, each with its failure_reason, in a note below."""
    groups = table.groups
    summary = table.summary
    header = ["APE (m)"]
    for g in groups:
        n_runs = int(summary[f"{g}_runs"].iloc[0])
        header.append(f"{g} ({n_runs} run{'s' if n_runs > 1 else ''})")
    if "change_percent" in summary:
        header.append("change")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" + "---:|" * (len(header) - 1)]
    for _, row in summary.iterrows():
        cells = [STAT_LABELS[row["statistic"]]]
        for g in groups:
            value, spread = row[g], row[f"{g}_std"]
            text = _number(value, digits)
            if not math.isnan(spread):
                text += f" ± {_number(spread, digits)}"
            cells.append(text)
        if "change_percent" in summary:
            change = row["change_percent"]
            cells.append("" if math.isnan(change) else f"{change:+.1f} %")
        lines.append("| " + " | ".join(cells) + " |")
    notes = [
        f"Alignment: {table.align}. Statistics of the translation part over all associated poses (evo's APE)."
    ]
    failed = table.per_run[table.per_run["failed"]]
    if len(failed):
        names = ", ".join(f"{r.group}/{r.name} ({r.failure_reason})" for r in failed.itertuples())
        notes.append(f"Failed runs: {names}.")
    return "\n".join(lines) + "\n\n" + "\n".join(notes) + "\n"


def _number(value: float, digits: int) -> str:
    return "nan" if math.isnan(value) else f"{value:.{digits}f}"


# --------------------------------------------------------------------------------------------------
# Density


def scott_bandwidth(samples: np.ndarray) -> float:
    """Scott's rule for one dimension: std (ddof 1) * n^(-1/5) (Scott 1992; scipy's gaussian_kde default)."""
    x = np.asarray(samples, np.float64).ravel()
    if x.size < 2:
        raise ValueError(f"a bandwidth needs at least 2 samples, got {x.size}")
    return float(np.std(x, ddof=1) * x.size ** (-1.0 / 5.0))


def gaussian_kde(samples: np.ndarray, points: np.ndarray, bandwidth: float | None = None) -> np.ndarray:
    """Gaussian kernel density estimate of 1-D samples, evaluated at points.

    density(p) = 1 / (n h sqrt(2 pi)) sum_i exp(-(p - x_i)^2 / (2 h^2)), evaluated in chunks so that memory
    stays bounded for long runs.

    Arguments:
        samples: [n] the data (non-finite values are dropped).
        points: [m] where to evaluate.
        bandwidth: the kernel's standard deviation h (same unit as samples); default Scott's rule.

    Returns:
        [m] density (per unit of the samples).
    """
    x = np.asarray(samples, np.float64).ravel()
    x = x[np.isfinite(x)]
    h = scott_bandwidth(x) if bandwidth is None else float(bandwidth)
    if not h > 0:
        raise ValueError(f"the bandwidth must be positive, got {h} (are all samples equal?)")
    p = np.asarray(points, np.float64)
    flat = p.ravel()
    out = np.empty(flat.size)
    step = max(1, _KDE_CHUNK // max(x.size, 1))
    norm = 1.0 / (x.size * h * math.sqrt(2.0 * math.pi))
    for start in range(0, flat.size, step):
        z = (flat[start : start + step, None] - x[None, :]) / h
        out[start : start + step] = np.exp(-0.5 * z * z).sum(axis=1) * norm
    return out.reshape(p.shape)


# --------------------------------------------------------------------------------------------------
# Plots


_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def _figure(width: float = 8.0, height: float = 4.0):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)  # no pyplot, no GUI backend: safe in scripts, threads and CI
    return fig


def _save(fig, stem: Path, formats: Sequence[str]) -> list[Path]:
    paths = []
    for fmt in formats:
        if fmt not in PLOT_FORMATS:
            raise ValueError(f"plot formats must be among {PLOT_FORMATS}, got {fmt!r}")
        path = stem.with_name(f"{stem.name}.{fmt}")
        # Without a date, the same table gives the same SVG.
        metadata = {"Date": None} if fmt == "svg" else None
        with atomic.atomic_path(path) as partial:
            fig.savefig(partial, format=fmt, dpi=150, metadata=metadata)
        paths.append(path)
    return paths


def _group_colors(table: TableOne) -> dict[str, str]:
    return {g: _COLORS[i % len(_COLORS)] for i, g in enumerate(table.groups)}


def plot_ape_over_time(
    table: TableOne, stem: str | os.PathLike, formats: Sequence[str] = PLOT_FORMATS
) -> list[Path]:
    """APE (m) of every run over time (or pose index), one colour per group, RMSE as a dashed line.

    Returns:
        The files written, `<stem>.png` / `<stem>.svg`.
    """
    colors = _group_colors(table)
    fig = _figure()
    ax = fig.add_subplot()
    labelled = set()
    for run in table.runs:
        label = run.group if run.group not in labelled else None
        labelled.add(run.group)
        ax.plot(run.t, run.errors, color=colors[run.group], lw=0.8, alpha=0.9, label=label)
    for g in table.groups:
        rmse = table.summary.loc[table.summary["statistic"] == "rmse", g].iloc[0]
        ax.axhline(rmse, color=colors[g], ls="--", lw=1.0, label=f"{g} RMSE {rmse:.3f} m")
    timed = all(r.timed for r in table.runs)
    ax.set_xlabel("time (s)" if timed else "pose index")
    ax.set_ylabel("APE (m)")
    ax.set_title(f"APE over time ({table.align} alignment)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    return _save(fig, Path(stem), formats)


def _pooled_errors(table: TableOne) -> dict[str, np.ndarray]:
    return {g: np.concatenate([r.errors for r in table.runs if r.group == g]) for g in table.groups}


def plot_error_histogram(
    table: TableOne, stem: str | os.PathLike, formats: Sequence[str] = PLOT_FORMATS, bins: int = 50
) -> list[Path]:
    """Distribution of the per-pose APE of each group (all its runs pooled), shared bins, as densities
    so that groups of different length compare."""
    errors = _pooled_errors(table)
    colors = _group_colors(table)
    edges = np.histogram_bin_edges(np.concatenate(list(errors.values())), bins=bins)
    fig = _figure()
    ax = fig.add_subplot()
    for g, e in errors.items():
        ax.hist(e, bins=edges, density=True, alpha=0.5, color=colors[g], label=f"{g} ({e.size} poses)")
    ax.set_xlabel("APE (m)")
    ax.set_ylabel("density (1/m)")
    ax.set_title("APE distribution")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return _save(fig, Path(stem), formats)


def plot_error_density(
    table: TableOne, stem: str | os.PathLike, formats: Sequence[str] = PLOT_FORMATS, n_points: int = 512
) -> list[Path]:
    """Gaussian KDE (Scott's bandwidth) of the per-pose APE of each group, its median marked."""
    errors = _pooled_errors(table)
    colors = _group_colors(table)
    everything = np.concatenate(list(errors.values()))
    fig = _figure()
    ax = fig.add_subplot()
    span = float(everything.max() - everything.min()) or 1.0
    grid = np.linspace(max(0.0, everything.min() - 0.1 * span), everything.max() + 0.1 * span, n_points)
    for g, e in errors.items():
        if e.size < 2 or np.ptp(e) == 0:
            ax.axvline(e[0], color=colors[g], label=f"{g} (constant)")
            continue
        ax.plot(grid, gaussian_kde(e, grid), color=colors[g], label=g)
        ax.axvline(np.median(e), color=colors[g], ls=":", lw=1.0)
    ax.set_xlabel("APE (m)")
    ax.set_ylabel("density (1/m)")
    ax.set_title("APE density (Gaussian KDE, Scott's bandwidth; dotted: median)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return _save(fig, Path(stem), formats)


# --------------------------------------------------------------------------------------------------
# Files


def write_kitti_poses(path: str | os.PathLike, poses: np.ndarray) -> Path:
    """Write poses [T, 4, 4] as a KITTI pose file (3 x 4 row-major per line, evo's writer, full precision),
    atomically (`<path>.partial`, then rename)."""
    from evo.core.trajectory import PosePath3D
    from evo.tools import file_interface

    path = Path(path)
    with atomic.atomic_path(path) as partial, open(partial, "w") as f:
        file_interface.write_kitti_poses_file(f, PosePath3D(poses_se3=list(np.asarray(poses, np.float64))))
    return path


def _safe_name(name: str) -> str:
    stem = Path(name).name
    for suffix in (".txt", ".csv", ".tum", ".kitti"):
        stem = stem.removesuffix(suffix)
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in stem) or "run"


def write_report(
    table: TableOne,
    out_dir: str | os.PathLike,
    *,
    formats: Sequence[str] = PLOT_FORMATS,
    plots: bool = True,
    aligned: bool = True,
) -> list[Path]:
    """Write Table I and its figures into a folder.

    Files: table1.md (Markdown), table1.csv (the summary), per_run.csv, ape_over_time / error_histogram /
    error_density in each of `formats`, and aligned/<group>-<k>-<name>.kitti (each aligned estimate as a
    KITTI pose file; k counts the group's runs from 0).

    Returns:
        The paths written.
    """
    out = atomic.make_dir(out_dir)
    written = [
        atomic.write_text(out / "table1.md", to_markdown(table)),
        atomic.write_table(table.summary, out / "table1.csv"),
        atomic.write_table(table.per_run, out / "per_run.csv"),
    ]
    if plots:
        written += plot_ape_over_time(table, out / "ape_over_time", formats)
        written += plot_error_histogram(table, out / "error_histogram", formats)
        written += plot_error_density(table, out / "error_density", formats)
    if aligned:
        counters: dict[str, int] = {}
        for run in table.runs:
            k = counters.get(run.group, 0)
            counters[run.group] = k + 1
            written.append(
                write_kitti_poses(
                    out / "aligned" / f"{run.group}-{k}-{_safe_name(run.name)}.kitti", run.aligned
                )
            )
    return written
