"""Trajectory error: `align` (the methods of jsve.core._align), APE statistics, and per-run evaluation.

Pure JAX over arrays, one run per call; batch over runs with `jax.vmap` (or `batched_run_error`). The public
functions are jit-compiled (strings and counts are static arguments; a call outside jit compiles once per
configuration and shape instead of dispatching hundreds of small operations), work inside jit/vmap/grad
with static shapes, and the statistics are differentiable with respect to the estimated positions
(square roots, norms and the SVD are guarded with the double-`where` idiom of jsve.core._numerics, so
gradients stay finite even for degenerate input).

Conventions: positions are rows `(T, 3)` in metres, world frame; quaternions are wxyz (body in world, T_wb);
masks are boolean `(T,)`. The estimate is mapped onto the reference: `aligned = scale * R @ est + t`.

The statistics are evo's APE on the translation part (`evo.core.metrics.APE(PoseRelation.translation_part)`):
per-frame error `|| aligned_p - ref_p ||` in metres; rmse, mean, median, std (population, ddof = 0), min, max,
sse, count. evo is the correctness oracle (tests/test_trajectory.py, 1e-6 in float64).
"""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int

from jsve.core._align import (
    ALIGNERS,
    MIN_ALIGNMENT_FRAMES,
    AlignMethod,
    Transform,
    apply_columns,
    fit,
)
from jsve.core._geometry import columns
from jsve.core._numerics import safe_divide, safe_sqrt

SegmentMode = Literal["largest", "first", "all"]

SEGMENT_MODES: tuple[str, ...] = ("largest", "first", "all")
"""Which map segments of a run are evaluated (see `run_error`)."""


class ErrorStats(eqx.Module):
    """APE statistics of the translation part over the masked frames (evo's definitions), all scalars.

    Attributes:
        rmse, mean, median, std, min, max: metres; std is the population standard deviation (ddof = 0).
        sse: sum of squared errors, square metres.
        count: number of frames the statistics are taken over (int32).
    When count is 0 every statistic is 0 (finite, so that a batch and its gradient stay finite); the host-side
    table (`jsve.evaluation._aggregate.per_run_table`) turns them into NaN, and `run_error` marks such a run
    failed.
    """

    rmse: Float[Array, "*runs"]
    mean: Float[Array, "*runs"]
    median: Float[Array, "*runs"]
    std: Float[Array, "*runs"]
    min: Float[Array, "*runs"]
    max: Float[Array, "*runs"]
    sse: Float[Array, "*runs"]
    count: Int[Array, "*runs"]


FAILURE_CAUSES: tuple[str, ...] = (
    "several map segments",
    "coverage below min_coverage",
    f"fewer than {MIN_ALIGNMENT_FRAMES} evaluated frames",
    "degenerate alignment",
    "non-finite error statistics (a value overflowed or was NaN)",
)
"""Why a run failed: cause k sets bit k of RunError.failure (`failure_bits`, `failure_reason`)."""


def failure_bits(*causes: Array) -> Int[Array, "*runs"]:
    """RunError.failure from one bool per FAILURE_CAUSES entry, in that order."""
    if len(causes) != len(FAILURE_CAUSES):
        raise ValueError(f"failure_bits takes {len(FAILURE_CAUSES)} causes, got {len(causes)}")
    return sum(
        (jnp.asarray(c).astype(jnp.int32) << k for k, c in enumerate(causes)), jnp.zeros((), jnp.int32)
    )


def failure_reason(bits: ArrayLike, causes: tuple[str, ...] = FAILURE_CAUSES) -> str:
    """The causes set in RunError.failure, in words joined by '; ' ('' for a run that did not fail).

    Arguments:
        bits: the failure bits of one run.
        causes: what each bit means: FAILURE_CAUSES (APE), or jsve.core._pose_error.RPE_FAILURE_CAUSES.
    """
    value = int(bits)  # type: ignore[arg-type]  (a scalar: int, numpy or JAX)
    return "; ".join(cause for k, cause in enumerate(causes) if value >> k & 1)


def non_finite(stats: ErrorStats) -> Bool[Array, "*runs"]:
    """Whether any statistic is NaN or infinite: an overflow or a NaN upstream reached it (the safe
    functions of jsve.core._numerics pass it on), so the number means nothing."""
    values = (stats.rmse, stats.mean, stats.median, stats.std, stats.min, stats.max, stats.sse)
    return ~jnp.all(jnp.stack([jnp.isfinite(v) for v in values]), axis=0)


