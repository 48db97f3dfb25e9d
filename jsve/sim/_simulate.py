"""The simulator: a stand-in front-end that writes format-v3 tracking logs as ORB-SLAM3 + logger would.

For any set of sequences x disturbance settings x runs, deterministically under a seed:

    recording   per sequence: a smooth true trajectory (EuRoC ground truth, or a procedural flight),
                the IMU stream it implies (ADIS16448 noise model, or the real EuRoC stream), the
                per-frame preintegration and the scene-texture process
                                              (jsve.sim._trajectory, jsve.sim._imu, jsve.sim._scene)
    setting     per (sequence, disturbance, level): ORB extraction counts and SVE bins on the
                degraded images, matching and localisation quality             (jsve.sim._vision)
    run         per run: the first map (monocular initialisation: 100 level-0 matches and parallax),
                map inliers (an occluder costs its edge's keypoints and the points emerging from
                behind it) and frustum counts, the visual pose error (information matrix of the
                inliers' geometry, drift, gross jumps when tracking is weak), IMU initialisation,
                and ORB-SLAM3's own state (its rule replayed by jsve.core._machine.machine_step)

Nothing is defined through the SVE formulas; docs/simulator.md describes the model, its parameters,
its calibration against real frames and its limits.

The configuration is jsve.sim._config's, the sequences and their recordings jsve.sim._recording's.

    simulate_run(sequence, "blur", 25, run=3)              one RunLog
    simulate_study(sequences=..., disturbances="seed")     RunLogs in memory
    write_study("out/", ...)                               logs on disk (jsve.sim._study)
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core._levels import LEVELS, SEED_DISTURBANCES, parse_disturbances
from jsve.core._machine import MONO_INIT_MIN_KEYPOINTS, MONO_INIT_MIN_MATCHES
from jsve.io import _schema as schema
from jsve.io._schema import RunLog
from jsve.sim._camera import EUROC_CAM0, bin_geometry
from jsve.sim._config import FRONTEND, SimConfig, TrackingParams
from jsve.sim._imu import gauss_markov
from jsve.sim._recording import (
    Recording,
    SequenceSpec,
    _cached_recording,
    euroc_sequences,
    generator_key,
    make_recording,
    procedural_sequences,
    seed_key,
)
from jsve.sim._trajectory import GRAVITY, quat_exp, quat_mul
from jsve.sim._vision import Counts, Degradation, degradation, extract

GRIDS = {name: (0, *levels) if name == "occlusion" else levels for name, levels in LEVELS.items()}
"""The level grids the simulator runs: jsve.core._levels.LEVELS (the image registry's), with the
undisturbed 0 before occlusion's 50..450, as each of the seed paper's figures starts from the
undisturbed camera (blur's grid starts at 0 and downsample's at 1.0 already)."""

SEED_GRIDS = {name: GRIDS[name] for name in SEED_DISTURBANCES}
"""The seed paper's 31 settings: blur 0..50 step 5 (11), downsample 1.0..0.1 (10), occlusion 0..450
step 50 (10)."""


@dataclass(frozen=True)
class Setting:
    """One disturbance at one level (`none` at 0 is the undisturbed camera)."""

    disturbance: str
    level: float

    @property
    def label(self) -> str:
        return f"{self.disturbance}-{_format_level(self.level)}"


def _format_level(level: float) -> str:
    return str(int(level)) if float(level).is_integer() else f"{level:g}"


def settings(spec: str | Iterable[str] = "seed") -> list[Setting]:
    """Disturbance settings from a spec.

    "seed": the seed paper's 31 (blur 0, 5, ..., 50: 11; downsample 1.0, 0.9, ..., 0.1: 10;
    occlusion 0, 50, ..., 450: 10; three of them, blur 0, downsample 1.0 and occlusion 0, are the
    undisturbed camera, run separately as each of the paper's figures starts from its own). "all":
    those and every level of the five further disturbances (72). Otherwise names, each optionally with
    levels (jsve.core._levels.parse_disturbances): "blur,occlusion", "blur=0,25,50,noise" (the earlier
    "blur:0:25:50,noise" too). A list of specs is read as one spec, joined by commas.
    """
    items = [spec] if isinstance(spec, str) else list(spec)
    out: list[Setting] = []
    for name, levels in parse_disturbances(",".join(items), ("seed", "all", "none", *GRIDS)):
        if name in ("seed", "all", "none") and levels is not None:
            raise ValueError(f"disturbances: {name!r} takes no levels")
        if name == "seed":
            out.extend(Setting(d, float(lv)) for d in SEED_GRIDS for lv in SEED_GRIDS[d])
        elif name == "all":
            out.extend(Setting(d, float(lv)) for d in GRIDS for lv in GRIDS[d])
        elif name == "none":
            out.append(Setting("none", 0.0))
        else:
            out.extend(Setting(name, float(lv)) for lv in (GRIDS[name] if levels is None else levels))
    seen, unique = set(), []
    for s in out:
        if (s.disturbance, s.level) not in seen:
            seen.add((s.disturbance, s.level))
            unique.append(s)
    return unique


# --------------------------------------------------------------------------------------------------
# Runs


def _linear_recurrence(a: np.ndarray, u: np.ndarray, block: int = 32) -> np.ndarray:
    """x_k = a_k x_(k-1) + u_k with x_(-1) = 0, for a [F] in (0, 1] and u [F, D]; closed form in blocks."""
    F = len(a)
    out = np.empty_like(u)
    carry = np.zeros(u.shape[1:])
    log_a = np.log(np.maximum(a, 1e-300))
    for start in range(0, F, block):
        sl = slice(start, min(F, start + block))
        cum = np.exp(np.cumsum(log_a[sl]))[:, None]
        out[sl] = cum * (carry + np.cumsum(u[sl] / cum, axis=0))
        carry = out[sl.stop - 1]
    return out


def _unit_information(recording: Recording, counts: Counts, tracking: TrackingParams) -> np.ndarray:
    """[F, 6, 6] pose information (camera translation, rotation; camera frame) if every extracted
    keypoint were an inlier: sum over bins of keypoints x the bin's mean J^T J (jsve.sim._vision.
    BinGeometry) at the scene depth, over the localisation variance (px^2 -> normalised by f^2).
    A run's information is its inlier probability times this, plus the motion-model prior."""
    geo = bin_geometry()
    depth = recording.scene.depth
    inv_z = 1.0 / depth
    inv_z2 = (1.0 + tracking.depth_spread**2) / depth**2
    blocks = np.concatenate(
        [geo.info_t.reshape(64, 36), geo.info_m.reshape(64, 36), geo.info_r.reshape(64, 36)], 1
    )
    per_frame = counts.texture_bins @ blocks  # [F, 108]; an occluder's edge gives no inliers
    info = per_frame[:, :36] * inv_z2[:, None] + per_frame[:, 36:72] * inv_z[:, None] + per_frame[:, 72:]
    return info.reshape(-1, 6, 6) * ((EUROC_CAM0.fx / counts.sigma_loc) ** 2)[:, None, None]


