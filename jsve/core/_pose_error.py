"""Pose errors of estimated trajectories against their references: APE and RPE, as evo defines them.

The one home of scoring pose pairs (an estimate and its reference, associated pose by pose), as `jsve ape`,
`jsve rpe` and Table I (jsve.masks._table_one) do. Single-run kernels, each jit-compiled and vmappable:

    align_poses(est, ref, valid, method=...)         the estimate mapped onto the reference (jsve.core._align)
    pose_errors(aligned, ref, relation)              APE per pose (evo's metrics.APE)
    rpe_pairs(poses, valid, delta, unit=...)         the pose pairs delta apart (evo's filter_pairs_by_*)
    rpe_angle_pairs(poses, valid, delta, ...)        all pairs delta degrees/radians apart, as a [T, T] mask
    relative_pose_errors(est, ref, first, second)    RPE per pair (evo's metrics.RPE)
    error_statistics(errors, mask)                   rmse, mean, median, std, min, max, sse, count

and, in jsve.core._pose_error_batch, the batched boundary over runs padded to one length (jsve.io.
_trajectories.stack_pose_pairs pads them): `batched_pose_error` / `batched_ape` and `batched_rpe`.
Compute in float64 (`jax_enable_x64`) to match evo
(tests/test_cli_ape.py: rel 1e-9 on random trajectories and KITTI 00).

Conventions: poses are [T, 4, 4] matrices T_wb (rotation, translation in metres), body in world; a run's
`valid` mask is a prefix (padding at the end). Pose relations (POSE_RELATIONS) are evo's:
"translation" (PoseRelation.translation_part, metres), "angle_deg" / "angle_rad" (rotation_angle_deg /
_rad: the angle of the error rotation), "full" (full_transformation: ||E - I||_F, unit-less).
"""

from __future__ import annotations

import functools
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int

from jsve.core._align import ALIGNERS, Transform, first_pose_transform
from jsve.core._geometry import (
    columns,
    matrix_to_quat,
    nearest_rotation,
    quat_conj,
    quat_mul,
    rotation_angle,
)
from jsve.core._numerics import safe_sqrt
from jsve.core._trajectory import (
    ErrorStats,
    _error_statistics,
    _position_errors,
    align,
)

POSE_RELATIONS: dict[str, tuple[str, str]] = {
    "translation": ("translation part", "m"),
    "angle_deg": ("rotation angle in degrees", "deg"),
    "angle_rad": ("rotation angle in radians", "rad"),
    "full": ("full transformation", "unit-less"),
}
"""jsve's pose relations -> (evo's PoseRelation value, evo's unit), e.g. "angle_deg" -> PoseRelation.
rotation_angle_deg, whose errors are in degrees."""

DELTA_UNITS: dict[str, str] = {"f": "frames", "d": "deg", "r": "rad", "m": "m"}
"""RPE's delta units (evo_rpe --delta_unit) -> evo's Unit value: frames, degrees, radians, metres."""

POSE_ALIGN_METHODS: tuple[str, ...] = (*ALIGNERS, "scale")
"""The alignments of `align_poses`: jsve.core._align's methods and "scale", evo's scale-only correction
(evo_ape -s without -a: Sim(3) Umeyama's scale applied to the positions, no rotation or translation)."""

RPE_FAILURE_CAUSES: tuple[str, ...] = (
    "no pose pair at this delta",
    "degenerate alignment",
    "non-finite error statistics (a value overflowed or was NaN)",
)
"""Why an RPE run failed: cause k sets bit k of RelativeErrorBatch.failure (`failure_reason(bits,
RPE_FAILURE_CAUSES)`)."""


def check_relation(relation: str) -> None:
    if relation not in POSE_RELATIONS:
        raise ValueError(f"relation must be one of {tuple(POSE_RELATIONS)}, got {relation!r}")


def _check_poses(name: str, poses, n_frames: int | None = None) -> None:
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (T, 4, 4), got {tuple(poses.shape)}")
    if n_frames is not None and poses.shape[0] != n_frames:
        raise ValueError(f"{name} has {poses.shape[0]} poses but est has {n_frames}")


# ----------------------------------------------------------------------------------------------------------
# Rigid-motion helpers (poses as rotation and translation parts).


def _matvec(m: Array, v: Array) -> Array:
    return jnp.einsum("...ij,...j->...i", m, v)


