"""One camera frame of a Scene: ray casting per pixel, mip-mapped texture, and what makes real footage hard.

    CameraRays.of(camera)            unit ray and angular footprint of every pixel, once per camera
    SensorModel                      exposure, motion blur sub-samples, vignetting, gain, noise, optics blur
    render_frame(scene, rays, poses, gain, rng, sensor)   an 8-bit grey frame

The rays are those of the distorted pixels (the radial-tangential model inverted at every pixel centre,
iterated to convergence), so the image is rendered directly with the lens distortion ORB-SLAM3 undoes.
Casting is plain numpy, vectorised over pixels: the room is one box seen from inside (the exit distance of
three slabs), every piece of furniture a box tested only on the pixels of its projected bounding
rectangle (the pinhole projection of its corners bounds it in undistorted coordinates; the distorted
window is the bounding box of that rectangle's distorted outline). visible_surfaces casts one pixel per
CELL x CELL cell and the full cells only where a projected box edge may cross (the same surfaces as cast,
at about a fifth of the pixels). The texture is sampled with cv2.remap from the two mip levels around each
pixel's footprint (trilinear filtering), both levels in one call on the side-by-side levels of Scene.mip:
the footprint is the pixel's angular size times the distance over the square root of the incidence cosine
(between the isotropic footprints along and across the slant), in texels.

Exposure motion blur averages `subframes` renders at poses spread over the exposure; then vignetting
(a cos^4-like falloff), the frame's gain (auto-exposure), a Gaussian optics blur and Poisson-Gaussian
sensor noise, and 8-bit quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jsve.image import Camera
from jsve.render._scene import MIP_LEVELS, Scene

EUROC_CAM0 = Camera(
    width=752,
    height=480,
    fx=458.654,
    fy=457.296,
    cx=367.215,
    cy=248.375,
    distortion_model="radial-tangential",
    distortion=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
)
"""EuRoC cam0 as ORB-SLAM3 v1.0's Examples/Monocular-Inertial/EuRoC.yaml gives it (Camera1.*), radtan."""


