"""Visibility response of real EuRoC frames to every disturbance level (the seed's Figures 4 to 6, measured).

Applies each registered disturbance (jsve.image.DISTURBANCES, plus downsampling in its calibration
mode) at every level of its grid to the frames of one EuRoC sequence, in memory, measures the
per-frame counts with jsve.image.measure_frames (ORB-SLAM3-style ORB, verified frame-to-frame inliers, frustum
stand-in, SVE bins) and summarises the SVE metrics (jsve.core via jsve.image.visibility_table) per
level: mean and standard deviation over frames. Writes

    docs/data/real_response.csv              one row per (disturbance, parameters, level): the calibration
                                             target of the simulator (mean/std of counts and metrics)
    docs/data/real_response_first_frame.csv  keypoints on the first frame per blur level, three extractors
                                             (the DESIGN section 7 check)
    docs/figures/real_response_<name>.png    counts, S_a/S_b/S_c and the Eq.1/Option 1/Option 2 scores

Run from the repository root (a few minutes with 2 workers on 2 free cores):

    python analysis/real_frame_response.py --workers 2

Statistics skip the first frame of each measured pair or sequence (it has no previous frame, so no
inliers). The seed's three disturbances are measured on the whole sequence (94 frames with a
predecessor). The extra ones are measured on the frame pairs (i, i + 1), i = 0, K, 2K, ... (--pair-step
K, default 4: 24 pairs): matching stays at 20 Hz, with 2/K of the extraction work.
Levels that leave every frame unchanged (blur 0, downsample 1, noise 0, ...) reuse the undisturbed
measurement of the same frames.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core import SEED_DISTURBANCES
from jsve.image import (
    DISTURBANCES,
    Camera,
    FrameCounts,
    OrbSettings,
    disturb_image,
    extract_orb,
    format_level,
    measure_frames,
    read_image,
    read_sequence,
    scale_intrinsics,
    visibility_table,
)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = REPO.parent / "shared" / "data" / "euroc" / "V1_01_first95"
SEED = 0

SUMMARY_COLUMNS = (
    "n_extracted",
    "n_inliers",
    "n_frustum",
    "inlier_ratio",
    "bins_occupied",
    "s_a_original",
    "s_a_rho025",
    "s_a_rho050",
    "s_b",
    "s_c",
    "sve_eq1",
    "sve_option1",
    "sve_option2",
)


@dataclass(frozen=True)
class Condition:
    """One (disturbance, parameters, level) measured on frame groups (consecutive runs of frames)."""

    name: str
    level: float
    parameters: tuple[tuple[str, object], ...]
    groups: tuple[tuple[int, ...], ...]

    @property
    def label(self) -> str:
        return ",".join(f"{k}={v}" for k, v in self.parameters) or "default"


# ---- worker side -------------------------------------------------------------------------------------

_FRAMES: dict = {}


def _load(dataset: str) -> None:
    import cv2

    cv2.setNumThreads(1)
    sequence = read_sequence(dataset)
    _FRAMES.update(t_ns=sequence.t_ns, camera=sequence.camera, images=[read_image(p) for p in sequence.paths])


def _disturbed(condition: Condition, index: int) -> np.ndarray:
    return disturb_image(
        _FRAMES["images"][index],
        condition.name,
        condition.level,
        dict(condition.parameters),
        seed=(SEED, 0),  # as jsve.image.disturb_datasets seeds cam0
        frame_seed=(SEED, 0, int(_FRAMES["t_ns"][index])),
    )


def _camera_for(image: np.ndarray, camera: Camera) -> Camera:
    """The calibration of a (possibly downsampled, calibration mode) image."""
    height, width = image.shape
    if (width, height) == (camera.width, camera.height):
        return camera
    fx, fy, cx, cy = scale_intrinsics(
        (camera.fx, camera.fy, camera.cx, camera.cy), (camera.width, camera.height), (width, height)
    )
    return Camera(width, height, fx, fy, cx, cy, camera.distortion_model, camera.distortion)


def _measure(condition: Condition) -> list[tuple[np.ndarray, FrameCounts]]:
    """(frame indices, counts) per frame group of a condition."""
    out = []
    for group in condition.groups:
        images = [_disturbed(condition, i) for i in group]
        camera = _camera_for(images[0], _FRAMES["camera"])
        out.append((np.array(group), measure_frames(images, camera)))
    return out


# ---- parent side -------------------------------------------------------------------------------------


def _groups(n_frames: int, pair_step: int) -> tuple[tuple[int, ...], ...]:
    if pair_step <= 1:
        return (tuple(range(n_frames)),)
    return tuple((i, i + 1) for i in range(0, n_frames - 1, pair_step))


def _is_identity(condition: Condition) -> bool:
    frames = sorted({i for group in condition.groups for i in group})
    return all(np.array_equal(_disturbed(condition, i), _FRAMES["images"][i]) for i in frames)


def _tag(condition: Condition, step: int) -> str:
    return f"{condition.name}-{format_level(condition.level)}_{condition.label}_step{step}"


def _frame_table(results, t_ns: np.ndarray) -> pd.DataFrame:
    """Per-frame visibility rows of a condition, first frame of every group dropped."""
    tables = []
    for indices, counts in results:
        table = visibility_table(t_ns[indices], counts).iloc[1:]
        tables.append(table)
    return pd.concat(tables, ignore_index=True)


def _summary_row(condition: Condition, frames: pd.DataFrame, step: int) -> dict:
    bins = frames[[f"bin_{k}" for k in range(64)]].to_numpy()
    frames = frames.assign(
        inlier_ratio=np.where(
            frames["n_extracted"] > 0, frames["n_inliers"] / frames["n_extracted"].clip(1), 0.0
        ),
        bins_occupied=(bins > 0).sum(axis=1),
    )
    row = {
        "disturbance": condition.name,
        "parameters": condition.label,
        "level": condition.level,
        "unit": DISTURBANCES[condition.name].unit if condition.name in DISTURBANCES else "",
        "frames": len(frames),
        "pair_step": step,
    }
    for column in SUMMARY_COLUMNS:
        row[f"mean_{column}"] = float(frames[column].mean())
        row[f"std_{column}"] = float(frames[column].std(ddof=0))
    return row


def _first_frame_blur(image: np.ndarray) -> pd.DataFrame:
    settings = {
        "orbslam3": OrbSettings(),
        "opencv_fallback": OrbSettings(extractor="opencv"),
        "opencv_plain": OrbSettings(extractor="opencv", fallback=False),
    }
    rows = []
    for level in DISTURBANCES["blur"].levels:
        blurred = disturb_image(image, "blur", level)
        rows.append({"blur": level, **{k: len(extract_orb(blurred, s).xy) for k, s in settings.items()}})
    return pd.DataFrame(rows)


def _figure(name: str, summary: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(summary))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    panels = (
        (
            "counts per frame",
            (("n_extracted", "N extracted"), ("n_frustum", "N frustum"), ("n_inliers", "N inliers")),
        ),
        ("SVE metrics", (("s_a_rho025", "S_a (rho 0.25)"), ("s_b", "S_b"), ("s_c", "S_c"))),
        ("SVE scores", (("sve_eq1", "Eq.1"), ("sve_option1", "Option 1"), ("sve_option2", "Option 2"))),
    )
    for ax, (title, series) in zip(axes, panels, strict=True):
        for column, label in series:
            mean, std = summary[f"mean_{column}"].to_numpy(), summary[f"std_{column}"].to_numpy()
            ax.errorbar(x, mean, yerr=std, marker="o", ms=4, capsize=3, label=label)
        ax.set_xticks(x, [format_level(v) for v in summary["level"]])
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        if title != "counts per frame":
            ax.set_ylim(-0.05, 1.05)
    unit = summary["unit"].iloc[0]
    for ax in axes:
        ax.set_xlabel(f"{summary['disturbance'].iloc[0]} level [{unit}]")
    label = summary["parameters"].iloc[0]
    frames = f"{summary['frames'].iloc[0]} frames"
    fig.suptitle(
        f"{name}{' (' + label + ')' if label != 'default' else ''}: mean +- std over {frames}, "
        "EuRoC V1_01 (first 95)"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET, help="EuRoC dataset folder")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument(
        "--pair-step",
        type=int,
        default=4,
        help="measure the extra disturbances on frame pairs (i, i + 1) every K frames (default 4; 1: the "
        "whole sequence)",
    )
    parser.add_argument("--out-csv", type=Path, default=REPO / "docs" / "data" / "real_response.csv")
    parser.add_argument("--fig-dir", type=Path, default=REPO / "docs" / "figures")
    parser.add_argument(
        "--cache",
        type=Path,
        help="folder of per-frame tables, one per measured condition: read when present, written when "
        "measured (outside the repository, e.g. /tmp/jsve_real_response)",
    )
    parser.add_argument("--only", help="comma-separated disturbances to run (default: all)")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    _load(str(args.dataset))
    n_frames = len(_FRAMES["images"])
    conditions: list[tuple[str, Condition, int]] = []
    selected = args.only.split(",") if args.only else list(DISTURBANCES)
    for name, entry in DISTURBANCES.items():
        if name not in selected:
            continue
        variants = [()] + ([(("mode", "calibration"),)] if name == "downsample" else [])
        step = 1 if name in SEED_DISTURBANCES else args.pair_step
        for parameters in variants:
            figure = name + ("_calibration" if parameters else "")
            for level in entry.levels:
                conditions.append((figure, Condition(name, level, parameters, _groups(n_frames, step)), step))

    references = {
        step: Condition("none", 0, (), _groups(n_frames, step)) for step in {c[2] for c in conditions}
    }
    step_of = {id(c): step for _, c, step in conditions}
    step_of.update({id(r): step for step, r in references.items()})
    # Levels that leave every frame unchanged reuse the undisturbed measurement of the same frames.
    source = {id(c): c if not _is_identity(c) else references[step] for _, c, step in conditions}
    source.update({id(r): r for r in references.values()})
    unique = {id(c): c for c in source.values()}
    tables: dict[int, pd.DataFrame] = {}
    if args.cache:
        args.cache.mkdir(parents=True, exist_ok=True)
        for key, condition in unique.items():
            path = args.cache / f"{_tag(condition, step_of[key])}.csv"
            if path.is_file():
                tables[key] = pd.read_csv(path)
    jobs = [c for key, c in unique.items() if key not in tables]
    if jobs:
        from tqdm.auto import tqdm

        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            args.workers, mp_context=context, initializer=_load, initargs=(str(args.dataset),)
        ) as pool:
            futures = {pool.submit(_measure_or_reference, job): job for job in jobs}
            for future in tqdm(
                concurrent.futures.as_completed(futures), total=len(futures), desc="conditions"
            ):
                job = futures[future]
                tables[id(job)] = _frame_table(future.result(), _FRAMES["t_ns"])
                if args.cache:
                    tables[id(job)].to_csv(args.cache / f"{_tag(job, step_of[id(job)])}.csv", index=False)

    rows = [_summary_row(r, tables[id(r)], step) for step, r in references.items()]
    rows += [_summary_row(c, tables[id(source[id(c)])], step) for _, c, step in conditions]
    summary = pd.DataFrame(rows)
    for count in ("n_extracted", "n_inliers", "n_frustum"):
        reference = summary[summary["disturbance"] == "none"].set_index("pair_step")[f"mean_{count}"]
        summary[f"rel_{count}"] = summary[f"mean_{count}"] / summary["pair_step"].map(reference)
    args.out_csv.parent.mkdir(parents=True, exist_ok=True)
    summary.to_csv(args.out_csv, index=False, float_format="%.6g")
    first = _first_frame_blur(_FRAMES["images"][0])
    first.to_csv(args.out_csv.with_name(args.out_csv.stem + "_first_frame.csv"), index=False)
    for figure in dict.fromkeys(f for f, _, _ in conditions):
        name = figure.removesuffix("_calibration")
        label = "mode=calibration" if figure.endswith("_calibration") else "default"
        part = summary[(summary["disturbance"] == name) & (summary["parameters"] == label)]
        _figure(figure, part, args.fig_dir / f"real_response_{figure}.png")
    elapsed = time.perf_counter() - started
    print(f"{len(summary)} rows -> {args.out_csv}; {len(jobs)} conditions measured in {elapsed:.0f} s")
    print(first.to_string(index=False))
    return 0


def _measure_or_reference(condition: Condition):
    if condition.name == "none":
        results = []
        for group in condition.groups:
            images = [_FRAMES["images"][i] for i in group]
            results.append((np.array(group), measure_frames(images, _FRAMES["camera"])))
        return results
    return _measure(condition)


if __name__ == "__main__":
    raise SystemExit(main())
