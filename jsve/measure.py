"""Scene visibility measured on real frames: the image side of SVE, with OpenCV (an I/O edge of jsve).

For every frame of a EuRoC camera folder this module extracts ORB features with ORB-SLAM3's EuRoC
settings, matches them to the previous frame, verifies the matches geometrically, bins the keypoints
into SVE's 8 x 8 bins and counts the previous frame's keypoints expected in view. The per-frame counts
(n_extracted, n_inliers, n_frustum, bin_0..bin_63) are those of the tracking log (jsve.schema), and
the SVE metrics follow from them through jsve.sve.sve_table. Stand-ins for what only a running
ORB-SLAM3 knows are documented where they are made, and in docs/disturbances.md:

- Extraction. ORB-SLAM3's ORBextractor runs FAST with iniThFAST = 20 in cells of about 35 x 35 px of
  every pyramid level, retries a cell with minThFAST = 7 when it yields nothing, and spreads the
  survivors with a quadtree. OpenCV's ORB runs FAST over whole levels and keeps the best Harris scores.
  We approximate the per-cell fallback with two OpenCV passes (extract_orb): first cv2.ORB with
  FAST 20 over the image; then, if it returned fewer than nFeatures, a second cv2.ORB with FAST 7,
  masked to the level-0 35-px cells (ORB-SLAM3's grid over the region inside EDGE_THRESHOLD - 3) in
  which the first pass kept no keypoint, asked for the remaining budget nFeatures - n1. Differences:
  cells are level-0 cells for all levels (ORB-SLAM3's grow with the level); a cell counts as empty
  after the first pass's Harris selection, not before; and the second pass never displaces a FAST-20
  keypoint (ORB-SLAM3's quadtree may). EDGE_THRESHOLD = 19 and PATCH_SIZE = 31 are ORB-SLAM3's.
- Inliers. Brute-force Hamming matching to the previous frame (best match within ORB-SLAM3's
  TH_HIGH = 100 and passing a Lowe ratio test, one match per current keypoint), then
  cv2.findEssentialMat with RANSAC on undistorted points; n_inliers is the RANSAC inlier count.
  ORB-SLAM3's n_inliers are map-point inliers after pose optimisation, a different but analogous count.
- Frustum. ORB-SLAM3's N_frustum (nToMatch) counts local-map points that project into the frame. We
  count the previous frame's keypoints that a homography fitted to the inliers maps inside the current
  image bounds (identity when fewer than MatchSettings.min_matches inliers: as ORB-SLAM3 projects with
  its motion model when tracking is weak, the expectation does not collapse with the measurement).
- The first frame has no predecessor: n_inliers = n_frustum = 0 there.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import pandas as pd

from .disturb import DatasetError, camera_dirs, read_frame_list, read_yaml_list, run_parallel
from .schema import BIN_COLUMNS, N_BINS

logger = logging.getLogger(__name__)

GRID_COLS = 64
GRID_ROWS = 48
"""ORB-SLAM3's keypoint grid (FRAME_GRID_COLS x FRAME_GRID_ROWS)."""

SVE_BINS_X = 8
SVE_BINS_Y = 8
"""SVE bins: bin x = grid col // 8, bin y = grid row // 6 (Haggart & Aitken 2021)."""

TABLE_COUNT_COLUMNS = ("t_ns", "n_extracted", "n_inliers", "n_frustum")