NEVER = -1
"""first_map_frame's value for a run that never starts a map."""


def init_match_probability(counts: Counts, tracking: TrackingParams) -> np.ndarray:
    """[F] probability that a level-0 keypoint of the frame is matched by monocular initialisation's
    windowed search (ORBmatcher::SearchForInitialization: level 0 only, 100 px window, Hamming <= 50,
    ratio 0.9): the frame-to-frame match probability times TrackingParams.init_match_share."""
    return np.clip(counts.match_prob * tracking.init_match_share, 0.0, 1.0)


def first_map_frame(
    n_keys: np.ndarray,
    n_level0: np.ndarray,
    p_match: np.ndarray,
    camera_p: np.ndarray,
    depth: np.ndarray,
    t: np.ndarray,
    z: np.ndarray,
    tracking: TrackingParams = TrackingParams(),
) -> np.ndarray:
    """[R] frame at which each run's monocular initialisation starts its first map (NEVER if none).

    ORB-SLAM3 v1.0 Tracking::MonocularInitialization (l.2448-2500): a frame with more than 100
    keypoints becomes the reference; each later frame is matched to it on level 0 and needs 100
    matches, else the reference is dropped (and that frame is not the next one); the reference is also
    dropped when the current frame has 100 keypoints or fewer, or when it is older than
    init_max_age_s (IMU_MONOCULAR). With the matches, TwoViewReconstruction needs init_parallax_deg of
    parallax (minParallax, l.116), here the camera's baseline over the scene depth.

    Arguments:
        n_keys: [F] keypoints of each frame (all levels). n_level0: [F] its level-0 keypoints (an
            occluder's edge's among them: static, they match too).
        p_match: [F] probability that a level-0 keypoint is matched to the reference
            (init_match_probability). camera_p: [F, 3] camera centres, m. depth: [F] median scene
            depth, m. t: [F] s. z: [R, F] standard normal draws of each run's match counts.
    Returns:
        [R] int frame index, or NEVER.
    """
    R, F = z.shape
    start = np.full(R, NEVER)
    keys_ok = n_keys > MONO_INIT_MIN_KEYPOINTS
    # A pair can only pass where the current frame could hold the matches at all: skip the rest.
    if not np.any(keys_ok & (n_level0 >= MONO_INIT_MIN_MATCHES)):
        return start
    min_parallax = math.radians(tracking.init_parallax_deg)
    ready = np.zeros(R, bool)
    ref = np.zeros(R, np.int64)
    for k in range(F):
        waiting = start == NEVER
        if not waiting.any():
            break
        take = waiting & ~ready & keys_ok[k]  # becomes the reference (and tries no match)
        trying = waiting & ready
        # l.2483: the reference is dropped when this frame is poor or the reference too old (the test
        # reads the previous frame's stamp).
        stale = trying & (~keys_ok[k] | (t[max(k - 1, 0)] - t[ref] > tracking.init_max_age_s))
        trying &= ~stale
        # Matches of the reference's level-0 keypoints that this frame also holds: binomial, drawn by
        # its normal approximation from the run's own draws (a run's log must not depend on which
        # other runs are simulated beside it).
        n = np.minimum(n_level0[ref], n_level0[k])
        p = p_match[k]
        matches = n * p + np.sqrt(n * p * (1.0 - p)) * z[:, k]
        enough = trying & (matches >= MONO_INIT_MIN_MATCHES)
        parallax = np.linalg.norm(camera_p[k] - camera_p[ref], axis=1) / depth[k]
        start[enough & (parallax >= min_parallax)] = k
        dropped = stale | (trying & ~enough)
        ready = (ready & ~dropped) | take
        ref = np.where(take, k, ref)
    return start


