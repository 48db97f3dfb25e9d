"""Simulated KITTI-odometry-like driving with dynamic objects whose features bias the visual pose.

The scenario of Masked ORB-SLAM3 (docs/masks.md, "Simulated driving scenario"): a car drives at 10 fps
with a 1242 x 375 camera; cars and pedestrians enter, cross and leave the image as boxes that drift
sideways. Every frame has static keypoints spread over the image (none on or right next to a box: they
are occluded) and keypoints inside each box that move with the object. The visual odometry error of a
frame is

    noise:  N(0, sigma^2 * n_ref / n_used)           n_used = inliers the estimator uses
    bias:   -gain * f_dyn * u_dyn / fx                f_dyn = dynamic share of those inliers,
                                                      u_dyn = their mean apparent motion, px/frame

on the frame-to-frame yaw (and, times a depth, on the lateral step), composed onto the ground-truth
relative motion, so that errors integrate into drift like odometry.

The original run (ORB-SLAM3) uses every inlier; its log's counts and bins are those of the full keypoint
set. The masked run's counts and bins come from `jsve.masks._masks.apply_masks` over the side file and the box
masks (`BoxMasks`). A log carries one visual pose, and a real masked run is a re-run of the front-end;
the simulator's stand-in is the same generative model evaluated without the dynamic keypoints: the same
standard-normal draws, only n_used (static inliers) and the bias (zero) change, so the two runs of a
seed are a paired comparison.

Body convention: x forward, y left, z up (world z up, gravity -z). KITTI odometry poses (camera frame:
x right, y down, z forward; world = first camera) are converted by T_wb = C^-1 T_wc C with C the
rotation taking body axes to camera axes (`kitti_body_poses`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import jax
import numpy as np
import pandas as pd

from jsve.core._geometry import yaw_rotation
from jsve.io import _schema as schema
from jsve.io._keypoints import KeypointLog
from jsve.io._schema import RunLog
from jsve.masks._masks import apply_masks, sve_bin_index
from jsve.sim._trajectory import GRAVITY, matrix_to_quat, quat_conj, quat_mul, quat_rotate

CAMERA_FROM_BODY = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""R_cb: body x (forward) -> camera z, body y (left) -> camera -x, body z (up) -> camera -y."""


@dataclass(frozen=True)
class DrivingConfig:
    """Parameters of the scenario (pixels, metres, seconds; per frame where it says so).

    Attributes:
        n_frames: frames of a procedural trajectory. fps: frame rate. image_size: (width, height) px.
        speed: car speed range, m/s. yaw_rate: largest yaw rate of the procedural path, rad/s.
        n_static: mean static keypoints per frame (before occlusion). static_inlier: their inlier rate.
        dynamic_inlier: inlier rate of keypoints on objects. density_car, density_pedestrian: keypoints
            per px^2 on an object. spawn_rate: new objects per frame; n_initial: objects at frame 0.
        car_fraction: share of new objects that are cars. car_speed, pedestrian_speed: apparent
            horizontal motion ranges, px/frame. edge_margin: px around a box without static keypoints.
        sigma_yaw, sigma_step: odometry noise per frame (rad, m) at n_ref inliers.
        bias_gain: share of the dynamic features' apparent motion the estimator absorbs.
        object_depth: m, depth that turns a yaw bias into a lateral step bias. fx: focal length, px.
    """

    n_frames: int = 400
    fps: float = 10.0
    image_size: tuple[int, int] = (1242, 375)
    speed: tuple[float, float] = (5.0, 15.0)
    yaw_rate: float = 0.15
    n_static: float = 700.0
    static_inlier: float = 0.6
    dynamic_inlier: float = 0.7
    density_car: float = 1.5e-3
    density_pedestrian: float = 1.5e-3
    spawn_rate: float = 0.04
    n_initial: int = 2
    car_fraction: float = 0.7
    car_speed: tuple[float, float] = (4.0, 20.0)
    pedestrian_speed: tuple[float, float] = (1.5, 5.0)
    edge_margin: int = 2
    sigma_yaw: float = 1.5e-3
    sigma_step: float = 0.03
    n_ref: float = 400.0
    bias_gain: float = 0.3
    object_depth: float = 12.0
    fx: float = 718.0


# --------------------------------------------------------------------------------------------------
# Ground truth


