"""ORB-SLAM3 v1.0's tracking state machine (IMU sensors), written once, hard and relaxed.

`machine_step` advances the OK / RECENTLY_LOST / LOST machine by one frame. It is written in
arithmetic over {0, 1} flags so that the same code runs hard (exact comparisons; the replay) and
relaxed (sigmoid comparisons with a temperature; the differentiable replay used for fitting): only
the `Logic` differs. See docs/state-machine.md for the ORB-SLAM3 source locations and the model's limits.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jsve.core._rules import Thresholds

MODE_OK, MODE_RECENTLY_LOST, MODE_LOST = 0, 1, 2
"""Replay modes (not ORB-SLAM3's enum values, which the log's `state` column uses)."""

TIME_RECENTLY_LOST_S = 5.0
"""ORB-SLAM3 v1.0 Tracking::time_recently_lost: seconds in RECENTLY_LOST before LOST."""


class HardLogic(eqx.Module):
    """Exact comparisons returning {0, 1} in the score's float dtype: the real state machine."""

    def less(self, x, threshold):
        return (x < threshold).astype(jnp.result_type(x, float))

    def greater(self, x, threshold):
        return (x > threshold).astype(jnp.result_type(x, float))

    def normalize_quat(self, q):
        return q  # blends of exact {0, 1} flags select one quaternion: already unit


class SoftLogic(eqx.Module):
    """Sigmoid comparisons with a temperature in score units; tends to HardLogic as it falls to 0."""

    temperature: Float[Array, ""]

    def less(self, x, threshold):
        return jax.nn.sigmoid((threshold - x) / self.temperature)

    def greater(self, x, threshold):
        return jax.nn.sigmoid((x - threshold) / self.temperature)

    def normalize_quat(self, q):
        return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


SWITCH_MODELS = ("orbslam3", "imu-coast")
"""What a frame in RECENTLY_LOST is posed with (docs/state-machine.md): "orbslam3", the logged pose
(ORB-SLAM3 v1.0 optimises every tracked frame before its success test); "imu-coast", PredictStateIMU
from the previous replayed state (a front-end that drops the visual update of a failed frame)."""


def check_switch_model(switch_model: str) -> str:
    """`switch_model` if it is one of SWITCH_MODELS, else a ValueError naming the choices."""
    if switch_model not in SWITCH_MODELS:
        raise ValueError(f"switch model must be one of {', '.join(SWITCH_MODELS)}; got {switch_model!r}")
    return switch_model


MONO_INIT_MIN_KEYPOINTS = 100
"""MonocularInitialization: both frames need more than 100 keypoints (Tracking.cc l.2454, l.2483)."""
MONO_INIT_MIN_MATCHES = 100
"""MonocularInitialization: at least 100 matches between them (l.2495); the recorded inliers stand in."""
STEREO_INIT_MIN_KEYPOINTS = 500
"""StereoInitialization: more than 500 keypoints (l.2337)."""


class FrameData(eqx.Module):
    """What the log says about each frame, as the machine reads it (exact flags in the float dtype;
    leading axes any shape, e.g. [F, R] frames-major in a scan, or one frame's [R]).

    Attributes:
        t: s since the log's first frame. k: frame index (float).
        imu_init, imu_ba2: the recorded map's inertial stage (Atlas::isImuInitialized, GetIniertialBA2).
        has_pose: the recorded run posed the frame (its logged pose exists).
        init_keys: the frame has the keypoints of an initialisation frame (monocular: > 100, a reference
            or a second frame; stereo: > 500).
        init_matches: the frame has the matches to a monocular reference (the recorded inliers stand in:
            >= 100); 1 for stereo, which needs no reference.
        rec_start: the recorded run starts a map here (a new map_id, or a pose after frames without one).
        rec_loss: rec_start, and not the log's first map: the recorded run lost its map.
        rec_start_t: s, start time of the recorded map the frame belongs to.
        rec_reloc: frame index at which ORB-SLAM3 restarted its relocalisation window for this recorded
            start (the recorded run's reset: its last posed frame), or -1.
    """

    t: Array
    k: Array
    imu_init: Array
    imu_ba2: Array
    has_pose: Array
    init_keys: Array
    init_matches: Array
    rec_start: Array
    rec_loss: Array
    rec_start_t: Array
    rec_reloc: Array


