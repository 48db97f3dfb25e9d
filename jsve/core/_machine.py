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
from jaxtyping import Array, Float

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


class MachineState(eqx.Module):
    """Carry of the state machine. Modes are {0, 1} flags (probabilities when relaxed).

    Attributes:
        ok, recently_lost, lost: mode flags, exactly one is 1 in the hard machine.
        t_lost: s, time of the frame that entered RECENTLY_LOST (the timer is never restarted there).
            Relaxed, it is the timer of the RECENTLY_LOST mass: the mass-weighted mean entry time of
            the mass now in RECENTLY_LOST (the OK and LOST masses have no timer).
        map_start_t: s, time of the first frame of the current map.
        map_start_k: frame index of the first frame of the current map (ORB-SLAM3 sets
            mnLastRelocFrameId to the initial frame of a new monocular map).
        segment: index of the current map (0 for the first).
    """

    ok: Float[Array, "*runs"]
    recently_lost: Float[Array, "*runs"]
    lost: Float[Array, "*runs"]
    t_lost: Float[Array, "*runs"]
    map_start_t: Float[Array, "*runs"]
    map_start_k: Float[Array, "*runs"]
    segment: Float[Array, "*runs"]


def initial_state(dtype=float) -> MachineState:
    """Tracking OK in map 0, started at frame 0: the log begins once the front-end has a map."""
    one, zero = jnp.ones((), dtype), jnp.zeros((), dtype)
    return MachineState(ok=one, recently_lost=zero, lost=zero, t_lost=zero, map_start_t=zero,
                        map_start_k=zero, segment=zero)  # fmt: skip


class FrameDecision(eqx.Module):
    """What the machine decided for one frame (flags in {0, 1}, probabilities when relaxed).

    accepted: the visual estimate is used. predicted: the IMU prediction is used (RECENTLY_LOST).
    has_estimate = accepted + predicted. new_map: a new map (segment) starts at this frame.
    """

    accepted: Float[Array, "*runs"]
    predicted: Float[Array, "*runs"]
    new_map: Float[Array, "*runs"]


def tracking_succeeds(logic, score, th: Thresholds, recently_lost, imu_ok, in_reloc):
    """Tracking::TrackLocalMap's success test with the rule's thresholds (ORB-SLAM3 v1.0, IMU).

    In order: inside the relocalisation window a score below `reloc` fails; in RECENTLY_LOST a score
    above `recovery` succeeds; otherwise fail below `imu_init` (IMU initialised) or `not_init`.
    """
    fail_reloc = in_reloc * logic.less(score, th.reloc)
    recover = recently_lost * logic.greater(score, th.recovery)
    pass_main = (imu_ok * (1 - logic.less(score, th.imu_init))
                 + (1 - imu_ok) * (1 - logic.less(score, th.not_init)))  # fmt: skip
    return (1 - fail_reloc) * (recover + (1 - recover) * pass_main)


def machine_step(
    logic,
    state: MachineState,
    score,
    t,
    k,
    imu_init_logged,
    th: Thresholds,
    fps,
    imu_init_delay,
    time_recently_lost=TIME_RECENTLY_LOST_S,
) -> tuple[MachineState, FrameDecision]:
    """Advance ORB-SLAM3's state machine by one frame (see docs/state-machine.md).

    Arguments:
        score: the rule's score of this frame. t: s since the first frame. k: frame index (float).
        imu_init_logged: 1 if the original run had the IMU initialised at this frame.
        fps: frames per second; the relocalisation window is floor(fps) frames (ORB-SLAM3 mMaxFrames).
        imu_init_delay: s the run needed to initialise the IMU; a new map waits as long again.
        time_recently_lost: s in RECENTLY_LOST before LOST (5 in ORB-SLAM3 v1.0).
    """
    dtype = jnp.result_type(t, float)
    ge = lambda a, b: (a >= b).astype(dtype)  # noqa: E731 - data comparisons stay exact when relaxed
    imu_ok = imu_init_logged * ge(t - state.map_start_t, imu_init_delay)
    # ORB-SLAM3's mMaxFrames is an int set from Camera.fps, so a fractional fps truncates.
    in_reloc = (k < state.map_start_k + jnp.floor(fps)).astype(dtype)
    expired = (t - state.t_lost > time_recently_lost).astype(dtype)

    ok_pass = tracking_succeeds(logic, score, th, 0.0, imu_ok, in_reloc)
    rl_pass = (1 - expired) * tracking_succeeds(logic, score, th, 1.0, imu_ok, in_reloc)
    # A new monocular map must pass the strict relocalisation-window test without the IMU.
    lost_pass = tracking_succeeds(logic, score, th, 0.0, 0.0, 1.0)

    ok_fail = state.ok * (1 - ok_pass)
    accepted = state.ok * ok_pass + state.recently_lost * rl_pass + state.lost * lost_pass
    # OK -> RECENTLY_LOST when the IMU can carry the estimate; before IMU initialisation ORB-SLAM3
    # resets the active map instead, which the replay treats as LOST (a new segment follows).
    entering = ok_fail * imu_ok
    staying = state.recently_lost * (1 - expired) * (1 - rl_pass)
    to_recently_lost = entering + staying
    to_lost = ok_fail * (1 - imu_ok) + state.recently_lost * expired + state.lost * (1 - lost_pass)
    new_map = state.lost * lost_pass
    tracking = accepted + to_recently_lost

    next_state = MachineState(
        ok=accepted,
        recently_lost=to_recently_lost,
        lost=to_lost,
        t_lost=_mass_mean(entering, staying, t, state.t_lost, ok_fail * t + (1 - ok_fail) * state.t_lost),
        # The map start belongs to the tracking (OK + RECENTLY_LOST) mass: the mass starting a new map
        # now, and the rest of the tracking mass, which keeps its own.
        map_start_t=_mass_mean(
            new_map, tracking - new_map, t, state.map_start_t, new_map * t + (1 - new_map) * state.map_start_t
        ),
        map_start_k=_mass_mean(
            new_map, tracking - new_map, k, state.map_start_k, new_map * k + (1 - new_map) * state.map_start_k
        ),
        segment=state.segment + new_map,
    )
    return next_state, FrameDecision(accepted=accepted, predicted=to_recently_lost, new_map=new_map)


def _mass_mean(entering, staying, now, old, hard_update):
    """A per-mass clock after a step: the mass-weighted mean of `now` (for the `entering` mass) and of
    `old` (the clock the `staying` mass already had).

    The relaxed machine holds probabilities, and the RECENTLY_LOST timer and the map start belong to
    parts of that mass, not to all of it: blending them with the clocks of the other modes (a LOST
    mass's stale map start, an OK mass's stale timer) would make recently lost mass expire at once or
    a new map look old (tests/test_replay.py). With exact flags this is `now` on entry and `old` while
    staying, bit for bit (1 * now / 1, 0 * now + 1 * old); when no mass holds the clock it is
    irrelevant and follows the hard machine's own update `hard_update`. The clocks feed only exact
    comparisons (expiry, relocalisation window, IMU age), so they carry no gradient (stopped, which
    also keeps 1 / mass out of the backward pass).
    """
    mass = entering + staying
    some = mass > 0
    mean = (entering * now + staying * old) / jnp.where(some, mass, 1.0)
    return jax.lax.stop_gradient(jnp.where(some, mean, hard_update))
