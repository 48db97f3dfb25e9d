"""ORB features of one frame, selected as ORB-SLAM3 v1.0's ORBextractor does (an I/O edge of jsve, OpenCV).

`extract_orb(image, OrbSettings())` gives the keypoints and descriptors that jsve.image._measure matches,
bins and counts, with one of two extractors (OrbSettings.extractor):

- "orbslam3" (default, extract_orb_orbslam3): ORBextractor's keypoint selection re-implemented with
  OpenCV primitives, level by level: FAST per ~35 px cell with a FAST 7 retry in empty cells
  (fast_in_cells), the quadtree spread (distribute_quadtree), the intensity-centroid orientation
  (intensity_centroid_angles); descriptors from cv2.ORB.
- "opencv" (extract_orb_opencv). ORB-SLAM3's ORBextractor runs FAST with iniThFAST = 20 in cells of
  about 35 x 35 px of every pyramid level, retries a cell with minThFAST = 7 when it yields nothing,
  and spreads the survivors with a quadtree. OpenCV's ORB runs FAST over whole levels and keeps the
  best Harris scores. This extractor approximates the per-cell fallback with two OpenCV passes: first
  cv2.ORB with FAST 20 over the image; then, if it returned fewer than nFeatures, a second cv2.ORB
  with FAST 7, masked to the level-0 35-px cells (ORB-SLAM3's grid over the region inside
  EDGE_THRESHOLD - 3) in which the first pass kept no keypoint, asked for the remaining budget
  nFeatures - n1. Differences: cells are level-0 cells for all levels (ORB-SLAM3's grow with the
  level); a cell counts as empty after the first pass's Harris selection, not before; and the second
  pass never displaces a FAST-20 keypoint (ORB-SLAM3's quadtree may).

EDGE_THRESHOLD = 19 and PATCH_SIZE = 31 are ORB-SLAM3's.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

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
