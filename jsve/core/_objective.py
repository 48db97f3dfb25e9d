"""Position-error objectives of a switching rule over a LogBatch, hard and relaxed.

The objective is the mean over runs of a per-run loss: the run's ATE RMSE (metres, after alignment to
ground truth) when it succeeded, and a configurable penalty when it failed. Failed runs are never
dropped: a rule that loses tracking on a hard run must not score better than one that keeps it (evo
issue #673). Runs can be weighted, e.g. so that every sequence, disturbance and level counts equally
(`group_weights`), and the weighted coverage and failure rate come with every value.

    loss_r = failure_penalty              if run r failed
           = RMSE_r                       otherwise
    J = sum_r w_r loss_r / sum_r w_r

A run fails as in `jsve.evaluation._evaluate`: it lost tracking (a reset, an expiry or a recorded map
loss: the hard replay then starts a new, unaligned map), its alignment was degenerate, fewer than 3 frames
were evaluated, or its coverage is below `min_coverage`. A run that never lost tracking stays in one map,
so its RMSE equals `jsve.evaluation._evaluate`'s (segments="largest"); the hard objective is therefore
exactly mean(where(failed, penalty, rmse)) of the per-run table (tests/test_objective.py).

Relaxed (SoftLogic with a temperature): the replay's flags are probabilities. The loss is the expected one,
P(ever LOST) x penalty + (1 - P) x RMSE, with the RMSE taken over frames weighted by the probability that
they have an estimate (a weighted Umeyama alignment, a smooth statistic). As the temperature falls every
probability tends to its hard 0/1 value and the relaxed objective to the hard one.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jsve.core._align import ALIGNERS, MIN_ALIGNMENT_FRAMES
from jsve.core._batch import LogBatch
from jsve.core._machine import TIME_RECENTLY_LOST_S, HardLogic, check_switch_model
from jsve.core._numerics import safe_divide
from jsve.core._replay import batch_features, replay
from jsve.core._rules import Rule
from jsve.core._sve import FrameFeatures
from jsve.core._trajectory import align, weighted_rmse

DEFAULT_FAILURE_PENALTY_M = 1.0
"""Metres charged for a failed run. A VI-SLAM run on EuRoC-sized scenes that keeps tracking stays well
below it (ORB-SLAM3's EuRoC ATE is centimetres); a run that reaches LOST costs more than any run that
keeps tracking with a plausible error. Configurable: it sets the exchange rate between failures and
metres of error, which is a choice the user owns (docs/fitting.md)."""


class ObjectiveConfig(eqx.Module):
    """How runs are scored (all static: a new value compiles once).

    Attributes:
        failure_penalty: metres charged for a failed run.
        align: alignment before the RMSE, a method of jsve.core._align.ALIGNERS: "se3" (default), "sim3",
            "posyaw", "origin", "none".
        min_coverage: runs whose coverage (evaluated / ground-truth frames) is below it fail.
        time_recently_lost: s in RECENTLY_LOST before LOST (ORB-SLAM3: 5).
        switch_model: the pose of a frame in RECENTLY_LOST, "orbslam3" (the logged pose, default) or
            "imu-coast" (IMU prediction); see docs/state-machine.md.
    """

    failure_penalty: float = eqx.field(static=True, default=DEFAULT_FAILURE_PENALTY_M)
    align: str = eqx.field(static=True, default="se3")
    min_coverage: float = eqx.field(static=True, default=0.0)
    time_recently_lost: float = eqx.field(static=True, default=TIME_RECENTLY_LOST_S)
    switch_model: str = eqx.field(static=True, default="orbslam3")

    def __check_init__(self):
        check_switch_model(self.switch_model)
        if not (np.isfinite(self.failure_penalty) and self.failure_penalty >= 0):
            raise ValueError(
                f"failure_penalty must be a finite number of metres >= 0, got {self.failure_penalty}"
            )
        if self.align not in ALIGNERS:
            raise ValueError(f"align must be one of {tuple(ALIGNERS)}, got {self.align!r}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must lie in [0, 1], got {self.min_coverage}")


class RunLoss(eqx.Module):
    """Per-run loss and the facts behind it (leaves [R]; probabilities where relaxed).

    Attributes:
        loss: metres; failure_penalty where failed.
        rmse: ATE RMSE over the evaluated frames, metres (also for failed runs, for reference).
        failed: the run failed (bool), or its probability of failing (relaxed).
        coverage: evaluated frames / valid frames with ground truth.
    """

    loss: Float[Array, " R"]
    rmse: Float[Array, " R"]
    failed: Array
    coverage: Float[Array, " R"]


class ObjectiveValue(eqx.Module):
    """A weighted objective with its diagnostics (scalars).

    Attributes:
        value: sum_r w_r loss_r / sum_r w_r, metres.
        coverage: weighted mean coverage. failure_rate: weighted mean of failed.
        rmse_ok: weighted mean RMSE of the runs that did not fail (NaN-free: 0 when all failed).
    """

    value: Float[Array, ""]
    coverage: Float[Array, ""]
    failure_rate: Float[Array, ""]
    rmse_ok: Float[Array, ""]


def _one_run_loss(est_p, est_q, has_estimate, lost_any, gt_p, gt_q, gt_valid, valid, config, hard):
    """Loss of one replayed run ([T, ...] arrays; has_estimate and lost_any are flags or probabilities)."""
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
    # Data facts, exact in both modes (their probability is 0 or 1).
    broken = transform.degenerate | (count < MIN_ALIGNMENT_FRAMES) | (coverage < config.min_coverage)
    if hard:
        failed = broken | (lost_any > 0.5)
        loss = jnp.where(failed, jnp.asarray(config.failure_penalty, dtype), rmse)
    else:
        failed = 1 - (1 - lost_any.astype(dtype)) * (1 - broken.astype(dtype))
        loss = failed * config.failure_penalty + (1 - failed) * rmse
    return RunLoss(loss=loss, rmse=rmse, failed=failed, coverage=coverage)


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
    with_q = ALIGNERS[config.align].first_pose  # only first-pose alignments read orientations
    kernel = functools.partial(_one_run_loss, config=config, hard=hard)
    return jax.vmap(kernel)(
        result.position,
        result.quaternion if with_q else None,
        result.has_estimate,
        result.lost_any,
        batch.gt_p,
        batch.gt_q if with_q else None,
        batch.gt_valid,
        batch.valid,
    )


def weighted_objective(losses: RunLoss, weights: Float[Array, " R"]) -> ObjectiveValue:
    """The weighted means of a RunLoss (weights >= 0, not all 0; padding runs get 0)."""
    w = jnp.asarray(weights, losses.loss.dtype)
    total = jnp.sum(w)
    mean = lambda x: safe_divide(jnp.sum(w * x), total)  # noqa: E731
    failed = losses.failed.astype(w.dtype)
    ok = w * (1 - failed)
    return ObjectiveValue(
        value=mean(losses.loss),
        coverage=mean(losses.coverage),
        failure_rate=mean(failed),
        rmse_ok=safe_divide(jnp.sum(ok * losses.rmse), jnp.sum(ok)),
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
