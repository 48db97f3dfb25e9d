"""The search kernel: the hard objective of a chunk of settings x runs in one compiled scan over the
frames (jsve.fitting._search drives it over a data set).

The kernel (`search_chunk`) walks the frames once for a chunk of settings x runs, with settings and runs
as the vector lanes of every scan step: ORB-SLAM3's state machine (jsve.core._machine.machine_step, the same
code the replay runs), ORB-SLAM3's IMU prediction (jsve.core._imu, on columns) and, instead of storing the
trajectory, the sufficient statistics of its alignment to ground truth. With e_k = p_k - g_k - o (the
estimate's offset from ground truth, less the run's mean visual offset o) and g_c the ground truth centred
on the run's posed frames, it accumulates sum e, M = sum e g_c^T and sum |e|^2 over the frames with an
estimate; the per-run Gram matrix G = sum g_c g_c^T over the posed frames is fixed. A lane whose estimated
frames differ from the posed ones (a frame coasting on the IMU where the recorded run has no pose, under
"imu-coast") also accumulates, over the difference (+1 for an extra frame, -1 for a missing one), its
count, sum g_c and sum g_c g_c^T, which recentre G and M on its own frames (G' = G + dG - a a^T / n',
M' = M - (sum e) a^T / n'; both corrections vanish, exactly, for the usual lane). Then the alignment
method's solver (jsve.core._align, Umeyama 1991) runs on the moments, with cov = (G' + M'^T) / n', and,
with A = I - cR, the alignment residual is

    E = tr(A^T A G') - 2c tr(A^T R M') + c^2 D,      D = sum |e - mean e|^2,

a sum of small terms (A is of the order of the error over the trajectory's extent), so float32 keeps it
to ~1e-5 relative where the textbook form sum|y|^2 + sum|x|^2 - 2 tr(...) would cancel to ~1e-2.
A run is aligned over the frames of its saved trajectory with ground truth (jsve.core._replay's
in_trajectory: frames with an estimate in the saved map, outside maps the replay started itself), as in
jsve.evaluation._evaluate: the sums of a replayed map are kept apart until the map ends (a reset erases
them, as ORB-SLAM3 marks a reset map's frames lost), and a frame's sums count only where the frame is in
the saved map. A run fails as jsve.core._objective says (ObjectiveConfig.failure), and a tracked run's loss
is capped there (ObjectiveConfig.loss). The support policy of the
objective (ObjectiveConfig.support: a run whose replay needs a recorded pose that does not exist is
penalised or excluded) is jsve.core._objective.support_outcome, applied to the same per-frame
out-of-support flag as the replay's. tests/test_search.py checks the kernel against
jsve.core._objective.run_losses setting by setting.

Everything per frame is spelled out in coordinate columns ([F, R] arrays) rather than [..., 3] rows:
XLA on CPU vectorises the former and not the latter, which matters most for the pose update and the
power means (benchmarks/bench_search.py).
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jsve.core._align import ALIGNERS, MIN_ALIGNMENT_FRAMES, Moments, fit_moments
from jsve.core._batch import LogBatch
from jsve.core._imu import imu_predict_columns
from jsve.core._machine import FrameData, HardLogic, RunConstants, initial_state, machine_step
from jsve.core._objective import ObjectiveConfig, support_outcome, tracked_loss
from jsve.core._replay import frame_data, run_constants
from jsve.core._rules import InlierRule, Rule
from jsve.core._sve import FrameFeatures, combination_from_logs, feature_logs


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
    pos_ratio: Array  # bool
    pos_s_b: Array  # bool
    pos_s_c: Array  # bool
    data: FrameData  # the log's facts per frame, [F, R] leaves, its flags bool (`_compact`)
    run: RunConstants  # [R] leaves
    valid: Array  # bool
    gt: Array  # bool: frame exists and has ground truth
    saved: Array  # bool: the frame's recorded pose belongs to the saved map (LogBatch.in_saved)
    weight: Array  # bool: gt, saved and a recorded pose: the frames the alignment statistics are fixed for
    vis_p: tuple
    g_c: tuple  # ground truth less its mean over the weight frames; 0 where gt is 0
    gravity: tuple  # [R] each
    offset: Array  # [3, R]
    g_mean: Array  # [3, R]
    gram: Array  # [3, 3, R] over the weight frames
    n_eval: Array  # [R] weight frames
    n_gt: Array  # [R] frames with ground truth
    imu: ImuColumns | None  # only "imu-coast" predicts from the IMU (`prepare(..., imu=False)`: None)

    @property
    def t(self) -> Array:
        """s since each log's first frame, [F, R]; its dtype is the kernel's float dtype."""
        return self.data.t

    @property
    def n_runs(self) -> int:
        return self.t.shape[1]

    @property
    def n_frames(self) -> int:
        return self.t.shape[0]


class ImuColumns(eqx.Module):
    """What ORB-SLAM3's IMU prediction reads per frame ([F, R] columns): the visual velocity and
    orientation it starts from and the preintegration from the previous frame (s, m, m/s, wxyz).
    Only the "imu-coast" switch model uses them: without them a frame's kernel inputs are 70 bytes
    instead of 142 in float32 (tests/test_search.py)."""

    vis_q: tuple
    vis_v: tuple
    dt: Array
    dp: tuple
    dv: tuple
    dq: tuple


FLAGS = ("imu_init", "imu_ba2", "has_pose", "init_keys", "init_matches", "rec_start", "rec_loss")
"""FrameData's 0/1 fields, held as bool in the kernel's inputs (a byte a frame instead of four) and
turned back into the float dtype a scan step at a time."""


def _compact(data: FrameData) -> FrameData:
    return dataclasses.replace(data, **{name: getattr(data, name) > 0.5 for name in FLAGS})


def _expanded(data: FrameData, dtype) -> FrameData:
    return dataclasses.replace(data, **{name: getattr(data, name).astype(dtype) for name in FLAGS})


@functools.partial(jax.jit, static_argnames=("imu",))
def prepare(batch: LogBatch, features: FrameFeatures, *, imu: bool = True) -> SearchBatch:
    """The kernel's inputs for a LogBatch and its features (one compiled call per shape); imu=False
    leaves out the columns only the "imu-coast" switch model reads (`ImuColumns`)."""
    dtype = batch.t.dtype
    fm = lambda x: jnp.swapaxes(x, 0, 1).astype(dtype)  # noqa: E731
    cols = lambda x: tuple(fm(x[..., i]) for i in range(x.shape[-1]))  # noqa: E731
    # Frames a run that keeps tracking usually has an estimate on: posed by the recorded run (a lane
    # whose estimates differ from these frames corrects the statistics in search_chunk).
    gt = batch.valid & batch.gt_valid
    weight = gt & batch.has_pose & batch.in_saved  # [R, F]
    gt_f, weight_f = gt.astype(dtype), weight.astype(dtype)
    n = jnp.sum(weight_f, axis=1)
    n_safe = jnp.maximum(n, 1.0)
    mean = lambda x: jnp.sum(weight_f[..., None] * x, axis=1) / n_safe[:, None]  # noqa: E731
    g_mean = mean(batch.gt_p)  # [R, 3]
    offset = mean(batch.vis_p - batch.gt_p)
    g_c = (batch.gt_p - g_mean[:, None]) * gt_f[..., None]
    gram = jnp.einsum("rfi,rfj->ijr", g_c * weight_f[..., None], g_c)
    logs = feature_logs(fm(features.inlier_ratio), fm(features.s_b), fm(features.s_c))
    swap = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731
    imu_columns = None
    if imu:
        imu_columns = ImuColumns(
            vis_q=cols(batch.vis_q),
            vis_v=cols(batch.vis_v),
            dt=fm(batch.imu_dt),
            dp=cols(batch.imu_dp),
            dv=cols(batch.imu_dv),
            dq=cols(batch.imu_dq),
        )
    return SearchBatch(
        n_inliers=fm(features.n_inliers),
        log_ratio=logs[0],
        log_s_b=logs[1],
        log_s_c=logs[2],
        pos_ratio=logs[3],
        pos_s_b=logs[4],
        pos_s_c=logs[5],
        data=_compact(jax.tree.map(fm, frame_data(batch))),
        run=run_constants(batch),
        valid=swap(batch.valid),
        gt=swap(gt),
        saved=swap(batch.in_saved),
        weight=swap(weight),
        vis_p=cols(batch.vis_p),
        g_c=cols(g_c),
        gravity=tuple(batch.gravity[:, i].astype(dtype) for i in range(3)),
        offset=offset.T,
        g_mean=g_mean.T,
        gram=gram,
        n_eval=n,
        n_gt=jnp.sum(gt_f, axis=1),
        imu=imu_columns,
    )


# ---------------------------------------------------------------------------------------------------
# The kernel


class ChunkResult(eqx.Module):
    """Kernel output, leaves [S, R]: loss (m), failed, rmse (m; NaN where failed), coverage, unsupported
    (the replay left the log's support), included (the pair counts in the objective: False only for an
    unsupported run under support="exclude"), as jsve.core._objective.RunLoss.
    """

    loss: Array
    failed: Array
    rmse: Array
    coverage: Array
    unsupported: Array
    included: Array


_MOMENTS = 3 + 9 + 1  # sum e, sum e_i g_c,j, sum |e|^2
_CORRECTIONS = 1 + 3 + 6  # over (estimated - weight) frames: count, sum g_c, sum g_c g_c^T (upper triangle)
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _umeyama_residual(sb: SearchBatch, s_e, m, s_ee, corrections, method: str):
    """RMSE of the aligned estimate from the alignment statistics (lanes [S, R]); the lanes' frame
    counts; and degeneracy.

    corrections: sums over (estimated - weight) frames (+1 / -1 per frame): count, sum g_c (3) and
    sum g_c g_c^T (the _PAIRS entries), all 0 where a lane's estimated frames are its weight frames.
    """
    dtype = s_ee.dtype
    d_n, d_g, d_gg = corrections[0], corrections[1:4], corrections[4:]
    n = sb.n_eval + d_n
    n_safe = jnp.maximum(n, 1.0)
    aligner = ALIGNERS[method]
    if aligner.solve is None:  # the identity (search_chunk refuses first-pose methods): sum |e + o|^2
        e2 = (
            s_ee
            + 2 * sum(sb.offset[i] * s_e[i] for i in range(3))
            + n * sum(sb.offset[i] ** 2 for i in range(3))
        )
        return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), n, jnp.zeros(s_ee.shape, bool)
    mu = [s / n_safe for s in s_e]  # mean of e (shifted offsets)
    d_c = s_ee - n * sum(x * x for x in mu)  # sum |e - mean e|^2
    # Recentre on the lane's frames: their ground-truth mean is g_mean + shift, shift = sum g_c / n
    # (sum g_c is 0 over the weight frames); G' = sum (g_c - shift)(g_c - shift)^T, M' = M - s_e shift^T.
    shift = [d / n_safe for d in d_g]
    pair = {ij: k for k, ij in enumerate(_PAIRS)}
    gram = [
        [sb.gram[i, j] + d_gg[pair[min(i, j), max(i, j)]] - d_g[i] * shift[j] for j in range(3)]
        for i in range(3)
    ]  # [3][3] of [S, R]; symmetric
    m = [[m[j][i] - s_e[j] * shift[i] for i in range(3)] for j in range(3)]
    # The moments of the pairs (estimate x = g + o + e, truth y = g): M[j][i] = sum e_j g_c,i and
    # cov[i][j] = (G[i][j] + M[j][i]) / n (Umeyama eq. 38), var_x = (tr G + 2 tr M + D) / n.
    cov = jnp.stack(
        [jnp.stack([(gram[i][j] + m[j][i]) / n_safe for j in range(3)], -1) for i in range(3)], -2
    )
    tr_g = gram[0][0] + gram[1][1] + gram[2][2]
    tr_m = m[0][0] + m[1][1] + m[2][2]
    moments = Moments(
        count=n,
        mu_x=jnp.stack([sb.g_mean[i] + shift[i] + sb.offset[i] + mu[i] for i in range(3)], -1),
        mu_y=jnp.stack([sb.g_mean[i] + shift[i] for i in range(3)], -1),
        var_x=jnp.maximum((tr_g + 2 * tr_m + d_c) / n_safe, 0.0),
        var_y=tr_g / n_safe,
        cov=cov,
    )
    # The rotation and scale of jsve.core._align's solver; the translation is the least-squares one, so the
    # residual below needs none (degenerate lanes get the identity and are failed by the caller).
    transform = fit_moments(moments, aligner.solve)
    rot, scale = transform.rotation, transform.scale
    a_mat = jnp.eye(3, dtype=dtype) - scale[..., None, None] * rot
    g = jnp.stack([jnp.stack(row, -1) for row in gram], -2)  # [S, R, 3, 3] = G'
    m_mat = jnp.stack([jnp.stack([m[j][i] for i in range(3)], -1) for j in range(3)], -2)  # [S, R, 3, 3] = M'
    term_g = jnp.sum((a_mat @ g) * a_mat, axis=(-2, -1))  # tr(A G A^T) = tr(A^T A G)
    term_m = jnp.trace(jnp.swapaxes(a_mat, -1, -2) @ rot @ m_mat, axis1=-2, axis2=-1)
    e2 = term_g - 2 * scale * term_m + scale * scale * d_c
    return jnp.sqrt(jnp.maximum(e2, 0.0) / n_safe), n, transform.degenerate


class _LaneSums(eqx.Module):
    """What one pass of the kernel's scan accumulates per lane ([S, R] leaves)."""

    lost: Array  # ever lost tracking (0 / 1)
    unsupported: Array  # ever out of the log's support (0 / 1)
    n_closed: Array  # saved estimates with ground truth in closed maps
    n_map: Array  # ... in the current map
    moments: tuple  # _MOMENTS sums over the saved estimated frames
    corrections: tuple  # _CORRECTIONS sums over (estimated - weight) frames (0 when not accumulated)
    n_off: Array  # frames off the weight frames (accumulated when the corrections are not)