# --------------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A EuRoC camera: image size, pinhole intrinsics and lens distortion (from sensor.yaml).

    Attributes:
        width, height: image size, px.
        fx, fy, cx, cy: pinhole intrinsics, px.
        distortion_model: "radial-tangential" (k1, k2, p1, p2; OpenCV's order) or "equidistant"
            (k1..k4, OpenCV's fisheye model).
        distortion: the coefficients.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "radial-tangential"
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_sensor_yaml(cls, path: Path | str) -> Camera:
        """Read a EuRoC cam*/sensor.yaml (resolution, intrinsics, distortion_model/_coefficients)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as error:
            raise DatasetError(f"{path}: cannot read camera calibration ({error})") from error
        resolution = read_yaml_list(text, "resolution")
        intrinsics = read_yaml_list(text, "intrinsics")
        coefficients = read_yaml_list(text, "distortion_coefficients") or []
        if resolution is None or len(resolution) != 2 or intrinsics is None or len(intrinsics) != 4:
            raise DatasetError(f"{path}: need `resolution: [w, h]` and `intrinsics: [fu, fv, cu, cv]`")
        model = re.search(r"^camera_model\s*:\s*(\S+)", text, flags=re.MULTILINE)
        if model is not None and model.group(1) != "pinhole":
            raise DatasetError(f"{path}: camera_model {model.group(1)!r} is not supported (pinhole only)")
        distortion = re.search(r"^distortion_model\s*:\s*(\S+)", text, flags=re.MULTILINE)
        distortion_model = distortion.group(1) if distortion else "radial-tangential"
        if distortion_model not in ("radial-tangential", "equidistant"):
            raise DatasetError(f"{path}: distortion_model {distortion_model!r} is not supported")
        return cls(
            int(resolution[0]),
            int(resolution[1]),
            *intrinsics,
            distortion_model=distortion_model,
            distortion=tuple(coefficients),
        )

    @property
    def matrix(self) -> np.ndarray:
        """K, 3 x 3."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return any(c != 0.0 for c in self.distortion)

    def undistort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted pixel coordinates (N, 2) of distorted pixel coordinates (N, 2), same K."""
        xy = np.asarray(xy, np.float64).reshape(-1, 1, 2)
        if not self.distorted or len(xy) == 0:
            return xy.reshape(-1, 2)
        coefficients = np.asarray(self.distortion, np.float64)
        if self.distortion_model == "equidistant":
            out = cv2.fisheye.undistortPoints(xy, self.matrix, coefficients, P=self.matrix)
        else:
            out = cv2.undistortPoints(xy, self.matrix, coefficients, P=self.matrix)
        return out.reshape(-1, 2)

    def grid_keypoints(self, xy: np.ndarray) -> np.ndarray:
        """Keypoint coordinates ORB-SLAM3 puts in its grid (mvKeysUn).

        ORB-SLAM3 v1.0 undistorts keypoints for the pinhole model (Frame::UndistortKeyPoints) and keeps
        them as extracted for the fisheye (Kannala-Brandt) model.
        """
        if self.distortion_model == "equidistant":
            return np.asarray(xy, np.float64).reshape(-1, 2)
        return self.undistort(xy)

    def bounds(self) -> tuple[float, float, float, float]:
        """(min_x, max_x, min_y, max_y) of the undistorted image, as ORB-SLAM3's Frame::ComputeImageBounds.

        With distortion, the four corners (0, 0), (W, 0), (0, H), (W, H) are undistorted and
        min_x = min(x0, x2), max_x = max(x1, x3), min_y = min(y0, y1), max_y = max(y2, y3).
        """
        if not self.distorted or self.distortion_model == "equidistant":
            return 0.0, float(self.width), 0.0, float(self.height)
        corners = self.undistort(
            np.array([[0, 0], [self.width, 0], [0, self.height], [self.width, self.height]], np.float64)
        )
        (x0, y0), (x1, y1), (x2, y2), (x3, y3) = corners
        return float(min(x0, x2)), float(max(x1, x3)), float(min(y0, y1)), float(max(y2, y3))


# --------------------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------------------


EXTRACTORS = ("orbslam3", "opencv")


@dataclass(frozen=True)
class OrbSettings:
    """ORB-SLAM3 v1.0's EuRoC extractor settings (Examples/Monocular-Inertial/EuRoC.yaml, ORBextractor.cc).

    Attributes:
        extractor: "orbslam3" (default) re-implements ORBextractor's keypoint selection with OpenCV
            primitives (extract_orb_orbslam3); "opencv" is cv2.ORB_create with a masked FAST-7
            second pass (extract_orb_opencv); with fallback=False it is plain cv2.ORB_create, the
            reference of DESIGN section 7.
        n_features, scale_factor, n_levels, ini_th_fast, min_th_fast: ORBextractor.* settings.
        edge_threshold, patch_size, cell_size: ORBextractor.cc's EDGE_THRESHOLD, PATCH_SIZE and the
            cell width W of ComputeKeyPointsOctTree.
        fallback: retry empty cells with min_th_fast.
    """

    extractor: str = "orbslam3"
    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    ini_th_fast: int = 20
    min_th_fast: int = 7
    edge_threshold: int = 19
    patch_size: int = 31
    cell_size: int = 35
    fallback: bool = True

    def __post_init__(self):
        if self.extractor not in EXTRACTORS:
            raise ValueError(f"OrbSettings.extractor must be one of {EXTRACTORS}; got {self.extractor!r}")

    def detector(self, fast_threshold: int, n_features: int) -> cv2.ORB:
        """cv2.ORB with these settings, a given FAST threshold and feature budget."""
        return cv2.ORB_create(
            nfeatures=int(n_features),
            scaleFactor=self.scale_factor,
            nlevels=self.n_levels,
            edgeThreshold=self.edge_threshold,
            patchSize=self.patch_size,
            fastThreshold=int(fast_threshold),
        )

    def features_per_level(self) -> list[int]:
        """ORBextractor's mnFeaturesPerLevel: a geometric series in 1 / scale_factor summing to n_features."""
        factor = 1.0 / self.scale_factor
        desired = self.n_features * (1.0 - factor) / (1.0 - factor**self.n_levels)
        counts = []
        for _ in range(self.n_levels - 1):
            counts.append(int(math.floor(desired + 0.5)))
            desired *= factor
        counts.append(max(self.n_features - sum(counts), 0))
        return counts


class Features(NamedTuple):
    """Keypoints of one frame: xy (N, 2) pixels as extracted, descriptors (N, 32) uint8, octave (N,)."""

    xy: np.ndarray
    descriptors: np.ndarray
    octave: np.ndarray


def _as_features(keypoints: Sequence[cv2.KeyPoint], descriptors: np.ndarray | None) -> Features:
    if not keypoints or descriptors is None:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.int32))
    xy = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
    octave = np.array([k.octave for k in keypoints], np.int32)
    return Features(xy, descriptors, octave)


