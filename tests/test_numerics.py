"""jsve.core._numerics: numpy's sqrt and division where they are defined, 0 where they are not, NaN (never a
finite number) for a non-finite input, and gradients that are the analytic ones where defined and 0 (never
inf or NaN) where not; eager == jit == vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jsve.core._numerics import safe_divide, safe_sqrt

pytestmark = pytest.mark.usefixtures("x64")

X = np.array([-2.0, -1e-300, 0.0, 1e-300, 1e-8, 0.25, 4.0, 1e8])
DEN = np.array([-2.0, 0.0, 0.0, 1e-3, 0.5, 0.0, 3.0, -1e-8])


def test_safe_sqrt_values_and_gradient():
    positive = X > 0
    np.testing.assert_array_equal(
        np.asarray(safe_sqrt(jnp.asarray(X))), np.where(positive, np.sqrt(np.abs(X)), 0.0)
    )
    grad = np.asarray(jax.vmap(jax.grad(safe_sqrt))(jnp.asarray(X)))
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(
        grad, np.where(positive, 0.5 / np.sqrt(np.where(positive, X, 1.0)), 0.0), rtol=1e-15
    )
    assert float(jax.jit(safe_sqrt)(2.0)) == float(np.sqrt(2.0))


def test_safe_divide_values_and_gradient():
    nonzero = DEN != 0
    expected = np.where(nonzero, X / np.where(nonzero, DEN, 1.0), 0.0)
    np.testing.assert_array_equal(np.asarray(safe_divide(jnp.asarray(X), jnp.asarray(DEN))), expected)
    np.testing.assert_array_equal(np.asarray(jax.jit(safe_divide)(X, DEN)), expected)
    d_num, d_den = jax.vmap(jax.grad(safe_divide, argnums=(0, 1)))(jnp.asarray(X), jnp.asarray(DEN))
    safe_den = np.where(nonzero, DEN, 1.0)
    np.testing.assert_allclose(np.asarray(d_num), np.where(nonzero, 1.0 / safe_den, 0.0), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(d_den), np.where(nonzero, -X / safe_den**2, 0.0), rtol=1e-15)


def test_vmap_equals_a_loop():
    x, d = jnp.asarray(X), jnp.asarray(DEN)
    np.testing.assert_array_equal(jax.vmap(safe_sqrt)(x), np.array([safe_sqrt(v) for v in x]))
    np.testing.assert_array_equal(
        jax.vmap(safe_divide)(x, d), np.array([safe_divide(a, b) for a, b in zip(x, d, strict=True)])
    )


def test_a_non_finite_input_never_gives_a_finite_value():
    # Overflow upstream (an inf sum of squares) or a NaN must reach the statistics, not become 0.
    x = jnp.array([np.nan, -np.inf, np.inf])
    np.testing.assert_array_equal(np.asarray(safe_sqrt(x)), [np.nan, np.nan, np.inf])
    assert np.all(np.asarray(jax.vmap(jax.grad(safe_sqrt))(x)) == 0.0)  # gradients stay finite
    num = jnp.array([np.nan, np.inf, np.nan, 1.0, 1.0, np.inf, 0.0])
    den = jnp.array([0.0, 0.0, 2.0, np.inf, np.nan, np.inf, -np.inf])
    for f in (safe_divide, jax.jit(safe_divide)):
        assert np.all(np.isnan(np.asarray(f(num, den))))
    d_num, d_den = jax.vmap(jax.grad(safe_divide, argnums=(0, 1)))(num[3:], den[3:])
    assert np.all(np.isfinite(np.asarray(d_num))) and np.all(np.isfinite(np.asarray(d_den)))
    # Finite input keeps its conventions: 0 / 0 = 0, sqrt of a rounding-error negative = 0.
    assert float(safe_divide(0.0, 0.0)) == 0.0 and float(safe_sqrt(-1e-300)) == 0.0
