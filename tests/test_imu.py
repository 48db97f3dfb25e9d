"""jsve.core._imu: ORB-SLAM3's PredictStateIMU against tests/oracle_orbslam3.py (an independent numpy
implementation that rotates by quaternion sandwich products); its column form (the search kernel's) and its
numpy form (the simulator's, jsve.sim._imu) against the array form; eager == jit == vmap (a stacked loop);
gradients == central differences.

Tolerances: 1e-12 against the oracle (float64 rounding of a different rotation formula); exact equality
between forms that perform the same operations in the same order; 1e-15 between numpy and XLA.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import oracle_orbslam3 as oracle
import pytest

from jsve.core._geometry import columns
from jsve.core._imu import imu_predict, imu_predict_columns
from jsve.sim import _imu as si
from jsve.sim import _trajectory as st

pytestmark = pytest.mark.usefixtures("x64")

N = 30


@pytest.fixture(scope="module")
def state():
    """(p, v, q, dt, dp, dv, dq, gravity) for N frames: metres, m/s, unit wxyz, s; gravity per frame."""
    rng = np.random.default_rng(7)
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    p, v, dp, dv = (rng.normal(size=(N, 3)) for _ in range(4))
    q, dq = (
        unit(rng.normal(size=(N, 4))),
        unit(rng.normal(size=(N, 4)) * [1, 0.05, 0.05, 0.05] + [1, 0, 0, 0]),
    )
    gravity = np.tile([0.0, 0.0, -9.81], (N, 1)) + rng.normal(size=(N, 3)) * 0.1
    return p, v, q, rng.uniform(0.0, 0.1, N), dp, dv, dq, gravity


def test_matches_the_oracle(state):
    ours = imu_predict(*map(jnp.asarray, state))
    for i in range(N):
        theirs = oracle.imu_predict(*(x[i] for x in state))
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(np.asarray(a[i]), b, rtol=0, atol=1e-12)


def test_column_form_is_the_array_form(state):
    p, v, q, dt, dp, dv, dq, gravity = state
    cols = imu_predict_columns(
        *(columns(x) for x in (p, v, q)), dt, *(columns(x) for x in (dp, dv, dq, gravity))
    )
    for a, b in zip(cols, imu_predict(*state, xp=np), strict=True):
        np.testing.assert_array_equal(np.stack(a, -1), b)


def test_numpy_form_equals_the_jax_form_and_is_the_simulators(state):
    ours = imu_predict(*state, xp=np)
    for a, b in zip(ours, imu_predict(*map(jnp.asarray, state)), strict=True):
        assert isinstance(a, np.ndarray) and a.dtype == np.float64
        np.testing.assert_allclose(a, np.asarray(b), rtol=1e-15, atol=1e-15)
    # the simulator's name, with its default gravity (the same for every frame)
    p, v, q, dt, dp, dv, dq, _ = state
    expected = imu_predict(p, v, q, dt, dp, dv, dq, st.GRAVITY, xp=np)
    for a, b in zip(si.imu_predict(p, v, q, dt, dp, dv, dq), expected, strict=True):
        np.testing.assert_array_equal(a, b)


def test_eager_jit_and_vmap_equal_a_loop(state):
    args = tuple(map(jnp.asarray, state))
    eager = imu_predict(*args)
    loop = [imu_predict(*(x[i] for x in args)) for i in range(N)]
    for k, out in enumerate((jax.jit(imu_predict)(*args), jax.vmap(imu_predict)(*args))):
        for a, b, c in zip(out, eager, zip(*loop, strict=True), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=1e-15, err_msg=str(k))
            np.testing.assert_allclose(np.asarray(a), np.stack(c), rtol=1e-15, atol=1e-15, err_msg=str(k))


def test_grad_equals_central_difference(state):
    """d/d(every input) of a fixed random projection of (p2, v2, q2), for 4 frames; h = 1e-6 (truncation
    ~1e-12, rounding ~1e-10)."""
    args = [jnp.asarray(x[:4]) for x in state]
    rng = np.random.default_rng(8)
    proj = [jnp.asarray(rng.normal(size=s)) for s in ((4, 3), (4, 3), (4, 4))]

    def loss(*xs):
        return sum(jnp.sum(w * y) for w, y in zip(proj, imu_predict(*xs), strict=True))

    grads = jax.grad(loss, argnums=tuple(range(8)))(*args)
    h = 1e-6
    for k, (x, grad) in enumerate(zip(args, grads, strict=True)):
        flat = np.asarray(x).ravel()
        fd = np.zeros_like(flat)
        for j in range(flat.size):
            bumped = [list(args), list(args)]
            for sign, row in zip((1, -1), bumped, strict=True):
                e = np.zeros_like(flat)
                e[j] = sign * h
                row[k] = jnp.asarray((flat + e).reshape(x.shape))
            fd[j] = (loss(*bumped[0]) - loss(*bumped[1])) / (2 * h)
        np.testing.assert_allclose(np.asarray(grad).ravel(), fd, rtol=1e-6, atol=1e-8, err_msg=str(k))