def procedural_poses(rng: np.random.Generator, config: DrivingConfig = DrivingConfig()) -> np.ndarray:
    """A car-like planar path: [F, 4, 4] T_wb at config.fps, speed within config.speed, gentle yaw.

    Speed and yaw rate are sums of slow random sinusoids (periods 8 to 60 s); the body starts at the
    origin facing +x, 1.65 m above the ground (KITTI's camera height).
    """
    n, dt = config.n_frames, 1.0 / config.fps
    t = np.arange(n) * dt
    period = np.exp(rng.uniform(np.log(8.0), np.log(60.0), size=(2, 4)))
    phase = rng.uniform(0, 2 * np.pi, size=(2, 4))
    waves = np.sin(2 * np.pi * t[:, None, None] / period + phase).mean(axis=2)  # [F, 2] in [-1, 1]
    lo, hi = config.speed
    speed = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.clip(1.6 * waves[:, 0], -1, 1)
    yaw_rate = config.yaw_rate * np.clip(1.6 * waves[:, 1], -1, 1)
    yaw = np.concatenate([[0.0], np.cumsum(yaw_rate[:-1] * dt)])
    step = speed[:-1, None] * dt * np.stack([np.cos(yaw[:-1]), np.sin(yaw[:-1])], axis=1)
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = yaw_rotation(yaw, xp=np)
    poses[:, :2, 3] = xy
    poses[:, 2, 3] = 1.65
    return poses


def kitti_body_poses(path: str | os.PathLike, n_frames: int | None = None) -> np.ndarray:
    """A KITTI odometry pose file (12 numbers per line: T_wc, 3 x 4, 10 Hz) as [F, 4, 4] body poses.

    T_wb = C^-1 T_wc C with C = [R_cb, 0; 0, 1]: the world becomes z up, x along the first heading.
    """
    rows = np.loadtxt(os.fspath(path), ndmin=2)
    if rows.shape[1] != 12:
        raise ValueError(f"{os.fspath(path)}: expected 12 numbers per line, found {rows.shape[1]}")
    rows = rows[:n_frames] if n_frames else rows
    t_wc = np.tile(np.eye(4), (len(rows), 1, 1))
    t_wc[:, :3, :4] = rows.reshape(-1, 3, 4)
    c = np.eye(4)
    c[:3, :3] = CAMERA_FROM_BODY
    return np.linalg.inv(c) @ t_wc @ c


# --------------------------------------------------------------------------------------------------
# Scene: moving boxes


@dataclass(frozen=True)
class Scene:
    """Moving objects over a sequence.

    Attributes:
        boxes: per frame, int64 [n, 4] (x0, y0, x1, y1) px, half-open (columns x0..x1-1, rows y0..y1-1),
            clipped to the image.
        motion: per frame, [n] apparent horizontal motion of each box, px/frame.
        kind: per frame, [n] class id (1 car, 2 pedestrian, KITTI MOTS numbering).
        image_size: (width, height) px.
    """

    boxes: list[np.ndarray]
    motion: list[np.ndarray]
    kind: list[np.ndarray]
    image_size: tuple[int, int]


def make_scene(rng: np.random.Generator, n_frames: int, config: DrivingConfig = DrivingConfig()) -> Scene:
    """Cars and pedestrians entering from either side (or appearing in view), drifting across, leaving."""
    width, height = config.image_size
    live: list[list[float]] = []  # x, y_bottom, w, h, vx, kind

    def spawn(anywhere: bool):
        car = rng.random() < config.car_fraction
        if car:
            w = rng.uniform(100, 260)
            h = w * rng.uniform(0.5, 0.7)
            speed = rng.uniform(*config.car_speed)
        else:
            h = rng.uniform(70, 150)
            w = h * rng.uniform(0.35, 0.5)
            speed = rng.uniform(*config.pedestrian_speed)
        direction = rng.choice([-1.0, 1.0])
        if anywhere:
            x = rng.uniform(0, width - w)
        else:
            x = -w + 1 if direction > 0 else width - 1
        live.append([x, rng.uniform(0.55, 0.95) * height, w, h, direction * speed, 1 if car else 2])

    for _ in range(config.n_initial):
        spawn(True)
    boxes, motion, kind = [], [], []
    for _ in range(n_frames):
        for _ in range(rng.poisson(config.spawn_rate)):
            spawn(rng.random() < 0.2)  # a parked car pulling out, a pedestrian stepping out of a doorway
        frame_boxes, frame_motion, frame_kind = [], [], []
        for obj in live:
            x, yb, w, h, vx, k = obj
            x0, x1 = int(np.clip(np.floor(x), 0, width)), int(np.clip(np.floor(x + w), 0, width))
            y0, y1 = int(np.clip(np.floor(yb - h), 0, height)), int(np.clip(np.floor(yb), 0, height))
            if x1 - x0 >= 4 and y1 - y0 >= 4:
                frame_boxes.append((x0, y0, x1, y1))
                frame_motion.append(vx)
                frame_kind.append(k)
            obj[0] += vx
        live[:] = [o for o in live if o[0] + o[2] > 0 and o[0] < width]
        boxes.append(np.array(frame_boxes, np.int64).reshape(-1, 4))
        motion.append(np.array(frame_motion, np.float64))
        kind.append(np.array(frame_kind, np.int64))
    return Scene(boxes, motion, kind, (width, height))


