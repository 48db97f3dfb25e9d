"""Batched search: thousands of rule settings over the same logs in one compiled scan.

`search` evaluates the hard (exact) objective of every setting of a design on every run and returns
per-run matrices [settings, runs] (loss, failed, rmse, coverage), so that any weighting of the runs
(cross-validation folds, bootstrap resamples, group balancing) is a matrix-vector product afterwards.

The kernel (`search_chunk`) walks the frames once for a chunk of settings x runs, with settings and runs
as the vector lanes of every scan step: ORB-SLAM3's state machine (jsve.core._rules.machine_step, the same
code the replay runs), ORB-SLAM3's IMU prediction and, instead of storing the trajectory, the sufficient
statistics of its SE(3) / Sim(3) / yaw alignment to ground truth. With e_k = p_k - g_k - o (the
estimate's offset from ground truth, less the run's mean visual offset o) and g_c the centred ground
truth, it accumulates sum e, M = sum e g_c^T and sum |e|^2; the per-run Gram matrix G = sum g_c g_c^T is
fixed. Then Umeyama (1991) runs on cov = (G + M^T) / n and, with A = I - cR, the alignment residual is

    E = tr(A^T A G) - 2c tr(A^T R M) + c^2 D,      D = sum |e - mean e|^2,

a sum of small terms (A is of the order of the error over the trajectory's extent), so float32 keeps it
to ~1e-5 relative where the textbook form sum|y|^2 + sum|x|^2 - 2 tr(...) would cancel to ~1e-2.
A run that never reached LOST has an estimate on every frame (docs/state-machine.md), so its RMSE is over
all frames with ground truth, as in jsve.evaluation._evaluate; a run that did is failed and costs the penalty.
tests/test_fit.py checks the kernel against jsve.core._objective.run_losses setting by setting.

Everything per frame is spelled out in coordinate columns ([F, R] arrays) rather than [..., 3] rows:
XLA on CPU vectorises the former and not the latter (measured 2x for the pose update and 7x for the
power means; analysis/bench_search.py).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array
from tqdm.auto import tqdm

from jsve.core._batch import LogBatch
from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import HardLogic, InlierRule, Rule, initial_state, machine_step
from jsve.core._sve import FrameFeatures, combination_from_logs, feature_logs
from jsve.core._trajectory import MIN_ALIGNMENT_FRAMES

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------------
# Designs in the unit cube (numpy; deterministic under a seed)

# Joe & Kuo (2008), new-joe-kuo-6.21201: dimension, degree s, polynomial a, initial direction numbers m.
_JOE_KUO = (
    (1, 0, (1,)),
    (2, 1, (1, 3)),
    (3, 1, (1, 3, 1)),
    (3, 2, (1, 1, 1)),
    (4, 1, (1, 1, 3, 3)),
    (4, 4, (1, 3, 5, 13)),
    (5, 2, (1, 1, 5, 5, 17)),
    (5, 4, (1, 1, 5, 5, 5)),
    (5, 7, (1, 1, 7, 11, 19)),
    (5, 11, (1, 1, 5, 1, 1)),
    (5, 13, (1, 1, 1, 3, 11)),
    (5, 14, (1, 3, 5, 5, 31)),
    (6, 1, (1, 3, 3, 9, 7, 49)),
    (6, 13, (1, 1, 1, 15, 21, 21)),
    (6, 16, (1, 3, 1, 13, 27, 49)),
)
SOBOL_MAX_DIM = 1 + len(_JOE_KUO)
_SOBOL_BITS = 32


def _sobol_directions(d: int) -> np.ndarray:
    """[d, 32] direction numbers V_i = m_i 2^(32 - i) (Bratley & Fox 1988, Joe & Kuo 2008)."""
    v = np.zeros((d, _SOBOL_BITS), np.uint64)
    v[0] = [1 << (_SOBOL_BITS - 1 - i) for i in range(_SOBOL_BITS)]  # dimension 1: m_i = 1
    for j in range(1, d):
        s, a, m0 = _JOE_KUO[j - 1]
        m = list(m0)
        for i in range(s, _SOBOL_BITS):
            new = m[i - s] ^ (m[i - s] << s)
            for k in range(1, s):
                new ^= ((a >> (s - 1 - k)) & 1) * (m[i - k] << k)
            m.append(new)
        v[j] = [m[i] << (_SOBOL_BITS - 1 - i) for i in range(_SOBOL_BITS)]
    return v


def sobol(n: int, d: int, *, seed: int | None = None) -> np.ndarray:
    """The first n points of the d-dimensional Sobol sequence (Gray-code order), [n, d] in [0, 1).

    Arguments:
        seed: None for the plain sequence (point 0 is the origin; the same points as
            scipy.stats.qmc.Sobol(scramble=False)); an int applies a random digital shift (XOR of every
            coordinate with a seeded 32-bit word), which keeps the net's balance.
    """
    if not 1 <= d <= SOBOL_MAX_DIM:
        raise ValueError(f"sobol supports 1 to {SOBOL_MAX_DIM} dimensions, got {d}")
    if n < 1 or n > 2**_SOBOL_BITS:
        raise ValueError(f"sobol needs 1 <= n <= 2^32 points, got {n}")
    v = _sobol_directions(d)
    # Gray code: point k = XOR of V_i over the bits i of k ^ (k >> 1).
    k = np.arange(n, dtype=np.uint64)
    gray = k ^ (k >> np.uint64(1))
    x = np.zeros((n, d), np.uint64)
    for i in range(_SOBOL_BITS):
        bit = ((gray >> np.uint64(i)) & np.uint64(1)).astype(bool)
        x[bit] ^= v[:, i]
    if seed is not None:
        shift = np.random.default_rng(seed).integers(0, 2**_SOBOL_BITS, size=d, dtype=np.uint64)
        x ^= shift
    return x.astype(np.float64) / 2.0**_SOBOL_BITS


def _primes(k: int) -> list[int]:
    out, c = [], 2
    while len(out) < k:
        if all(c % p for p in out if p * p <= c):
            out.append(c)
        c += 1
    return out


def halton(n: int, d: int, *, seed: int | None = None) -> np.ndarray:
    """The first n points of the d-dimensional Halton sequence (radical inverses in the first d primes).

    Point 0 is the origin, as scipy.stats.qmc.Halton(scramble=False). An int seed adds a random
    Cranley-Patterson rotation (a seeded shift modulo 1 per dimension).
    """
    if d < 1 or n < 1:
        raise ValueError(f"halton needs n >= 1 and d >= 1, got n={n}, d={d}")
    out = np.zeros((n, d))
    k0 = np.arange(n)
    for j, base in enumerate(_primes(d)):
        k = k0.copy()
        f, value = 1.0 / base, np.zeros(n)
        while np.any(k > 0):
            value += f * (k % base)
            k //= base
            f /= base
        out[:, j] = value
    if seed is not None:
        out = (out + np.random.default_rng(seed).random(d)) % 1.0
    return out


def random_design(n: int, d: int, *, seed: int = 0) -> np.ndarray:
    """n independent uniform points of [0, 1)^d."""
    return np.random.default_rng(seed).random((n, d))


def grid_design(levels: Sequence[int | Sequence[float]]) -> np.ndarray:
    """The full factorial grid: per dimension a number of equally spaced levels in [0, 1] (including
    both ends) or explicit unit coordinates; [prod(levels), d], the last dimension varying fastest."""
    axes = [np.linspace(0.0, 1.0, int(lv)) if np.isscalar(lv) else np.asarray(lv, float) for lv in levels]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=-1)


DESIGNS = {"sobol": sobol, "halton": halton, "random": random_design}


def design(kind: str, n: int, d: int, *, seed: int = 0) -> np.ndarray:
    """A design by name: "sobol" and "halton" (randomised by the seed) or "random"."""
    if kind not in DESIGNS:
        raise ValueError(f"design must be one of {sorted(DESIGNS)}, got {kind!r}")
    return DESIGNS[kind](n, d, seed=seed)


def score_columns(rule: Rule, n_inliers, log_ratio, log_s_b, log_s_c, pos_ratio, pos_s_b, pos_s_c):
    """The rule's score from feature columns (rule leaves broadcast against the columns).

    SVE features come as logs (jsve.core._sve.feature_logs: log of N_inliers / N_extracted, of S_b, of S_c;
    `pos_*` where the feature is > 0), computed once per frame and shared by every setting; the
    combination itself is jsve.core._sve.combination_from_logs, the same code the replay's rules use.
    """
    if isinstance(rule, InlierRule):
        return n_inliers
    return combination_from_logs(rule.combination, log_ratio, log_s_b, log_s_c, pos_ratio, pos_s_b, pos_s_c)


# ---------------------------------------------------------------------------------------------------
# Inputs of the kernel


class SearchBatch(eqx.Module):
    """A chunk of runs in the kernel's layout: frames-major columns [F, R], per-run values [R].

    Built by `prepare`; the alignment statistics of the ground truth are computed once here.
    """

    n_inliers: Array
    log_ratio: Array  # log N_inliers / N_extracted (0 where it is 0, see pos_ratio)
    log_s_b: Array
    log_s_c: Array
    pos_ratio: Array
    pos_s_b: Array
    pos_s_c: Array
    t: Array
    imu_init: Array
    valid: Array
    weight: Array  # frame has ground truth and exists
    vis_p: tuple
    vis_q: tuple
    vis_v: tuple
    imu_dt: Array
    imu_dp: tuple
    imu_dv: tuple
    imu_dq: tuple
    ref: tuple  # ground truth + the run's mean visual offset
    g_c: tuple  # centred ground truth, 0 where weight is 0
    gravity: tuple  # [R] each
    fps: Array
    imu_init_delay: Array
    offset: Array  # [3, R]
    g_mean: Array  # [3, R]
    gram: Array  # [3, 3, R]
    n_eval: Array  # [R] frames with ground truth

    @property
    def n_runs(self) -> int:
        return self.t.shape[1]

    @property
    def n_frames(self) -> int:
        return self.t.shape[0]


@jax.jit
def prepare(batch: LogBatch, features: FrameFeatures) -> SearchBatch:
    """The kernel's inputs for a LogBatch and its features (one compiled call per shape)."""
    dtype = batch.t.dtype
    fm = lambda x: jnp.swapaxes(x, 0, 1).astype(dtype)  # noqa: E731
    cols = lambda x: tuple(fm(x[..., i]) for i in range(x.shape[-1]))  # noqa: E731
    weight = (batch.valid & batch.gt_valid).astype(dtype)  # [R, F]
    n = jnp.sum(weight, axis=1)
    n_safe = jnp.maximum(n, 1.0)
    mean = lambda x: jnp.sum(weight[..., None] * x, axis=1) / n_safe[:, None]  # noqa: E731
    g_mean = mean(batch.gt_p)  # [R, 3]
    offset = mean(batch.vis_p - batch.gt_p)
    g_c = (batch.gt_p - g_mean[:, None]) * weight[..., None]
    gram = jnp.einsum("rfi,rfj->ijr", g_c, g_c)
    logs = feature_logs(fm(features.inlier_ratio), fm(features.s_b), fm(features.s_c))
    return SearchBatch(
        n_inliers=fm(features.n_inliers),
        log_ratio=logs[0],
        log_s_b=logs[1],
        log_s_c=logs[2],
        pos_ratio=logs[3],
        pos_s_b=logs[4],
        pos_s_c=logs[5],
        t=fm(batch.t),
        imu_init=fm(batch.imu_init),
        valid=fm(batch.valid),
        weight=fm(weight),
        vis_p=cols(batch.vis_p),
        vis_q=cols(batch.vis_q),
        vis_v=cols(batch.vis_v),
        imu_dt=fm(batch.imu_dt),
        imu_dp=cols(batch.imu_dp),
        imu_dv=cols(batch.imu_dv),
        imu_dq=cols(batch.imu_dq),
        ref=cols(batch.gt_p + offset[:, None]),
        g_c=cols(g_c),
        gravity=tuple(batch.gravity[:, i].astype(dtype) for i in range(3)),
        fps=batch.fps.astype(dtype),
        imu_init_delay=batch.imu_init_delay.astype(dtype),
        offset=offset.T,
        g_mean=g_mean.T,
        gram=gram,
        n_eval=n,
    )