OCCLUDER_DISTANCES_PX = np.arange(0.0, 760.0, 10.0)
"""px: distances at which occluder_map_share tabulates the bins' shares near an occluder."""


def occluder_map_share(
    recording: Recording, counts: Counts, deg: Degradation, tracking: TrackingParams
) -> np.ndarray:
    """[F] share of the frame's scene keypoints that carry a map point despite an occluder (1 without).

    A point hidden behind the occluder drops out of the local map's view; one that emerges from behind
    it is new to the map until keyframes have seen it long enough to triangulate it (map_lifetime_s).
    The image moves f (|omega_xy| + |v| / depth) px/s, so the keypoints within that speed times
    map_lifetime_s of the occluder's edge, on the side the scene emerges from (half of them), have no
    map point yet. Without an occluder the image border does the same, and TrackingParams.map_fraction
    already holds its share.
    """
    if deg.occluder_px <= 0:
        return np.ones(recording.n_frames)
    geometry = bin_geometry()
    near = geometry.near_occluder_share(deg.occluder_px, OCCLUDER_DISTANCES_PX)  # [D, 64]
    speed = EUROC_CAM0.fx * (
        np.linalg.norm(recording.omega[:, :2], axis=1)
        + np.linalg.norm(recording.v, axis=1) / recording.scene.depth
    )
    reach = np.clip(speed * tracking.map_lifetime_s, OCCLUDER_DISTANCES_PX[0], OCCLUDER_DISTANCES_PX[-1])
    # Linear interpolation of each frame's reach between the tabulated distances.
    j = np.clip(np.searchsorted(OCCLUDER_DISTANCES_PX, reach) - 1, 0, len(OCCLUDER_DISTANCES_PX) - 2)
    w = (reach - OCCLUDER_DISTANCES_PX[j]) / (OCCLUDER_DISTANCES_PX[j + 1] - OCCLUDER_DISTANCES_PX[j])
    share_near = near[j] * (1 - w)[:, None] + near[j + 1] * w[:, None]  # [F, 64]
    weight = counts.texture_bins / np.maximum(counts.texture_bins.sum(axis=1, keepdims=True), 1e-12)
    return 1.0 - 0.5 * np.sum(weight * share_near, axis=1)