class RunConstants(eqx.Module):
    """Per-run constants of the machine (leaves shaped like one frame's batch shape).

    Attributes:
        fps: frames/s; the relocalisation window is floor(fps) frames (mMaxFrames, an int).
        imu_init_delay, ba2_delay: s the recorded run needed from its first map to IMU initialisation
            and to inertial BA2; a map the replay starts later than the recorded one waits as long again.
        stereo: 1 for IMU_STEREO / IMU_RGBD (their main test ignores the IMU state), else 0.
    """

    fps: Array
    imu_init_delay: Array
    ba2_delay: Array
    stereo: Array


class MachineState(eqx.Module):
    """Carry of the state machine. Modes are {0, 1} flags (probabilities when relaxed).

    Attributes:
        ok, recently_lost, lost: mode flags, exactly one is 1 in the hard machine. LOST means no map:
            waiting for one to initialise (also before the log's first map).
        lost_ready: the part of `lost` that holds a monocular reference frame
            (mbReadyToInitializate): the next frame may initialise a map.
        t_lost: s, time of the frame that entered RECENTLY_LOST (the timer is never restarted there).
            Relaxed, each clock is the mass-weighted mean over the mass that owns it (`_mass_mean`).
        map_start_t: s, time of the first frame of the replay's current map.
        reloc_k: mnLastRelocFrameId of the tracking (OK + RECENTLY_LOST) mass: frame index the
            relocalisation window counts from.
        lost_reloc_k: mnLastRelocFrameId of the LOST mass (a reset restarts it there, and the mass
            carries it into its next map). The hard machine has one mnLastRelocFrameId: the two clocks
            are equal there.
        segment: index of the replay's current map (-1 before the first).
    """

    ok: Float[Array, "*runs"]
    recently_lost: Float[Array, "*runs"]
    lost: Float[Array, "*runs"]
    lost_ready: Float[Array, "*runs"]
    t_lost: Float[Array, "*runs"]
    map_start_t: Float[Array, "*runs"]
    reloc_k: Float[Array, "*runs"]
    lost_reloc_k: Float[Array, "*runs"]
    segment: Float[Array, "*runs"]


def initial_state(dtype=float) -> MachineState:
    """No map yet (LOST), relocalisation window from frame 0 (mnLastRelocFrameId starts at 0): the
    first recorded map start begins map 0."""
    one, zero = jnp.ones((), dtype), jnp.zeros((), dtype)
    return MachineState(ok=zero, recently_lost=zero, lost=one, lost_ready=zero, t_lost=zero, map_start_t=zero,
                        reloc_k=zero, lost_reloc_k=zero, segment=-one)  # fmt: skip


class FrameDecision(eqx.Module):
    """What the machine decided for one frame (flags in {0, 1}, probabilities when relaxed).

    Attributes:
        tracked: OK after the frame, posed by tracking (the test passed, or a map started here).
        coasting: RECENTLY_LOST after the frame with an estimate (the logged pose under "orbslam3",
            the IMU prediction under "imu-coast").
        new_map: a map starts at this frame (the replay's own initialisation or a recorded start).
        loss: tracking was lost at this frame (a reset, an expiry or a recorded map loss).
        reset: the replay's map was reset here: its earlier frames lose their estimates.
    """

    tracked: Float[Array, "*runs"]
    coasting: Float[Array, "*runs"]
    new_map: Float[Array, "*runs"]
    loss: Float[Array, "*runs"]
    reset: Float[Array, "*runs"]


def tracking_succeeds(logic, score, th: Thresholds, recently_lost, imu_ok, in_reloc, stereo: ArrayLike = 0.0):
    """Tracking::TrackLocalMap's success test with the rule's thresholds (ORB-SLAM3 v1.0, l.3027-3064).

    In order: inside the relocalisation window a score below `reloc` fails; in RECENTLY_LOST a score
    above `recovery` succeeds; otherwise fail below `imu_init` (IMU initialised, or a stereo sensor
    whatever the IMU state) or below `not_init`.
    """
    fail_reloc = in_reloc * logic.less(score, th.reloc)
    recover = recently_lost * logic.greater(score, th.recovery)
    strict_imu = imu_ok + stereo - imu_ok * stereo
    pass_main = (strict_imu * (1 - logic.less(score, th.imu_init))
                 + (1 - strict_imu) * (1 - logic.less(score, th.not_init)))  # fmt: skip
    return (1 - fail_reloc) * (recover + (1 - recover) * pass_main)