def _scan(sb: SearchBatch, rule, config: ObjectiveConfig, exact: bool) -> _LaneSums:
    """The frames scan of search_chunk for lanes [S, R] (rule leaves [S, 1]); `exact` (static) also
    accumulates the corrections for estimated frames other than the weight frames, else only counts
    those frames."""
    dtype = sb.t.dtype
    coast = config.switch_model == "imu-coast"
    if coast and sb.imu is None:
        raise ValueError(
            'switch_model="imu-coast" predicts from the IMU, and these kernel inputs were prepared '
            "without its columns (prepare(..., imu=False), FitData loaded for another switch model): "
            "load the study again with the imu-coast objective"
        )
    lanes = (jax.tree.leaves(rule)[0].shape[0], sb.n_runs)
    state0 = jax.tree.map(lambda x: jnp.broadcast_to(x, lanes), initial_state(dtype))
    first = lambda cols: tuple(jnp.broadcast_to(c[0], lanes) for c in cols)  # noqa: E731
    zeros = jnp.zeros(lanes, dtype)
    counts = (zeros, zeros)  # estimates in closed maps, in the current map
    # ever lost, ever out of support, frames off the weight frames, in a map of the replay's own
    flags = (zeros, zeros, zeros, zeros)
    n_sums = _MOMENTS + (_CORRECTIONS if exact else 0)
    # The moments per map (closed, current; a reset erases the current map's); when exact, the
    # corrections over (counted - weight) frames, closed and current, and the current map's weight
    # terms, which a reset turns into -1 corrections (its frames lose their estimates).
    # Only the IMU prediction reads the velocity and orientation: without it the pose is the position.
    pose0 = (first(sb.vis_p), first(sb.imu.vis_v), first(sb.imu.vis_q)) if coast else first(sb.vis_p)
    n_w = _CORRECTIONS if exact else 0
    start = (state0, pose0, flags, counts, ((zeros,) * n_sums, (zeros,) * n_sums, (zeros,) * n_w))
    features = (sb.log_ratio, sb.log_s_b, sb.log_s_c, sb.pos_ratio, sb.pos_s_b, sb.pos_s_c)
    imu = sb.imu if coast else None
    xs = (sb.n_inliers, features, sb.data, sb.valid, sb.gt, sb.saved, sb.weight, sb.vis_p, sb.g_c, imu)
    # e = p - (g + o) = (p - (g_mean + o)) - g_c on frames with ground truth (where it counts)
    base = tuple(sb.g_mean[i] + sb.offset[i] for i in range(3))
    logic = HardLogic()

    def step(carry, x):
        state, pose, (lost, unsupported, n_off, own), (n_closed, n_map), (closed, current, w_map) = carry
        n_inl, feats, fd, valid, gt, saved, w, vp, g_c, imu = x
        valid, gt, saved, w = (f.astype(dtype) for f in (valid, gt, saved, w))
        fd = _expanded(fd, dtype)
        score = score_columns(rule, n_inl, *feats)
        state, decision = machine_step(
            logic, state, score, fd, sb.run, rule.thresholds, config.time_recently_lost
        )
        # (machine_step computes in result_type(t, float): float64 for float32 data under jax_enable_x64)
        state, decision = jax.tree.map(lambda x: x.astype(dtype), (state, decision))
        posed = fd.has_pose > 0.5
        if coast:
            p, v, q = pose
            pp, pv, pq = imu_predict_columns(p, v, q, imu.dt, imu.dp, imu.dv, imu.dq, sb.gravity)
            tracked = decision.tracked > 0.5
            a = tracked & posed
            sel = lambda vis, pred: tuple(jnp.where(a, u, z) for u, z in zip(vis, pred, strict=True))  # noqa: E731
            pose = (sel(vp, pp), sel(imu.vis_v, pv), sel(imu.vis_q, pq))
            p2 = pose[0]
            est = (a | (decision.coasting > 0.5)).astype(dtype)
            needs_pose = tracked  # as jsve.core._replay: a coasting frame needs no recorded pose
        else:
            pose = p2 = tuple(jnp.where(posed, u, z) for u, z in zip(vp, pose, strict=True))
            needs_pose = decision.tracked + decision.coasting > 0.5
            est = (needs_pose & posed).astype(dtype)
        lost = jnp.maximum(lost, decision.loss * valid)
        unsupported = jnp.maximum(unsupported, (needs_pose & ~posed).astype(dtype) * valid)
        # (padding frames at the end run the machine too: their resets and map starts are not the run's)
        new_map, reset = decision.new_map * valid, decision.reset * valid
        # A map the replay starts after its own loss is its own until the recorded run starts one.
        own = (1 - fd.rec_start) * jnp.maximum(own, new_map)
        # The saved trajectory's frames (jsve.core._replay's in_trajectory): a new map closes the current
        # one's sums; a reset erases them, this frame's with them.
        counted = est * gt * saved * (1 - own)
        n_closed = n_closed + new_map * n_map
        n_off = n_off + reset * n_map  # erased estimates are off the weight frames
        n_map = (1 - reset) * ((1 - new_map) * n_map + counted)
        e = [counted * ((p2[i] - base[i]) - g_c[i]) for i in range(3)]
        new = [
            *e,
            *(e[j] * g_c[i] for j in range(3) for i in range(3)),
            e[0] * e[0] + e[1] * e[1] + e[2] * e[2],
        ]
        off = counted - w  # +1 / -1 on frames off those the statistics were fixed for; usually 0
        erased = (0.0,) * n_w
        if exact:
            new += _correction_terms(off, g_c)
            w_new = _correction_terms(w, g_c)
            # A reset erases the current map, this frame included: its weight frames become -1s.
            erased = tuple(-(m + d) for m, d in zip(w_map, w_new, strict=True))
            w_map = tuple((1 - reset) * ((1 - new_map) * m + d) for m, d in zip(w_map, w_new, strict=True))
        else:
            n_off = n_off + jnp.abs(off)
        to_close = tuple(new_map * m for m in current[:_MOMENTS]) + tuple(
            new_map * m + reset * x for m, x in zip(current[_MOMENTS:], erased, strict=True)
        )
        closed = tuple(c + d for c, d in zip(closed, to_close, strict=True))
        current = tuple((1 - reset) * ((1 - new_map) * m + d) for m, d in zip(current, new, strict=True))
        return (
            state,
            pose,
            (lost, unsupported, n_off, own),
            (n_closed, n_map),
            (closed, current, w_map),
        ), None

    (_, _, (lost, unsupported, n_off, _), (n_closed, n_map), (closed, current, _)), _ = jax.lax.scan(
        step, start, xs
    )
    mom = tuple(c + m for c, m in zip(closed, current, strict=True))
    corrections = mom[_MOMENTS:] if exact else (jnp.zeros(lanes, dtype),) * _CORRECTIONS
    return _LaneSums(
        lost=lost,
        unsupported=unsupported,
        n_closed=n_closed,
        n_map=n_map,
        moments=mom[:_MOMENTS],
        corrections=corrections,
        n_off=n_off,
    )


