"""The simulator's visibility response beside the real-frame measurement, per disturbance level.

Simulates the reference scene (texture 1, the spatial texture process, the camera at rest) under
every disturbance level of docs/data/real_response.csv (ORB on real EuRoC V1_01 frames, measured by
analysis/real_frame_response.py) and prints, side by side, the per-level means of

    n_extracted      keypoints per frame
    match ratio      frame-to-frame matched-and-verified share of the keypoints (the measurement's
                     n_inliers / n_extracted; the logs' n_inliers are ORB-SLAM3 map inliers instead)
    bins occupied    SVE bins holding at least one keypoint
    S_b              feature homogeneity (jsve.core.s_b)

and whether each is within the stated tolerance (TOLERANCE). With --fit it re-fits the model's
parameters (jsve.sim.VisionParams) to the measurement by Nelder-Mead and prints them.

    python analysis/simulator_calibration.py                 # table (markdown with --markdown)
    python analysis/simulator_calibration.py --fit           # refit, a few minutes
    python analysis/simulator_calibration.py --octaves       # keypoints per pyramid level, real vs model
    python analysis/simulator_calibration.py --measure-octaves [--rendered DIR ...]   # remeasure them

Per pyramid level (ORB-SLAM3 keeps a budget per level, level_budgets): ORB as ORB-SLAM3 extracts it
(jsve.image.extract_orb) on every 5th of the 95 real V1_01 frames under each seed setting, and on every
20th of the first 700 frames of `jsve render`'s V1_01 and V2_01 (the images the real front-end ran on,
docs/validation.md), writes docs/data/simulator_octaves.csv; the extraction fit matches the first, and
`--fit render` fits SceneProfile.texture_scale, the rendered scenes' coarser texture, to the second.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core import SEED_DISTURBANCES, s_a, s_b
from jsve.sim import (
    RENDERED_TEXTURE_SCALE,
    Scene,
    SceneProfile,
    VisionParams,
    degradation,
    extract,
    make_scene,
    settings,
)

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "docs" / "data" / "real_response.csv"
OCTAVES = REPO / "docs" / "data" / "simulator_octaves.csv"
PHOTOS = REPO.parent / "shared" / "data" / "euroc" / "V1_01_first95" / "mav0" / "cam0" / "data"
N_FEATURES = 1000
LEVELS = [f"octave{level}" for level in range(8)]
"""Columns of the keypoints kept per pyramid level (jsve.image's Features.octave)."""
RENDERED_SETTINGS = (("none", 0.0), *(("blur", float(v)) for v in range(5, 45, 5)),
                     ("occlusion", 200.0), ("occlusion", 350.0))  # fmt: skip
"""Settings measured on the rendered frames: the validation's blur and occlusion, and the blur cliff."""

TOLERANCE = {
    "n_extracted": ("relative", 0.15),
    "match_ratio": ("absolute", 0.08),
    "bins_occupied": ("absolute", 6.0),
    "s_b": ("absolute", 0.15),
}
"""How close a simulated per-level mean must be to the measured one. n_extracted: 15 % (the measured
ORB-SLAM3-style extractor gives 1006 where ORB-SLAM3 caps at 1000, and its steep fall between blur
25 and 30 sits on a single scene's contrast); the match ratio: 0.08 (its frame-to-frame spread on the
measured frames is 0.05 to 0.08); bins occupied: 6 of 64; S_b: 0.15 (its per-frame spread is about
0.1 and a single scene's layout sets it)."""


def real_table(path: Path = REAL, octaves: Path = OCTAVES) -> pd.DataFrame:
    """Measured per-level means of the default (rescale) variants, seed grids first, with the photos'
    keypoints per pyramid level (LEVELS, NaN where not measured)."""
    real = pd.read_csv(path)
    real = real[(real["parameters"] == "default") & (real["disturbance"] != "none")].copy()
    real["match_ratio"] = real["mean_inlier_ratio"]
    real["n_extracted_cv"] = real["std_n_extracted"] / real["mean_n_extracted"].clip(lower=1.0)
    real = real.rename(
        columns={"mean_n_extracted": "n_extracted", "mean_bins_occupied": "bins_occupied", "mean_s_b": "s_b"}
    )
    columns = ["disturbance", "level", "frames", "n_extracted", "n_extracted_cv", "match_ratio",
               "bins_occupied", "s_b"]  # fmt: skip
    real = real[columns]
    if octaves.is_file():
        levels = octave_table(octaves, "photos")[["disturbance", "level", *LEVELS]]
        real = real.reset_index().merge(levels, on=["disturbance", "level"], how="left").set_index("index")
    return real


def reference_scene(n_frames: int = 400, seed: int = 0, profile: SceneProfile | None = None) -> Scene:
    """The reference scene: texture 1 (V1_01's start), the spatial process, no camera motion blur; the
    texture's scale as `profile`'s (the default: the camera images; rendered_profile: the renders)."""
    t = np.arange(n_frames) / 20.0
    scene = make_scene(np.random.default_rng(seed), t, profile=profile or SceneProfile())
    return dataclasses.replace(scene, texture=np.ones(n_frames), streak_px=np.zeros(n_frames))


# ---- keypoints per pyramid level --------------------------------------------------------------------


def measure_octaves(frames: list[Path], settings_, source: str) -> pd.DataFrame:
    """Mean keypoints per pyramid level (LEVELS) and the 10/90 % quantiles of level 0 per frame, over
    `frames` (PNG paths) under each (disturbance, level) of `settings_` ("none" the undisturbed); for an
    occlusion, `edge_share`: the keypoints' share within FAST's radius (3 px of their level) of the black
    square's edge, or on it (static in the image: jsve.sim's border keypoints)."""
    from jsve.image import disturb_image, extract_orb, read_image

    images = [read_image(p) for p in frames]
    rows = []
    for name, level in settings_:
        found = [extract_orb(im if name == "none" else disturb_image(im, name, level)) for im in images]
        counts = np.array([np.bincount(f.octave, minlength=len(LEVELS))[: len(LEVELS)] for f in found])
        edge = np.nan
        if name == "occlusion" and level > 0:
            edge = float(
                np.mean([np.mean(_edge_distance(f.xy, level) <= 3.0 * 1.2**f.octave) for f in found])
            )
        rows.append({"source": source, "disturbance": name, "level": float(level), "frames": len(images),
                     **dict(zip(LEVELS, counts.mean(axis=0), strict=True)),
                     "octave0_q10": np.quantile(counts[:, 0], 0.1),
                     "octave0_q90": np.quantile(counts[:, 0], 0.9), "edge_share": edge})  # fmt: skip
    return pd.DataFrame(rows)


def _edge_distance(xy: np.ndarray, side: float, width: int = 752, height: int = 480) -> np.ndarray:
    """px (Chebyshev) from each keypoint to the centred black square of jsve.image's occlusion, 0 inside."""
    n = int(side)
    x0, y0 = (width - n) // 2, (height - n) // 2
    dx = np.maximum(np.maximum(x0 - xy[:, 0], xy[:, 0] - (x0 + n - 1)), 0.0)
    dy = np.maximum(np.maximum(y0 - xy[:, 1], xy[:, 1] - (y0 + n - 1)), 0.0)
    return np.maximum(dx, dy)


def fit_border_share(table: pd.DataFrame, frames: int = 100) -> float:
    """VisionParams.border_share: the measured share of keypoints on an occluder's edge (`edge_share` of
    the photos, every occlusion level) over the model's with every crossed node keeping one
    (border_share 1), averaged over the levels."""
    measured = table[table["source"].str.startswith("photos") & table["edge_share"].notna()]
    params = dataclasses.replace(VisionParams(), border_share=1.0)
    scene = reference_scene(frames)
    ratios = []
    for level, share in zip(measured["level"], measured["edge_share"], strict=True):
        counts = extract(scene, degradation("occlusion", level, params), params)
        ratios.append(share / np.mean(counts.border.sum(axis=1) / np.maximum(counts.n_extracted, 1)))
    return float(np.mean(ratios))


def measure_all_octaves(rendered: list[Path]) -> pd.DataFrame:
    """The photos under the seed's settings (every 5th of 95 frames) and each rendered dataset (its
    mav0/cam0/data, every 20th frame) under RENDERED_SETTINGS."""
    seed = [(s.disturbance, s.level) for s in settings("seed")]
    tables = [measure_octaves(sorted(PHOTOS.glob("*.png"))[::5], seed, "photos V1_01")]
    for folder in rendered:
        frames = sorted((folder / "mav0" / "cam0" / "data").glob("*.png"))[:700:20]
        tables.append(measure_octaves(frames, RENDERED_SETTINGS, f"rendered {folder.name}"))
    return pd.concat(tables, ignore_index=True)


INIT_MATCHES = REPO / "docs" / "data" / "simulator_init_matches.csv"
INIT_PAIRS = tuple((k, k + 10) for k in range(70, 85))
"""Pairs of the photos (frame indices) 0.5 s apart while the camera moves (V1_01 takes off at frame 70):
a reference and a frame monocular initialisation could reconstruct from."""


def init_matches(
    reference, current, window: float = 100.0, max_distance: int = 50, ratio: float = 0.9
) -> int:
    """Matches of monocular initialisation between two frames' features (jsve.image.Features), as
    ORBmatcher::SearchForInitialization finds them: level-0 keypoints only, each reference keypoint's
    nearest level-0 descriptor (Hamming) within a +-`window` px square, if at most `max_distance` and
    below `ratio` times the second nearest; a current keypoint keeps its closest claimant. (The
    rotation-consistency check is left out: the features carry no angle.)"""
    a, b = np.flatnonzero(reference.octave == 0), np.flatnonzero(current.octave == 0)
    if len(a) == 0 or len(b) == 0:
        return 0
    xor = np.bitwise_xor(reference.descriptors[a][:, None, :], current.descriptors[b][None, :, :])
    distance = np.unpackbits(xor, axis=2).sum(axis=2).astype(float)
    offset = np.abs(reference.xy[a][:, None, :] - current.xy[b][None, :, :])
    distance[(offset > window).any(axis=2)] = np.inf
    nearest = np.sort(distance, axis=1)
    best = np.argmin(distance, axis=1)
    ok = (nearest[:, 0] <= max_distance) & (nearest[:, 0] < ratio * nearest[:, 1])
    claimed: dict[int, float] = {}
    for i in np.flatnonzero(ok):
        claimed[best[i]] = min(claimed.get(best[i], np.inf), nearest[i, 0])
    return len(claimed)


def measure_init_matches(
    settings_=(("none", 0.0), ("blur", 10.0), ("blur", 20.0), ("blur", 25.0)),
) -> pd.DataFrame:
    """Per setting, over INIT_PAIRS of the photos: mean level-0 keypoints of the reference, mean
    initialisation matches (init_matches), their share, the frame-to-frame match ratio of the same
    setting (real_response.csv), and init_match_share = the share over that ratio."""
    from jsve.image import disturb_image, extract_orb, read_image

    frames = sorted(PHOTOS.glob("*.png"))
    ratios = pd.read_csv(REAL).query("parameters == 'default'").set_index(["disturbance", "level"])
    rows = []
    for name, level in settings_:
        used = sorted({k for pair in INIT_PAIRS for k in pair})
        images = {k: read_image(frames[k]) for k in used}
        found = {
            k: extract_orb(im if name == "none" else disturb_image(im, name, level))
            for k, im in images.items()
        }
        level0 = np.mean([np.sum(found[a].octave == 0) for a, _ in INIT_PAIRS])
        matches = np.mean([init_matches(found[a], found[b]) for a, b in INIT_PAIRS])
        ratio = float(np.ravel(ratios.loc[(name, level), "mean_inlier_ratio"])[0])
        rows.append({"disturbance": name, "level": level, "pairs": len(INIT_PAIRS), "level0": level0,
                     "init_matches": matches, "init_share": matches / level0, "match_ratio": ratio,
                     "init_match_share": matches / level0 / ratio})  # fmt: skip
    return pd.DataFrame(rows)


def octave_table(path: Path = OCTAVES, source: str = "photos") -> pd.DataFrame:
    """Measured keypoints per level of the sources starting with `source`, averaged over those sources."""
    table = pd.read_csv(path)
    table = table[table["source"].str.startswith(source)]
    return table.groupby(["disturbance", "level"], as_index=False)[
        [*LEVELS, "octave0_q10", "octave0_q90"]
    ].mean()


def simulate_octaves(real: pd.DataFrame, params: VisionParams, scene: Scene) -> pd.DataFrame:
    """Simulated mean keypoints per level for every row of an octave table."""
    rows = []
    for name, level in zip(real["disturbance"], real["level"], strict=True):
        counts = extract(scene, degradation(name, level, params), params)
        rows.append({**dict(zip(LEVELS, counts.levels.mean(axis=0), strict=True)),
                     "octave0_q10": np.quantile(counts.levels[:, 0], 0.1),
                     "octave0_q90": np.quantile(counts.levels[:, 0], 0.9)})  # fmt: skip
    return pd.DataFrame(rows, index=real.index)


def octave_loss(real: pd.DataFrame, sim: pd.DataFrame, weight0: float = 10.0) -> float:
    """Squared log-ratio of (keypoints + 5) per level, level 0 weighted `weight0` times (monocular
    initialisation matches level 0 alone)."""
    weights = np.array([weight0] + [1.0] * (len(LEVELS) - 1))
    err = np.log((sim[LEVELS].to_numpy() + 5.0) / (real[LEVELS].to_numpy() + 5.0)) / 0.25
    return float(np.sum(weights * np.minimum(err**2, 25.0)))


def octaves_markdown(real: pd.DataFrame, sim: pd.DataFrame) -> str:
    """Measured and simulated keypoints per level, `real / sim` per cell."""
    lines = ["| disturbance | level | " + " | ".join(f"level {i}" for i in range(len(LEVELS))) + " |",
             "|---|---:|" + "---:|" * len(LEVELS)]  # fmt: skip
    for (_, r), (_, m) in zip(real.iterrows(), sim.iterrows(), strict=True):
        cells = " | ".join(f"{r[c]:.0f} / {m[c]:.0f}" for c in LEVELS)
        lines.append(f"| {r['disturbance']} | {r['level']:g} | {cells} |")
    return "\n".join(lines)


def simulate_levels(real: pd.DataFrame, params: VisionParams, scene: Scene) -> pd.DataFrame:
    """Simulated per-level means for every row of the real table (keypoints per pyramid level too)."""
    rows = []
    for name, level in zip(real["disturbance"], real["level"], strict=True):
        counts = extract(scene, degradation(name, level, params), params)
        ratio = counts.match_prob
        rows.append(
            {
                "n_extracted": counts.n_extracted.mean(),
                "n_extracted_cv": counts.n_extracted.std() / max(counts.n_extracted.mean(), 1.0),
                "match_ratio": float(np.mean(np.where(counts.n_extracted > 0, ratio, 0.0))),
                "bins_occupied": (counts.bins > 0).sum(axis=1).mean(),
                "s_b": float(np.mean(np.asarray(s_b(counts.bins, counts.n_extracted)))),
                **dict(zip(LEVELS, counts.levels.mean(axis=0), strict=True)),
            }
        )
    return pd.DataFrame(rows, index=real.index)


def compare(real: pd.DataFrame, sim: pd.DataFrame) -> pd.DataFrame:
    out = real[["disturbance", "level"]].copy()
    for key, (kind, tol) in TOLERANCE.items():
        target = real[key].clip(upper=N_FEATURES) if key == "n_extracted" else real[key]
        out[f"{key}_real"] = real[key]
        out[f"{key}_sim"] = sim[key]
        error = sim[key] - target
        limit = tol * np.maximum(target, 1.0) if kind == "relative" else tol
        out[f"{key}_ok"] = np.abs(error) <= limit
    return out


# ---- fitting ----------------------------------------------------------------------------------------

FIT_GROUPS = {
    # Haze and low light scale contrast without blurring: with blur, downsampling and occlusion they
    # pin both the corners' contrast distribution and the texture's wavelengths.
    "extraction": dict(
        bounds={
            "candidates": (2e3, 1e5),
            "contrast_mu": (0.0, 3.5),
            "contrast_sigma": (0.2, 1.5),
            "fine_wavelength": (1.5, 40.0),
            "coarse_wavelength": (10.0, 80.0),
            "coarse_fraction": (0.005, 0.5),
            "coarse_sigma": (0.1, 4.0),
            "fine_wavelength_sigma": (0.0, 1.0),
            "fine_wavelength_spread": (0.05, 1.2),
            "texture_sigma": (0.2, 4.0),
            "contrast_coupling": (-0.5, 1.5),
            "blank_z": (-3.0, 1.5),
            "blank_density": (1e-4, 0.3),
            "level_decay": (0.0, 3.0),
            "natural_noise": (0.5, 5.0),
            "noise_corners": (1e2, 1e5),
        },
        log=(
            "candidates",
            "fine_wavelength",
            "coarse_wavelength",
            "coarse_fraction",
            "noise_corners",
            "blank_density",
        ),
        disturbances=SEED_DISTURBANCES + ("haze", "low_light"),
        keys=("octaves", "n_extracted", "n_extracted_cv", "bins_occupied", "s_b"),
    ),
    # The per-level split: what each pyramid level finds under blur and downsampling (the photos'
    # keypoints per level), with the totals and the spatial statistics it must keep.
    "levels": dict(
        bounds={
            "level_decay": (0.0, 3.0),
            "contrast_mu": (0.0, 3.5),
            "contrast_sigma": (0.2, 1.5),
            "fine_wavelength": (1.5, 40.0),
            "fine_wavelength_spread": (0.05, 1.2),
            "coarse_wavelength": (10.0, 80.0),
            "coarse_fraction": (0.005, 0.5),
            "fine_wavelength_sigma": (0.0, 1.0),
            "contrast_coupling": (-0.5, 1.5),
        },
        log=("fine_wavelength", "coarse_wavelength", "coarse_fraction"),
        disturbances=("blur", "downsample"),
        keys=("octaves", "n_extracted", "bins_occupied", "s_b"),
    ),
    "matching": dict(
        # The camera noise and the spurious corners shape the extraction (bins, S_b, level 0) too:
        # refitted here with the matching law, the extraction kept in the loss.
        bounds={
            "match_max": (0.6, 0.95),
            "match_noise": (0.01, 10.0),
            "match_gamma": (0.5, 3.0),
            "natural_noise": (0.5, 5.0),
            "noise_corners": (1e2, 1e5),
        },
        log=("match_noise", "noise_corners"),
        disturbances=SEED_DISTURBANCES + ("noise", "haze", "low_light"),
        keys=("match_ratio", "octaves", "bins_occupied", "s_b"),
    ),
    "extra": dict(
        bounds={"motion_blur_alpha": (0.0, 0.3), "streak_match": (5.0, 200.0), "dirt_scale": (0.5, 4.0)},
        log=("streak_match",),
        disturbances=("motion_blur", "lens_dirt"),
        keys=("n_extracted", "match_ratio", "bins_occupied", "s_b"),
    ),
}

SCALE = {"n_extracted": 0.05, "n_extracted_cv": 0.1, "match_ratio": 0.03, "bins_occupied": 5.0, "s_b": 0.12}
CAP = {"n_extracted": 400.0, "n_extracted_cv": 25.0, "match_ratio": 25.0, "bins_occupied": 25.0, "s_b": 9.0}
# n_extracted_cv: the frame-to-frame spread of the keypoint count over a few seconds of one scene
# (the measured frames span 4.7 s); without it the fit buys the spatial statistics with a scene
# whose keypoint count jumps from frame to frame near the blur cliff.


def loss(real: pd.DataFrame, sim: pd.DataFrame, keys) -> float:
    total = 0.0
    if "octaves" in keys:
        measured = real[LEVELS[0]].notna().to_numpy()
        total += octave_loss(real[measured], sim[measured])
    for key in (k for k in keys if k != "octaves"):
        if key == "n_extracted":
            err = np.log((sim[key] + 5) / (real[key].clip(upper=N_FEATURES) + 5))
        else:
            err = sim[key] - real[key]
        # Each level's term is capped, so that one level the model cannot follow (S_b at blur 25) does
        # not steer the whole fit.
        total += float(np.sum(np.minimum((err / SCALE[key]) ** 2, CAP[key])))
    return total


def nelder_mead(f, x0, step, iterations=400, tol=1e-4):
    """Plain Nelder-Mead (Nelder & Mead 1965; standard coefficients 1, 2, 0.5, 0.5)."""
    n = len(x0)
    simplex = [np.asarray(x0, float)] + [np.asarray(x0, float) + step[i] * np.eye(n)[i] for i in range(n)]
    values = [f(x) for x in simplex]
    for _ in range(iterations):
        order = np.argsort(values)
        simplex = [simplex[i] for i in order]
        values = [values[i] for i in order]
        if abs(values[-1] - values[0]) <= tol * (abs(values[0]) + 1e-9):
            break
        centroid = np.mean(simplex[:-1], axis=0)
        reflected = centroid + (centroid - simplex[-1])
        fr = f(reflected)
        if fr < values[0]:
            expanded = centroid + 2 * (centroid - simplex[-1])
            fe = f(expanded)
            simplex[-1], values[-1] = (expanded, fe) if fe < fr else (reflected, fr)
        elif fr < values[-2]:
            simplex[-1], values[-1] = reflected, fr
        else:
            contracted = centroid + 0.5 * (simplex[-1] - centroid)
            fc = f(contracted)
            if fc < values[-1]:
                simplex[-1], values[-1] = contracted, fc
            else:
                simplex = [simplex[0]] + [simplex[0] + 0.5 * (x - simplex[0]) for x in simplex[1:]]
                values = [values[0]] + [f(x) for x in simplex[1:]]
    best = int(np.argmin(values))
    return simplex[best], values[best]


def fit(
    real: pd.DataFrame,
    params: VisionParams,
    scene: Scene,
    group: str,
    iterations: int,
    samples: int = 0,
    restarts: int = 2,
    seed: int = 0,
) -> VisionParams:
    """Nelder-Mead from the best of the current values and `samples` random points in the group's
    bounds, restarted `restarts` times; returns the best parameters found."""
    spec = FIT_GROUPS[group]
    part = real[real["disturbance"].isin(spec["disturbances"])]
    fields = tuple(spec["bounds"])
    lo = np.array(
        [math.log(spec["bounds"][k][0]) if k in spec["log"] else spec["bounds"][k][0] for k in fields]
    )
    hi = np.array(
        [math.log(spec["bounds"][k][1]) if k in spec["log"] else spec["bounds"][k][1] for k in fields]
    )

    def unpack(x):
        x = np.clip(x, lo, hi)
        values = {k: (math.exp(v) if k in spec["log"] else float(v)) for k, v in zip(fields, x, strict=True)}
        return dataclasses.replace(params, **values)

    def objective(x):
        penalty = float(np.sum(np.maximum(lo - x, 0) ** 2 + np.maximum(x - hi, 0) ** 2)) * 1e4
        with np.errstate(all="ignore"):
            return loss(part, simulate_levels(part, unpack(x), scene), spec["keys"]) + penalty

    started = time.perf_counter()
    x_now = np.array(
        [math.log(getattr(params, k)) if k in spec["log"] else getattr(params, k) for k in fields]
    )
    rng = np.random.default_rng(seed)
    points = [x_now] + [lo + (hi - lo) * rng.uniform(size=len(fields)) for _ in range(samples)]
    values = [objective(x) for x in points]
    x = points[int(np.argmin(values))]
    value = min(values)
    for restart in range(restarts):  # restarts shrink the simplex: a local polish of the last result
        x, value = nelder_mead(objective, x, 0.1 * (hi - lo) / (1 + restart), iterations)
    print(
        f"fit {group}: loss {values[0]:.1f} -> {value:.1f} in {time.perf_counter() - started:.0f} s",
        file=sys.stderr,
    )
    return unpack(x)


def failure_table(
    procedural: int = 3,
    runs: int = 5,
    rules=("orbslam3", "sve-option2"),
    disturbances: str = "seed",
    seed: int = 0,
    sequences=None,
    euroc_gt=None,
) -> pd.DataFrame:
    """Replay the seed's rules over a simulated study: per (disturbance, level, rule) the share of
    failed runs (jsve.evaluate's `failed`: LOST at least once, or no estimate) and the median APE RMSE
    (m, SE3-aligned, largest segment) of the runs that did not fail. One sequence at a time, so
    memory stays bounded."""
    from jsve.core import preset
    from jsve.evaluation import evaluate
    from jsve.io import buckets
    from jsve.sim import euroc_sequences, procedural_sequences, simulate_study

    specs = euroc_sequences(sequences, euroc_gt) if sequences else procedural_sequences(procedural)
    tables = []
    for spec in specs:
        logs = simulate_study([spec], disturbances=disturbances, runs=runs, seed=seed)
        groups = buckets(logs)
        tables += [evaluate(groups, preset(rule), rule_name=rule, progress=False) for rule in rules]
        del logs, groups
    table = pd.concat(tables, ignore_index=True)
    table["rmse_ok"] = table["rmse"].where(~table["failed"])
    out = table.groupby(["disturbance", "level", "rule"], sort=False).agg(
        runs=("failed", "size"),
        failed=("failed", "mean"),
        rmse_median=("rmse_ok", "median"),
        accepted=("accepted_fraction", "mean"),
    )
    return out.reset_index()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fit", nargs="*", choices=tuple(FIT_GROUPS), help="refit these parameter groups")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument(
        "--samples", type=int, default=0, help="random starting points tried before Nelder-Mead"
    )
    parser.add_argument("--frames", type=int, default=1000, help="frames of the reference scene (50 s)")
    parser.add_argument("--markdown", action="store_true", help="print the table as markdown")
    parser.add_argument(
        "--all", action="store_true", help="also the extra disturbances (not only the seed's)"
    )
    parser.add_argument(
        "--failures",
        action="store_true",
        help="instead: failure rate per level of the orbslam3 and sve-option2 rules on a "
        "simulated study (--procedural flights x --runs)",
    )
    parser.add_argument("--octaves", action="store_true", help="instead: keypoints per pyramid level")
    parser.add_argument("--measure-octaves", action="store_true",
                        help=f"measure keypoints per level on real frames into {OCTAVES.name}")  # fmt: skip
    parser.add_argument("--rendered", nargs="*", type=Path, default=[],
                        help="`jsve render` datasets measured too (their first 700 frames)")  # fmt: skip
    parser.add_argument("--fit-frames", type=int, default=300, help="frames of the fit's scene")
    parser.add_argument("--fit-render", action="store_true",
                        help="instead: fit texture_scale to the rendered frames")  # fmt: skip
    parser.add_argument("--fit-occlusion", action="store_true",
                        help="instead: fit map_lifetime_s to the real S_a under occlusion")  # fmt: skip
    parser.add_argument("--procedural", type=int, default=3)
    parser.add_argument("--sequences", help="EuRoC sequences for --failures (with --euroc-gt)")
    parser.add_argument(
        "--euroc-gt", default=str(REPO.parent / "shared" / "data" / "euroc" / "groundtruth_left_cam")
    )
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args(argv)
    if args.failures:
        sequences = args.sequences.split(",") if args.sequences else None
        table = failure_table(args.procedural, args.runs, sequences=sequences, euroc_gt=args.euroc_gt)
        wide = table.pivot_table(
            index=["disturbance", "level"], columns="rule", values=["failed", "rmse_median"], sort=False
        )
        if args.markdown:
            rules = list(dict.fromkeys(table["rule"]))
            print(
                "| disturbance | level | "
                + " | ".join(f"failed {r}" for r in rules)
                + " | "
                + " | ".join(f"RMSE {r} (m)" for r in rules)
                + " |"
            )
            print("|---|---:|" + "---:|" * (2 * len(rules)))
            for (d, lv), r in wide.iterrows():
                fails = " | ".join(f"{r[('failed', rule)]:.2f}" for rule in rules)
                rmse = " | ".join(
                    "-" if pd.isna(r[("rmse_median", rule)]) else f"{r[('rmse_median', rule)]:.3f}"
                    for rule in rules
                )
                print(f"| {d} | {lv:g} | {fails} | {rmse} |")
        else:
            with pd.option_context("display.width", 200, "display.max_rows", 200):
                print(wide.round(3).to_string())
        return 0
    if args.measure_octaves:
        table = measure_all_octaves(args.rendered)
        table.to_csv(OCTAVES, index=False, float_format="%.6g")
        print(table.round(1).to_string(index=False))
        matches = measure_init_matches()
        matches.to_csv(INIT_MATCHES, index=False, float_format="%.6g")
        print(matches.round(3).to_string(index=False))
        print(f"init_match_share: {matches['init_match_share'].mean():.3f} (mean over the settings)")
        print(f"border_share: {fit_border_share(table):.3f}")
        return 0
    if args.octaves:
        return print_octaves(args.frames, args.markdown)
    if args.fit_occlusion:
        from jsve.sim import ImuNoise, SimConfig

        best, table = fit_map_lifetime(SimConfig(imu=ImuNoise.datasheet(), scene=rendered_profile()))
        table.to_csv(OCCLUSION_FIT, index=False, float_format="%.6g")
        print(table.round(3).to_string(index=False))
        print(f"map_lifetime_s: {best:g} s")
        return 0
    if args.fit_render:
        print(
            f"texture_scale of the rendered scenes: {fit_texture_scale(VisionParams(), args.fit_frames):.2f}"
        )
        return 0
    real = real_table()
    params = VisionParams()
    if args.fit is not None:
        fit_scene = reference_scene(args.fit_frames, seed=1)
        for group in args.fit or tuple(FIT_GROUPS):
            params = fit(real, params, fit_scene, group, args.iterations, samples=args.samples)
        changed = {
            f.name: round(getattr(params, f.name), 4)
            for f in dataclasses.fields(params)
            if getattr(params, f.name) != getattr(VisionParams(), f.name)
        }
        print("fitted VisionParams changes:", changed)
    shown = real if args.all else real[real["disturbance"].isin(SEED_DISTURBANCES)]
    table = compare(shown, simulate_levels(shown, params, reference_scene(args.frames)))
    ok_cols = [c for c in table.columns if c.endswith("_ok")]
    if args.markdown:
        print(_markdown(table))
    else:
        with pd.option_context("display.width", 220, "display.max_rows", 200):
            print(table.round(3).to_string(index=False))
    limits = ", ".join(
        f"{k} {tol:g}{' relative' if kind == 'relative' else ''}" for k, (kind, tol) in TOLERANCE.items()
    )
    print(f"within tolerance: {int(table[ok_cols].to_numpy().sum())} of {table[ok_cols].size} ({limits})")
    return 0


