"""Replay: what trajectory a switching rule would have produced from a logged run (DESIGN section 5).

For every frame the state machine (jsve.core._machine.machine_step) decides between the logged visual
estimate and ORB-SLAM3's IMU prediction from the previous state (PredictStateIMU, jsve.core._imu);
after LOST a new map starts a new, unaligned segment. One `lax.scan` over frames, vmapped over runs.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jsve.core._batch import LogBatch
from jsve.core._imu import imu_predict
from jsve.core._machine import (
    MODE_LOST,
    MODE_OK,
    MODE_RECENTLY_LOST,
    TIME_RECENTLY_LOST_S,
    HardLogic,
    initial_state,
    machine_step,
)
from jsve.core._rules import Rule
from jsve.core._sve import FrameFeatures, frame_features


class ReplayResult(eqx.Module):
    """Per-frame outcome of a replay, shapes [runs, frames] (+ 3 or 4).

    Attributes:
        position, quaternion, velocity: the estimate (m, wxyz, m/s; world frame of its segment).
            Meaningful where has_estimate; on frames without one (LOST) they hold the IMU
            prediction carried forward, which no error statistic uses.
        accepted: the visual estimate was used. predicted: the IMU prediction was used.
        has_estimate: accepted or predicted, and the frame exists.
        mode: MODE_OK / MODE_RECENTLY_LOST / MODE_LOST after the frame (int8; -1 on padding; the
            expected mode, rounded, when relaxed).
        segment: index of the map the frame belongs to (int32).
        lost_any: [runs] the run reached LOST at least once (tracking failure).
    In a relaxed replay (SoftLogic) the flags are probabilities.
    """

    position: Float[Array, "R F 3"]
    quaternion: Float[Array, "R F 4"]
    velocity: Float[Array, "R F 3"]
    accepted: Array
    predicted: Array
    has_estimate: Array
    mode: Int[Array, "R F"]
    segment: Array
    lost_any: Array


def replay_run(
    score: Float[Array, " F"],
    t: Float[Array, " F"],
    valid: Bool[Array, " F"],
    imu_init: Bool[Array, " F"],
    vis_p,
    vis_q,
    vis_v,
    imu_dt,
    imu_dp,
    imu_dv,
    imu_dq,
    gravity: Float[Array, " 3"],
    fps: Float[Array, ""],
    imu_init_delay: Float[Array, ""],
    thresholds,
    logic=HardLogic(),
    time_recently_lost: float = TIME_RECENTLY_LOST_S,
):
    """Replay one run (no leading runs axis); see `replay` for the batched entry point.

    Returns a dict of per-frame arrays (float flags) consumed by `replay`.
    """
    xs = (score, t, imu_init, vis_p, vis_q, vis_v, imu_dt, imu_dp, imu_dv, imu_dq)
    return _scan_frames(xs, valid, gravity, fps, imu_init_delay, thresholds, logic, time_recently_lost)


def _scan_frames(xs, valid, gravity, fps, imu_init_delay, thresholds, logic, time_recently_lost):
    """The replay scan over a leading frames axis; per-frame slices may carry any batch shape B.

    With B = (runs,) every scan step advances all runs at once as vector lanes: frames-major data
    make each step read contiguous memory, which measured 2-4x faster on CPU than vmapping a
    per-run scan over runs-major arrays (analysis/bench_evaluate.py).

    Arguments:
        xs: (score, t, imu_init, vis_p, vis_q, vis_v, imu_dt, imu_dp, imu_dv, imu_dq), each [F, *B, ...].
        valid: [F, *B]. gravity: [*B, 3]. fps, imu_init_delay: [*B].
    """
    score, t, imu_init, vis_p, vis_q, vis_v = xs[:6]
    dtype = t.dtype
    batch_shape = t.shape[1:]
    init = jax.tree.map(lambda x: jnp.broadcast_to(x, batch_shape), initial_state(dtype))
    k = jnp.broadcast_to(
        jnp.arange(t.shape[0], dtype=dtype).reshape((-1,) + (1,) * len(batch_shape)), t.shape
    )
    hard = isinstance(logic, HardLogic)
    # Hard: a 0/1 flag, set once LOST is reached. Relaxed: the part of the mass that has never been
    # LOST, as a machine state of its own whose LOST mass is dropped every frame, so that
    # lost_any = 1 - (its OK + RECENTLY_LOST mass) is the probability of ever having been LOST
    # (accumulating 1 - prod(1 - lost) instead counts mass that stays LOST for n frames n times).
    lost_carry = jnp.zeros(batch_shape, dtype) if hard else init
    start = (init, vis_p[0], vis_v[0], vis_q[0], lost_carry)

    def step(carry, x):
        state, p, v, q, lost_carry = carry
        sc, tt, ii, vp, vq, vv, dt, dp, dv, dq, kk = x
        args = (sc, tt, kk, ii.astype(dtype), thresholds, fps, imu_init_delay, time_recently_lost)
        state, decision = machine_step(logic, state, *args)
        pp, pv, pq = imu_predict(p, v, q, dt, dp, dv, dq, gravity)
        a = decision.accepted[..., None]
        p2 = a * vp + (1 - a) * pp
        v2 = a * vv + (1 - a) * pv
        q2 = logic.normalize_quat(a * vq + (1 - a) * pq)
        mode = state.recently_lost * MODE_RECENTLY_LOST + state.lost * MODE_LOST
        if hard:
            lost_carry = lost_carry + (1 - lost_carry) * state.lost
            lost_any = lost_carry
        else:
            never, _ = machine_step(logic, lost_carry, *args)
            lost_carry = eqx.tree_at(lambda s: s.lost, never, jnp.zeros_like(never.lost))
            lost_any = 1 - (never.ok + never.recently_lost)
        out = (p2, q2, v2, decision.accepted, decision.predicted, mode, state.segment, lost_any)
        return (state, p2, v2, q2, lost_carry), out

    _, (p, q, v, accepted, predicted, mode, segment, lost_any) = jax.lax.scan(step, start, tuple(xs) + (k,))
    validf = valid.astype(dtype)
    return dict(
        position=p, quaternion=q, velocity=v, accepted=accepted * validf, predicted=predicted * validf,
        has_estimate=(accepted + predicted) * validf, mode=mode, segment=segment,
        lost_any=jnp.max(lost_any * validf, axis=0),
    )  # fmt: skip


def replay(
    batch: LogBatch,
    rule: Rule,
    features: FrameFeatures | None = None,
    *,
    logic=HardLogic(),
    time_recently_lost: float = TIME_RECENTLY_LOST_S,
) -> ReplayResult:
    """Replay `rule` over every run of `batch` (jit it at the call site, or use `jsve.evaluation._evaluate`).

    Arguments:
        batch: the logs. features: per-frame features of the batch (computed if omitted; pass them
            when replaying many rules over the same batch). logic: HardLogic() for the real machine,
            SoftLogic(temperature) for the differentiable relaxation.
        time_recently_lost: s before RECENTLY_LOST turns LOST (ORB-SLAM3: 5).
    Returns:
        ReplayResult with [runs, frames] leaves, as the batch.
    """
    if features is None:
        features = batch_features(batch)
    score = rule.score(features).astype(batch.t.dtype)
    frames_major = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731
    xs = (score, batch.t, batch.imu_init, batch.vis_p, batch.vis_q, batch.vis_v, batch.imu_dt, batch.imu_dp,
          batch.imu_dv, batch.imu_dq)  # fmt: skip
    out = _scan_frames(tuple(frames_major(x) for x in xs), frames_major(batch.valid), batch.gravity,
                       batch.fps, batch.imu_init_delay, rule.thresholds, logic,
                       time_recently_lost)  # fmt: skip
    lost_any = out.pop("lost_any")
    out = {key: frames_major(value) for key, value in out.items()}
    mode = jnp.where(batch.valid, jnp.round(out["mode"]).astype(jnp.int8), jnp.int8(-1))
    if isinstance(logic, HardLogic):
        return ReplayResult(
            position=out["position"], quaternion=out["quaternion"], velocity=out["velocity"],
            accepted=out["accepted"] > 0.5, predicted=out["predicted"] > 0.5,
            has_estimate=out["has_estimate"] > 0.5, mode=mode,
            segment=out["segment"].astype(jnp.int32), lost_any=lost_any > 0.5,
        )  # fmt: skip
    return ReplayResult(
        position=out["position"], quaternion=out["quaternion"], velocity=out["velocity"],
        accepted=out["accepted"], predicted=out["predicted"], has_estimate=out["has_estimate"], mode=mode,
        segment=out["segment"], lost_any=lost_any,
    )  # fmt: skip


def batch_features(batch: LogBatch) -> FrameFeatures:
    """FrameFeatures of every frame of the batch, computed once and shared by all rules."""
    return frame_features(batch.n_extracted, batch.n_inliers, batch.n_frustum, batch.bins)


__all__ = [
    "MODE_OK",
    "MODE_RECENTLY_LOST",
    "MODE_LOST",
    "ReplayResult",
    "replay",
    "replay_run",
    "batch_features",
]
