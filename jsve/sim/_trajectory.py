"""Simulator, trajectories (host numpy, float64): smooth body trajectories from EuRoC ground truth or
a procedural flight, and the rotation helpers the simulator shares.

Part of the stand-in front-end (jsve.sim._simulate; docs/simulator.md). Everything here is plain numpy in
float64: the simulator's worker processes never dispatch to JAX. The rotation helpers are jsve.core.
_geometry's, computed with numpy (their `xp=np`).

    Trajectory                 a smooth continuous-time body trajectory (uniform cubic B-splines fitted
                               to poses): position, velocity, acceleration, orientation, body rates
    load_euroc_trajectory      EuRoC left-camera ground truth -> body frame (T_wb = T_wc inv(T_BS))
    procedural_trajectory      an EuRoC-like flight (quadrotor attitude from thrust, 20 fps stamps)

The IMU synthesised along a trajectory is jsve.sim._imu's.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jsve.core import _geometry as geometry

GRAVITY = np.array([0.0, 0.0, -9.81])
"""World gravity, m/s^2 (EuRoC world frame, z up; jsve.io._schema.DEFAULT_GRAVITY)."""

EUROC_CAM0_T_BS = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
"""EuRoC cam0 extrinsics T_BS (body <- camera), from mav0/cam0/sensor.yaml of every EuRoC sequence."""

EUROC_SEQUENCES = {
    "MH_01": "MH01", "MH_02": "MH02", "MH_03": "MH03", "MH_04": "MH04", "MH_05": "MH05",
    "V1_01": "V101", "V1_02": "V102", "V1_03": "V103", "V2_01": "V201", "V2_02": "V202", "V2_03": "V203",
}  # fmt: skip
"""EuRoC sequence name -> the short name of ORB-SLAM3's files (MH01_GT.txt, timestamps/MH01.txt)."""


# --------------------------------------------------------------------------------------------------
# Rotations: jsve.core._geometry's functions computed in numpy float64 (xp=np), the same operations; the
# worker processes never dispatch to JAX, and IMU deltas need double precision.

quat_mul = functools.partial(geometry.quat_mul, xp=np)
quat_conj = functools.partial(geometry.quat_conj, xp=np)
quat_normalize = functools.partial(geometry.quat_normalize, xp=np)
quat_to_matrix = functools.partial(geometry.quat_to_matrix, xp=np)
matrix_to_quat = functools.partial(geometry.matrix_to_quat, xp=np)
quat_rotate = functools.partial(geometry.quat_rotate, xp=np)
so3_exp = functools.partial(geometry.so3_exp, xp=np)
quat_exp = functools.partial(geometry.quat_exp, xp=np)
quat_log = functools.partial(geometry.quat_log, xp=np)
skew = functools.partial(geometry.skew, xp=np)


# --------------------------------------------------------------------------------------------------
# Uniform cubic B-splines