def _draw_run(
    recording: Recording,
    counts: Counts,
    unit_info: np.ndarray,
    map_share: np.ndarray,
    p_init: np.ndarray,
    rng: np.random.Generator,
    config: SimConfig,
) -> dict:
    """Per-frame columns of one run (everything that varies between runs of one setting). Frames
    before the run's first map (`start`) have no inliers, no frustum and no pose."""
    tr = config.tracking
    F = recording.n_frames
    t = recording.t
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0] if F > 1 else 0.05))
    # Monocular initialisation: the frame of the first map.
    border = counts.border.sum(axis=1)
    z = rng.normal(size=(1, F))
    start = first_map_frame(
        counts.n_extracted, counts.levels[:, 0], p_init, recording.camera_p, recording.scene.depth, t, z, tr
    )[0]
    mapped = np.arange(F) >= start if start != NEVER else np.zeros(F, bool)
    # Map quality of this run: a slow multiplicative process on the inlier probability.
    quality = np.exp(gauss_markov(rng, t, tr.run_sigma, tr.run_tau, 1)[:, 0] - 0.5 * tr.run_sigma**2)
    p_inlier = np.clip(counts.match_prob * tr.map_fraction * counts.gate * quality * map_share, 0.0, 1.0)
    # An occluder's edge keypoints are static in the image: never inliers of the moving map.
    n_inliers = rng.binomial(np.maximum(counts.n_extracted - border, 0), p_inlier) * mapped
    # Local-map points in view: the keypoints of about the last second.
    window = max(1, int(round(tr.frustum_window_s / max(float(np.median(dt)), 1e-3))))
    csum = np.concatenate([[0.0], np.cumsum(counts.n_extracted)])
    k = np.arange(F)
    lo = np.maximum(k - window + 1, 0)
    recent = (csum[k + 1] - csum[lo]) / (k + 1 - lo)
    n_frustum = rng.poisson(np.maximum(recent * tr.frustum_ratio, 0.0)) * mapped
    # Visual pose error: per-frame jitter from the inliers' information, slow drift, gross jumps.
    share = n_inliers / np.maximum(counts.n_extracted - border, 1)
    prior = np.diag([tr.prior_position**-2] * 3 + [tr.prior_rotation**-2] * 3)
    cov = np.linalg.inv(unit_info * share[:, None, None] + prior)
    chol = np.linalg.cholesky(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    xi = np.einsum("fij,fj->fi", chol, rng.normal(size=(F, 6)))
    r_wc = recording.r_wc
    jitter = np.concatenate(
        [np.einsum("fij,fj->fi", r_wc, xi[:, :3]), np.einsum("fij,fj->fi", r_wc, xi[:, 3:])], 1
    )
    step = np.diff(recording.travelled, prepend=0.0)
    drift_inc = np.zeros((F, 6))
    drift_inc[:, :3] = rng.normal(size=(F, 3)) * (tr.drift_per_sqrt_m * np.sqrt(step))[:, None]
    drift_inc[:, 5] = rng.normal(size=F) * tr.yaw_drift_per_sqrt_m * np.sqrt(step)
    # The map is anchored at its first frame: nothing accumulates before it.
    drift = np.cumsum((drift_inc + tr.jitter_to_drift * jitter) * mapped[:, None], axis=0)
    jump_prob = tr.outlier_rate * np.exp(-n_inliers / tr.outlier_inliers) * mapped
    jumps = (rng.uniform(size=F) < jump_prob)[:, None] * np.concatenate(
        [rng.normal(0, tr.outlier_position, (F, 3)), rng.normal(0, tr.outlier_rotation, (F, 3))], axis=1
    )
    strength = n_inliers / (n_inliers + tr.recovery_inliers)
    excursion = _linear_recurrence(np.exp(-dt * strength / tr.recovery_s), jumps)
    error = drift + excursion + jitter
    if start != NEVER:
        error[start] = 0.0
    # The visual-inertial velocity follows the smooth part of the pose error (low-passed over velocity_tau).
    keep = np.exp(-dt / tr.velocity_tau)
    smooth = _linear_recurrence(keep, (drift[:, :3] + excursion[:, :3]) * (1.0 - keep)[:, None])
    vel_err = np.diff(smooth, axis=0, prepend=smooth[:1]) / dt[:, None]
    unposed = ~mapped[:, None]
    vis_p = np.where(unposed, np.nan, recording.p + error[:, :3])
    vis_q = quat_mul(quat_exp(error[:, 3:]), recording.q)
    vis_q = np.where(unposed, np.nan, vis_q / np.linalg.norm(vis_q, axis=1, keepdims=True))
    vis_v = np.where(unposed, np.nan, recording.v + vel_err)
    # IMU initialisation a run-drawn time after the map starts (never without a map).
    t_init = t[start] + rng.uniform(*tr.imu_init_s) if start != NEVER else np.inf
    return dict(n_inliers=n_inliers, n_frustum=n_frustum, vis_p=vis_p, vis_q=vis_q, vis_v=vis_v,
                t_init=t_init, start=start)  # fmt: skip


def _orbslam3_states(
    n_inliers: np.ndarray,
    n_extracted: np.ndarray,
    frame_ns: np.ndarray,
    imu_init: np.ndarray,
    imu_ba2: np.ndarray,
    start: np.ndarray,
    fps: float,
) -> np.ndarray:
    """ORB-SLAM3's logged eTrackingState per frame [R, F] under its own rule (15/50/50/10) and switch
    model, from jsve.core._machine.machine_step on the run's log (one recorded map from `start`, a pose
    on every frame from there): NOT_INITIALIZED 1 before the first map (all frames where start is
    NEVER) and while a new map waits; OK 2; RECENTLY_LOST 3 (also on the frame that requests a reset,
    as Tracking.cc l.2155 logs it); LOST 4 on the frame the 5 s timer expires."""
    import jax.numpy as jnp

    from jsve.core._rules import preset

    R, F = n_inliers.shape
    padded = max(1024, int(math.ceil(F / 1024)) * 1024)  # few distinct shapes: few compilations
    pad = ((0, 0), (0, padded - F))
    t = (frame_ns - frame_ns[0]) / 1e9
    k = np.arange(F)
    has_pose = (start[:, None] != NEVER) & (k[None] >= start[:, None])
    first_map = (k[None] == start[:, None]).astype(np.float32)
    t_start = np.where(start != NEVER, t[np.maximum(start, 0)], np.inf)

    # The recorded run's delays from its first map to IMU initialisation and BA2 (as jsve.io reads them).
    def first(flags):
        return np.array(
            [t[np.argmax(f)] - ts if f.any() else np.inf for f, ts in zip(flags, t_start, strict=True)]
        )

    n_ext = np.broadcast_to(n_extracted, (R, F))
    init_keys = n_ext > MONO_INIT_MIN_KEYPOINTS
    init_matches = n_inliers >= MONO_INIT_MIN_MATCHES  # the replay's stand-in (jsve.core._replay)
    flags = (n_inliers, imu_init, imu_ba2, has_pose, init_keys, init_matches, first_map)
    columns = [np.pad(x.astype(np.float32), pad) for x in flags]
    tt = np.pad(t.astype(np.float32), (0, padded - F), mode="edge")
    delays = (jnp.asarray(first(imu_init), jnp.float32), jnp.asarray(first(imu_ba2), jnp.float32))
    out = _machine_fn()(*map(jnp.asarray, columns), jnp.asarray(tt), jnp.float32(fps), *delays,
                        preset("orbslam3").thresholds)  # fmt: skip
    modes, reset, loss = (np.asarray(x)[:, :F] for x in out)
    state = np.select(
        [modes == 0, modes == 1], [schema.STATE_OK, schema.STATE_RECENTLY_LOST], schema.STATE_LOST
    )
    was_lost = np.concatenate([np.zeros((R, 1), bool), modes[:, :-1] == 2], axis=1)
    state = np.where((modes == 2) & (was_lost | reset), schema.STATE_NOT_INITIALIZED, state)
    state = np.where(reset, schema.STATE_RECENTLY_LOST, state)
    state = np.where(has_pose, state, schema.STATE_NOT_INITIALIZED)
    return state.astype(np.int64)


@functools.cache
def _machine_fn():
    import jax
    import jax.numpy as jnp

    from jsve.core._machine import FrameData, HardLogic, RunConstants, initial_state, machine_step

    def one(score, init, ba2, has_pose, init_keys, init_matches, rec_start, t, fps, delay, ba2_delay,
            thresholds):  # fmt: skip
        k = jnp.arange(t.shape[0], dtype=t.dtype)
        zero = jnp.zeros_like(t)
        data = FrameData(t=t, k=k, imu_init=init, imu_ba2=ba2, has_pose=has_pose,
                         init_keys=init_keys, init_matches=init_matches, rec_start=rec_start, rec_loss=zero,
                         rec_start_t=jnp.cumsum(rec_start * t), rec_reloc=zero - 1)  # fmt: skip
        run = RunConstants(fps=fps, imu_init_delay=delay, ba2_delay=ba2_delay, stereo=jnp.zeros((), t.dtype))

        def step(state, x):
            sc, fd = x
            state, decision = machine_step(HardLogic(), state, sc, fd, run, thresholds)
            modes = jnp.stack([state.ok, state.recently_lost, state.lost])
            return state, (jnp.argmax(modes).astype(jnp.int8), decision.reset > 0.5, decision.loss > 0.5)

        _, out = jax.lax.scan(step, initial_state(t.dtype), (score, data))
        return out

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, 0, 0, 0, None, None, 0, 0, None)))


