"""Test oracle: ORB-SLAM3 v1.0's tracking state machine and the replay, as a plain Python loop.

Written from the specification (DESIGN.md section 5 and the model stated in jsve/core/_rules.py), not from
jsve's code: explicit if/else on integer modes, Python floats (or numpy float32 scalars, to mirror a
float32 replay operation by operation), numpy only for the pose algebra, with its own quaternion
product and rotation. It must not import jsve.core._rules or jsve.core._geometry.

The model, per frame k at time t (s since the first frame), score s:

    imu_usable  = logged imu_init[k] and t - map_start_t >= imu_init_delay
    in_reloc    = k < map_start_k + int(fps)      (ORB-SLAM3 mMaxFrames is an int set from Camera.fps)
    success(rl, imu) = Tracking::TrackLocalMap:
        in_reloc and s < reloc            -> fail
        rl and s > recovery               -> success
        imu: s < imu_init -> fail;  not imu: s < not_init -> fail;  else success
    OK:   success(False, imu_usable) -> OK, visual pose
          else if imu_usable -> RECENTLY_LOST, t_lost = t, IMU prediction
          else -> LOST (ORB-SLAM3 resets the active map), no estimate
    RECENTLY_LOST: t - t_lost > time_recently_lost -> LOST, no estimate (no attempt on this frame)
          else success(True, imu_usable) -> OK, visual pose; else stay, IMU prediction
    LOST: success(False, False) with in_reloc forced on -> new map: OK, segment + 1,
          map_start = this frame, visual pose; else stay LOST, no estimate.

Initial state: OK in map 0 that started at frame 0; the previous state is frame 0's visual
pose and velocity. IMU prediction (PredictStateIMU), from the previous frame's replayed state:
R2 = R1 dR; v2 = v1 + g dt + R1 dV; p2 = p1 + v1 dt + 0.5 g dt^2 + R1 dP.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OK, RECENTLY_LOST, LOST = 0, 1, 2


def qmul(a, b):
    """Hamilton product of wxyz quaternions (numpy, one pair)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def qconj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


def qrotate(q, v):
    """R(q) v computed as the vector part of q (0, v) q*: a different route from jsve's."""
    return qmul(qmul(q, np.array([0.0, v[0], v[1], v[2]])), qconj(q))[1:]


def qmatrix(q):
    """Rotation matrix of a unit wxyz quaternion."""
    return np.stack([qrotate(q, e) for e in np.eye(3)], axis=1)


def imu_predict(p, v, q, dt, dp, dv, dq, g):
    """PredictStateIMU: one step of the dead reckoning from the previous body state."""
    p2 = p + v * dt + 0.5 * g * dt * dt + qrotate(q, dp)
    v2 = v + g * dt + qrotate(q, dv)
    q2 = qmul(q, dq)
    return p2, v2, q2


@dataclass
class OracleResult:
    """Per-frame outcome for the n frames of one run (no padding)."""

    accepted: np.ndarray  # bool [n]
    predicted: np.ndarray  # bool [n]
    has_estimate: np.ndarray  # bool [n]
    mode: np.ndarray  # int8 [n], mode after the frame
    segment: np.ndarray  # int [n]
    lost_any: bool
    position: np.ndarray | None = None  # [n, 3], NaN where no estimate
    quaternion: np.ndarray | None = None  # [n, 4]
    velocity: np.ndarray | None = None  # [n, 3]


def success(score, th, recently_lost, imu_usable, in_reloc):
    """Tracking::TrackLocalMap's decision with the rule's thresholds."""
    if in_reloc and score < th["reloc"]:
        return False
    if recently_lost and score > th["recovery"]:
        return True
    if imu_usable:
        return not (score < th["imu_init"])
    return not (score < th["not_init"])


@dataclass
class State:
    """The machine's state between frames (ORB-SLAM3: mState, mTimeStampLost, the map's start)."""

    mode: int = OK
    t_lost: float = 0.0
    map_start_t: float = 0.0
    map_start_k: int = 0
    segment: int = 0


