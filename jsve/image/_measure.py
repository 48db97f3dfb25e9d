"""Scene visibility measured on real frames: the image side of SVE, with OpenCV (an I/O edge of jsve).

For every frame of a EuRoC camera folder this module extracts ORB features with ORB-SLAM3's EuRoC
settings, matches them to the previous frame, verifies the matches geometrically, bins the keypoints
into SVE's 8 x 8 bins and counts the previous frame's keypoints expected in view. The per-frame counts
(n_extracted, n_inliers, n_frustum, bin_0..bin_63) are those of the tracking log (jsve.io._schema), and
the SVE metrics follow from them through jsve.core._sve.sve_table. Stand-ins for what only a running
ORB-SLAM3 knows are documented where they are made, and in docs/disturbances.md:

- Extraction: jsve.image._orb (ORB-SLAM3's ORBextractor keypoint selection, or cv2.ORB with a second pass).
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

import json
import logging
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from jsve.core._numerics import round_half_away
from jsve.image._datasets import (
    DatasetError,
    camera_dirs,
    content_hash,
    read_frame_list,
    read_yaml_list,
    run_parallel,
)
from jsve.image._orb import EXTRACTORS as EXTRACTORS
from jsve.image._orb import Features as Features
from jsve.image._orb import OrbSettings as OrbSettings
from jsve.image._orb import distribute_quadtree as distribute_quadtree
from jsve.image._orb import extract_orb as extract_orb
from jsve.image._orb import extract_orb_opencv as extract_orb_opencv
from jsve.image._orb import extract_orb_orbslam3 as extract_orb_orbslam3
from jsve.image._orb import fallback_cells as fallback_cells
from jsve.image._orb import fast_in_cells as fast_in_cells
from jsve.image._orb import image_pyramid as image_pyramid
from jsve.image._orb import intensity_centroid_angles as intensity_centroid_angles
from jsve.io import _atomic as atomic
from jsve.io._resume import differences, stop_if_stale
from jsve.io._schema import BIN_COLUMNS, N_BINS

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
# SVE bins
# --------------------------------------------------------------------------------------------------


def sve_bins(grid_xy: np.ndarray, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """Keypoints per SVE bin (64,), row-major (k = 8 bin_y + bin_x).

    ORB-SLAM3's Frame::PosInGrid: col = round((x - min_x) 64 / (max_x - min_x)), row likewise with 48;
    keypoints with col outside [0, 64) or row outside [0, 48) are in no cell (they still count in N).
    SVE bins the grid 8 x 8: bin x = col // 8, bin y = row // 6.
    """
    min_x, max_x, min_y, max_y = bounds
    xy = np.asarray(grid_xy, np.float64).reshape(-1, 2)
    col = round_half_away((xy[:, 0] - min_x) * (GRID_COLS / (max_x - min_x)), xp=np).astype(np.int64)
    row = round_half_away((xy[:, 1] - min_y) * (GRID_ROWS / (max_y - min_y)), xp=np).astype(np.int64)
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
    """One row per frame: t_ns, the counts, bin_0..bin_63 and every SVE metric of jsve.core._sve.sve_table."""
    from jsve.core._sve import sve_table

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

KEY_SUFFIX = ".key.json"
"""A table's key file is the table's name with this suffix (`V1_01.csv.key.json`), written after it."""

KEY_VERSION = 1


def write_table(table: pd.DataFrame, path: Path) -> None:
    """Write a table as CSV or Parquet (by suffix) atomically: a temporary file renamed into place."""
    atomic.write_table(table, path)


def key_path(table: Path) -> Path:
    """Where the key of the table at `table` is recorded."""
    return table.with_name(table.name + KEY_SUFFIX)


def measure_key(
    dataset: Path | str,
    camera: str = "cam0",
    stride: int = 1,
    orb: OrbSettings = OrbSettings(),
    match: MatchSettings = MatchSettings(),
) -> dict:
    """What a visibility table is a function of: the dataset (resolved path, and the content hash of
    the camera folder the table reads: every frame's bytes, data.csv and sensor.yaml), the camera, the
    stride and every extraction and matching setting. Recorded next to the table (key_path); a finished
    table is kept only under an equal key.

    Raises:
        DatasetError: the dataset has no such camera folder.
    """
    cam_dir = Path(dataset) / "mav0" / camera
    if cam_dir not in camera_dirs(Path(dataset)):
        raise DatasetError(f"{cam_dir}: no such camera folder with data/ and data.csv")
    key = {
        "source": str(Path(dataset).resolve()),
        "camera_hash": content_hash(cam_dir)[0],
        "camera": camera,
        "stride": stride,
        "orb": asdict(orb),
        "match": asdict(match),
    }
    return json.loads(json.dumps(key))  # as the key file reads back (tuples as lists)


def _stale(table: Path, key: dict) -> str | None:
    """What differs between a finished table's recorded key and `key`, or None when they are equal."""
    path = key_path(table)
    try:
        recorded = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return f"{path.name} is missing (a table of an older jsve or an interrupted write)"
    except (OSError, ValueError) as error:
        return f"{path.name} cannot be read ({error})"
    if not isinstance(recorded, dict):
        return f"{path.name} holds no key"
    recorded = {k: recorded[k] for k in key if k in recorded}
    return None if recorded == key else differences(recorded, key)


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
    force: bool = False,
    progress: bool = True,
) -> list[Path]:
    """Measure every dataset found under `roots` in parallel and write one table per dataset.

    A dataset at `root/a/b` gets `out_dir/<root name>/a/b.<format>` (`out_dir/<root name>.<format>`
    when the root is itself a dataset), and its key (measure_key: the dataset's path and camera content,
    the camera, stride and settings) in `<table>.key.json`, written after the table. A batch resumes:
    a table whose recorded key equals its job's is kept; a table of another key (or without one) stops
    the call with StaleOutputError before anything is written, unless force=True (those tables are
    measured again). overwrite=True measures every dataset again. Image work runs in `workers`
    processes with a tqdm bar; the SVE metrics are computed for all frames here, in this process.

    Returns:
        The table paths, one per dataset found, in order.

    Raises:
        StaleOutputError: a table of another key (and force is False).
        DatasetError: a root holds no dataset, or a dataset cannot be read.
        OutputError: a table cannot be written.
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
    keys = [measure_key(dataset, camera, stride, orb, match) for dataset, _ in targets]
    # Every finished table is checked before any is written: a folder never mixes two keys.
    stale = [
        (target, what)
        for (_, target), key in zip(targets, keys, strict=True)
        if target.exists() and not overwrite and (what := _stale(target, key))
    ]
    if not force:
        stop_if_stale(out_dir, stale, "tables measured under another key")
    redo = {target for target, _ in stale}
    todo = [
        (dataset, target, key)
        for (dataset, target), key in zip(targets, keys, strict=True)
        if overwrite or target in redo or not target.exists()
    ]
    if todo:
        atomic.check_writable(out_dir)
    jobs = [_CountJob(dataset, camera, stride, orb, match) for dataset, _, _ in todo]
    results = run_parallel(_count_job, jobs, workers, progress, "measure")
    for (_, target, key), (t_ns, counts) in zip(todo, results, strict=True):
        key_path(target).unlink(missing_ok=True)  # a table without its key is never taken as finished
        write_table(visibility_table(t_ns, counts, orb.n_features), target)
        atomic.write_json(key_path(target), {"jsve_measure": KEY_VERSION, **key})
    return [t for _, t in targets]