def _correction_terms(a, g_c) -> list:
    """A frame's terms of the corrections, weighted by a (+1 / -1 / 0): a, a g_c (3), a g_c g_c^T
    (the _PAIRS entries)."""
    ag = [a * g_c[i] for i in range(3)]
    return [a] + ag + [ag[i] * g_c[j] for i, j in _PAIRS]


def search_chunk(sb: SearchBatch, rules: Rule, config: ObjectiveConfig = ObjectiveConfig()) -> ChunkResult:  # noqa: B008
    """Hard objective of S rule settings (leaves [S]) on every run of a SearchBatch: [S, R] results.

    The alignment corrections (estimated frames other than the posed ones) cost ~20-30 % of a scan and
    are rarely needed, so the scan runs without them where it can and checks afterwards. A lane that
    keeps tracking is estimated exactly on its posed frames with ground truth (a tracked frame needs the
    recorded pose; a posed frame without an estimate is LOST, a loss), except where a lane coasts on the
    IMU over frames the recorded run did not pose ("imu-coast") or sits in RECENTLY_LOST with the IMU
    flag dropped (a log whose imu_init falls inside a map). So under "imu-coast" on runs with unposed
    frames with ground truth the scan carries the corrections from the start; otherwise it runs
    without them and again with them only if some lane that never lost has frames off its posed ones.

    Compiled calls decided on the host: the scan (`_lane_sums`: one, or two when the corrections turn
    out to be needed), then the alignment from its sums (`chunk_result`), which `search` runs one at a
    time (see there). The choice between the scans is made on the host because on CPU a `lax.cond`
    between them about doubles the scan's time, even with the cheap branch taken; under an enclosing
    trace (a jitted objective) the `lax.cond` is used.
    """
    check_align(config)
    return chunk_result(sb, _lane_sums(sb, rules, config), config)