def _round(x: np.ndarray, decimals: int) -> np.ndarray:
    # Fixed decimals keep the CSV short (shortest round-trip form of a rounded double); far below
    # every error the simulator models (um, nm/s, 1e-9 of a unit quaternion).
    return np.round(x, decimals)


def simulate_setting(
    recording: Recording,
    setting: Setting,
    runs: Sequence[int],
    seed: int = 0,
    config: SimConfig = SimConfig(),
) -> list[RunLog]:
    """All runs of one (sequence, setting): extraction once, then each run's tracking draws.

    `seed` and `config` are the recording's (make_recording's arguments); each log's metadata records
    them as `generator` (generator_key).
    """
    deg = degradation(setting.disturbance, setting.level, config.vision, seed=seed)
    generator = generator_key(recording.spec, seed, config)
    counts = extract(recording.scene, deg, config.vision, n_features=config.n_features)
    F = recording.n_frames
    # EuRoC's stamps alternate 50,000,128 and 49,999,872 ns: fps to the millihertz (20.0).
    fps = float(round(1e9 / np.median(np.diff(recording.frame_ns)), 3)) if F > 1 else 20.0
    unit_info = _unit_information(recording, counts, config.tracking)
    map_share = occluder_map_share(recording, counts, deg, config.tracking)
    p_init = init_match_probability(counts, config.tracking)
    draws = [
        _draw_run(
            recording,
            counts,
            unit_info,
            map_share,
            p_init,
            np.random.default_rng(
                seed_key(seed, "run", recording.spec.name, setting.disturbance, float(setting.level), int(r))
            ),
            config,
        )
        for r in runs
    ]
    start = np.array([d["start"] for d in draws], np.int64)
    imu_init = np.stack([recording.t >= d["t_init"] for d in draws])
    imu_ba2 = np.stack([_ba2(recording.frame_ns, init, s) for init, s in zip(imu_init, start, strict=True)])
    states = _orbslam3_states(
        np.stack([d["n_inliers"] for d in draws]),
        counts.n_extracted,
        recording.frame_ns,
        imu_init,
        imu_ba2,
        start,
        fps,
    )
    out = []
    dt0, dp0, dv0, dq0 = recording.preint_zero
    dt1, dp1, dv1, dq1 = recording.preint_est
    bins = counts.bins
    for i, (r, d) in enumerate(zip(runs, draws, strict=True)):
        # The interval ending at frame k is corrected with the biases held at frame k - 1.
        ready = np.concatenate([[False], imu_init[i, :-1]])[:, None]
        columns = {
            "t_ns": recording.frame_ns,
            "state": states[i],
            "imu_init": imu_init[i].astype(np.int64),
            # One map from the first map's frame on (a pose on every later frame: full support for
            # any rule), inertial BA2 from 15 s after its start (docs/simulator.md).
            "map_id": np.zeros(F, np.int64),
            "imu_ba2": imu_ba2[i].astype(np.int64),
            "n_extracted": counts.n_extracted,
            "n_inliers": d["n_inliers"],
            "n_frustum": d["n_frustum"],
        }
        columns.update({c: bins[:, k] for k, c in enumerate(schema.BIN_COLUMNS)})
        columns.update(_split(schema.VIS_POSITION, _round(d["vis_p"], 6)))
        columns.update(_split(schema.VIS_QUATERNION, _round(d["vis_q"], 9)))
        columns.update(_split(schema.VIS_VELOCITY, _round(d["vis_v"], 6)))
        columns["imu_dt"] = dt1
        columns.update(_split(schema.IMU_DP, _round(np.where(ready, dp1, dp0), 9)))
        columns.update(_split(schema.IMU_DV, _round(np.where(ready, dv1, dv0), 9)))
        columns.update(_split(schema.IMU_DQ, _round(np.where(ready, dq1, dq0), 9)))
        columns.update(_split(schema.GT_POSITION, _round(recording.p, 6)))
        columns.update(_split(schema.GT_QUATERNION, _round(recording.q, 9)))
        frames = pd.DataFrame(columns, columns=list(schema.COLUMNS))
        meta = {
            "sequence": recording.spec.name,
            "disturbance": setting.disturbance,
            "level": _meta_level(setting.level),
            "run": int(r),
            "sensor": "imu_monocular",
            "n_features": config.n_features,
            "image_size": [EUROC_CAM0.width, EUROC_CAM0.height],
            "grid": [8, 8],
            "fps": fps,
            "gravity": [float(g) for g in GRAVITY],
            "frontend": FRONTEND,
            "rule": "orbslam3",  # the logged state is ORB-SLAM3's own rule ...
            "switch_model": "orbslam3",  # ... and a rejected frame keeps its optimised pose
            "seed": int(seed),
            "trajectory": Path(recording.trajectory.source).name,  # file names: logs do not
            "imu": Path(recording.imu_source).name,  # depend on where the data sits
            "generator": generator,  # what write_study checks before resuming
        }
        out.append(
            RunLog(meta=meta, frames=frames, source=f"<simulated {recording.spec.name}/{setting.label}/{r}>")
        )
    return out


