"""Known-answer tracking logs for the objective and fitting tests, built directly (no simulator).

A smooth flight (sums of sines; yaw, pitch, roll swing) is the ground truth. The IMU preintegration
between frames is exact for that flight, up to a small constant accelerometer bias, so that coasting
on the IMU for one frame costs micrometres and for five seconds decimetres. The visual estimate is the
truth on good frames and a gross error (decimetres to a metre, in position and velocity) on bad ones.
Two kinds of bad frames:

- "counts": visual tracking is catastrophic exactly when fewer than K inliers are tracked. Good frames
  have K or more inliers (many of them just K..K+3, so that a threshold above K rejects good frames),
  bad frames K-1 or fewer. ORB-SLAM3's own rule with imu_init = K accepts exactly the good frames.
- "occlusion": most bad frames have as many inliers as good ones but all their keypoints sit in a few
  SVE bins (S_b ~ 0: the geometry is bad), which an inlier count cannot see; a few bad frames have
  few inliers. Good frames spread their keypoints over 16-64 bins (S_b 0.5-1).

Bad episodes last 0.2-2.5 s (less than ORB-SLAM3's 5 s RECENTLY_LOST timer) and begin after the
first second, so the relocalisation window of the first map sees good frames only. The IMU is
initialised from frame 0 (imu_init_delay 0): the `not_init` threshold never decides a frame.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from jsve.io import _schema as schema
from jsve.io._schema import RunLog
from jsve.sim._trajectory import matrix_to_quat, quat_normalize, quat_to_matrix

GRAVITY = np.array([0.0, 0.0, -9.81])
FPS = 20.0
T0_NS = 1_403_715_274_312_143_104
N_EXTRACTED = 1000


def _euler_matrix(yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    rz = np.stack(
        [
            np.stack([cy, -sy, 0 * cy], -1),
            np.stack([sy, cy, 0 * cy], -1),
            np.stack([0 * cy, 0 * cy, 1 + 0 * cy], -1),
        ],
        -2,
    )
    ry = np.stack(
        [
            np.stack([cp, 0 * cp, sp], -1),
            np.stack([0 * cp, 1 + 0 * cp, 0 * cp], -1),
            np.stack([-sp, 0 * cp, cp], -1),
        ],
        -2,
    )
    rx = np.stack(
        [
            np.stack([1 + 0 * cr, 0 * cr, 0 * cr], -1),
            np.stack([0 * cr, cr, -sr], -1),
            np.stack([0 * cr, sr, cr], -1),
        ],
        -2,
    )
    return rz @ ry @ rx


def flight(n_frames: int, rng: np.random.Generator):
    """Ground truth: t (s), p (m), v (m/s), R (body to world) of a smooth flight."""
    t = np.arange(n_frames) / FPS
    amp = rng.uniform(1.0, 3.0, 3)
    omega = rng.uniform(0.25, 0.6, 3)
    phase = rng.uniform(0, 2 * np.pi, 3)
    p = amp * np.sin(omega * t[:, None] + phase)
    v = amp * omega * np.cos(omega * t[:, None] + phase)
    a_ang = rng.uniform(0.3, 0.6, 4)
    yaw = 1.2 * np.sin(a_ang[0] * t + phase[0])
    pitch = 0.15 * np.sin(a_ang[1] * t + phase[1])
    roll = 0.15 * np.sin(a_ang[2] * t + phase[2])
    return t, p, v, _euler_matrix(yaw, pitch, roll)


def preintegration(p, v, rot, dt, accel_bias):
    """dP, dV, dR from each frame to the next, in the previous body frame, that make ORB-SLAM3's
    PredictStateIMU (p2 = p1 + v1 dt + g dt^2 / 2 + R1 dP; v2 = v1 + g dt + R1 dV; R2 = R1 dR) exact
    for the flight, plus the effect of a constant accelerometer bias (body frame, m/s^2)."""
    d = dt[1:, None]
    r1t = np.swapaxes(rot[:-1], -1, -2)
    dp = (
        np.einsum("kij,kj->ki", r1t, p[1:] - p[:-1] - v[:-1] * d - 0.5 * GRAVITY * d * d)
        + 0.5 * accel_bias * d * d
    )
    dv = np.einsum("kij,kj->ki", r1t, v[1:] - v[:-1] - GRAVITY * d) + accel_bias * d
    dq = matrix_to_quat(r1t @ rot[1:])
    zero = np.zeros((1, 3))
    return (
        np.concatenate([zero, dp]),
        np.concatenate([zero, dv]),
        np.concatenate([[[1.0, 0.0, 0.0, 0.0]], dq]),
    )


def bad_episodes(n_frames: int, rng: np.random.Generator, rate_per_s: float) -> np.ndarray:
    """[F] bool: frames in bad episodes of 0.2-2.5 s, none in the first second."""
    bad = np.zeros(n_frames, bool)
    k = int(FPS)
    while True:
        k += int(rng.exponential(FPS / rate_per_s)) + 1
        if k >= n_frames:
            return bad
        length = int(rng.uniform(0.2, 2.5) * FPS)
        bad[k : k + length] = True
        k += length


def _spread_bins(rng, n, n_bins_lo, n_bins_hi):
    """[n, 64] keypoint counts summing to N_EXTRACTED, spread evenly over a random number of bins."""
    out = np.zeros((n, schema.N_BINS), np.int64)
    for i in range(n):
        m = int(rng.integers(n_bins_lo, n_bins_hi + 1))
        chosen = rng.choice(schema.N_BINS, m, replace=False)
        out[i, chosen] = rng.multinomial(N_EXTRACTED, np.full(m, 1.0 / m))
    return out


def make_run(
    kind: str,
    seed: int,
    *,
    k_min: int = 40,
    n_frames: int = 600,
    sequence: str = "KA",
    disturbance: str = "none",
    level: int = 0,
    accel_bias: float = 0.05,
) -> RunLog:
    """One known-answer run of `kind` "counts" or "occlusion" (see the module docstring).

    Arguments:
        k_min: K, the fewest inliers with which visual tracking is still right.
        accel_bias: m/s^2, the IMU's constant accelerometer bias (norm; random direction).
    """
    rng = np.random.default_rng(seed)
    t, p, v, rot = flight(n_frames, rng)
    t_ns = T0_NS + np.round(t * 1e9).astype(np.int64)
    dt = np.concatenate([[0.0], np.diff(t_ns) * 1e-9])
    bias = rng.normal(size=3)
    bias *= accel_bias / np.linalg.norm(bias)
    dp, dv, dq = preintegration(p, v, rot, dt, bias)

    n = n_frames
    if kind == "counts":
        bad = bad_episodes(n, rng, rate_per_s=0.15)
        marginal = rng.random(n) < 0.5  # half the good frames are just above K
        inliers = np.where(marginal, rng.integers(k_min, k_min + 4, n), rng.integers(k_min, k_min + 200, n))
        inliers = np.where(bad, rng.integers(max(k_min - 30, 0), k_min, n), inliers)
        bins = _spread_bins(rng, n, 16, 64)
    elif kind == "occlusion":
        occluded = bad_episodes(n, rng, rate_per_s=0.15)
        weak = bad_episodes(n, rng, rate_per_s=0.03) & ~occluded
        bad = occluded | weak
        inliers = rng.integers(80, 300, n)
        inliers = np.where(weak, rng.integers(max(k_min - 30, 0), k_min, n), inliers)
        bins = np.where(occluded[:, None], _spread_bins(rng, n, 3, 6), _spread_bins(rng, n, 16, 64))
    else:
        raise ValueError(f"kind must be 'counts' or 'occlusion', got {kind!r}")
    frustum = np.round(inliers / rng.uniform(0.55, 0.9, n)).astype(np.int64)

    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    vis_p = p + bad[:, None] * direction * rng.uniform(0.3, 1.0, (n, 1))
    vis_v = v + bad[:, None] * rng.normal(scale=0.3, size=(n, 3))
    q = quat_normalize(matrix_to_quat(rot))

    cols = {
        "t_ns": t_ns,
        "state": np.full(n, schema.STATE_OK),
        "imu_init": np.ones(n, np.int64),
        "map_id": np.zeros(n, np.int64),  # one map, inertial BA2 done from frame 0: a failure never resets
        "imu_ba2": np.ones(n, np.int64),
        "n_extracted": np.full(n, N_EXTRACTED),
        "n_inliers": inliers.astype(np.int64),
        "n_frustum": frustum,
    }
    for j, c in enumerate(schema.BIN_COLUMNS):
        cols[c] = bins[:, j]
    for names, values in (
        (schema.VIS_POSITION, vis_p),
        (schema.VIS_QUATERNION, q),
        (schema.VIS_VELOCITY, vis_v),
        (schema.IMU_DP, dp),
        (schema.IMU_DV, dv),
        (schema.IMU_DQ, dq),
        (schema.GT_POSITION, p),
        (schema.GT_QUATERNION, q),
    ):
        for j, c in enumerate(names):
            cols[c] = np.ascontiguousarray(values[:, j], dtype=np.float64)
    cols["imu_dt"] = dt
    meta = {
        "sequence": sequence,
        "disturbance": disturbance,
        "level": level,
        "run": seed,
        "fps": FPS,
        "gravity": GRAVITY.tolist(),
        "n_features": N_EXTRACTED,
        "frontend": "tests/knownanswer.py",
    }
    assert np.allclose(quat_to_matrix(q), rot, atol=1e-12)
    return RunLog(
        meta=meta, frames=pd.DataFrame(cols, columns=list(schema.COLUMNS)), source=f"<{kind} {seed}>"
    )


def lose_map(run: RunLog, start: int, stop: int | None = None, *, blind: bool = True) -> RunLog:
    """The run with its recorded map lost on frames [start, stop): state LOST and no pose there (the
    recorded run's rule gave up where a more permissive one could have kept tracking). Frames from
    `stop` on, if any, are a new recorded map (map_id + 1). `blind`: no inlier matches on the lost
    frames (n_inliers = n_frustum = 0, as when ORB-SLAM3 does not track them); otherwise they keep
    their counts, so a rule that would have kept tracking needs poses the log does not have."""
    frames = run.frames.copy()
    stop = len(frames) if stop is None else stop
    rows = slice(start, stop - 1)  # .loc slices include their end
    frames.loc[rows, list(schema.VIS_COLUMNS)] = np.nan
    frames.loc[rows, "state"] = schema.STATE_LOST
    if blind:
        frames.loc[rows, ["n_inliers", "n_frustum"]] = 0
    if stop < len(frames):
        frames.loc[stop:, "map_id"] = frames["map_id"].iloc[0] + 1
    return RunLog(meta=run.meta, frames=frames, source=f"{run.source} lost {start}-{stop}")


def make_study(kind: str, seeds, **kwargs) -> list[RunLog]:
    """Runs of `kind` for every seed, spread over 3 sequences and 2 'levels' (metadata for CV tests)."""
    runs = []
    for i, seed in enumerate(seeds):
        runs.append(
            make_run(kind, int(seed), sequence=f"S{i % 3}", disturbance=kind, level=(i // 3) % 2, **kwargs)
        )
    return runs
