"""jsve.sim._vision: the vision model against the real-frame measurement and its own physics.

Per-level mean counts match the real-frame measurement (docs/data/real_response.csv) within the
tolerances of analysis/simulator_calibration.py; blur never adds keypoints, occlusion moves them, and
crowded features give a less certain pose than spread ones.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from jsve.core import s_b
from jsve.sim import _camera as sim_camera
from jsve.sim import _scene as sim_scene
from jsve.sim import _vision as sv

REPO = Path(__file__).resolve().parents[1]


# ---- vision ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reference_scene() -> sim_scene.Scene:
    t = np.arange(600) / 20.0  # 30 s: about six independent spatial patterns
    scene = sim_scene.make_scene(np.random.default_rng(0), t)
    return dataclasses.replace(scene, texture=np.ones(len(t)), streak_px=np.zeros(len(t)))


TOLERANCE = {"n_extracted": 0.35, "match_ratio": 0.08, "bins_occupied": 12.0, "s_b": 0.25}
"""Bounds every seed level meets (docs/simulator.md, section 6, gives the table): the tighter bounds
of analysis/simulator_calibration.py (15 %, 0.08, 6 bins, 0.15) hold at 108 of 120 entries; the rest
sit at blur 30-35 (the model's blur cliff is gentler: +26 % and +34 % keypoints), downsampling (bins
empty sooner in the model) and in the spatial statistics of one real scene."""
KNOWN_QUIRKS = {
    ("blur", 25.0, "s_b"),
    ("downsample", 0.1, "s_b"),
    ("blur", 40.0, "s_b"),
    ("blur", 45.0, "s_b"),
    ("downsample", 0.1, "n_extracted"),
}
"""Misses docs/simulator.md (section 6) lists: the measured S_b of 0.08 at blur 25 (the few
checkerboard cells left with FAST-20 corners fill the whole budget, a property of that one scene);
S_b at downsample 0.1, where the model keeps only the coarse structure's few bins (0.3) but ORB on the
real 10x-upscaled image also finds corners on the interpolation's blocks (0.56), and for the same reason
its keypoints there (511 against 851); S_b at blur 40-45 (0.14-0.18 against 0.44-0.48), where the
per-level fit spreads the coarse levels' few keypoints over fewer bins. At all of these level 0 is
empty in both, so no map starts and no rule reads them."""


def test_counts_match_the_real_frame_measurement(reference_scene):
    real = pd.read_csv(REPO / "docs" / "data" / "real_response.csv")
    real = real[
        (real["parameters"] == "default") & real["disturbance"].isin(["blur", "downsample", "occlusion"])
    ]
    assert len(real) == 30
    misses = []
    for _, row in real.iterrows():
        counts = sv.extract(reference_scene, sv.degradation(row["disturbance"], row["level"]))
        simulated = {
            "n_extracted": counts.n_extracted.mean(),
            "match_ratio": counts.match_prob.mean(),
            "bins_occupied": (counts.bins > 0).sum(axis=1).mean(),
            "s_b": float(np.mean(np.asarray(s_b(counts.bins, counts.n_extracted)))),
        }
        measured = {
            "n_extracted": min(row["mean_n_extracted"], 1000.0),
            "match_ratio": row["mean_inlier_ratio"],
            "bins_occupied": row["mean_bins_occupied"],
            "s_b": row["mean_s_b"],
        }
        for key, tol in TOLERANCE.items():
            limit = tol * measured[key] if key == "n_extracted" else tol
            if (
                abs(simulated[key] - measured[key]) > limit
                and (row["disturbance"], row["level"], key) not in KNOWN_QUIRKS
            ):
                misses.append(
                    (row["disturbance"], row["level"], key, round(simulated[key], 3), measured[key])
                )
    assert not misses, misses


def test_extraction_physics(reference_scene):
    base = sv.extract(reference_scene, sv.degradation("none", 0))
    assert base.n_extracted.max() <= 1000 and np.median(base.n_extracted) == 1000  # nFeatures saturates
    previous = base
    for level in range(5, 55, 5):  # common random numbers: more blur never adds keypoints to a frame
        counts = sv.extract(reference_scene, sv.degradation("blur", level))
        assert np.all(counts.bins.sum(axis=1) <= counts.n_extracted)
        assert np.all(counts.n_extracted <= previous.n_extracted + 2)  # + rounding
        # Expected map inliers fall with the blur from blur 5 on (the first blur filters the camera's
        # noise and raises the match ratio, as on the real frames: 0.69 -> 0.77). The gate alone need
        # not fall: the corners that survive are coarse, found at higher pyramid levels.
        expected = counts.n_extracted * counts.match_prob * counts.gate
        if level > 5:
            assert expected.mean() <= (previous.n_extracted * previous.match_prob * previous.gate).mean()
        previous = counts
    assert previous.n_extracted.mean() < 0.5 * base.n_extracted.mean()
    # A 450 px square hides the central bins entirely; their keypoints move to the visible ones.
    occluded = sv.extract(reference_scene, sv.degradation("occlusion", 450))
    hidden = sim_camera.bin_geometry().occluded_share(450) > 0.999
    # Only the edge's keypoints can fall in a hidden bin (a few of its border pixels lie outside).
    assert (
        hidden.sum() >= 8
        and occluded.texture_bins[:, hidden].max() < 1e-9
        and occluded.bins[:, hidden].max() <= 1
    )
    assert np.median(occluded.n_extracted) == 1000


def test_pose_information_needs_spread_features():
    # The same number of inliers gives a far less certain pose when they crowd one bin than when
    # they spread over the image (the poor-geometry term of the visual error).
    geo = sim_camera.bin_geometry()
    depth, spread = 3.0, 0.3

    def covariance(bins):
        b = np.asarray(bins, float)
        info = (
            np.einsum("b,bij->ij", b, geo.info_t) * (1 + spread**2) / depth**2
            + np.einsum("b,bij->ij", b, geo.info_m) / depth
            + np.einsum("b,bij->ij", b, geo.info_r)
        )
        return np.linalg.inv(info * (sim_camera.EUROC_CAM0.fx / 1.0) ** 2 + np.eye(6) * 1e-6)

    spread_bins = np.where(geo.share > 0, 1.0, 0.0)
    spread_bins *= 100 / spread_bins.sum()
    crowded = np.zeros(64)
    crowded[27] = 100
    # About 9x here: one central bin still spans 12 x 7 degrees of view.
    assert np.trace(covariance(crowded)[:3, :3]) > 5 * np.trace(covariance(spread_bins)[:3, :3])


# ---- pyramid levels --------------------------------------------------------------------------------


def test_level_budgets_are_orbslam3s():
    """ORBextractor's mnFeaturesPerLevel, as jsve.image computes it for the image side."""
    from jsve.image._orb import OrbSettings

    budgets = sv.level_budgets()
    assert budgets.tolist() == OrbSettings().features_per_level()
    assert budgets.sum() == 1000 and budgets[0] == 217  # 1000 (1 - 1/1.2) / (1 - 1.2^-8)
    assert sv.level_budgets(2000, 1.2, 8).tolist() == OrbSettings(n_features=2000).features_per_level()