def _between(ra: Array, ta: Array, rb: Array, tb: Array) -> tuple[Array, Array]:
    """A^-1 B of rigid poses given as (rotation, translation): evo's lie.relative_se3(A, B)."""
    rat = jnp.swapaxes(ra, -1, -2)
    # evo: se3_inverse(A) = [R^T, -R^T t_A], times B
    return rat @ rb, _matvec(rat, tb) - _matvec(rat, ta)


def _relation_error(r: Array, t: Array, relation: str) -> Array:
    """The error of an error pose E = (r, t) under a pose relation (evo's PE.process_data)."""
    if relation == "translation":
        return safe_sqrt(jnp.sum(t * t, axis=-1))
    if relation == "full":
        # ||E - I||_F over the 4x4 matrix; its bottom row [0 0 0 1] cancels.
        d = r - jnp.eye(3, dtype=r.dtype)
        return safe_sqrt(jnp.sum(d * d, axis=(-2, -1)) + jnp.sum(t * t, axis=-1))
    angle = cast(Array, rotation_angle(r))  # evo: |so3_log_angle(E_R)|, scipy's rotation vector norm
    return jnp.rad2deg(angle) if relation == "angle_deg" else angle


def transform_poses(transform: Transform, poses: Float[Array, "T 4 4"]) -> Float[Array, "T 4 4"]:
    """Poses mapped by a similarity transform, as evo's PosePath3D.align applies one: orientations R R_i,
    positions s R p_i + t (metres, the transform's target frame)."""
    rotation = transform.rotation @ poses[..., :3, :3]
    position = transform.apply(poses[..., :3, 3])
    top = jnp.concatenate([rotation, position[..., None]], axis=-1)
    return jnp.concatenate([top, poses[..., 3:, :]], axis=-2)


# ----------------------------------------------------------------------------------------------------------
# Single-run kernels.


@functools.partial(jax.jit, static_argnames=("method", "n_first"))
def align_poses(
    est: Float[Array, "T 4 4"],
    ref: Float[Array, "T 4 4"],
    valid: Bool[Array, " T"],
    *,
    method: str = "se3",
    n_first: int | None = None,
) -> tuple[Float[Array, "T 4 4"], Transform]:
    """The estimate aligned to the reference on its valid poses, whole poses mapped as evo maps them.

    Arguments:
        est: [T, 4, 4] estimated poses T_wb, estimate world frame.
        ref: [T, 4, 4] reference poses of the same frames, reference world frame.
        valid: [T] the poses to align on.
        method: (static) a method of jsve.core._align ("se3": evo -a, "sim3": -a -s, "posyaw", "origin":
            --align_origin, "none") or "scale" (evo -s alone: Sim(3) Umeyama's scale only).
        n_first: (static) align on the first n_first valid poses only (evo's --n_to_align); None: all.

    Returns:
        (aligned [T, 4, 4] in the reference world frame, transform). A degenerate alignment is the
        identity with transform.degenerate set (jsve.core._trajectory.align).
    """
    if method not in POSE_ALIGN_METHODS:
        raise ValueError(f"method must be one of {POSE_ALIGN_METHODS}, got {method!r}")
    _check_poses("est", est)
    _check_poses("ref", ref, est.shape[0])
    if method == "origin":  # from the matrices, as evo's align_origin: no round trip through quaternions
        first = jnp.argmax(valid)
        transform = first_pose_transform(
            est[first, :3, :3], est[first, :3, 3], ref[first, :3, :3], ref[first, :3, 3], ~jnp.any(valid)
        )
        return transform_poses(transform, est), transform
    fitted = "sim3" if method == "scale" else method
    _, _, transform = align(
        est[:, :3, 3],
        ref[:, :3, 3],
        valid,
        method=fitted,
        est_q=matrix_to_quat(est[:, :3, :3]),
        ref_q=matrix_to_quat(ref[:, :3, :3]),
        n_first=n_first,
    )
    if method == "scale":  # evo's correct_only_scale: the positions scaled about the origin
        transform = Transform(
            rotation=jnp.eye(3, dtype=transform.scale.dtype),
            translation=jnp.zeros(3, transform.scale.dtype),
            scale=transform.scale,
            degenerate=transform.degenerate,
        )
    return transform_poses(transform, est), transform