# ---------------------------------------------------------------------------------------------------
# The kernel


def _quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _quat_rotate(q, v):
    w, x, y, z = q
    vx, vy, vz = v
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)  # t = 2 u x v
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx))


def imu_predict_columns(p, v, q, dt, dp, dv, dq, gravity):
    """jsve.core._replay.imu_predict (ORB-SLAM3's PredictStateIMU) on coordinate columns (tuples)."""
    rp, rv = _quat_rotate(q, dp), _quat_rotate(q, dv)
    p2 = tuple(p[i] + v[i] * dt + 0.5 * gravity[i] * dt * dt + rp[i] for i in range(3))
    v2 = tuple(v[i] + gravity[i] * dt + rv[i] for i in range(3))
    return p2, v2, _quat_mul(q, dq)


class ChunkResult(eqx.Module):
    """Kernel output, leaves [S, R]: loss (m), failed, rmse (m; NaN where failed), coverage."""

    loss: Array
    failed: Array
    rmse: Array
    coverage: Array


_MOMENTS = 3 + 9 + 1  # sum e, sum e_i g_c,j, sum |e|^2


def _umeyama_residual(sb: SearchBatch, s_e, m, s_ee, method: str):
    """RMSE of the aligned estimate from the alignment statistics (lanes [S, R]); and degeneracy."""
    dtype = s_ee.dtype
    eps = jnp.finfo(dtype).eps
    n = sb.n_eval
    n_safe = jnp.maximum(n, 1.0)
    mu = [s / n_safe for s in s_e]  # mean of e (shifted offsets)
    d_c = s_ee - n * sum(x * x for x in mu)  # sum |e - mean e|^2
    gram = sb.gram  # [3, 3, R]; symmetric
    # M[j][i] = sum e_j g_c,i;  cov[i][j] = (G[i][j] + M[j][i]) / n  (Umeyama eq. 38 with y = truth)
    cov = jnp.stack(
        [jnp.stack([(gram[i, j] + m[j][i]) / n_safe for j in range(3)], -1) for i in range(3)], -2
    )
    tr_g = gram[0, 0] + gram[1, 1] + gram[2, 2]
    tr_m = m[0][0] + m[1][1] + m[2][2]
    var_y = tr_g / n_safe
    var_x = jnp.maximum((tr_g + 2 * tr_m + d_c) / n_safe, 0.0)
    mu_x = [sb.g_mean[i] + sb.offset[i] + mu[i] for i in range(3)]
    ms_x = sum(x * x for x in mu_x) + var_x
    ms_y = sum(sb.g_mean[i] ** 2 for i in range(3)) + var_y
    tol = (64.0 * eps) ** 2  # jsve.core._trajectory's "all points identical" test
    degenerate = (n < MIN_ALIGNMENT_FRAMES) | (var_x <= tol * ms_x) | (var_y <= tol * ms_y)
    eye = jnp.eye(3, dtype=dtype)
    if method == "none":
        e2 = (
            s_ee
            + 2 * sum(sb.offset[i] * s_e[i] for i in range(3))
            + n * sum(sb.offset[i] ** 2 for i in range(3))
        )
        return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), jnp.zeros_like(degenerate)
    if method == "posyaw":
        a = cov[..., 0, 0] + cov[..., 1, 1]
        b = cov[..., 1, 0] - cov[..., 0, 1]
        r = jnp.sqrt(jnp.where(a * a + b * b > 0, a * a + b * b, 1.0))
        ok = a * a + b * b > 0
        c_t, s_t = jnp.where(ok, a / r, 1.0), jnp.where(ok, b / r, 0.0)
        zero, one = jnp.zeros_like(a), jnp.ones_like(a)
        rot = jnp.stack(
            [
                jnp.stack([c_t, -s_t, zero], -1),
                jnp.stack([s_t, c_t, zero], -1),
                jnp.stack([zero, zero, one], -1),
            ],
            -2,
        )
        scale = one
    else:
        u, d, vt = jnp.linalg.svd(
            jnp.where(degenerate[..., None, None], jnp.diag(jnp.array([3.0, 2.0, 1.0], dtype)), cov)
        )
        flip = jnp.linalg.det(u) * jnp.linalg.det(vt) < 0  # Umeyama eq. 43
        s = jnp.stack([jnp.ones_like(d[..., 0]), jnp.ones_like(d[..., 0]), jnp.where(flip, -1.0, 1.0)], -1)
        rot = (u * s[..., None, :]) @ vt
        if method == "sim3":
            scale = jnp.sum(d * s, -1) / jnp.where(var_x > 0, var_x, 1.0)  # eq. 42
        else:
            scale = jnp.ones_like(var_x)
    a_mat = eye - scale[..., None, None] * rot
    g = jnp.moveaxis(gram, -1, 0)  # [R, 3, 3], broadcast over settings
    m_mat = jnp.stack([jnp.stack([m[j][i] for i in range(3)], -1) for j in range(3)], -2)  # [S, R, 3, 3] = M
    term_g = jnp.sum((a_mat @ g) * a_mat, axis=(-2, -1))  # tr(A G A^T) = tr(A^T A G)
    term_m = jnp.trace(jnp.swapaxes(a_mat, -1, -2) @ rot @ m_mat, axis1=-2, axis2=-1)
    e2 = term_g - 2 * scale * term_m + scale * scale * d_c
    return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), degenerate


