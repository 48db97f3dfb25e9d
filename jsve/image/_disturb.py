"""Image disturbances: pure functions on one grey image, and their registry (an I/O edge of jsve).

Every disturbance is a pure function on one 8-bit grey image (H x W numpy array) and one level,
registered in `DISTURBANCES` as name -> Disturbance(function, levels, unit, doc); the level grids
are jsve.core._levels.LEVELS, which the simulator shares. The seed paper's
three (Rugg-Gunn & Aitken 2022, section 3) keep its exact level grids: Gaussian blur, downsampling and
a centred black occlusion. Five more cover what SLAM users meet in the field: sensor noise, low
light, motion blur, haze and lens dirt. See docs/disturbances.md.

Randomness is deterministic. A function with a `frame_seed` argument draws new noise for every frame
(the dataset writer passes `(seed, camera index, t_ns)`); a function with a `seed` argument draws one
fixed pattern per dataset and camera (the writer passes `(seed, camera index)`), so lens dirt sits in
the same place on every frame.

jsve.image._datasets applies them to EuRoC-format datasets (`disturb_datasets`, resumable, with
manifests); its public names can also be imported from here, as before it had a home of its own.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import cv2
import numpy as np

from jsve.core._levels import LEVELS

# --------------------------------------------------------------------------------------------------
# Checks shared by the image functions
# --------------------------------------------------------------------------------------------------


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(
            f"image must be 8-bit grey (H x W uint8); got shape {image.shape}, dtype {image.dtype}"
        )
    return image


def _to_uint8(values: np.ndarray) -> np.ndarray:
    """Round to the nearest DN and saturate to [0, 255], as a camera's ADC does."""
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------------
# The seed paper's three disturbances
# --------------------------------------------------------------------------------------------------


def blur_kernel_size(n: int) -> int:
    """OpenCV kernel size for the seed's "n x n" Gaussian blur: n for odd n, n + 1 for even n, 0 = none.

    cv2.GaussianBlur needs an odd size, so the even levels 10, 20, ... 50 become 11, 21, ... 51.
    """
    if int(n) != n or n < 0:
        raise ValueError(f"blur level n must be a non-negative integer; got {n!r}")
    n = int(n)
    if n == 0:
        return 0
    return n if n % 2 == 1 else n + 1


def blur_sigma(n: int) -> float:
    """Standard deviation (px) of the seed's blur at level n: OpenCV's default for the kernel size.

    cv2.getGaussianKernel with sigma <= 0 uses sigma = 0.3 ((ksize - 1) / 2 - 1) + 0.8; for ksize <= 7 it
    uses fixed binomial-like tables instead (ksize 5: [1, 4, 6, 4, 1] / 16, close to sigma 1.1).
    Returns 0 for n = 0 (no blur).
    """
    ksize = blur_kernel_size(n)
    return 0.0 if ksize == 0 else 0.3 * ((ksize - 1) * 0.5 - 1.0) + 0.8


def gaussian_blur(image: np.ndarray, n: int) -> np.ndarray:
    """Gaussian blur with an n x n kernel (seed: n in 0, 5, ..., 50).

    cv2.GaussianBlur(image, (k, k), 0) with k = blur_kernel_size(n) and OpenCV's default sigma for k
    (see blur_sigma); border BORDER_REFLECT_101. n = 0 returns an unchanged copy.
    """
    image = _check_image(image)
    ksize = blur_kernel_size(n)
    if ksize == 0:
        return image.copy()
    return cv2.GaussianBlur(image, (ksize, ksize), 0)


def downsampled_size(width: int, height: int, s: float) -> tuple[int, int]:
    """(round(width s), round(height s)), at least 1 x 1: the size of the seed's downsampled image."""
    if not 0.0 < s <= 1.0:
        raise ValueError(f"downsample factor s must be in (0, 1]; got {s!r}")
    return max(1, math.floor(width * s + 0.5)), max(1, math.floor(height * s + 0.5))


DOWNSAMPLE_MODES = ("rescale", "calibration")