def test_fast_sees_each_wavelength_at_its_level():
    # A blob against a ring 3 px out: the full swing up to a 6 px wavelength, half of it at 12 px.
    np.testing.assert_allclose(
        sv.fast_scale_response(np.array([2.0, 6.0, 12.0])), [1.0, 1.0, 0.5], atol=1e-12
    )
    coarse = sv.fast_scale_response(np.array([20.0, 20.0 / 1.2**3, 20.0 / 1.2**7]))
    assert coarse[0] < coarse[1] < coarse[2] == 1.0  # coarse texture is found at coarse levels
    # The pyramid's own smoothing: none at level 0, one tent (0.408 px) at level 1, growing.
    blurs = [sv.pyramid_blur(level) for level in range(8)]
    assert blurs[0] == 0.0 and blurs[1] == pytest.approx(0.408) and np.all(np.diff(blurs) > 0)


def _octaves(source: str) -> pd.DataFrame:
    table = pd.read_csv(REPO / "docs" / "data" / "simulator_octaves.csv")
    table = table[table["source"].str.startswith(source)]
    return table.groupby(["disturbance", "level"], as_index=False).mean(numeric_only=True)


LEVEL_TOLERANCE = 0.2
"""Keypoints at levels 0-4 within 20 % plus 15 (for the levels that empty) of the measured ones, and all
levels together within 15 %, at every blur level of the photographs: what the fit reaches
(docs/simulator.md, section 6). Levels 5-7 are left out: from blur 30 the model keeps up to twice the
measured 31-45 keypoints there."""
RENDERED_MISSES = {20.0}
"""The rendered frames' levels 0-1 fall more gently than the model's: level 0 191, 71, 22 keypoints at blur
15, 20, 25 against the model's 217, 185, 25 (level 1 at blur 20: 117 against 180), so at blur 20 the
model holds initialisation's 100 where the mean rendered frame does not (docs/simulator.md, section 6)."""


def _scene(profile: sim_scene.SceneProfile, frames: int = 1000) -> sim_scene.Scene:
    """The calibration's reference scene (analysis/simulator_calibration.py): texture 1, no motion blur."""
    t = np.arange(frames) / 20.0
    scene = sim_scene.make_scene(np.random.default_rng(0), t, profile=profile)
    return dataclasses.replace(scene, texture=np.ones(len(t)), streak_px=np.zeros(len(t)))


def _levels(scene: sim_scene.Scene, level: float) -> np.ndarray:
    return sv.extract(scene, sv.degradation("blur", level)).levels.mean(axis=0)


