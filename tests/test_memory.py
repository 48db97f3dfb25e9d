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
    # a Python process with JAX holds tens of MB at least; the kernel's high-water mark lags the
    # resident count by its per-thread caches (a few hundred kB), so "at least" within 5 %
    assert 10e6 < now and peak >= 0.95 * now


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


def test_the_environment_turns_it_off(monkeypatch):
    @jax.jit
    def f(x):
        return x + 1

    f(jnp.ones(3))
    monkeypatch.setenv("JSVE_RELEASE_MEMORY", "0")
    assert release_memory(above_bytes=None) == {"before": None, "after": None, "cleared": False}
    assert f._cache_size() == 1