def downsample(image: np.ndarray, s: float, *, mode: str = "rescale") -> np.ndarray:
    """Downsampling by a factor s (seed: s in 1.0, 0.9, ..., 0.1).

    The image is resized to downsampled_size(W, H, s) with INTER_AREA (pixel averaging, no aliasing).
    mode "rescale" scales it back to W x H with INTER_LINEAR, so the camera calibration is unchanged
    and only detail is lost; mode "calibration" returns the small image, and the dataset writer scales
    the intrinsics in sensor.yaml to match (scale_intrinsics). s = 1 returns an unchanged copy.
    """
    image = _check_image(image)
    if mode not in DOWNSAMPLE_MODES:
        raise ValueError(f"downsample mode must be one of {DOWNSAMPLE_MODES}; got {mode!r}")
    height, width = image.shape
    size = downsampled_size(width, height, s)
    if size == (width, height):
        return image.copy()
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if mode == "calibration":
        return small
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)


def scale_intrinsics(
    intrinsics: Sequence[float], source_size: tuple[int, int], target_size: tuple[int, int]
) -> tuple[float, float, float, float]:
    """Pinhole intrinsics (fu, fv, cu, cv) of an image resized from source_size to target_size (W, H).

    cv2.resize maps pixel centres as x' = (x + 0.5) W'/W - 0.5, so the focal lengths scale by W'/W
    (H'/H) and the principal point by the same map. Distortion coefficients act on normalised
    coordinates and do not change. The actual size ratio is used, not s, because sizes are rounded.
    """
    fu, fv, cu, cv = (float(v) for v in intrinsics)
    sx = target_size[0] / source_size[0]
    sy = target_size[1] / source_size[1]
    return fu * sx, fv * sy, (cu + 0.5) * sx - 0.5, (cv + 0.5) * sy - 0.5


