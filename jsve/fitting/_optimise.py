"""Fits of one setting from a start, on the whole objective: Nelder-Mead on the hard objective and the
annealed BFGS (optimistix) on the relaxed one.

    hard_objective(data, space, values, weights)        the objective of one setting, metres
    relaxed_objective(data, space, values, t, weights)  the same with SoftLogic at temperature t
    nelder_mead(data, space, x0, weights)               one simplex on the hard objective
    relaxed_fit(data, space, x0, weights)               BFGS on the relaxed objective, annealed
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jsve.core._machine import SoftLogic
from jsve.core._objective import ObjectiveConfig, run_losses
from jsve.fitting._data import FitData, _default_weights
from jsve.fitting._polish import polish_in_lockstep
from jsve.fitting._space import ParamSpace

log = logging.getLogger(__name__)


DEFAULT_TEMPERATURES = (0.1, 0.03, 0.01, 0.003)
"""Annealing schedule of the relaxed fit, in SVE units (x250 for inlier thresholds). It starts broad:
at a temperature much below the distance of most scores from the thresholds every sigmoid saturates
and the relaxed objective is flat (no gradient) far from the optimum."""


def _included_mean(parts):
    """sum w x loss / sum w over the included runs of (loss, included, w) per part; over all runs where
    none is included (whose losses are then the penalty), as jsve.core._objective.weighted_objective."""
    num_in = sum(jnp.sum(w * inc * loss) for loss, inc, w in parts)
    den_in = sum(jnp.sum(w * inc) for _, inc, w in parts)
    num_all = sum(jnp.sum(w * loss) for loss, _, w in parts)
    den_all = sum(jnp.sum(w) for _, _, w in parts)
    return jnp.where(den_in > 0, num_in / jnp.where(den_in > 0, den_in, 1.0), num_all / den_all)


def _relaxed_value(z, batches, features, weights, temperature, space: ParamSpace, config: ObjectiveConfig):
    """Weighted mean relaxed loss (SoftLogic(temperature x score scale)); differentiable in z."""
    rule = space.rule(space.values_from_z(z))
    logic = SoftLogic(temperature * space.score_scale)
    losses = [
        (run_losses(b, rule, f, config, logic=logic), w)
        for b, f, w in zip(batches, features, weights, strict=True)
    ]
    return _included_mean([(r.loss, r.included, w) for r, w in losses])


def hard_objective(data: FitData, space: ParamSpace, values, weights=None) -> float:
    """The hard objective (metres) of one setting's free values `values` [d] under run weights [R]
    (default: every run 1): the study's scorer scores the setting on every run, as the search scores
    its settings (the same compiled scans), and its included runs are averaged with the weights."""
    w = _default_weights(data, weights)
    result = data.scorer.score(space, np.asarray(values, np.float64)[None], desc="objective")
    return float(result.objective(w)[0])


def relaxed_objective(data: FitData, space: ParamSpace, values, temperature: float, weights=None) -> float:
    """The relaxed objective (metres) of one setting at a temperature in SVE units."""
    w = data.split_weights(_default_weights(data, weights))
    batches, features = data.slim()
    z = space.z_from_values(jnp.asarray(values, data.parts[0].t.dtype))
    return float(_relaxed_jit(z, batches, features, w, jnp.asarray(temperature, z.dtype), space, data.config))


_relaxed_jit = eqx.filter_jit(_relaxed_value)
_relaxed_grad = eqx.filter_jit(jax.value_and_grad(_relaxed_value))


# ---------------------------------------------------------------------------------------------------
# Optimisers


@eqx.filter_jit
def _bfgs(z0, batches, features, weights, temperature, space, config, max_steps, rtol, atol):
    def fn(z, args):
        return _relaxed_value(z, args[0], args[1], args[2], args[3], space, config)

    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(
        fn, solver, z0, args=(batches, features, weights, temperature), max_steps=max_steps, throw=False
    )
    return sol.value, sol.stats["num_steps"]


def nelder_mead(
    data: FitData,
    space: ParamSpace,
    start,
    weights=None,
    *,
    max_steps: int = 200,
    step: float = 0.5,
    rtol: float = 1e-4,
    atol: float = 1e-4,
    window: int = 0,
    ftol: float = 1e-4,
    on_runs: int = 0,
    seed: int = 0,
    pool=None,
) -> tuple[np.ndarray, float, int]:
    """Nelder-Mead on the hard objective from `start` (free values): one run of the fit's polish
    (jsve.fitting._simplex.lockstep_nelder_mead; `polish_fits` moves many together).

    on_runs: where more runs have weight, the simplex moves on the first on_runs of them in the study's
    stratified order (seeded by `seed`), packed by length class (jsve.fitting._polish); 0: on every run.
    pool: [R] the weights those runs are drawn from (a fold: the study's, `polish_runs`); default weights.

    The simplex starts at the start's unconstrained coordinates z plus `step` along each axis (a step
    of 0.5 in z moves a value at mid-box by ~12 % of its box). The hard objective is piecewise constant
    in the thresholds (finitely many frames), which a simplex method handles where gradients cannot.
    window, ftol: stop once `window` steps improve the best value by at most `ftol` metres; window 0:
    run to the simplex's convergence test or max_steps.

    Returns:
        (values [d], hard objective at them over every run with weight, steps taken).
    """
    w = _default_weights(data, weights)
    ended = polish_in_lockstep(
        data, space, [w], [(0, np.asarray(start, np.float64))], n_runs=on_runs, seed=seed, step=step,
        max_steps=max_steps, window=window, ftol=ftol, rtol=rtol, atol=atol, pool=pool,
    )  # fmt: skip
    values = ended.values[0]
    # The objective on every run with weight: where the polish ran on a subset, the verdict is not its.
    return values, hard_objective(data, space, values, w), int(ended.steps[0])


def relaxed_fit(
    data: FitData,
    space: ParamSpace,
    start,
    weights=None,
    *,
    temperatures: Sequence[float] = DEFAULT_TEMPERATURES,
    max_steps: int = 60,
    rtol: float = 1e-4,
    atol: float = 1e-5,
) -> tuple[np.ndarray, list[dict]]:
    """optimistix BFGS on the relaxed objective, annealing the temperature (SVE units) from high to low.

    Returns:
        (values [d] after the last temperature, one dict per temperature: temperature, relaxed value,
        hard value, steps).
    """
    w = data.split_weights(_default_weights(data, weights))
    batches, features = data.slim()
    dtype = data.parts[0].t.dtype
    z = space.z_from_values(jnp.asarray(start, dtype))
    history = []
    for temperature in temperatures:
        tau = jnp.asarray(temperature, dtype)
        z, steps = _bfgs(
            z,
            batches,
            features,
            w,
            tau,
            space,
            data.config,
            int(max_steps),
            float(rtol),
            float(atol),
        )
        relaxed = float(_relaxed_jit(z, batches, features, w, tau, space, data.config))
        hard = hard_objective(data, space, np.asarray(space.values_from_z(z), np.float64), weights)
        history.append(
            {"temperature": float(temperature), "relaxed": relaxed, "hard": hard, "steps": int(steps)}
        )
        log.info(
            "relaxed fit T=%g: relaxed %.5f m, hard %.5f m (%d steps)", temperature, relaxed, hard, steps
        )
    return np.asarray(space.values_from_z(z), np.float64), history


__all__ = ["DEFAULT_TEMPERATURES", "hard_objective", "relaxed_objective", "nelder_mead", "relaxed_fit"]