TEXTURE_SCALES = np.arange(0.3, 1.51, 0.05)
"""The grid fit_texture_scale searches."""


def rendered_profile(texture_scale: float = RENDERED_TEXTURE_SCALE) -> SceneProfile:
    """The scene of `jsve render`'s images: its texture at texture_scale, and the renderer's 8 ms exposure."""
    return SceneProfile(texture_scale=texture_scale, exposure_s=0.008)


def fit_texture_scale(params: VisionParams, frames: int = 120, grid=TEXTURE_SCALES) -> float:
    """SceneProfile.texture_scale that best matches the rendered frames' keypoints per level
    (octave_loss over RENDERED_SETTINGS' blur levels, where the levels differ), on a grid."""
    real = octave_table(OCTAVES, "rendered")
    real = real[real["disturbance"] == "blur"].reset_index(drop=True)
    scenes = (reference_scene(frames, seed=1, profile=rendered_profile(g)) for g in grid)
    losses = [octave_loss(real, simulate_octaves(real, params, scene)) for scene in scenes]
    for g, value in zip(grid, losses, strict=True):
        print(f"texture_scale {g:.2f}: loss {value:.1f}", file=sys.stderr)
    return float(grid[int(np.argmin(losses))])


FRONTEND_RESPONSE = REPO / "docs" / "data" / "real_frontend_response.csv"
OCCLUSION_FIT = REPO / "docs" / "data" / "simulator_occlusion_fit.csv"
OCCLUSIONS = (0.0, 100.0, 200.0, 300.0, 350.0)
"""Occlusion levels of the real front-end's response (0: its undisturbed row)."""
MAP_LIFETIMES = np.arange(0.0, 2.01, 0.25)
"""s: the grid fit_map_lifetime searches."""