@functools.partial(jax.jit, static_argnames=("relation",))
def pose_errors(
    est: Float[Array, "T 4 4"], ref: Float[Array, "T 4 4"], relation: str = "translation"
) -> Float[Array, " T"]:
    """Absolute pose error of each pose, evo's metrics.APE.

    Arguments:
        est: [T, 4, 4] estimated poses, already aligned (reference world frame).
        ref: [T, 4, 4] reference poses.
        relation: (static) a key of POSE_RELATIONS. "translation": |p_est - p_ref| (metres); the others
            from E = est^-1 ref (evo's APE.ape_base): the angle of E's rotation (degrees or radians), or
            ||E - I||_F.

    Returns:
        [T] errors (>= 0) in the relation's unit.
    """
    check_relation(relation)
    _check_poses("est", est)
    _check_poses("ref", ref, est.shape[0])
    if relation == "translation":  # as ape_statistics: the distance of the positions
        return _position_errors(columns(est[:, :3, 3]), columns(ref[:, :3, 3]))
    r, t = _between(est[:, :3, :3], est[:, :3, 3], ref[:, :3, :3], ref[:, :3, 3])
    return _relation_error(r, t, relation)


@functools.partial(jax.jit, static_argnames=("relation",))
def relative_pose_errors(
    est: Float[Array, "T 4 4"],
    ref: Float[Array, "T 4 4"],
    first: Int[Array, " P"],
    second: Int[Array, " P"],
    relation: str = "translation",
) -> Float[Array, " P"]:
    """Relative pose error of each pose pair (i, j), evo's metrics.RPE.

    E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) with Q the reference and P the estimate (evo's RPE.rpe_base, the TUM
    RGB-D benchmark's definition): the motion from i to j of the estimate against the reference's.

    Arguments:
        est: [T, 4, 4] estimated poses (aligned or not: a rigid alignment does not change E).
        ref: [T, 4, 4] reference poses.
        first, second: [P] int indices i and j of each pair (indices outside [0, T) are clipped: mask such
            pairs out of the statistics).
        relation: (static) a key of POSE_RELATIONS: |t_E| (metres), the angle of R_E (degrees or radians)
            or ||E - I||_F.

    Returns:
        [P] errors (>= 0) in the relation's unit.
    """
    check_relation(relation)
    _check_poses("est", est)
    _check_poses("ref", ref, est.shape[0])
    if first.shape != second.shape or first.ndim != 1:
        raise ValueError(f"first and second must have one shape (P,), got {first.shape} and {second.shape}")

    def motion(poses):
        a = jnp.take(poses, first, axis=0, mode="clip")
        b = jnp.take(poses, second, axis=0, mode="clip")
        return _between(a[:, :3, :3], a[:, :3, 3], b[:, :3, :3], b[:, :3, 3])

    r, t = _between(*motion(ref), *motion(est))
    return _relation_error(r, t, relation)


def _accumulate_and_reset(steps: Array, usable: Array, delta: Array) -> tuple[Array, Array, Array]:
    """evo's consecutive pairs by path length or angle: sum the steps from the last chosen pose; a pose
    where the sum reaches delta closes a pair and restarts the sum. Slot j holds the pair ending at pose j
    (slot 0 never does)."""

    def step(carry, x):
        total, last = carry
        s, j, ok = x
        total = total + s
        hit = ok & (total >= delta)
        return (jnp.where(hit, jnp.zeros_like(total), total), jnp.where(hit, j, last)), (last, hit)

    n_frames = steps.shape[0] + 1
    frames = jnp.arange(1, n_frames)
    start = (jnp.zeros((), steps.dtype), jnp.zeros((), frames.dtype))
    _, (first, hit) = jax.lax.scan(step, start, (steps, frames, usable))
    zero = jnp.zeros(1, frames.dtype)
    return (
        jnp.concatenate([zero, first]),
        jnp.concatenate([zero, frames]),
        jnp.concatenate([jnp.zeros(1, bool), hit]),
    )


def _first_true(pred, lo: Array, hi: Array, n_steps: int) -> Array:
    """The first index in [lo, hi) where the monotone (False ... True) predicate holds, hi where none
    does; bisection, vectorised over the bounds."""

    def halve(_, bounds):
        lo, hi = bounds
        open_ = lo < hi
        mid = (lo + hi) // 2
        yes = pred(jnp.where(open_, mid, 0))
        return jnp.where(open_ & ~yes, mid + 1, lo), jnp.where(open_ & yes, mid, hi)

    lo, _ = jax.lax.fori_loop(0, n_steps, halve, (lo, hi))
    return lo


