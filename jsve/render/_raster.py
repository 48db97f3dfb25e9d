"""One camera frame of a Scene: ray casting per pixel, mip-mapped texture, and what makes real footage hard.

    CameraRays.of(camera)            unit ray and angular footprint of every pixel, once per camera
    SensorModel                      exposure, motion blur sub-samples, vignetting, gain, noise, optics blur
    render_frame(scene, rays, poses, gain, rng, sensor)   an 8-bit grey frame

The rays are those of the distorted pixels (the radial-tangential model inverted at every pixel centre,
iterated to convergence), so the image is rendered directly with the lens distortion ORB-SLAM3 undoes.
Casting is plain numpy, vectorised over pixels: the room is one box seen from inside (the exit distance of
three slabs), every piece of furniture a box tested only on the pixels of its projected bounding
rectangle (the pinhole projection of its corners bounds it in undistorted coordinates; the distorted
window is the bounding box of that rectangle's distorted outline). The texture is sampled with cv2.remap
from the two mip levels around each pixel's footprint (trilinear filtering): the footprint is the pixel's
angular size times the distance over the square root of the incidence cosine (between the isotropic
footprints along and across the slant), in texels.

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


def _box_window(
    rays: CameraRays, r_cw: np.ndarray, p_cw: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[slice, slice] | None:
    """The pixel rows and columns that can see a box, or None when no pixel can.

    The box's visible part (cut at the near plane) projects inside the bounding rectangle of its corners'
    (and cut points') pinhole projections; that rectangle, clipped to the image's undistorted extent, maps
    to the distorted image inside the bounding box of its distorted outline.
    """
    corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1).reshape(-1, 3)
    c = corners @ r_cw.T + p_cw
    front = c[:, 2] > _NEAR
    if not front.any():
        return None
    points = c[front]
    if not front.all():
        a, b = c[_EDGES[:, 0]], c[_EDGES[:, 1]]
        crossing = (a[:, 2] > _NEAR) != (b[:, 2] > _NEAR)
        s = (_NEAR - a[crossing, 2]) / (b[crossing, 2] - a[crossing, 2])
        points = np.concatenate([points, a[crossing] + s[:, None] * (b[crossing] - a[crossing])])
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    x0, x1 = max(x.min(), rays.x_range[0]), min(x.max(), rays.x_range[1])
    y0, y1 = max(y.min(), rays.y_range[0]), min(y.max(), rays.y_range[1])
    if x0 >= x1 or y0 >= y1:
        return None
    edge = np.linspace(0.0, 1.0, 24)
    bx = np.concatenate([x0 + (x1 - x0) * edge, np.full(24, x1), x1 - (x1 - x0) * edge, np.full(24, x0)])
    by = np.concatenate([np.full(24, y0), y0 + (y1 - y0) * edge, np.full(24, y1), y1 - (y1 - y0) * edge])
    u, v = rays.distort(bx, by)
    h, w = rays.xn.shape
    c0, c1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 3, w)
    r0, r1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 3, h)
    if c0 >= c1 or r0 >= r1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _pick(rows: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """rows[axis[n], n] of a [3, N] array for axis in 0..2 (elementwise selects)."""
    return np.where(axis == 0, rows[0], np.where(axis == 1, rows[1], rows[2]))


def cast(scene: Scene, rays: CameraRays, r_wc: np.ndarray, p_wc: np.ndarray):
    """Nearest surface along every pixel's ray.

    Arguments:
        r_wc: [3, 3] camera-to-world rotation. p_wc: [3] camera centre, m, world frame.
    Returns:
        (t [H W] distance along the unit ray, m; surface [H W] int32 6 box + face, the face 2 axis + side;
        d [3, H W] world ray directions).
    """
    h, w = rays.xn.shape
    d = r_wc.astype(np.float32) @ rays.rays
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
    t2, s2 = t.reshape(h, w), surface.reshape(h, w)
    inv2 = inv.reshape(3, h, w)
    r_cw = r_wc.T
    p_cw = -r_cw @ p_wc
    for b in range(1, scene.n_boxes):
        window = _box_window(rays, r_cw, p_cw, scene.lo[b], scene.hi[b])
        if window is None:
            continue
        rows, cols = window
        iv = inv2[:, rows, cols].reshape(3, -1)
        t_lo = (scene.lo[b].astype(np.float32) - o)[:, None] * iv
        t_hi = (scene.hi[b].astype(np.float32) - o)[:, None] * iv
        t_near, near_axis = _nearest_of_three(np.minimum(t_lo, t_hi), largest=True)
        t_far = np.maximum(t_lo, t_hi).min(axis=0)
        current = t2[rows, cols].reshape(-1)
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < current)
        if not hit.any():
            continue
        # Seen from outside: the face on the side the ray comes from (the low one for a ray going up).
        side = _pick(iv, near_axis) < 0
        shape = t2[rows, cols].shape
        t2[rows, cols] = np.where(hit, t_near, current).reshape(shape)
        s2[rows, cols] = np.where(hit, 6 * b + 2 * near_axis + side, s2[rows, cols].reshape(-1)).reshape(
            shape
        )
    return t2.reshape(-1), s2.reshape(-1), d


@dataclass(frozen=True)
class _Surfaces:
    """Per surface (6 box + face): its plane and texture mapping, as 1-D tables for per-pixel lookups."""

    normal_axis: np.ndarray  # [S] int32, the world axis the face is normal to
    plane: np.ndarray  # [S] float32, the face's coordinate along that axis, m
    u_is_x: np.ndarray  # [S] bool: texture u is world x (else y)
    v_is_y: np.ndarray  # [S] bool: texture v is world y (else z)
    off_u: np.ndarray  # [S] float32 atlas x of world u = 0, texels
    off_v: np.ndarray  # [S] float32 atlas y of world v = 0, texels
    shade: np.ndarray  # [S] float32

    @classmethod
    def of(cls, scene: Scene) -> _Surfaces:
        n = scene.n_boxes * 6
        face, box = np.arange(n) % 6, np.arange(n) // 6
        axis = face // 2
        u_axis = np.array([1, 1, 0, 0, 0, 0])[face]  # the two other axes in increasing order
        v_axis = np.array([2, 2, 2, 2, 1, 1])[face]
        plane = np.where(face % 2 == 1, scene.hi[box, axis], scene.lo[box, axis])
        origin = scene.face_origin.reshape(n, 2)
        return cls(
            normal_axis=axis.astype(np.int32),
            plane=plane.astype(np.float32),
            u_is_x=u_axis == 0,
            v_is_y=v_axis == 1,
            off_u=(origin[:, 0] - scene.lo[box, u_axis] / scene.texel_m).astype(np.float32),
            off_v=(origin[:, 1] - scene.lo[box, v_axis] / scene.texel_m).astype(np.float32),
            shade=scene.shade.reshape(n).astype(np.float32),
        )


def _atlas_coords(
    rays: np.ndarray, r_wc: np.ndarray, p_wc: np.ndarray, surface: _PixelSurfaces
) -> tuple[np.ndarray, np.ndarray]:
    """Atlas texel coordinates (x, y) [N] where rays [3, N] (camera frame) from the pose (r_wc, p_wc) meet
    the planes of their given surfaces.

    Used for the sub-exposure poses around the one the surfaces were cast from: within an exposure a pixel
    stays on its surface except at silhouettes, where the plane runs a pixel or two past its edge into
    the atlas's padding."""
    d = r_wc.astype(np.float32) @ rays
    o = p_wc.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (surface.plane - o[surface.normal_axis]) / _pick(d, surface.normal_axis)
    t = np.where(np.isfinite(t) & (t > 0), t, np.float32(0.0))
    x = np.where(surface.u_is_x, o[0] + d[0] * t, o[1] + d[1] * t) * surface.scale + surface.off_u
    y = np.where(surface.v_is_y, o[1] + d[1] * t, o[2] + d[2] * t) * surface.scale + surface.off_v
    return x, y


@dataclass(frozen=True)
class _PixelSurfaces:
    """_Surfaces' entries gathered per pixel (of a permutation of the pixels) for one frame."""

    normal_axis: np.ndarray
    plane: np.ndarray
    u_is_x: np.ndarray
    v_is_y: np.ndarray
    off_u: np.ndarray
    off_v: np.ndarray
    scale: np.float32

    @classmethod
    def of(cls, tables: _Surfaces, surface: np.ndarray, texel_m: float) -> _PixelSurfaces:
        return cls(
            normal_axis=tables.normal_axis[surface],
            plane=tables.plane[surface],
            u_is_x=tables.u_is_x[surface],
            v_is_y=tables.v_is_y[surface],
            off_u=tables.off_u[surface],
            off_v=tables.off_v[surface],
            scale=np.float32(1.0 / texel_m),
        )


def _level_of_detail(scene: Scene, rays: CameraRays, t: np.ndarray, d: np.ndarray, normal_axis: np.ndarray):
    """Mip level of every pixel: log2 of its footprint in texels (isotropic between along and across the
    slant: the angular size times the distance over sqrt(cos incidence)), in [0, MIP_LEVELS - 1]."""
    cos_incidence = np.abs(_pick(d, normal_axis)) + np.float32(1e-3)
    texels = t * rays.footprint / (np.float32(scene.texel_m) * np.sqrt(cos_incidence))
    return np.clip(np.log2(np.maximum(texels, np.float32(1e-6))), 0.0, MIP_LEVELS - 1)


_MAP_WIDTH = 1024
"""Width of the maps handed to cv2.remap (a long list of samples is folded into rows)."""


def _remap_list(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of image at the points (x, y) [N] (cv2.remap on the list folded into rows)."""
    n = len(x)
    rows = -(-n // _MAP_WIDTH)
    mx = np.zeros(rows * _MAP_WIDTH, np.float32)
    my = np.zeros(rows * _MAP_WIDTH, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(image, mx.reshape(rows, -1), my.reshape(rows, -1), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT)  # fmt: skip
    return out.reshape(-1)[:n].astype(np.float32)  # the atlas is 8-bit: differences need a signed type


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
    """One 8-bit grey frame.

    The visible surface of every pixel is cast once, at the middle sub-exposure pose; every sub-exposure
    then intersects each pixel's ray with that surface's plane and samples the texture (trilinear, at the
    middle pose's level of detail); their mean is the exposure's radiance.

    Arguments:
        poses: (r_wc [S, 3, 3], p_wc [S, 3]) camera poses at the S sub-exposure instants (world frame, m).
        gain: the frame's brightness factor (auto-exposure). rng: the frame's noise.
        vignette: vignetting_map(camera, sensor.vignetting), passed in to compute it once.
    Returns:
        [H, W] uint8.
    """
    r_wc, p_wc = poses
    h, w = rays.xn.shape
    tables = _Surfaces.of(scene)
    middle = len(r_wc) // 2
    t, surface, d = cast(scene, rays, r_wc[middle], p_wc[middle])
    lod = _level_of_detail(scene, rays, t, d, tables.normal_axis[surface])
    # Pixels sorted by their finer mip level, so each level's samples are one contiguous run.
    level = np.minimum(lod.astype(np.int32), MIP_LEVELS - 2)
    runs = [np.flatnonzero(level == lv) for lv in range(MIP_LEVELS - 1)]
    order = np.concatenate(runs)
    bounds = np.concatenate([[0], np.cumsum([len(r) for r in runs])])
    upper = (lod - level)[order]  # weight of the coarser level
    surface = surface[order]
    pixels = _PixelSurfaces.of(tables, surface, scene.texel_m)
    directions = rays.rays[:, order]
    radiance = np.zeros(h * w, np.float32)
    for r, p in zip(r_wc, p_wc, strict=True):
        x, y = _atlas_coords(directions, r, p, pixels)
        for lv in range(MIP_LEVELS - 1):
            sl = slice(bounds[lv], bounds[lv + 1])
            if sl.start == sl.stop:
                continue
            step = np.float32(0.5**lv)
            fine = _remap_list(scene.atlas[lv], x[sl] * step, y[sl] * step)
            coarse = _remap_list(scene.atlas[lv + 1], x[sl] * (step / 2), y[sl] * (step / 2))
            radiance[sl] += fine + upper[sl] * (coarse - fine)
    shaded = np.empty(h * w, np.float32)
    shaded[order] = radiance * (tables.shade[surface] / np.float32(len(r_wc)))
    radiance = shaded.reshape(h, w)
    if vignette is None:
        vignette = vignetting_map(rays.camera, sensor.vignetting)
    signal = radiance * np.float32(gain * sensor.brightness / 128.0) * vignette
    if sensor.optics_sigma > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), sensor.optics_sigma)
    sigma = np.sqrt(
        np.float32(sensor.read_noise**2) + np.float32(sensor.shot_noise) * np.maximum(signal, 0.0)
    )
    noisy = signal + sigma * rng.standard_normal(signal.shape, dtype=np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