@functools.partial(jax.jit, static_argnames=("config",))
def search_chunk(sb: SearchBatch, rules: Rule, config: ObjectiveConfig = ObjectiveConfig()) -> ChunkResult:  # noqa: B008
    """Hard objective of S rule settings (leaves [S]) on every run of a SearchBatch: [S, R] results."""
    if config.align == "origin":
        raise ValueError(
            "the search kernel aligns from sufficient statistics; align='origin' needs the first "
            "pose: use jsve.core._objective.run_losses"
        )
    dtype = sb.t.dtype
    S = jax.tree.leaves(rules)[0].shape[0]
    lanes = (S, sb.n_runs)
    rule = jax.tree.map(lambda x: x.astype(dtype)[:, None], rules)  # leaves [S, 1] broadcast over runs
    state0 = jax.tree.map(lambda x: jnp.broadcast_to(x, lanes), initial_state(dtype))
    first = lambda cols: tuple(jnp.broadcast_to(c[0], lanes) for c in cols)  # noqa: E731
    zeros = jnp.zeros(lanes, dtype)
    start = (state0, first(sb.vis_p), first(sb.vis_v), first(sb.vis_q), zeros, zeros, (zeros,) * _MOMENTS)
    k = jnp.arange(sb.n_frames, dtype=dtype)
    xs = (
        sb.n_inliers,
        (sb.log_ratio, sb.log_s_b, sb.log_s_c, sb.pos_ratio, sb.pos_s_b, sb.pos_s_c),
        sb.t,
        sb.imu_init,
        sb.valid,
        sb.weight,
        sb.vis_p,
        sb.vis_q,
        sb.vis_v,
        sb.imu_dt,
        sb.imu_dp,
        sb.imu_dv,
        sb.imu_dq,
        sb.ref,
        sb.g_c,
        k,
    )
    logic = HardLogic()

    def step(carry, x):
        state, p, v, q, lost, n_est, mom = carry
        n_inl, feats, t, imu_init, valid, w, vp, vq, vv, dt, dp, dv, dq, ref, g_c, kk = x
        score = score_columns(rule, n_inl, *feats)
        state, decision = machine_step(
            logic,
            state,
            score,
            t,
            kk,
            imu_init,
            rule.thresholds,
            sb.fps,
            sb.imu_init_delay,
            config.time_recently_lost,
        )
        pp, pv, pq = imu_predict_columns(p, v, q, dt, dp, dv, dq, sb.gravity)
        # (machine_step computes in result_type(t, float): float64 for float32 data under jax_enable_x64)
        state, decision = jax.tree.map(lambda x: x.astype(dtype), (state, decision))
        a = decision.accepted > 0.5
        sel = lambda vis, pred: tuple(jnp.where(a, u, z) for u, z in zip(vis, pred, strict=True))  # noqa: E731
        p2, v2, q2 = sel(vp, pp), sel(vv, pv), sel(vq, pq)
        lost = jnp.maximum(lost, state.lost * valid)
        n_est = n_est + w * (decision.accepted + decision.predicted)
        e = [w * (p2[i] - ref[i]) for i in range(3)]
        new = (
            e
            + [e[j] * g_c[i] for j in range(3) for i in range(3)]
            + [e[0] * e[0] + e[1] * e[1] + e[2] * e[2]]
        )
        mom = tuple(acc + d for acc, d in zip(mom, new, strict=True))
        return (state, p2, v2, q2, lost, n_est, mom), None

    (_, _, _, _, lost, n_est, mom), _ = jax.lax.scan(step, start, xs)
    s_e, s_ee = mom[:3], mom[12]
    m = [[mom[3 + 3 * j + i] for i in range(3)] for j in range(3)]  # m[j][i] = sum e_j g_c,i
    rmse, degenerate = _umeyama_residual(sb, s_e, m, s_ee, config.align)
    n = sb.n_eval
    coverage = jnp.where(n > 0, n_est / jnp.maximum(n, 1.0), 0.0)
    failed = (lost > 0.5) | degenerate | (n < MIN_ALIGNMENT_FRAMES) | (coverage < config.min_coverage)
    loss = jnp.where(failed, jnp.asarray(config.failure_penalty, dtype), rmse)
    return ChunkResult(loss=loss, failed=failed, rmse=jnp.where(failed, jnp.nan, rmse), coverage=coverage)