def _ba2(frame_ns: np.ndarray, imu_init: np.ndarray, start: int) -> np.ndarray:
    """[F] inertial BA2 done: schema.v1_defaults' rule (V1_BA2_DELAY_S after the map's first frame, on
    frames whose IMU is initialised) counted from the first map's frame `start` (none if NEVER)."""
    out = np.zeros(len(frame_ns), np.int64)
    if start != NEVER:
        out[start:] = schema.v1_defaults(frame_ns[start:], imu_init[start:])["imu_ba2"]
    return out


def _meta_level(level: float):
    return int(level) if float(level).is_integer() else float(level)


def _split(names: Sequence[str], values: np.ndarray) -> dict:
    return {n: values[:, j] for j, n in enumerate(names)}


# --------------------------------------------------------------------------------------------------
# Public API


def _as_specs(sequences, euroc_gt, procedural) -> list[SequenceSpec]:
    if (
        sequences is not None
        and not isinstance(sequences, str)
        and sequences
        and isinstance(sequences[0], SequenceSpec)
    ):
        return list(sequences)
    if isinstance(sequences, str):
        sequences = [s.strip() for s in sequences.split(",") if s.strip()]
    if sequences:
        if euroc_gt is None:
            raise ValueError(
                "EuRoC sequences need euroc_gt (the folder of ORB-SLAM3's *_GT.txt files); "
                "without it use procedural=N"
            )
        return euroc_sequences(sequences, euroc_gt)
    return procedural_sequences(11 if procedural is None else int(procedural))