class BoxMasks:
    """The scene's boxes as a jsve.masks mask source: frame index -> bool [height, width] (in memory)."""

    def __init__(self, scene: Scene):
        self.scene = scene

    @property
    def shape(self) -> tuple[int, int]:
        width, height = self.scene.image_size
        return height, width

    def mask(self, key: int) -> np.ndarray:
        out = np.zeros(self.shape, bool)
        for x0, y0, x1, y1 in self.scene.boxes[int(key)]:
            out[y0:y1, x0:x1] = True
        return out

    __getitem__ = mask

    def describe(self) -> str:
        return "jsve.sim._driving boxes"


def write_png_masks(scene: Scene, folder: str | os.PathLike) -> list[str]:
    """One binary PNG per frame (`000042.png`, 255 on objects) for jsve.masks._masks.PngMasks."""
    import cv2

    os.makedirs(folder, exist_ok=True)
    source = BoxMasks(scene)
    paths = []
    for f in range(len(scene.boxes)):
        path = os.path.join(os.fspath(folder), f"{f:06d}.png")
        if not cv2.imwrite(path, source.mask(f).astype(np.uint8) * 255):
            raise OSError(f"{path}: cv2.imwrite failed")
        paths.append(path)
    return paths


# --------------------------------------------------------------------------------------------------
# Runs


@dataclass(frozen=True)
class DrivingRun:
    """One simulated run.

    Attributes:
        original: the log of ORB-SLAM3 on every keypoint (counts, bins, vis_* from the full set).
        keypoints: its side file (every keypoint; x, y = ux, uy: no distortion).
        dynamic: [K] bool per keypoint row: on a moving object.
        masks: the mask source (one box mask per frame).
        masked_vis: [F, 4, 4] the visual poses of the same model without the dynamic keypoints.
        scene: the objects.
    """

    original: RunLog
    keypoints: KeypointLog
    dynamic: np.ndarray
    masks: BoxMasks
    masked_vis: np.ndarray
    scene: Scene = field(repr=False)

    def masked(self, **options) -> RunLog:
        """The masked run: counts and bins from jsve.masks._masks.apply_masks, vis_* from `masked_vis`."""
        run = apply_masks(self.original, self.keypoints, self.masks, **options).log
        frames = run.frames.copy()
        _set_vis(frames, self.masked_vis, 1.0 / float(run.meta["fps"]))
        return RunLog(meta={**run.meta, "vis_model": "masked re-run stand-in"}, frames=frames,
                      source=run.source)  # fmt: skip


def _set_vis(frames: pd.DataFrame, poses: np.ndarray, dt: float) -> None:
    p = poses[:, :3, 3]
    frames[list(schema.VIS_POSITION)] = p
    frames[list(schema.VIS_QUATERNION)] = matrix_to_quat(poses[:, :3, :3])
    v = np.gradient(p, dt, axis=0) if len(p) > 1 else np.zeros_like(p)
    frames[list(schema.VIS_VELOCITY)] = v