def overflows(points: Float[Array, "T 3"], mask: Bool[Array, " T"]) -> Bool[Array, ""]:
    """Whether a masked row is NaN or infinite, or so large that its square overflows the dtype (|x| above
    ~1.8e19 m in float32): the alignment's moments would be inf, and the run's error means nothing."""
    return jnp.any(mask & ~jnp.isfinite(jnp.sum(points * points, axis=-1)))


class RunError(eqx.Module):
    """Trajectory error of one replayed run, with the facts that say whether the error can be trusted.

    Attributes:
        stats: APE statistics over the evaluated frames (metres).
        coverage: evaluated frames / valid frames that have ground truth, in [0, 1]. The evaluated frames are
            the frames with an estimate and ground truth in the evaluated segment(s) whose alignment was
            possible.
        n_segments: number of distinct map segments among the frames with an estimate (int32); more than one
            means tracking was lost and a new map started.
        failed: True when n_segments > 1, coverage < min_coverage, fewer than 3 frames were evaluated, the
            alignment was degenerate, or a statistic is not finite (an overflow or a NaN reached it: never a
            number). Failure is never hidden behind a low error (evo issue #673).
        segment: the evaluated segment id (int32); -1 when segments="all".
        failure: why (int32 bits, one per FAILURE_CAUSES entry; `failure_reason` in words); 0 when not
            failed.
    """

    stats: ErrorStats
    coverage: Float[Array, "*runs"]
    n_segments: Int[Array, "*runs"]
    failed: Bool[Array, "*runs"]
    segment: Int[Array, "*runs"]
    failure: Int[Array, "*runs"]


# ----------------------------------------------------------------------------------------------------------
# Argument checks (trace time).


def _float_dtype(*arrays) -> jnp.dtype:
    return jnp.result_type(*(a.dtype for a in arrays if a is not None), jnp.float32)


def _check_points(name: str, x, n_frames: int | None = None, width: int = 3) -> None:
    if x.ndim != 2 or x.shape[1] != width:
        raise ValueError(f"{name} must have shape (T, {width}), got {tuple(x.shape)}")
    if n_frames is not None and x.shape[0] != n_frames:
        raise ValueError(f"{name} has {x.shape[0]} frames but est_p has {n_frames}")


def _check_mask(name: str, m, n_frames: int) -> None:
    if m.shape != (n_frames,):
        raise ValueError(f"{name} must have shape ({n_frames},) like est_p's frames, got {tuple(m.shape)}")


def _check_method(name: str, method) -> None:
    if method not in ALIGNERS:
        raise ValueError(f"{name} must be one of {tuple(ALIGNERS)}, got {method!r}")


def _check_orientations(name: str, method, est_q, ref_q) -> None:
    if ALIGNERS[method].first_pose and (est_q is None or ref_q is None):
        raise ValueError(f"{name}={method!r} needs est_q and ref_q (the first poses' orientations)")


def _check_n_first(n_first) -> None:
    if isinstance(n_first, bool) or (isinstance(n_first, int) and n_first < 1):
        raise ValueError(f"n_first must be a positive number of frames or None (all frames), got {n_first!r}")


# ----------------------------------------------------------------------------------------------------------
# Alignment.


def _as_weights(mask, dtype) -> Array:
    return mask.astype(dtype) if mask.dtype == jnp.bool_ else jnp.asarray(mask, dtype)