def check_align(config: ObjectiveConfig) -> None:
    if ALIGNERS[config.align].first_pose:
        raise ValueError(
            f"the search kernel aligns from sufficient statistics; align={config.align!r} needs the first "
            "pose: use jsve.core._objective.run_losses"
        )


def scan_sums(sb: SearchBatch, rules: Rule, config: ObjectiveConfig, exact: bool) -> _LaneSums:
    """One compiled scan of search_chunk over settings `rules` (leaves [S]): per-lane sums ([S, R]).
    Objectives that differ only in how the sums are scored share it (scan_config)."""
    return _compiled_scan_sums(sb, rules, scan_config(config), exact)


def scan_config(config: ObjectiveConfig) -> ObjectiveConfig:
    """The part of `config` the scan reads (the switch model and RECENTLY_LOST's time), the rest at its
    defaults: the penalty, alignment, coverage, failure, loss and support act on the sums afterwards
    (needs_corrections, chunk_result), so one compiled scan serves every such objective."""
    return ObjectiveConfig(switch_model=config.switch_model, time_recently_lost=config.time_recently_lost)


@functools.partial(jax.jit, static_argnames=("config", "exact"))
def _compiled_scan_sums(sb: SearchBatch, rules: Rule, config: ObjectiveConfig, exact: bool) -> _LaneSums:
    rule = jax.tree.map(lambda x: x.astype(sb.t.dtype)[:, None], rules)  # leaves [S, 1] broadcast over runs
    return _scan(sb, rule, config, exact=exact)


