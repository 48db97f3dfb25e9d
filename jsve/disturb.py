"""Image disturbances and their application to EuRoC-format datasets (an I/O edge of jsve).

Every disturbance is a pure function on one 8-bit grey image (H x W numpy array) and one level,
registered in `DISTURBANCES` as name -> Disturbance(function, levels, unit, doc). The seed paper's
three (Rugg-Gunn & Aitken 2022, section 3) keep its exact level grids: Gaussian blur, downsampling and
a centred black occlusion. Five more cover what SLAM users meet in the field: sensor noise, low
light, motion blur, haze and lens dirt. See docs/disturbances.md.

Randomness is deterministic. A function with a `frame_seed` argument draws new noise for every frame
(the dataset writer passes `(seed, camera index, t_ns)`); a function with a `seed` argument draws one
fixed pattern per dataset and camera (the writer passes `(seed, camera index)`), so lens dirt sits in
the same place on every frame.

`disturb_datasets` writes one dataset per (source, disturbance, level) under
`OUT/<source name>/<disturbance>-<level>[_<param>=<value>...]`. Each is built in a sibling folder
ending in `.partial` and renamed when complete, with a manifest (`jsve_manifest.json`) written last;
a re-run skips finished datasets and discards stale `.partial` folders.
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import inspect
import json
import logging
import math
import multiprocessing
import os
import re
import shutil
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

logger = logging.getLogger(__name__)

MANIFEST_NAME = "jsve_manifest.json"
"""File name of the manifest inside every written dataset; its presence marks the dataset finished."""

PARTIAL_SUFFIX = ".partial"
"""Suffix of the folder a dataset is built in before it is renamed into place."""

MANIFEST_VERSION = 1

IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


class DatasetError(Exception):
    """A dataset folder that cannot be read or written; the message names the path."""


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
    """One registered disturbance: a pure image function, its default level grid, unit and doc."""

    function: Callable[..., np.ndarray]
    levels: tuple[float, ...]
    unit: str
    doc: str


DISTURBANCES: dict[str, Disturbance] = {
    "blur": Disturbance(
        gaussian_blur,
        tuple(range(0, 55, 5)),
        "kernel px (n x n; even n -> n + 1)",
        "Gaussian blur, seed paper; OpenCV default sigma for the kernel size",
    ),
    "downsample": Disturbance(
        downsample,
        tuple(round(1.0 - 0.1 * i, 1) for i in range(10)),
        "scale factor s",
        "INTER_AREA down to round(W s) x round(H s), seed paper; mode rescale (back up, INTER_LINEAR) or "
        "calibration (small image, scaled intrinsics)",
    ),
    "occlusion": Disturbance(
        occlusion,
        tuple(range(50, 500, 50)),
        "square side px",
        "black n x n square in the centre, seed paper",
    ),
    "noise": Disturbance(
        sensor_noise,
        (0, 2, 5, 10, 15, 20, 30, 40),
        "sigma DN",
        "additive white Gaussian sensor noise, new every frame",
    ),
    "low_light": Disturbance(
        low_light,
        (1.0, 0.5, 0.3, 0.2, 0.15, 0.1, 0.07, 0.05, 0.03),
        "light fraction k",
        "irradiance times k with Poisson-Gaussian noise; optional auto gain and gamma",
    ),
    "motion_blur": Disturbance(
        motion_blur,
        (0, 5, 10, 15, 20, 30, 40, 50),
        "streak length px",
        "line kernel of the given length along `angle` degrees (default 0, horizontal)",
    ),
    "haze": Disturbance(
        haze,
        (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0),
        "optical depth tau",
        "I = J t + A (1 - t), t = exp(-tau), uniform or patchy depth-free transmission",
    ),
    "lens_dirt": Disturbance(
        lens_dirt,
        (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6),
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


# --------------------------------------------------------------------------------------------------
# EuRoC datasets
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    """One dataset to write: `source` disturbed by `name` at `level` into `target`."""

    source: Path
    target: Path
    name: str
    level: float
    parameters: tuple[tuple[str, object], ...]
    seed: int


@dataclass(frozen=True)
class JobResult:
    """What happened to one job: status "written", "skipped" (finished before) or "redone" (stale partial)."""

    target: Path
    status: str
    manifest: dict


def format_level(level: float) -> str:
    """Level as it appears in folder names: 15 -> "15", 0.9 -> "0.9", 0.05 -> "0.05"."""
    return f"{float(level):g}"


def dataset_dir_name(name: str, level: float, parameters: Mapping[str, object] | None = None) -> str:
    """`<name>-<level>`, with `_<param>=<value>` appended for every parameter not at its default."""
    defaults = disturbance_parameters(name)
    parts = [f"{name}-{format_level(level)}"]
    for key, value in sorted(_check_parameters(name, parameters).items()):
        if value != defaults[key]:
            parts.append(f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}")
    return "_".join(parts)


def _mav0(dataset: Path) -> Path:
    dataset = Path(dataset)
    if (dataset / "mav0").is_dir():
        return dataset / "mav0"
    raise DatasetError(f"{dataset}: not a EuRoC dataset folder (no mav0/ inside)")


def camera_dirs(dataset: Path) -> list[Path]:
    """The camera folders mav0/cam*/ of a EuRoC dataset that hold data/ and data.csv, sorted."""
    mav0 = _mav0(dataset)
    cams = sorted(p for p in mav0.glob("cam*") if (p / "data").is_dir() and (p / "data.csv").is_file())
    if not cams:
        raise DatasetError(f"{mav0}: no camera folder with data/ and data.csv")
    return cams


def read_frame_list(cam_dir: Path) -> list[tuple[int, str]]:
    """(t_ns, file name) per frame from a EuRoC camera's data.csv, in file order."""
    path = Path(cam_dir) / "data.csv"
    frames = []
    with open(path, encoding="utf-8") as stream:
        for lineno, line in enumerate(stream, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = [f.strip() for f in line.split(",")]
            try:
                frames.append((int(fields[0]), fields[1]))
            except (ValueError, IndexError) as error:
                raise DatasetError(f"{path}:{lineno}: expected `t_ns,filename`, got {line!r}") from error
    return frames


_FLOW_LIST = r"^(?P<key>{key})\s*:\s*\[(?P<values>[^\]]*)\](?P<rest>.*)$"


def read_yaml_list(text: str, key: str) -> list[float] | None:
    """The numbers of a one-line flow list `key: [a, b, ...]` in an EuRoC sensor.yaml, or None."""
    match = re.search(_FLOW_LIST.format(key=re.escape(key)), text, flags=re.MULTILINE)
    if match is None:
        return None
    return [float(v) for v in match.group("values").split(",") if v.strip()]


def rescale_sensor_yaml(text: str, target_size: tuple[int, int]) -> str:
    """sensor.yaml text with `resolution` set to target_size and `intrinsics` scaled to match.

    Everything else (comments, extrinsics, distortion) is kept byte for byte.
    """
    resolution = read_yaml_list(text, "resolution")
    intrinsics = read_yaml_list(text, "intrinsics")
    if resolution is None or intrinsics is None or len(resolution) != 2 or len(intrinsics) != 4:
        raise DatasetError("sensor.yaml: need `resolution: [w, h]` and `intrinsics: [fu, fv, cu, cv]`")
    source_size = (int(resolution[0]), int(resolution[1]))
    scaled = scale_intrinsics(intrinsics, source_size, target_size)

    def replace(key: str, values: str, text: str) -> str:
        pattern = _FLOW_LIST.format(key=re.escape(key))
        return re.sub(
            pattern,
            lambda m: f"{m.group('key')}: [{values}]{m.group('rest')}",
            text,
            count=1,
            flags=re.MULTILINE,
        )

    text = replace("resolution", f"{target_size[0]}, {target_size[1]}", text)
    return replace("intrinsics", ", ".join(f"{v:.9g}" for v in scaled), text)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def content_hash(folder: Path, exclude: Iterable[str] = (MANIFEST_NAME,)) -> tuple[str, int]:
    """sha256 over every file's relative path and bytes, in sorted path order; and the file count."""
    folder = Path(folder)
    exclude = set(exclude)
    files = sorted(
        p for p in folder.rglob("*") if p.is_file() and p.relative_to(folder).as_posix() not in exclude
    )
    total = hashlib.sha256()
    for path in files:
        total.update(path.relative_to(folder).as_posix().encode())
        total.update(b"\0")
        digest = hashlib.sha256()
        with open(path, "rb") as stream:
            for chunk in iter(lambda: stream.read(1 << 20), b""):
                digest.update(chunk)
        total.update(digest.digest())
    return "sha256:" + total.hexdigest(), len(files)


def read_manifest(dataset: Path) -> dict | None:
    """The manifest of a written dataset, or None when it has none."""
    path = Path(dataset) / MANIFEST_NAME
    if not path.is_file():
        return None
    with open(path, encoding="utf-8") as stream:
        return json.load(stream)


def _jsve_version() -> str:
    try:
        from importlib.metadata import version

        return version("jsve")
    except Exception:  # not installed (running from a checkout)
        from . import __version__

        return __version__


def _write_dataset(job: Job, partial: Path) -> dict:
    source = Path(job.source)
    parameters = dict(job.parameters)
    partial.mkdir(parents=True)
    cams = camera_dirs(source)
    cam_names = {cam.relative_to(source).as_posix() for cam in cams}
    # Everything outside the camera folders (IMU, ground truth, body.yaml, licence) is linked untouched.
    for path in sorted(source.rglob("*")):
        rel = path.relative_to(source)
        if any(rel.as_posix() == c or rel.as_posix().startswith(c + "/") for c in cam_names):
            continue
        if path.is_dir():
            (partial / rel).mkdir(parents=True, exist_ok=True)
        elif path.is_file():
            (partial / rel).parent.mkdir(parents=True, exist_ok=True)
            _link_or_copy(path, partial / rel)
    n_frames = {}
    for cam_index, cam in enumerate(cams):
        rel_cam = cam.relative_to(source)
        out_cam = partial / rel_cam
        (out_cam / "data").mkdir(parents=True, exist_ok=True)
        for path in sorted(cam.rglob("*")):
            rel = path.relative_to(cam)
            if rel.parts[0] == "data" or rel.as_posix() == "sensor.yaml":
                continue
            if path.is_dir():
                (out_cam / rel).mkdir(parents=True, exist_ok=True)
            elif path.is_file():
                (out_cam / rel).parent.mkdir(parents=True, exist_ok=True)
                _link_or_copy(path, out_cam / rel)
        frames = read_frame_list(cam)
        sizes = set()
        for t_ns, filename in frames:
            image = cv2.imread(str(cam / "data" / filename), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise DatasetError(f"{cam / 'data' / filename}: cannot read image listed in data.csv")
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            if image.dtype != np.uint8:
                raise DatasetError(f"{cam / 'data' / filename}: expected an 8-bit image, got {image.dtype}")
            out = disturb_image(
                image,
                job.name,
                job.level,
                parameters,
                seed=(job.seed, cam_index),
                frame_seed=(job.seed, cam_index, t_ns),
            )
            sizes.add((image.shape[1], image.shape[0], out.shape[1], out.shape[0]))
            if not cv2.imwrite(str(out_cam / "data" / filename), out):
                raise DatasetError(f"{out_cam / 'data' / filename}: cannot write image")
        # Images not listed in data.csv are not part of the sequence and are not written.
        sensor = cam / "sensor.yaml"
        if sensor.is_file():
            resized = {(w1, h1) for w0, h0, w1, h1 in sizes if (w0, h0) != (w1, h1)}
            if resized:
                if len(resized) > 1:
                    raise DatasetError(f"{cam}: frames of different sizes after {job.name}")
                text = rescale_sensor_yaml(sensor.read_text(encoding="utf-8"), resized.pop())
                (out_cam / "sensor.yaml").write_text(text, encoding="utf-8")
            else:
                shutil.copy2(sensor, out_cam / "sensor.yaml")
        n_frames[rel_cam.as_posix()] = len(frames)
    digest, file_count = content_hash(partial)
    manifest = {
        "jsve_manifest": MANIFEST_VERSION,
        "source": str(source.resolve()),
        "dataset": source.name,
        "disturbance": job.name,
        "level": job.level,
        "unit": DISTURBANCES[job.name].unit,
        "parameters": {**disturbance_parameters(job.name), **parameters, "seed": job.seed},
        "jsve_version": _jsve_version(),
        "frames": n_frames,
        "file_count": file_count,
        "content_hash": digest,
    }
    with open(partial / MANIFEST_NAME, "w", encoding="utf-8") as stream:
        json.dump(manifest, stream, indent=2)
    return manifest


def disturb_dataset(job: Job) -> JobResult:
    """Write one disturbed dataset, atomically and resumably.

    A finished dataset (target folder with a manifest) is skipped. Otherwise the dataset is built in
    `<target>.partial/` (a stale one from a crashed run is discarded first), its manifest written last,
    and the folder renamed to `target`. A target folder without a manifest is not jsve's and raises.
    """
    target = Path(job.target)
    manifest = read_manifest(target)
    if manifest is not None:
        return JobResult(target, "skipped", manifest)
    if target.exists():
        raise DatasetError(
            f"{target}: exists but has no {MANIFEST_NAME}; not overwriting a folder jsve did not write"
        )
    partial = target.with_name(target.name + PARTIAL_SUFFIX)
    status = "written"
    if partial.exists():
        logger.info("discarding stale %s", partial)
        shutil.rmtree(partial)
        status = "redone"
    manifest = _write_dataset(job, partial)
    os.replace(partial, target)
    return JobResult(target, status, manifest)


def make_jobs(
    sources: Sequence[Path | str],
    out_dir: Path | str,
    disturbances: Sequence[str] | None = None,
    levels: Mapping[str, Sequence[float]] | None = None,
    parameters: Mapping[str, Mapping[str, object]] | None = None,
    seed: int = 0,
) -> list[Job]:
    """One Job per (source, disturbance, level): targets `out_dir/<source name>/<dataset_dir_name>`.

    Arguments:
        sources: EuRoC dataset folders (each holding mav0/).
        out_dir: root of the written datasets.
        disturbances: names from DISTURBANCES (default: all).
        levels: per-disturbance level lists overriding the registry's grid.
        parameters: per-disturbance keyword parameters, e.g. {"downsample": {"mode": "calibration"}}.
        seed: base seed of every random disturbance.
    """
    names = list(disturbances) if disturbances is not None else list(DISTURBANCES)
    levels = dict(levels or {})
    parameters = dict(parameters or {})
    for name in list(levels) + list(parameters):
        if name not in names:
            raise ValueError(
                f"levels/parameters given for {name!r}, which is not among the disturbances {names}"
            )
    jobs = []
    for source in sources:
        source = Path(source)
        camera_dirs(source)  # fail early on a folder that is not a dataset
        for name in names:
            params = _check_parameters(name, parameters.get(name))
            for level in levels.get(name, DISTURBANCES[name].levels):
                target = Path(out_dir) / source.name / dataset_dir_name(name, level, params)
                jobs.append(Job(source, target, name, level, tuple(sorted(params.items())), int(seed)))
    return jobs


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one process per core; OpenCV's own threads would oversubscribe


def run_parallel(function: Callable, items: Sequence, workers: int, progress: bool, desc: str) -> list:
    """function(item) for every item, in `workers` processes (in this one when workers <= 1), in order.

    Uses the spawn start method (no fork of a process that may hold JAX or OpenCV threads) and a tqdm
    progress bar over finished items.
    """
    from tqdm.auto import tqdm

    results: list = [None] * len(items)
    with tqdm(total=len(items), desc=desc, disable=not progress, unit="job") as bar:
        if workers <= 1 or len(items) <= 1:
            for index, item in enumerate(items):
                results[index] = function(item)
                bar.update()
            return results
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            workers, mp_context=context, initializer=_init_worker
        ) as pool:
            futures = {pool.submit(function, item): index for index, item in enumerate(items)}
            for future in concurrent.futures.as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    return results


def disturb_datasets(
    sources: Sequence[Path | str],
    out_dir: Path | str,
    disturbances: Sequence[str] | None = None,
    levels: Mapping[str, Sequence[float]] | None = None,
    parameters: Mapping[str, Mapping[str, object]] | None = None,
    *,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
) -> list[JobResult]:
    """Write every (source, disturbance, level) dataset, in parallel, skipping finished ones.

    See make_jobs for the arguments; `workers` processes write datasets side by side and a tqdm bar
    counts finished datasets. Returns one JobResult per job, in job order.
    """
    jobs = make_jobs(sources, out_dir, disturbances, levels, parameters, seed)
    for job in jobs:
        job.target.parent.mkdir(parents=True, exist_ok=True)
    return run_parallel(disturb_dataset, jobs, workers, progress, "disturb")
