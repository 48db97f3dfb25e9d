"""jsve.core._replay: the replayed ORB-SLAM3 machine on hand-built logs, scenario by scenario.

Every scenario of docs/state-machine.md is a short log built here (`log_batch`) whose modes, estimates
and segments are computed by hand from the table (Tracking.cc locations there). The randomized
comparisons with the plain-Python oracle live in tests/test_oracle.py. Then the must-shows: accept-all
is the logged trajectory bit for bit, IMU coasting on noise-free preintegration from EuRoC V1_01's
ground truth stays on the ground truth; eager, jit and vmap agree; and the relaxed (SoftLogic) replay
tends to the hard one, keeps its clocks with the masses that own them, and has the gradient of finite
differences.

Mode letters in the scenarios: O ok, R recently lost, L lost. Thresholds are the orbslam3 preset's
(imu_init 15, not_init 50, reloc 50, recovery 10) unless a test says otherwise.
"""

from __future__ import annotations

import dataclasses
import math
import re
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsve.core._batch import LogBatch
from jsve.core._imu import imu_predict
from jsve.core._machine import (
    MODE_LOST,
    MODE_OK,
    MODE_RECENTLY_LOST,
    FrameData,
    MachineState,
    RunConstants,
    SoftLogic,
    machine_step,
)
from jsve.core._replay import as_logged_mode, batch_features, frame_data, replay
from jsve.core._rules import InlierRule, SVERule, Thresholds, preset

ORB = dict(imu_init=15.0, not_init=50.0, reloc=50.0, recovery=10.0)
ACCEPT_ALL = dict(imu_init=-math.inf, not_init=-math.inf, reloc=-math.inf, recovery=math.inf)
REJECT_ALL = dict(imu_init=math.inf, not_init=math.inf, reloc=math.inf, recovery=math.inf)
# Half-integer thresholds: integer inlier scores never tie with them, so the relaxation converges.
OFF_TIE = dict(imu_init=15.5, not_init=49.5, reloc=49.5, recovery=10.5)
GRAVITY = (0.0, 0.0, -9.81)

F_SCENARIO = 192  # every scenario is padded to this length: one compilation serves them all

replay_jit = eqx.filter_jit(replay)


# ------------------------------------------------------------------------------------------------
# Building logs