def occlusion(image: np.ndarray, n: int) -> np.ndarray:
    """A black n x n square in the centre of the image (seed: n in 50, 100, ..., 450).

    The square's top-left corner is ((W - n) // 2, (H - n) // 2): exactly centred when W - n and H - n
    are even (all seed levels on 752 x 480), otherwise half a pixel up and left. A square larger than
    the image is clipped to it.
    """
    image = _check_image(image)
    if int(n) != n or n < 0:
        raise ValueError(f"occlusion level n must be a non-negative integer; got {n!r}")
    n = int(n)
    out = image.copy()
    height, width = image.shape
    y0, x0 = max(0, (height - n) // 2), max(0, (width - n) // 2)
    out[y0 : y0 + n, x0 : x0 + n] = 0
    return out


# --------------------------------------------------------------------------------------------------
# Further disturbances
# --------------------------------------------------------------------------------------------------


def sensor_noise(image: np.ndarray, sigma: float, *, frame_seed: int | Sequence[int] = 0) -> np.ndarray:
    """Additive white Gaussian sensor noise of standard deviation sigma (DN), new on every frame.

    out = quantise(I + N(0, sigma^2)), rounded to the nearest DN and saturated to [0, 255].
    sigma = 0 returns an unchanged copy.
    """
    image = _check_image(image)
    if sigma < 0:
        raise ValueError(f"noise sigma must be >= 0 DN; got {sigma!r}")
    if sigma == 0:
        return image.copy()
    rng = np.random.default_rng(frame_seed)
    return _to_uint8(image + rng.normal(0.0, sigma, image.shape))


ELECTRONS_PER_DN = 20.0
"""Assumed conversion gain of the 8-bit output (electrons per DN) for the low-light noise model.
An order of magnitude for a small global-shutter pixel, not a calibration of EuRoC's MT9M034."""

READ_NOISE_ELECTRONS = 2.0
"""Assumed read noise (electrons rms) for the low-light noise model."""


def low_light(
    image: np.ndarray,
    k: float,
    *,
    frame_seed: int | Sequence[int] = 0,
    auto_gain: bool = False,
    gamma: float = 1.0,
    electrons_per_dn: float = ELECTRONS_PER_DN,
    read_noise_e: float = READ_NOISE_ELECTRONS,
) -> np.ndarray:
    """Less light on the sensor: the scene's irradiance times k in (0, 1], with the noise that follows.

    The signal becomes k I (DN). Photon shot noise and read noise are relative to the signal, so the
    dimmed frame needs more noise than the scaled original carries. With c electrons per DN and read
    noise r electrons, the original holds variance I / c + (r / c)^2 (DN^2) and scales to k^2 of it,
    while a true exposure at k I holds k I / c + (r / c)^2; the difference

        var_added = k (1 - k) I / c + (1 - k^2) (r / c)^2        (DN^2, Poisson-Gaussian model)

    is added as Gaussian noise before quantisation. auto_gain=True then multiplies by 1 / k (a camera
    that restores brightness with analogue gain: contrast back, noise amplified). gamma != 1 applies a
    tone curve 255 (v / 255)^gamma afterwards (gamma < 1 brightens the shadows). k = 1 is a copy.
    """
    image = _check_image(image)
    if not 0.0 < k <= 1.0:
        raise ValueError(f"low-light factor k must be in (0, 1]; got {k!r}")
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0; got {gamma!r}")
    if k == 1.0 and gamma == 1.0:
        return image.copy()
    signal = k * image.astype(np.float64)
    variance = (
        k * (1.0 - k) * image / electrons_per_dn + (1.0 - k * k) * (read_noise_e / electrons_per_dn) ** 2
    )
    rng = np.random.default_rng(frame_seed)
    values = np.clip(np.rint(signal + rng.standard_normal(image.shape) * np.sqrt(variance)), 0, 255)
    if auto_gain:
        values = values / k
    if gamma != 1.0:
        values = 255.0 * (np.clip(values, 0, 255) / 255.0) ** gamma
    return _to_uint8(values)


def motion_blur_kernel(length: float, angle: float = 0.0) -> np.ndarray:
    """Normalised line kernel: a segment of `length` px through the centre at `angle` degrees.

    The segment [-L/2, L/2] along (cos a, sin a) (image x right, y down) is sampled at 16 L midpoints,
    each assigned to its nearest pixel, so for a = 0 and odd L the kernel is exactly a 1 x L box
    (and an L x 1 box for a = 90). The kernel is square with an odd side that holds the segment.
    """
    if length < 0:
        raise ValueError(f"motion-blur length must be >= 0 px; got {length!r}")
    if length <= 1:
        return np.ones((1, 1), np.float32)
    theta = math.radians(angle)
    direction = np.array([math.cos(theta), math.sin(theta)])
    half = int(math.ceil(length / 2.0))
    size = 2 * half + 1
    n_samples = int(16 * math.ceil(length))
    t = -length / 2.0 + (np.arange(n_samples) + 0.5) * (length / n_samples)
    cols = np.rint(half + t * direction[0]).astype(int)
    rows = np.rint(half + t * direction[1]).astype(int)
    kernel = np.zeros((size, size), np.float64)
    np.add.at(kernel, (rows, cols), 1.0)
    return (kernel / kernel.sum()).astype(np.float32)


def motion_blur(image: np.ndarray, length: float, *, angle: float = 0.0) -> np.ndarray:
    """Linear motion blur: the image convolved with motion_blur_kernel(length, angle).

    Models a camera moving `length` px in the image during the exposure along `angle` degrees
    (0 = horizontal, as a yaw gives). Border BORDER_REFLECT_101. length <= 1 returns a copy.
    """
    image = _check_image(image)
    kernel = motion_blur_kernel(length, angle)
    if kernel.size == 1:
        return image.copy()
    return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT_101)


HAZE_AIRLIGHT = 230.0
"""Default airlight A (DN): the brightness of the fog itself, a bright grey."""


