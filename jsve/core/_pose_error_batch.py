"""Pose errors of many runs at once: APE and RPE over runs padded to one length, as evo defines them.

    batched_ape(est, ref, valid, ...)         each estimate aligned to its reference and scored (evo_ape)
    batched_pose_error(est, ref, valid, ...)  the same with the facts of a failed run (jsve.core._trajectory)
    batched_rpe(est, ref, valid, delta, ...)  each run's pose pairs delta apart and their errors (evo_rpe)

Each is one compiled program per configuration and shape over the single-run kernels of
jsve.core._pose_error (conventions, relations and alignments are described there);
jsve.io._trajectories.stack_pose_pairs pads the runs. Compute in float64 (`jax_enable_x64`) to match evo.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int

from jsve.core._align import Transform
from jsve.core._pose_error import (
    DELTA_UNITS,
    align_poses,
    check_relation,
    pose_errors,
    relative_pose_errors,
    rpe_angle_pairs,
    rpe_pairs,
)
from jsve.core._trajectory import (
    MIN_ALIGNMENT_FRAMES,
    ErrorStats,
    RunError,
    _error_statistics,
    failure_bits,
    non_finite,
    overflows,
)


class PoseErrorBatch(eqx.Module):
    """APE of R runs (`batched_ape`), every leaf with a leading axis R.

    Attributes:
        errors: the statistics in the relation's unit, with the facts `run_error` reports for a run that is
            one segment with every pose (coverage, failed, failure: see `batched_pose_error`).
        transforms: each estimate's alignment onto its reference.
        aligned: [R, T, 4, 4] the aligned estimates (padding as given).
        per_pose: [R, T] the error of each pose (meaningless on padding and on failed runs).
    """

    errors: RunError
    transforms: Transform
    aligned: Float[Array, "R T 4 4"]
    per_pose: Float[Array, "R T"]


class RelativeErrorBatch(eqx.Module):
    """RPE of R runs (`batched_rpe`), every leaf with a leading axis R.

    Attributes:
        stats: the statistics over each run's pairs, in the relation's unit.
        failed: no pair at this delta, a degenerate alignment or a statistic that is not finite.
        failure: why (bits of RPE_FAILURE_CAUSES; 0 when not failed).
        transforms: each estimate's alignment onto its reference (the identity for "none").
        aligned: [R, T, 4, 4] the aligned estimates.
        first, second, mask: [R, P] each run's pairs (i, j) where mask (evo's order within a run).
        per_pair: [R, P] the error of each pair.
    """

    stats: ErrorStats
    failed: Bool[Array, " R"]
    failure: Int[Array, " R"]
    transforms: Transform
    aligned: Float[Array, "R T 4 4"]
    first: Int[Array, "R P"]
    second: Int[Array, "R P"]
    mask: Bool[Array, "R P"]
    per_pair: Float[Array, "R P"]


def _check_batch(est, ref, valid) -> None:
    if est.ndim != 4 or est.shape[2:] != (4, 4) or ref.shape != est.shape or valid.shape != est.shape[:2]:
        raise ValueError(
            f"est and ref must have shape (R, T, 4, 4) and valid (R, T), got {tuple(est.shape)}, "
            f"{tuple(ref.shape)} and {tuple(valid.shape)}"
        )


@functools.partial(jax.jit, static_argnames=("method", "n_first", "relation"))
def _ape_kernel(est, ref, valid, *, method, n_first, relation):
    """`batched_ape` in one compiled program: each run aligned on its valid poses and scored there."""

    def one(e, r, m):
        aligned, transform = align_poses(e, r, m, method=method, n_first=n_first)
        per_pose = pose_errors(aligned, r, relation)
        return transform, aligned, per_pose, _error_statistics(per_pose, m & ~transform.degenerate)

    transforms, aligned, per_pose, stats = jax.vmap(one)(est, ref, valid)
    n_runs = est.shape[0]
    no = jnp.zeros(n_runs, bool)
    bad_input = jax.vmap(overflows)(est[..., :3, 3], valid) | jax.vmap(overflows)(ref[..., :3, 3], valid)
    failure = failure_bits(
        no, no, stats.count < MIN_ALIGNMENT_FRAMES, transforms.degenerate, non_finite(stats) | bad_input
    )
    errors = RunError(
        stats=stats,
        coverage=stats.count / jnp.sum(valid, axis=1),
        n_segments=jnp.ones(n_runs, jnp.int32),
        failed=failure != 0,
        segment=jnp.zeros(n_runs, jnp.int32),
        failure=failure,
    )
    return PoseErrorBatch(errors, transforms, aligned, per_pose)


def batched_ape(
    est: Float[ArrayLike, "R T 4 4"],
    ref: Float[ArrayLike, "R T 4 4"],
    valid: Bool[ArrayLike, "R T"],
    *,
    align: str = "se3",
    n_first: int | None = None,
    relation: str = "translation",
) -> PoseErrorBatch:
    """Align every estimate to its reference on its valid poses and take its APE there (evo_ape).

    Arguments:
        est: [R, T, 4, 4] estimated poses T_wb (rotation, translation in metres), estimate world frame.
        ref: [R, T, 4, 4] reference poses of the same frames, reference world frame.
        valid: [R, T] the pose exists (False on padding).
        align: a method of POSE_ALIGN_METHODS: "se3" (evo_ape -a), "sim3" (-a -s), "scale" (-s),
            "origin" (--align_origin), "posyaw", "none".
        n_first: align on the first n_first poses only (evo's --n_to_align); None: all.
        relation: a key of POSE_RELATIONS (evo_ape --pose_relation).

    Returns:
        PoseErrorBatch (one compiled program per configuration and shape). Precision follows JAX's:
        enable jax_enable_x64 for float64 (evo's).
    """
    check_relation(relation)
    est, ref, valid = jnp.asarray(est), jnp.asarray(ref), jnp.asarray(valid, bool)
    _check_batch(est, ref, valid)
    return _ape_kernel(est, ref, valid, method=align, n_first=n_first, relation=relation)


def batched_pose_error(
    est: Float[ArrayLike, "R T 4 4"],
    ref: Float[ArrayLike, "R T 4 4"],
    valid: Bool[ArrayLike, "R T"],
    *,
    align: str = "se3",
    n_first: int | None = None,
    relation: str = "translation",
) -> tuple[RunError, Transform]:
    """Align every estimate to its reference on its valid poses and score it there (`batched_ape`'s
    errors and transforms).

    Arguments:
        est, ref, valid, align, n_first, relation: as `batched_ape`.

    Returns:
        (errors, transforms), every leaf with a leading axis R. errors holds the APE statistics (metres
        for "translation") and the facts `run_error` reports for a run that is one segment with every
        pose: coverage = count / valid poses, n_segments 1, segment 0, failed = degenerate alignment, fewer
        than MIN_ALIGNMENT_FRAMES poses or a statistic that is not finite (causes in `failure`).
        transforms maps each estimate onto its reference.
    """
    result = batched_ape(est, ref, valid, align=align, n_first=n_first, relation=relation)
    return result.errors, result.transforms


def _score_pairs(est, ref, valid, aligned, transforms, first, second, mask, relation) -> RelativeErrorBatch:
    """Each run's pair errors, statistics and failure causes (`_rpe_scores`)."""
    mask = mask & ~transforms.degenerate[:, None]

    def one(e, r, i, j, m):
        per_pair = relative_pose_errors(e, r, i, j, relation)
        return per_pair, _error_statistics(per_pair, m)

    per_pair, stats = jax.vmap(one)(aligned, ref, first, second, mask)
    bad_input = jax.vmap(overflows)(est[..., :3, 3], valid) | jax.vmap(overflows)(ref[..., :3, 3], valid)
    no_pair = (stats.count == 0) & ~transforms.degenerate
    failure = (  # bits of RPE_FAILURE_CAUSES
        no_pair.astype(jnp.int32)
        | transforms.degenerate.astype(jnp.int32) << 1
        | (non_finite(stats) | bad_input).astype(jnp.int32) << 2
    )
    return RelativeErrorBatch(
        stats=stats,
        failed=failure != 0,
        failure=failure,
        transforms=transforms,
        aligned=aligned,
        first=first,
        second=second,
        mask=mask,
        per_pair=per_pair,
    )


def _align_runs(est, ref, valid, method, n_first):
    return jax.vmap(lambda e, r, m: align_poses(e, r, m, method=method, n_first=n_first))(est, ref, valid)


@functools.partial(jax.jit, static_argnames=("unit", "all_pairs", "from_reference", "method", "n_first"))
def _rpe_pairs(est, ref, valid, delta, rel_tol, *, unit, all_pairs, from_reference, method, n_first):
    """The aligned runs and the pairs `rpe_pairs` chooses (a slot per pose): one compiled program for
    every relation, which `_rpe_scores` then scores."""
    aligned, transforms = _align_runs(est, ref, valid, method, n_first)
    source = ref if from_reference else aligned
    first, second, mask = jax.vmap(
        lambda p, m: rpe_pairs(p, m, delta, unit=unit, all_pairs=all_pairs, rel_tol=rel_tol)
    )(source, valid)
    return aligned, transforms, first, second, mask


@functools.partial(jax.jit, static_argnames=("degrees", "from_reference", "method", "n_first"))
def _angle_pair_masks(est, ref, valid, delta, rel_tol, *, degrees, from_reference, method, n_first):
    """All pairs by angle: the aligned runs and each run's [T, T] mask (`rpe_angle_pairs`)."""
    aligned, transforms = _align_runs(est, ref, valid, method, n_first)
    source = ref if from_reference else aligned
    masks = jax.vmap(lambda p, m: rpe_angle_pairs(p, m, delta, degrees=degrees, rel_tol=rel_tol))(
        source, valid
    )
    return aligned, transforms, masks


_rpe_scores = jax.jit(_score_pairs, static_argnames=("relation",))


def _compact(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[R, T, T] pair masks as (first, second, mask) [R, P], P the most pairs of a run (at least 1), each
    run's pairs in np.nonzero's (evo's) order."""
    found = [np.nonzero(m) for m in masks]
    width = max(1, *(len(i) for i, _ in found))
    first = np.zeros((len(found), width), np.int32)
    second, mask = first.copy(), np.zeros((len(found), width), bool)
    for r, (i, j) in enumerate(found):
        first[r, : len(i)], second[r, : len(j)], mask[r, : len(i)] = i, j, True
    return first, second, mask


def check_delta(delta: float | int, unit: str, rel_tol: float | int = 0.1) -> None:
    """Refuse an RPE delta evo would refuse (or loop on): not a whole number >= 1 of frames, not positive,
    an angle beyond 180 degrees / pi radians; an unknown unit; a negative tolerance.

    Raises:
        ValueError: naming the argument and the value received.
    """
    if unit not in DELTA_UNITS:
        raise ValueError(f"unit must be one of {tuple(DELTA_UNITS)}, got {unit!r}")
    if unit == "f" and not (float(delta) >= 1 and float(delta).is_integer()):
        raise ValueError(f"delta must be a whole number of frames >= 1 for unit 'f', got {delta!r}")
    if not float(delta) > 0:
        raise ValueError(f"delta must be positive, got {delta!r}")
    bound = {"d": 180.0, "r": float(np.pi)}.get(unit)
    if bound is not None and float(delta) > bound:
        raise ValueError(f"delta must be an angle within (0, {bound:g}] for unit {unit!r}, got {delta!r}")
    if not float(rel_tol) >= 0:
        raise ValueError(f"rel_tol must be >= 0, got {rel_tol!r}")


def batched_rpe(
    est: Float[ArrayLike, "R T 4 4"],
    ref: Float[ArrayLike, "R T 4 4"],
    valid: Bool[ArrayLike, "R T"],
    *,
    delta: float | int = 1,
    unit: str = "f",
    all_pairs: bool = False,
    rel_tol: float | int = 0.1,
    pairs_from_reference: bool = False,
    relation: str = "translation",
    align: str = "none",
    n_first: int | None = None,
) -> RelativeErrorBatch:
    """The relative pose error of every estimate against its reference (evo_rpe).

    As evo_rpe: each estimate is aligned first (`align`, default none), the pose pairs are chosen on the
    aligned estimate (or on the reference with pairs_from_reference) by `rpe_pairs` / `rpe_angle_pairs`,
    and each pair's error is `relative_pose_errors`.

    Arguments:
        est, ref, valid: as `batched_ape` (valid a prefix of each run).
        delta: the pairs' distance: frames (a whole number >= 1), metres (> 0), degrees (0-180] or
            radians (0-pi], after unit (evo_rpe --delta, default 1).
        unit: a key of DELTA_UNITS (evo_rpe --delta_unit, default "f").
        all_pairs: every pair delta apart, not only consecutive ones (evo_rpe --all_pairs).
        rel_tol: all pairs by metres or angle: the accepted miss, a fraction of delta (--delta_tol, 0.1).
        pairs_from_reference: choose the pairs on the reference (evo_rpe --pairs_from_reference).
        relation: a key of POSE_RELATIONS (evo_rpe --pose_relation).
        align: a method of POSE_ALIGN_METHODS, as `batched_ape` (default "none", evo_rpe's).
        n_first: align on the first n_first poses only.

    Returns:
        RelativeErrorBatch. A run without a pair at this delta is failed (evo raises "empty index list").

    Raises:
        ValueError: a delta that is not a positive whole number of frames or an angle out of range, an
            unknown unit or relation.
    """
    check_relation(relation)
    check_delta(delta, unit, rel_tol)
    est, ref, valid = jnp.asarray(est), jnp.asarray(ref), jnp.asarray(valid, bool)
    _check_batch(est, ref, valid)
    if unit in ("d", "r") and all_pairs:  # a [T, T] mask per run, compacted on the host
        aligned, transforms, masks = _angle_pair_masks(
            est, ref, valid, delta, rel_tol, degrees=unit == "d", from_reference=pairs_from_reference,
            method=align, n_first=n_first,
        )  # fmt: skip
        first, second, mask = _compact(np.asarray(masks))
    else:
        aligned, transforms, first, second, mask = _rpe_pairs(
            est, ref, valid, delta, rel_tol, unit=unit, all_pairs=all_pairs,
            from_reference=pairs_from_reference, method=align, n_first=n_first,
        )  # fmt: skip
    return _rpe_scores(est, ref, valid, aligned, transforms, first, second, mask, relation=relation)
