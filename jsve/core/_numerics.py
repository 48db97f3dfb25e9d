"""Safe elementary functions (finite gradients where the textbook function has none) and C's rounding.

The one home of jsve's safe math. Each uses the double-`where` idiom: the input of the unsafe operation is
replaced where it would be singular, so that the branch `jnp.where` does not take never sees an infinite
derivative (a plain `where(x > 0, sqrt(x), 0)` still back-propagates 0 * inf = NaN from the discarded branch).

They are safe for gradients, never for values: a non-finite input gives a non-finite value (NaN), so that
an overflow or a NaN upstream reaches the statistics and fails the run (jsve.core._trajectory.RunError)
instead of turning into a finite number, as 0 or x / inf = 0 would. Where they return NaN their own
derivative is 0; a NaN produced upstream may still carry NaN derivatives of its own.

`round_half_away` is C's round(), as ORB-SLAM3 bins keypoints with it, for numpy and JAX arrays alike.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def safe_sqrt(x: Array | float) -> Array:
    """sqrt(x) where x > 0 (inf at inf), 0 where x is finite and <= 0 (a rounding-error negative), NaN
    where x is NaN or -inf; the gradient where x <= 0 or is NaN is 0 (not inf or NaN)."""
    x = jnp.asarray(x)
    positive = x > 0
    root = jnp.sqrt(jnp.where(positive, x, 1.0))
    return jnp.where(positive, root, jnp.where(jnp.isfinite(x), 0.0, jnp.nan).astype(root.dtype))


def safe_divide(num: Array | float, den: Array | float) -> Array:
    """num / den where den is finite and != 0; where den == 0, 0 for a finite num and NaN otherwise; NaN
    where den is NaN or infinite (x / inf = 0 would hide the overflow). The gradient where den is 0 or
    not finite is 0 (not inf or NaN)."""
    num, den = jnp.asarray(num), jnp.asarray(den)
    usable = (den != 0) & jnp.isfinite(den)
    quotient = num / jnp.where(usable, den, 1.0)
    fallback = jnp.where(jnp.isfinite(num) & (den == 0), 0.0, jnp.nan).astype(quotient.dtype)
    return jnp.where(usable, quotient, fallback)


def round_half_away(v, xp=jnp):
    """C's round(): halves away from zero (numpy's and JAX's rint round them to even), in v's dtype, with
    `xp` numpy or jax.numpy. Exact: floor(|v| + 0.5) is not (0.49999997f + 0.5f == 1 in float32)."""
    v = xp.asarray(v)
    t = xp.trunc(v)
    return xp.where(xp.abs(v - t) >= 0.5, t + xp.sign(v), t)