def step(state, score, t, k, imu_init, th, fps, imu_init_delay, time_recently_lost=5.0):
    """One frame of the machine. All of score, t, thresholds, delay and the limit must already be
    of one scalar type (Python float, or np.float32 to mirror float32 arithmetic).

    Returns (next_state, use_visual, use_imu).
    """
    imu_usable = bool(imu_init) and (t - state.map_start_t >= imu_init_delay)
    in_reloc = k < state.map_start_k + int(fps)
    nxt = State(state.mode, state.t_lost, state.map_start_t, state.map_start_k, state.segment)
    use_visual = use_imu = False
    if state.mode == OK:
        if success(score, th, False, imu_usable, in_reloc):
            use_visual = True
        elif imu_usable:
            nxt.mode, nxt.t_lost, use_imu = RECENTLY_LOST, t, True
        else:
            nxt.mode = LOST  # ORB-SLAM3 resets the map before the IMU is usable
    elif state.mode == RECENTLY_LOST:
        if t - state.t_lost > time_recently_lost:
            nxt.mode = LOST  # no recovery attempt on this frame
        elif success(score, th, True, imu_usable, in_reloc):
            nxt.mode, use_visual = OK, True
        else:
            use_imu = True  # the timer is not restarted
    else:  # LOST: a new monocular map must pass the strict test without the IMU
        if success(score, th, False, False, True):
            nxt.mode, use_visual = OK, True
            nxt.segment += 1
            nxt.map_start_t, nxt.map_start_k = t, k
    return nxt, use_visual, use_imu


def replay_run(
    score,
    t,
    imu_init,
    fps,
    imu_init_delay,
    thresholds,
    time_recently_lost=5.0,
    poses=None,
    real=float,
) -> OracleResult:
    """Replay one run frame by frame.

    Arguments:
        score, t, imu_init: per-frame sequences of the run's n frames (t in s since the first frame).
        fps: frames per second (the relocalisation window is int(fps) frames).
        imu_init_delay: s a map needs before its IMU is usable.
        thresholds: dict with imu_init, not_init, reloc, recovery.
        poses: None (decisions only) or a dict of numpy arrays vis_p, vis_q, vis_v [n, 3|4|3],
            imu_dt [n], imu_dp, imu_dv [n, 3], imu_dq [n, 4], gravity [3].
        real: the scalar type of the time and score arithmetic: float (IEEE double) or np.float32
            (to mirror a float32 replay: every subtraction and comparison rounds to float32).
    """
    n = len(t)
    th = {key: real(value) for key, value in thresholds.items()}
    t = [real(x) for x in t]
    score = [real(x) for x in score]
    delay, limit = real(imu_init_delay), real(time_recently_lost)

    state = State(t_lost=real(0.0), map_start_t=real(0.0))
    accepted = np.zeros(n, bool)
    predicted = np.zeros(n, bool)
    modes = np.zeros(n, np.int8)
    segments = np.zeros(n, np.int64)
    if poses is not None:
        g = np.asarray(poses["gravity"], float)
        p, v, q = (np.asarray(poses[key][0], float) for key in ("vis_p", "vis_v", "vis_q"))
        out_p, out_q, out_v = np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full((n, 3), np.nan)

    for k in range(n):
        state, use_visual, use_imu = step(state, score[k], t[k], k, imu_init[k], th, fps, delay, limit)
        accepted[k], predicted[k] = use_visual, use_imu
        modes[k], segments[k] = state.mode, state.segment
        if poses is None:
            continue
        if use_visual:
            p, v, q = (np.asarray(poses[key][k], float) for key in ("vis_p", "vis_v", "vis_q"))
        elif use_imu:
            delta = (np.asarray(poses[key][k], float) for key in ("imu_dp", "imu_dv", "imu_dq"))
            p, v, q = imu_predict(p, v, q, float(poses["imu_dt"][k]), *delta, g)
        # LOST frames have no estimate; the next estimate is a new map's visual pose.
        if use_visual or use_imu:
            out_p[k], out_v[k], out_q[k] = p, v, q

    result = OracleResult(
        accepted=accepted, predicted=predicted, has_estimate=accepted | predicted, mode=modes,
        segment=segments, lost_any=bool(np.any(modes == LOST)),
    )  # fmt: skip
    if poses is not None:
        result.position, result.quaternion, result.velocity = out_p, out_q, out_v
    return result