def _bspline_weights(u: np.ndarray, order: int) -> np.ndarray:
    """Weights of the 4 control points of a uniform cubic B-spline segment at u in [0, 1): [N, 4]."""
    if order == 0:
        return (
            np.stack([(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], -1) / 6
        )
    if order == 1:
        return np.stack([-((1 - u) ** 2), 3 * u**2 - 4 * u, -3 * u**2 + 2 * u + 1, u**2], -1) / 2
    if order == 2:
        return np.stack([1 - u, 3 * u - 2, -3 * u + 1, u], -1)
    raise ValueError(f"B-spline derivative order must be 0, 1 or 2; got {order}")


def _solve_banded_spd(band: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve S x = rhs for a symmetric positive definite S given in lower band form
    (band[k, r] = S[r, r - k]), by banded Cholesky S = L L^T (Golub & Van Loan, algorithm 4.3.5)."""
    p, m = band.shape[0] - 1, band.shape[1]
    low = np.zeros_like(band)  # low[k, r] = L[r, r - k]
    b = [list(row) for row in band]
    lo = [[0.0] * m for _ in range(p + 1)]
    for r in range(m):
        for k in range(min(p, r), 0, -1):
            c = r - k
            acc = b[k][r]
            for j in range(1, p - k + 1):
                if c - j < 0:
                    break
                acc -= lo[k + j][r] * lo[j][c]
            lo[k][r] = acc / lo[0][c]
        acc = b[0][r] - sum(lo[k][r] ** 2 for k in range(1, min(p, r) + 1))
        lo[0][r] = math.sqrt(acc)
    low[:] = np.array(lo)
    x = np.array(rhs, float)
    for r in range(m):  # L z = rhs
        for k in range(1, min(p, r) + 1):
            x[r] -= low[k, r] * x[r - k]
        x[r] /= low[0, r]
    for r in range(m - 1, -1, -1):  # L^T x = z
        for k in range(1, min(p, m - 1 - r) + 1):
            x[r] -= low[k, r + k] * x[r + k]
        x[r] /= low[0, r]
    return x


@dataclass(frozen=True)
class Spline:
    """A uniform cubic B-spline in time: control points [M, D], knot spacing h (s), start t0 (s).

    Segment i covers [t0 + i h, t0 + (i + 1) h) and uses control points i..i+3.
    """

    coef: np.ndarray
    h: float
    t0: float

    @property
    def t_end(self) -> float:
        return self.t0 + (len(self.coef) - 3) * self.h

    def _locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = (np.asarray(t, float) - self.t0) / self.h
        i = np.clip(np.floor(x).astype(np.int64), 0, len(self.coef) - 4)
        return i, x - i

    def __call__(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """Value (order 0) or time derivative (1, 2) at times t [N] -> [N, D]."""
        i, u = self._locate(t)
        w = _bspline_weights(u, order) / self.h**order
        idx = i[:, None] + np.arange(4)
        return np.einsum("nk,nkd->nd", w, self.coef[idx])

    @staticmethod
    def fit(t: np.ndarray, y: np.ndarray, h: float, smooth: float = 1e-3) -> Spline:
        """Least-squares fit to samples y [N, D] at times t [N] (s), with a curvature penalty.

        smooth weighs the squared second differences of the control points (units of y^2 per knot),
        which damps ground-truth measurement noise before it is differentiated twice.
        """
        t = np.asarray(t, float)
        t0, t1 = float(t[0]), float(t[-1])
        n_seg = max(1, int(math.ceil((t1 - t0) / h - 1e-9)))
        m = n_seg + 3
        x = (t - t0) / h
        i = np.clip(np.floor(x).astype(np.int64), 0, n_seg - 1)
        w = _bspline_weights(x - i, 0)
        # Normal equations in lower band form: band[k, r] = (A^T A + smooth D^T D)[r, r - k], k = 0..3.
        band = np.zeros((4, m))
        aty = np.zeros((m, y.shape[1]))
        for a in range(4):
            aty += np.stack(
                [np.bincount(i + a, weights=w[:, a] * y[:, d], minlength=m) for d in range(y.shape[1])], 1
            )
            for b in range(a + 1):
                band[a - b] += np.bincount(i + a, weights=w[:, a] * w[:, b], minlength=m)
        # D^T D of second differences (rows r, r+1, r+2 with 1, -2, 1).
        stencil = np.array([1.0, -2.0, 1.0])
        for a in range(3):
            for b in range(a + 1):
                np.add.at(band[a - b], np.arange(m - 2) + a, smooth * stencil[a] * stencil[b])
        coef = _solve_banded_spd(band, aty)
        return Spline(coef=coef, h=h, t0=t0)


# --------------------------------------------------------------------------------------------------
# Trajectories


@dataclass(frozen=True)
class Trajectory:
    """A smooth body trajectory T_wb(t) and the frame stamps it is observed at.

    Attributes:
        name: sequence name (log metadata `sequence`).
        frame_ns: [F] int64 frame timestamps, ns.
        position: spline of the body position (m, world frame) in s since frame_ns[0].
        quaternion: spline of the (unnormalised, sign-continuous) body-to-world quaternion wxyz.
        source: where the poses came from (a path, or "procedural seed=...").
    """

    name: str
    frame_ns: np.ndarray
    position: Spline
    quaternion: Spline
    source: str

    @property
    def t0_ns(self) -> int:
        return int(self.frame_ns[0])

    def seconds(self, t_ns: np.ndarray) -> np.ndarray:
        """s since the first frame (int64 difference first, then float: exact to the ns)."""
        return (np.asarray(t_ns, np.int64) - self.t0_ns) / 1e9

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position [N, 3] m, unit quaternion [N, 4] wxyz) at t (s since the first frame)."""
        return self.position(t), quat_normalize(self.quaternion(t))

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """m/s, world frame."""
        return self.position(t, 1)

    def acceleration(self, t: np.ndarray) -> np.ndarray:
        """m/s^2, world frame (kinematic; gravity not included)."""
        return self.position(t, 2)

    def angular_velocity(self, t: np.ndarray) -> np.ndarray:
        """Body angular rate (rad/s, body frame): omega = 2 vec(q^* dq/dt) with q = u / |u|."""
        u = self.quaternion(t)
        du = self.quaternion(t, 1)
        norm = np.linalg.norm(u, axis=-1, keepdims=True)
        q = u / norm
        dq = (du - q * np.sum(q * du, axis=-1, keepdims=True)) / norm
        return 2.0 * quat_mul(quat_conj(q), dq)[..., 1:]

    def specific_force(self, t: np.ndarray, gravity: np.ndarray = GRAVITY) -> np.ndarray:
        """What an ideal accelerometer reads: R^T (a - g), m/s^2, body frame."""
        _, q = self.pose(t)
        return quat_rotate(quat_conj(q), self.acceleration(t) - gravity)


def _continuous_sign(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs so consecutive samples lie in the same hemisphere (q and -q are equal)."""
    q = q.copy()
    flips = np.sum(q[1:] * q[:-1], axis=-1) < 0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def trajectory_from_poses(
    name: str,
    t_ns: np.ndarray,
    p: np.ndarray,
    q: np.ndarray,
    *,
    frame_ns: np.ndarray | None = None,
    knot_s: float = 0.1,
    smooth: float = 1e-3,
    source: str = "<memory>",
) -> Trajectory:
    """Fit smooth splines to sampled body poses.

    Arguments:
        t_ns: [N] int64 pose stamps. p: [N, 3] m. q: [N, 4] wxyz body-to-world.
        frame_ns: stamps of the frames to simulate (default t_ns); must lie within t_ns.
        knot_s: knot spacing, s (0.1: resolves motion up to about 5 Hz).
        smooth: curvature penalty (see Spline.fit).
    """
    t_ns = np.asarray(t_ns, np.int64)
    frame_ns = t_ns if frame_ns is None else np.asarray(frame_ns, np.int64)
    if frame_ns[0] < t_ns[0] or frame_ns[-1] > t_ns[-1]:
        raise ValueError(f"{name}: frame stamps reach beyond the poses ({source})")
    t = (t_ns - frame_ns[0]) / 1e9
    q = _continuous_sign(quat_normalize(np.asarray(q, float)))
    return Trajectory(
        name=name,
        frame_ns=frame_ns,
        position=Spline.fit(t, np.asarray(p, float), knot_s, smooth),
        quaternion=Spline.fit(t, q, knot_s, smooth),
        source=source,
    )


def read_yaml_matrix(path: str | os.PathLike, key: str = "T_BS") -> np.ndarray:
    """A 4 x 4 `key: {rows, cols, data: [...]}` matrix from a EuRoC sensor.yaml."""
    text = Path(path).read_text()
    start = text.find(key + ":")
    if start < 0:
        raise ValueError(f"{path}: no '{key}' entry")
    open_b = text.find("[", start)
    close_b = text.find("]", open_b)
    values = [float(v) for v in text[open_b + 1 : close_b].replace("\n", " ").split(",") if v.strip()]
    if len(values) != 16:
        raise ValueError(f"{path}: '{key}' has {len(values)} values, expected 16")
    return np.array(values).reshape(4, 4)


def read_stamped_rows(path: str | os.PathLike, n_values: int) -> tuple[np.ndarray, np.ndarray]:
    """(int64 ns stamps, float values [N, n_values]) of a CSV with '#' comments; stamps may carry a
    decimal fraction ('1403715274312143104.0000000000'), read exactly as integers."""
    stamps, rows = [], []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split(",")
            if len(fields) != n_values + 1:
                raise ValueError(f"{path}:{line_no}: expected {n_values + 1} fields, found {len(fields)}")
            stamps.append(int(fields[0].split(".")[0]))
            rows.append(fields[1:])
    return np.array(stamps, np.int64), np.array(rows, float)


def euroc_file_stem(sequence: str) -> str:
    """'MH_01' or 'MH01' -> 'MH01' (the stem of ORB-SLAM3's EuRoC files)."""
    if sequence in EUROC_SEQUENCES:
        return EUROC_SEQUENCES[sequence]
    if sequence in EUROC_SEQUENCES.values():
        return sequence
    raise ValueError(f"unknown EuRoC sequence {sequence!r}; known: {', '.join(EUROC_SEQUENCES)}")


def load_euroc_trajectory(
    sequence: str,
    gt_dir: str | os.PathLike,
    *,
    timestamps_dir: str | os.PathLike | None = None,
    t_bs: np.ndarray = EUROC_CAM0_T_BS,
    knot_s: float = 0.1,
    smooth: float = 1e-3,
) -> Trajectory:
    """A EuRoC sequence from ORB-SLAM3's left-camera ground truth (`<gt_dir>/MH01_GT.txt`, ...).

    The file holds T_wc (camera cam0 in the world) at the camera stamps; the body (IMU) pose is
    T_wb = T_wc inv(T_BS), T_BS being body <- camera. Frames are the ground-truth stamps, restricted to
    the image stamps of `<timestamps_dir>/MH01.txt` when that is given (ORB-SLAM3's frame list).

    Arguments:
        sequence: 'MH_01' ... 'V2_03' (or 'MH01').
        gt_dir: folder of the *_GT.txt files. timestamps_dir: optional folder of frame stamp lists.
        t_bs: 4 x 4 body <- camera (default EuRoC cam0's; see read_yaml_matrix).
    """
    stem = euroc_file_stem(sequence)
    path = Path(gt_dir) / f"{stem}_GT.txt"
    t_ns, values = read_stamped_rows(path, 7)
    # The files store the camera centre p_wc with the conjugate of q_wc (i.e. q_cw) despite their
    # 'q_RS' header: conjugating reproduces T_wb T_BS from EuRoC's body ground truth to 1e-7 and the
    # real gyro's rates (docs/simulator.md, "Ground truth"); positions are unaffected.
    p_wc, q_wc = values[:, :3], quat_conj(quat_normalize(values[:, 3:7]))
    r_cb = t_bs[:3, :3].T
    p_cb = -r_cb @ t_bs[:3, 3]
    q_cb = matrix_to_quat(r_cb)
    p_wb = p_wc + quat_rotate(q_wc, np.broadcast_to(p_cb, p_wc.shape))
    q_wb = quat_normalize(quat_mul(q_wc, np.broadcast_to(q_cb, q_wc.shape)))
    frame_ns = t_ns
    if timestamps_dir is not None:
        stamps_path = Path(timestamps_dir) / f"{stem}.txt"
        if stamps_path.is_file():
            stamps = np.loadtxt(stamps_path, dtype=np.int64, ndmin=1)
            frame_ns = t_ns[np.isin(t_ns, stamps)]
    name = (
        sequence if sequence in EUROC_SEQUENCES else next(k for k, v in EUROC_SEQUENCES.items() if v == stem)
    )
    return trajectory_from_poses(name, t_ns, p_wb, q_wb, frame_ns=frame_ns, knot_s=knot_s, smooth=smooth,
                                 source=str(path))  # fmt: skip


@dataclass(frozen=True)
class FlightProfile:
    """Ranges of the procedural flights (EuRoC-like; docs/simulator.md compares them with EuRoC).

    Attributes:
        duration_s: flight length range, s. mean_speed: target mean speed range, m/s.
        room: half extents of the flight volume, m (x, y, z). fps: frame rate.
        yaw_rate: typical yaw rate scale, rad/s. camera_pitch_deg: camera tilt below the horizon.
        periods_s: range of the periods of the path's sinusoids, s.
    """

    duration_s: tuple[float, float] = (80.0, 180.0)
    mean_speed: tuple[float, float] = (0.3, 1.0)
    room: tuple[float, float, float] = (4.0, 4.0, 1.0)
    fps: float = 20.0
    yaw_rate: float = 0.6
    periods_s: tuple[float, float] = (2.0, 60.0)
    camera_pitch_deg: tuple[float, float] = (5.0, 30.0)


PROCEDURAL_T0_NS = 1_600_000_000_000_000_000
"""Start stamp of procedural flights (an arbitrary epoch in 2020, far from EuRoC's 2014 stamps)."""


def procedural_trajectory(
    name: str, rng: np.random.Generator, profile: FlightProfile = FlightProfile()
) -> Trajectory:
    """An EuRoC-like flight: smooth 3D path in a room, quadrotor attitude, frames at profile.fps.

    The path is a sum of random sinusoids per axis (periods 10 to 60 s) scaled to fill the room and
    re-timed to the drawn mean speed; the body's x axis follows the thrust direction a - g (a
    quadrotor's attitude, as on the EuRoC MAV whose IMU x axis points up), the heading wanders with
    a slow random yaw, and the camera (body z) looks ahead, tilted down.
    """
    duration = rng.uniform(*profile.duration_s)
    target_speed = rng.uniform(*profile.mean_speed)
    n_terms = 6
    fine_dt = 0.01
    t_fine = np.arange(0.0, duration + 2 * fine_dt, fine_dt)
    # Periods log-uniform in profile.periods_s; amplitudes in proportion to the period, so that slow
    # terms carry the MAV across the room and fast ones make its manoeuvres and wobble.
    period = np.exp(rng.uniform(*np.log(profile.periods_s), size=(3, n_terms)))
    freq = 1.0 / period
    phase = rng.uniform(0, 2 * np.pi, size=(3, n_terms))
    amp = rng.uniform(0.5, 1.0, size=(3, n_terms)) * period
    amp /= amp.sum(axis=1, keepdims=True)
    amp *= np.asarray(profile.room)[:, None]

    omega = 2 * np.pi * freq

    def path(time_scale, order=0):
        w = omega[None] * time_scale
        arg = w * t_fine[:, None, None] + phase[None]
        wave = (np.sin, np.cos, lambda x: -np.sin(x))[order](arg)
        return np.sum(amp[None] * w**order * wave, axis=-1)

    # Re-time so that the mean speed matches the target (speed scales linearly with time_scale).
    scale = target_speed / np.mean(np.linalg.norm(path(1.0, 1), axis=1))
    p = path(scale)
    p[:, 2] += profile.room[2] + 0.5  # fly above the floor
    a = path(scale, 2)
    # Heading: slow random yaw (sum of sinusoids) around the direction of travel's mean.
    yaw_freq = rng.uniform(1 / 40, 1 / 4, size=3)
    yaw_phase = rng.uniform(0, 2 * np.pi, size=3)
    yaw_amp = profile.yaw_rate / (2 * np.pi * yaw_freq) / 3
    yaw = rng.uniform(-np.pi, np.pi) + np.sum(
        yaw_amp * np.sin(2 * np.pi * yaw_freq * t_fine[:, None] + yaw_phase), 1
    )
    up = a - GRAVITY  # thrust direction
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    forward = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], 1)
    pitch = np.deg2rad(rng.uniform(*profile.camera_pitch_deg))
    # Camera axis: forward tilted down, made orthogonal to the thrust axis.
    look = np.cos(pitch) * forward - np.sin(pitch) * np.array([0.0, 0.0, 1.0])
    z_b = look - up * np.sum(look * up, axis=1, keepdims=True)
    z_b /= np.linalg.norm(z_b, axis=1, keepdims=True)
    x_b = up
    y_b = np.cross(z_b, x_b)
    r_wb = np.stack([x_b, y_b, z_b], axis=-1)  # columns: body axes in the world
    q = matrix_to_quat(r_wb)

    period_ns = int(round(1e9 / profile.fps))
    n_frames = int(duration * profile.fps)
    frame_ns = PROCEDURAL_T0_NS + period_ns * np.arange(n_frames, dtype=np.int64)
    pose_ns = PROCEDURAL_T0_NS + np.round(t_fine * 1e9).astype(np.int64)
    return trajectory_from_poses(name, pose_ns, p, q, frame_ns=frame_ns, knot_s=0.05, smooth=1e-6,
                                 source=f"procedural {name}")  # fmt: skip
