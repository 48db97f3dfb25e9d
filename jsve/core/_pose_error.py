"""APE of many estimated trajectories against their references at once, from padded pose arrays.

The one home of scoring pose pairs (an estimate and its reference, associated pose by pose), as `jsve ape`
and Table I (jsve.masks._table_one) do: the runs are padded to one length (padding masked out), so that one
compiled kernel aligns (`align`) and scores (`ape_statistics`, evo's APE of the translation part) every
run. jsve.io._trajectories reads the pairs and pads them (`stack_pose_pairs`). Compute in float64
(`jax_enable_x64`) to match evo to 1e-6.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Bool, Float

from jsve.core._geometry import matrix_to_quat
from jsve.core._trajectory import (
    MIN_ALIGNMENT_FRAMES,
    RunError,
    Transform,
    align,
    ape_statistics,
    failure_bits,
    non_finite,
    overflows,
)


@functools.partial(jax.jit, static_argnames=("method", "n_first"))
def _align_and_score(est_p, ref_p, valid, est_q, ref_q, *, method, n_first):
    """Over a leading runs axis: each run aligned on its valid poses and scored on them (one compile)."""

    def one(e, r, m, eq, rq):
        aligned_p, _, transform = align(e, r, m, method=method, est_q=eq, ref_q=rq, n_first=n_first)
        return transform, ape_statistics(aligned_p, r, m & ~transform.degenerate)

    return jax.vmap(one)(est_p, ref_p, valid, est_q, ref_q)


def batched_pose_error(
    est: Float[ArrayLike, "R T 4 4"],
    ref: Float[ArrayLike, "R T 4 4"],
    valid: Bool[ArrayLike, "R T"],
    *,
    align: str = "se3",
    n_first: int | None = None,
) -> tuple[RunError, Transform]:
    """Align every estimate to its reference on its valid poses and score it there.

    Arguments:
        est: [R, T, 4, 4] estimated poses T_wb (rotation, translation in metres), estimate world frame.
        ref: [R, T, 4, 4] reference poses of the same frames, reference world frame.
        valid: [R, T] the pose exists (False on padding).
        align: "se3" (evo_ape --align), "sim3" (--align --correct_scale), "posyaw", "origin", "none"
            (jsve.core._trajectory.ALIGN_METHODS).
        n_first: align on the first n_first poses only (evo's --n_to_align); None: all.

    Returns:
        (errors, transforms), every leaf with a leading axis R. errors holds the APE statistics (metres)
        and the facts `run_error` reports for a run that is one segment with every pose: coverage =
        count / valid poses, n_segments 1, segment 0, failed = degenerate alignment, fewer than
        MIN_ALIGNMENT_FRAMES poses or a statistic that is not finite (causes in `failure`). transforms
        maps each estimate onto its reference. Precision follows JAX's: enable jax_enable_x64 for
        float64 (evo's).
    """
    est, ref, valid = jnp.asarray(est), jnp.asarray(ref), jnp.asarray(valid, bool)
    if est.ndim != 4 or est.shape[2:] != (4, 4) or ref.shape != est.shape or valid.shape != est.shape[:2]:
        raise ValueError(
            f"est and ref must have shape (R, T, 4, 4) and valid (R, T), got {tuple(est.shape)}, "
            f"{tuple(ref.shape)} and {tuple(valid.shape)}"
        )
    transforms, stats = _align_and_score(
        est[..., :3, 3],
        ref[..., :3, 3],
        valid,
        matrix_to_quat(est[..., :3, :3]),
        matrix_to_quat(ref[..., :3, :3]),
        method=align,
        n_first=n_first,
    )
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
    return errors, transforms
