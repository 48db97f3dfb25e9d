"""Simulator, IMU (host numpy, float64): synthesis along a trajectory and per-frame preintegration.

Part of the stand-in front-end (jsve.sim._simulate; docs/simulator.md). Plain numpy in float64: the
simulator's worker processes never dispatch to JAX, and IMU deltas need double precision. The IMU
prediction is jsve.core._imu's, computed with numpy (its `xp=np`); trajectories are jsve.sim._trajectory's.

    synthesize_imu             200 Hz gyro/accel from a trajectory with the ADIS16448 noise model
    read_imu_stream            a real EuRoC imu0 stream (t[ns], w, a)
    frame_substeps             IMU samples between consecutive frames, ORB-SLAM3's midpoint averaging
    preintegrate               dP, dV, dR per frame (ORB-SLAM3 IntegrateNewMeasurement), bias-corrected
    trailing_bias              the bias a sliding-window estimator would hold (oracle + lag)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from jsve.core import _imu
from jsve.sim._trajectory import GRAVITY, Trajectory, matrix_to_quat, read_stamped_rows, so3_exp

IMU_RATE_HZ = 200.0
"""ADIS16448 sampling rate in EuRoC."""

# EuRoC imu0 sensor.yaml (ADIS16448), as ORB-SLAM3's EuRoC Monocular-Inertial.yaml rounds them.
GYRO_NOISE_DENSITY = 1.7e-4  # rad/s/sqrt(Hz)
ACCEL_NOISE_DENSITY = 2.0e-3  # m/s^2/sqrt(Hz)
GYRO_RANDOM_WALK = 1.9e-5  # rad/s^2/sqrt(Hz)
ACCEL_RANDOM_WALK = 3.0e-3  # m/s^3/sqrt(Hz)


# --------------------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True)
class ImuStream:
    """IMU samples: t_ns [S] int64; gyro [S, 3] rad/s and accel [S, 3] m/s^2 in the body frame.

    bias_gyro, bias_accel: [S, 3] the true biases where known (synthetic streams), else None.
    """

    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    bias_gyro: np.ndarray | None = None
    bias_accel: np.ndarray | None = None
    source: str = "<memory>"


@dataclass(frozen=True)
class ImuNoise:
    """IMU error model: the ADIS16448 datasheet noise plus correlated in-flight errors.

    The datasheet terms (white noise and bias random walk, EuRoC's imu0 sensor.yaml) describe the
    sensor at rest. On the flying MAV the real EuRoC streams also carry errors correlated over
    seconds (vibration rectification, scale-factor and axis-misalignment errors under the flight's
    accelerations, and ground-truth attitude error when integrated against ground truth); they are
    modelled as first-order Gauss-Markov processes, the usual model of such errors, with the
    variance and correlation time that make dead reckoning drift as the real V1_01 stream drifts
    against its ground truth (analysis/imu_drift.py; docs/simulator.md, "IMU"). `datasheet()`
    leaves them out.

    Attributes:
        gyro_density, accel_density: white noise, rad/s/sqrt(Hz) and m/s^2/sqrt(Hz).
        gyro_walk, accel_walk: bias random walk, rad/s^2/sqrt(Hz) and m/s^3/sqrt(Hz).
        gyro_bias0, accel_bias0: standard deviation of the initial bias per axis, rad/s and m/s^2
            (EuRoC's estimated biases reach 0.08 rad/s and 0.55 m/s^2).
        gyro_gm, accel_gm: stationary standard deviation of the Gauss-Markov errors per axis.
        gyro_gm_tau, accel_gm_tau: their correlation times, s.
    """

    gyro_density: float = GYRO_NOISE_DENSITY
    accel_density: float = ACCEL_NOISE_DENSITY
    gyro_walk: float = GYRO_RANDOM_WALK
    accel_walk: float = ACCEL_RANDOM_WALK
    gyro_bias0: float = 0.03
    accel_bias0: float = 0.1
    gyro_gm: float = 0.006
    gyro_gm_tau: float = 10.0
    accel_gm: float = 0.07
    accel_gm_tau: float = 5.0

    @classmethod
    def datasheet(cls) -> ImuNoise:
        """Only the ADIS16448 datasheet terms (no in-flight correlated errors)."""
        return cls(gyro_gm=0.0, accel_gm=0.0)


def gauss_markov(
    rng: np.random.Generator, t: np.ndarray, sigma: float, tau: float, dim: int = 3
) -> np.ndarray:
    """A stationary first-order Gauss-Markov (Ornstein-Uhlenbeck) process sampled at times t (s).

    x_i = a_i x_(i-1) + sigma sqrt(1 - a_i^2) n_i with a_i = exp(-(t_i - t_(i-1)) / tau): exact for any
    spacing. Solved in closed form in blocks (no Python loop over samples).
    """
    n = len(t)
    out = np.zeros((n, dim))
    if sigma == 0.0 or n == 0:
        return out
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / tau)
    z = rng.normal(0.0, 1.0, (n, dim)) * (sigma * np.sqrt(1.0 - a * a))[:, None]
    z[0] = rng.normal(0.0, sigma, dim)
    block = max(1, int(tau / max(np.median(dt[1:]) if n > 1 else tau, 1e-9)))  # a^-block stays ~e^1
    carry = np.zeros(dim)
    for start in range(0, n, block):
        sl = slice(start, min(n, start + block))
        # x_i = A_i (carry + sum_{j<=i} z_j / A_j), A_i = prod_{j<=i} a_j within the block
        log_a = np.cumsum(np.log(a[sl]))
        A = np.exp(log_a)[:, None]
        out[sl] = A * (carry + np.cumsum(z[sl] / A, axis=0))
        carry = out[sl.stop - 1]
    return out


def imu_sample_times(frame_ns: np.ndarray, rate_hz: float = IMU_RATE_HZ) -> np.ndarray:
    """IMU stamps: every frame interval cut into round(dt rate) equal steps (frame stamps included).

    EuRoC's camera is triggered by the IMU clock, so its frames fall on IMU samples; a dropped frame
    (a 100 ms interval) simply holds 20 samples.
    """
    frame_ns = np.asarray(frame_ns, np.int64)
    gaps = np.diff(frame_ns)
    steps = np.maximum(1, np.round(gaps * rate_hz / 1e9).astype(np.int64))
    offsets = np.concatenate([[0], np.cumsum(steps)])
    k = np.arange(offsets[-1])
    interval = np.searchsorted(offsets, k, side="right") - 1
    within = k - offsets[interval]
    t = frame_ns[interval] + (gaps[interval] * within) // steps[interval]
    return np.concatenate([t, frame_ns[-1:]])


def synthesize_imu(
    trajectory: Trajectory,
    rng: np.random.Generator,
    noise: ImuNoise | None = ImuNoise(),
    rate_hz: float = IMU_RATE_HZ,
    gravity: np.ndarray = GRAVITY,
) -> ImuStream:
    """Gyro and accelerometer samples of the trajectory under the ImuNoise model.

    The ideal readings are the spline's body rate and specific force R^T (a - g). Discrete noise per
    sample: density / sqrt(dt); bias increments: walk sqrt(dt) (Brownian motion sampled at the IMU
    rate); then the Gauss-Markov in-flight errors. The stream's bias_* hold the random-walk biases
    (the Gauss-Markov part is not a bias an estimator could know). noise=None gives the ideal
    readings with zero bias.
    """
    t_ns = imu_sample_times(trajectory.frame_ns, rate_hz)
    t = trajectory.seconds(t_ns)
    gyro = trajectory.angular_velocity(t)
    accel = trajectory.specific_force(t, gravity)
    if noise is None:
        zero = np.zeros_like(gyro)
        return ImuStream(t_ns, gyro, accel, zero, zero.copy(), source=f"ideal {trajectory.name}")
    dt = np.diff(t, prepend=t[0] - 1.0 / rate_hz)
    dt_nominal = 1.0 / rate_hz
    n = len(t)
    bg = rng.normal(0, noise.gyro_bias0, 3) + np.cumsum(
        rng.normal(0, 1, (n, 3)) * noise.gyro_walk * np.sqrt(dt)[:, None], axis=0
    )
    ba = rng.normal(0, noise.accel_bias0, 3) + np.cumsum(
        rng.normal(0, 1, (n, 3)) * noise.accel_walk * np.sqrt(dt)[:, None], axis=0
    )
    gyro = gyro + bg + rng.normal(0, noise.gyro_density / math.sqrt(dt_nominal), (n, 3))
    accel = accel + ba + rng.normal(0, noise.accel_density / math.sqrt(dt_nominal), (n, 3))
    gyro += gauss_markov(rng, t, noise.gyro_gm, noise.gyro_gm_tau)
    accel += gauss_markov(rng, t, noise.accel_gm, noise.accel_gm_tau)
    return ImuStream(t_ns, gyro, accel, bg, ba, source=f"synthetic {trajectory.name}")


def read_imu_stream(path: str | os.PathLike) -> ImuStream:
    """A EuRoC imu0 CSV (t[ns], wx, wy, wz [rad/s], ax, ay, az [m/s^2]), one header line."""
    t_ns, rows = read_stamped_rows(path, 6)
    return ImuStream(t_ns, rows[:, :3], rows[:, 3:], source=os.fspath(path))


@dataclass(frozen=True)
class Substeps:
    """IMU integration steps of every frame interval, padded: arrays [F, S] (frame 0 has none).

    dt: s (0 on padding). gyro, accel: [F, S, 3] midpoint readings (ORB-SLAM3 averages the two
    samples bounding each step). t_mid: [F, S] s since the first frame, at each step's midpoint.
    """

    dt: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    t_mid: np.ndarray


def frame_substeps(imu: ImuStream, frame_ns: np.ndarray) -> Substeps:
    """Cut an IMU stream into the steps between consecutive frames, as Tracking::PreintegrateIMU.

    Samples inside [t_{k-1}, t_k] are used; where a frame stamp falls between two samples the
    reading there is linearly interpolated (ORB-SLAM3's first/last-step interpolation). Each step
    integrates the mean of the readings at its two ends.
    """
    frame_ns = np.asarray(frame_ns, np.int64)
    if imu.t_ns[0] > frame_ns[0] or imu.t_ns[-1] < frame_ns[-1]:
        raise ValueError(f"IMU stream {imu.source} does not cover the frames")
    t_all = np.union1d(imu.t_ns[(imu.t_ns >= frame_ns[0]) & (imu.t_ns <= frame_ns[-1])], frame_ns)
    rel = (imu.t_ns - frame_ns[0]) / 1e9
    x = (t_all - frame_ns[0]) / 1e9
    gyro = np.stack([np.interp(x, rel, imu.gyro[:, j]) for j in range(3)], -1)
    accel = np.stack([np.interp(x, rel, imu.accel[:, j]) for j in range(3)], -1)
    frame_of_step = np.searchsorted(frame_ns, t_all[:-1], side="right")  # step [t_i, t_i+1] -> frame k
    counts = np.bincount(frame_of_step, minlength=len(frame_ns))
    n_sub = int(counts.max())
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(frame_of_step)) - start[frame_of_step]
    F = len(frame_ns)
    dt = np.zeros((F, n_sub))
    g = np.zeros((F, n_sub, 3))
    a = np.zeros((F, n_sub, 3))
    tm = np.zeros((F, n_sub))
    dt[frame_of_step, slot] = np.diff(x)
    g[frame_of_step, slot] = 0.5 * (gyro[:-1] + gyro[1:])
    a[frame_of_step, slot] = 0.5 * (accel[:-1] + accel[1:])
    tm[frame_of_step, slot] = 0.5 * (x[:-1] + x[1:])
    return Substeps(dt=dt, gyro=g, accel=a, t_mid=tm)


def preintegrate(steps: Substeps, bias_gyro: np.ndarray, bias_accel: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-frame preintegration, ORB-SLAM3 v1.0 IMU::Preintegrated::IntegrateNewMeasurement.

    For each step (midpoint readings minus the bias estimate): dP += dV dt + 0.5 dR a dt^2;
    dV += dR a dt; dR = dR Exp(w dt). Expressed in the previous frame's body frame.

    Arguments:
        steps: from frame_substeps. bias_gyro, bias_accel: [F, 3] (or [3]) the estimate used for the
            interval ending at each frame (rad/s, m/s^2).
    Returns:
        (dt [F] s, dp [F, 3] m, dv [F, 3] m/s, dq [F, 4] wxyz); frame 0 is (0, 0, 0, identity).
    """
    F, S = steps.dt.shape
    bg = np.broadcast_to(bias_gyro, (F, 3))
    ba = np.broadcast_to(bias_accel, (F, 3))
    dp = np.zeros((F, 3))
    dv = np.zeros((F, 3))
    dr = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
    for s in range(S):
        h = steps.dt[:, s, None]
        acc = steps.accel[:, s] - ba
        w = steps.gyro[:, s] - bg
        ra = np.einsum("fij,fj->fi", dr, acc)
        dp += dv * h + 0.5 * ra * h * h
        dv += ra * h
        dr = dr @ so3_exp(w * h)
    dq = matrix_to_quat(dr)
    dq[0] = (1.0, 0.0, 0.0, 0.0)
    dp[0] = 0.0
    dv[0] = 0.0
    return steps.dt.sum(axis=1), dp, dv, dq


def trailing_bias(
    imu: ImuStream, trajectory: Trajectory, window_s: float = 10.0, gravity: np.ndarray = GRAVITY
) -> tuple[np.ndarray, np.ndarray]:
    """The biases a sliding-window estimator with perfect motion knowledge would hold at each sample.

    Mean of (measurement - ideal reading) over the trailing window [t - window_s, t] (the first
    window_s seconds use the first window). Works the same on real and synthetic streams, so
    the two are compared on equal terms (analysis/imu_drift.py).

    Returns:
        (bias_gyro, bias_accel), [S, 3] each.
    """
    t = trajectory.seconds(imu.t_ns)
    inside = (t >= 0) & (t <= trajectory.position.t_end)
    tt = np.clip(t, 0.0, trajectory.position.t_end)
    res_g = np.where(inside[:, None], imu.gyro - trajectory.angular_velocity(tt), 0.0)
    res_a = np.where(inside[:, None], imu.accel - trajectory.specific_force(tt, gravity), 0.0)
    csum_g = np.concatenate([np.zeros((1, 3)), np.cumsum(res_g, axis=0)])
    csum_a = np.concatenate([np.zeros((1, 3)), np.cumsum(res_a, axis=0)])
    cnt = np.concatenate([[0], np.cumsum(inside)])
    t_first = t[inside][0]
    hi = np.searchsorted(t, t, side="right")
    lo = np.searchsorted(t, np.maximum(t - window_s, t_first), side="left")
    short = t < t_first + window_s
    hi = np.where(short, np.searchsorted(t, t_first + window_s, side="right"), hi)
    lo = np.where(short, np.searchsorted(t, t_first, side="left"), lo)
    n = np.maximum(cnt[hi] - cnt[lo], 1)[:, None]
    return (csum_g[hi] - csum_g[lo]) / n, (csum_a[hi] - csum_a[lo]) / n


def frame_bias_estimate(
    imu: ImuStream, trajectory: Trajectory, *, window_s: float = 10.0, t_init_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The bias estimate each frame's preintegration is corrected with, [F, 3] gyro and accel.

    ORB-SLAM3 preintegrates the interval ending at frame k with the estimate held at frame k - 1;
    that estimate is modelled as `trailing_bias` (a sliding-window estimator) sampled at frame
    k - 1, and zero before the IMU is initialised at t_init_s (ORB-SLAM3 starts from zero biases).
    """
    bg, ba = trailing_bias(imu, trajectory, window_s)
    idx = np.clip(np.searchsorted(imu.t_ns, trajectory.frame_ns), 0, len(imu.t_ns) - 1)
    held = np.concatenate([[0], np.arange(len(idx) - 1)])  # frame k uses frame k - 1's estimate
    t_prev = trajectory.seconds(trajectory.frame_ns)[held]
    ready = (t_prev >= t_init_s)[:, None]
    return np.where(ready, bg[idx[held]], 0.0), np.where(ready, ba[idx[held]], 0.0)


def imu_predict(p, v, q, dt, dp, dv, dq, gravity=GRAVITY):
    """jsve.core._imu.imu_predict (ORB-SLAM3's PredictStateIMU) in numpy float64; gravity m/s^2, world."""
    return _imu.imu_predict(p, v, q, np.asarray(dt), dp, dv, dq, np.asarray(gravity), xp=np)


def dead_reckoning_drift(
    trajectory: Trajectory,
    preintegration: tuple[np.ndarray, ...],
    *,
    horizons_s=(1.0, 2.0, 5.0),
    start_every_s: float = 1.0,
    skip_s: float = 10.0,
    gravity: np.ndarray = GRAVITY,
) -> dict[float, np.ndarray]:
    """Position error of IMU-only prediction from the true state, per start and horizon.

    From every start frame (every start_every_s after skip_s) the true position, velocity and
    orientation are propagated with the per-frame preintegration (dt, dp, dv, dq) alone, as the
    replay does in RECENTLY_LOST, and compared with the true position after each horizon.

    Returns:
        horizon (s) -> [starts] position errors, m.
    """
    dt, dp, dv, dq = preintegration
    t = trajectory.seconds(trajectory.frame_ns)
    p_true, q_true = trajectory.pose(t)
    v_true = trajectory.velocity(t)
    longest = max(horizons_s)
    last = np.searchsorted(t, t[-1] - longest, side="right")
    first = np.searchsorted(t, skip_s)
    starts = np.unique(np.searchsorted(t, np.arange(t[first], t[max(first, last - 1)] + 1e-9, start_every_s)))
    p, v, q = p_true[starts], v_true[starts], q_true[starts]
    k = starts.copy()
    out = {}
    for horizon in sorted(horizons_s):
        target = t[starts] + horizon
        while True:
            move = (k + 1 < len(t)) & (t[np.minimum(k + 1, len(t) - 1)] <= target + 1e-6)
            if not move.any():
                break
            kk = np.where(move, k + 1, k)
            p2, v2, q2 = imu_predict(p, v, q, dt[kk], dp[kk], dv[kk], dq[kk], gravity)
            m = move[:, None]
            p, v, q, k = np.where(m, p2, p), np.where(m, v2, v), np.where(m, q2, q), kk
        out[horizon] = np.linalg.norm(p - p_true[k], axis=1)
    return out
