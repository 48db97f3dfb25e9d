"""Replay: what trajectory a switching rule would have produced from a logged run (docs/state-machine.md).

For every frame the state machine (jsve.core._machine.machine_step) decides the tracking state; the
switch model decides the pose of a frame in RECENTLY_LOST: the logged, optimised pose ("orbslam3", what
ORB-SLAM3 v1.0 does) or ORB-SLAM3's IMU prediction from the previous replayed state ("imu-coast",
jsve.core._imu). Every map start (the replay's own, or one of the recorded run) begins a new, unaligned
segment; a reset before inertial BA2 takes the estimates of its map's frames away. One `lax.scan` over
frames with all runs as vector lanes.

The trajectory a run is scored on is the one the front-end saves (docs/state-machine.md, "Scoring a
run"): its frames with an estimate whose recorded pose belongs to the saved map (LogBatch.in_saved),
outside the maps the replay started itself after a loss the recorded run did not have (`own_map`: their
keyframes are not in the log, and their frames belong to no recorded map).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jsve.core._batch import LogBatch
from jsve.core._imu import imu_predict
from jsve.core._machine import (
    MODE_LOST,
    MODE_OK,
    MODE_RECENTLY_LOST,
    MONO_INIT_MIN_KEYPOINTS,
    MONO_INIT_MIN_MATCHES,
    STEREO_INIT_MIN_KEYPOINTS,
    TIME_RECENTLY_LOST_S,
    FrameData,
    HardLogic,
    RunConstants,
    check_switch_model,
    initial_state,
    machine_step,
)
from jsve.core._rules import Rule
from jsve.core._sve import FrameFeatures, frame_features


class ReplayResult(eqx.Module):
    """Per-frame outcome of a replay, shapes [runs, frames] (+ 3 or 4).

    Attributes:
        position, quaternion, velocity: the estimate (m, wxyz, m/s; world frame of its segment).
            Meaningful where has_estimate only.
        accepted: OK after the frame with a tracked pose (the test passed, or a map started here).
        coasting: RECENTLY_LOST after the frame with an estimate (the logged pose under "orbslam3",
            the IMU prediction under "imu-coast").
        has_estimate: the frame has an estimate in the replayed trajectory (after resets took theirs
            away, and only where the log supports it).
        out_of_support: the replay needs the recorded pose of a frame the recorded run did not pose.
        mode: MODE_OK / MODE_RECENTLY_LOST / MODE_LOST after the frame (int8; -1 on padding; the
            expected mode, rounded, when relaxed).
        segment: index of the replay's map the frame belongs to (int32; -1 before the first map).
        reset: the replay reset its map at this frame (before inertial BA2; ORB-SLAM3 logs the frame
            as RECENTLY_LOST, l.2149-2155, and its map's frames lose their estimates).
        own_map: the frame belongs to a map the replay started itself, after a loss of its own (not at a
            recorded map start).
        in_trajectory: the frame is in the trajectory the run is scored on: has_estimate, in the saved
            map (LogBatch.in_saved), not own_map.
        lost_any: [runs] the run lost tracking at least once (a reset, an expiry, a recorded map loss).
    In a relaxed replay (SoftLogic) the flags are probabilities.
    """

    position: Float[Array, "R F 3"]
    quaternion: Float[Array, "R F 4"]
    velocity: Float[Array, "R F 3"]
    accepted: Array
    coasting: Array
    has_estimate: Array
    out_of_support: Array
    mode: Int[Array, "R F"]
    segment: Array
    reset: Array
    own_map: Array
    in_trajectory: Array
    lost_any: Array


def as_logged_mode(result: ReplayResult) -> Array:
    """The mode of the state ORB-SLAM3 would log for each replayed frame ([R, F] int8): the replayed
    mode, except RECENTLY_LOST on a reset frame (the reset is requested after the state is set)."""
    return jnp.where(result.reset > 0.5, jnp.int8(MODE_RECENTLY_LOST), result.mode)


def _shift(x: Array, fill) -> Array:
    """x delayed by one frame along the last axis, `fill` at frame 0."""
    return jnp.concatenate([jnp.full_like(x[..., :1], fill), x[..., :-1]], axis=-1)


def frame_data(batch: LogBatch) -> FrameData:
    """The log's facts per frame ([R, F] leaves in the batch's float dtype), see FrameData."""
    dtype = batch.t.dtype
    has = batch.has_pose & batch.valid
    idx = jnp.broadcast_to(jnp.arange(batch.n_frames), has.shape)
    prev_map = _shift(batch.map_id, -1)
    rec_start = has & (~_shift(has, False) | (batch.map_id != prev_map))
    # The recorded map each frame belongs to starts at the last recorded start so far.
    start_idx = jax.lax.cummax(jnp.where(rec_start, idx, -1), axis=1)
    rec_start_t = jnp.take_along_axis(batch.t, jnp.maximum(start_idx, 0), axis=1)
    rec_loss = rec_start & (jnp.cumsum(rec_start, axis=1) > 1)
    # A recorded start in the map of the last posed frame is a reset of that map: ORB-SLAM3 restarted
    # its relocalisation window at the failed frame (ResetActiveMap, l.3915), the last posed one.
    last_posed = _shift(jax.lax.cummax(jnp.where(has, idx, -1), axis=1), -1)
    same_map = jnp.take_along_axis(batch.map_id, jnp.maximum(last_posed, 0), axis=1) == batch.map_id
    rec_reloc = jnp.where(rec_start & (last_posed >= 0) & same_map, last_posed, -1)
    stereo = batch.stereo[:, None]
    min_keys = jnp.where(stereo, STEREO_INIT_MIN_KEYPOINTS, MONO_INIT_MIN_KEYPOINTS)
    init_keys = batch.valid & (batch.n_extracted > min_keys)
    init_matches = stereo | (batch.n_inliers >= MONO_INIT_MIN_MATCHES)
    f = lambda x: x.astype(dtype)  # noqa: E731
    return FrameData(
        t=batch.t,
        k=f(idx),
        imu_init=f(batch.imu_init),
        imu_ba2=f(batch.imu_ba2),
        has_pose=f(has),
        init_keys=f(init_keys),
        init_matches=f(init_matches),
        rec_start=f(rec_start),
        rec_loss=f(rec_loss),
        rec_start_t=rec_start_t,
        rec_reloc=f(rec_reloc),
    )


def run_constants(batch: LogBatch) -> RunConstants:
    """The machine's per-run constants of a batch ([R] leaves)."""
    dtype = batch.t.dtype
    return RunConstants(
        fps=batch.fps.astype(dtype),
        imu_init_delay=batch.imu_init_delay.astype(dtype),
        ba2_delay=batch.ba2_delay.astype(dtype),
        stereo=batch.stereo.astype(dtype),
    )