def test_keypoints_per_level_match_the_photographs():
    """ORB's keypoints per pyramid level under blur on the real V1_01 photographs, with the camera images'
    scene; level 0, which monocular initialisation needs, holds 100 exactly where the photos do."""
    real = _octaves("photos")
    scene = _scene(sim_scene.SceneProfile())
    misses = []
    for _, row in real[real["disturbance"] == "blur"].iterrows():
        levels = _levels(scene, row["level"])
        measured = row[[f"octave{i}" for i in range(8)]].to_numpy(float)
        bad = np.abs(levels - measured)[:5] > LEVEL_TOLERANCE * measured[:5] + 15.0
        if (
            bad.any()
            or abs(levels.sum() / measured.sum() - 1) > 0.15
            or (levels[0] >= 100) != (measured[0] >= 100)
        ):
            misses.append((row["level"], np.round(levels).tolist(), np.round(measured).tolist()))
    assert not misses, misses


def test_the_rendered_scene_loses_level_zero_to_less_blur():
    """On `jsve render`'s frames level 0 empties from blur 15 on, where the photographs keep it to blur 25;
    the rendered scene (RENDERED_TEXTURE_SCALE) agrees on whether level 0
    holds initialisation's 100 keypoints at every blur level but RENDERED_MISSES, and its levels 1-4 are
    within 35 % plus 15 up to blur 30 (there too)."""
    real = _octaves("rendered")
    profile = sim_scene.SceneProfile(texture_scale=sim_scene.RENDERED_TEXTURE_SCALE)
    rendered, camera = _scene(profile), _scene(sim_scene.SceneProfile())
    misses = []
    for _, row in real[real["disturbance"] == "blur"].iterrows():
        levels = _levels(rendered, row["level"])
        measured = row[[f"octave{i}" for i in range(8)]].to_numpy(float)
        if row["level"] not in RENDERED_MISSES and (levels[0] >= 100) != (measured[0] >= 100):
            misses.append(("level 0", row["level"], levels[0], measured[0]))
        near = np.abs(levels - measured)[1:5] <= 0.35 * measured[1:5] + 15.0
        if row["level"] <= 30 and row["level"] not in RENDERED_MISSES and not near.all():
            misses.append(
                ("levels 1-4", row["level"], np.round(levels).tolist(), np.round(measured).tolist())
            )
    assert not misses, misses
    assert _levels(rendered, 25.0)[0] < 100 <= _levels(camera, 25.0)[0]


def test_an_occluders_edge_takes_keypoints(reference_scene):
    """The quadtree nodes an occluder's edge crosses keep the edge's keypoints: as many as measured
    within FAST's radius of the square on the photos (docs/data/simulator_octaves.csv, edge_share), to
    0.05; they stay out of the hidden bins and are part of every level's budget."""
    geo = sim_camera.bin_geometry()
    perimeter, edge = geo.occluder_edge(200)
    assert perimeter == pytest.approx(800, rel=0.05) and edge.sum() == pytest.approx(1.0)
    assert not edge[geo.occluded_share(200) > 0.999].any()
    budgets = sv.level_budgets()
    expected = 0.5 * 800 * np.sqrt(budgets / 282560.0)  # P sqrt(B_l / A) nodes crossed, half kept
    np.testing.assert_allclose(sv.border_keypoints(800, 282560.0, budgets, 0.5), expected)
    assert not sv.border_keypoints(0.0, 282560.0, budgets, 0.5).any()
    measured = _octaves("photos").set_index(["disturbance", "level"])["edge_share"]
    for side in (100.0, 200.0, 350.0, 450.0):
        counts = sv.extract(reference_scene, sv.degradation("occlusion", side))
        share = np.mean(counts.border.sum(axis=1) / counts.n_extracted)
        assert share == pytest.approx(measured[("occlusion", side)], abs=0.05), side
        np.testing.assert_array_equal(counts.levels.sum(axis=1) - counts.n_extracted <= 1, True)


def _calibration():
    """analysis/simulator_calibration.py, imported by path (analysis/ is a folder of scripts)."""
    import importlib.util
    import sys

    path = REPO / "analysis" / "simulator_calibration.py"
    spec = importlib.util.spec_from_file_location("analysis_simulator_calibration", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_level_zero_empties_between_blur_20_and_30_on_the_photos(shared_data):
    """The measurement the first map rests on: ORB as ORB-SLAM3 extracts it keeps its full level-0 budget
    (217 of 1000) at blur 20 and almost none at blur 30 on the real V1_01 photographs, and monocular
    initialisation's windowed search matches about half of level 0 between frames 0.5 s apart."""
    calibration = _calibration()
    frames = sorted(calibration.PHOTOS.glob("*.png"))[::30]
    wanted = [("none", 0.0), ("blur", 20.0), ("blur", 30.0), ("occlusion", 350.0)]
    table = calibration.measure_octaves(frames, wanted, "photos").set_index(["disturbance", "level"])
    assert table.loc[("none", 0.0), "octave0"] > 200 and table.loc[("blur", 20.0), "octave0"] > 150
    assert table.loc[("blur", 30.0), "octave0"] < 50
    assert 0.1 < table.loc[("occlusion", 350.0), "edge_share"] < 0.35  # the edge holds keypoints
    matches = calibration.measure_init_matches((("none", 0.0),)).iloc[0]
    assert 0.35 < matches["init_share"] < 0.65 and 0.5 < matches["init_match_share"] < 1.0
