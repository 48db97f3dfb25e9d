"""Batched search: thousands of rule settings over the same logs in one compiled scan.

`search` evaluates the hard (exact) objective of every setting of a design on every run and returns
per-run matrices [settings, runs] (loss, failed, rmse, coverage), so that any weighting of the runs
(cross-validation folds, bootstrap resamples, group balancing) is a matrix-vector product afterwards.

The kernel (`search_chunk`) walks the frames once for a chunk of settings x runs, with settings and runs
as the vector lanes of every scan step: ORB-SLAM3's state machine (jsve.core._machine.machine_step, the same
code the replay runs), ORB-SLAM3's IMU prediction (jsve.core._imu, on columns) and, instead of storing the
trajectory, the sufficient statistics of its alignment to ground truth. With e_k = p_k - g_k - o (the
estimate's offset from ground truth, less the run's mean visual offset o) and g_c the centred ground
truth, it accumulates sum e, M = sum e g_c^T and sum |e|^2; the per-run Gram matrix G = sum g_c g_c^T is
fixed. Then the alignment method's solver (jsve.core._align, Umeyama 1991) runs on the moments, with
cov = (G + M^T) / n, and, with A = I - cR, the alignment residual is

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

from jsve.core._align import ALIGNERS, MIN_ALIGNMENT_FRAMES, Moments, fit_moments
from jsve.core._batch import LogBatch
from jsve.core._imu import imu_predict_columns
from jsve.core._machine import FrameData, HardLogic, RunConstants, initial_state, machine_step
from jsve.core._objective import ObjectiveConfig
from jsve.core._replay import frame_data, run_constants
from jsve.core._rules import InlierRule, Rule
from jsve.core._sve import FrameFeatures, combination_from_logs, feature_logs

log = logging.getLogger(__name__)


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
    data: FrameData  # the log's facts per frame, [F, R] leaves
    run: RunConstants  # [R] leaves
    valid: Array
    gt: Array  # frame exists and has ground truth
    weight: Array  # ... and a recorded pose
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
    offset: Array  # [3, R]
    g_mean: Array  # [3, R]
    gram: Array  # [3, 3, R]
    n_eval: Array  # [R] frames with ground truth and a recorded pose
    n_gt: Array  # [R] frames with ground truth

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
    # Frames a run that keeps tracking has an estimate on: posed by the recorded run (under both switch
    # models; search_chunk refuses a lane whose estimates differ from these frames).
    weight = (batch.valid & batch.gt_valid & batch.has_pose).astype(dtype)  # [R, F]
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
        data=jax.tree.map(fm, frame_data(batch)),
        run=run_constants(batch),
        valid=fm(batch.valid),
        gt=fm(batch.valid & batch.gt_valid),
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
        offset=offset.T,
        g_mean=g_mean.T,
        gram=gram,
        n_eval=n,
        n_gt=jnp.sum((batch.valid & batch.gt_valid).astype(dtype), axis=1),
    )


# ---------------------------------------------------------------------------------------------------
# The kernel


class ChunkResult(eqx.Module):
    """Kernel output, leaves [S, R]: loss (m), failed, rmse (m; NaN where failed), coverage.

    A lane the kernel cannot score exactly (a run that kept tracking but whose estimates are not exactly
    its posed frames with ground truth: the alignment statistics were fixed for those) has a NaN loss;
    `search` refuses it with a message rather than returning a number.
    """

    loss: Array
    failed: Array
    rmse: Array
    coverage: Array


_MOMENTS = 3 + 9 + 1  # sum e, sum e_i g_c,j, sum |e|^2


def _umeyama_residual(sb: SearchBatch, s_e, m, s_ee, method: str):
    """RMSE of the aligned estimate from the alignment statistics (lanes [S, R]); and degeneracy."""
    dtype = s_ee.dtype
    n = sb.n_eval
    n_safe = jnp.maximum(n, 1.0)
    aligner = ALIGNERS[method]
    if aligner.solve is None:  # the identity (search_chunk refuses first-pose methods): sum |e + o|^2
        e2 = (
            s_ee
            + 2 * sum(sb.offset[i] * s_e[i] for i in range(3))
            + n * sum(sb.offset[i] ** 2 for i in range(3))
        )
        return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), jnp.zeros(s_ee.shape, bool)
    mu = [s / n_safe for s in s_e]  # mean of e (shifted offsets)
    d_c = s_ee - n * sum(x * x for x in mu)  # sum |e - mean e|^2
    gram = sb.gram  # [3, 3, R]; symmetric
    # The moments of the pairs (estimate x = g + o + e, truth y = g): M[j][i] = sum e_j g_c,i and
    # cov[i][j] = (G[i][j] + M[j][i]) / n (Umeyama eq. 38), var_x = (tr G + 2 tr M + D) / n.
    cov = jnp.stack(
        [jnp.stack([(gram[i, j] + m[j][i]) / n_safe for j in range(3)], -1) for i in range(3)], -2
    )
    tr_g = gram[0, 0] + gram[1, 1] + gram[2, 2]
    tr_m = m[0][0] + m[1][1] + m[2][2]
    moments = Moments(
        count=n,
        mu_x=jnp.stack([sb.g_mean[i] + sb.offset[i] + mu[i] for i in range(3)], -1),
        mu_y=sb.g_mean.T,
        var_x=jnp.maximum((tr_g + 2 * tr_m + d_c) / n_safe, 0.0),
        var_y=tr_g / n_safe,
        cov=cov,
    )
    # The rotation and scale of jsve.core._align's solver; the translation is the least-squares one, so the
    # residual below needs none (degenerate lanes get the identity and are failed by the caller).
    transform = fit_moments(moments, aligner.solve)
    rot, scale = transform.rotation, transform.scale
    a_mat = jnp.eye(3, dtype=dtype) - scale[..., None, None] * rot
    g = jnp.moveaxis(gram, -1, 0)  # [R, 3, 3], broadcast over settings
    m_mat = jnp.stack([jnp.stack([m[j][i] for i in range(3)], -1) for j in range(3)], -2)  # [S, R, 3, 3] = M
    term_g = jnp.sum((a_mat @ g) * a_mat, axis=(-2, -1))  # tr(A G A^T) = tr(A^T A G)
    term_m = jnp.trace(jnp.swapaxes(a_mat, -1, -2) @ rot @ m_mat, axis1=-2, axis2=-1)
    e2 = term_g - 2 * scale * term_m + scale * scale * d_c
    return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), transform.degenerate


@functools.partial(jax.jit, static_argnames=("config",))
def search_chunk(sb: SearchBatch, rules: Rule, config: ObjectiveConfig = ObjectiveConfig()) -> ChunkResult:  # noqa: B008
    """Hard objective of S rule settings (leaves [S]) on every run of a SearchBatch: [S, R] results."""
    if ALIGNERS[config.align].first_pose:
        raise ValueError(
            f"the search kernel aligns from sufficient statistics; align={config.align!r} needs the first "
            "pose: use jsve.core._objective.run_losses"
        )
    dtype = sb.t.dtype
    S = jax.tree.leaves(rules)[0].shape[0]
    lanes = (S, sb.n_runs)
    rule = jax.tree.map(lambda x: x.astype(dtype)[:, None], rules)  # leaves [S, 1] broadcast over runs
    state0 = jax.tree.map(lambda x: jnp.broadcast_to(x, lanes), initial_state(dtype))
    first = lambda cols: tuple(jnp.broadcast_to(c[0], lanes) for c in cols)  # noqa: E731
    zeros = jnp.zeros(lanes, dtype)
    counts = (zeros, zeros, zeros)  # estimates in closed maps, in the current map, off the fixed frames
    start = (state0, first(sb.vis_p), first(sb.vis_v), first(sb.vis_q), zeros, counts, (zeros,) * _MOMENTS)
    xs = (
        sb.n_inliers,
        (sb.log_ratio, sb.log_s_b, sb.log_s_c, sb.pos_ratio, sb.pos_s_b, sb.pos_s_c),
        sb.data,
        sb.valid,
        sb.gt,
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
    )
    logic = HardLogic()
    coast = config.switch_model == "imu-coast"

    def step(carry, x):
        state, p, v, q, lost, (n_closed, n_map, n_off), mom = carry
        n_inl, feats, fd, valid, gt, w, vp, vq, vv, dt, dp, dv, dq, ref, g_c = x
        score = score_columns(rule, n_inl, *feats)
        state, decision = machine_step(
            logic, state, score, fd, sb.run, rule.thresholds, config.time_recently_lost
        )
        # (machine_step computes in result_type(t, float): float64 for float32 data under jax_enable_x64)
        state, decision = jax.tree.map(lambda x: x.astype(dtype), (state, decision))
        posed = fd.has_pose > 0.5
        if coast:
            pp, pv, pq = imu_predict_columns(p, v, q, dt, dp, dv, dq, sb.gravity)
            a = (decision.tracked > 0.5) & posed
            sel = lambda vis, pred: tuple(jnp.where(a, u, z) for u, z in zip(vis, pred, strict=True))  # noqa: E731
            p2, v2, q2 = sel(vp, pp), sel(vv, pv), sel(vq, pq)
            est = (a | (decision.coasting > 0.5)).astype(dtype)
        else:
            keep = lambda vis, old: tuple(jnp.where(posed, u, z) for u, z in zip(vis, old, strict=True))  # noqa: E731
            p2, v2, q2 = keep(vp, p), keep(vv, v), keep(vq, q)
            est = ((decision.tracked + decision.coasting > 0.5) & posed).astype(dtype)
        lost = jnp.maximum(lost, decision.loss * valid)
        # Coverage follows the replay: a new map closes the current one; a reset takes its estimates away.
        counted = est * gt
        # (padding frames at the end run the machine too: their resets and map starts are not the run's)
        new_map, reset = decision.new_map * valid, decision.reset * valid
        n_closed = n_closed + new_map * n_map
        n_map = (1 - new_map) * (1 - reset) * n_map + counted
        n_off = n_off + jnp.abs(counted - w)  # estimates off the frames the statistics were fixed for
        e = [w * est * (p2[i] - ref[i]) for i in range(3)]
        new = (
            e
            + [e[j] * g_c[i] for j in range(3) for i in range(3)]
            + [e[0] * e[0] + e[1] * e[1] + e[2] * e[2]]
        )
        mom = tuple(acc + d for acc, d in zip(mom, new, strict=True))
        return (state, p2, v2, q2, lost, (n_closed, n_map, n_off), mom), None

    (_, _, _, _, lost, (n_closed, n_map, n_off), mom), _ = jax.lax.scan(step, start, xs)
    s_e, s_ee = mom[:3], mom[12]
    m = [[mom[3 + 3 * j + i] for i in range(3)] for j in range(3)]  # m[j][i] = sum e_j g_c,i
    rmse, degenerate = _umeyama_residual(sb, s_e, m, s_ee, config.align)
    n = sb.n_eval
    n_gt = sb.n_gt
    coverage = jnp.where(n_gt > 0, (n_closed + n_map) / jnp.maximum(n_gt, 1.0), 0.0)
    failed = (lost > 0.5) | degenerate | (n < MIN_ALIGNMENT_FRAMES) | (coverage < config.min_coverage)
    loss = jnp.where(failed, jnp.asarray(config.failure_penalty, dtype), rmse)
    loss = jnp.where(~failed & (n_off > 0.5), jnp.nan, loss)
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
    inexact = np.isnan(merged.loss)
    if inexact.any():
        setting, run = (int(i[0]) for i in np.nonzero(inexact))
        raise ValueError(
            f"search: run {run} under setting {setting} kept tracking but has estimates on frames other "
            f"than its posed frames with ground truth ({int(inexact.sum())} setting-run pairs): the fixed "
            "alignment statistics do not apply; score such logs with jsve.core._objective.run_losses"
        )
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
    "SearchBatch",
    "prepare",
    "search_chunk",
    "search",
    "SearchResult",
    "score_columns",
    "feature_logs",
    "use_all_cores",
]