@functools.partial(jax.jit, static_argnames=("method", "n_first"))
def align(
    est_p: Float[Array, "T 3"],
    ref_p: Float[Array, "T 3"],
    mask: Bool[Array, " T"] | Float[Array, " T"],
    *,
    method: str,  # AlignMethod; an unknown name gets a ValueError naming the choices
    est_q: Float[Array, "T 4"] | None = None,
    ref_q: Float[Array, "T 4"] | None = None,
    n_first: int | None = None,
) -> tuple[Float[Array, "T 3"], Float[Array, "T 4"] | None, Transform]:
    """Align an estimated trajectory to a reference one on the masked frames.

    Arguments:
        est_p: [T, 3] estimated positions, metres, estimate world frame.
        ref_p: [T, 3] reference (ground-truth) positions of the same frames, metres, reference world frame.
        mask: [T] bool, the frames used for the alignment (frames with an estimate in the evaluated segment);
            nonnegative float weights give the weighted Umeyama estimate.
        method: (static) "se3" (rotation + translation), "sim3" (+ scale, for monocular), "posyaw" (yaw about
            the world z axis + translation, 4-DoF, the VIO convention of rpg_trajectory_evaluation), "origin"
            (maps the first masked estimated pose onto the first masked reference pose, like evo's
            align_origin; needs est_q and ref_q), or "none".
        est_q, ref_q: [T, 4] orientations (wxyz, body in world); est_q is also mapped when given.
        n_first: (static) use only the first n_first masked frames (evo's `n`); None uses them all.

    Returns:
        (aligned_p [T, 3] metres in the reference frame, aligned_q [T, 4] (None when est_q is None),
        transform). All frames are mapped, masked or not. Degenerate input (fewer than 3 masked frames, or all
        estimated or all reference points identical) gives the identity with `transform.degenerate` set,
        never NaN. Collinear points are not degenerate: the rotation about their line is arbitrary but moves
        none of them, so the errors are well defined (the gradient of an exactly collinear set may not be).
    """
    _check_method("method", method)
    _check_n_first(n_first)
    _check_points("est_p", est_p)
    n_frames = est_p.shape[0]
    _check_points("ref_p", ref_p, n_frames)
    _check_mask("mask", mask, n_frames)
    if est_q is not None:
        _check_points("est_q", est_q, n_frames, width=4)
    if ref_q is not None:
        _check_points("ref_q", ref_q, n_frames, width=4)
    _check_orientations("method", method, est_q, ref_q)

    dtype = _float_dtype(est_p, ref_p, est_q, ref_q)
    est_p, ref_p = est_p.astype(dtype), ref_p.astype(dtype)
    est_q = None if est_q is None else est_q.astype(dtype)
    ref_q = None if ref_q is None else ref_q.astype(dtype)
    transform = fit(est_p, ref_p, _as_weights(mask, dtype), method, est_q, ref_q, n_first)
    aligned_q = None if est_q is None else transform.apply_quat(est_q)
    return transform.apply(est_p), aligned_q, transform


# ----------------------------------------------------------------------------------------------------------
# Statistics.


def _squared_errors(aligned_cols, ref_cols) -> Float[Array, " T"]:
    """|| aligned - ref ||^2 per frame (square metres), from coordinate columns."""
    return sum((a - r) * (a - r) for a, r in zip(aligned_cols, ref_cols, strict=True))  # type: ignore[return-value]


def _position_errors(aligned_cols, ref_cols) -> Float[Array, " T"]:
    """|| aligned - ref || per frame (metres), from coordinate columns; 0 (with zero gradient) where equal."""
    return safe_sqrt(_squared_errors(aligned_cols, ref_cols))


def weighted_rmse(
    aligned_p: Float[Array, "T 3"], ref_p: Float[Array, "T 3"], weight: Float[Array, " T"]
) -> Float[Array, ""]:
    """Position RMSE over frames weighted by `weight` >= 0, metres; 0 when every weight is 0.

    sqrt(sum_i w_i |aligned_i - ref_i|^2 / sum_i w_i): the objective's RMSE, where the weights are the
    probabilities that frames have an estimate (0/1 in the hard replay, where it is `ape_statistics`' rmse
    up to rounding: that one squares each frame's error norm).
    """
    sq = _squared_errors(columns(aligned_p), columns(ref_p))
    return safe_sqrt(safe_divide(jnp.sum(weight * sq), jnp.sum(weight)))


_BITS_OF_FLOAT = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}