def simulate_run(
    sequence: str | SequenceSpec = "proc_00",
    disturbance: str = "none",
    level: float = 0.0,
    run: int = 0,
    *,
    seed: int = 0,
    euroc_gt: str | os.PathLike | None = None,
    config: SimConfig = SimConfig(),
) -> RunLog:
    """Simulate one run's tracking log.

    Arguments:
        sequence: a procedural name ("proc_03": any name gives a flight) or a EuRoC name with euroc_gt.
        disturbance, level: one setting (see `settings`; "none" for the undisturbed camera).
        run: run index (a different run draws new tracking noise on the same recording).
        seed: study seed; everything is a deterministic function of (seed, sequence, setting, run).
    Returns:
        A RunLog (validated by jsve.io._logs when written or read).
    """
    spec = (
        sequence
        if isinstance(sequence, SequenceSpec)
        else (euroc_sequences([sequence], euroc_gt)[0] if euroc_gt is not None else SequenceSpec(sequence))
    )
    recording = _cached_recording(spec, seed, config)
    return simulate_setting(recording, Setting(disturbance, float(level)), [run], seed, config)[0]


def simulate_study(
    sequences: Sequence[str] | str | None = None,
    *,
    procedural: int | None = None,
    euroc_gt: str | os.PathLike | None = None,
    disturbances: str | Iterable[str] = "seed",
    runs: int | Sequence[int] = 10,
    seed: int = 0,
    config: SimConfig = SimConfig(),
    progress: bool = False,
) -> list[RunLog]:
    """Simulate a study in memory: every sequence x setting x run, as RunLogs.

    Arguments:
        sequences: EuRoC names (with euroc_gt) or SequenceSpecs; default `procedural` flights.
        procedural: number of procedural flights when no sequences are given (default 11).
        disturbances: a settings spec (see `settings`): "seed" (31), "all", "blur,occlusion", ...
        runs: number of runs per setting, or the run indices.
    """
    from tqdm.auto import tqdm

    specs = _as_specs(sequences, euroc_gt, procedural)
    grid = settings(disturbances)
    run_ids = list(range(runs)) if isinstance(runs, int) else list(runs)
    out: list[RunLog] = []
    with tqdm(total=len(specs) * len(grid), desc="simulate", unit="setting", disable=not progress) as bar:
        for spec in specs:
            recording = make_recording(spec, seed, config)
            for setting in grid:
                out.extend(simulate_setting(recording, setting, run_ids, seed, config))
                bar.update()
    return out


__all__ = [
    "GRIDS",
    "Setting",
    "settings",
    "simulate_setting",
    "simulate_run",
    "simulate_study",
]
