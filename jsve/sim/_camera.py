"""Simulator, camera side: the EuRoC camera model and where its pixels fall among the 64 SVE bins
(ORB-SLAM3's undistorted 64 x 48 keypoint grid, 8 x 8 cells a bin). Part of the stand-in front-end
(docs/simulator.md); the vision model (jsve.sim._vision) counts keypoints per bin through it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from jsve.core._numerics import round_half_away

GRID_COLS, GRID_ROWS = 64, 48
ORB_BORDER = 16
"""Keypoints lie at least EDGE_THRESHOLD - 3 = 16 px from the image border (ORBextractor)."""

DETECTABLE_AREA_PX = (752 - 2 * ORB_BORDER) * (480 - 2 * ORB_BORDER)
"""px^2 of a EuRoC frame where ORB-SLAM3 detects keypoints (inside ORB_BORDER)."""


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
    col = round_half_away((und[:, 0] - min_x) * GRID_COLS / (max_x - min_x), xp=np).astype(np.int64)
    row = round_half_away((und[:, 1] - min_y) * GRID_ROWS / (max_y - min_y), xp=np).astype(np.int64)
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
