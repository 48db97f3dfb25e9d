"""jsve._memory: giving back what finished work leaves behind (compiled executables, freed heap) without
changing any result."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jsve._memory import peak_resident_bytes, release_memory, resident_bytes


def test_resident_sizes_are_read():
    now, peak = resident_bytes(), peak_resident_bytes()
    assert now is not None and peak is not None
    assert 10e6 < now <= peak  # a Python process with JAX holds tens of MB at least


def test_executables_are_dropped_only_above_the_threshold_and_results_do_not_change():
    @jax.jit
    def f(x):
        return jnp.cumsum(jnp.sin(x) ** 2)

    x = jnp.linspace(0.0, 3.0, 257)
    first = np.asarray(f(x))
    assert f._cache_size() == 1
    kept = release_memory(above_bytes=2**62)  # no process holds that: executables kept
    assert not kept["cleared"] and f._cache_size() == 1
    dropped = release_memory(above_bytes=None)
    assert dropped["cleared"] and f._cache_size() == 0
    np.testing.assert_array_equal(np.asarray(f(x)), first)  # compiled again, the same values
    assert f._cache_size() == 1