def machine_step(
    logic,
    state: MachineState,
    score,
    frame: FrameData,
    run: RunConstants,
    th: Thresholds,
    time_recently_lost=TIME_RECENTLY_LOST_S,
) -> tuple[MachineState, FrameDecision]:
    """Advance ORB-SLAM3's state machine by one frame (the table of docs/state-machine.md).

    Arguments:
        score: the rule's score of this frame. frame: the log's facts about it. run: per-run constants.
        th: the rule's thresholds. time_recently_lost: s in RECENTLY_LOST before LOST (5 in v1.0).
    """
    dtype = jnp.result_type(frame.t, float)
    flag = lambda c: c.astype(dtype)  # noqa: E731 - data comparisons stay exact when relaxed
    # Exact flags put all of a mode's mass in one part, whose clock is the hard update: skip the
    # mass-weighted means (a third of the step's arithmetic in the search kernel's scan).
    clock = _hard_clock if isinstance(logic, HardLogic) else _mass_mean
    t, k = frame.t, frame.k
    # The replay's map is younger than the recorded one when it started later: it then waits the
    # recorded run's delays again before its IMU counts as initialised (and BA2 as done).
    young = flag(state.map_start_t > frame.rec_start_t)
    age = t - state.map_start_t
    imu_ok = frame.imu_init * (1 - young * flag(age < run.imu_init_delay))
    ba2_ok = frame.imu_ba2 * (1 - young * flag(age < run.ba2_delay))
    in_reloc = flag(k < state.reloc_k + jnp.floor(run.fps))
    expired = flag(t - state.t_lost > time_recently_lost)

    ok_pass = tracking_succeeds(logic, score, th, 0.0, imu_ok, in_reloc, run.stereo)
    ok_fail = state.ok * (1 - ok_pass)
    ok_to_rl = ok_fail * imu_ok * ba2_ok  # l.2142-2163: RECENTLY_LOST, timer set
    ok_reset = ok_fail * (1 - imu_ok * ba2_ok)  # l.2149-2153: ResetActiveMap before BA2
    # l.1993-1997, then CreateMapInAtlas (l.2286). The reset of l.2279-2284 (IMU not initialised)
    # cannot be reached: RECENTLY_LOST is entered only with the IMU initialised, which a map keeps.
    rl_expire = state.recently_lost * expired
    rl_live = state.recently_lost * (1 - expired)
    rl_blind = rl_live * (1 - imu_ok)  # l.1988-1991: no PredictStateIMU, no TrackLocalMap
    rl_pass = rl_live * imu_ok * tracking_succeeds(logic, score, th, 1.0, imu_ok, in_reloc, run.stereo)
    rl_stay = rl_live * imu_ok - rl_pass
    # Map initialisation from LOST (data facts only: exact). The frame that lost the map returned
    # early (l.2272-2288; a reset runs at the next frame's start, System.cc), so it never starts one.
    mono = 1 - run.stereo
    ready = state.lost_ready
    unready = state.lost - ready
    # Monocular (l.2448-2500): an unready mass takes this frame as its reference if it has the
    # keypoints; a ready one initialises a map if the frame has the keypoints and the matches (and a
    # recorded pose, standing for ReconstructWithTwoViews' success), and else drops its reference
    # without taking this frame as the next one. (ORB-SLAM3 keeps the reference when only the
    # reconstruction fails, for up to 1 s; in the log that is a frame without a pose, and the next
    # posed frame starts a recorded map anyway, so the difference cannot show.)
    becomes_ready = mono * unready * frame.init_keys
    attempt = frame.init_keys * frame.init_matches * frame.has_pose
    # Stereo (l.2335-2337): any frame after the loss with the keypoints (and a recorded pose).
    lost_init = mono * ready * attempt + run.stereo * state.lost * frame.init_keys * frame.has_pose

    tracked = state.ok * ok_pass + rl_pass + lost_init
    coasting = ok_to_rl + rl_stay
    reset = ok_reset
    loss = ok_reset + rl_expire
    still_tracking = tracked + coasting + rl_blind - lost_init  # OK or RECENTLY_LOST before and after
    lost_stay = state.lost - lost_init
    reloc_hard = reset * k + (1 - reset) * state.reloc_k
    natural = MachineState(
        ok=tracked,
        recently_lost=coasting + rl_blind,
        lost=loss + lost_stay,
        lost_ready=becomes_ready,
        t_lost=clock([(ok_to_rl, t), (rl_stay + rl_blind, state.t_lost)],
                          ok_to_rl * t + (1 - ok_to_rl) * state.t_lost),
        # The map start belongs to the OK + RECENTLY_LOST mass: the mass starting a map now, and the
        # rest of the tracking mass, which keeps its own.
        map_start_t=clock([(lost_init, t), (still_tracking, state.map_start_t)],
                               lost_init * t + (1 - lost_init) * state.map_start_t),
        # mnLastRelocFrameId: a reset restarts the window of the mass it sends to LOST, which takes its
        # window into its next map; an expiry keeps it.
        reloc_k=clock([(still_tracking, state.reloc_k), (lost_init, state.lost_reloc_k)], reloc_hard),
        lost_reloc_k=clock([(reset, k), (rl_expire, state.reloc_k), (lost_stay, state.lost_reloc_k)],
                                reloc_hard),
        segment=state.segment + lost_init,
    )  # fmt: skip
    # The recorded run starts a map here (exact): every replayed world ends its map and starts this one.
    rs = frame.rec_start
    tracking_before = state.ok + state.recently_lost
    windows = [(tracking_before, state.reloc_k), (state.lost, state.lost_reloc_k)]
    reloc_now = clock(windows, state.reloc_k)
    reloc = jnp.where(frame.rec_reloc >= 0, frame.rec_reloc, reloc_now) + 0 * tracked
    zero = jnp.zeros_like(tracked)
    forced = MachineState(ok=zero + 1, recently_lost=zero, lost=zero, lost_ready=zero, t_lost=state.t_lost,
                          map_start_t=t + zero, reloc_k=reloc, lost_reloc_k=reloc,
                          segment=jnp.round(state.segment) + 1)  # fmt: skip
    next_state = jax.tree.map(lambda f, n: rs * f + (1 - rs) * n, forced, natural)
    decision = FrameDecision(
        tracked=rs + (1 - rs) * tracked,
        coasting=(1 - rs) * coasting,
        new_map=rs + (1 - rs) * lost_init,
        loss=frame.rec_loss + (1 - rs) * loss,
        reset=(1 - rs) * reset,
    )
    return next_state, decision