def _masked_median(
    err: Float[Array, " T"], mask: Bool[Array, " T"], count: Int[Array, ""]
) -> Float[Array, ""]:
    """numpy.median of err[mask] for err >= 0, without sorting (XLA's sort is the slowest step on CPU).

    The lower middle value (rank (count - 1) // 2) is found by bisection on the floats' bit patterns, which
    order non-negative floats exactly like their values: one count per bit, exact, static trip count. The
    upper middle value (rank count // 2) is either the same value or the next larger masked one. Both are
    then read back from `err` where it equals them, so the gradient reaches the middle element(s) as it
    would through a sort (tied elements share it).
    """
    int_type = _BITS_OF_FLOAT[err.dtype.itemsize]
    frozen = jax.lax.stop_gradient(err)
    candidates = jnp.where(mask, frozen, jnp.inf)  # unmasked frames never count as "at or below"
    bits = jax.lax.bitcast_convert_type(frozen, int_type)
    rank_lo = jnp.maximum((count - 1) // 2, 0)

    def halve(_, bounds):
        lo, hi = bounds
        mid = lo + (hi - lo) // 2
        at_or_below = jnp.sum(candidates <= jax.lax.bitcast_convert_type(mid, err.dtype), dtype=jnp.float32)
        enough = at_or_below > rank_lo  # counts up to 2^24 frames are exact in float32
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    start = (jnp.zeros((), int_type), jnp.max(jnp.where(mask, bits, 0)))
    _, lower_bits = jax.lax.fori_loop(0, 8 * err.dtype.itemsize, halve, start)
    lower = jax.lax.bitcast_convert_type(lower_bits, err.dtype)
    upper_is_same = jnp.sum(candidates <= lower, dtype=jnp.int32) > count // 2
    upper = jnp.where(upper_is_same, lower, jnp.min(jnp.where(candidates > lower, candidates, jnp.inf)))

    def pick(value):
        # The masked element(s) equal to `value`, as a differentiable average (ties share the gradient).
        hit = candidates == value
        return jnp.sum(jnp.where(hit, err, 0.0)) / jnp.maximum(jnp.sum(hit, dtype=err.dtype), 1.0)

    return jnp.where(count > 0, 0.5 * (pick(lower) + pick(upper)), 0.0)


def _error_statistics(err: Float[Array, " T"], mask: Bool[Array, " T"]) -> ErrorStats:
    """evo's APE statistics of the per-frame errors (metres, >= 0) over the masked frames."""
    dtype = err.dtype
    err = jnp.where(mask, err, 0.0)
    count = jnp.sum(mask, dtype=jnp.int32)
    n = count.astype(dtype)
    any_frame = count > 0
    sse = jnp.sum(err * err)
    mean = safe_divide(jnp.sum(err), n)
    dev = jnp.where(mask, err - mean, 0.0)
    std = safe_sqrt(safe_divide(jnp.sum(dev * dev), n))  # two-pass, like numpy.std
    rmse = safe_sqrt(safe_divide(sse, n))
    median = _masked_median(err, mask, count)
    minimum = jnp.where(any_frame, jnp.min(jnp.where(mask, err, jnp.inf)), 0.0)
    maximum = jnp.where(any_frame, jnp.max(jnp.where(mask, err, -jnp.inf)), 0.0)
    return ErrorStats(
        rmse=rmse, mean=mean, median=median, std=std, min=minimum, max=maximum, sse=sse, count=count
    )


@jax.jit
def ape_statistics(
    aligned_p: Float[Array, "T 3"], ref_p: Float[Array, "T 3"], mask: Bool[Array, " T"]
) -> ErrorStats:
    """APE statistics (translation part, metres) over the masked frames, as evo defines them.

    Arguments:
        aligned_p: [T, 3] aligned estimated positions, metres, reference world frame.
        ref_p: [T, 3] reference positions, metres, reference world frame.
        mask: [T] bool, the frames to take the statistics over.

    Returns:
        ErrorStats: rmse = sqrt(sse / count), mean, median (numpy's: the average of the two middle values for
        an even count), std (population, ddof = 0), min, max, sse = sum of squared errors, count. All 0 when
        no frame is masked.
    """
    _check_points("aligned_p", aligned_p)
    n_frames = aligned_p.shape[0]
    _check_points("ref_p", ref_p, n_frames)
    _check_mask("mask", mask, n_frames)
    dtype = _float_dtype(aligned_p, ref_p)
    err = _position_errors(columns(aligned_p.astype(dtype)), columns(ref_p.astype(dtype)))
    return _error_statistics(err, mask.astype(bool))


# ----------------------------------------------------------------------------------------------------------
# One replayed run.


@functools.partial(
    jax.jit, static_argnames=("align", "n_first", "segments", "max_segments", "check_segments")
)
def run_error(
    est_p: Float[Array, "T 3"],
    est_q: Float[Array, "T 4"] | None,
    has_estimate: Bool[Array, " T"],
    segment: Int[Array, " T"],
    ref_p: Float[Array, "T 3"],
    ref_q: Float[Array, "T 4"] | None,
    ref_valid: Bool[Array, " T"],
    valid: Bool[Array, " T"],
    *,
    align: AlignMethod = "se3",
    n_first: int | None = None,
    segments: str = "largest",  # SegmentMode; checked here with a message naming the choices
    min_coverage: float | Float[Array, ""] = 0.0,
    max_segments: int = 8,
    check_segments: bool = True,
) -> RunError:
    """Align and score one replayed run, reporting coverage, segments and failure next to the error.

    A frame can be evaluated when it is inside the run (`valid`), has an estimate and has ground truth.

    Arguments:
        est_p, est_q: [T, 3] estimated positions (metres) and [T, 4] orientations (wxyz) in the estimate's
            world frame; est_q may be None unless align="origin".
        has_estimate: [T] the replay produced a pose for the frame.
        segment: [T] int, the map segment of each frame from the replay (a new map after LOST starts a new
            segment). Ids of frames with an estimate must lie in [0, T); other frames' ids are ignored.
        ref_p, ref_q: [T, 3] / [T, 4] ground truth for the same frames, reference world frame.
        ref_valid: [T] ground truth is available for the frame.
        valid: [T] the frame exists (False on padding).
        align: (static) alignment method, see `align`; each evaluated segment is aligned on its own frames.
        n_first: (static) align on the first n_first evaluated frames of each segment only (None: all).
        segments: (static) "largest": the segment with most evaluable frames (ties: the smallest id);
            "first": the segment of the first evaluable frame; "all": every segment aligned on its own and the
            errors pooled (the `max_segments` largest segments; frames of further segments are not evaluated).
        min_coverage: runs whose coverage is below this fraction are failed.
        max_segments: (static) how many segments segments="all" aligns.
        check_segments: (static) raise when a frame with an estimate has a segment id outside [0, T).
            The check is a host callback, which keeps the computation out of JAX's persistent cache;
            jsve.evaluation leaves it out for the replay's own ids, valid by construction.

    Returns:
        RunError: statistics over the evaluated frames, coverage = evaluated frames / valid frames with ground
        truth, n_segments (distinct segments among frames with an estimate) and failed = n_segments > 1
        or coverage < min_coverage or fewer than 3 evaluated frames or a degenerate alignment or a
        statistic that is not finite, with the causes in `failure`. Frames of a segment whose alignment
        is degenerate are not evaluated.
    """
    _check_method("align", align)
    _check_n_first(n_first)
    if segments not in SEGMENT_MODES:
        raise ValueError(f"segments must be one of {SEGMENT_MODES}, got {segments!r}")
    if isinstance(max_segments, bool) or not isinstance(max_segments, int) or max_segments < 1:
        raise ValueError(f"max_segments must be a positive int (static), got {max_segments!r}")
    _check_points("est_p", est_p)
    n_frames = est_p.shape[0]
    _check_points("ref_p", ref_p, n_frames)
    for name, m in (
        ("has_estimate", has_estimate),
        ("segment", segment),
        ("ref_valid", ref_valid),
        ("valid", valid),
    ):
        _check_mask(name, m, n_frames)
    if est_q is not None:
        _check_points("est_q", est_q, n_frames, width=4)
    if ref_q is not None:
        _check_points("ref_q", ref_q, n_frames, width=4)
    _check_orientations("align", align, est_q, ref_q)

    dtype = _float_dtype(est_p, ref_p, est_q, ref_q)
    est_p, ref_p = est_p.astype(dtype), ref_p.astype(dtype)
    est_q = None if est_q is None else est_q.astype(dtype)
    ref_q = None if ref_q is None else ref_q.astype(dtype)
    valid = valid.astype(bool)
    estimated = has_estimate.astype(bool) & valid
    with_gt = ref_valid.astype(bool) & valid
    evaluable = estimated & with_gt

    segment = segment.astype(jnp.int32)
    bad_id = estimated & ((segment < 0) | (segment >= n_frames))
    if check_segments:
        segment = eqx.error_if(
            segment, jnp.any(bad_id), "run_error: segment ids of frames with an estimate must lie in [0, T)"
        )
    # Per-segment frame counts (ids index a length-T table; out-of-range ids of frames without estimate drop).
    counts = (
        jnp.zeros((n_frames, 2), jnp.int32)
        .at[segment]
        .add(jnp.stack([estimated, evaluable], axis=-1).astype(jnp.int32), mode="drop")
    )
    n_segments = jnp.sum(counts[:, 0] > 0, dtype=jnp.int32)
    eval_counts = counts[:, 1]

    if segments == "all":
        k = min(max_segments, n_frames)
        _, ids = jax.lax.top_k(eval_counts, k)  # the k segments with most evaluable frames
        masks = evaluable[None, :] & (segment[None, :] == ids[:, None])  # [k, T]
        fit_each = jax.vmap(lambda m: fit(est_p, ref_p, m.astype(dtype), align, est_q, ref_q, n_first))
        transforms = fit_each(masks)
        usable = masks & ~transforms.degenerate[:, None]
        evaluated = jnp.any(usable, axis=0)
        # Each frame's segment among the k (0 where none: such frames are not evaluated).
        which = jnp.argmax(masks, axis=0)
        per_frame = jax.tree_util.tree_map(lambda leaf: leaf[which], transforms)
        aligned_cols = apply_columns(per_frame, columns(est_p))
        chosen = jnp.array(-1, jnp.int32)
        degenerate = jnp.zeros((), bool)
        scored = jnp.any(masks, axis=0)
    else:
        if segments == "largest":
            chosen = jnp.argmax(eval_counts).astype(jnp.int32)
        else:
            chosen = segment[jnp.argmax(evaluable)]
        selected = evaluable & (segment == chosen)
        transform = fit(est_p, ref_p, selected.astype(dtype), align, est_q, ref_q, n_first)
        aligned_cols = apply_columns(transform, columns(est_p))
        degenerate = transform.degenerate
        evaluated = selected & ~degenerate
        scored = selected

    stats = _error_statistics(_position_errors(aligned_cols, columns(ref_p)), evaluated)
    coverage = safe_divide(stats.count.astype(dtype), jnp.sum(with_gt).astype(dtype))
    # A non-finite or overflowing input makes the alignment degenerate (inf moments) or NaN: named as such.
    bad_input = overflows(est_p, scored) | overflows(ref_p, scored)
    failure = failure_bits(
        n_segments > 1,
        coverage < min_coverage,
        stats.count < MIN_ALIGNMENT_FRAMES,
        degenerate,
        non_finite(stats) | bad_input,
    )
    return RunError(
        stats=stats,
        coverage=coverage,
        n_segments=n_segments,
        failed=failure != 0,
        segment=chosen,
        failure=failure,
    )


RUNS_PER_BLOCK = 32
"""Runs evaluated together inside `batched_run_error`: blocks this size keep each pass over the frames in
cache, where one vmap over every run does not (benchmarks/bench_ape.py)."""


@functools.partial(
    jax.jit,
    static_argnames=("align", "n_first", "segments", "max_segments", "runs_per_block", "check_segments"),
)
def batched_run_error(
    est_p: Float[Array, "R T 3"],
    est_q: Float[Array, "R T 4"] | None,
    has_estimate: Bool[Array, "R T"],
    segment: Int[Array, "R T"],
    ref_p: Float[Array, "R T 3"],
    ref_q: Float[Array, "R T 4"] | None,
    ref_valid: Bool[Array, "R T"],
    valid: Bool[Array, "R T"],
    *,
    align: AlignMethod = "se3",
    n_first: int | None = None,
    segments: str = "largest",  # SegmentMode; checked here with a message naming the choices
    min_coverage: float | Float[Array, ""] = 0.0,
    max_segments: int = 8,
    runs_per_block: int = RUNS_PER_BLOCK,
    check_segments: bool = True,
) -> RunError:
    """`run_error` over a leading runs axis R (jit-compiled); every leaf of the result has shape [R].

    Equal to `jax.vmap(run_error)`; runs are evaluated in vmapped blocks of `runs_per_block` (static), one
    block after another, for cache locality. min_coverage is shared by all runs; the other keywords are
    static (each value compiles once); check_segments: see `run_error`.
    """
    if est_p.ndim != 3:
        raise ValueError(f"est_p must have shape (R, T, 3), got {tuple(est_p.shape)}")

    def kernel(args):
        ep, eq, he, sg, rp, rq, rv, va = args
        return run_error(
            ep, eq, he, sg, rp, rq, rv, va,
            align=align, n_first=n_first, segments=segments, min_coverage=min_coverage,
            max_segments=max_segments, check_segments=check_segments,
        )  # fmt: skip

    args = (est_p, est_q, has_estimate, segment, ref_p, ref_q, ref_valid, valid)
    if est_p.shape[0] <= runs_per_block:
        return jax.vmap(kernel)(args)
    return jax.lax.map(kernel, args, batch_size=runs_per_block)