def _imu_columns(poses: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Noise-free preintegration between frames, consistent with simulate_motion.imu_predict."""
    n = len(poses)
    p = poses[:, :3, 3]
    q = matrix_to_quat(poses[:, :3, :3])
    v = np.gradient(p, dt, axis=0) if n > 1 else np.zeros_like(p)
    dp, dv = np.zeros((n, 3)), np.zeros((n, 3))
    dq = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    if n > 1:
        qc = quat_conj(q[:-1])
        dp[1:] = quat_rotate(qc, p[1:] - p[:-1] - v[:-1] * dt - 0.5 * GRAVITY * dt * dt)
        dv[1:] = quat_rotate(qc, v[1:] - v[:-1] - GRAVITY * dt)
        dq[1:] = quat_mul(qc, q[1:])
        dq[1:] /= np.linalg.norm(dq[1:], axis=1, keepdims=True)
    out = {"imu_dt": np.where(np.arange(n) > 0, dt, 0.0)}
    out.update({c: dp[:, i] for i, c in enumerate(schema.IMU_DP)})
    out.update({c: dv[:, i] for i, c in enumerate(schema.IMU_DV)})
    out.update({c: dq[:, i] for i, c in enumerate(schema.IMU_DQ)})
    return out


_jit_bins = jax.jit(sve_bin_index)


def _bins(xy: np.ndarray, bounds) -> np.ndarray:
    """SVE bin of every keypoint (jsve.masks._masks.sve_bin_index), padded to a multiple of 2^16 rows so that
    runs of similar size share one compiled kernel."""
    padded = np.zeros((-(-len(xy) // 65536) * 65536, 2), np.float32)
    padded[: len(xy)] = xy
    return np.asarray(_jit_bins(padded, np.asarray(bounds, np.float32)))[: len(xy)]


def _odometry(gt: np.ndarray, yaw_err: np.ndarray, step_err: np.ndarray) -> np.ndarray:
    """Compose per-frame errors (yaw rad, body step m) onto the ground-truth relative motion."""
    est = np.empty_like(gt)
    est[0] = gt[0]
    rel = np.linalg.inv(gt[:-1]) @ gt[1:]
    err = np.tile(np.eye(4), (len(gt) - 1, 1, 1))
    err[:, :3, :3] = yaw_rotation(yaw_err[1:], xp=np)
    err[:, :3, 3] = step_err[1:]
    steps = rel @ err
    for k in range(1, len(gt)):
        est[k] = est[k - 1] @ steps[k - 1]
    return est


def simulate_run(
    sequence: str,
    run: int,
    gt_poses: np.ndarray,
    scene: Scene,
    *,
    seed: int,
    config: DrivingConfig = DrivingConfig(),
) -> DrivingRun:
    """One run over a sequence (ground truth + scene); `seed` draws the keypoints and the noise."""
    rng = np.random.default_rng(seed)
    width, height = config.image_size
    n = len(gt_poses)
    if len(scene.boxes) < n:
        raise ValueError(f"the scene has {len(scene.boxes)} frames, the trajectory {n}")
    m = config.edge_margin
    xs, ys, dyn, inl, motion = [], [], [], [], []
    sizes = np.zeros(n, np.int64)
    for f in range(n):
        boxes = scene.boxes[f]
        k = rng.poisson(config.n_static)
        x = rng.uniform(0, width, k)
        y = rng.uniform(0, height, k)
        near = np.zeros(k, bool)
        first = len(xs)
        for x0, y0, x1, y1 in boxes:
            near |= (x >= x0 - m) & (x < x1 + m) & (y >= y0 - m) & (y < y1 + m)
        x, y = x[~near], y[~near]
        xs.append(x), ys.append(y)
        dyn.append(np.zeros(len(x), bool)), motion.append(np.zeros(len(x)))
        inl.append(rng.random(len(x)) < config.static_inlier)
        for (x0, y0, x1, y1), vx, kind in zip(boxes, scene.motion[f], scene.kind[f], strict=True):
            density = config.density_car if kind == 1 else config.density_pedestrian
            j = rng.poisson(density * (x1 - x0) * (y1 - y0))
            # Strictly inside the box: floor(x) in [x0, x1 - 1], so Algorithm 1 finds every one.
            xs.append(rng.uniform(x0, x1 - 1e-6, j)), ys.append(rng.uniform(y0, y1 - 1e-6, j))
            dyn.append(np.ones(j, bool)), motion.append(np.full(j, vx))
            inl.append(rng.random(j) < config.dynamic_inlier)
        sizes[f] = sum(len(a) for a in xs[first:])
    x, y = np.concatenate(xs), np.concatenate(ys)
    dynamic, inlier, apparent = np.concatenate(dyn), np.concatenate(inl), np.concatenate(motion)
    frame = np.repeat(np.arange(n), sizes)
    t_ns = (np.arange(n) * round(1e9 / config.fps)).astype(np.int64) + 1_000_000_000
    octave = np.minimum(rng.geometric(0.45, len(x)) - 1, 7)

    # Counts per frame over every keypoint, and the inliers each estimator uses.
    n_ext = np.bincount(frame, minlength=n)
    n_inl = np.bincount(frame, weights=inlier, minlength=n).astype(np.int64)
    dyn_inl = inlier & dynamic
    n_dyn = np.bincount(frame, weights=dyn_inl, minlength=n)
    u_dyn = np.bincount(frame, weights=np.where(dyn_inl, apparent, 0.0), minlength=n) / np.maximum(n_dyn, 1)
    n_static = n_inl - n_dyn
    bins_of = _bins(np.stack([x, y], 1), (0.0, width, 0.0, height))
    bins = np.zeros((n, schema.N_BINS), np.int64)
    np.add.at(bins, (frame[bins_of >= 0], bins_of[bins_of >= 0]), 1)

    z = rng.standard_normal((n, 4))  # shared by both runs: the pairing

    def vis(n_used, bias_yaw):
        s = np.sqrt(config.n_ref / np.maximum(n_used, 20))
        yaw = config.sigma_yaw * s * z[:, 0] + bias_yaw
        step = config.sigma_step * s[:, None] * z[:, 1:] * np.array([1.0, 1.0, 0.5])
        step[:, 1] += bias_yaw * config.object_depth
        return _odometry(gt_poses, yaw, step)

    f_dyn = n_dyn / np.maximum(n_inl, 1)
    original_vis = vis(n_inl, -config.bias_gain * f_dyn * u_dyn / config.fx)
    masked_vis = vis(n_static, np.zeros(n))

    dt = 1.0 / config.fps
    imu_init = np.ones(n, np.int64)
    columns = {
        "t_ns": t_ns,
        "state": np.full(n, schema.STATE_OK),
        "imu_init": imu_init,
        # One map, a pose on every frame; inertial BA2 from 15 s in (schema.v1_defaults' rule).
        **schema.v1_defaults(t_ns, imu_init),
        "n_extracted": n_ext,
        "n_inliers": n_inl,
        "n_frustum": n_inl + n_ext // 3,
    }
    columns.update({c: bins[:, k] for k, c in enumerate(schema.BIN_COLUMNS)})
    frames = pd.DataFrame(columns)
    for c in schema.FLOAT_COLUMNS:
        frames[c] = 0.0
    _set_vis(frames, original_vis, dt)
    for c, values in _imu_columns(gt_poses, dt).items():
        frames[c] = values
    frames[list(schema.GT_POSITION)] = gt_poses[:, :3, 3]
    frames[list(schema.GT_QUATERNION)] = matrix_to_quat(gt_poses[:, :3, :3])
    frames = frames[list(schema.COLUMNS)]
    for c in schema.INT_COLUMNS:
        frames[c] = frames[c].astype(np.int64)
    meta = {
        "sequence": sequence, "run": int(run), "fps": config.fps, "sensor": "monocular",
        "image_size": [width, height], "frontend": "jsve simulate_driving (original: all keypoints)",
        "rule": "orbslam3", "switch_model": "orbslam3", "seed": int(seed),
    }  # fmt: skip
    kp = pd.DataFrame({
        "t_ns": t_ns[frame], "x": x, "y": y, "ux": x, "uy": y,
        "octave": octave.astype(np.int64), "inlier": inlier.astype(np.int64),
    })  # fmt: skip
    kmeta = {"sequence": sequence, "run": int(run), "image_size": [width, height]}
    return DrivingRun(
        original=RunLog(meta=meta, frames=frames, source=f"<{sequence}/{run}>"),
        keypoints=KeypointLog(meta=kmeta, keypoints=kp, source=f"<{sequence}/{run} keypoints>"),
        dynamic=dynamic,
        masks=BoxMasks(scene),
        masked_vis=masked_vis,
        scene=scene,
    )


def simulate_sequence(
    sequence: str,
    seed: int,
    n_runs: int,
    config: DrivingConfig = DrivingConfig(),
    poses: np.ndarray | None = None,
) -> list[DrivingRun]:
    """`n_runs` runs over one sequence: trajectory (procedural, or `poses` e.g. from kitti_body_poses)
    and scene drawn from `seed`, each run's keypoints and noise from (seed, run)."""
    rng = np.random.default_rng([seed, 0])
    gt = procedural_poses(rng, config) if poses is None else np.asarray(poses, np.float64)
    scene = make_scene(rng, len(gt), replace(config, n_frames=len(gt)))
    return [
        simulate_run(
            sequence,
            r,
            gt,
            scene,
            seed=int(np.random.SeedSequence([seed, 1, r]).generate_state(1)[0]),
            config=config,
        )  # fmt: skip
        for r in range(n_runs)
    ]