def _hard_clock(parts, hard_update):
    """The hard machine's clock update: `_mass_mean` with exact flags, without its arithmetic. (The two
    relocalisation clocks are equal there, so the hard update of either serves both.)"""
    del parts
    return hard_update


def _mass_mean(parts, hard_update):
    """A per-mass clock after a step: the mass-weighted mean of the clocks each part of the mass brings,
    `parts` a sequence of (mass, clock) pairs (e.g. the mass entering a mode now with `t`, and the mass
    staying with the clock it already had).

    The relaxed machine holds probabilities, and the RECENTLY_LOST timer, the map start and the loss
    frame belong to parts of that mass, not to all of it: blending them with the clocks of the other
    modes (a LOST mass's stale map start, an OK mass's stale timer) would make recently lost mass
    expire at once or a new map look old (tests/test_replay.py). With exact flags one part has mass 1
    and the others 0, and this is that part's clock, bit for bit (1 * c / 1); when no mass holds
    the clock it is irrelevant and follows the hard machine's own update `hard_update`. The clocks
    feed only exact comparisons (expiry, relocalisation window, IMU age, initialisation), so they
    carry no gradient (stopped, which also keeps 1 / mass out of the backward pass).
    """
    mass = sum(m for m, _ in parts)
    some = mass > 0
    mean = sum(m * c for m, c in parts) / jnp.where(some, mass, 1.0)
    return jax.lax.stop_gradient(jnp.where(some, mean, hard_update))
