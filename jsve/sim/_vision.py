"""Simulator, vision side: scene texture, image disturbances, ORB extraction and tracking counts.

Part of the stand-in front-end (jsve.sim._simulate; docs/simulator.md). A physical model of what
ORB-SLAM3's front-end counts on a EuRoC camera (752 x 480, radial-tangential lens), in numpy:

- Corners. Each SVE bin holds candidate corners in proportion to its share of the image (through
  ORB-SLAM3's undistorted grid), the scene's texture density there and the part not occluded. A
  corner's FAST contrast, relative to the detector threshold, is lognormal; blur (Gaussian, motion,
  downsampling) attenuates the texture that makes it by the blur's modulation transfer at the
  texture's wavelength, exp(-2 pi^2 sigma^2 / wavelength^2); haze, low light and lens dirt scale it.
  A corner is a candidate while its contrast clears the threshold. Sensor noise adds spurious corners.
- Extraction, per pyramid level. ORB-SLAM3 detects and spreads keypoints level by level, keeping at most
  nFeatures (1 - 1/1.2) 1.2^-l / (1 - 1.2^-8) at level l (level_budgets: 217 of 1000 at level 0). A
  level sees the image through the pyramid's own smoothing, and FAST's radius-3 circle there finds the
  texture whose wavelength spans about 6 of the level's pixels (fast_scale_response): blur empties the
  fine levels first. Within a level the quadtree spreads the budget over the image: every bin keeps
  min(candidates, L x its image share), L set so that the level's total is its budget. An occluder's
  edge takes the nodes it crosses (border_keypoints).
- Matching. A keypoint is matched and verified from frame to frame with a probability that falls
  with the noise-to-contrast ratio and with the share of spurious corners.
- Localisation. A keypoint's position is uncertain by sigma_loc px, which grows with the blur; a
  tracked map point is an inlier of ORB-SLAM3's pose optimisation if its reprojection error passes
  the chi-square gate (5.991 at 1 px, Optimizer::PoseOptimization).

Parameters (`VisionParams`) were fitted to the real-frame measurement (docs/data/real_response.csv and
the keypoints per pyramid level of docs/data/simulator_octaves.csv, ORB on EuRoC V1_01 frames) by
analysis/simulator_calibration.py --fit; the localisation gate was set so that ORB-SLAM3's own rule
fails beyond blur 35, as the seed paper reports.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from jsve.sim._motion import gauss_markov

N_FEATURES = 1000
"""ORB-SLAM3's nFeatures in its EuRoC configurations."""

FAST_FALLBACK_THRESHOLD = 7.0
"""ORB-SLAM3's minThFAST (DN): the threshold a spurious corner on noise must clear."""

CHI2_GATE = 5.991
"""ORB-SLAM3 Optimizer::PoseOptimization: chi-square (2 dof, 95 %) gate on the reprojection error."""

GRID_COLS, GRID_ROWS = 64, 48
ORB_BORDER = 16
"""Keypoints lie at least EDGE_THRESHOLD - 3 = 16 px from the image border (ORBextractor)."""

DETECTABLE_AREA_PX = (752 - 2 * ORB_BORDER) * (480 - 2 * ORB_BORDER)
"""px^2 of a EuRoC frame where ORB-SLAM3 detects keypoints (inside ORB_BORDER)."""

MEAN_INTENSITY_DN = 100.0
"""Typical mean grey level of EuRoC frames, for the shot noise of the low-light model."""