def _scan_frames(
    score, data, run, logged, valid, gravity, thresholds, logic, switch_model, time_recently_lost
):
    """The replay scan over a leading frames axis; per-frame slices carry the batch shape B = (runs,).

    Every scan step advances all runs at once as vector lanes: frames-major data make each step read
    contiguous memory, which on CPU is several times faster than vmapping a per-run scan over
    runs-major arrays (benchmarks/bench_evaluate.py).

    Arguments:
        score: [F, *B]. data: FrameData with [F, *B] leaves. run: RunConstants with [*B] leaves.
        logged: (vis_p, vis_q, vis_v, imu_dt, imu_dp, imu_dv, imu_dq), each [F, *B, ...].
        valid: [F, *B]. gravity: [*B, 3].
    """
    vis_p, vis_q, vis_v = logged[:3]
    dtype = data.t.dtype
    batch_shape = data.t.shape[1:]
    init = jax.tree.map(lambda x: jnp.broadcast_to(x, batch_shape), initial_state(dtype))
    hard = isinstance(logic, HardLogic)
    coast = switch_model == "imu-coast"
    # Hard: a 0/1 flag, set at the first loss. Relaxed: the part of the mass that has never lost
    # tracking, as a machine state of its own from which every loss is dropped, so that
    # lost_any = 1 - its mass is the probability of ever having lost tracking.
    never = jnp.zeros(batch_shape, dtype) if hard else init
    start = (init, vis_p[0], vis_v[0], vis_q[0], never, jnp.zeros(batch_shape, dtype))

    def step(carry, x):
        state, p, v, q, never, own = carry
        sc, fd, vp, vq, vv, dt, dp, dv, dq = x
        args = (sc, fd, run, thresholds, time_recently_lost)
        state, decision = machine_step(logic, state, *args)
        # A map the replay starts after its own loss is its own until the recorded run starts one.
        own = (1 - fd.rec_start) * (own + (1 - own) * decision.new_map)
        posed = fd.has_pose
        if coast:
            pp, pv, pq = imu_predict(p, v, q, dt, dp, dv, dq, gravity)
            visual = decision.tracked * posed
            estimate = visual + decision.coasting
            out_of_support = decision.tracked * (1 - posed)
            # The visual share of the estimate mass. Its gradient -visual / estimate^2 (at most
            # 1 / estimate in size) overflows, and 0 * inf = NaN backwards, where estimate^2 underflows:
            # below sqrt(tiny) (~1e-154 in float64, ~1e-19 in float32) the share keeps its value but
            # carries no gradient; such a frame weighs nothing in any loss. Both branches stay finite.
            big = estimate > jnp.sqrt(jnp.finfo(dtype).tiny)
            share = visual / jnp.where(estimate > 0, estimate, 1.0)
            a = jnp.where(big, visual / jnp.where(big, estimate, 1.0), jax.lax.stop_gradient(share))
            a = a[..., None]
            p2, v2, q2 = (
                a * vp + (1 - a) * pp,
                a * vv + (1 - a) * pv,
                logic.normalize_quat(a * vq + (1 - a) * pq),
            )
        else:
            needs_pose = decision.tracked + decision.coasting
            estimate = needs_pose * posed
            out_of_support = needs_pose * (1 - posed)
            h = posed[..., None]
            p2, v2, q2 = h * vp + (1 - h) * p, h * vv + (1 - h) * v, h * vq + (1 - h) * q
        mode = state.recently_lost * MODE_RECENTLY_LOST + state.lost * MODE_LOST
        if hard:
            never = jnp.maximum(never, decision.loss)
            lost_any = never
        else:
            nxt, dn = machine_step(logic, never, *args)
            nxt = eqx.tree_at(lambda s: s.lost, nxt, nxt.lost - dn.loss + fd.rec_loss)
            keep = 1 - fd.rec_loss
            never = eqx.tree_at(lambda s: (s.ok, s.recently_lost, s.lost), nxt,
                                (nxt.ok * keep, nxt.recently_lost * keep, nxt.lost * keep))  # fmt: skip
            lost_any = 1 - (never.ok + never.recently_lost + never.lost)
        out = (p2, q2, v2, decision.tracked, decision.coasting, estimate, out_of_support, mode, state.segment,
               decision.reset, own, lost_any)  # fmt: skip
        return (state, p2, v2, q2, never, own), out

    _, out = jax.lax.scan(step, start, (score, data) + tuple(logged))
    p, q, v, tracked, coasting, estimate, out_of_support, mode, segment, reset, own, lost_any = out
    validf = valid.astype(dtype)
    return dict(
        position=p, quaternion=q, velocity=v, accepted=tracked * validf, coasting=coasting * validf,
        has_estimate=estimate * validf, out_of_support=out_of_support * validf, mode=mode, segment=segment,
        reset=reset * validf, own_map=own * validf, lost_any=jnp.max(lost_any * validf, axis=0),
    )  # fmt: skip


