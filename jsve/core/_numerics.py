"""Safe elementary functions: finite values and finite gradients where the textbook function has none.

The one home of jsve's safe math. Each uses the double-`where` idiom: the input of the unsafe operation is
replaced where it would be singular, so that the branch `jnp.where` does not take never sees an infinite
derivative (a plain `where(x > 0, sqrt(x), 0)` still back-propagates 0 * inf = NaN from the discarded branch).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def safe_sqrt(x: Array | float) -> Array:
    """sqrt(x) where x > 0, else 0; the gradient at x <= 0 is 0 (not inf or NaN)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_divide(num: Array | float, den: Array | float) -> Array:
    """num / den where den != 0, else 0; the gradient where den == 0 is 0 (not inf or NaN)."""
    nonzero = den != 0
    return jnp.where(nonzero, num / jnp.where(nonzero, den, 1.0), 0.0)