@dataclass(frozen=True)
class CameraRays:
    """Per-pixel rays of a camera, in the camera frame (x right, y down, z forward).

    Attributes:
        camera: the model. xn, yn: [H, W] float32 undistorted normalised coordinates of each pixel.
        rays: [3, H W] float32 unit directions. footprint: [H W] float32 angular size of a pixel, rad.
        x_range, y_range: smallest and largest xn and yn.
    """

    camera: Camera
    xn: np.ndarray
    yn: np.ndarray
    rays: np.ndarray
    footprint: np.ndarray
    x_range: tuple[float, float]
    y_range: tuple[float, float]

    @classmethod
    def of(cls, camera: Camera = EUROC_CAM0) -> CameraRays:
        w, h = camera.width, camera.height
        px, py = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        # OpenCV's undistortPoints stops after 5 fixed-point iterations, up to 0.3 px off at EuRoC's corners:
        # iterate on to convergence (the same fixed point, from its result).
        und = camera.undistort(np.stack([px.ravel(), py.ravel()], -1))
        x, y = (und[:, 0] - camera.cx) / camera.fx, (und[:, 1] - camera.cy) / camera.fy
        xd, yd = (px.ravel() - camera.cx) / camera.fx, (py.ravel() - camera.cy) / camera.fy
        k1, k2, p1, p2 = camera.distortion[:4]
        for _ in range(100):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        und = np.stack([x, y], -1)
        xn, yn = und[:, 0].reshape(h, w), und[:, 1].reshape(h, w)
        d = np.stack([xn, yn, np.ones_like(xn)], 0)
        d /= np.linalg.norm(d, axis=0, keepdims=True)
        # Angular size: the geometric mean of the angles to the next pixel across and down.
        ax = np.arccos(np.clip(np.sum(d[:, :, 1:] * d[:, :, :-1], 0), -1, 1))
        ay = np.arccos(np.clip(np.sum(d[:, 1:] * d[:, :-1], 0), -1, 1))
        ax = np.concatenate([ax, ax[:, -1:]], 1)
        ay = np.concatenate([ay, ay[-1:]], 0)
        return cls(
            camera=camera,
            xn=xn.astype(np.float32),
            yn=yn.astype(np.float32),
            rays=d.reshape(3, -1).astype(np.float32),
            footprint=np.sqrt(ax * ay).ravel().astype(np.float32),
            x_range=(float(xn.min()), float(xn.max())),
            y_range=(float(yn.min()), float(yn.max())),
        )

    def distort(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates of undistorted normalised coordinates (radial-tangential, OpenCV's model)."""
        k1, k2, p1, p2 = self.camera.distortion[:4]
        r2 = xn * xn + yn * yn
        radial = 1 + k1 * r2 + k2 * r2 * r2
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd * self.camera.fx + self.camera.cx, yd * self.camera.fy + self.camera.cy


@dataclass(frozen=True)
class SensorModel:
    """The camera's image formation beyond geometry.

    Attributes:
        exposure_s: exposure time, s (the frame's stamp is its middle).
        subframe_px: image motion between the sub-exposures averaged over it, px (their number follows the
            motion: 1 for a still camera, odd, at most max_subframes).
        vignetting: brightness lost at the image corners (0.35: corners at 65 %).
        read_noise: Gaussian noise, grey levels (sigma). shot_noise: variance per grey level (Poisson-like).
        optics_sigma: Gaussian blur of the lens, px (also antialiases silhouettes).
        brightness: grey level of a texel of level 128 on a face of shade 1 at gain 1.
    """

    exposure_s: float = 0.008
    subframe_px: float = 1.0
    max_subframes: int = 5
    vignetting: float = 0.35
    read_noise: float = 1.5
    shot_noise: float = 0.04
    optics_sigma: float = 0.6
    brightness: float = 128.0


def _nearest_of_three(t: np.ndarray, largest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(value, axis) of the smallest (or largest) of three rows [3, N], the first on ties; elementwise
    comparisons, much faster than a reduction over the short leading axis."""
    a, b, c = t
    if largest:
        ab = b > a
        best = np.where(ab, b, a)
        axis = np.where(c > best, 2, ab.astype(np.int32))
        return np.maximum(best, c), axis
    ab = b < a
    best = np.where(ab, b, a)
    axis = np.where(c < best, 2, ab.astype(np.int32))
    return np.minimum(best, c), axis


_NEAR = 0.05
"""Near plane, m: box corners closer than this to the camera plane are cut off there."""

# The 12 edges of a box, as pairs of indices into its 8 corners (corner i has coordinate bits i & 4, 2, 1).
_EDGES = np.array([(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit])
_CORNER_BITS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], bool)

CELL = 4
"""Side of the square cells, px, whose centre pixel is cast first (visible_surfaces)."""


def _camera_corners(r_cw: np.ndarray, p_cw: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """[B, 8, 3] corners of boxes (lo, hi [B, 3], world frame) in the camera frame, m."""
    corners = np.where(_CORNER_BITS[None], hi[:, None], lo[:, None])
    return corners @ r_cw.T + p_cw


def _box_windows(rays: CameraRays, corners: np.ndarray) -> np.ndarray:
    """[B, 4] pixel rows r0:r1 and columns c0:c1 that can see each box (empty, r0 = r1, where none can).

    A box's visible part (cut at the near plane) projects inside the bounding rectangle of its corners'
    (and cut points') pinhole projections; that rectangle, clipped to the image's undistorted extent, maps
    to the distorted image inside the bounding box of its distorted outline.

    Arguments:
        corners: [B, 8, 3] box corners in the camera frame (_camera_corners), m.
    """
    a, b = corners[:, _EDGES[:, 0]], corners[:, _EDGES[:, 1]]
    crossing = (a[..., 2] > _NEAR) != (b[..., 2] > _NEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crossing, (_NEAR - a[..., 2]) / (b[..., 2] - a[..., 2]), 0.0)
    points = np.concatenate([corners, a + s[..., None] * (b - a)], 1)
    valid = np.concatenate([corners[..., 2] > _NEAR, crossing], 1)
    z = np.where(valid, points[..., 2], 1.0)
    x, y = points[..., 0] / z, points[..., 1] / z
    x0 = np.maximum(np.where(valid, x, np.inf).min(1), rays.x_range[0])
    x1 = np.minimum(np.where(valid, x, -np.inf).max(1), rays.x_range[1])
    y0 = np.maximum(np.where(valid, y, np.inf).min(1), rays.y_range[0])
    y1 = np.minimum(np.where(valid, y, -np.inf).max(1), rays.y_range[1])
    seen = valid.any(1) & (x0 < x1) & (y0 < y1)
    x0, x1, y0, y1 = (np.where(seen, v, 0.0)[:, None] for v in (x0, x1, y0, y1))
    edge = np.linspace(0.0, 1.0, 24)
    bx = np.concatenate([x0 + (x1 - x0) * edge, np.broadcast_to(x1, (len(x1), 24)),
                         x1 - (x1 - x0) * edge, np.broadcast_to(x0, (len(x0), 24))], 1)  # fmt: skip
    by = np.concatenate([np.broadcast_to(y0, (len(y0), 24)), y0 + (y1 - y0) * edge,
                         np.broadcast_to(y1, (len(y1), 24)), y1 - (y1 - y0) * edge], 1)  # fmt: skip
    u, v = rays.distort(bx, by)
    h, w = rays.xn.shape
    c0 = np.clip(np.floor(u.min(1)) - 2, 0, w)
    c1 = np.clip(np.ceil(u.max(1)) + 3, 0, w)
    r0 = np.clip(np.floor(v.min(1)) - 2, 0, h)
    r1 = np.clip(np.ceil(v.max(1)) + 3, 0, h)
    seen &= (c0 < c1) & (r0 < r1)
    return np.where(seen[:, None], np.stack([r0, r1, c0, c1], 1), 0).astype(np.int64)


def _edge_cells(
    rays: CameraRays, corners: np.ndarray, shape: tuple[int, int], samples: int = 32
) -> np.ndarray:
    """[rows, cols] bool: the CELL x CELL cells that an edge of a box may cross in the image.

    Each edge is cut at the near plane, projected (a straight segment in undistorted coordinates), clipped
    to the image's undistorted extent, sampled and distorted, and drawn into the cell grid; the grid is then
    dilated by one cell, which covers the chords between samples and the lines' rasterisation.

    Arguments:
        corners: [B, 8, 3] box corners in the camera frame (_camera_corners), m. shape: the cell grid.
    """
    a = corners[:, _EDGES[:, 0]].reshape(-1, 3)
    b = corners[:, _EDGES[:, 1]].reshape(-1, 3)
    keep = (a[:, 2] > _NEAR) | (b[:, 2] > _NEAR)
    crossing = (a[:, 2] > _NEAR) != (b[:, 2] > _NEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(crossing, (_NEAR - a[:, 2]) / (b[:, 2] - a[:, 2]), 0.0)[:, None]
    a, b = np.where(a[:, 2:] > _NEAR, a, a + s * (b - a)), np.where(b[:, 2:] > _NEAR, b, a + s * (b - a))
    a, b = a[keep], b[keep]
    xa, ya = a[:, 0] / a[:, 2], a[:, 1] / a[:, 2]
    dx, dy = b[:, 0] / b[:, 2] - xa, b[:, 1] / b[:, 2] - ya
    # Liang-Barsky clipping to the undistorted extent, widened by about a pixel.
    margin = 1.0 / rays.camera.fx
    t0, t1 = np.zeros(len(a)), np.ones(len(a))
    inside = np.ones(len(a), bool)
    for p, q in ((-dx, xa - rays.x_range[0] + margin), (dx, rays.x_range[1] + margin - xa),
                 (-dy, ya - rays.y_range[0] + margin), (dy, rays.y_range[1] + margin - ya)):  # fmt: skip
        with np.errstate(divide="ignore", invalid="ignore"):
            r = q / p
        t0 = np.where(p < 0, np.maximum(t0, r), t0)
        t1 = np.where(p > 0, np.minimum(t1, r), t1)
        inside &= (p != 0) | (q >= 0)
    inside &= t0 <= t1
    tt = t0[inside, None] + (t1 - t0)[inside, None] * np.linspace(0.0, 1.0, samples)
    u, v = rays.distort(xa[inside, None] + dx[inside, None] * tt, ya[inside, None] + dy[inside, None] * tt)
    # Cell coordinates (cell i spans pixels CELL i to CELL i + CELL - 1), 4 fractional bits for cv2, in a
    # grid with a border of 2 cells: cv2 clips a line to the grid exactly, so a line half a cell outside
    # must still be drawn for the dilation to reach the cells it touches.
    pad = 2
    points = np.rint((np.stack([u, v], -1) - (CELL - 1) / 2) * (16 / CELL) + 16 * pad).astype(np.int32)
    mask = np.zeros((shape[0] + 2 * pad, shape[1] + 2 * pad), np.uint8)
    cv2.polylines(mask, list(points), False, 1, thickness=1, lineType=cv2.LINE_8, shift=4)
    return cv2.dilate(mask, np.ones((3, 3), np.uint8))[pad:-pad, pad:-pad].astype(bool)


def _rotate(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """r [3, 3] @ v [3, N] in float32, row by row: a BLAS call for so thin a product is several times
    slower (and starts threads)."""
    r = np.asarray(r, np.float32)
    return np.stack([r[i, 0] * v[0] + r[i, 1] * v[1] + r[i, 2] * v[2] for i in range(3)])


def _pick(rows: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """rows[axis[n], n] of a [3, N] array for axis in 0..2 (elementwise selects)."""
    return np.where(axis == 0, rows[0], np.where(axis == 1, rows[1], rows[2]))


def cast_pixels(
    scene: Scene,
    rays: CameraRays,
    index: np.ndarray,
    r_wc: np.ndarray,
    p_wc: np.ndarray,
    windows: np.ndarray | None = None,
):
    """Nearest surface along the rays of the given pixels.

    Arguments:
        index: [M] flat pixel indices (row W + column). r_wc: [3, 3] camera-to-world rotation. p_wc: [3]
            camera centre, m, world frame. windows: _box_windows of the furniture, when already known.
    Returns:
        (t [M] distance along the unit ray, m; surface [M] int32 6 box + face, the face 2 axis + side;
        d [3, M] world ray directions).
    """
    w = rays.xn.shape[1]
    d = _rotate(r_wc, rays.rays[:, index])
    with np.errstate(divide="ignore"):
        inv = np.float32(1.0) / d
    o = p_wc.astype(np.float32)
    # Room, from inside: per axis the distance to the wall the ray heads for; the nearest of the three.
    positive = d > 0
    far_wall = np.where(
        positive, scene.hi[0].astype(np.float32)[:, None], scene.lo[0].astype(np.float32)[:, None]
    )
    t, axis = _nearest_of_three((far_wall - o[:, None]) * inv)
    surface = (2 * axis + _pick(positive, axis)).astype(np.int32)
    if windows is None:
        r_cw = r_wc.T
        windows = _box_windows(rays, _camera_corners(r_cw, -r_cw @ p_wc, scene.lo[1:], scene.hi[1:]))
    cols = index % w
    ordered = len(index) < 2 or bool(np.all(index[1:] > index[:-1]))
    for b, (r0, r1, c0, c1) in enumerate(windows, 1):
        if r0 >= r1:
            continue
        # Increasing indices (row-major): the window's rows are one run of them.
        first, last = np.searchsorted(index, [r0 * w, r1 * w]) if ordered else (0, len(index))
        inside = (cols[first:last] >= c0) & (cols[first:last] < c1)
        if not ordered:
            rows = index // w
            inside &= (rows >= r0) & (rows < r1)
        sel = first + np.flatnonzero(inside)
        if not len(sel):
            continue
        iv = inv[:, sel]
        t_lo = (scene.lo[b].astype(np.float32) - o)[:, None] * iv
        t_hi = (scene.hi[b].astype(np.float32) - o)[:, None] * iv
        t_near, near_axis = _nearest_of_three(np.minimum(t_lo, t_hi), largest=True)
        far = np.maximum(t_lo, t_hi)
        t_far = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < t[sel])
        if not hit.any():
            continue
        # Seen from outside: the face on the side the ray comes from (the low one for a ray going up).
        side = _pick(iv[:, hit], near_axis[hit]) < 0
        t[sel[hit]] = t_near[hit]
        surface[sel[hit]] = 6 * b + 2 * near_axis[hit] + side
    return t, surface, d


def cast(scene: Scene, rays: CameraRays, r_wc: np.ndarray, p_wc: np.ndarray):
    """cast_pixels for every pixel: (t [H W], surface [H W], d [3, H W]); the reference visible_surfaces
    is tested against."""
    h, w = rays.xn.shape
    return cast_pixels(scene, rays, np.arange(h * w), r_wc, p_wc)


def visible_surfaces(scene: Scene, rays: CameraRays, r_wc: np.ndarray, p_wc: np.ndarray) -> np.ndarray:
    """The surface (6 box + face) every pixel sees, [H W] int32: cast's surfaces, cast at a fraction of
    the pixels.

    One pixel per CELL x CELL cell is cast; a cell keeps its pixel's surface unless the projection of a
    box edge may cross it (_edge_cells) or a neighbouring cell saw another surface, and then all its pixels
    are cast. Inside a cell no edge crosses, every pixel sees the same face (faces change only across
    projected edges), so thin furniture (a leg, a shelf board seen edge-on) is found however small.
    """
    h, w = rays.xn.shape
    r_cw = r_wc.T
    corners = _camera_corners(r_cw, -r_cw @ p_wc, scene.lo, scene.hi)
    windows = _box_windows(rays, corners[1:])
    rows, cols = -(-h // CELL), -(-w // CELL)
    centre_r = np.minimum(np.arange(rows) * CELL + CELL // 2, h - 1)
    centre_c = np.minimum(np.arange(cols) * CELL + CELL // 2, w - 1)
    _, cells, _ = cast_pixels(scene, rays, (centre_r[:, None] * w + centre_c).ravel(), r_wc, p_wc, windows)
    cells = cells.reshape(rows, cols)
    refine = _edge_cells(rays, corners, (rows, cols))
    across = cells[:, 1:] != cells[:, :-1]
    down = cells[1:] != cells[:-1]
    refine[:, 1:] |= across
    refine[:, :-1] |= across
    refine[1:] |= down
    refine[:-1] |= down
    surface = np.repeat(np.repeat(cells, CELL, 0), CELL, 1)[:h, :w].ravel()
    fine = np.repeat(np.repeat(refine, CELL, 0), CELL, 1)[:h, :w].ravel()
    index = np.flatnonzero(fine)
    if len(index):
        surface[index] = cast_pixels(scene, rays, index, r_wc, p_wc, windows)[1]
    return surface


@dataclass(frozen=True)
class _Surfaces:
    """Per surface (6 box + face): its plane and texture mapping, as 1-D tables for per-pixel lookups."""

    normal_axis: np.ndarray  # [S] int64, the world axis the face is normal to (texture axes: _TEXTURE_AXES)
    plane: np.ndarray  # [S] float64, the face's coordinate along its normal axis, m
    off_u: np.ndarray  # [S] float64 atlas x of world u = 0, texels
    off_v: np.ndarray  # [S] float64 atlas y of world v = 0, texels
    shade: np.ndarray  # [S] float32

    @classmethod
    def of(cls, scene: Scene) -> _Surfaces:
        n = scene.n_boxes * 6
        face, box = np.arange(n) % 6, np.arange(n) // 6
        axis = face // 2
        u_axis = np.array([1, 1, 0, 0, 0, 0])[face]  # the two other axes in increasing order
        v_axis = np.array([2, 2, 2, 2, 1, 1])[face]
        origin = scene.face_origin.reshape(n, 2).astype(np.float64)
        return cls(
            normal_axis=axis,
            plane=np.where(face % 2 == 1, scene.hi[box, axis], scene.lo[box, axis]),
            off_u=origin[:, 0] - scene.lo[box, u_axis] / scene.texel_m,
            off_v=origin[:, 1] - scene.lo[box, v_axis] / scene.texel_m,
            shade=scene.shade.reshape(n).astype(np.float32),
        )


@dataclass(frozen=True)
class _Planes:
    """The pixels of one frame grouped by the normal axis of the face they see (x, y, z faces; each group
    in image order), with what their ray-plane intersections need: within a group the plane's normal and
    texture axes are the same world axes, so intersecting a group is plain arithmetic on contiguous runs.

    Attributes:
        order: [N] the pixel (flat index) at each position. bounds: [4] the groups' start and stop.
        rays: [3, N] float32 unit rays, camera frame. footprint: [N] float32 angular size, rad.
        plane: [N] float32 the face's coordinate along its normal, m. off_u, off_v: [N] float32 atlas
            texel of world (u, v) = (0, 0) of the face. shade: [N] float32 the face's brightness.
    """

    order: np.ndarray
    bounds: np.ndarray
    rays: np.ndarray
    footprint: np.ndarray
    plane: np.ndarray
    off_u: np.ndarray
    off_v: np.ndarray
    shade: np.ndarray

    @classmethod
    def of(cls, tables: _Surfaces, rays: CameraRays, surface: np.ndarray) -> _Planes:
        axis = np.take(tables.normal_axis.astype(np.int8), surface)
        groups = [np.flatnonzero(axis == a) for a in range(3)]
        order = np.concatenate(groups)
        surface = np.take(surface, order).astype(np.intp)
        return cls(
            order=order,
            bounds=np.cumsum([0] + [len(g) for g in groups]),
            rays=np.take(rays.rays, order, axis=1),
            footprint=np.take(rays.footprint, order),
            plane=np.take(tables.plane.astype(np.float32), surface),
            off_u=np.take(tables.off_u.astype(np.float32), surface),
            off_v=np.take(tables.off_v.astype(np.float32), surface),
            shade=np.take(tables.shade, surface),
        )


_FAR = 1e3
"""Distances along a ray are clipped to this, m (a ray parallel to its plane at some sub-exposure)."""

_TEXTURE_AXES = ((1, 2), (0, 2), (0, 1))
"""The world axes of texture (u, v) on faces normal to x, y and z (the other two, in increasing order)."""


def _atlas_coords(
    scene: Scene, planes: _Planes, r_wc: np.ndarray, p_wc: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where every pixel's ray from the pose (r_wc, p_wc) meets the plane of its surface (in planes' order).

    Used for all sub-exposure poses with the surfaces cast at the middle one: within an exposure a pixel
    stays on its surface except at silhouettes, where the plane runs a pixel or two past its edge into
    the atlas's padding.

    Returns:
        (x, y) [N] float32 atlas texel coordinates (level 0); t [N] distance along the unit ray, m;
        the ray's world component along the plane's normal [N].
    """
    o = np.asarray(p_wc, np.float64)
    scale = 1.0 / scene.texel_m
    d = _rotate(r_wc, planes.rays)
    n = d.shape[1]
    x, y, t = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
    along = np.empty(n, np.float32)
    for axis, (u, v) in enumerate(_TEXTURE_AXES):
        g = slice(planes.bounds[axis], planes.bounds[axis + 1])
        along[g] = d[axis, g]
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = (planes.plane[g] - np.float32(o[axis])) / along[g]
        tg = np.fmin(np.fmax(tg, np.float32(0.0)), np.float32(_FAR))  # fmax: NaN (0 / 0) -> 0
        t[g] = tg
        tg *= np.float32(scale)
        x[g] = d[u, g] * tg + planes.off_u[g] + np.float32(o[u] * scale)
        y[g] = d[v, g] * tg + planes.off_v[g] + np.float32(o[v] * scale)
    return x, y, t, along


def _level_of_detail(footprint: np.ndarray, texel_m: float, t: np.ndarray, along: np.ndarray) -> np.ndarray:
    """Mip level of every pixel: log2 of its footprint in texels (isotropic between along and across the
    slant: the angular size times the distance over sqrt(cos incidence)), in [0, MIP_LEVELS - 1]."""
    texels = t * (footprint / np.float32(texel_m)) / np.sqrt(np.abs(along) + np.float32(1e-3))
    return np.clip(np.log2(np.maximum(texels, np.float32(1e-6))), 0.0, MIP_LEVELS - 1)


@dataclass(frozen=True)
class _MipMaps:
    """Per pixel, the affine maps from level-0 atlas coordinates to the texels of its two mip levels in
    scene.mip (the finer level's N entries, then the coarser level's), and the coarser level's weight
    (trilinear filtering)."""

    scale: np.ndarray  # [2 N] float32
    shift_x: np.ndarray  # [2 N] float32
    shift_y: np.ndarray  # [2 N] float32
    weight: np.ndarray  # [N] float32

    @classmethod
    def of(cls, scene: Scene, lod: np.ndarray) -> _MipMaps:
        level = np.minimum(lod.astype(np.intp), MIP_LEVELS - 2)  # lod >= 0: truncation is floor
        both = np.concatenate([level, level + 1])
        # cv2.pyrDown keeps the even texels (smoothed): level l's texel i lies on level 0's texel 2^l i.
        step = (0.5 ** np.arange(MIP_LEVELS)).astype(np.float32)
        return cls(
            scale=np.take(step, both),
            shift_x=np.take(scene.mip_origin[:, 0], both),
            shift_y=np.take(scene.mip_origin[:, 1], both),
            weight=lod - level,
        )


def vignetting_map(camera: Camera, strength: float) -> np.ndarray:
    """[H, W] brightness factor: 1 at the principal point, 1 - strength at the farthest corner (r^2 falloff
    squared, like cos^4)."""
    px, py = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    r2 = ((px - camera.cx) / camera.fx) ** 2 + ((py - camera.cy) / camera.fy) ** 2
    r2 /= r2.max()
    return (1.0 - strength * (2 * r2 - r2 * r2)).astype(np.float32)


def render_frame(
    scene: Scene,
    rays: CameraRays,
    poses: tuple[np.ndarray, np.ndarray],
    gain: float,
    rng: np.random.Generator,
    sensor: SensorModel = SensorModel(),
    vignette: np.ndarray | None = None,
) -> np.ndarray:
    """One 8-bit grey frame [H, W] (render_frame_and_instances without the instance map)."""
    return render_frame_and_instances(scene, rays, poses, gain, rng, sensor, vignette)[0]


def render_frame_and_instances(
    scene: Scene,
    rays: CameraRays,
    poses: tuple[np.ndarray, np.ndarray],
    gain: float,
    rng: np.random.Generator,
    sensor: SensorModel = SensorModel(),
    vignette: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One 8-bit grey frame and the object each pixel sees.

    The visible surface of every pixel is cast once, at the middle sub-exposure pose; every sub-exposure
    then intersects each pixel's ray with that surface's plane and samples the texture (trilinear, at the
    middle pose's level of detail); their mean is the exposure's radiance.

    Arguments:
        poses: (r_wc [S, 3, 3], p_wc [S, 3]) camera poses at the S sub-exposure instants (world frame, m).
        gain: the frame's brightness factor (auto-exposure). rng: the frame's noise.
        vignette: vignetting_map(camera, sensor.vignetting), passed in to compute it once.
    Returns:
        ([H, W] uint8 image, [H, W] uint16 instance map: the KITTI MOTS object id (Scene.instance_ids) of
        the surface each pixel sees at the middle sub-exposure, 0 for the room and its furniture).
    """
    r_wc, p_wc = poses
    h, w = rays.xn.shape
    middle = len(r_wc) // 2
    tables = _Surfaces.of(scene)
    surfaces = visible_surfaces(scene, rays, r_wc[middle], p_wc[middle])
    instances = np.take(scene.instance_ids(), surfaces // 6).reshape(h, w)
    planes = _Planes.of(tables, rays, surfaces)
    x, y, t, along = _atlas_coords(scene, planes, r_wc[middle], p_wc[middle])
    mip = _MipMaps.of(scene, _level_of_detail(planes.footprint, scene.texel_m, t, along))
    n = h * w
    # Both levels' samples of every pixel (in planes' order) in one cv2.remap call: maps of 2 H rows.
    map_x, map_y = np.empty((2 * h, w), np.float32), np.empty((2 * h, w), np.float32)
    mx, my = map_x.reshape(-1), map_y.reshape(-1)
    total = np.zeros((2 * h, w), np.float32)
    exact = {k: _atlas_coords(scene, planes, r_wc[k], p_wc[k])[:2] for k in {0, len(r_wc) - 1} - {middle}}
    exact[middle] = (x, y)
    slope = bend = (x, y)  # unused unless there are sub-exposures between the ends and the middle
    if len(r_wc) > 3:
        # Between the ends and the middle, the quadratic through the three: the sub-exposures are evenly
        # spaced in time and the image motion over 8 ms is smooth (error measured in docs/render.md).
        (x0, y0), (x1, y1) = exact[0], exact[len(r_wc) - 1]
        slope = ((x1 - x0) * np.float32(0.5), (y1 - y0) * np.float32(0.5))
        bend = ((x1 + x0) * np.float32(0.5) - x, (y1 + y0) * np.float32(0.5) - y)
    for k in range(len(r_wc)):
        if k in exact:
            x, y = exact[k]
        else:
            tau = np.float32((k - middle) / middle)
            x, y = (exact[middle][i] + tau * (slope[i] + tau * bend[i]) for i in range(2))
        for coords, out, shift in ((x, mx, mip.shift_x), (y, my, mip.shift_y)):
            np.multiply(coords, mip.scale[:n], out=out[:n])
            np.multiply(coords, mip.scale[n:], out=out[n:])
            out += shift
        samples = cv2.remap(scene.mip, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        cv2.accumulate(samples, total)
    fine, coarse = total.reshape(2, n)
    radiance = np.empty(n, np.float32)
    radiance[planes.order] = (fine + mip.weight * (coarse - fine)) * planes.shade
    if vignette is None:
        vignette = vignetting_map(rays.camera, sensor.vignetting)
    signal = radiance.reshape(h, w) * vignette * np.float32(gain * sensor.brightness / 128.0 / len(r_wc))
    if sensor.optics_sigma > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), sensor.optics_sigma)
    sigma = np.sqrt(
        np.float32(sensor.read_noise**2) + np.float32(sensor.shot_noise) * np.maximum(signal, 0.0)
    )
    noisy = signal + sigma * rng.standard_normal(signal.shape, dtype=np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8), instances