def exact_from_start(sb: SearchBatch, config: ObjectiveConfig) -> bool:
    """Under "imu-coast", runs with frames with ground truth and no recorded pose: lanes coasting over
    them need the corrections, so the scan carries them from the start."""
    return config.switch_model == "imu-coast" and bool(np.any(np.asarray(sb.gt) & ~np.asarray(sb.weight)))


def needs_corrections(fast: _LaneSums, config: ObjectiveConfig, n_gt) -> bool:
    """Some lane that can be scored has counted frames off its weight frames (host sync; on the host,
    since an eager jnp test would compile per shape). A lane that fails whatever its alignment needs
    none: below the coverage floor (its counts are exact without the corrections), or, under
    failure="strict", one that lost tracking."""
    off = np.asarray(fast.n_off) > 0.5
    counted = np.asarray(fast.n_closed) + np.asarray(fast.n_map)
    off &= counted >= config.min_coverage * np.asarray(n_gt) - 0.5
    if config.failure == "strict":
        off &= np.asarray(fast.lost) < 0.5
    return bool(np.any(off))


def _traced_lane_sums(sb: SearchBatch, rules: Rule, config: ObjectiveConfig) -> _LaneSums:
    """_lane_sums inside an enclosing trace (a Nelder-Mead objective under jit): the same choice as a
    `lax.cond` between the two scans, since no value reaches the host there."""
    rule = jax.tree.map(lambda x: x.astype(sb.t.dtype)[:, None], rules)
    exact = lambda: _scan(sb, rule, config, exact=True)  # noqa: E731

    def fast_then_exact():
        fast = _scan(sb, rule, config, exact=False)
        off = (fast.n_off > 0.5) & (fast.n_closed + fast.n_map >= config.min_coverage * sb.n_gt - 0.5)
        inexact = jnp.any(off & (fast.lost < 0.5) if config.failure == "strict" else off)
        return jax.lax.cond(inexact, exact, lambda: fast)

    if config.switch_model == "imu-coast":
        return jax.lax.cond(jnp.any(sb.gt & ~sb.weight), exact, fast_then_exact)
    return fast_then_exact()


