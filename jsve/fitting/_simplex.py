"""Nelder-Mead that stops when it stops improving: optimistix's simplex plus a stall test.

The fit's hard objective is piecewise constant in the thresholds (finitely many frames cross them),
so the simplex rarely meets optimistix's own test, which asks every vertex to lie within rtol/atol of
the best point: it keeps finding steps of a few frames' worth and runs to its step limit (measured on
every fit of docs/fitting.md). On the 3,410-log study that limit made the cross-validation's
Nelder-Mead ~50 minutes. `StallingNelderMead` runs the same simplex and also stops when the best value
has improved by no more than `ftol` (metres of the objective) over the last `window` steps: a polish
that has stopped paying.

    solver = StallingNelderMead(rtol=1e-4, atol=1e-4, adelta=0.5, window=25, ftol=1e-4)
    sol = optx.minimise(fn, solver, z0, max_steps=200, throw=False)
    sol.stats["num_steps"], sol.stats["stalled"]

window = 0 turns the stall test off (optimistix's NelderMead, step for step).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int


class _StallState(eqx.Module):
    """The simplex's own state, the best value at the last checkpoint and whether it stalled."""

    simplex: Any
    mark: Float[Array, ""]
    steps: Int[Array, ""]
    stalled: Bool[Array, ""]


class StallingNelderMead(optx.AbstractMinimiser):
    """optimistix.NelderMead (rdelta 0, simplex of size `adelta` in every coordinate) that also stops
    once `window` steps in a row improve its best value by at most `ftol`.

    Attributes:
        rtol, atol: optimistix's convergence test on the simplex (vertices and values).
        adelta: initial simplex size, in the coordinates of y.
        window: steps between checkpoints of the best value (0: never stall).
        ftol: the smallest improvement over a window that keeps the simplex going, in the objective's
            units (metres for the fit's objective).
    """

    rtol: float
    atol: float
    adelta: float
    window: int = 25
    ftol: float = 1e-4
    norm: Callable = optx.max_norm

    def _inner(self) -> optx.NelderMead:
        return optx.NelderMead(rtol=self.rtol, atol=self.atol, norm=self.norm, rdelta=0.0, adelta=self.adelta)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> _StallState:
        simplex = self._inner().init(fn, y, args, options, f_struct, aux_struct, tags)
        return _StallState(
            simplex=simplex,
            mark=jnp.array(jnp.inf, f_struct.dtype),
            steps=jnp.array(0),
            stalled=jnp.array(False),
        )

    def step(self, fn, y, args, options, state: _StallState, tags):
        y, simplex, aux = self._inner().step(fn, y, args, options, state.simplex, tags)
        steps = state.steps + 1
        best = simplex.best[0]
        # The initial simplex's evaluation is step 1 and the first checkpoint: its best is the mark the
        # first window of moves is judged against (checkpoints at multiples of the window left the first
        # window unjudged, so every run took two windows even where its first improved nothing).
        checkpoint = (self.window > 0) & ((steps - 1) % max(self.window, 1) == 0)
        stalled = checkpoint & (state.mark - best <= self.ftol)
        mark = jnp.where(checkpoint, best, state.mark).astype(state.mark.dtype)
        return y, _StallState(simplex=simplex, mark=mark, steps=steps, stalled=stalled), aux

    def terminate(self, fn, y, args, options, state: _StallState, tags):
        done, result = self._inner().terminate(fn, y, args, options, state.simplex, tags)
        return done | state.stalled, result

    def postprocess(self, fn, y, aux, args, options, state: _StallState, tags, result):
        y, aux, stats = self._inner().postprocess(fn, y, aux, args, options, state.simplex, tags, result)
        return y, aux, {**stats, "stalled": state.stalled}


__all__ = ["StallingNelderMead"]