def occlusion_response(
    config, runs: int = 3, frames: int = 700, seed: int = 0, euroc_gt=None
) -> pd.DataFrame:
    """Mean S_a (rho 0.25) over the frames where TrackLocalMap ran (n_frustum > 0) and the share of runs
    that lost tracking (a RECENTLY_LOST or LOST after the first map), per occlusion level (OCCLUSIONS), of
    simulated V1_01 cut to its first `frames` frames: analysis/real_frontend_response.py's measures."""
    from jsve.sim import euroc_sequences, simulate_study

    gt = euroc_gt or REPO.parent / "shared" / "data" / "euroc" / "groundtruth_left_cam"
    spec = "none,occlusion=" + ",".join(f"{v:g}" for v in OCCLUSIONS[1:])
    logs = simulate_study(
        euroc_sequences(["V1_01"], gt), disturbances=spec, runs=runs, seed=seed, config=config
    )
    rows = []
    for log in logs:
        f = log.frames.iloc[:frames]
        ran = f["n_frustum"].to_numpy() > 0
        s_a_frames = np.asarray(s_a(f["n_inliers"].to_numpy(), f["n_extracted"].to_numpy(), 0.25))[ran]
        state = f["state"].to_numpy()
        after = state[np.argmax(state == 2) :] if (state == 2).any() else state[:0]
        mean = float(s_a_frames.mean()) if ran.any() else np.nan
        rows.append(
            {
                "level": float(log.meta["level"]),
                "s_a_rho025": mean,
                "lost": bool(np.isin(after, (3, 4)).any()),
            }
        )
    return pd.DataFrame(rows).groupby("level", as_index=False).mean()