def _lane_sums(sb: SearchBatch, rules: Rule, config: ObjectiveConfig) -> _LaneSums:
    """The scan of search_chunk: per-lane sums ([S, R] leaves), with the corrections where needed."""
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((sb, rules))):
        return _traced_lane_sums(sb, rules, config)
    if exact_from_start(sb, config):
        return scan_sums(sb, rules, config, exact=True)
    fast = scan_sums(sb, rules, config, exact=False)
    return scan_sums(sb, rules, config, exact=True) if needs_corrections(fast, config, sb.n_gt) else fast


@functools.partial(jax.jit, static_argnames=("config",))
def chunk_result(sb: SearchBatch, sums: _LaneSums, config: ObjectiveConfig) -> ChunkResult:
    """search_chunk's results from the lanes' sums: the alignment, coverage, failure and support."""
    dtype = sb.t.dtype
    s_e, s_ee = sums.moments[:3], sums.moments[12]
    m = [[sums.moments[3 + 3 * j + i] for i in range(3)] for j in range(3)]  # m[j][i] = sum e_j g_c,i
    rmse, n, degenerate = _umeyama_residual(sb, s_e, m, s_ee, sums.corrections, config.align)
    n_gt = sb.n_gt
    coverage = jnp.where(n_gt > 0, (sums.n_closed + sums.n_map) / jnp.maximum(n_gt, 1.0), 0.0)
    # An RMSE that is not finite (an overflow in the sums) fails the run, as in run_losses.
    failed = degenerate | (n < MIN_ALIGNMENT_FRAMES) | (coverage < config.min_coverage) | ~jnp.isfinite(rmse)
    if config.failure == "strict":
        failed = failed | (sums.lost > 0.5)
    unsupported = sums.unsupported > 0.5
    failed, included = support_outcome(unsupported, failed, config, hard=True)
    loss = jnp.where(failed, jnp.asarray(config.failure_penalty, dtype), tracked_loss(rmse, config))
    return ChunkResult(
        loss=loss,
        failed=failed,
        rmse=jnp.where(failed, jnp.nan, rmse),
        coverage=coverage,
        unsupported=unsupported,
        included=included,
    )


__all__ = [
    "SearchBatch",
    "ImuColumns",
    "prepare",
    "score_columns",
    "search_chunk",
    "ChunkResult",
    "scan_sums",
    "exact_from_start",
    "needs_corrections",
    "chunk_result",
    "check_align",
]