@functools.lru_cache(maxsize=32)
def _smooth_field(shape: tuple[int, int], seed: tuple[int, ...]) -> np.ndarray:
    """A smooth random field in [-1, 1] (features about a sixth of the image), fixed by the seed."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(-1.0, 1.0, (5, 7))
    field = cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    field = np.clip(field, -1.0, 1.0)
    field.setflags(write=False)
    return field


def haze(
    image: np.ndarray,
    tau: float,
    *,
    airlight: float = HAZE_AIRLIGHT,
    patchiness: float = 0.0,
    seed: int | Sequence[int] = 0,
) -> np.ndarray:
    """Haze or fog by the atmospheric scattering model I = J t + A (1 - t) (Koschmieder; Narasimhan & Nayar).

    J is the clear image, A the airlight (DN) and t = exp(-tau) the transmission for optical depth
    tau = beta d. Without a depth map the transmission is depth-free: uniform over the image when
    patchiness = 0, otherwise t = exp(-tau (1 + patchiness f)) with f a smooth random field in [-1, 1]
    fixed by `seed` (drifting fog banks; the same on every frame). tau = 0 returns a copy.
    """
    image = _check_image(image)
    if tau < 0:
        raise ValueError(f"haze optical depth tau must be >= 0; got {tau!r}")
    if not 0.0 <= patchiness <= 1.0:
        raise ValueError(f"haze patchiness must be in [0, 1]; got {patchiness!r}")
    if tau == 0:
        return image.copy()
    depth = np.full(image.shape, float(tau))
    if patchiness > 0:
        depth = tau * (1.0 + patchiness * _smooth_field(image.shape, _seed_tuple(seed)))
    t = np.exp(-depth)
    return _to_uint8(image * t + airlight * (1.0 - t))


DIRT_SCATTER = 0.35
"""Fraction of the light blocked by dirt that reaches the sensor again as a diffuse glow."""

DIRT_GLOW_SIGMA = 0.05
"""Width of the diffuse glow behind dirt, as a fraction of the image diagonal."""


@functools.lru_cache(maxsize=64)
def dirt_mask(shape: tuple[int, int], coverage: float, seed: tuple[int, ...] = (0,)) -> np.ndarray:
    """Opacity alpha in [0, 1] of out-of-focus dirt blotches on the lens, fixed by the seed.

    Blotches are drawn one after another from the seed's stream (centre uniform over the image,
    radius 3 to 12 % of the image diagonal, peak opacity 0.5 to 0.95, a soft flat-topped profile
    o exp(-(d / R)^4) since dirt on the lens is far out of focus) and combined as
    alpha = 1 - prod(1 - alpha_i), until the mean opacity reaches `coverage`. The stream does not depend
    on the coverage, so a higher level adds blotches to those of a lower one. Read-only, cached.
    """
    if not 0.0 <= coverage <= 0.9:
        raise ValueError(f"lens-dirt coverage must be in [0, 0.9]; got {coverage!r}")
    height, width = shape
    transmitted = np.ones(shape, np.float64)
    rng = np.random.default_rng(seed)
    diagonal = math.hypot(width, height)
    for _ in range(10_000):
        if 1.0 - transmitted.mean() >= coverage:
            break
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        radius = diagonal * rng.uniform(0.03, 0.12)
        peak = rng.uniform(0.5, 0.95)
        reach = 2.0 * radius  # exp(-(2)^4) ~ 1e-7: nothing beyond
        x0, x1 = max(0, int(cx - reach)), min(width, int(cx + reach) + 1)
        y0, y1 = max(0, int(cy - reach)), min(height, int(cy + reach) + 1)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        d2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (radius * radius)
        transmitted[y0:y1, x0:x1] *= 1.0 - peak * np.exp(-(d2**2))
    alpha = 1.0 - transmitted
    alpha.setflags(write=False)
    return alpha


def lens_dirt(image: np.ndarray, coverage: float, *, seed: int | Sequence[int] = 0) -> np.ndarray:
    """Dirt on the lens: fixed soft blotches (dirt_mask) that block light and scatter part of it.

    out = (1 - alpha) I + alpha s G(I), with alpha = dirt_mask(shape, coverage, seed), s = DIRT_SCATTER the
    share of blocked light scattered back and G a wide Gaussian (DIRT_GLOW_SIGMA of the diagonal): under
    a blotch the scene loses contrast and brightness. Same seed, same blotches on every frame.
    coverage = 0 returns a copy.
    """
    image = _check_image(image)
    if coverage == 0:
        return image.copy()
    alpha = dirt_mask(image.shape, float(coverage), _seed_tuple(seed))
    sigma = DIRT_GLOW_SIGMA * math.hypot(*image.shape)
    glow = cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma)
    return _to_uint8((1.0 - alpha) * image + alpha * DIRT_SCATTER * glow)


def _seed_tuple(seed: int | Sequence[int]) -> tuple[int, ...]:
    return (int(seed),) if np.isscalar(seed) else tuple(int(s) for s in seed)


# --------------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------------


class Disturbance(NamedTuple):
    """One registered disturbance: a pure image function, its default level grid (jsve.core._levels),
    unit and doc."""

    function: Callable[..., np.ndarray]
    levels: tuple[float, ...]
    unit: str
    doc: str


DISTURBANCES: dict[str, Disturbance] = {
    "blur": Disturbance(
        gaussian_blur,
        LEVELS["blur"],
        "kernel px (n x n; even n -> n + 1)",
        "Gaussian blur, seed paper; OpenCV default sigma for the kernel size",
    ),
    "downsample": Disturbance(
        downsample,
        LEVELS["downsample"],
        "scale factor s",
        "INTER_AREA down to round(W s) x round(H s), seed paper; mode rescale (back up, INTER_LINEAR) or "
        "calibration (small image, scaled intrinsics)",
    ),
    "occlusion": Disturbance(
        occlusion,
        LEVELS["occlusion"],
        "square side px",
        "black n x n square in the centre, seed paper",
    ),
    "noise": Disturbance(
        sensor_noise,
        LEVELS["noise"],
        "sigma DN",
        "additive white Gaussian sensor noise, new every frame",
    ),
    "low_light": Disturbance(
        low_light,
        LEVELS["low_light"],
        "light fraction k",
        "irradiance times k with Poisson-Gaussian noise; optional auto gain and gamma",
    ),
    "motion_blur": Disturbance(
        motion_blur,
        LEVELS["motion_blur"],
        "streak length px",
        "line kernel of the given length along `angle` degrees (default 0, horizontal)",
    ),
    "haze": Disturbance(
        haze,
        LEVELS["haze"],
        "optical depth tau",
        "I = J t + A (1 - t), t = exp(-tau), uniform or patchy depth-free transmission",
    ),
    "lens_dirt": Disturbance(
        lens_dirt,
        LEVELS["lens_dirt"],
        "mean opacity",
        "fixed soft blotches from a seed, the same on every frame; blocked light partly scattered",
    ),
}
"""name -> Disturbance(function, levels, unit, doc). function(image, level, **parameters) -> image."""


def _parameters_of(name: str) -> dict[str, inspect.Parameter]:
    if name not in DISTURBANCES:
        raise ValueError(f"unknown disturbance {name!r}; known: {', '.join(DISTURBANCES)}")
    params = inspect.signature(DISTURBANCES[name].function).parameters
    return {k: p for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}


def disturbance_parameters(name: str) -> dict[str, object]:
    """The tunable keyword parameters of a disturbance and their defaults (seeds excluded)."""
    return {k: p.default for k, p in _parameters_of(name).items() if k not in ("seed", "frame_seed")}


def _check_parameters(name: str, parameters: Mapping[str, object] | None) -> dict[str, object]:
    parameters = dict(parameters or {})
    allowed = disturbance_parameters(name)
    unknown = sorted(set(parameters) - set(allowed))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {unknown} for disturbance {name!r}; it takes {sorted(allowed) or 'none'}"
        )
    return parameters


def disturb_image(
    image: np.ndarray,
    name: str,
    level: float,
    parameters: Mapping[str, object] | None = None,
    *,
    seed: int | Sequence[int] = 0,
    frame_seed: int | Sequence[int] = 0,
) -> np.ndarray:
    """Apply the registered disturbance `name` at `level` to one image.

    Arguments:
        image: 8-bit grey image, H x W.
        name: a key of DISTURBANCES.
        level: the level in the disturbance's unit.
        parameters: keyword parameters of the disturbance (e.g. {"mode": "calibration"}).
        seed: fixed-pattern seed, passed to disturbances with a `seed` argument (dataset-wide).
        frame_seed: per-frame seed, passed to disturbances with a `frame_seed` argument.
    Returns:
        The disturbed image (uint8; a different size only for downsample in calibration mode).
    """
    kwargs = _check_parameters(name, parameters)
    accepted = _parameters_of(name)
    if "seed" in accepted:
        kwargs["seed"] = seed
    if "frame_seed" in accepted:
        kwargs["frame_seed"] = frame_seed
    return DISTURBANCES[name].function(image, level, **kwargs)