def dead_reckon(p0, v0, q0, imu_dt, imu_dp, imu_dv, imu_dq, gravity):
    """Pure IMU integration from (p0, v0, q0) at frame 0 through frames 1..n-1 (frame 0's own
    preintegration is applied too: it is zero in a log that starts there). Returns [n] states."""
    n = len(imu_dt)
    g = np.asarray(gravity, float)
    p, v, q = np.asarray(p0, float), np.asarray(v0, float), np.asarray(q0, float)
    P, V, Q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    for k in range(n):
        p, v, q = imu_predict(p, v, q, float(imu_dt[k]), imu_dp[k], imu_dv[k], imu_dq[k], g)
        P[k], V[k], Q[k] = p, v, q
    return P, V, Q


# ----------------------------------------------------------------------------------------------
# Random tracking logs for the property tests (numpy only; no jsve).

INLIER_EDGES = (9, 10, 11, 14, 15, 16, 49, 50, 51)
"""Inlier counts at and next to ORB-SLAM3's thresholds 10 / 15 / 50 (exact ties included)."""
SVE_EDGES = (0.04, 0.06, 0.2)


def random_unit_quaternions(rng, shape, scale=None):
    """Uniform random rotations, or small ones (angle ~ scale rad) when scale is given."""
    if scale is None:
        q = rng.normal(size=shape + (4,))
    else:
        q = np.concatenate([np.ones(shape + (1,)), rng.normal(scale=scale / 2, size=shape + (3,))], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _regimes(rng, n):
    """Per-frame regime labels 0 good, 1 at the thresholds, 2 between, 3 bad, in stretches; a
    third of the bad stretches last 60-200 frames so that RECENTLY_LOST outlasts the 5 s timer."""
    labels = np.empty(n, np.int64)
    k = 0
    while k < n:
        label = rng.choice(4, p=[0.4, 0.25, 0.15, 0.2])
        long = label == 3 and rng.random() < 0.35
        length = int(rng.integers(60, 201)) if long else int(rng.integers(1, 40))
        labels[k : k + length] = label
        k += length
    return labels


def s_b_numpy(bins, n_extracted):
    """Reference S_b (clamped): 1 - chi2 / (7 N), chi2 = sum (n_i - N/64)^2 / (N/64); 0 when N = 0."""
    bins = np.asarray(bins, float)
    n = np.asarray(n_extracted, float)
    e = n[..., None] / 64.0
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = np.sum((bins - e) ** 2 / e, axis=-1)
        value = 1.0 - chi2 / (7.0 * n)
    return np.where(n > 0, np.clip(value, 0.0, 1.0), 0.0)


def option2_numpy(n_extracted, n_inliers, n_frustum, bins):
    """Option 2 by hand: sqrt(S_a (0.5 S_b + 0.5 S_c)), rho = 0.25, clamped metrics, 0/0 -> 0."""
    ext, inl, fru = (np.asarray(x, float) for x in (n_extracted, n_inliers, n_frustum))
    with np.errstate(divide="ignore", invalid="ignore"):
        sa = np.where(ext > 0, np.clip(inl / (0.25 * ext), 0, 1), 0.0)
        sc = np.where(fru > 0, np.clip(inl / fru, 0, 1), 0.0)
    return np.sqrt(sa * (0.5 * s_b_numpy(bins, ext) + 0.5 * sc))


def random_logs(seed, n_runs, n_frames=400, min_frames=150, kind="inliers", fractional_fps=True):
    """A batch of random logs as padded numpy arrays [runs, frames, ...] plus `length` [runs].

    Scores cluster at the thresholds (with exact ties for inlier counts), stretches of bad frames
    outlast the 5 s timer, imu_init switches on mid-run (sometimes flickers, sometimes never),
    imu_init_delay is that switch time, 0, a random value or inf, and fps varies (10-30, some
    fractional). kind = 'inliers' fills n_inliers around 10/15/50; kind = 'sve' fills the counts so
    that Option 2 scores cluster around 0.04 / 0.06 / 0.2 and edge frames reuse a small palette
    of count tuples (so that thresholds set to palette scores give exact ties).
    """
    rng = np.random.default_rng(seed)
    R, F = n_runs, n_frames
    out = dict(
        length=np.zeros(R, np.int64), t=np.zeros((R, F)), valid=np.zeros((R, F), bool),
        imu_init=np.zeros((R, F), bool), n_extracted=np.zeros((R, F), np.int64),
        n_inliers=np.zeros((R, F), np.int64), n_frustum=np.zeros((R, F), np.int64),
        vis_p=np.zeros((R, F, 3)), vis_q=np.tile([1.0, 0, 0, 0], (R, F, 1)), vis_v=np.zeros((R, F, 3)),
        imu_dt=np.zeros((R, F)), imu_dp=np.zeros((R, F, 3)), imu_dv=np.zeros((R, F, 3)),
        imu_dq=np.tile([1.0, 0, 0, 0], (R, F, 1)), fps=np.zeros(R), gravity=np.zeros((R, 3)),
        imu_init_delay=np.zeros(R),
    )  # fmt: skip
    if kind == "sve":
        out["bins"] = np.zeros((R, F, 64), np.int64)
        palette = _sve_palette(rng)
    fps_choices = [10.0, 15.0, 20.0, 20.0, 20.0, 25.0, 30.0] + ([12.5, 20.5, 29.97] if fractional_fps else [])
    for i in range(R):
        n = int(rng.integers(min_frames, F + 1))
        out["length"][i] = n
        out["valid"][i, :n] = True
        fps = float(rng.choice(fps_choices))
        out["fps"][i] = fps
        step_ns = np.full(n - 1, int(round(1e9 / fps)), np.int64)
        if rng.random() < 0.5:  # jitter and dropped frames
            step_ns += rng.integers(-2_000_000, 2_000_001, n - 1)
            step_ns[rng.random(n - 1) < 0.02] *= 3
        stamps = 1_403_715_274_312_143_104 + np.concatenate([[0], np.cumsum(step_ns)])
        t = (stamps - stamps[0]) / 1e9
        out["t"][i, :n] = t
        out["t"][i, n:] = t[-1]  # padding: any finite value
        # IMU initialisation: switches on at k_init (sometimes at 0, sometimes never), may flicker.
        u = rng.random()
        k_init = 0 if u < 0.3 else (n if u < 0.4 else int(rng.integers(1, n // 2)))
        init = np.arange(n) >= k_init
        if rng.random() < 0.1:
            init ^= rng.random(n) < 0.05
        out["imu_init"][i, :n] = init
        u = rng.random()
        if u < 0.4:
            out["imu_init_delay"][i] = t[k_init] if k_init < n else np.inf
        elif u < 0.55:
            out["imu_init_delay"][i] = 0.0
        elif u < 0.65:
            out["imu_init_delay"][i] = np.inf
        else:
            out["imu_init_delay"][i] = rng.uniform(0.0, 4.0)
        regime = _regimes(rng, n)
        if kind == "inliers":
            inl = np.where(regime == 0, rng.integers(51, 301, n), 0)
            inl = np.where(regime == 1, rng.choice(INLIER_EDGES, n), inl)
            inl = np.where(regime == 2, rng.integers(16, 50, n), inl)
            inl = np.where(regime == 3, rng.integers(0, 10, n), inl)
            out["n_inliers"][i, :n] = inl
            out["n_extracted"][i, :n] = 1000
            out["n_frustum"][i, :n] = inl + rng.integers(0, 200, n)
        else:
            _fill_sve(rng, out, i, n, regime, palette)
        # Poses: a random walk for the visual estimate, random preintegration, some gravity.
        out["vis_p"][i, :n] = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), 0) + rng.normal(size=3)
        out["vis_v"][i, :n] = rng.normal(size=(n, 3))
        out["vis_q"][i, :n] = random_unit_quaternions(rng, (n,))
        out["imu_dt"][i, 1:n] = np.diff(t)
        out["imu_dp"][i, 1:n] = rng.normal(scale=0.05, size=(n - 1, 3))
        out["imu_dv"][i, 1:n] = rng.normal(scale=0.5, size=(n - 1, 3))
        out["imu_dq"][i, 1:n] = random_unit_quaternions(rng, (n - 1,), scale=0.05)
        out["gravity"][i] = [0.0, 0.0, -9.81] if rng.random() < 0.7 else rng.normal(scale=5.0, size=3)
    return out


def _sve_palette(rng, size=8):
    """Count tuples (n_extracted, n_inliers, n_frustum, bins) whose Option 2 scores lie near the
    SVE thresholds; edge frames draw from it so that the same score value recurs."""
    tuples = []
    while len(tuples) < size:
        target = rng.choice(SVE_EDGES) + rng.normal(scale=0.004)
        ext, fru, bins = _random_counts(rng)
        inl = _inliers_for(target, ext, fru, bins)
        tuples.append((ext, inl, fru, bins))
    return tuples


def _random_counts(rng):
    ext = int(rng.integers(200, 1001))
    inside = ext - int(rng.integers(0, 20))
    bins = rng.multinomial(inside, rng.dirichlet(np.full(64, rng.uniform(0.2, 5.0))))
    return ext, int(rng.integers(50, 600)), bins


def _inliers_for(target, ext, fru, bins):
    """The integer inlier count whose Option 2 score is closest to `target` (a search over all)."""
    inl = np.arange(ext + 1)
    scores = option2_numpy(np.full_like(inl, ext), inl, np.full_like(inl, fru), np.tile(bins, (ext + 1, 1)))
    return int(inl[np.argmin(np.abs(scores - target))])


def _fill_sve(rng, out, i, n, regime, palette):
    targets = np.where(regime == 0, rng.uniform(0.25, 1.0, n), 0.0)
    targets = np.where(regime == 1, rng.choice(SVE_EDGES, n) + rng.normal(scale=0.004, size=n), targets)
    targets = np.where(regime == 2, rng.uniform(0.06, 0.2, n), targets)
    targets = np.where(regime == 3, rng.uniform(0.0, 0.04, n), targets)
    ext = rng.integers(200, 1001, n)
    ext[rng.random(n) < 0.02] = 0  # frames without features: every metric is 0
    fru = rng.integers(50, 600, n)
    inside = np.maximum(ext - rng.integers(0, 20, n), 0)
    # Bad frames get clumped keypoints (S_b near 0): Option 2 cannot go below ~0.06 sqrt(S_b / 2)
    # with a single inlier, so low scores need a low S_b.
    bins = rng.multinomial(inside, rng.dirichlet(np.full(64, rng.uniform(0.2, 5.0))))
    bad = regime == 3
    bins[bad] = rng.multinomial(inside[bad], rng.dirichlet(np.full(64, 0.03)))
    # Closed form for the unclamped inlier count, then rounded: scores land near the targets.
    with np.errstate(divide="ignore", invalid="ignore"):
        a2, a1 = 0.5 / (0.25 * ext * fru), 0.5 * s_b_numpy(bins, ext) / (0.25 * ext)
        root = (-a1 + np.sqrt(a1 * a1 + 4 * a2 * targets**2)) / (2 * a2)
    inl = np.where(ext > 0, np.clip(np.rint(np.nan_to_num(root)), 0, ext), 0).astype(np.int64)
    use = np.flatnonzero((regime == 1) & (rng.random(n) < 0.5))
    for k in use:
        ext[k], inl[k], fru[k], bins[k] = palette[int(rng.integers(len(palette)))]
    out["n_extracted"][i, :n], out["n_inliers"][i, :n], out["n_frustum"][i, :n] = ext, inl, fru
    out["bins"][i, :n] = bins