# ---------------------------------------------------------------------------------------------------
# Driving the kernel over a data set


@dataclass(frozen=True)
class SearchResult:
    """Per-run results of every setting, [S, R] numpy arrays over all runs of the data (in data order).

    Attributes:
        values: [S, d] the settings' free parameter values (in the space's order).
        loss, failed, rmse, coverage: [S, R]; rmse is NaN where failed.
    """

    values: np.ndarray
    loss: np.ndarray
    failed: np.ndarray
    rmse: np.ndarray
    coverage: np.ndarray

    def objective(self, weights: np.ndarray) -> np.ndarray:
        """[S] weighted mean loss for run weights [R] (or [..., R] for many weightings: [..., S])."""
        w = np.asarray(weights, np.float64)
        return (w @ self.loss.T.astype(np.float64)) / w.sum(axis=-1, keepdims=True)

    def failure_rate(self, weights: np.ndarray) -> np.ndarray:
        w = np.asarray(weights, np.float64)
        return (w @ self.failed.T.astype(np.float64)) / w.sum(axis=-1, keepdims=True)

    def coverage_mean(self, weights: np.ndarray) -> np.ndarray:
        w = np.asarray(weights, np.float64)
        return (w @ self.coverage.T.astype(np.float64)) / w.sum(axis=-1, keepdims=True)

    def concat(self, other: SearchResult) -> SearchResult:
        """Both sets of settings (same runs)."""
        return SearchResult(
            *(np.concatenate([a, b]) for a, b in zip(self.as_tuple(), other.as_tuple(), strict=True))
        )

    def as_tuple(self):
        return (self.values, self.loss, self.failed, self.rmse, self.coverage)