def fit_map_lifetime(config, runs: int = 3, grid=MAP_LIFETIMES) -> tuple[float, pd.DataFrame]:
    """TrackingParams.map_lifetime_s whose simulated S_a under occlusion (occlusion_response) is nearest
    the real front-end's (real_frontend_response.csv, squared differences over OCCLUSIONS), and the
    table of every value tried."""
    real = pd.read_csv(FRONTEND_RESPONSE).query("source == 'real'")
    real = real[(real["disturbance"] == "occlusion") | (real["disturbance"] == "none")]
    real = real.set_index("level")["s_a_rho025"]
    tables = []
    for lifetime in grid:
        tracking = dataclasses.replace(config.tracking, map_lifetime_s=float(lifetime))
        table = occlusion_response(dataclasses.replace(config, tracking=tracking), runs)
        tables.append(table.assign(map_lifetime_s=lifetime, real_s_a=table["level"].map(real)))
    table = pd.concat(tables, ignore_index=True)
    error = (
        table.assign(sq=(table["s_a_rho025"] - table["real_s_a"]) ** 2).groupby("map_lifetime_s")["sq"].sum()
    )
    return float(error.idxmin()), table


def print_octaves(frames: int, as_markdown: bool) -> int:
    """Keypoints per level, measured against simulated: the photos under the seed's settings with the
    camera images' scene, the rendered frames with the rendered scene (RENDERED_TEXTURE_SCALE)."""
    for source, profile in (("photos", SceneProfile()), ("rendered", rendered_profile())):
        real = octave_table(OCTAVES, source)
        sim = simulate_octaves(real, VisionParams(), reference_scene(frames, profile=profile))
        print(
            f"\n{source} (texture_scale {profile.texture_scale:g}): measured / simulated keypoints per level"
        )
        if as_markdown:
            print(octaves_markdown(real, sim))
        else:
            both = (
                real[["disturbance", "level"]]
                .join(real[LEVELS].round(0))
                .join(sim[LEVELS].round(0), rsuffix="_sim")
            )
            print(both.to_string(index=False))
    return 0


def _markdown(table: pd.DataFrame) -> str:
    head = (
        "| disturbance | level | N real | N sim | match real | match sim | bins real | bins sim | "
        "S_b real | S_b sim |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    lines = [head]

    def cell(r, key, fmt):
        mark = "" if r[f"{key}_ok"] else " *"
        return f"{r[f'{key}_real']:{fmt}} | {r[f'{key}_sim']:{fmt}}{mark}"

    for _, r in table.iterrows():
        lines.append(
            f"| {r['disturbance']} | {r['level']:g} | {cell(r, 'n_extracted', '.0f')} | "
            f"{cell(r, 'match_ratio', '.2f')} | {cell(r, 'bins_occupied', '.1f')} | {cell(r, 's_b', '.2f')} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
