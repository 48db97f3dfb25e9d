"""Position-error objectives of a switching rule over a LogBatch, hard and relaxed.

The objective is the mean over runs of a per-run loss on the trajectory the front-end saves
(jsve.core._replay: ReplayResult.in_trajectory; docs/state-machine.md, "Scoring a run"): the run's ATE
RMSE (metres, after alignment to ground truth), capped at a configurable penalty, which a failed run
costs. Failed runs are never dropped: a rule that loses tracking on a hard run must not score better
than one that keeps it (evo issue #673). Runs can be weighted, e.g. so that every sequence, disturbance
and level counts equally (`group_weights`), and the weighted coverage and failure rate come with every
value.

    loss_r = failure_penalty              if run r failed
           = min(RMSE_r, failure_penalty) otherwise (loss="bounded", the default; "raw": RMSE_r)
    J = sum_r w_r loss_r / sum_r w_r

A run fails as the field counts failures (failure="coverage", the default): its saved trajectory covers
less than `min_coverage` of the frames with ground truth (none at all included), its alignment was
degenerate, fewer than 3 frames were evaluated, or its RMSE is not finite (an overflow or a NaN reached
it: `RunLoss.non_finite`; it costs the penalty, never a number). Resets, new maps and merges are events,
not failures. failure="strict" also fails every run that lost tracking once (a reset, an expiry or a
recorded map loss). The hard objective
is exactly mean(loss) of `jsve.evaluation._evaluate`'s per-run table (tests/test_objective.py).

The bounded loss makes a diverged run cost what a failed one costs: without the cap one run tracked
metres off outweighs dozens of centimetre runs, and comparisons of rules lose their power
(docs/validation.md).

Support (docs/state-machine.md): a run whose replay needs the recorded pose of a frame the recorded run
did not pose (the rule kept tracking where the recorded run had lost its map) has left the log's
support: what that run would have done is unknown. Such a run is never scored as a good one. Under
`support="penalise"` (the default) it counts as failed and costs the penalty; under `support="exclude"`
it also carries the penalty as its loss but weighs nothing: the run-rule pair leaves the mean, and
`ObjectiveValue.excluded` says how much weight was dropped (the remaining runs differ from rule to rule,
so compare rules under "exclude" only on the runs every one of them supports; jsve.fitting does).
Should every run of a rule be excluded, its value is that of "penalise" (the penalty): a rule
supported by no run has no evidence for it.

    unsupported_r = any frame of run r out of support
    loss_r  = failure_penalty              if run r failed or unsupported_r
    w'_r    = w_r (penalise),  w_r (1 - unsupported_r) (exclude)
    J       = sum_r w'_r loss_r / sum_r w'_r

Relaxed (SoftLogic with a temperature): the replay's flags are probabilities. The loss is the expected one,
P(ever LOST) x penalty + (1 - P) x RMSE, with the RMSE taken over frames weighted by the probability that
they have an estimate (a weighted Umeyama alignment, a smooth statistic). P(unsupported) is the largest
per-frame probability of being out of support (exact when the out-of-support mass is one mass, as where
the recorded run lost its map; a lower bound otherwise); failure, loss of tracking and leaving the support
combine as independent events. As the temperature falls every probability tends to its hard 0/1 value
and the relaxed objective to the hard one.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jsve.core._align import ALIGNERS, MIN_ALIGNMENT_FRAMES
from jsve.core._batch import LogBatch
from jsve.core._machine import TIME_RECENTLY_LOST_S, HardLogic, check_switch_model
from jsve.core._numerics import safe_divide
from jsve.core._replay import ReplayResult, batch_features, replay
from jsve.core._rules import Rule
from jsve.core._sve import FrameFeatures
from jsve.core._trajectory import align, weighted_rmse

DEFAULT_FAILURE_PENALTY_M = 1.0
"""Metres charged for a failed run. A VI-SLAM run on EuRoC-sized scenes that keeps tracking stays well
below it (ORB-SLAM3's EuRoC ATE is centimetres); a run that reaches LOST costs more than any run that
keeps tracking with a plausible error. Configurable: it sets the exchange rate between failures and
metres of error, which is a choice the user owns (docs/fitting.md)."""

DEFAULT_MIN_COVERAGE = 0.5
"""Share of the frames with ground truth the saved trajectory must cover for a run to count as tracked.
ORB-SLAM3's paper (Campos et al. 2021, Table II) counts a run as successful when the system completes
the sequence, with the error "for all the frames in the trajectory", and ORB-SLAM (Mur-Artal et al.
2015) marks a failure where "a significant portion of the sequence is not processed"; neither states a
share, and both count the frames before initialisation as processed. Half is jsve's choice within that
practice: a run that starts its map late (EuRoC's machine-hall sequences start at rest, and ORB-SLAM3
resets until the IMU is excited) still counts, one that loses its map for most of the sequence fails."""

FAILURE_DEFINITIONS = ("coverage", "strict")
"""What fails a run: "coverage" (default; the module docstring), or "strict", which also fails every
run that lost tracking once (a reset, an expiry, a recorded map loss)."""

LOSSES = ("bounded", "raw")
"""A tracked run's loss: "bounded" (default) min(RMSE, failure_penalty), "raw" its RMSE."""

SUPPORT_POLICIES = ("penalise", "exclude")
"""What the objective does with a run whose replay leaves the log's support (see the module docstring):
"penalise" (default) scores it as failed; "exclude" drops the run-rule pair from the mean."""


def check_loss(loss: str) -> str:
    """`loss` if it is one of LOSSES, else a ValueError naming the choices."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    return loss


def check_support(support: str) -> str:
    """`support` if it is one of SUPPORT_POLICIES, else a ValueError naming the choices."""
    if support not in SUPPORT_POLICIES:
        raise ValueError(f"support must be one of {SUPPORT_POLICIES}, got {support!r}")
    return support


class ObjectiveConfig(eqx.Module):
    """How runs are scored (all static: a new value compiles once).

    Attributes:
        failure_penalty: metres charged for a failed run.
        align: alignment before the RMSE, a method of jsve.core._align.ALIGNERS: "se3" (default), "sim3",
            "posyaw", "origin", "none".
        min_coverage: runs whose coverage (saved frames / frames with ground truth) is below it fail.
        failure: FAILURE_DEFINITIONS: "coverage" (default) or "strict".
        loss: LOSSES: "bounded" (default, a tracked run costs at most the penalty) or "raw".
        time_recently_lost: s in RECENTLY_LOST before LOST (ORB-SLAM3: 5).
        switch_model: the pose of a frame in RECENTLY_LOST, "orbslam3" (the logged pose, default) or
            "imu-coast" (IMU prediction); see docs/state-machine.md.
        support: a run whose replay leaves the log's support (needs a recorded pose that does not
            exist) has an unknown outcome: "penalise" (default) scores it as failed, "exclude" drops
            it from the mean (SUPPORT_POLICIES; the module docstring).
    """

    failure_penalty: float = eqx.field(static=True, default=DEFAULT_FAILURE_PENALTY_M)
    align: str = eqx.field(static=True, default="se3")
    min_coverage: float = eqx.field(static=True, default=DEFAULT_MIN_COVERAGE)
    failure: str = eqx.field(static=True, default="coverage")
    loss: str = eqx.field(static=True, default="bounded")
    time_recently_lost: float = eqx.field(static=True, default=TIME_RECENTLY_LOST_S)
    switch_model: str = eqx.field(static=True, default="orbslam3")
    support: str = eqx.field(static=True, default="penalise")

    def __check_init__(self):
        check_switch_model(self.switch_model)
        check_support(self.support)
        if not (np.isfinite(self.failure_penalty) and self.failure_penalty >= 0):
            raise ValueError(
                f"failure_penalty must be a finite number of metres >= 0, got {self.failure_penalty}"
            )
        if self.align not in ALIGNERS:
            raise ValueError(f"align must be one of {tuple(ALIGNERS)}, got {self.align!r}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must lie in [0, 1], got {self.min_coverage}")
        if self.failure not in FAILURE_DEFINITIONS:
            raise ValueError(f"failure must be one of {FAILURE_DEFINITIONS}, got {self.failure!r}")
        check_loss(self.loss)


def tracked_loss(rmse, config: ObjectiveConfig):
    """The loss of a run that did not fail (metres): min(rmse, penalty) under loss="bounded", else rmse.
    The one home of the cap: the replay objective, the search kernel and the per-run tables use it."""
    if config.loss == "bounded":
        return jnp.minimum(rmse, jnp.asarray(config.failure_penalty, jnp.result_type(rmse)))
    return rmse


class RunLoss(eqx.Module):
    """Per-run loss and the facts behind it (leaves [R], or scalars for one run inside the vmapped
    kernel; probabilities where relaxed).

    Attributes:
        loss: metres; failure_penalty where failed, else tracked_loss(rmse).
        rmse: ATE RMSE over the saved trajectory, metres (also for failed runs, for reference).
        failed: the run failed (bool), or its probability of failing (relaxed); a run out of support
            counts as failed under both policies.
        coverage: frames of the saved trajectory with ground truth / valid frames with ground truth.
        unsupported: the replay left the log's support on some frame (bool; relaxed: the largest
            per-frame probability).
        included: the run counts in the objective: 1 under "penalise", 1 - unsupported under "exclude"
            (a float in [0, 1], multiplying the run's weight).
        non_finite: the RMSE is NaN or infinite (an overflow or a NaN upstream): the run failed for
            that reason (bool, in both modes), whatever its other facts; rmse keeps the value.
    """

    loss: Float[Array, "*R"]
    rmse: Float[Array, "*R"]
    failed: Array
    coverage: Float[Array, "*R"]
    unsupported: Array
    included: Float[Array, "*R"]
    non_finite: Bool[Array, "*R"]


class ObjectiveValue(eqx.Module):
    """A weighted objective with its diagnostics (scalars).

    Attributes:
        value: sum_r w'_r loss_r / sum_r w'_r, metres, over the included runs (w' = w x included).
        coverage: weighted mean coverage. failure_rate: weighted mean of failed (both over the
            included runs).
        rmse_ok: weighted mean RMSE of the included runs that did not fail (NaN-free: 0 when all failed).
        unsupported_rate: weighted share of all runs whose replay left the log's support.
        excluded: weighted share of all runs dropped from the mean (0 under "penalise").
    """

    value: Float[Array, ""]
    coverage: Float[Array, ""]
    failure_rate: Float[Array, ""]
    rmse_ok: Float[Array, ""]
    unsupported_rate: Float[Array, ""]
    excluded: Float[Array, ""]


def support_outcome(unsupported, failed, config: ObjectiveConfig, hard: bool):
    """(failed, included) of runs once the support policy applies ([R] or [S, R] flags, or probabilities
    when not `hard`): an unsupported run counts as failed; under "exclude" it is also left out.

    The one home of the policy: the replay objective (`run_losses`) and the search kernel
    (jsve.fitting._kernel) both call it.
    """
    if hard:
        failed = failed | unsupported
        included = jnp.ones(failed.shape, bool) if config.support == "penalise" else ~unsupported
        return failed, included
    failed = 1 - (1 - failed) * (1 - unsupported)
    included = jnp.ones_like(failed) if config.support == "penalise" else 1 - unsupported
    return failed, included


def _one_run_loss(
    est_p, est_q, has_estimate, out_of_support, lost_any, gt_p, gt_q, gt_valid, valid, config, hard
):
    """Loss of one replayed run ([T, ...] arrays; has_estimate (the frames of the saved trajectory),
    out_of_support and lost_any are flags or probabilities)."""
    dtype = est_p.dtype
    with_gt = (gt_valid & valid).astype(dtype)
    weight = has_estimate.astype(dtype) * with_gt
    # Hard: a boolean mask, as jsve.evaluation._evaluate aligns; relaxed: the probability weights
    # (weighted Umeyama).
    mask = weight > 0.5 if hard else weight
    aligned, _, transform = align(est_p, gt_p, mask, method=config.align, est_q=est_q, ref_q=gt_q)
    weight = mask.astype(dtype)
    rmse = weighted_rmse(aligned, gt_p, weight)
    count = jnp.sum(weight)
    coverage = safe_divide(count, jnp.sum(with_gt))
    # Data facts, exact in both modes (their probability is 0 or 1). An RMSE that is not finite (an
    # overflow or a NaN reached it) means nothing: the run fails, as run_error fails it.
    non_finite = ~jnp.isfinite(rmse)
    broken = (
        transform.degenerate | (count < MIN_ALIGNMENT_FRAMES) | (coverage < config.min_coverage) | non_finite
    )
    strict = config.failure == "strict"
    if hard:
        unsupported = jnp.any(out_of_support & valid)
        lost = (lost_any > 0.5) if strict else jnp.zeros((), bool)
        failed, included = support_outcome(unsupported, broken | lost, config, hard)
        loss = jnp.where(failed, jnp.asarray(config.failure_penalty, dtype), tracked_loss(rmse, config))
        included = included.astype(dtype)
    else:
        # (the replay's out_of_support is 0 on padding frames already)
        unsupported = jnp.max(out_of_support.astype(dtype), initial=0.0)
        lost = lost_any.astype(dtype) if strict else 0.0
        failed = 1 - (1 - lost) * (1 - broken.astype(dtype))
        failed, included = support_outcome(unsupported, failed, config, hard)
        # failed is 1 where the RMSE is not finite; 0 x NaN would still be NaN.
        loss = failed * config.failure_penalty + (1 - failed) * tracked_loss(
            jnp.where(non_finite, 0.0, rmse), config
        )
    return RunLoss(
        loss=loss,
        rmse=rmse,
        failed=failed,
        coverage=coverage,
        unsupported=unsupported,
        included=included,
        non_finite=non_finite,
    )


def run_losses(
    batch: LogBatch,
    rule: Rule,
    features: FrameFeatures | None = None,
    config: ObjectiveConfig = ObjectiveConfig(),  # noqa: B008 - an immutable module of static fields
    *,
    logic=None,
) -> RunLoss:
    """Replay `rule` over every run of `batch` and score each run (jit at the call site).

    Arguments:
        batch: the logs, with ground truth. rule: any jsve rule. features: the batch's FrameFeatures
            (computed when omitted). config: penalty, alignment, coverage floor.
        logic: HardLogic() (default: the real machine) or SoftLogic(temperature) for the relaxation.
    Returns:
        RunLoss with [R] leaves (padding runs score 0 coverage and fail; give them weight 0).
    """
    logic = HardLogic() if logic is None else logic
    hard = isinstance(logic, HardLogic)
    if features is None:
        features = batch_features(batch)
    result = replay(batch, rule, features, switch_model=config.switch_model, logic=logic,
                    time_recently_lost=config.time_recently_lost)  # fmt: skip
    return replay_losses(result, batch, config, hard=hard)


def replay_losses(
    result: ReplayResult, batch: LogBatch, config: ObjectiveConfig, *, hard: bool = True
) -> RunLoss:
    """Score every run of a replay of `batch` (`run_losses` after its replay; jsve.evaluation._evaluate
    calls it on the replay it evaluates, so that a rule's objective terms come without a second
    replay). `result` must come from a replay under config's switch model and time_recently_lost.

    Returns:
        RunLoss with [R] leaves.
    """
    with_q = ALIGNERS[config.align].first_pose  # only first-pose alignments read orientations
    kernel = functools.partial(_one_run_loss, config=config, hard=hard)
    return jax.vmap(kernel)(
        result.position,
        result.quaternion if with_q else None,
        result.in_trajectory,
        result.out_of_support,
        result.lost_any,
        batch.gt_p,
        batch.gt_q if with_q else None,
        batch.gt_valid,
        batch.valid,
    )


def weighted_objective(losses: RunLoss, weights: Float[Array, " R"]) -> ObjectiveValue:
    """The weighted means of a RunLoss (weights >= 0, not all 0; padding runs get 0) over its included
    runs; where no weight is included (every run excluded), over all runs, whose losses are then the
    penalty: the value "penalise" gives."""
    dtype = losses.loss.dtype
    w_all = jnp.asarray(weights, dtype)
    w_in = w_all * losses.included.astype(dtype)
    total_all, total_in = jnp.sum(w_all), jnp.sum(w_in)
    w = jnp.where(total_in > 0, w_in, w_all)
    total = jnp.sum(w)
    mean = lambda x: safe_divide(jnp.sum(w * x), total)  # noqa: E731
    failed = losses.failed.astype(dtype)
    ok = w * (1 - failed)
    return ObjectiveValue(
        value=mean(losses.loss),
        coverage=mean(losses.coverage),
        failure_rate=mean(failed),
        # ok is 0 where the RMSE is not finite (such a run failed), and 0 x NaN would be NaN.
        rmse_ok=safe_divide(jnp.sum(jnp.where(ok > 0, ok * losses.rmse, 0.0)), jnp.sum(ok)),
        unsupported_rate=safe_divide(jnp.sum(w_all * losses.unsupported.astype(dtype)), total_all),
        excluded=safe_divide(total_all - total_in, total_all),
    )


def objective(
    batch: LogBatch,
    rule: Rule,
    weights: Float[Array, " R"],
    features: FrameFeatures | None = None,
    config: ObjectiveConfig = ObjectiveConfig(),  # noqa: B008
    *,
    logic=None,
) -> ObjectiveValue:
    """The weighted mean loss of `rule` over `batch` (metres), with coverage and failure rate.

    Arguments:
        weights: [R] run weights (see `group_weights`; 0 for padding or held-out runs).
        Others as `run_losses`.
    """
    if weights.shape != (batch.n_runs,):
        raise ValueError(
            f"weights must have shape ({batch.n_runs},) (one per run), got {tuple(weights.shape)}"
        )
    return weighted_objective(run_losses(batch, rule, features, config, logic=logic), weights)