LANES_PER_CALL = 8192
"""Settings x runs per kernel call: enough lanes to vectorise each frame step, few enough that the scan's
carry (~50 floats per lane, 1.6 MB) stays in a core's L2 cache (measured best of 4k-64k lanes,
analysis/bench_search.py)."""


def _settings_chunks(n: int, size: int) -> Iterator[slice]:
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


def search(
    parts: Sequence[SearchBatch],
    space,
    values: np.ndarray,
    config: ObjectiveConfig = ObjectiveConfig(),  # noqa: B008
    *,
    run_counts: Sequence[int] | None = None,
    settings_per_call: int | None = None,
    progress: bool = True,
    desc: str = "search",
) -> SearchResult:
    """Evaluate every setting (`values`, [S, d] in `space`) on every run of `parts`.

    Arguments:
        parts: SearchBatches (from `prepare`), each a chunk of runs; results are concatenated in order.
        space: jsve.fitting._space.ParamSpace of the values.
        run_counts: real runs of each part (the rest is padding and is dropped); default all.
        settings_per_call: settings per compiled call (default: ~32k lanes / runs per part, a power of 2,
            fixed so one compilation serves every call; the last call is padded).
    Returns:
        SearchResult with [S, R_total] matrices.
    """
    values = np.asarray(values, np.float64)
    if values.ndim != 2 or values.shape[1] != space.dim:
        raise ValueError(f"values must have shape (S, {space.dim}) for {space.names}, got {values.shape}")
    n_settings = values.shape[0]
    run_counts = list(run_counts) if run_counts is not None else [p.n_runs for p in parts]
    # Calls are dispatched asynchronously, round-robin over the local devices: with several CPU devices
    # (XLA_FLAGS=--xla_force_host_platform_device_count=N, which `jsve fit` / `jsve demo` set to the
    # number of cores) the calls run on all cores at once; the results are collected afterwards.
    devices = jax.local_devices()
    pending = []
    for p, (part, n_real) in enumerate(zip(parts, run_counts, strict=True)):
        size = settings_per_call or 2 ** int(math.log2(max(1, LANES_PER_CALL // part.n_runs)))
        size = min(size, 2 ** math.ceil(math.log2(n_settings)))
        copies = [part] if len(devices) == 1 else [jax.device_put(part, d) for d in devices]
        for i, sl in enumerate(_settings_chunks(n_settings, size)):
            chunk = values[sl]
            if len(chunk) < size:
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], size - len(chunk), 0)])
            k = i % len(copies)
            rules = space.rule(jnp.asarray(chunk, part.t.dtype))
            if len(copies) > 1:
                rules = jax.device_put(rules, devices[k])
            pending.append((p, sl, n_real, search_chunk(copies[k], rules, config)))
    per_part: list[list] = [[] for _ in parts]
    total = n_settings * sum(run_counts)
    with tqdm(total=total, desc=desc, unit="run-setting", unit_scale=True, disable=not progress) as bar:
        for p, sl, n_real, res in pending:
            n = sl.stop - sl.start
            per_part[p].append(jax.tree.map(lambda x, n=n, r=n_real: np.asarray(x)[:n, :r], res))
            bar.update(n * n_real)
    merged = [jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *chunks) for chunks in per_part]
    merged = jax.tree.map(lambda *xs: np.concatenate(xs, axis=1), *merged)
    return SearchResult(
        values=values, loss=merged.loss, failed=merged.failed, rmse=merged.rmse, coverage=merged.coverage
    )


def use_all_cores() -> None:
    """Ask XLA for one CPU device per core, so that `search` runs its calls on every core. Effective
    only before JAX's backend starts, and only when XLA_FLAGS does not set a device count already.
    For the command line and scripts: a library user decides this for their own process."""
    import os

    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_force_host_platform_device_count={os.cpu_count() or 1}".strip()
        )


__all__ = [
    "sobol",
    "halton",
    "random_design",
    "grid_design",
    "design",
    "SearchBatch",
    "prepare",
    "search_chunk",
    "search",
    "SearchResult",
    "score_columns",
    "feature_logs",
    "imu_predict_columns",
    "use_all_cores",
]
