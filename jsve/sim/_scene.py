"""Simulator, scene side: the texture process along a flight (density, contrast and wavelength of the
scene's corners over time and across the image), drawn once per sequence. Part of the stand-in
front-end (docs/simulator.md); the vision model (jsve.sim._vision) extracts keypoints from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jsve.sim._camera import EUROC_CAM0, CameraModel
from jsve.sim._imu import gauss_markov

RENDERED_TEXTURE_SCALE = 0.7
"""SceneProfile.texture_scale of `jsve render`'s images. Their texture is a mosaic of the V1_01 photographs
at 5 mm a texel, one texel a pixel at 2.3 m, seen from farther in most of the room: minified (and
mip-mapped) it is finer than the camera images' and loses its level-0 corners to less blur (level 0
falls to 58-85 keypoints at blur 20 where the photographs keep 209). Fitted to the rendered frames'
keypoints per level under blur 0-40 (docs/data/simulator_octaves.csv; `python
analysis/simulator_calibration.py --fit-render`: loss 637 at 1.0, 281 at 0.70, 286 at 0.65, 289 at 0.75)."""


@dataclass(frozen=True)
class SceneProfile:
    """The scene-texture process along a flight (sequence-level randomness).

    Attributes:
        texture_sigma: log spread of the texture density along the flight (OU process).
        texture_tau: s, its correlation time (how long a view lasts).
        sequence_sigma: log spread of a sequence's mean texture around the reference scene.
        lowtex_rate: low-texture stretches per second (a blank wall, a dark corner, the floor).
        lowtex_duration: (min, max) s of a stretch. lowtex_depth: (min, max) of -ln(texture factor).
        init_clear_s: s at the start free of low-texture stretches: EuRoC's flights start their
            first map within a few seconds, on a textured view.
        field_tau: s, correlation time of the spatial pattern over the bins.
        depth: (min, max) m, median scene depth along the flight (EuRoC rooms and hall).
        exposure_s: s, exposure time: the camera's own motion blur is f |omega| exposure px.
        texture_scale: factor on every texture wavelength: 1 for EuRoC's camera images (the vision
            model was fitted on them); `jsve render`'s images are finer (RENDERED_TEXTURE_SCALE).
    """

    texture_sigma: float = 0.35
    texture_tau: float = 4.0
    sequence_sigma: float = 0.25
    lowtex_rate: float = 1.0 / 45.0
    lowtex_duration: tuple[float, float] = (0.5, 3.0)
    lowtex_depth: tuple[float, float] = (1.0, 4.0)
    init_clear_s: float = 5.0
    field_tau: float = 5.0
    depth: tuple[float, float] = (2.0, 6.0)
    exposure_s: float = 0.003
    texture_scale: float = 1.0


@dataclass(frozen=True)
class Scene:
    """The scene along one flight, per frame (shared by all runs and disturbances of a sequence).

    Attributes:
        texture: [F] texture density factor (1 = the reference scene).
        field: [F, 64] standardised spatial pattern of texture density over the bins.
        scale_field: [F, 64] standardised spatial pattern of the coarse structure's density.
        grain_field: [F, 64] standardised spatial pattern of the fine grain's wavelength.
        pool_z: [F, 64] standard normal draws realising the candidate counts per bin (common to all
            settings, so a stronger disturbance never adds corners to a frame).
        depth: [F] m, median scene depth; streak_px: [F] the camera's own motion-blur streak, px.
        texture_scale: factor on the texture's wavelengths (SceneProfile.texture_scale).
    """

    texture: np.ndarray
    field: np.ndarray
    scale_field: np.ndarray
    grain_field: np.ndarray
    pool_z: np.ndarray
    depth: np.ndarray
    streak_px: np.ndarray
    texture_scale: float = 1.0


def _spatial_smoother() -> np.ndarray:
    """[64, 64] Gaussian smoothing over the 8 x 8 bins (length 1.5 bins), rows scaled to unit variance."""
    yy, xx = np.divmod(np.arange(64), 8)
    d2 = (yy[:, None] - yy[None]) ** 2 + (xx[:, None] - xx[None]) ** 2
    k = np.exp(-d2 / (2 * 1.5**2))
    return k / np.sqrt(np.sum(k * k, axis=1, keepdims=True))


def make_scene(
    rng: np.random.Generator,
    t: np.ndarray,
    angular_rate: np.ndarray | None = None,
    profile: SceneProfile = SceneProfile(),
    camera: CameraModel = EUROC_CAM0,
) -> Scene:
    """Draw the scene process along frame times t (s).

    Arguments:
        angular_rate: [F, 3] body rates (rad/s); the rate about the optical axis (body z, which
            EuRoC's camera nearly shares) streaks less, the others streak f |omega| exposure px.
    """
    n = len(t)
    log_tex = (
        rng.normal(0.0, profile.sequence_sigma)
        + gauss_markov(rng, t, profile.texture_sigma, profile.texture_tau, 1)[:, 0]
    )
    # Low-texture stretches: Poisson events, smooth (raised-cosine) entry and exit of 0.3 s.
    duration = t[-1] - t[0] if n > 1 else 0.0
    n_events = rng.poisson(profile.lowtex_rate * max(duration - profile.init_clear_s, 0.0))
    start = min(t[0] + profile.init_clear_s, t[-1])
    centres = rng.uniform(start, t[-1], n_events) if n_events else np.zeros(0)
    lengths = rng.uniform(*profile.lowtex_duration, n_events)
    depths = rng.uniform(*profile.lowtex_depth, n_events)
    for c, length, d in zip(centres, lengths, depths, strict=True):
        c = max(c, start + length / 2 + 0.3)  # wholly after the initialisation view
        edge = np.clip((length / 2 + 0.3 - np.abs(t - c)) / 0.3, 0.0, 1.0)
        log_tex -= d * (0.5 - 0.5 * np.cos(np.pi * edge))
    # Spatial patterns only redistribute texture over the image: each frame's pattern has mean 0 and
    # standard deviation 1 over the bins (the overall amount is `texture`).
    smoother = _spatial_smoother().T

    def pattern():
        g = gauss_markov(rng, t, 1.0, profile.field_tau, 64) @ smoother
        g = g - g.mean(axis=1, keepdims=True)
        return g / np.maximum(g.std(axis=1, keepdims=True), 1e-9)

    field, scale_field, grain_field = pattern(), pattern(), pattern()
    log_depth = np.log(rng.uniform(*profile.depth)) + gauss_markov(rng, t, 0.25, 8.0, 1)[:, 0]
    if angular_rate is None:
        streak = np.zeros(n)
    else:
        streak = camera.fx * np.linalg.norm(angular_rate[:, :2], axis=1) * profile.exposure_s
    return Scene(
        texture=np.exp(log_tex),
        field=field,
        scale_field=scale_field,
        grain_field=grain_field,
        pool_z=rng.normal(0.0, 1.0, (n, 64)),
        depth=np.exp(log_depth),
        streak_px=streak,
        texture_scale=profile.texture_scale,
    )
