"""jsve.fitting._designs against scipy's Sobol and Halton sequences (implementations we did not write), and
the properties a design must have: points in the unit cube, balanced, deterministic under a seed."""

from __future__ import annotations

import numpy as np
import pytest

from jsve.fitting._designs import DESIGNS, design, grid_design, halton, random_design, sobol


def test_sobol_and_halton_match_scipy():
    qmc = pytest.importorskip("scipy.stats.qmc")
    for d in (1, 2, 4, 9, 16):
        ours = sobol(1024, d)
        theirs = qmc.Sobol(d, scramble=False).random(1024)
        assert np.array_equal(ours, theirs), d
        np.testing.assert_allclose(
            halton(500, d), qmc.Halton(d, scramble=False).random(500), rtol=0, atol=1e-15
        )


def test_designs_are_balanced_deterministic_and_in_the_cube():
    for seed in (None, 3):
        x = sobol(256, 5, seed=seed)
        assert x.min() >= 0 and x.max() < 1
        # a (t, m, s)-net property: every dyadic interval of length 1/16 of each coordinate holds 16 points
        for j in range(5):
            assert np.array_equal(np.bincount((x[:, j] * 16).astype(int), minlength=16), np.full(16, 16))
    assert np.array_equal(sobol(64, 3, seed=7), sobol(64, 3, seed=7))
    assert not np.array_equal(sobol(64, 3, seed=7), sobol(64, 3, seed=8))
    h = halton(100, 3, seed=1)
    assert h.min() >= 0 and h.max() < 1 and np.array_equal(h, halton(100, 3, seed=1))
    g = grid_design([3, [0.0, 0.5]])
    assert np.array_equal(g, [[0, 0], [0, 0.5], [0.5, 0], [0.5, 0.5], [1, 0], [1, 0.5]])
    with pytest.raises(ValueError, match="dimensions"):
        sobol(8, 40)


def test_design_by_name():
    assert np.array_equal(design("sobol", 16, 2, seed=4), sobol(16, 2, seed=4))
    assert np.array_equal(design("halton", 16, 2, seed=4), halton(16, 2, seed=4))
    r = design("random", 50, 3, seed=4)
    assert np.array_equal(r, random_design(50, 3, seed=4)) and r.min() >= 0 and r.max() < 1
    assert set(DESIGNS) == {"sobol", "halton", "random"}
    with pytest.raises(ValueError, match="design must be one of"):
        design("latin", 4, 2)