def unit_quaternions(rng, n, scale=None):
    """n random unit quaternions (wxyz): uniform, or within ~`scale` rad of the identity."""
    if scale is None:
        q = rng.normal(size=(n, 4))
    else:
        q = np.concatenate([np.ones((n, 1)), rng.normal(scale=scale, size=(n, 3))], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def log_batch(
    score,
    *,
    fps=20.0,
    t=None,
    imu_init=True,
    imu_ba2=True,
    map_id=0,
    has_pose=True,
    n_extracted=1000,
    n_inliers=None,
    stereo=False,
    imu_init_delay=None,
    ba2_delay=None,
    gravity=GRAVITY,
    n_frames=None,
    seed=0,
    dtype=jnp.float32,
    **frame_arrays,
) -> LogBatch:
    """A one-run LogBatch of len(score) frames, padded to `n_frames`.

    Arguments:
        score: per frame, the InlierRule's score (the logged n_inliers unless `n_inliers` is given).
        t: s since the first frame; default k / fps from int64 nanoseconds, as jsve.io._batching does.
        imu_init, imu_ba2, map_id, has_pose, n_extracted, n_inliers: per frame, or one value for all.
        imu_init_delay, ba2_delay: s; default measured from the flags as jsve.io._batching does (from
            the first posed frame to the first flagged one, inf if never).
        frame_arrays: [n, ...] per-frame arrays replacing the random ones (vis_p, imu_dp, bins, ...).
    Poses and preintegration are random (seeded); frames without a pose get zeros and identities,
    as from_runs writes them.
    """
    score = np.asarray(score)
    n = len(score)
    F = n_frames or n

    def per_frame(x, dt):
        return np.broadcast_to(np.asarray(x, dt), (n,)).copy()

    if t is None:
        t = (np.arange(n, dtype=np.int64) * round(1e9 / fps)) / 1e9
    t = np.asarray(t, float)
    imu_init, imu_ba2, has_pose = (per_frame(x, bool) for x in (imu_init, imu_ba2, has_pose))
    t_first = t[np.argmax(has_pose)] if has_pose.any() else 0.0
    if imu_init_delay is None:
        imu_init_delay = t[np.argmax(imu_init)] - t_first if imu_init.any() else math.inf
    if ba2_delay is None:
        ba2_delay = t[np.argmax(imu_ba2)] - t_first if imu_ba2.any() else math.inf
    rng = np.random.default_rng(seed)
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    posed = has_pose[:, None]
    frames = dict(
        t=t,
        valid=np.ones(n, bool),
        state=np.zeros(n, np.int8),
        imu_init=imu_init,
        imu_ba2=imu_ba2,
        map_id=per_frame(map_id, np.int32),
        has_pose=has_pose,
        in_saved=has_pose,  # every recorded map saved unless a test says otherwise (frame_arrays)
        n_extracted=per_frame(n_extracted, np.int32),
        n_inliers=per_frame(score if n_inliers is None else n_inliers, np.int32),
        n_frustum=np.full(n, 500, np.int32),
        bins=np.zeros((n, 64), np.uint16),
        vis_p=np.where(posed, rng.normal(size=(n, 3)), 0.0),
        vis_q=np.where(posed, unit_quaternions(rng, n), identity),
        vis_v=np.where(posed, rng.normal(size=(n, 3)), 0.0),
        imu_dt=np.diff(t, prepend=t[0]),
        imu_dp=rng.normal(scale=0.05, size=(n, 3)),
        imu_dv=rng.normal(scale=0.5, size=(n, 3)),
        imu_dq=unit_quaternions(rng, n, scale=0.05),
        gt_p=np.zeros((n, 3)),
        gt_q=identity,
        gt_valid=np.zeros(n, bool),
    )
    frames.update({key: np.asarray(value) for key, value in frame_arrays.items()})

    def pad(key, x):
        x = np.concatenate([x, np.repeat(x[-1:], F - n, axis=0)])  # as pad_runs: repeat, then invalidate
        return np.where(np.arange(F) < n, x.T, False).T if key in ("valid", "gt_valid") else x

    def leaf(x):
        return jnp.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else jnp.asarray(x)

    runs = dict(
        fps=float(fps),
        gravity=gravity,
        imu_init_delay=imu_init_delay,
        ba2_delay=ba2_delay,
        n_features=1000.0,
        stereo=bool(stereo),
        run_index=0,
    )
    return LogBatch(
        **{key: leaf(pad(key, x)[None]) for key, x in frames.items()},
        **{key: leaf(np.asarray(x)[None]) for key, x in runs.items()},
    )


def stack_runs(batches) -> LogBatch:
    """One batch of the given one-run batches (same frame count), runs in order."""
    batch = jax.tree.map(lambda *x: jnp.concatenate(x), *batches)
    return dataclasses.replace(batch, run_index=jnp.arange(batch.n_runs, dtype=jnp.int32))


def scenario(score, *, th=ORB, switch_model="orbslam3", time_recently_lost=5.0, **log):
    """Replay one hand-built run (padded to F_SCENARIO frames) with an InlierRule scoring `score`
    (also where the log's n_inliers differ) and return its outcome as numpy: letters (modes), accepted,
    coasting, has_estimate, out_of_support, reset, segment, lost_any, logged (the mode ORB-SLAM3 would
    log, as_logged_mode), and the batch and result themselves.
    Padding frames must carry no decision."""
    n = len(score)
    batch = log_batch(score, n_frames=F_SCENARIO, **log)
    padded = np.concatenate([np.asarray(score, float), np.zeros(F_SCENARIO - n)])[None]
    features = dataclasses.replace(batch_features(batch), n_inliers=jnp.asarray(padded, batch.t.dtype))
    res = replay_jit(
        batch,
        InlierRule(Thresholds(**th)),
        features,
        switch_model=switch_model,
        time_recently_lost=time_recently_lost,
    )
    mode = np.asarray(res.mode[0])
    assert (mode[n:] == -1).all()
    keys = ("accepted", "coasting", "has_estimate", "out_of_support", "reset")
    flags = {k: np.asarray(getattr(res, k)[0]) for k in keys}
    assert not any(flag[n:].any() for flag in flags.values())
    return SimpleNamespace(
        letters="".join("ORL"[m] for m in mode[:n]),
        logged="".join("ORL"[m] for m in np.asarray(as_logged_mode(res)[0, :n])),
        **{k: flag[:n] for k, flag in flags.items()},
        segment=np.asarray(res.segment[0, :n]),
        lost_any=bool(res.lost_any[0]),
        batch=batch,
        res=res,
    )


# ------------------------------------------------------------------------------------------------
# The log's facts per frame


def test_frame_data_marks_recorded_map_starts():
    """A recorded map starts at the first posed frame, at a map_id change and at a pose after frames
    without one; every start but the log's first is a recorded loss. A start in the map of the last
    posed frame (a reset: the pose-less gap keeps the map id) restarts the relocalisation window at
    that posed frame; a new map id does not. A frame has the keypoints of an initialisation frame with
    > 100 (mono) or > 500 (stereo), and the matches to a monocular reference with >= 100 inliers."""
    has_pose = [False, True, True, True, False, False, True, True, True, True]
    map_id = [0, 0, 0, 0, 0, 0, 0, 0, 1, 1]
    ext = [1000, 1000, 101, 1000, 1000, 1000, 1000, 100, 1000, 600]
    inl = [200, 200, 200, 99, 200, 200, 100, 200, 200, 100]
    batch = log_batch(inl, has_pose=has_pose, map_id=map_id, n_extracted=ext)
    data = frame_data(batch)
    get = lambda key: np.asarray(getattr(data, key)[0]).tolist()  # noqa: E731
    assert get("rec_start") == [0, 1, 0, 0, 0, 0, 1, 0, 1, 0]
    assert get("rec_loss") == [0, 0, 0, 0, 0, 0, 1, 0, 1, 0]
    assert get("rec_reloc") == [-1, -1, -1, -1, -1, -1, 3, -1, -1, -1]
    assert get("init_keys") == [1, 1, 1, 1, 1, 1, 1, 0, 1, 1]
    assert get("init_matches") == [1, 1, 1, 0, 1, 1, 1, 1, 1, 1]
    t = np.asarray(batch.t[0])
    assert get("rec_start_t") == t[[0, 1, 1, 1, 1, 1, 6, 6, 8, 8]].tolist()
    stereo = frame_data(log_batch(inl, has_pose=has_pose, map_id=map_id, n_extracted=ext, stereo=True))
    assert np.asarray(stereo.init_keys[0]).tolist() == [1, 1, 0, 1, 1, 1, 1, 0, 1, 1]
    assert np.asarray(stereo.init_matches[0]).tolist() == [1] * 10


# ------------------------------------------------------------------------------------------------
# RECENTLY_LOST: the timer and recovery


def test_timer_expires_strictly_after_five_seconds():
    # fps 16: frame times k / 16 are exact in binary, so t - t_lost is exactly 5.0 at 80 frames.
    run = scenario([100] * 20 + [5] * 120, fps=16)
    # Frame 20 fails (t_lost = 1.25); frame 100 has t - t_lost = 5.0 exactly: not expired (strict >);
    # frame 101 expires. 5 inliers never allow a new map (< 100).
    assert run.letters == "O" * 20 + "R" * 81 + "L" * 39
    assert run.coasting[20:101].all() and not run.accepted[20:101].any()
    assert run.has_estimate[:101].all() and not run.has_estimate[101:].any()
    assert run.lost_any and (run.segment == 0).all()


def test_timer_is_not_restarted_and_the_expiry_frame_is_not_tried():
    # Failing frames in RECENTLY_LOST do not restart the timer; the expiry frame (101) is not tried
    # although 200 would pass; the next frame is the new map's reference and the one after starts it.
    run = scenario([100] * 20 + [5] * 81 + [200] * 6, fps=16)
    assert run.letters == "O" * 20 + "R" * 81 + "LL" + "O" * 4
    assert run.accepted[103] and run.segment[102] == 0 and run.segment[103] == 1
    assert (
        run.has_estimate[:101].all() and not run.has_estimate[101:103].any() and run.has_estimate[103:].all()
    )
    # A recovery ends RECENTLY_LOST; the next failure in OK starts a new timer (t_lost = 61 / 16).
    run = scenario([100] * 20 + [5] * 40 + [12] + [5] * 90, fps=16)
    assert run.letters == "O" * 20 + "R" * 40 + "O" + "R" * 81 + "L" * 9


def test_recovery_needs_the_recovery_threshold_and_the_imu():
    # RECENTLY_LOST -> OK needs score > recovery (strict): 10 stays, 11 recovers.
    run = scenario([100] * 25 + [5, 10, 11])
    assert run.letters[25:] == "RRO"
    assert run.coasting[25:27].all() and run.accepted[27]
    # In OK a tie with imu_init passes (fail only below).
    assert scenario([100] * 25 + [15, 14]).letters[25:] == "OR"
    # Recovery above imu_init: in RECENTLY_LOST the main test still applies (17 >= 15 succeeds).
    assert scenario([100] * 25 + [5, 17], th=dict(ORB, recovery=20.0)).letters[25:] == "RO"
    # The recorded IMU switched off on frames 26-28 (l.1988-1991): RECENTLY_LOST without an estimate and
    # without a recovery attempt (200 would pass); with the IMU back, a failing frame coasts again.
    run = scenario([100] * 25 + [5] + [200] * 3 + [5, 200], imu_init=[True] * 26 + [False] * 3 + [True] * 2)
    assert run.letters[25:] == "RRRRRO"
    assert run.coasting.tolist()[25:] == [True, False, False, False, True, False]
    assert run.has_estimate.tolist()[25:] == [True, False, False, False, True, True]
    assert not run.lost_any


# ------------------------------------------------------------------------------------------------
# Resets, relocalisation windows, new maps


@pytest.mark.parametrize("missing", ["imu_init", "imu_ba2"])
def test_failure_before_imu_or_ba2_resets_the_map(missing):
    """OK fails without the IMU initialised or before inertial BA2 (l.2149-2153): the map is reset, so
    that frame and every earlier frame of the map lose their estimates, and the run lost tracking; a new
    map starts two frames later (the reset frame's successor is the reference)."""
    run = scenario([100] * 30 + [5] + [100] * 9, **{missing: False})
    assert run.letters == "O" * 30 + "LL" + "O" * 8
    assert run.accepted[:30].all() and not run.coasting.any()
    assert not run.has_estimate[:32].any() and run.has_estimate[32:].all()
    assert run.segment.tolist() == [0] * 32 + [1] * 8
    assert run.lost_any and run.reset.tolist() == [False] * 30 + [True] + [False] * 9
    # ORB-SLAM3 sets RECENTLY_LOST on the failed frame and resets the map at the next one (l.2149-2155).
    assert run.logged == "O" * 30 + "RL" + "O" * 8
    # The same failure with the IMU initialised and BA2 done goes to RECENTLY_LOST and keeps everything.
    run = scenario([100] * 30 + [5] + [100] * 9)
    assert run.letters == "O" * 30 + "R" + "O" * 9 and run.has_estimate.all() and not run.lost_any


def test_relocalisation_window_of_the_log_start():
    # fps 20: frames 0..19 need >= 50 (reloc); frame 19 fails with 49, frame 20 passes with 49.
    assert scenario([100] * 19 + [49] + [100] * 5).letters[19] == "R"
    assert scenario([100] * 20 + [49] + [100] * 5).letters[20] == "O"
    # Fractional fps truncates like ORB-SLAM3's int mMaxFrames: 20.9 -> 20 frames.
    assert scenario([100] * 20 + [49] + [100] * 5, fps=20.9).letters[20] == "O"
    # In RECENTLY_LOST the window check comes before the recovery rule: 30 > 10 still fails.
    assert scenario([100] * 5 + [5] + [30] * 3 + [100] * 3).letters[5:] == "RRRRO" + "OO"


@pytest.mark.parametrize("fail_at, letter", [(33, "R"), (49, "R"), (50, "O")])
def test_relocalisation_window_after_a_reset(fail_at, letter):
    """A reset sets mnLastRelocFrameId (l.3915): BA2 missing on frame 30 only resets there, the new map
    starts at 32, and frames 32..49 (< 30 + 20) need the reloc threshold: 40 fails inside, passes after."""
    score = [100] * 30 + [5] + [100] * 29
    score[fail_at] = 40
    run = scenario(score, imu_ba2=[True] * 30 + [False] + [True] * 29)
    assert run.letters[30:32] == "LL" and run.segment[32] == 1
    assert run.letters[fail_at] == letter


def test_no_relocalisation_window_after_a_new_map_from_expiry():
    """CreateMapInAtlas leaves mnLastRelocFrameId alone (l.2675): after the expiry at frame 101 the new map
    starts at 103 and its frame 104 passes with 40 (< reloc, >= imu_init); after a reset it would not."""
    run = scenario([100] * 20 + [5] * 81 + [100] * 3 + [40] + [100] * 3, fps=16)
    assert run.letters[100:] == "RLLOOOOO" and run.segment[103] == 1


@pytest.mark.parametrize(
    "change, init_at",
    [
        ({}, 27),  # the loss at 25, the reference at 26, the map at 27
        ({"n_extracted": {26: 100}}, 28),  # the reference needs > 100 keypoints
        ({"n_extracted": {27: 100}}, 29),  # so does the second frame (and then it is no reference)
        ({"n_inliers": {27: 100}}, 27),  # >= 100 matches (the recorded inliers stand in) suffice
        ({"n_inliers": {27: 99, 28: 99}}, 29),  # 99 do not
    ],
)
def test_map_initialisation_after_a_loss(change, init_at):
    """MonocularInitialization (l.2448-2522), without the rule: IMU never initialised, so the failure at
    frame 25 (40 < not_init) resets; the new map needs two frames after the loss, > 100 keypoints on both
    frames and >= 100 inliers on the second."""
    n = 40
    ext, inl = np.full(n, 1000), np.array([100] * 25 + [40] + [150] * 14)
    for k, value in change.get("n_extracted", {}).items():
        ext[k] = value
    for k, value in change.get("n_inliers", {}).items():
        inl[k] = value
    # The rule scores 100 after the loss whatever the recorded inliers: only the data decide the map.
    score = [100] * 25 + [40] + [100] * 14
    run = scenario(score, imu_init=False, n_extracted=ext, n_inliers=inl)
    assert run.letters == "O" * 25 + "L" * (init_at - 25) + "O" * (n - init_at)
    assert run.segment[init_at - 1] == 0 and run.segment[init_at] == 1 and run.accepted[init_at]


def test_new_maps_do_not_need_the_rule():
    """A rule that rejects every frame, IMU never initialised: every map is reset on its second frame,
    the next starts two frames later, and no frame keeps an estimate."""
    run = scenario([200] * 30, th=REJECT_ALL, imu_init=False)
    assert run.letters == "OLL" * 10
    assert run.segment.tolist() == [k // 3 for k in range(30)]
    assert not run.has_estimate.any() and run.lost_any


@pytest.mark.parametrize("delayed", ["imu_init", "imu_ba2"])
@pytest.mark.parametrize("fail_at, letter", [(38, "L"), (39, "R")])
def test_a_map_started_by_the_replay_waits_for_the_recorded_delays(delayed, fail_at, letter):
    """fps 16 (dyadic times). The recorded run's flag turns on at frame 32 (t = 2 s, its delay). The
    replay resets at frame 5 and starts a map at frame 7 (t = 0.4375), which waits as long again: its IMU
    (or BA2) counts from t = 2.4375, frame 39. A failure at 38 resets, one at 39 goes to RECENTLY_LOST."""
    flag = np.arange(60) >= 32
    flags = dict.fromkeys(["imu_init", "imu_ba2"] if delayed == "imu_init" else ["imu_ba2"], flag)
    score = [100] * 5 + [10] + [100] * 54
    score[fail_at] = 10
    run = scenario(score, fps=16, **flags)
    assert run.letters[5:8] == "LLO" and run.segment[7] == 1
    assert run.letters[fail_at] == letter
    if letter == "L":
        assert not run.has_estimate[: fail_at + 2].any()  # the second map was reset too
    else:
        assert run.coasting[fail_at] and run.has_estimate[7:].all()
    # The recorded run's own map needs no wait beyond the flag: 10 at frame 31 resets, at 32 coasts.
    assert scenario([100] * 31 + [10] + [100] * 28, fps=16, **flags).letters[31] == "L"
    assert scenario([100] * 32 + [10] + [100] * 27, fps=16, **flags).letters[32] == "R"


# ------------------------------------------------------------------------------------------------
# The recorded run's own maps, support


def test_recorded_map_change_starts_a_new_segment():
    """A new map_id at frame 30: the replay ends its map whatever the rule (a segment break and
    lost_any), starts the recorded one, and gets no relocalisation window (not a reset): 40 passes."""
    score = [100] * 60
    score[31] = 40
    run = scenario(score, map_id=[0] * 30 + [1] * 30)
    assert run.letters == "O" * 60 and run.has_estimate.all()
    assert run.segment.tolist() == [0] * 30 + [1] * 30
    assert run.lost_any
    # Never one segment: without the change, the same run is one map that never lost tracking.
    run = scenario(score)
    assert (run.segment == 0).all() and not run.lost_any


def test_pose_less_gap_starts_a_new_segment_and_is_out_of_support():
    """Frames 30..34 have no recorded pose (the recorded run reset, map id kept). The replay keeps
    tracking through them (100 inliers pass) but has no pose to give: out of support, no estimate.
    The recorded map restarts at 35: a new segment, lost_any, and a relocalisation window restarted at
    the recorded reset (its last posed frame, 29): 40 fails at frame 40 (< 49), passes at 49."""
    score = [100] * 65
    score[40] = score[49] = 40
    run = scenario(score, has_pose=[True] * 30 + [False] * 5 + [True] * 30)
    assert run.letters[:40] == "O" * 40 and run.letters[40] == "R" and run.letters[49] == "O"
    assert run.out_of_support.tolist() == [False] * 30 + [True] * 5 + [False] * 30
    assert not run.has_estimate[30:35].any() and run.has_estimate[35:].all() and run.has_estimate[:30].all()
    assert run.segment.tolist() == [0] * 35 + [1] * 30
    assert run.lost_any


def test_log_start_without_pose_is_no_loss():
    """Frames before the recorded run's first pose: LOST, no map yet (segment -1), not out of support
    (the replay needs no pose there); the first map starts at the first posed frame, not a loss."""
    run = scenario([100] * 20, has_pose=[False] * 5 + [True] * 15)
    assert run.letters == "L" * 5 + "O" * 15
    assert run.segment.tolist() == [-1] * 5 + [0] * 15
    assert not run.out_of_support.any() and run.has_estimate.tolist() == [False] * 5 + [True] * 15
    assert not run.lost_any


@pytest.mark.parametrize("switch_model", ["orbslam3", "imu-coast"])
def test_support_depends_on_the_switch_model(switch_model):
    """RECENTLY_LOST from frame 30; the recorded run has no pose on 32..37; the replay recovers at 36.
    Under "orbslam3" every frame the replay tracks or coasts needs the recorded pose; under
    "imu-coast" coasting frames are predicted and need none, tracked ones still do."""
    run = scenario(
        [100] * 30 + [5] * 6 + [100] * 14,
        has_pose=[True] * 32 + [False] * 6 + [True] * 12,
        switch_model=switch_model,
    )
    assert run.letters == "O" * 30 + "R" * 6 + "O" * 14
    coast = switch_model == "imu-coast"
    expected = [False] * 32 + [not coast] * 4 + [True] * 2 + [False] * 12
    assert run.out_of_support.tolist() == expected
    assert run.has_estimate.tolist() == [not x for x in expected]
    assert run.segment.tolist() == [0] * 38 + [1] * 12 and run.lost_any


@pytest.mark.parametrize(
    "stereo, imu, score, letter",
    [
        (False, False, 20, "L"),  # mono before IMU initialisation: 20 < not_init, a reset
        (True, False, 20, "O"),  # stereo: only imu_init (15) applies, whatever the IMU
        (True, False, 14, "L"),  # below it the stereo map resets (no IMU yet)
        (False, True, 20, "O"),
        (True, True, 14, "R"),
    ],
)
def test_stereo_fails_below_imu_init_whatever_the_imu(stereo, imu, score, letter):
    """IMU_STEREO / IMU_RGBD (l.3047-3053): the main test is `imu_init` with or without the IMU."""
    run = scenario([100] * 25 + [score] + [100] * 2, stereo=stereo, imu_init=imu)
    assert run.letters[25] == letter
    # The relocalisation window still applies to stereo: 40 < reloc on frame 10.
    assert scenario([100] * 10 + [40], stereo=stereo, imu_init=imu).letters[10] == ("R" if imu else "L")


def test_stereo_map_initialisation_needs_500_keypoints():
    """StereoInitialization (l.2337): > 500 keypoints on the frame itself; the monocular one needs
    > 100 on two frames. Frames 26, 27 have 400 keypoints after the reset at frame 25."""
    ext = [1000] * 26 + [400] * 2 + [1000] * 4
    score = [100] * 25 + [5] + [100] * 6
    assert scenario(score, imu_init=False, n_extracted=ext).letters[25:] == "LL" + "O" * 5
    assert scenario(score, imu_init=False, n_extracted=ext, stereo=True).letters[25:] == "LLL" + "O" * 4


# ------------------------------------------------------------------------------------------------
# Switch models: the pose of a frame in RECENTLY_LOST


def test_orbslam3_poses_are_the_logged_ones():
    """Under "orbslam3" every estimated frame, tracked or coasting, has its logged pose bit for bit."""
    # RECENTLY_LOST from frame 20 and from 60; from 80 the IMU is off: no estimate.
    run = scenario([100] * 20 + [5] * 30 + [100] * 10 + [5] * 60, imu_init=[True] * 80 + [False] * 40)
    assert run.coasting.sum() == 50 and run.accepted.sum() == 30 and not run.has_estimate[80:].any()
    est = run.has_estimate
    for key, name in (("position", "vis_p"), ("quaternion", "vis_q"), ("velocity", "vis_v")):
        got, logged = (
            np.asarray(getattr(run.res, key)[0, :120]),
            np.asarray(getattr(run.batch, name)[0, :120]),
        )
        assert np.array_equal(got[est], logged[est]), key


def test_imu_coast_follows_predict_state_imu(x64):
    """Under "imu-coast" a frame in RECENTLY_LOST is PredictStateIMU from the previous replayed state:
    jsve.core._imu.imu_predict chained by hand from the last tracked frame's logged state (float64, to
    1e-12: the replay's fused arithmetic may round differently, a few ulp of metre-scale values over
    30 steps); tracked frames keep their logged pose bit for bit."""
    score = [100] * 20 + [5] * 30 + [100] * 10 + [5] * 20
    run = scenario(score, switch_model="imu-coast", dtype=jnp.float64)
    assert run.letters == "O" * 20 + "R" * 30 + "O" * 10 + "R" * 20
    b = jax.tree.map(lambda x: np.asarray(x[0]), run.batch)
    pos, quat, vel = (np.asarray(getattr(run.res, k)[0]) for k in ("position", "quaternion", "velocity"))
    for k in range(len(score)):
        if run.letters[k] == "O":
            p, v, q = b.vis_p[k], b.vis_v[k], b.vis_q[k]
            assert np.array_equal(pos[k], p) and np.array_equal(vel[k], v) and np.array_equal(quat[k], q)
        else:
            p, v, q = (np.asarray(x) for x in imu_predict(
                p, v, q, b.imu_dt[k], b.imu_dp[k], b.imu_dv[k], b.imu_dq[k], b.gravity))  # fmt: skip
            np.testing.assert_allclose(pos[k], p, rtol=0, atol=1e-12, err_msg=f"frame {k}")
            np.testing.assert_allclose(vel[k], v, rtol=0, atol=1e-12, err_msg=f"frame {k}")
            np.testing.assert_allclose(quat[k], q, rtol=0, atol=1e-12, err_msg=f"frame {k}")
            assert np.abs(pos[k] - b.vis_p[k]).max() > 0.1  # not the logged pose


# ------------------------------------------------------------------------------------------------
# Must-shows: accept-all, dead reckoning on EuRoC ground truth


def random_log(rng, n, n_frames, *, kind="inliers", dtype=jnp.float32, seed=0) -> LogBatch:
    """A random one-run log of n frames (padded to n_frames) that drives the machine everywhere:
    stretches of good, marginal and bad scores, the IMU and BA2 switched on mid-run, sometimes a
    recorded map change, a pose-less gap, frames with few keypoints, stereo; SVE bins when kind="sve"."""
    score = []
    while len(score) < n:
        stretch = rng.choice(3, p=[0.5, 0.3, 0.2])  # good, marginal, bad (never above recovery)
        lo, hi = [(60, 400), (5, 60), (0, 10)][stretch]
        score += rng.integers(lo, hi, int(rng.integers(3, [60, 60, 120][stretch]))).tolist()
    score = np.asarray(score[:n])
    # Half the runs have the IMU and BA2 from the start (losses go to RECENTLY_LOST), half later (resets).
    k_imu, k_ba2 = (0, 0) if rng.random() < 0.5 else sorted(rng.integers(0, n // 4, 2).tolist())
    map_id = np.zeros(n, int)
    if rng.random() < 0.3:
        map_id[int(rng.integers(n // 2, n)) :] = 1
    has_pose = np.ones(n, bool)
    if rng.random() < 0.3:
        start = int(rng.integers(5, n - 5))
        has_pose[start : start + int(rng.integers(1, 10))] = False
    ext = np.where(rng.random(n) < 0.1, rng.integers(50, 150, n), 1000)
    extra = {}
    if kind == "sve":
        ext = np.where(rng.random(n) < 0.05, 0, rng.integers(100, 1000, n))  # some frames without features
        score = np.minimum(score, ext)
        spread = rng.choice([0.05, 0.5, 5.0], n)  # Dirichlet concentration: few bins to all bins
        extra["bins"] = np.stack(
            [
                rng.multinomial(int(e * 0.95), rng.dirichlet(np.full(64, a)))
                for e, a in zip(ext, spread, strict=True)
            ]
        ).astype(np.uint16)
        extra["n_frustum"] = np.round(score / rng.uniform(0.5, 0.95, n)).astype(np.int32)
    return log_batch(
        score,
        fps=float(rng.choice([10.0, 16.0, 20.0, 20.5])),
        imu_init=np.arange(n) >= k_imu,
        imu_ba2=np.arange(n) >= k_ba2,
        map_id=map_id,
        has_pose=has_pose,
        n_extracted=ext,
        stereo=rng.random() < 0.25,
        n_frames=n_frames,
        seed=seed,
        dtype=dtype,
        **extra,
    )


def random_batch(seed, n_runs, n_frames, *, min_frames=None, kind="inliers", dtype=jnp.float32) -> LogBatch:
    rng = np.random.default_rng(seed)
    lengths = rng.integers(min_frames or n_frames // 2, n_frames + 1, n_runs)
    return stack_runs([random_log(rng, int(n), n_frames, kind=kind, dtype=dtype, seed=seed * 1000 + i)
                       for i, n in enumerate(lengths)])  # fmt: skip


@pytest.mark.parametrize("switch_model", ["orbslam3", "imu-coast"])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_accept_all_returns_the_logged_trajectory_bitwise(switch_model, dtype):
    """A rule that never fails keeps the logged trajectory bit for bit (under "imu-coast" the blend
    a * logged + (1 - a) * prediction with a = 1 must not touch a bit): one map, no loss."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", dtype == jnp.float64)
    try:
        rng = np.random.default_rng(3)
        logs = [
            log_batch(
                rng.integers(0, 300, n), n_frames=200, seed=n, dtype=dtype, imu_init=False, imu_ba2=False
            )
            for n in rng.integers(100, 201, 8).tolist()
        ]
        batch = stack_runs(logs)
        res = replay_jit(batch, InlierRule(Thresholds(**ACCEPT_ALL)), switch_model=switch_model)
    finally:
        jax.config.update("jax_enable_x64", previous)
    assert res.position.dtype == dtype
    valid = np.asarray(batch.valid)
    assert np.asarray(res.accepted)[valid].all() and not np.asarray(res.coasting).any()
    assert np.asarray(res.has_estimate)[valid].all() and (np.asarray(res.segment)[valid] == 0).all()
    assert not np.asarray(res.lost_any).any()
    for key, name in (("position", "vis_p"), ("quaternion", "vis_q"), ("velocity", "vis_v")):
        assert np.array_equal(
            np.asarray(getattr(res, key))[valid], np.asarray(getattr(batch, name))[valid]
        ), key


def _read_t_bs(path) -> np.ndarray:
    text = path.read_text()
    block = text[text.index("T_BS:") :]
    data = block[block.index("[") + 1 : block.index("]")]
    return np.array([float(x) for x in re.split(r"[,\s]+", data.strip()) if x]).reshape(4, 4)


def euroc_body_states(shared_data):
    """V1_01 ground-truth body states: t (s), positions, rotations (scipy) and finite-difference
    velocities (world frame)."""
    rows = (shared_data / "euroc/groundtruth_left_cam/V101_GT.txt").read_text().splitlines()[1:]
    stamps = np.array([int(r.split(",")[0].split(".")[0]) for r in rows], np.int64)
    values = np.array([[float(x) for x in r.split(",")[1:]] for r in rows])
    t = (stamps - stamps[0]) / 1e9
    p_wc = values[:, :3]
    r_wc = Rotation.from_quat(values[:, [4, 5, 6, 3]])  # wxyz -> scipy's xyzw (normalised by scipy)
    T_bs = _read_t_bs(shared_data / "euroc/V1_01_first95/mav0/cam0/sensor.yaml")
    u, _, vt = np.linalg.svd(T_bs[:3, :3])  # orthonormalise the 12-digit calibration
    r_bs = Rotation.from_matrix(u @ vt)
    # T_BS is body-from-camera: T_wc = T_wb T_bs, so T_wb = T_wc T_bs^-1.
    r_wb = r_wc * r_bs.inv()
    p_wb = p_wc - r_wb.apply(T_bs[:3, 3])
    v_wb = np.gradient(p_wb, t, axis=0)  # second-order finite differences on the 20 Hz samples
    return t, p_wb, r_wb, v_wb


def test_imu_coast_dead_reckoning_on_euroc_ground_truth(shared_data, x64):
    """Noise-free preintegration from consecutive ground-truth states (the prediction equations
    inverted exactly: dR = R1^T R2, dV = R1^T (v2 - v1 - g dt), dP = R1^T (p2 - p1 - v1 dt - g dt^2/2),
    in scipy's rotation algebra, not jsve's) makes a reject-all rule coast on the IMU through the whole
    143 s of V1_01 up to rounding. Bound: 1e-6 m. Rounding in float64 is ~1e-16 relative per step; an
    orientation error of k * 1e-16 rad after k steps feeds |dV| ~ 0.5 m/s, so velocity and position
    errors stay below ~1e-9 over 2,871 frames; any model error (a sign of g, the frame of dP, the
    0.5 dt^2) is metres."""
    t, p, rot, v = euroc_body_states(shared_data)
    n = len(t)
    g = np.asarray(GRAVITY)
    dt = np.diff(t, prepend=0.0)
    dq, dv, dp = np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))
    back = rot[:-1].inv()
    dq[1:] = np.roll((back * rot[1:]).as_quat(), 1, axis=1)  # xyzw -> wxyz
    dv[1:] = back.apply(v[1:] - v[:-1] - g * dt[1:, None])
    dp[1:] = back.apply(p[1:] - p[:-1] - v[:-1] * dt[1:, None] - 0.5 * g * dt[1:, None] ** 2)
    q = np.roll(rot.as_quat(), 1, axis=1)
    # The logged estimate is ground truth at frame 0 and far off elsewhere: coasting must not use it.
    vis_p = p + 100.0
    vis_p[0] = p[0]
    preintegration = dict(imu_dt=dt, imu_dp=dp, imu_dv=dv, imu_dq=dq)
    batch = log_batch(np.zeros(n), t=t, vis_p=vis_p, vis_q=q, vis_v=v, dtype=jnp.float64, **preintegration)
    res = replay_jit(
        batch, InlierRule(Thresholds(**REJECT_ALL)), switch_model="imu-coast", time_recently_lost=math.inf
    )
    assert bool(res.accepted[0, 0]) and np.asarray(res.coasting[0, 1:]).all()
    err_p = np.abs(np.asarray(res.position[0]) - p).max()
    err_v = np.abs(np.asarray(res.velocity[0]) - v).max()
    # q and -q are one rotation.
    err_q = np.abs(np.abs(np.sum(np.asarray(res.quaternion[0]) * q, axis=1)) - 1).max()
    assert err_p < 1e-6, err_p
    assert err_v < 1e-6, err_v
    assert err_q < 1e-12, err_q
    # The data are a real trajectory (not a trivial one): it moves metres and turns.
    assert np.ptp(p, axis=0).max() > 2.0 and np.abs(dv).max() > 0.3


# ------------------------------------------------------------------------------------------------
# Eager, jit, vmap


@pytest.mark.parametrize("switch_model", ["orbslam3", "imu-coast"])
def test_replay_eager_jit_vmap_agree(x64, switch_model):
    """Eagerly, under jit, and vmapped over stacked one-run batches, replay equals one batched call:
    decisions, modes and segments exactly, poses to 1e-12 (float64; differently fused arithmetic may
    round differently: a few ulp of metre-scale values after at most 5 s of prediction)."""
    n_runs = 4
    batch = random_batch(11, n_runs, 160, min_frames=120, dtype=jnp.float64)
    rule = InlierRule(Thresholds(**ORB))
    batched = replay_jit(batch, rule, switch_model=switch_model)
    singles = [jax.tree.map(lambda x, i=i: x[i : i + 1], batch) for i in range(n_runs)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *singles)
    vmapped = jax.jit(jax.vmap(lambda b: replay(b, rule, switch_model=switch_model)))(stacked)
    vmapped = jax.tree.map(lambda x: x[:, 0], vmapped)  # [runs, 1, ...] -> [runs, ...]
    eager = replay(batch, rule, switch_model=switch_model)
    for other in (vmapped, eager):
        for key in ("accepted", "coasting", "has_estimate", "out_of_support", "mode", "segment", "lost_any"):
            assert np.array_equal(np.asarray(getattr(batched, key)), np.asarray(getattr(other, key))), key
        est = np.asarray(batched.has_estimate)
        for key in ("position", "quaternion", "velocity"):
            got, want = np.asarray(getattr(other, key))[est], np.asarray(getattr(batched, key))[est]
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=key)
    # The runs drive the machine: every mode, resets and new maps, coasting frames.
    mode = np.asarray(batched.mode)
    assert all((mode == m).any() for m in (MODE_OK, MODE_RECENTLY_LOST, MODE_LOST))
    assert np.asarray(batched.coasting).sum() > 20 and (np.asarray(batched.segment).max(axis=1) >= 1).any()


# ------------------------------------------------------------------------------------------------
# The relaxed (SoftLogic) replay


def test_soft_logic_converges_to_hard_logic(x64):
    """As the temperature falls the relaxed replay tends to the hard one ("imu-coast", where the pose
    of a frame blends the logged pose and the prediction). At 0.01 inliers every |score - threshold| / T
    >= 50: each sigmoid is within e^-50 of its limit, and flags, modes, segments and poses are the hard
    ones to rounding (flags 1e-12; positions 1e-9 m: errors of 1e-22 in a flag, times metre-scale
    differences between logged and predicted states, amplified by at most 5 s of prediction). The
    relaxed estimate flag leaves out a reset's erasure of earlier frames (docs/state-machine.md): it is
    compared with the hard one before erasure."""
    batch = random_batch(12, 40, 300, dtype=jnp.float64)
    rule = InlierRule(Thresholds(**OFF_TIE))
    hard = replay_jit(batch, rule, switch_model="imu-coast")
    valid = np.asarray(batch.valid)
    flags = {k: np.asarray(getattr(hard, k)) for k in ("accepted", "coasting", "out_of_support")}
    flags["has_estimate"] = (flags["accepted"] & np.asarray(batch.has_pose)) | flags["coasting"]
    assert (flags["has_estimate"] & ~np.asarray(hard.has_estimate) & valid).any()  # some frames were erased
    est = flags["has_estimate"] & valid
    flag_err, pos_err = [], []
    for temperature in (1.0, 0.1, 0.05, 0.03, 0.02, 0.01):
        soft = replay_jit(batch, rule, switch_model="imu-coast", logic=SoftLogic(jnp.asarray(temperature)))
        flag_err.append(
            max(np.abs(np.asarray(getattr(soft, k))[valid] - v[valid]).max() for k, v in flags.items())
        )
        pos_err.append(np.abs(np.asarray(soft.position)[est] - np.asarray(hard.position)[est]).max())
    assert flag_err[0] > 0.5 and pos_err[0] > 1.0, (flag_err, pos_err)
    assert all(b <= a + 1e-12 for a, b in zip(flag_err, flag_err[1:], strict=False)), flag_err
    assert all(b <= a + 1e-12 for a, b in zip(pos_err, pos_err[1:], strict=False)), pos_err
    assert flag_err[-1] < 1e-12 and pos_err[-1] < 1e-9, (flag_err, pos_err)
    assert np.array_equal(np.asarray(soft.mode), np.asarray(hard.mode))
    np.testing.assert_allclose(
        np.asarray(soft.segment)[valid], np.asarray(hard.segment)[valid], rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(soft.lost_any, float), np.asarray(hard.lost_any, float), rtol=0, atol=1e-12
    )


def _frame(t, k, **flags) -> FrameData:
    """One frame's FrameData (float64 scalars): IMU initialised and BA2 done, posed, no recorded start."""
    values = dict(t=t, k=k, imu_init=1.0, imu_ba2=1.0, has_pose=1.0, init_keys=0.0, init_matches=0.0,
                  rec_start=0.0, rec_loss=0.0, rec_start_t=0.0, rec_reloc=-1.0) | flags  # fmt: skip
    return FrameData(**{key: jnp.asarray(value, jnp.float64) for key, value in values.items()})


def _run(**constants) -> RunConstants:
    values = dict(fps=20.0, imu_init_delay=0.0, ba2_delay=0.0, stereo=0.0) | constants
    return RunConstants(**{key: jnp.asarray(value, jnp.float64) for key, value in values.items()})


def _state(ok=1.0, recently_lost=0.0, lost=0.0, **clocks) -> MachineState:
    """A machine state in the log's first map (started at t = 0, frame 0)."""
    values = dict(ok=ok, recently_lost=recently_lost, lost=lost, lost_ready=0.0, t_lost=0.0, map_start_t=0.0,
                  reloc_k=0.0, lost_reloc_k=0.0, segment=0.0) | clocks  # fmt: skip
    return MachineState(**{key: jnp.asarray(value, jnp.float64) for key, value in values.items()})


def test_relaxed_timer_belongs_to_the_recently_lost_mass(x64):
    """After 10 s of tracking, a frame that fails with probability 0.3 leaves 30 % of the mass in
    RECENTLY_LOST with its timer started at 10 s; a good next frame must recover that mass (5 s
    have not passed). Blending t_lost with the OK mass's stale timer (0.3 * 10 + 0.7 * 0 = 3 s)
    would make the mass 'expire' (10.05 - 3 > 5) and go LOST: the relaxed replay would lose
    tracking early. machine_step carries the RECENTLY_LOST mass's own (mass-weighted) timer."""
    th = Thresholds(**ORB)
    logic = SoftLogic(jnp.asarray(1.0))
    p_fail = 0.3
    score = 15.0 + math.log((1 - p_fail) / p_fail)  # sigmoid((15 - score) / 1) = 0.3
    state, decision = machine_step(logic, _state(), score, _frame(10.0, 200.0), _run(), th)
    np.testing.assert_allclose(float(state.recently_lost), p_fail, rtol=1e-12)
    np.testing.assert_allclose(float(decision.coasting), p_fail, rtol=1e-12)
    np.testing.assert_allclose(float(state.t_lost), 10.0, rtol=1e-15)
    state, _ = machine_step(logic, state, 100.0, _frame(10.05, 201.0), _run(), th)
    assert float(state.lost) < 1e-6, float(state.lost)
    np.testing.assert_allclose(float(state.ok), 1.0, atol=1e-6)


def test_relaxed_map_start_belongs_to_the_new_map_mass(x64):
    """Frame 200 (t = 10 s): 40 % of the mass is LOST and starts a new map there (the data allow it);
    the 60 % in OK, in the log's first map before BA2, fails (0 inliers) and resets. All the mass that
    tracks after the frame is in the new map, so its map start is 10 s. On the next frame that map is
    too young for the IMU (imu_init_delay 2 s): 30 inliers must fail (< not_init). Blending the map
    start with the mass that reset (0.4 * 10 + 0.6 * 0 = 4 s) would make the map look 6 s old, the IMU
    usable, and 30 inliers pass (ok = 0.4 instead of ~0). The reloc threshold is 0 so that no window
    decides the frame."""
    th = Thresholds(**dict(ORB, reloc=0.0))
    logic = SoftLogic(jnp.asarray(0.5))
    run = _run(imu_init_delay=2.0, ba2_delay=2.0)
    state = _state(ok=0.6, lost=0.4, lost_ready=0.4)  # the LOST mass holds a reference frame
    frame = _frame(10.0, 200.0, imu_ba2=0.0, init_keys=1.0, init_matches=1.0)
    state, decision = machine_step(logic, state, 0.0, frame, run, th)
    np.testing.assert_allclose(float(decision.new_map), 0.4, rtol=1e-12)
    np.testing.assert_allclose(float(decision.reset), 0.6, rtol=1e-9)
    np.testing.assert_allclose(float(state.map_start_t), 10.0, rtol=1e-9)
    state, _ = machine_step(logic, state, 30.0, _frame(10.05, 201.0), run, th)
    assert float(state.ok) < 1e-6, float(state.ok)


def test_relaxed_relocalisation_window_belongs_to_the_mass_that_reset(x64):
    """Frame 20 (t = 1 s, just after the log's first window), BA2 not done: the frame fails with
    probability 0.1, and that mass resets (its window restarts at 20). The 90 % that did not reset has
    its window behind it: 40 inliers (>= imu_init, < reloc) on frame 21 must pass for it (ok ~0.9)."""
    th = Thresholds(**ORB)
    logic = SoftLogic(jnp.asarray(1.0))
    score = 15.0 + math.log(9.0)  # sigmoid((15 - score) / 1) = 0.1
    state, decision = machine_step(logic, _state(), score, _frame(1.0, 20.0, imu_ba2=0.0), _run(), th)
    np.testing.assert_allclose(float(decision.reset), 0.1, rtol=1e-12)
    state, _ = machine_step(logic, state, 40.0, _frame(1.05, 21.0, imu_ba2=0.0), _run(), th)
    np.testing.assert_allclose(float(state.ok), 0.9, atol=1e-6)


@pytest.mark.parametrize(
    "switch_model",
    ["orbslam3", "imu-coast"],
)
def test_relaxed_gradient_is_finite_with_a_vanishing_mass(x64, switch_model):
    """IMU never initialised, 0 inliers after the map's first frame: every frame fails, and the relaxed
    tracked mass falls by ~1e-11 a frame (sigmoid(-49.5 / 2)) to ~1e-215 after ten frames. The first
    frame's position is the logged one whatever the thresholds: its gradient is 0, finite."""
    batch = log_batch([100] + [0] * 10, imu_init=False, dtype=jnp.float64)

    def first_position(rule):
        res = replay(batch, rule, switch_model=switch_model, logic=SoftLogic(jnp.asarray(2.0)))
        return res.position[0, 0, 0]

    grads = jax.grad(first_position)(InlierRule(Thresholds(**OFF_TIE)))
    assert all(float(g) == 0.0 for g in jax.tree.leaves(grads)), grads


TEMPERATURE = {InlierRule: 2.0, SVERule: 0.02}  # in score units: inliers, SVE


def _soft_loss(rule, batch, features, direction, switch_model):
    """A smooth scalar of the relaxed replay: accepted share plus a projection of the positions, each
    weighted by its estimate mass as the objective weights them (jsve.core._objective)."""
    logic = SoftLogic(jnp.asarray(TEMPERATURE[type(rule)]))
    res = replay(batch, rule, features, switch_model=switch_model, logic=logic)
    valid = batch.valid.astype(batch.t.dtype)
    positions = jnp.sum(res.position * direction * (valid * res.has_estimate)[..., None])
    return (jnp.sum(res.accepted) + positions) / jnp.sum(valid)


@pytest.mark.parametrize(
    "kind, switch_model",
    [
        ("inliers", "orbslam3"),
        ("inliers", "imu-coast"),  # tracked masses of ~1e-200 in long failing stretches
        ("sve", "imu-coast"),
    ],
)
def test_relaxed_replay_gradient_matches_finite_difference(x64, kind, switch_model):
    """d loss / d theta of the relaxed replay (thresholds; for SVE also the combination's w_a, u_b,
    p, q and rho) equals a central difference with h = 1e-5: truncation ~h^2 times third derivatives
    of sigmoids (at temperature 0.02 for SVE, ~1e-6 relative); for p at 0 the power mean switches to
    its p -> 0 expansion inside |p| < 1e-6 and the float64 power formula just outside it carries
    ~eps / p relative error, ~5e-6 relative in this difference. Tolerance 2e-5 relative + 1e-9
    absolute: a missing or wrong term of a gradient is O(1) relative. Under "orbslam3" only the
    accepted share depends on the rule (the poses are the logged ones); under "imu-coast" the positions
    do too. Finite everywhere, frames without features included (the SVE logs have N_extracted = 0)."""
    batch = random_batch(13, 6, 200, min_frames=150, kind=kind, dtype=jnp.float64)
    features = batch_features(batch)
    if kind == "sve":
        assert int(jnp.min(batch.n_extracted)) == 0
    direction = jnp.asarray(np.random.default_rng(0).normal(size=(1, 1, 3)))
    rule = InlierRule(Thresholds(**OFF_TIE)) if kind == "inliers" else preset("sve-option2")
    loss = eqx.filter_jit(lambda r: _soft_loss(r, batch, features, direction, switch_model))
    grads = eqx.filter_jit(
        eqx.filter_grad(lambda r: _soft_loss(r, batch, features, direction, switch_model))
    )(rule)
    leaves, treedef = jax.tree.flatten(rule)
    g_leaves = jax.tree.leaves(grads)
    assert len(g_leaves) == len(leaves) == (4 if kind == "inliers" else 9)
    h = 1e-5
    for j, g in enumerate(g_leaves):
        up = jax.tree.unflatten(treedef, [x + h if m == j else x for m, x in enumerate(leaves)])
        down = jax.tree.unflatten(treedef, [x - h if m == j else x for m, x in enumerate(leaves)])
        fd = (loss(up) - loss(down)) / (2 * h)
        assert np.isfinite(float(g)), j
        np.testing.assert_allclose(float(g), float(fd), rtol=2e-5, atol=1e-9, err_msg=f"leaf {j}")
    # Not vacuous: the parameters do move the loss.
    assert max(abs(float(g)) for g in g_leaves) > 1e-3