def _erase_reset_maps(has_estimate, segment, reset):
    """Frames of a map that was later reset lose their estimates (one run: [F] arrays).

    ORB-SLAM3's ResetActiveMap marks every frame of the active map lost (l.3893-3911); a map's frames
    are contiguous, so a frame is erased when its segment had a reset at any frame.
    """
    slot = segment.astype(jnp.int32) + 1  # -1 (no map yet) -> 0
    was_reset = jnp.zeros(segment.shape[0] + 1, bool).at[slot].max(reset > 0.5)
    return has_estimate & ~was_reset[slot]


def replay(
    batch: LogBatch,
    rule: Rule,
    features: FrameFeatures | None = None,
    *,
    switch_model: str = "orbslam3",
    logic=HardLogic(),
    time_recently_lost: float = TIME_RECENTLY_LOST_S,
    checked: bool = True,
) -> ReplayResult:
    """Replay `rule` over every run of `batch` (jit it at the call site, or use `jsve.evaluation._evaluate`).

    Arguments:
        batch: the logs. rule: any jsve rule. features: per-frame features of the batch (computed if
            omitted; pass them when replaying many rules over the same batch).
        switch_model: "orbslam3" or "imu-coast" (jsve.core._machine.SWITCH_MODELS).
        logic: HardLogic() for the real machine, SoftLogic(temperature) for the differentiable relaxation.
        time_recently_lost: s before RECENTLY_LOST turns LOST (ORB-SLAM3: 5).
        checked: False leaves the traced checks (host callbacks) out of the computation, so that JAX
            can keep it in its persistent cache; only for a rule whose `check_defined` has passed.
    Returns:
        ReplayResult with [runs, frames] leaves, as the batch.
    """
    check_switch_model(switch_model)
    if features is None:
        features = batch_features(batch)
    dtype = batch.t.dtype
    score = rule.score(features, checked=checked).astype(dtype)
    frames_major = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731
    data = jax.tree.map(frames_major, frame_data(batch))
    logged = (batch.vis_p, batch.vis_q, batch.vis_v, batch.imu_dt, batch.imu_dp, batch.imu_dv, batch.imu_dq)
    out = _scan_frames(
        frames_major(score),
        data,
        run_constants(batch),
        tuple(frames_major(x) for x in logged),
        frames_major(batch.valid),
        batch.gravity,
        rule.thresholds,
        logic,
        switch_model,
        time_recently_lost,
    )
    lost_any = out.pop("lost_any")
    out = {key: frames_major(value) for key, value in out.items()}
    mode = jnp.where(batch.valid, jnp.round(out["mode"]).astype(jnp.int8), jnp.int8(-1))
    if isinstance(logic, HardLogic):
        has_estimate = jax.vmap(_erase_reset_maps)(out["has_estimate"] > 0.5, out["segment"], out["reset"])
        own = out["own_map"] > 0.5
        return ReplayResult(
            position=out["position"], quaternion=out["quaternion"], velocity=out["velocity"],
            accepted=out["accepted"] > 0.5, coasting=out["coasting"] > 0.5, has_estimate=has_estimate,
            out_of_support=out["out_of_support"] > 0.5, mode=mode, segment=out["segment"].astype(jnp.int32),
            reset=out["reset"] > 0.5, own_map=own, in_trajectory=has_estimate & batch.in_saved & ~own,
            lost_any=lost_any > 0.5,
        )  # fmt: skip
    # Relaxed: a reset's erasure of earlier frames is left out (docs/state-machine.md, "The relaxed machine").
    in_saved = batch.in_saved.astype(dtype)
    return ReplayResult(
        position=out["position"], quaternion=out["quaternion"], velocity=out["velocity"],
        accepted=out["accepted"], coasting=out["coasting"], has_estimate=out["has_estimate"],
        out_of_support=out["out_of_support"], mode=mode, segment=out["segment"], reset=out["reset"],
        own_map=out["own_map"], in_trajectory=out["has_estimate"] * in_saved * (1 - out["own_map"]),
        lost_any=lost_any,
    )  # fmt: skip


def batch_features(batch: LogBatch) -> FrameFeatures:
    """FrameFeatures of every frame of the batch, computed once and shared by all rules.

    Compiled once per batch shape: called eagerly, its array operations (a few hundred) would each be
    compiled (or read back from the persistent cache) one by one, a large share of the time that
    loading a study for `jsve fit` takes (FitData.from_parquet)."""
    return _compiled_features(batch)


@jax.jit
def _compiled_features(batch: LogBatch) -> FrameFeatures:
    return frame_features(
        batch.n_extracted, batch.n_inliers, batch.n_frustum, batch.bins, batch.n_features[:, None]
    )


__all__ = [
    "MODE_OK",
    "MODE_RECENTLY_LOST",
    "MODE_LOST",
    "ReplayResult",
    "as_logged_mode",
    "frame_data",
    "run_constants",
    "replay",
    "batch_features",
]
