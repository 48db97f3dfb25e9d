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

import math
from dataclasses import dataclass, field, replace

import numpy as np

from jsve.sim._camera import (
    DETECTABLE_AREA_PX,
    BinGeometry,
    bin_geometry,
)
from jsve.sim._scene import Scene

N_FEATURES = 1000
"""ORB-SLAM3's nFeatures in its EuRoC configurations."""

FAST_FALLBACK_THRESHOLD = 7.0
"""ORB-SLAM3's minThFAST (DN): the threshold a spurious corner on noise must clear."""

CHI2_GATE = 5.991
"""ORB-SLAM3 Optimizer::PoseOptimization: chi-square (2 dof, 95 %) gate on the reprojection error."""

MEAN_INTENSITY_DN = 100.0
"""Typical mean grey level of EuRoC frames, for the shot noise of the low-light model."""


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