def extract_orb(image: np.ndarray, settings: OrbSettings = OrbSettings()) -> Features:
    """ORB keypoints and descriptors of one 8-bit grey image with the chosen extractor."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"image must be 8-bit grey (H x W uint8); got {image.shape}, {image.dtype}")
    if settings.extractor == "opencv":
        return extract_orb_opencv(image, settings)
    return extract_orb_orbslam3(image, settings)


# ORB-SLAM3-style selection ------------------------------------------------------------------------


def image_pyramid(image: np.ndarray, settings: OrbSettings) -> list[np.ndarray]:
    """ORBextractor::ComputePyramid: level l is level l-1 resized (INTER_LINEAR) to round(size / 1.2^l)."""
    levels = [image]
    height, width = image.shape
    for level in range(1, settings.n_levels):
        inverse = settings.scale_factor ** (-level)
        size = (int(math.floor(width * inverse + 0.5)), int(math.floor(height * inverse + 0.5)))
        if min(size) < 1:
            break
        levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR))
    return levels


def fast_in_cells(level_image: np.ndarray, settings: OrbSettings) -> tuple[np.ndarray, np.ndarray]:
    """FAST corners of one pyramid level found cell by cell, as ORBextractor::ComputeKeyPointsOctTree.

    The region [EDGE_THRESHOLD - 3, size - EDGE_THRESHOLD + 3] is cut into cells of about W = 35 px,
    each enlarged by 6 px so that FAST's 3 px margin leaves no gap; FAST (9/16, non-max suppression)
    runs with ini_th_fast in every cell and again with min_th_fast in a cell that gave nothing.

    Returns:
        xy (n, 2), relative to the region's corner (EDGE_THRESHOLD - 3, EDGE_THRESHOLD - 3), level px;
        response (n,), the FAST score.
    """
    height, width = level_image.shape
    lo = settings.edge_threshold - 3
    max_x, max_y = width - settings.edge_threshold + 3, height - settings.edge_threshold + 3
    extent_x, extent_y = max_x - lo, max_y - lo
    n_cols, n_rows = int(extent_x // settings.cell_size), int(extent_y // settings.cell_size)
    if n_cols < 1 or n_rows < 1:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    w_cell, h_cell = math.ceil(extent_x / n_cols), math.ceil(extent_y / n_rows)
    strong = cv2.FastFeatureDetector_create(settings.ini_th_fast, True)
    weak = cv2.FastFeatureDetector_create(settings.min_th_fast, True)
    points, responses = [], []
    for i in range(n_rows):
        y0 = lo + i * h_cell
        if y0 >= max_y - 3:
            continue
        y1 = min(y0 + h_cell + 6, max_y)
        for j in range(n_cols):
            x0 = lo + j * w_cell
            if x0 >= max_x - 6:
                continue
            x1 = min(x0 + w_cell + 6, max_x)
            cell = np.ascontiguousarray(level_image[y0:y1, x0:x1])
            found = strong.detect(cell)
            if not found and settings.fallback:
                found = weak.detect(cell)
            if found:
                points.append(cv2.KeyPoint_convert(found) + np.float32([j * w_cell, i * h_cell]))
                responses.append(np.array([k.response for k in found], np.float32))
    if not points:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    return np.concatenate(points).reshape(-1, 2), np.concatenate(responses)


def distribute_quadtree(
    xy: np.ndarray, response: np.ndarray, width: float, height: float, n_wanted: int
) -> np.ndarray:
    """Indices of keypoints kept by ORB-SLAM3's quadtree (ORBextractor::DistributeOctTree).

    The region [0, width) x [0, height) starts as round(width / height) columns; nodes holding more
    than one keypoint are split in four (at x0 + ceil(w / 2), y0 + ceil(h / 2)), all at once while far
    from n_wanted nodes; once a full round could overshoot, the fullest nodes are split first (ties:
    larger x0 first), one at a time, until there are n_wanted nodes or nothing splits further. Each
    node keeps its keypoint with the highest response (the first one on ties). The result may exceed
    n_wanted by up to 3, as in ORB-SLAM3.

    Nodes are held as a label per keypoint and a box per label, and a round of splits is one
    vectorised relabelling (a split node's children are labelled parent * 4 + quadrant).
    """
    n = len(xy)
    if n == 0 or n_wanted <= 0:
        return np.zeros(0, np.int64)
    x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
    n_initial = max(1, int(math.floor(width / height + 0.5)))
    step = width / n_initial
    column = np.clip((x / step).astype(np.int64), 0, n_initial - 1)
    columns, labels = np.unique(column, return_inverse=True)
    # int() truncation of the corners, as cv::Point2i(hX * i, 0) does.
    boxes = np.stack(
        [
            (step * columns).astype(np.int64),
            np.zeros(len(columns), np.int64),
            (step * (columns + 1)).astype(np.int64),
            np.full(len(columns), int(height), np.int64),
        ],
        axis=1,
    )

    def split(labels, boxes, chosen):
        """Split the nodes flagged in `chosen`; returns new labels, boxes and the children's parents."""
        x0, y0, x1, y1 = boxes.T
        mx = x0 + (x1 - x0 + 1) // 2  # x0 + ceil(w / 2)
        my = y0 + (y1 - y0 + 1) // 2
        quadrant = (x >= mx[labels]).astype(np.int64) + 2 * (y >= my[labels])
        key = labels * 4 + np.where(chosen[labels], quadrant, 0)
        keys, new_labels = np.unique(key, return_inverse=True)
        parent, q = keys // 4, keys % 4
        was_split = chosen[parent]
        right, bottom = (q % 2 == 1) & was_split, (q >= 2) & was_split
        left_half, top_half = (q % 2 == 0) & was_split, (q < 2) & was_split
        new_boxes = boxes[parent].copy()
        new_boxes[right, 0] = mx[parent][right]
        new_boxes[left_half, 2] = mx[parent][left_half]
        new_boxes[bottom, 1] = my[parent][bottom]
        new_boxes[top_half, 3] = my[parent][top_half]
        return new_labels, new_boxes, np.where(was_split, parent, -1)

    while True:
        counts = np.bincount(labels)
        before = len(counts)
        labels, boxes, parent = split(labels, boxes, counts > 1)
        counts = np.bincount(labels)
        if len(counts) >= n_wanted or len(counts) == before:
            break
        expandable = np.nonzero((parent >= 0) & (counts > 1))[0]
        if len(counts) + 3 * len(expandable) <= n_wanted:
            continue
        # Close to the target: split the fullest first, stopping as soon as there are enough nodes.
        while True:
            before = len(counts)
            order = np.lexsort((boxes[expandable, 0], counts[expandable]))[::-1]
            candidates = expandable[order]
            flagged = np.zeros(len(counts), bool)
            flagged[candidates] = True
            _, _, trial_parent = split(labels, boxes, flagged)
            children = np.bincount(trial_parent[trial_parent >= 0], minlength=len(counts))[candidates]
            reached = before + np.cumsum(children - 1) >= n_wanted
            n_split = int(np.argmax(reached)) + 1 if reached.any() else len(candidates)
            chosen = np.zeros(len(counts), bool)
            chosen[candidates[:n_split]] = True
            labels, boxes, parent = split(labels, boxes, chosen)
            counts = np.bincount(labels)
            expandable = np.nonzero((parent >= 0) & (counts > 1))[0]
            if len(counts) >= n_wanted or len(counts) == before:
                break
        break
    order = np.lexsort((-response.astype(np.float64), labels))
    _, first = np.unique(labels[order], return_index=True)
    return np.sort(order[first])


def _disc_half_widths(radius: int) -> np.ndarray:
    """Half-widths u_max[v] of the circular patch of IC_Angle, made symmetric under u <-> v (Rublee 2011)."""
    v_max = math.floor(radius * math.sqrt(2.0) / 2.0 + 1.0)
    v_min = math.ceil(radius * math.sqrt(2.0) / 2.0)
    u_max = np.zeros(radius + 1, np.int64)
    u_max[: v_max + 1] = np.floor(np.sqrt(radius * radius - np.arange(v_max + 1) ** 2) + 0.5)
    inner = u_max[: v_max + 1].copy()
    for v in range(v_min, radius + 1):
        u_max[v] = np.nonzero(inner >= v)[0].max()
    return u_max


@functools.lru_cache(maxsize=4)
def _moment_kernels(radius: int) -> tuple[np.ndarray, np.ndarray]:
    u_max = _disc_half_widths(radius)
    offsets = np.arange(-radius, radius + 1)
    v, u = np.meshgrid(offsets, offsets, indexing="ij")
    disc = np.abs(u) <= u_max[np.abs(v)]
    return (u * disc).astype(np.float64), (v * disc).astype(np.float64)


def intensity_centroid_angles(level_image: np.ndarray, xy: np.ndarray, radius: int) -> np.ndarray:
    """Orientation (degrees, [0, 360)) of keypoints by the intensity centroid of a disc (ORB's IC_Angle).

    The keypoints must lie at least `radius` px inside the image (ORB-SLAM3's always do).
    """
    if len(xy) == 0:
        return np.zeros(0, np.float32)
    kernel_u, kernel_v = _moment_kernels(radius)
    corner = np.floor(xy + 0.5).astype(np.int64) - radius
    windows = np.lib.stride_tricks.sliding_window_view(level_image, (2 * radius + 1, 2 * radius + 1))
    patches = windows[corner[:, 1], corner[:, 0]].astype(np.float64)
    m_10 = np.einsum("kij,ij->k", patches, kernel_u)
    m_01 = np.einsum("kij,ij->k", patches, kernel_v)
    return (np.degrees(np.arctan2(m_01, m_10)) % 360.0).astype(np.float32)


def extract_orb_orbslam3(image: np.ndarray, settings: OrbSettings = OrbSettings()) -> Features:
    """ORB features selected as ORB-SLAM3's ORBextractor does, described by OpenCV's ORB.

    Per pyramid level (image_pyramid): FAST 20 per ~35 px cell with a FAST 7 retry in empty cells
    (fast_in_cells), the quadtree spread to mnFeaturesPerLevel (distribute_quadtree), the intensity
    centroid orientation (intensity_centroid_angles). Descriptors come from cv2.ORB.compute on the
    level-0 image with these keypoints (octave, angle, size PATCH_SIZE scale given; OpenCV builds its
    own pyramid and Gaussian-smooths each level 7 x 7, sigma 2, as ORB-SLAM3 does). Keypoints OpenCV
    cannot describe (too close to a border after rounding) are dropped and not counted.
    """
    pyramid = image_pyramid(image, settings)
    wanted = settings.features_per_level()
    lo = settings.edge_threshold - 3
    keypoints = []
    for level, level_image in enumerate(pyramid):
        height, width = level_image.shape
        xy, response = fast_in_cells(level_image, settings)
        extent = (width - settings.edge_threshold + 3 - lo, height - settings.edge_threshold + 3 - lo)
        keep = distribute_quadtree(xy, response, extent[0], extent[1], wanted[level])
        if len(keep) == 0:
            continue
        level_xy = xy[keep] + lo
        angles = intensity_centroid_angles(level_image, level_xy, settings.patch_size // 2)
        scale = settings.scale_factor**level
        size = settings.patch_size * scale
        for (x, y), angle, score in zip(level_xy, angles, response[keep], strict=True):
            keypoints.append(
                cv2.KeyPoint(float(x * scale), float(y * scale), size, float(angle), float(score), level)
            )
    if not keypoints:
        return _as_features([], None)
    described, descriptors = settings.detector(settings.ini_th_fast, settings.n_features).compute(
        image, keypoints
    )
    return _as_features(described, descriptors)


# OpenCV ORB with a second pass ----------------------------------------------------------------------


def fallback_cells(image_size: tuple[int, int], settings: OrbSettings) -> tuple[np.ndarray, np.ndarray]:
    """Level-0 cell edges (x_edges, y_edges) of ORB-SLAM3's FAST cells, for extract_orb_opencv.

    The region [EDGE_THRESHOLD - 3, size - EDGE_THRESHOLD + 3] is cut into floor(extent / W) cells of
    ceil(extent / n) px per axis (W = 35); at least one cell, so that tiny images still get one.
    """
    edges = []
    for size in image_size:
        lo = settings.edge_threshold - 3
        hi = max(lo + 1, size - settings.edge_threshold + 3)
        extent = hi - lo
        n = max(1, extent // settings.cell_size)
        step = math.ceil(extent / n)
        edges.append(np.minimum(lo + step * np.arange(n + 1), hi))
    return edges[0], edges[1]


def extract_orb_opencv(image: np.ndarray, settings: OrbSettings = OrbSettings()) -> Features:
    """cv2.ORB_create with ORB-SLAM3's settings, plus a FAST-7 pass over the cells it left empty.

    Pass 1: cv2.ORB with FAST threshold ini_th_fast over the whole image (n_features wanted; OpenCV
    keeps the best Harris scores per level, so keypoints crowd on strong texture). Pass 2 (fallback
    and pass 1 short of n_features): cv2.ORB with min_th_fast, masked to the level-0 cells
    (fallback_cells) holding no pass-1 keypoint, for the remaining n_features - n1.
    """
    keypoints, descriptors = settings.detector(settings.ini_th_fast, settings.n_features).detectAndCompute(
        image, None
    )
    first = _as_features(keypoints, descriptors)
    budget = settings.n_features - len(first.xy)
    if not settings.fallback or budget <= 0:
        return first
    x_edges, y_edges = fallback_cells((image.shape[1], image.shape[0]), settings)
    col = np.searchsorted(x_edges, first.xy[:, 0], side="right") - 1
    row = np.searchsorted(y_edges, first.xy[:, 1], side="right") - 1
    occupied = np.zeros((len(y_edges) - 1, len(x_edges) - 1), bool)
    inside = (col >= 0) & (col < occupied.shape[1]) & (row >= 0) & (row < occupied.shape[0])
    occupied[row[inside], col[inside]] = True
    if occupied.all():
        return first
    mask = np.zeros(image.shape, np.uint8)
    for r, c in np.argwhere(~occupied):
        mask[y_edges[r] : y_edges[r + 1], x_edges[c] : x_edges[c + 1]] = 255
    keypoints, descriptors = settings.detector(settings.min_th_fast, budget).detectAndCompute(image, mask)
    second = _as_features(keypoints, descriptors)
    if len(second.xy) == 0:
        return first
    return Features(
        np.concatenate([first.xy, second.xy]),
        np.concatenate([first.descriptors, second.descriptors]),
        np.concatenate([first.octave, second.octave]),
    )


def _round_half_away(values: np.ndarray) -> np.ndarray:
    """C's round(): halves away from zero (np.rint rounds them to even)."""
    return (np.sign(values) * np.floor(np.abs(values) + 0.5)).astype(np.int64)


def sve_bins(grid_xy: np.ndarray, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """Keypoints per SVE bin (64,), row-major (k = 8 bin_y + bin_x).

    ORB-SLAM3's Frame::PosInGrid: col = round((x - min_x) 64 / (max_x - min_x)), row likewise with 48;
    keypoints with col outside [0, 64) or row outside [0, 48) are in no cell (they still count in N).
    SVE bins the grid 8 x 8: bin x = col // 8, bin y = row // 6.
    """
    min_x, max_x, min_y, max_y = bounds
    xy = np.asarray(grid_xy, np.float64).reshape(-1, 2)
    col = _round_half_away((xy[:, 0] - min_x) * (GRID_COLS / (max_x - min_x)))
    row = _round_half_away((xy[:, 1] - min_y) * (GRID_ROWS / (max_y - min_y)))
    valid = (col >= 0) & (col < GRID_COLS) & (row >= 0) & (row < GRID_ROWS)
    bin_index = (row[valid] // (GRID_ROWS // SVE_BINS_Y)) * SVE_BINS_X + col[valid] // (
        GRID_COLS // SVE_BINS_X
    )
    return np.bincount(bin_index, minlength=N_BINS).astype(np.int64)


# --------------------------------------------------------------------------------------------------
# Matching, verification, frustum
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MatchSettings:
    """Frame-to-frame matching and geometric verification.

    Attributes:
        max_distance: largest Hamming distance of a match (ORB-SLAM3's ORBmatcher::TH_HIGH = 100).
        ratio: Lowe ratio best / second best. ORB-SLAM3 uses 0.9 inside a small projection window; over
            the whole image the candidates are many more, so the stricter 0.8 (Lowe 2004).
        epipolar_threshold_px: RANSAC inlier threshold, the distance to the epipolar line (px):
            sqrt(3.841), ORB-SLAM3's chi-square 95 % bound for one degree of freedom at unit sigma
            (TwoViewReconstruction::CheckFundamental).
        confidence: RANSAC confidence.
        min_matches: fewer matches than this give no verification (n_inliers = 0): a minimal set of 5
            would always be "consistent".
        homography_threshold_px: RANSAC threshold of the homography used for the frustum count.
    """

    max_distance: int = 100
    ratio: float = 0.8
    epipolar_threshold_px: float = math.sqrt(3.841)
    confidence: float = 0.999
    min_matches: int = 8
    homography_threshold_px: float = 3.0


def match_descriptors(
    previous: np.ndarray, current: np.ndarray, settings: MatchSettings = MatchSettings()
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_previous, i_current) of accepted matches of the previous frame's descriptors.

    Each previous descriptor takes its nearest current descriptor (Hamming) if within max_distance
    and passing the ratio test; a current keypoint claimed twice keeps its closest match only.
    """
    empty = np.zeros(0, np.int64)
    if len(previous) == 0 or len(current) == 0:
        return empty, empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(previous, current, k=2)
    best: dict[int, tuple[float, int]] = {}
    for candidates in pairs:
        if not candidates:
            continue
        first = candidates[0]
        if first.distance > settings.max_distance:
            continue
        if len(candidates) > 1 and first.distance >= settings.ratio * candidates[1].distance:
            continue
        claimed = best.get(first.trainIdx)
        if claimed is None or first.distance < claimed[0]:
            best[first.trainIdx] = (first.distance, first.queryIdx)
    if not best:
        return empty, empty
    i_current = np.fromiter(best.keys(), np.int64, len(best))
    i_previous = np.fromiter((v[1] for v in best.values()), np.int64, len(best))
    order = np.argsort(i_previous, kind="stable")
    return i_previous[order], i_current[order]


def verify_matches(
    previous_xy: np.ndarray, current_xy: np.ndarray, camera: Camera, settings: MatchSettings = MatchSettings()
) -> np.ndarray:
    """Inlier mask (M,) of matched undistorted points under an essential matrix found by RANSAC.

    cv2.findEssentialMat with the camera's K; all False when fewer than settings.min_matches matches
    or no model is found.
    """
    n = len(previous_xy)
    if n < settings.min_matches:
        return np.zeros(n, bool)
    _, mask = cv2.findEssentialMat(
        np.asarray(previous_xy, np.float64),
        np.asarray(current_xy, np.float64),
        camera.matrix,
        method=cv2.RANSAC,
        prob=settings.confidence,
        threshold=settings.epipolar_threshold_px,
    )
    if mask is None:
        return np.zeros(n, bool)
    return mask.ravel().astype(bool)


def count_in_frustum(
    previous_xy: np.ndarray,
    inlier_previous: np.ndarray,
    inlier_current: np.ndarray,
    bounds: tuple[float, float, float, float],
    settings: MatchSettings = MatchSettings(),
) -> int:
    """Previous-frame keypoints (undistorted px) expected inside the current image: the N_frustum stand-in.

    They are mapped by a homography fitted (RANSAC) to the verified matches, or kept in place when
    there are fewer than settings.min_matches of them or the fit fails, and counted when inside
    [min_x, max_x] x [min_y, max_y] (the test of ORB-SLAM3's Frame::isInFrustum).
    """
    points = np.asarray(previous_xy, np.float64).reshape(-1, 2)
    if len(points) == 0:
        return 0
    homography = None
    if len(inlier_previous) >= settings.min_matches:
        homography, _ = cv2.findHomography(
            np.asarray(inlier_previous, np.float64),
            np.asarray(inlier_current, np.float64),
            cv2.RANSAC,
            settings.homography_threshold_px,
        )
    if homography is not None and np.all(np.isfinite(homography)):
        projected = cv2.perspectiveTransform(points.reshape(-1, 1, 2), homography).reshape(-1, 2)
    else:
        projected = points
    min_x, max_x, min_y, max_y = bounds
    inside = (
        (projected[:, 0] >= min_x)
        & (projected[:, 0] <= max_x)
        & (projected[:, 1] >= min_y)
        & (projected[:, 1] <= max_y)
    )
    return int(np.count_nonzero(inside))


# --------------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameCounts:
    """Per-frame counts of a sequence (T frames): the image side of the tracking log.

    Attributes:
        n_extracted: keypoints extracted (T,).
        n_inliers: geometrically verified matches to the previous frame (T,); 0 on the first frame.
        n_frustum: previous-frame keypoints expected in view (T,); 0 on the first frame.
        bins: keypoints per SVE bin (T, 64).
    """

    n_extracted: np.ndarray
    n_inliers: np.ndarray
    n_frustum: np.ndarray
    bins: np.ndarray = field(repr=False)


def measure_frames(
    images: Iterable[np.ndarray],
    camera: Camera,
    orb: OrbSettings = OrbSettings(),
    match: MatchSettings = MatchSettings(),
) -> FrameCounts:
    """Counts for a sequence of grey images from one camera, each matched to the one before it.

    Arguments:
        images: 8-bit grey images of camera.width x camera.height, in time order.
        camera: calibration (K and distortion for undistortion and the grid bounds).
        orb, match: extraction and matching settings.
    """
    bounds = camera.bounds()
    rows = []
    previous: tuple[Features, np.ndarray] | None = None
    for index, image in enumerate(images):
        if image.shape != (camera.height, camera.width):
            raise ValueError(
                f"frame {index} is {image.shape[1]} x {image.shape[0]} but the calibration is for "
                f"{camera.width} x {camera.height}"
            )
        features = extract_orb(image, orb)
        undistorted = camera.undistort(features.xy)
        bins = sve_bins(features.xy if camera.distortion_model == "equidistant" else undistorted, bounds)
        n_inliers = n_frustum = 0
        if previous is not None:
            prev_features, prev_undistorted = previous
            i_prev, i_cur = match_descriptors(prev_features.descriptors, features.descriptors, match)
            inliers = verify_matches(prev_undistorted[i_prev], undistorted[i_cur], camera, match)
            n_inliers = int(np.count_nonzero(inliers))
            n_frustum = count_in_frustum(
                prev_undistorted,
                prev_undistorted[i_prev][inliers],
                undistorted[i_cur][inliers],
                bounds,
                match,
            )
        rows.append((len(features.xy), n_inliers, n_frustum, bins))
        previous = (features, undistorted)
    if not rows:
        raise ValueError("no frames to measure")
    return FrameCounts(
        np.array([r[0] for r in rows], np.int64),
        np.array([r[1] for r in rows], np.int64),
        np.array([r[2] for r in rows], np.int64),
        np.stack([r[3] for r in rows]),
    )


def visibility_table(t_ns: Sequence[int], counts: FrameCounts, n_features: int = 1000) -> pd.DataFrame:
    """One row per frame: t_ns, the counts, bin_0..bin_63 and every SVE metric of jsve.sve.sve_table."""
    from .sve import sve_table

    t_ns = np.asarray(t_ns, np.int64)
    if len(t_ns) != len(counts.n_extracted):
        raise ValueError(f"t_ns has {len(t_ns)} frames but the counts have {len(counts.n_extracted)}")
    table = pd.DataFrame(
        {
            "t_ns": t_ns,
            "n_extracted": counts.n_extracted,
            "n_inliers": counts.n_inliers,
            "n_frustum": counts.n_frustum,
        }
    )
    bins = pd.DataFrame(counts.bins, columns=list(BIN_COLUMNS))
    metrics = sve_table(counts.n_extracted, counts.n_inliers, counts.n_frustum, counts.bins, n_features)
    metrics = pd.DataFrame({k: np.asarray(v, np.float64) for k, v in metrics.items()})
    return pd.concat([table, bins, metrics], axis=1)


@dataclass(frozen=True)
class CameraSequence:
    """The frames of one camera of a EuRoC dataset: timestamps, image paths and calibration."""

    t_ns: np.ndarray
    paths: tuple[Path, ...]
    camera: Camera


def read_sequence(dataset: Path | str, camera: str = "cam0", stride: int = 1) -> CameraSequence:
    """Frames listed in mav0/<camera>/data.csv (every stride-th) and the camera of its sensor.yaml."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1; got {stride}")
    cam_dir = Path(dataset) / "mav0" / camera
    if cam_dir not in camera_dirs(Path(dataset)):
        raise DatasetError(f"{cam_dir}: no such camera folder with data/ and data.csv")
    frames = read_frame_list(cam_dir)[::stride]
    if not frames:
        raise DatasetError(f"{cam_dir / 'data.csv'}: no frames")
    return CameraSequence(
        np.array([t for t, _ in frames], np.int64),
        tuple(cam_dir / "data" / name for _, name in frames),
        Camera.from_sensor_yaml(cam_dir / "sensor.yaml"),
    )


def read_image(path: Path) -> np.ndarray:
    """An 8-bit grey image from disk (colour converted to grey)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: cannot read image")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise DatasetError(f"{path}: expected an 8-bit image, got {image.dtype}")
    return image


def measure_counts(
    dataset: Path | str,
    camera: str = "cam0",
    stride: int = 1,
    orb: OrbSettings = OrbSettings(),
    match: MatchSettings = MatchSettings(),
) -> tuple[np.ndarray, FrameCounts]:
    """(t_ns, FrameCounts) of one camera of a EuRoC dataset; OpenCV only (no JAX), for worker processes."""
    sequence = read_sequence(dataset, camera, stride)
    counts = measure_frames((read_image(p) for p in sequence.paths), sequence.camera, orb, match)
    return sequence.t_ns, counts


def measure_dataset(
    dataset: Path | str,
    camera: str = "cam0",
    stride: int = 1,
    orb: OrbSettings = OrbSettings(),
    match: MatchSettings = MatchSettings(),
) -> pd.DataFrame:
    """The visibility table (visibility_table) of one camera of a EuRoC dataset."""
    t_ns, counts = measure_counts(dataset, camera, stride, orb, match)
    return visibility_table(t_ns, counts, orb.n_features)


def find_datasets(root: Path | str) -> list[Path]:
    """EuRoC datasets at or below `root` (folders holding mav0/), sorted; `.partial` folders skipped."""
    root = Path(root)
    if (root / "mav0").is_dir():
        return [root]
    found = []
    for mav0 in sorted(root.rglob("mav0")):
        dataset = mav0.parent
        if mav0.is_dir() and not any(part.endswith(".partial") for part in dataset.relative_to(root).parts):
            found.append(dataset)
    return found


@dataclass(frozen=True)
class _CountJob:
    dataset: Path
    camera: str
    stride: int
    orb: OrbSettings
    match: MatchSettings


def _count_job(job: _CountJob) -> tuple[np.ndarray, FrameCounts]:
    return measure_counts(job.dataset, job.camera, job.stride, job.orb, job.match)


TABLE_FORMATS = ("csv", "parquet")


def write_table(table: pd.DataFrame, path: Path) -> None:
    """Write a table as CSV or Parquet (by suffix) atomically: a temporary file renamed into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    if path.suffix == ".parquet":
        table.to_parquet(tmp, index=False)
    else:
        table.to_csv(tmp, index=False)
    os.replace(tmp, path)


def measure_datasets(
    roots: Sequence[Path | str],
    out_dir: Path | str,
    *,
    table_format: str = "csv",
    camera: str = "cam0",
    stride: int = 1,
    orb: OrbSettings = OrbSettings(),
    match: MatchSettings = MatchSettings(),
    workers: int = 1,
    overwrite: bool = False,
    progress: bool = True,
) -> list[Path]:
    """Measure every dataset found under `roots` in parallel and write one table per dataset.

    A dataset at `root/a/b` gets `out_dir/<root name>/a/b.<format>` (`out_dir/<root name>.<format>`
    when the root is itself a dataset). Existing tables are kept unless overwrite=True, so a batch can
    be resumed. Image work runs in `workers` processes with a tqdm bar; the SVE metrics are computed
    for all frames here, in this process.

    Returns:
        The table paths, one per dataset found, in order.
    """
    if table_format not in TABLE_FORMATS:
        raise ValueError(f"table_format must be one of {TABLE_FORMATS}; got {table_format!r}")
    targets: list[tuple[Path, Path]] = []
    for root in roots:
        root = Path(root)
        datasets = find_datasets(root)
        if not datasets:
            raise DatasetError(f"{root}: no EuRoC dataset (folder with mav0/) found")
        for dataset in datasets:
            rel = Path(root.name) / dataset.relative_to(root) if dataset != root else Path(root.name)
            targets.append((dataset, Path(out_dir) / rel.with_name(rel.name + "." + table_format)))
    todo = [(d, t) for d, t in targets if overwrite or not t.exists()]
    jobs = [_CountJob(d, camera, stride, orb, match) for d, _ in todo]
    results = run_parallel(_count_job, jobs, workers, progress, "measure")
    for (_, target), (t_ns, counts) in zip(todo, results, strict=True):
        write_table(visibility_table(t_ns, counts, orb.n_features), target)
    return [t for _, t in targets]