# --------------------------------------------------------------------------------------------------
# Camera and the SVE bins


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with radial-tangential distortion (k1, k2, p1, p2); pixels."""

    width: int = 752
    height: int = 480
    fx: float = 458.654
    fy: float = 457.296
    cx: float = 367.215
    cy: float = 248.375
    distortion: tuple[float, float, float, float] = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)

    def undistort(self, xy: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Undistorted pixel coordinates of distorted ones (fixed-point inversion, as cv::undistortPoints)."""
        k1, k2, p1, p2 = self.distortion
        xd = (xy[:, 0] - self.cx) / self.fx
        yd = (xy[:, 1] - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        return np.stack([x * self.fx + self.cx, y * self.fy + self.cy], axis=1)


EUROC_CAM0 = CameraModel()
"""EuRoC cam0 (mav0/cam0/sensor.yaml): 752 x 480, the MT9M034 behind a wide lens."""


@dataclass(frozen=True)
class BinGeometry:
    """How the image maps onto the 8 x 8 SVE bins, from a dense sample of keypoint positions.

    Attributes:
        share: [64] share of the detectable image area (inside the ORB border) in each bin; the rest
            (1 - share.sum()) falls outside ORB-SLAM3's grid (counted in N, in no bin).
        pixel_bin: [S] bin of every sampled pixel (-1 outside the grid); pixel_xy: [S, 2] its
            distorted position (px), for occlusion and lens dirt.
        info_t, info_m, info_r: [64, 6, 6] per-bin means of the projection Jacobian blocks
            (A^T A, A^T B + B^T A, B^T B) over the bin's pixels, A = d(x, y)/dt Z, B = d(x, y)/d omega in
            normalised image coordinates, for the pose information matrix.
    """

    share: np.ndarray
    pixel_bin: np.ndarray
    pixel_xy: np.ndarray
    info_t: np.ndarray
    info_m: np.ndarray
    info_r: np.ndarray

    @property
    def n_pixels(self) -> int:
        return len(self.pixel_bin)

    def occluded_share(self, side_px: float, camera: CameraModel = EUROC_CAM0) -> np.ndarray:
        """[64] share of each bin's area hidden by a centred black square of side_px px (as
        jsve.image._disturb.occlusion draws it)."""
        if side_px <= 0:
            return np.zeros(64)
        n = int(side_px)
        y0, x0 = max(0, (camera.height - n) // 2), max(0, (camera.width - n) // 2)
        x, y = self.pixel_xy[:, 0], self.pixel_xy[:, 1]
        inside = (x >= x0) & (x < x0 + n) & (y >= y0) & (y < y0 + n)
        return _per_bin_fraction(self.pixel_bin, inside)

    def occluder_edge(self, side_px: float, camera: CameraModel = EUROC_CAM0) -> tuple[float, np.ndarray]:
        """(length in px of the edge of a centred black square of side_px px inside the detectable
        image, [64] share of that edge in each bin), from the sampled pixels within 2 px outside it."""
        distance = self.occluder_distance(side_px, camera)
        band = (distance > 0) & (distance <= 2.0)
        if not band.any():
            return 0.0, np.zeros(64)
        stride_area = float(DETECTABLE_AREA_PX) / self.n_pixels  # px^2 a sample stands for
        perimeter = band.sum() * stride_area / 2.0  # a band 2 px wide
        ok = band & (self.pixel_bin >= 0)
        return float(perimeter), np.bincount(self.pixel_bin[ok], minlength=64) / band.sum()

    def occluder_distance(self, side_px: float, camera: CameraModel = EUROC_CAM0) -> np.ndarray:
        """[S] px from each sampled pixel to a centred black square of side_px px (Chebyshev distance,
        0 inside it; inf without one)."""
        if side_px <= 0:
            return np.full(self.n_pixels, np.inf)
        n = int(side_px)
        y0, x0 = max(0, (camera.height - n) // 2), max(0, (camera.width - n) // 2)
        x, y = self.pixel_xy[:, 0], self.pixel_xy[:, 1]
        dx = np.maximum(np.maximum(x0 - x, x - (x0 + n - 1)), 0.0)
        dy = np.maximum(np.maximum(y0 - y, y - (y0 + n - 1)), 0.0)
        return np.maximum(dx, dy)

    def near_occluder_share(self, side_px: float, distances: np.ndarray) -> np.ndarray:
        """[D, 64] share of each bin's visible sampled pixels within each of `distances` px of a centred
        black square of side_px px (0 without one, or where a bin has no visible pixel)."""
        distance = self.occluder_distance(side_px)
        visible = (distance > 0) & (self.pixel_bin >= 0)
        count = np.maximum(np.bincount(self.pixel_bin[visible], minlength=64), 1)
        d, b = distance[visible], self.pixel_bin[visible]
        return np.stack([np.bincount(b[d <= r], minlength=64) / count for r in np.asarray(distances, float)])

    def field_share(self, values: np.ndarray, camera: CameraModel = EUROC_CAM0) -> np.ndarray:
        """[64] mean over each bin's pixels of a coarse image field values [h, w] (bilinear)."""
        h, w = values.shape
        gx = self.pixel_xy[:, 0] / camera.width * (w - 1)
        gy = self.pixel_xy[:, 1] / camera.height * (h - 1)
        x0 = np.clip(np.floor(gx).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(gy).astype(int), 0, h - 2)
        fx, fy = gx - x0, gy - y0
        v = (
            values[y0, x0] * (1 - fx) * (1 - fy)
            + values[y0, x0 + 1] * fx * (1 - fy)
            + values[y0 + 1, x0] * (1 - fx) * fy
            + values[y0 + 1, x0 + 1] * fx * fy
        )
        ok = self.pixel_bin >= 0
        total = np.bincount(self.pixel_bin[ok], weights=v[ok], minlength=64)
        count = np.bincount(self.pixel_bin[ok], minlength=64)
        return np.where(count > 0, total / np.maximum(count, 1), 0.0)


def _per_bin_fraction(pixel_bin: np.ndarray, mask: np.ndarray) -> np.ndarray:
    ok = pixel_bin >= 0
    hit = np.bincount(pixel_bin[ok & mask], minlength=64)
    count = np.bincount(pixel_bin[ok], minlength=64)
    return np.where(count > 0, hit / np.maximum(count, 1), 0.0)


def _round_half_away(v: np.ndarray) -> np.ndarray:
    return (np.sign(v) * np.floor(np.abs(v) + 0.5)).astype(np.int64)


@functools.lru_cache(maxsize=4)
def bin_geometry(camera: CameraModel = EUROC_CAM0, stride: int = 2) -> BinGeometry:
    """The SVE bin geometry of a camera, as ORB-SLAM3 bins keypoints (Frame::ComputeImageBounds and
    PosInGrid on undistorted keypoints; bin x = col // 8, bin y = row // 6)."""
    w, h = camera.width, camera.height
    corners = camera.undistort(np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]))
    min_x, max_x = min(corners[0, 0], corners[2, 0]), max(corners[1, 0], corners[3, 0])
    min_y, max_y = min(corners[0, 1], corners[1, 1]), max(corners[2, 1], corners[3, 1])
    ys, xs = np.mgrid[ORB_BORDER : h - ORB_BORDER : stride, ORB_BORDER : w - ORB_BORDER : stride]
    xy = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(float) + 0.5 * (stride - 1)
    und = camera.undistort(xy)
    col = _round_half_away((und[:, 0] - min_x) * GRID_COLS / (max_x - min_x))
    row = _round_half_away((und[:, 1] - min_y) * GRID_ROWS / (max_y - min_y))
    inside = (col >= 0) & (col < GRID_COLS) & (row >= 0) & (row < GRID_ROWS)
    pixel_bin = np.where(inside, (row // 6) * 8 + col // 8, -1)
    share = np.bincount(pixel_bin[inside], minlength=64) / len(xy)
    # Projection Jacobian of a point at normalised (x, y), depth Z, w.r.t. a camera perturbation
    # (translation t, rotation omega): d(x, y) = A t / Z + B omega (e.g. Hartley & Zisserman; Barfoot).
    x = (und[:, 0] - camera.cx) / camera.fx
    y = (und[:, 1] - camera.cy) / camera.fy
    zero, one = np.zeros_like(x), np.ones_like(x)
    a = np.stack([np.stack([one, zero, -x], -1), np.stack([zero, one, -y], -1)], -2)  # [S, 2, 3]
    b = np.stack([np.stack([-x * y, 1 + x * x, -y], -1), np.stack([-(1 + y * y), x * y, x], -1)], -2)
    blocks = {
        "t": np.einsum("sij,sik->sjk", a, a),
        "m": np.einsum("sij,sik->sjk", a, b),
        "r": np.einsum("sij,sik->sjk", b, b),
    }
    count = np.maximum(np.bincount(pixel_bin[inside], minlength=64), 1)
    means = {}
    for key, value in blocks.items():
        flat = value.reshape(len(xy), -1)[inside]
        sums = np.stack(
            [np.bincount(pixel_bin[inside], weights=flat[:, j], minlength=64) for j in range(9)], 1
        )
        means[key] = (sums / count[:, None]).reshape(64, 3, 3)

    def embed(tt, tr, rr):
        out = np.zeros((64, 6, 6))
        out[:, :3, :3], out[:, :3, 3:], out[:, 3:, :3], out[:, 3:, 3:] = tt, tr, np.swapaxes(tr, 1, 2), rr
        return out

    zeros = np.zeros((64, 3, 3))
    return BinGeometry(
        share=share,
        pixel_bin=pixel_bin,
        pixel_xy=xy,
        info_t=embed(means["t"], zeros, zeros),
        info_m=embed(zeros, means["m"], zeros),
        info_r=embed(zeros, zeros, means["r"]),
    )


# --------------------------------------------------------------------------------------------------
# Parameters


@dataclass(frozen=True)
class VisionParams:
    """Calibrated parameters of the vision model (docs/simulator.md lists each with its source).

    Corners:
        candidates: FAST candidates in the whole (undistorted-grid) image of the reference scene
            (EuRoC V1_01 at the start, texture 1), before nFeatures applies.
        contrast_mu, contrast_sigma: mean and spread of ln(corner contrast / FAST threshold).
        fine_wavelength, coarse_wavelength: px, wavelengths of the two scales of texture that make
            corners: fine grain (carpet, concrete) and coarse structure (furniture, panels, edges);
            ORB-SLAM3's 8-level pyramid finds each at the level whose FAST circle matches it.
        fine_wavelength_sigma: log spread of the fine grain's median wavelength over the image (its
            own spatial pattern): regions of very fine grain lose their corners to the slightest blur.
        fine_wavelength_spread: log spread of the wavelengths mixed within one region.
        coarse_fraction, coarse_sigma: candidates of the coarse structure relative to the fine grain,
            and the log spread of their density over the image (an independent spatial pattern).
        texture_sigma: spread (log) of the fine texture's density between image regions.
        contrast_coupling: ln-contrast offset per unit of the spatial field (textured regions are
            also more contrasted).
        blank_z, blank_density: regions where the standardised spatial field is below blank_z (a
            share Q(-blank_z) of the image: bare walls, ceiling, floor) hold only blank_density of
            the texture (a smooth step of width 0.25).
        motion_blur_alpha: isotropic blur (px) equivalent to a streak of 1 px.
        level_decay: a pyramid level 1.2^l smaller holds 1.2^(-l level_decay) of the candidates that
            level 0 would (0: every level finds the same corners; 2: in proportion to its area).
        border_share: share of the quadtree nodes an occluder's edge crosses that keep a keypoint of
            the edge (border_keypoints).
    Noise and matching:
        natural_noise: DN, the camera's own noise (MT9M034 at EuRoC's exposures).
        match_max: frame-to-frame match-and-verify probability of a real corner without noise.
        match_noise, match_gamma: the probability falls as 1 / (1 + (n / match_noise)^gamma), n the
            noise over the detected corners' mean FAST contrast (DN / DN).
        streak_match: px, motion-blur length that halves matchability (elongated corners).
        noise_corners: spurious FAST corners per frame on pure noise at the fallback threshold.
        dirt_scale: peak-to-mean ratio of lens-dirt opacity over the image (its blotches).
    Tracking (ORB-SLAM3's map, not measurable frame to frame; see docs/simulator.md):
        loc_floor: px, keypoint localisation error of a sharp corner.
        loc_per_blur: px of localisation error per px of effective blur.
        loc_noise: noise-to-contrast ratio at which the localisation error grows by sqrt 2.
    """

    candidates: float = 5678.7511
    contrast_mu: float = 1.9106
    contrast_sigma: float = 0.2817
    fine_wavelength: float = 11.397
    coarse_wavelength: float = 29.9437
    fine_wavelength_sigma: float = 0.0881
    fine_wavelength_spread: float = 0.1553
    coarse_fraction: float = 0.0391
    coarse_sigma: float = 2.7614
    texture_sigma: float = 3.0739
    contrast_coupling: float = 0.3744
    blank_z: float = 1.4049
    blank_density: float = 0.001
    motion_blur_alpha: float = 0.0791
    level_decay: float = 1.174
    border_share: float = 0.66
    natural_noise: float = 2.3587
    match_max: float = 0.7366
    match_noise: float = 8.0575
    match_gamma: float = 2.9533
    streak_match: float = 60.1796
    dirt_scale: float = 0.5003
    noise_corners: float = 3578.8051
    loc_floor: float = 0.5
    loc_per_blur: float = 0.35
    loc_noise: float = 0.3


# --------------------------------------------------------------------------------------------------
# Disturbances as physical degradations


"""The seed paper's level grids as the simulator runs them: blur 0..50 step 5 (11), downsample 1.0..0.1
(10), occlusion 0..450 step 50 (10: the seed's 50..450 plus the undisturbed 0 that each figure of the
paper starts from). 31 settings."""


@dataclass(frozen=True)
class Degradation:
    """What a disturbance at one level does to the image, in the model's terms.

    Attributes:
        blur_px: isotropic Gaussian blur, px (0: none).
        box_px: width (px) of the pixel averaging of downsampling then up-sampling (1/s; 0: none).
        streak_px: motion-blur streak length, px.
        contrast: [64] factor on every corner's contrast per bin (haze, low light, dirt).
        noise_dn: DN, extra white noise (before the blur filters it).
        visible: [64] share of each bin's area not hidden (occlusion).
        noise_scale: factor on the camera's own noise (low light darkens the signal and its noise).
        occluder_px: side (px) of the black square of an occlusion (0: none); its edge takes keypoints.
    """

    blur_px: float = 0.0
    box_px: float = 0.0
    streak_px: float = 0.0
    contrast: np.ndarray = field(default_factory=lambda: np.ones(64))
    noise_dn: float = 0.0
    visible: np.ndarray = field(default_factory=lambda: np.ones(64))
    noise_scale: float = 1.0
    occluder_px: float = 0.0


def gaussian_blur_sigma(n: float) -> float:
    """px: OpenCV's default sigma of the seed's n x n blur (jsve.image's blur_sigma, no OpenCV)."""
    if n <= 0:
        return 0.0
    k = int(n) if int(n) % 2 == 1 else int(n) + 1
    return 0.3 * ((k - 1) * 0.5 - 1.0) + 0.8


def degradation(
    name: str,
    level: float,
    params: VisionParams = VisionParams(),
    geometry: BinGeometry | None = None,
    seed: int = 0,
) -> Degradation:
    """The Degradation of jsve.image._disturb's disturbance `name` at `level` (its default parameters).

    Arguments:
        name: "none", "blur", "downsample", "occlusion", "noise", "low_light", "motion_blur", "haze",
            "lens_dirt".
        level: in the disturbance's unit (docs/disturbances.md).
        seed: pattern seed of lens dirt (fixed per dataset, as jsve.image._disturb).
    """
    geometry = geometry or bin_geometry()
    level = float(level)
    if name == "none":
        return Degradation()
    if name == "blur":
        return Degradation(blur_px=gaussian_blur_sigma(level))
    if name == "downsample":
        if not 0.0 < level <= 1.0:
            raise ValueError(f"downsample level must be in (0, 1]; got {level}")
        # INTER_AREA averages boxes of 1/s px and INTER_LINEAR interpolates back over 1/s px: the
        # modulation transfer of a box times that of a tent (texture_mtf). Averaging 1/s^2 pixels
        # also divides the camera's noise by 1/s.
        return Degradation(box_px=1.0 / level if level < 1.0 else 0.0, noise_scale=level)
    if name == "occlusion":
        return Degradation(visible=1.0 - geometry.occluded_share(level), occluder_px=level)
    if name == "noise":
        return Degradation(noise_dn=level)
    if name == "low_light":
        if not 0.0 < level <= 1.0:
            raise ValueError(f"low_light level must be in (0, 1]; got {level}")
        # jsve.image._disturb.low_light: signal x k, Poisson-Gaussian noise of variance
        # k (1 - k) I / c + (1 - k^2) (r / c)^2 added (c = 20 e-/DN, r = 2 e-).
        added = math.sqrt(level * (1 - level) * MEAN_INTENSITY_DN / 20.0 + (1 - level**2) * (2.0 / 20.0) ** 2)
        # The dimmer image: contrast and the camera's own noise x k, plus the added shot/read noise.
        return Degradation(contrast=np.full(64, level), noise_dn=added, noise_scale=level)
    if name == "motion_blur":
        return Degradation(streak_px=level)
    if name == "haze":
        t = math.exp(-level)
        # I = J t + A (1 - t): contrast and the camera's noise x t; rounding to DN adds 1/sqrt(12).
        return Degradation(contrast=np.full(64, t), noise_dn=math.sqrt(1 / 12), noise_scale=t)
    if name == "lens_dirt":
        rng = np.random.default_rng((seed, 7))
        coarse = rng.uniform(0.0, 1.0, (5, 7))
        opacity = np.clip(geometry.field_share(coarse) * params.dirt_scale * level, 0.0, 0.98)
        return Degradation(contrast=1.0 - opacity)
    raise ValueError(f"unknown disturbance {name!r} for the simulator")


# --------------------------------------------------------------------------------------------------
# Scene


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


# --------------------------------------------------------------------------------------------------
# Counts


def _erfc_fast(x: np.ndarray) -> np.ndarray:
    """erfc to 1.2e-7 (Numerical Recipes' Chebyshev fit), vectorised in numpy."""
    z = np.abs(x)
    t = 1.0 / (1.0 + 0.5 * z)
    r = t * np.exp(
        -z * z
        - 1.26551223
        + t
        * (
            1.00002368
            + t
            * (
                0.37409196
                + t
                * (
                    0.09678418
                    + t
                    * (
                        -0.18628806
                        + t
                        * (
                            0.27886807
                            + t * (-1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277)))
                        )
                    )
                )
            )
        )
    )
    return np.where(x >= 0, r, 2.0 - r)


def normal_sf(z: np.ndarray) -> np.ndarray:
    return 0.5 * _erfc_fast(np.asarray(z, float) / math.sqrt(2.0))


_GH_NODES, _GH_WEIGHTS = np.polynomial.hermite_e.hermegauss(5)
_GH_WEIGHTS = _GH_WEIGHTS / _GH_WEIGHTS.sum()
"""5-point Gauss-Hermite rule for expectations over a standard normal."""

SCALE_FACTOR = 1.2
N_LEVELS = 8
"""ORB-SLAM3's EuRoC pyramid: scaleFactor 1.2, nLevels 8 (Examples/Monocular-Inertial/EuRoC.yaml)."""

FAST_RADIUS_PX = 3.0
"""FAST-9 compares a pixel with the 16 pixels of a circle of radius 3 px (Rosten & Drummond 2006), in
the pixels of the pyramid level it runs on."""

PYRAMID_STEP_BLUR = 0.408
"""px of the finer level: standard deviation of the tent that one INTER_LINEAR resize by 1 / 1.2 applies
(ORBextractor::ComputePyramid resizes each level from the one before; a tent of half-width 1 px has
variance 1/6)."""


def level_budgets(
    n_features: int = N_FEATURES, scale_factor: float = SCALE_FACTOR, n_levels: int = N_LEVELS
) -> np.ndarray:
    """[n_levels] keypoints ORB-SLAM3 keeps at most per pyramid level.

    ORBextractor's constructor (ORBextractor.cc l.434-445): a geometric series in 1 / scale_factor
    summing to n_features, nFeatures (1 - 1/1.2) 1.2^-l / (1 - 1.2^-8) at level l, each rounded, the
    last level taking the rest. A level never lends its unused budget to another, so a level short of
    corners leaves n_extracted short. (jsve.image.OrbSettings.features_per_level is the same series for
    the image side; a test holds them equal.)
    """
    factor = 1.0 / scale_factor
    desired = n_features * (1.0 - factor) / (1.0 - factor**n_levels)
    counts = [math.floor(desired * factor**level + 0.5) for level in range(n_levels - 1)]
    return np.array([*counts, max(n_features - sum(counts), 0)], dtype=np.int64)


def pyramid_blur(level: int, scale_factor: float = SCALE_FACTOR) -> float:
    """px (level 0): the smoothing the pyramid itself has applied to level `level`, the tents of its
    `level` successive resizes added in quadrature, each PYRAMID_STEP_BLUR pixels of the finer level."""
    steps = np.arange(level)
    return float(np.sqrt(np.sum((PYRAMID_STEP_BLUR * scale_factor**steps) ** 2)))


def fast_scale_response(wavelength: np.ndarray) -> np.ndarray:
    """Share of a texture's full contrast that FAST's radius-3 circle sees, for texture of `wavelength`
    pixels of the level FAST runs on.

    The largest intensity difference between a pixel and its circle is that of a blob's centre against
    a ring 3 px out: amplitude x (1 - cos(2 pi 3 / wavelength)), the whole peak-to-peak swing (2 x the
    amplitude) from wavelength 6 px down. Coarse texture is therefore found at coarse levels: at level l
    a wavelength of lambda level-0 px spans lambda / 1.2^l px.
    """
    phase = np.minimum(
        2.0 * math.pi * FAST_RADIUS_PX / np.maximum(np.asarray(wavelength, float), 1e-9), math.pi
    )
    return 0.5 * (1.0 - np.cos(phase))


@dataclass(frozen=True)
class Counts:
    """Front-end counts of one setting along a flight.

    Attributes:
        bins: [F, 64] int keypoints per SVE bin. n_extracted: [F] int (bins plus those outside the grid).
        levels: [F, N_LEVELS] int keypoints kept per pyramid level (sum n_extracted up to rounding);
            levels[:, 0] are the ones monocular initialisation matches.
        border: [F, N_LEVELS] int keypoints per level on an occluder's edge (static in the image: never
            map inliers, never matched as the camera moves); included in levels, bins and n_extracted.
        match_prob: [F] probability that an extracted keypoint is matched and verified frame to frame.
        gate: [F] probability that a tracked map point passes the pose optimisation's chi-square gate.
        sigma_loc: [F] px (level 0), RMS keypoint localisation error of the extracted keypoints.
        texture_bins: [F, 64] keypoints per bin on the scene's texture (bins less the border), not
            rounded: the weights of per-bin tracking terms.
    """

    bins: np.ndarray
    n_extracted: np.ndarray
    levels: np.ndarray
    border: np.ndarray
    match_prob: np.ndarray
    gate: np.ndarray
    sigma_loc: np.ndarray
    texture_bins: np.ndarray


def texture_mtf(sigma: np.ndarray, wavelength: np.ndarray, box: float = 0.0) -> np.ndarray:
    """Amplitude left of texture of wavelength `wavelength` (px) after a Gaussian blur sigma (px) and
    a box average of width `box` px followed by linear interpolation over the same width (jsve.image's
    downsample-rescale): exp(-2 pi^2 sigma^2 / wavelength^2) |sinc(box / wavelength)|^3 (box: sinc,
    tent: sinc^2; sinc(x) = sin(pi x) / (pi x))."""
    wavelength = np.asarray(wavelength, float)
    out = np.exp(-2.0 * math.pi**2 * (np.asarray(sigma, float) / wavelength) ** 2)
    if box > 1.0:
        out = out * np.abs(np.sinc(box / wavelength)) ** 3
    return out


def border_keypoints(
    perimeter_px: float, visible_area_px: float, budgets: np.ndarray, share: float
) -> np.ndarray:
    """[levels] keypoints per level that ORB-SLAM3 keeps on the edge of an occluder (a black square).

    Where texture meets the black edge FAST finds corners of the edge's full contrast, and the quadtree
    (ORBextractor::DistributeOctTree) keeps the strongest keypoint of each node: every node the edge
    crosses keeps one of the edge's with probability `share`. Level l's B_l nodes tile the visible
    area, sqrt(A / B_l) px (level 0) a side, so the edge crosses P / sqrt(A / B_l) of them.

    Arguments:
        perimeter_px: visible length of the edge, px. visible_area_px: px^2 left to detect in.
        budgets: [levels] keypoints per level (level_budgets). share: VisionParams.border_share.
    """
    if perimeter_px <= 0.0 or visible_area_px <= 0.0:
        return np.zeros(len(budgets))
    crossed = perimeter_px * np.sqrt(np.asarray(budgets, float) / visible_area_px)
    return np.minimum(share * crossed, np.asarray(budgets, float))


def extract(
    scene: Scene,
    deg: Degradation,
    params: VisionParams = VisionParams(),
    geometry: BinGeometry | None = None,
    n_features: int = N_FEATURES,
) -> Counts:
    """Keypoints per bin and pyramid level after ORB-SLAM3's extraction, and the per-frame matching and
    localisation.

    Each of the 8 levels is detected and spread on its own (ORBextractor::ComputeKeyPointsOctTree): a
    level sees the degraded image through the pyramid's own smoothing (pyramid_blur), FAST finds there
    the texture whose wavelength its circle matches (fast_scale_response), and the quadtree keeps at
    most the level's budget (level_budgets). Deterministic given the scene (ORB extraction on the same
    images is deterministic): run-level randomness is drawn by the caller.
    """
    geometry = geometry or bin_geometry()
    budgets = level_budgets(n_features)
    # Effective isotropic blur (px): the disturbance, the camera's own streak, a disturbance streak.
    streak = np.sqrt(scene.streak_px**2 + deg.streak_px**2)
    blur = np.sqrt(deg.blur_px**2 + (params.motion_blur_alpha * streak) ** 2)[:, None]  # [F, 1]
    # Gaussian-equivalent width of the box-and-tent of downsampling (std 0.29 w and 0.41 w), for the
    # noise it averages and the localisation it coarsens.
    blur_eq = np.sqrt(blur**2 + 0.25 * max(deg.box_px**2 - 1.0, 0.0))
    # Two scales of texture per bin: fine grain (dense, short wavelength; its spatial density follows
    # `field`) and coarse structure (sparse, long wavelength; density follows `scale_field`).
    blank = params.blank_density + (1.0 - params.blank_density) / (
        1.0 + np.exp(-(scene.field - params.blank_z) / 0.25)
    )
    # Spatial patterns redistribute texture over the image; the amount per frame is scene.texture.
    fine = np.exp(params.texture_sigma * scene.field) * blank
    fine /= np.maximum(np.sum(fine * geometry.share, axis=1, keepdims=True), 1e-12)
    coarse = np.exp(params.coarse_sigma * scene.scale_field)
    coarse *= params.coarse_fraction / np.maximum(
        np.sum(coarse * geometry.share, axis=1, keepdims=True), 1e-12
    )
    mu = params.contrast_mu + params.contrast_coupling * scene.field
    share = geometry.share / max(geometry.share.sum(), 1e-12)
    base = params.candidates * scene.texture[:, None] * share * deg.visible
    # The fine grain of a region mixes wavelengths (log-normal, spread fine_wavelength_spread about
    # the region's median): Gauss-Hermite quadrature over it. A rendered scene's wavelengths are
    # scene.texture_scale times those of the camera images the parameters were fitted on.
    magnify = scene.texture_scale
    fine_wavelength = (
        params.fine_wavelength * magnify * np.exp(params.fine_wavelength_sigma * scene.grain_field)
    )
    coarse_wavelength = params.coarse_wavelength * magnify
    upper = _upper_tail(mu, params.contrast_sigma)
    upper_c = _upper_tail(params.contrast_mu, params.contrast_sigma)
    inside = max(geometry.share.sum(), 1e-12)
    border = _occluder_border(deg, geometry, budgets, params)  # [levels], [64]
    F = len(scene.texture)
    levels = np.zeros((F, len(budgets)))
    bins = np.zeros((F, 64))
    match_sum = np.zeros(F)
    gate_sum = np.zeros(F)
    loc2_sum = np.zeros(F)
    for level, budget in enumerate(budgets):
        scale = SCALE_FACTOR**level
        blur_l = np.sqrt(blur**2 + pyramid_blur(level) ** 2)
        lam_f = np.zeros_like(base)
        contrast_f = np.zeros_like(base)  # candidates x their mean contrast, summed over the quadrature
        for node, w in zip(_GH_NODES, _GH_WEIGHTS, strict=True):
            wl = fine_wavelength * np.exp(params.fine_wavelength_spread * node)
            seen = texture_mtf(blur_l, wl, deg.box_px) * fast_scale_response(wl / scale)
            p_detect, mean_contrast = _detected(
                mu, params.contrast_sigma, np.maximum(seen * deg.contrast, 1e-300), upper
            )
            lam_f += w * base * fine * p_detect
            contrast_f += w * base * fine * p_detect * mean_contrast
        seen_c = texture_mtf(blur_l, coarse_wavelength, deg.box_px) * fast_scale_response(
            coarse_wavelength / scale
        )
        p_detect, mean_contrast = _detected(
            params.contrast_mu, params.contrast_sigma, np.maximum(seen_c * deg.contrast, 1e-300), upper_c
        )
        lam_c = base * coarse * p_detect
        # The same physical corners are found again at every level that resolves them; a coarser level
        # holds fewer (its image is smaller): level_decay per octave of 1.2.
        thin = scale**-params.level_decay
        lam_real = (lam_f + lam_c) * thin
        contrast_dn = FAST_FALLBACK_THRESHOLD * np.maximum(
            (contrast_f + lam_c * mean_contrast) / np.maximum(lam_f + lam_c, 1e-300), 1.0
        )
        # Spurious corners on noise: FAST-7 fires when the noise across its circle exceeds 7 DN; the
        # pyramid's smoothing averages the noise down, and a level of 1 / scale^2 the pixels holds
        # that many fewer.
        noise = _effective_noise(deg, blur_l[:, 0], params)  # [F] DN left at this level
        p_noise = np.exp(-((FAST_FALLBACK_THRESHOLD / (math.sqrt(2.0) * np.maximum(noise, 1e-6))) ** 2))
        lam_noise = params.noise_corners * p_noise[:, None] * share * deg.visible / scale**2
        lam = lam_real + lam_noise
        pool = np.maximum(lam + np.sqrt(lam) * scene.pool_z, 0.0)
        # The quadtree spreads the level's budget over the image; nodes on an occluder's edge keep
        # the edge's corners, the rest the texture's. Keypoints beyond ORB-SLAM3's grid (undistorted
        # corners past its bounds) count in N, in no bin.
        kept = _quadtree_keep(pool, share, (budget - border[0][level]) * inside)
        bins += kept + border[0][level] * border[1]
        levels[:, level] = kept.sum(axis=1) / inside + border[0][level]
        # Matching: noise over the corners' contrast; spurious corners and the border never match
        # from frame to frame as the camera moves (the border's keypoints are counted below).
        real_share = np.where(lam > 0, lam_real / np.maximum(lam, 1e-300), 1.0)
        rel_noise = noise[:, None] / contrast_dn
        match_b = (
            params.match_max
            * real_share
            / (1.0 + np.minimum(rel_noise / params.match_noise, 1e6) ** params.match_gamma)
        )
        # Localisation in the level's pixels, in which ORB-SLAM3's gate applies (its sigma is the
        # level's scale): the blur shrinks by the scale, the localisation floor does not.
        loc = np.hypot(params.loc_floor, params.loc_per_blur * blur_eq / scale) * np.hypot(
            1.0, np.minimum(rel_noise, 1e6) / params.loc_noise
        )
        match_sum += np.sum(kept * match_b, axis=1)
        gate_sum += np.sum(kept * inlier_gate(loc), axis=1)
        loc2_sum += np.sum(kept * (loc * scale) ** 2, axis=1)
    on_edge = border[1] * border[0].sum()  # [64] the border's keypoints per bin
    bins_int = _round_preserving_total(bins)
    n_extracted = np.minimum(np.floor(levels.sum(axis=1) + 0.5).astype(np.int64), n_features)
    kept_texture = np.maximum(bins.sum(axis=1) - on_edge.sum(), 1e-12)
    streak_match = 1.0 / (1.0 + (streak / params.streak_match) ** 2)
    return Counts(
        bins=bins_int,
        n_extracted=n_extracted,
        levels=np.round(levels).astype(np.int64),
        border=np.broadcast_to(np.round(border[0]).astype(np.int64), levels.shape),
        # Over the texture's keypoints: the border's never match a moving scene (the caller counts
        # them out of the inliers).
        match_prob=match_sum / kept_texture * streak_match,
        gate=gate_sum / kept_texture,
        sigma_loc=np.sqrt(loc2_sum / kept_texture),
        texture_bins=np.maximum(bins - on_edge, 0.0),
    )


def _occluder_border(
    deg: Degradation, geometry: BinGeometry, budgets: np.ndarray, params: VisionParams
) -> tuple[np.ndarray, np.ndarray]:
    """(border keypoints per level [levels], the bins' shares of the edge [64]) of the degradation's
    occluder; zeros without one."""
    if deg.occluder_px <= 0:
        return np.zeros(len(budgets)), np.zeros(64)
    perimeter, edge = geometry.occluder_edge(deg.occluder_px)
    visible_area = DETECTABLE_AREA_PX * float(np.sum(geometry.share * deg.visible) / geometry.share.sum())
    return border_keypoints(perimeter, visible_area, budgets, params.border_share), edge


MAX_CONTRAST = 255.0 / FAST_FALLBACK_THRESHOLD
"""An 8-bit corner cannot differ from its surround by more than 255 DN: 36 times the FAST-7 threshold."""


def _upper_tail(mu, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Terms of `_detected` that do not depend on the gain: the mass below MAX_CONTRAST and the two
    tail probabilities at it."""
    z_max = (math.log(MAX_CONTRAST) - mu) / sigma
    q_max, q_max_shift = normal_sf(z_max), normal_sf(z_max - sigma)
    return np.maximum(1.0 - q_max, 1e-300), q_max, q_max_shift


def _detected(mu, sigma: float, gain, upper=None) -> tuple[np.ndarray, np.ndarray]:
    """For corners whose contrast over the FAST-7 threshold is log-normal (ln x ~ N(mu, sigma^2)),
    truncated at MAX_CONTRAST, seen through a gain: the probability that x gain clears 1, and the
    mean x gain of those that do (the truncated log-normal's mean over [1 / gain, MAX_CONTRAST]).
    `upper` is `_upper_tail(mu, sigma)` when the caller reuses it over several gains."""
    norm, q_max, q_max_shift = upper if upper is not None else _upper_tail(mu, sigma)
    log_gain = np.log(gain)
    z = np.minimum(-(mu + log_gain), math.log(MAX_CONTRAST) - mu) / sigma
    p = np.maximum(normal_sf(z) - q_max, 0.0) / norm
    tail = np.maximum(normal_sf(z - sigma) - q_max_shift, 0.0) / norm
    mean = np.exp(mu + log_gain + 0.5 * sigma * sigma) * tail / np.maximum(p, 1e-300)
    return p, np.where(p > 1e-300, mean, 1.0)


def _effective_noise(deg: Degradation, blur: np.ndarray, params: VisionParams) -> np.ndarray:
    """DN of white noise left after the blur filters it (a Gaussian of sigma s keeps 1 / (2 s sqrt(pi)))."""
    raw = np.sqrt((params.natural_noise * deg.noise_scale) ** 2 + deg.noise_dn**2)
    keep = np.where(blur > 0.5, 1.0 / (2.0 * np.maximum(blur, 0.5) * math.sqrt(math.pi)), 1.0)
    return raw * np.minimum(keep, 1.0)


def _quadtree_keep(pool: np.ndarray, share: np.ndarray, budget: np.ndarray) -> np.ndarray:
    """ORB-SLAM3's spread of nFeatures over the image: each bin keeps min(pool, L share), with L
    such that the total is the budget (water filling; everything when the pool is smaller)."""
    total = pool.sum(axis=1)
    ratio = pool / np.maximum(share, 1e-12)  # the L at which a bin saturates
    order = np.argsort(ratio, axis=1)
    r_sorted = np.take_along_axis(ratio, order, axis=1)
    p_sorted = np.take_along_axis(pool, order, axis=1)
    s_sorted = np.take_along_axis(np.broadcast_to(share, pool.shape), order, axis=1)
    # With L between r_sorted[j-1] and r_sorted[j]: kept = sum_{i<j} pool_i + L sum_{i>=j} share_i.
    cum_pool = np.concatenate([np.zeros((len(pool), 1)), np.cumsum(p_sorted, axis=1)], axis=1)[:, :-1]
    rest_share = np.cumsum(s_sorted[:, ::-1], axis=1)[:, ::-1]
    budget = np.broadcast_to(np.asarray(budget, float), total.shape)
    level = (budget[:, None] - cum_pool) / np.maximum(rest_share, 1e-12)
    ok = (level <= r_sorted) & (level >= np.concatenate([np.zeros((len(pool), 1)), r_sorted[:, :-1]], 1))
    j = np.argmax(ok, axis=1)
    L = np.take_along_axis(level, j[:, None], axis=1)
    kept = np.minimum(pool, L * share)
    return np.where((total > budget)[:, None], kept, pool)


def inlier_gate(sigma_loc: np.ndarray) -> np.ndarray:
    """Probability that a tracked map point passes ORB-SLAM3's chi-square gate (5.991 at the
    keypoint's level; sigma_loc in that level's pixels).

    The reprojection error compares the current keypoint with a map point triangulated from earlier
    keyframes, so both localisation errors add: e ~ N(0, 2 sigma_loc^2) per axis, and
    P(|e|^2 < g) = 1 - exp(-g / (4 sigma_loc^2))."""
    return 1.0 - np.exp(-CHI2_GATE / (4.0 * sigma_loc**2))


def _round_preserving_total(x: np.ndarray) -> np.ndarray:
    """Integer counts per row with each row's total rounded and distributed by largest remainders."""
    base = np.floor(x)
    remainder = x - base
    target = np.floor(x.sum(axis=1) + 0.5)
    extra = (target - base.sum(axis=1)).astype(np.int64)
    order = np.argsort(-remainder, axis=1)
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(x.shape[1])[None].repeat(len(x), 0), axis=1)
    return (base + (rank < extra[:, None])).astype(np.int64)


def replace_params(params: VisionParams, **changes) -> VisionParams:
    return replace(params, **changes)
