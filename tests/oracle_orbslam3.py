"""Test oracle: ORB-SLAM3 v1.0's tracking-state machine replayed over a log, as a plain Python loop.

Written afresh from the control flow of `src/Tracking.cc` of UZ-SLAMLab/ORB_SLAM3 @4452a3c (v1.0),
not from jsve's code; it imports nothing from jsve. Explicit if/else on integer modes, Python floats,
numpy float64 only for the pose algebra (its own quaternion code, wxyz). Where the log cannot say
what ORB-SLAM3 would do it follows docs/state-machine.md ("The replayed machine, frame by frame",
"Map initialisation", "The recorded run's own map changes", "Support").

Tracking.cc locations followed (line numbers of v1.0):
    l.48          constructor: mnLastRelocFrameId(0), time_recently_lost(5.0).
    l.585, l.1158 mMaxFrames = fps, an int (Tracking.h l.302; Settings.cc l.410 reads Camera.fps as int).
    Track(), l.1794-2330:
      l.1899-1919   NOT_INITIALIZED: StereoInitialization / MonocularInitialization; the frame has
                    no pose unless the map initialised on it (then mState = OK, no TrackLocalMap).
      l.1939-1976   OK: TrackWithMotionModel / TrackReferenceKeyFrame (not logged; the log's
                    inliers stand for them, docs/state-machine.md "What the log cannot tell").
      l.1981-1998   RECENTLY_LOST with an IMU: bOK = true; PredictStateIMU if the map's IMU is
                    initialised, else bOK = false (l.1986-1991); then t - mTimeStampLost >
                    time_recently_lost -> LOST, bOK = false (l.1993-1998): expiry wins.
      l.2017-2031   LOST: ResetActiveMap or CreateMapInAtlas, return (no pose on that frame).
      l.2123-2129   bOK -> TrackLocalMap (the success test).
      l.2142-2163   bOK -> OK. Else from OK with an IMU: ResetActiveMap when the IMU is not
                    initialised or BA2 not done (l.2149-2153); mState = RECENTLY_LOST and
                    mTimeStampLost = t (l.2155, l.2162). From RECENTLY_LOST the timer is not touched.
      l.2272-2288   LOST after tracking: ResetActiveMap / CreateMapInAtlas, return.
      l.2300-2320   OK and RECENTLY_LOST frames are stored in the trajectory (the estimate).
    TrackLocalMap(), l.2949-3064, the success test l.3030-3063: relocalisation window first
      (l.3030), then the recovery clause in RECENTLY_LOST (l.3033), then IMU_MONOCULAR (l.3037-3044,
      threshold by Atlas::isImuInitialized) or IMU_STEREO / IMU_RGBD (l.3047-3053, one threshold).
    StereoInitialization(), l.2335: a map needs more than 500 features (l.2337).
    MonocularInitialization(), l.2448: without a reference (mbReadyToInitializate false) a frame with
      > 100 keypoints becomes it (l.2451-2476); with one, a frame with <= 100 keypoints drops it
      (l.2483-2488), as do < 100 matches (l.2495-2499); else ReconstructWithTwoViews decides (l.2504):
      success makes the map. A dropping frame is no reference. mnLastRelocFrameId untouched (l.2630).
      CreateMapInAtlas (l.2680) and ResetActiveMap (l.3879) clear mbReadyToInitializate.
    CreateMapInAtlas(), l.2662: a new map, mnLastRelocFrameId untouched (l.2675 is commented out).
    ResetActiveMap(), l.3840-3925: every stored frame of the active map is marked lost
      (l.3898-3912) and mnLastRelocFrameId = the current frame (l.3915).

Modelling choices of docs/state-machine.md (and the precisions the JAX machine shares):
    - The replay starts in LOST; a recorded map start (a posed frame after a pose-less one, or a
      map_id change) starts a replay map whatever the mode: OK, estimate, no success test on it.
      A later one counts as a loss; one that continues the map_id of the last posed frame (a
      recorded reset) restarts the relocalisation window at that last posed frame.
    - IMU initialised / BA2 done for the replay's map: the logged flag, and the replay's map began
      no later than the current recorded map or is at least imu_init_delay / ba2_delay old.
    - A natural map initialisation from LOST: (stereo) a frame after the loss frame with
      n_extracted > 500 and a logged pose; (monocular) MonocularInitialization above, with the
      recorded inliers standing for the matches and a logged pose for ReconstructWithTwoViews'
      success; without a pose the reference is dropped (ORB-SLAM3 keeps it for up to 1 s when only
      the reconstruction fails; the next posed frame is a recorded map start either way). The loss
      frame itself returns early: the next frame is the first that can be a reference, so a
      monocular map starts two frames after the loss at the earliest.
    - A reset takes the estimate from this frame and every earlier frame of the replay's map, on the
      failing frame (System::ResetActiveMap only raises a flag that the next frame's Track* call acts
      on, System.cc l.509-512 and l.304-307; the replay puts the reset and mnLastRelocFrameId on the
      failing frame k, and the new map at k + 2 at the earliest).
    - A frame whose estimate is the logged pose but has none is without estimate, out of support
      (decided on the frame: a later reset's erasure leaves the flag).
    - The pose state that `imu-coast` predicts from is the previous frame's: its estimate, or, on a
      frame without one, the IMU prediction carried forward (ReplayResult's documented contents).
    - The trajectory the run is scored on is what System::SaveTrajectoryEuRoC (System.cc l.662-777)
      writes: frames stored in the trajectory (l.2300-2320) and not marked lost, whose reference
      keyframe ends in the map with the most keyframes. The log says which recorded frames that is
      (`in_saved`); a map the replay initialises itself after a loss the recorded run did not have
      has no keyframes in the log, so its frames are not in the trajectory (docs/state-machine.md,
      "Scoring a run").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

OK, RECENTLY_LOST, LOST = 0, 1, 2
"""Replayed modes after a frame (ORB-SLAM3's eTrackingState OK, RECENTLY_LOST, and LOST for
"no map": LOST / NOT_INITIALIZED / NO_IMAGES_YET are all waiting for a new map)."""

SWITCH_MODELS = ("orbslam3", "imu-coast")
TIME_RECENTLY_LOST_S = 5.0  # Tracking.cc l.48


# ------------------------------------------------------------------------------------------------
# Quaternion algebra (wxyz, Hamilton, body to world) and ORB-SLAM3's PredictStateIMU


def qmul(a, b):
    """Hamilton product a * b of wxyz quaternions (float64)."""
    aw, ax, ay, az = (float(x) for x in a)
    bw, bx, by, bz = (float(x) for x in b)
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])  # fmt: skip


def qconj(q):
    """The conjugate (the inverse rotation of a unit quaternion)."""
    q = np.asarray(q, float)
    return np.array([q[0], -q[1], -q[2], -q[3]])


def qrotate(q, v):
    """Rotate the 3-vector v by the unit quaternion q: the vector part of q (0, v) q*."""
    return qmul(qmul(q, np.concatenate([[0.0], np.asarray(v, float)])), qconj(q))[1:]


def imu_predict(p, v, q, dt, dp, dv, dq, g):
    """Tracking::PredictStateIMU (l.1738) from the previous frame (docs/state-machine.md, switch models):
    R2 = R1 dR, v2 = v1 + g dt + R1 dV, p2 = p1 + v1 dt + g dt^2 / 2 + R1 dP.

    Arguments: previous position (m), velocity (m/s), orientation (wxyz, body to world), dt (s),
    preintegrated dp (m), dv (m/s), dq (wxyz) in the previous body frame, gravity g (m/s^2, world).
    Returns (p2, v2, q2) as float64 arrays.
    """
    p, v, dp, dv, g = (np.asarray(x, float) for x in (p, v, dp, dv, g))
    dt = float(dt)
    p2 = p + v * dt + 0.5 * g * dt * dt + qrotate(q, dp)
    v2 = v + g * dt + qrotate(q, dv)
    return p2, v2, qmul(q, dq)


def dead_reckon(p0, v0, q0, imu_dt, imu_dp, imu_dv, imu_dq, gravity):
    """Frame 0's state, then imu_predict with each later frame's preintegration. Returns (P, V, Q)."""
    n = len(imu_dt)
    P, V, Q = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 4))
    P[0], V[0], Q[0] = p0, v0, q0
    for k in range(1, n):
        P[k], V[k], Q[k] = imu_predict(P[k - 1], V[k - 1], Q[k - 1], imu_dt[k], imu_dp[k], imu_dv[k],
                                       imu_dq[k], gravity)  # fmt: skip
    return P, V, Q


# ------------------------------------------------------------------------------------------------
# The success test and the replay


def _threshold(thresholds, name: str) -> float:
    if isinstance(thresholds, Mapping):
        return float(thresholds[name])
    return float(getattr(thresholds, name))


def success(score, thresholds, *, recently_lost: bool, imu_initialised: bool, in_reloc: bool,
            stereo: bool) -> bool:  # fmt: skip
    """Tracking::TrackLocalMap's decision (l.3030-3063) with the rule's score for mnMatchesInliers.

    `thresholds`: a mapping or an object with imu_init, not_init, reloc, recovery.
    """
    s = float(score)
    if in_reloc and s < _threshold(thresholds, "reloc"):  # l.3030
        return False
    if recently_lost and s > _threshold(thresholds, "recovery"):  # l.3033
        return True
    if stereo:  # IMU_STEREO / IMU_RGBD, l.3047-3053: the IMU state does not enter
        return not s < _threshold(thresholds, "imu_init")
    if imu_initialised:  # IMU_MONOCULAR, l.3037-3044
        return not s < _threshold(thresholds, "imu_init")
    return not s < _threshold(thresholds, "not_init")


@dataclass
class OracleResult:
    """The replay of one run (frames axis first).

    mode: int8 OK / RECENTLY_LOST / LOST after each frame. has_estimate: bool. segment: int32, the
    replay's map index (-1 before the first map; LOST frames keep the last map's index).
    position, quaternion, velocity: float64, NaN where has_estimate is False. out_of_support: the
    estimate would be the logged pose and the log has none. lost_any: the run entered LOST (a
    reset, an expiry, or a recorded map start after the replay's first map). own_map: the frame is in
    a map the replay initialised itself. in_trajectory: has_estimate, in_saved, not own_map.
    events: (frame, name) in order; names "recorded_start", "recorded_reset", "natural_init",
    "reset", "erase" (once per reset that erased earlier frames), "expiry", "ok_to_rl", "recovery",
    "rl_no_imu", "out_of_support", "predicted".
    """

    mode: np.ndarray
    has_estimate: np.ndarray
    segment: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    velocity: np.ndarray
    out_of_support: np.ndarray
    lost_any: bool
    events: list
    own_map: np.ndarray
    in_trajectory: np.ndarray

    def count(self, name: str) -> int:
        return sum(1 for _, e in self.events if e == name)


def replay_run(
    *,
    score,
    t,
    n_extracted,
    n_inliers,
    has_pose,
    map_id,
    imu_init,
    imu_ba2,
    vis_p,
    vis_q,
    vis_v,
    imu_dt,
    imu_dp,
    imu_dv,
    imu_dq,
    fps,
    gravity,
    imu_init_delay,
    ba2_delay,
    stereo,
    thresholds,
    switch_model: str = "orbslam3",
    time_recently_lost: float = TIME_RECENTLY_LOST_S,
    in_saved=None,
) -> OracleResult:
    """Replay one run of n frames (arrays [n, ...], no padding) frame by frame.

    Arguments:
        score: the rule's score per frame. t: s since the first frame. n_extracted, n_inliers: counts.
        has_pose, map_id, imu_init, imu_ba2: the recorded run's pose flag, Atlas map id and inertial stage.
        vis_p, vis_q, vis_v: the recorded pose (m, wxyz, m/s; world). imu_dt, imu_dp, imu_dv, imu_dq:
            preintegration from the previous frame in the previous body frame (s, m, m/s, wxyz).
        fps: frames per second (the window is floor(fps) frames). gravity: (3,) m/s^2, world.
        imu_init_delay, ba2_delay: s from the first posed frame to the first imu_init / imu_ba2 frame
            (inf if never). stereo: IMU_STEREO / IMU_RGBD rather than IMU_MONOCULAR.
        thresholds: imu_init, not_init, reloc, recovery (mapping or attributes).
        switch_model: "orbslam3" or "imu-coast". time_recently_lost: s (ORB-SLAM3: 5).
        in_saved: the recorded frames whose pose the saved trajectory holds (default: every posed frame).
    """
    if switch_model not in SWITCH_MODELS:
        raise ValueError(f"switch_model must be one of {SWITCH_MODELS}, got {switch_model!r}")
    n = len(t)
    t = [float(x) for x in t]
    score = [float(x) for x in score]
    n_ext = [int(x) for x in n_extracted]
    n_inl = [int(x) for x in n_inliers]
    has_pose = [bool(x) for x in has_pose]
    map_id = [int(x) for x in map_id]
    imu_flag = [bool(x) for x in imu_init]
    ba2_flag = [bool(x) for x in imu_ba2]
    vis_p, vis_q, vis_v = (np.asarray(x, float) for x in (vis_p, vis_q, vis_v))
    imu_dt = [float(x) for x in imu_dt]
    imu_dp, imu_dv, imu_dq = (np.asarray(x, float) for x in (imu_dp, imu_dv, imu_dq))
    g = np.asarray(gravity, float)
    max_frames = int(math.floor(float(fps)))  # mMaxFrames, an int (l.585)
    stereo = bool(stereo)
    imu_init_delay, ba2_delay = float(imu_init_delay), float(ba2_delay)

    in_saved = list(has_pose) if in_saved is None else [bool(x) for x in in_saved]
    own = False  # the replay's current map is one it initialised itself
    own_out = np.zeros(n, bool)
    mode_out = np.full(n, LOST, np.int8)
    has_est = np.zeros(n, bool)
    segment_out = np.full(n, -1, np.int32)
    oos = np.zeros(n, bool)
    P, V, Q = np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full((n, 4), np.nan)
    events: list[tuple[int, str]] = []

    mode = LOST  # no map before the first posed frame
    segment = -1
    lost_any = False
    reloc_frame = 0  # mnLastRelocFrameId, l.48
    t_lost = math.nan  # mTimeStampLost
    ready = False  # mbReadyToInitializate
    map_start_k, map_start_t = None, math.nan  # the replay's current map
    rec_start_t = math.nan  # start of the current recorded map
    last_posed = None  # index of the last frame with a recorded pose
    state = None  # (p, v, q) the replay holds after the previous frame

    def imu_ready(flags, delay, k):
        # docs/state-machine.md: the logged flag, and the replay's map is as old as the recorded run
        # needed (or began with the recorded map)
        return flags[k] and (map_start_t <= rec_start_t or t[k] - map_start_t >= delay)

    for k in range(n):
        # What the frame gets: "logged" (the recorded pose), "predicted" (imu-coast), or None.
        estimate = None
        recorded_start = has_pose[k] and (k == 0 or not has_pose[k - 1] or map_id[k] != map_id[k - 1])

        if recorded_start:
            # The recorded run reset or made a new map: the replay starts its map here whatever its
            # mode, and the frame is the map's initialisation frame (no TrackLocalMap, l.1899-1919).
            events.append((k, "recorded_start"))
            if last_posed is not None and map_id[last_posed] == map_id[k]:
                # ResetActiveMap keeps the map id and sets mnLastRelocFrameId (l.3915)
                reloc_frame = last_posed
                events.append((k, "recorded_reset"))
            if segment >= 0:
                lost_any = True
            rec_start_t = t[k]
            ready = False
            own = False
            segment += 1
            map_start_k, map_start_t = k, t[k]
            mode = OK
            estimate = "logged"

        elif mode == OK:
            imu_ok = imu_ready(imu_flag, imu_init_delay, k)
            ba2_ok = imu_ready(ba2_flag, ba2_delay, k)
            in_reloc = k < reloc_frame + max_frames  # l.3030
            if success(score[k], thresholds, recently_lost=False, imu_initialised=imu_ok, in_reloc=in_reloc,
                       stereo=stereo):  # fmt: skip
                estimate = "logged"  # l.2142-2143
            elif imu_ok and ba2_ok:
                # l.2155-2162: RECENTLY_LOST, the timer starts; the frame keeps a pose (l.2300-2320)
                mode = RECENTLY_LOST
                t_lost = t[k]
                estimate = "logged" if switch_model == "orbslam3" else "predicted"
                events.append((k, "ok_to_rl"))
            else:
                # l.2149-2153: ResetActiveMap; every frame of the active map is marked lost
                # (l.3898-3912) and mnLastRelocFrameId = this frame (l.3915)
                mode = LOST
                lost_any = True
                reloc_frame = k
                ready = False  # l.3879
                if has_est[map_start_k:k].any():
                    events.append((k, "erase"))
                has_est[map_start_k:k] = False
                events.append((k, "reset"))

        elif mode == RECENTLY_LOST:
            imu_ok = imu_ready(imu_flag, imu_init_delay, k)
            if t[k] - t_lost > time_recently_lost:
                # l.1993-1998, then l.2272-2288: LOST, the map is kept (CreateMapInAtlas)
                mode = LOST
                lost_any = True
                ready = False  # l.2680
                events.append((k, "expiry"))
            elif not imu_ok:
                # l.1988-1991: no PredictStateIMU, bOK = false, no TrackLocalMap; mState stays
                events.append((k, "rl_no_imu"))
            else:
                in_reloc = k < reloc_frame + max_frames
                passes = success(score[k], thresholds, recently_lost=True, imu_initialised=imu_ok,
                                 in_reloc=in_reloc, stereo=stereo)  # fmt: skip
                if passes:
                    mode = OK  # l.2142-2143
                    estimate = "logged"
                    events.append((k, "recovery"))
                else:
                    # stays RECENTLY_LOST; mTimeStampLost is set only from OK (l.2144-2162)
                    estimate = "logged" if switch_model == "orbslam3" else "predicted"

        else:  # LOST
            # StereoInitialization / MonocularInitialization; the loss frame returned early
            # (l.2017-2031, l.2271-2288), so this is a later frame
            initialises = False
            if stereo:
                initialises = n_ext[k] > 500 and has_pose[k]  # l.2337
            elif not ready:
                if n_ext[k] > 100:  # l.2454: this frame becomes the reference
                    ready = True
                    events.append((k, "reference"))
            elif n_ext[k] > 100 and n_inl[k] >= 100 and has_pose[k]:
                initialises = True  # l.2483, l.2495, l.2504 (the recorded pose: the reconstruction)
            else:
                ready = False  # l.2483-2499: the reference is dropped; this frame is no reference
                events.append((k, "reference_dropped"))
            if initialises:
                ready = False
                own = True
                segment += 1
                map_start_k, map_start_t = k, t[k]
                mode = OK
                estimate = "logged"
                events.append((k, "natural_init"))

        # The frame's estimate, and the state the next frame predicts from.
        prediction = None  # only imu-coast ever uses the carried state
        if switch_model == "imu-coast" and state is not None and k > 0:
            prediction = imu_predict(*state, imu_dt[k], imu_dp[k], imu_dv[k], imu_dq[k], g)
        if estimate == "logged":
            if has_pose[k]:
                has_est[k] = True
                state = (vis_p[k].copy(), vis_v[k].copy(), vis_q[k].copy())
            else:
                oos[k] = True
                events.append((k, "out_of_support"))
                state = prediction
        elif estimate == "predicted":
            if prediction is None:
                raise RuntimeError(f"frame {k}: an IMU prediction without a previous state")
            has_est[k] = True
            state = prediction
            events.append((k, "predicted"))
        else:
            state = prediction
        if has_est[k]:
            P[k], V[k], Q[k] = state[0], state[1], state[2]
        mode_out[k] = mode
        own_out[k] = own
        segment_out[k] = segment
        if has_pose[k]:
            last_posed = k

    P[~has_est], V[~has_est], Q[~has_est] = np.nan, np.nan, np.nan  # frames a reset erased
    in_trajectory = has_est & np.asarray(in_saved, bool) & ~own_out
    return OracleResult(mode=mode_out, has_estimate=has_est, segment=segment_out, position=P, quaternion=Q,
                        velocity=V, out_of_support=oos, lost_any=lost_any, events=events, own_map=own_out,
                        in_trajectory=in_trajectory)  # fmt: skip


# ------------------------------------------------------------------------------------------------
# Not the state machine: random rotations for the tests' logs, and the numpy S_b of tests/test_rules.py


def random_unit_quaternions(rng, shape, scale=None):
    """Uniform random rotations, or small ones (angle ~ scale rad) when scale is given."""
    if scale is None:
        q = rng.normal(size=shape + (4,))
    else:
        q = np.concatenate([np.ones(shape + (1,)), rng.normal(scale=scale / 2, size=shape + (3,))], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def s_b_numpy(bins, n_extracted):
    """Reference S_b (clamped): 1 - chi2 / (7 N), chi2 = sum (n_i - N/64)^2 / (N/64); 0 when N = 0."""
    bins = np.asarray(bins, float)
    n = np.asarray(n_extracted, float)
    e = n[..., None] / 64.0
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = np.sum((bins - e) ** 2 / e, axis=-1)
        value = 1.0 - chi2 / (7.0 * n)
    return np.where(n > 0, np.clip(value, 0.0, 1.0), 0.0)
