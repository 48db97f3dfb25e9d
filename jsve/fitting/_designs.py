"""Space-filling designs in the unit cube [0, 1)^d: the settings a batched search evaluates.

Sobol (Gray-code order, Joe & Kuo direction numbers) and Halton sequences, optionally randomised by a seed,
uniform random points and full factorial grids; numpy, deterministic under a seed. `jsve.fitting._space`
maps unit points to rule parameters, `jsve.fitting._search` evaluates them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# Joe & Kuo (2008), new-joe-kuo-6.21201: dimension, degree s, polynomial a, initial direction numbers m.
_JOE_KUO = (
    (1, 0, (1,)),
    (2, 1, (1, 3)),
    (3, 1, (1, 3, 1)),
    (3, 2, (1, 1, 1)),
    (4, 1, (1, 1, 3, 3)),
    (4, 4, (1, 3, 5, 13)),
    (5, 2, (1, 1, 5, 5, 17)),
    (5, 4, (1, 1, 5, 5, 5)),
    (5, 7, (1, 1, 7, 11, 19)),
    (5, 11, (1, 1, 5, 1, 1)),
    (5, 13, (1, 1, 1, 3, 11)),
    (5, 14, (1, 3, 5, 5, 31)),
    (6, 1, (1, 3, 3, 9, 7, 49)),
    (6, 13, (1, 1, 1, 15, 21, 21)),
    (6, 16, (1, 3, 1, 13, 27, 49)),
)
SOBOL_MAX_DIM = 1 + len(_JOE_KUO)
_SOBOL_BITS = 32


def _sobol_directions(d: int) -> np.ndarray:
    """[d, 32] direction numbers V_i = m_i 2^(32 - i) (Bratley & Fox 1988, Joe & Kuo 2008)."""
    v = np.zeros((d, _SOBOL_BITS), np.uint64)
    v[0] = [1 << (_SOBOL_BITS - 1 - i) for i in range(_SOBOL_BITS)]  # dimension 1: m_i = 1
    for j in range(1, d):
        s, a, m0 = _JOE_KUO[j - 1]
        m = list(m0)
        for i in range(s, _SOBOL_BITS):
            new = m[i - s] ^ (m[i - s] << s)
            for k in range(1, s):
                new ^= ((a >> (s - 1 - k)) & 1) * (m[i - k] << k)
            m.append(new)
        v[j] = [m[i] << (_SOBOL_BITS - 1 - i) for i in range(_SOBOL_BITS)]
    return v


def sobol(n: int, d: int, *, seed: int | None = None) -> np.ndarray:
    """The first n points of the d-dimensional Sobol sequence (Gray-code order), [n, d] in [0, 1).

    Arguments:
        seed: None for the plain sequence (point 0 is the origin; the same points as
            scipy.stats.qmc.Sobol(scramble=False)); an int applies a random digital shift (XOR of every
            coordinate with a seeded 32-bit word), which keeps the net's balance.
    """
    if not 1 <= d <= SOBOL_MAX_DIM:
        raise ValueError(f"sobol supports 1 to {SOBOL_MAX_DIM} dimensions, got {d}")
    if n < 1 or n > 2**_SOBOL_BITS:
        raise ValueError(f"sobol needs 1 <= n <= 2^32 points, got {n}")
    v = _sobol_directions(d)
    # Gray code: point k = XOR of V_i over the bits i of k ^ (k >> 1).
    k = np.arange(n, dtype=np.uint64)
    gray = k ^ (k >> np.uint64(1))
    x = np.zeros((n, d), np.uint64)
    for i in range(_SOBOL_BITS):
        bit = ((gray >> np.uint64(i)) & np.uint64(1)).astype(bool)
        x[bit] ^= v[:, i]
    if seed is not None:
        shift = np.random.default_rng(seed).integers(0, 2**_SOBOL_BITS, size=d, dtype=np.uint64)
        x ^= shift
    return x.astype(np.float64) / 2.0**_SOBOL_BITS


def _primes(k: int) -> list[int]:
    out, c = [], 2
    while len(out) < k:
        if all(c % p for p in out if p * p <= c):
            out.append(c)
        c += 1
    return out


def halton(n: int, d: int, *, seed: int | None = None) -> np.ndarray:
    """The first n points of the d-dimensional Halton sequence (radical inverses in the first d primes).

    Point 0 is the origin, as scipy.stats.qmc.Halton(scramble=False). An int seed adds a random
    Cranley-Patterson rotation (a seeded shift modulo 1 per dimension).
    """
    if d < 1 or n < 1:
        raise ValueError(f"halton needs n >= 1 and d >= 1, got n={n}, d={d}")
    out = np.zeros((n, d))
    k0 = np.arange(n)
    for j, base in enumerate(_primes(d)):
        k = k0.copy()
        f, value = 1.0 / base, np.zeros(n)
        while np.any(k > 0):
            value += f * (k % base)
            k //= base
            f /= base
        out[:, j] = value
    if seed is not None:
        out = (out + np.random.default_rng(seed).random(d)) % 1.0
    return out


def random_design(n: int, d: int, *, seed: int = 0) -> np.ndarray:
    """n independent uniform points of [0, 1)^d."""
    return np.random.default_rng(seed).random((n, d))


def grid_design(levels: Sequence[int | Sequence[float]]) -> np.ndarray:
    """The full factorial grid: per dimension a number of equally spaced levels in [0, 1] (including
    both ends) or explicit unit coordinates; [prod(levels), d], the last dimension varying fastest."""
    axes = [np.linspace(0.0, 1.0, int(lv)) if np.isscalar(lv) else np.asarray(lv, float) for lv in levels]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=-1)


DESIGNS = {"sobol": sobol, "halton": halton, "random": random_design}


def design(kind: str, n: int, d: int, *, seed: int = 0) -> np.ndarray:
    """A design by name: "sobol" and "halton" (randomised by the seed) or "random"."""
    if kind not in DESIGNS:
        raise ValueError(f"design must be one of {sorted(DESIGNS)}, got {kind!r}")
    return DESIGNS[kind](n, d, seed=seed)


__all__ = ["DESIGNS", "SOBOL_MAX_DIM", "design", "grid_design", "halton", "random_design", "sobol"]