def _cumsum_in_order(x: Array) -> Array:
    """numpy.cumsum's sums, left to right (XLA's cumsum may associate differently and lose monotonicity)."""

    def add(total, v):
        total = total + v
        return total, total

    _, out = jax.lax.scan(add, jnp.zeros((), x.dtype), x)
    return out


@functools.partial(jax.jit, static_argnames=("unit", "all_pairs"))
def rpe_pairs(
    poses: Float[Array, "T 4 4"],
    valid: Bool[Array, " T"],
    delta: ArrayLike,
    *,
    unit: str = "f",
    all_pairs: bool = False,
    rel_tol: ArrayLike = 0.1,
) -> tuple[Int[Array, " T"], Int[Array, " T"], Bool[Array, " T"]]:
    """The pose pairs (i, j) delta apart, as evo's metrics.id_pairs_from_delta chooses them.

    Arguments:
        poses: [T, 4, 4] the poses that set the distances (evo: the aligned estimate, or the reference
            with --pairs_from_reference).
        valid: [T] a prefix: the first n are poses, the rest padding.
        delta: > 0; frames (an integer), metres, degrees or radians, after `unit`.
        unit: (static) "f" frames: consecutive pairs (0, d), (d, 2d), ... or with all_pairs every (i, i + d);
            "m" metres of path: consecutive pairs each closing when the path since the pair's start reaches
            delta, or with all_pairs for every i the first j > i whose path from i is closest to delta,
            kept within delta * rel_tol; "d" / "r" degrees / radians: consecutive pairs closing when the sum
            of the rotation angles between successive poses reaches delta (all pairs: `rpe_angle_pairs`).
        all_pairs: (static) every pair rather than consecutive ones.
        rel_tol: the relative tolerance of all_pairs in metres (evo_rpe --delta_tol, default 0.1).

    Returns:
        (first, second, mask), each [T] (a slot per possible pair): pair k is (first[k], second[k]) where
        mask[k]; evo's pairs, in evo's order, are the masked slots in slot order.
    """
    if unit not in DELTA_UNITS:
        raise ValueError(f"unit must be one of {tuple(DELTA_UNITS)}, got {unit!r}")
    if unit in ("d", "r") and all_pairs:
        raise ValueError("all pairs by angle are a [T, T] mask: use rpe_angle_pairs")
    _check_poses("poses", poses)
    n_frames = poses.shape[0]
    if valid.shape != (n_frames,):
        raise ValueError(f"valid must have shape ({n_frames},) like poses, got {tuple(valid.shape)}")
    valid = valid.astype(bool)
    valid = eqx.error_if(valid, jnp.any(valid[1:] & ~valid[:-1]), "rpe_pairs: valid must be a prefix")
    n = jnp.sum(valid, dtype=jnp.int32)
    k = jnp.arange(n_frames, dtype=jnp.int32)
    if unit == "f":
        d = jnp.asarray(delta).astype(jnp.int32)
        d = eqx.error_if(d, d < 1, "rpe_pairs: delta must be at least 1 frame")
        if all_pairs:  # (i, i + d) for every i with i + d < n
            mask = k < n - d
            first = k
        else:  # consecutive ids 0, d, 2d, ... < n: pair k is (k d, (k + 1) d) while (k + 1) d <= n - 1
            mask = k < (n - 1) // d
            first = k * d
        first = jnp.where(mask, first, 0)
        return first, jnp.where(mask, first + d, 0), mask

    dtype = poses.dtype
    limit = jnp.asarray(delta, dtype)
    limit = eqx.error_if(limit, ~(limit > 0), "rpe_pairs: delta must be positive")  # NaN too
    usable = valid[1:]
    if unit == "m":
        p = poses[:, :3, 3]
        diff = p[1:] - p[:-1]
        steps = safe_sqrt(jnp.sum(diff * diff, axis=-1))  # evo: np.linalg.norm of each step
        if not all_pairs:
            return _accumulate_and_reset(steps, usable, limit)
        # evo's filter_pairs_by_path(all_pairs): for each i < n - 1, j = argmin over j > i of
        # |(d_j - d_i) - delta| (the first on ties), kept when that is <= delta * rel_tol. d is the
        # accumulated path, non-decreasing, so the offsets are too: bisect instead of scanning all j.
        dist = jnp.concatenate([jnp.zeros(1, dtype), _cumsum_in_order(steps)])
        tol = limit * jnp.asarray(rel_tol, dtype)
        n_steps = int(n_frames).bit_length() + 1

        def offset(j):
            return (jnp.take(dist, j, mode="clip") - dist) - limit

        hi = _first_true(lambda j: offset(j) >= 0, k + 1, jnp.broadcast_to(n, k.shape), n_steps)
        has_hi = hi < n
        has_lo = hi - 1 >= k + 1
        v_hi = jnp.abs(offset(hi))
        v_below = offset(hi - 1)
        # the first j with the value of the last one below delta (stationary poses repeat it)
        lo = _first_true(lambda j: offset(j) >= v_below, k + 1, hi, n_steps)
        take_lo = has_lo & (~has_hi | (jnp.abs(v_below) <= v_hi))
        second = jnp.where(take_lo, lo, hi)
        miss = jnp.where(take_lo, jnp.abs(v_below), v_hi)
        mask = (k < n - 1) & (has_lo | has_hi) & (miss <= tol)
        return jnp.where(mask, k, 0), jnp.where(mask, second, 0), mask

    r = poses[:, :3, :3]
    steps = cast(
        Array, rotation_angle(jnp.swapaxes(r[:-1], -1, -2) @ r[1:])
    )  # evo: so3_log_angle(R_i^T R_i+1)
    return _accumulate_and_reset(steps, usable, jnp.deg2rad(limit) if unit == "d" else limit)


@functools.partial(jax.jit, static_argnames=("degrees", "rows_per_block"))
def rpe_angle_pairs(
    poses: Float[Array, "T 4 4"],
    valid: Bool[Array, " T"],
    delta: ArrayLike,
    *,
    degrees: bool,
    rel_tol: ArrayLike = 0.1,
    rows_per_block: int = 256,
) -> Bool[Array, "T T"]:
    """All pose pairs whose relative rotation is delta, within delta * rel_tol (evo's
    filter_pairs_by_angle with all_pairs): mask[i, j] for i < j.

    Arguments:
        poses: [T, 4, 4]; valid: [T] the poses (padding False).
        delta: the angle, degrees or radians after `degrees`, in [0, 180] / [0, pi].
        degrees: (static) delta is in degrees.
        rel_tol: the accepted |angle - delta| as a fraction of delta (evo_rpe --delta_tol).
        rows_per_block: (static) rows computed together (memory: rows x T quaternions).

    Returns:
        [T, T] bool; np.nonzero of it lists evo's pairs in evo's order.
    """
    _check_poses("poses", poses)
    n_frames = poses.shape[0]
    if valid.shape != (n_frames,):
        raise ValueError(f"valid must have shape ({n_frames},) like poses, got {tuple(valid.shape)}")
    dtype = poses.dtype
    delta = jnp.asarray(delta, dtype)
    tol = delta * jnp.asarray(rel_tol, dtype)
    if degrees:
        delta, tol = jnp.deg2rad(delta), jnp.deg2rad(tol)
    q = matrix_to_quat(nearest_rotation(poses[:, :3, :3]))  # evo: scipy's from_matrix projects too
    valid = valid.astype(bool)
    k = jnp.arange(n_frames)

    def row(args):
        qi, i, ok = args
        rel = quat_mul(quat_conj(qi)[None, :], q)  # evo: scipy's R_i^-1 * R_j, then |rotvec|
        s = safe_sqrt(jnp.sum(rel[:, 1:] * rel[:, 1:], axis=-1))
        angle = 2.0 * jnp.arctan2(s, jnp.abs(rel[:, 0]))
        return ok & valid & (k > i) & (delta - tol <= angle) & (angle <= delta + tol)

    return jax.lax.map(row, (q, k, valid), batch_size=min(rows_per_block, n_frames))


@jax.jit
def error_statistics(errors: Float[Array, " N"], mask: Bool[Array, " N"]) -> ErrorStats:
    """evo's statistics of errors (>= 0) over the masked entries: rmse, mean, median, std (population),
    min, max, sse, count, in the errors' unit (sse in its square); all 0 when none is masked."""
    if errors.ndim != 1 or mask.shape != errors.shape:
        raise ValueError(f"errors and mask must have one shape (N,), got {errors.shape} and {mask.shape}")
    return _error_statistics(errors, mask.astype(bool))
