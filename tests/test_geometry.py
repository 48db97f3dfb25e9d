"""jsve.core._geometry: rotation algebra against scipy's Rotation (an implementation we did not write); its
column forms and its numpy form (the simulator's, jsve.sim._trajectory) against its JAX form; eager == jit ==
vmap (a stacked loop); gradients == central differences, finite at the identity.

Tolerances: 1e-12 against scipy (float64 rounding of different formulas); exact equality between forms that
perform the same operations in the same order (columns and arrays; numpy and the simulator's names);
1e-15 between numpy and XLA for the same formulas (XLA's sin, cos and arctan2 are its own).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsve.core import _geometry as g
from jsve.sim import _trajectory as st

pytestmark = pytest.mark.usefixtures("x64")

N = 40


def wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()  # xyzw
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 1e-12) -> None:
    """Quaternions equal up to sign (q and -q are one rotation)."""
    sign = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    np.testing.assert_allclose(a, sign * b, rtol=0, atol=atol)


@pytest.fixture(scope="module")
def data():
    """Random rotations and vectors; rotation vectors of sizes down to 1e-13 rad (the Taylor branches)."""
    rng = np.random.default_rng(0)
    ra, rb = Rotation.random(N, random_state=1), Rotation.random(N, random_state=2)
    phi = rng.normal(size=(N, 3)) * np.logspace(-13, 0.4, N)[:, None]
    return dict(
        ra=ra, rb=rb, a=wxyz(ra), b=wxyz(rb), v=rng.normal(size=(N, 3)), phi=phi, yaw=rng.normal(size=N)
    )


def test_matches_scipy(data):
    ra, rb, a, b, v, phi = (data[k] for k in ("ra", "rb", "a", "b", "v", "phi"))
    j = jnp.asarray
    same_rotation(np.asarray(g.quat_mul(j(a), j(b))), wxyz(ra * rb))
    np.testing.assert_allclose(g.quat_rotate(j(a), j(v)), ra.apply(v), rtol=0, atol=1e-12)
    same_rotation(np.asarray(g.quat_conj(j(a))), wxyz(ra.inv()))
    np.testing.assert_allclose(g.quat_to_matrix(j(a)), ra.as_matrix(), rtol=0, atol=1e-12)
    q = np.asarray(g.matrix_to_quat(j(ra.as_matrix())))
    same_rotation(q, a)
    assert np.all(q[:, 0] >= 0)
    rot = Rotation.from_rotvec(phi)
    np.testing.assert_allclose(g.so3_exp(j(phi)), rot.as_matrix(), rtol=0, atol=1e-12)
    same_rotation(np.asarray(g.quat_exp(j(phi))), wxyz(rot))
    np.testing.assert_allclose(g.quat_log(j(wxyz(rot))), rot.as_rotvec(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        g.yaw_rotation(j(data["yaw"])), Rotation.from_euler("z", data["yaw"][:, None]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(np.einsum("nij,nj->ni", g.skew(j(v)), phi), np.cross(v, phi), atol=1e-12)


def off_orthogonal(m: np.ndarray, scale: float = 1e-6, seed: int = 4) -> np.ndarray:
    """Rotation matrices as a pose file's 6 digits leave them: off orthogonal by about `scale`."""
    return m + np.random.default_rng(seed).normal(scale=scale, size=m.shape)


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-6, 1e-3])
def test_rotation_angle_and_nearest_rotation_match_scipy(data, scale):
    """scipy's Rotation.from_matrix (evo's so3_log_angle) projects a matrix that is not orthogonal onto the
    nearest rotation (an SVD) before taking its quaternion: Newton's polar iteration gives that rotation,
    and the angle is its magnitude. 1e-14: float64 rounding of an SVD against 5 Newton steps."""
    rot = data["ra"]  # random rotations, angles over (0, pi)
    m = off_orthogonal(rot.as_matrix(), scale)
    u, _, vt = np.linalg.svd(m)
    np.testing.assert_allclose(np.asarray(g.nearest_rotation(jnp.asarray(m))), u @ vt, rtol=0, atol=1e-14)
    angle = np.asarray(g.rotation_angle(jnp.asarray(m)))
    np.testing.assert_allclose(angle, Rotation.from_matrix(m).magnitude(), rtol=1e-13, atol=1e-15)
    assert np.all((angle >= 0) & (angle <= np.pi))


def test_rotation_angle_is_zero_with_a_zero_gradient_at_the_identity():
    eye = jnp.eye(3)[None]
    assert float(g.rotation_angle(eye)[0]) == 0.0
    grad = jax.grad(lambda m: jnp.sum(g.rotation_angle(m)))(eye)
    np.testing.assert_array_equal(np.asarray(grad), 0.0)


def test_normalize_gives_unit_nonnegative_w_and_identity_for_zero():
    q = jnp.asarray([[0.0, 0.0, 0.0, 0.0], [-2.0, 0.0, 0.0, 0.0], [1.0, 2.0, -2.0, 4.0]])
    out = np.asarray(g.quat_normalize(q))
    np.testing.assert_allclose(out, [[1, 0, 0, 0], [1, 0, 0, 0], [0.2, 0.4, -0.4, 0.8]], atol=1e-15)
    grad = jax.grad(lambda x: jnp.sum(g.quat_normalize(x)[:, 1:]))(q)
    assert np.all(np.isfinite(np.asarray(grad)))


# (function, which inputs of `data` it takes)
ARRAY_FUNCTIONS = [
    (g.quat_mul, ("a", "b")),
    (g.quat_conj, ("a",)),
    (g.quat_normalize, ("a",)),
    (g.quat_rotate, ("a", "v")),
    (g.quat_to_matrix, ("a",)),
    (g.matrix_to_quat, ("m",)),
    (g.yaw_rotation, ("yaw",)),
    (g.skew, ("v",)),
    (g.so3_exp, ("phi",)),
    (g.quat_exp, ("phi",)),
    (g.quat_log, ("a",)),
    (g.nearest_rotation, ("m_off",)),
    (g.rotation_angle, ("m_off",)),
]
IDS = [f.__name__ for f, _ in ARRAY_FUNCTIONS]
DIFFERENTIABLE = [f for f in ARRAY_FUNCTIONS if f[0] is not g.matrix_to_quat]  # argmax picks a branch
SIMULATOR_NAMES = (
    "quat_mul",
    "quat_conj",
    "quat_normalize",
    "quat_rotate",
    "quat_to_matrix",
    "matrix_to_quat",
)
SIMULATOR_NAMES += ("skew", "so3_exp", "quat_exp", "quat_log")


def _inputs(data, names):
    extra = dict(
        m=data["ra"].as_matrix(),
        a=data["a"] * np.where(np.arange(N) % 2, 1.0, -1.0)[:, None],
        m_off=off_orthogonal(data["ra"].as_matrix()),
    )
    return [np.asarray(extra[n] if n in extra else data[n], np.float64) for n in names]


@pytest.mark.parametrize(("fn", "names"), ARRAY_FUNCTIONS, ids=IDS)
def test_numpy_form_equals_the_jax_form(data, fn, names):
    """xp=numpy (the simulator's float64 host path) computes what the JAX form computes."""
    args = _inputs(data, names)
    ours = fn(*args, xp=np)
    assert isinstance(ours, np.ndarray) and ours.dtype == np.float64
    np.testing.assert_allclose(ours, np.asarray(fn(*map(jnp.asarray, args))), rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("name", SIMULATOR_NAMES)
def test_the_simulators_rotations_are_the_numpy_form(data, name):
    """jsve.sim._trajectory's rotation helpers are this module's with xp=numpy: the same numbers, exactly."""
    fn, names = next(f for f in ARRAY_FUNCTIONS if f[0].__name__ == name)
    args = _inputs(data, names)
    np.testing.assert_array_equal(getattr(st, name)(*args), fn(*args, xp=np))


def test_column_forms_are_the_array_forms(data):
    a, b, v = data["a"], data["b"], data["v"]
    cols = g.columns
    np.testing.assert_array_equal(np.stack(g.quat_mul_columns(cols(a), cols(b)), -1), g.quat_mul(a, b, xp=np))
    np.testing.assert_array_equal(
        np.stack(g.quat_rotate_columns(cols(a), cols(v)), -1), g.quat_rotate(a, v, xp=np)
    )
    # and in JAX, op by op (eager) and compiled
    ja, jb, jv = map(jnp.asarray, (a, b, v))
    rotate_cols = jax.jit(lambda q, x: jnp.stack(g.quat_rotate_columns(cols(q), cols(x)), -1))
    np.testing.assert_array_equal(rotate_cols(ja, jv), jax.jit(g.quat_rotate)(ja, jv))
    np.testing.assert_array_equal(jnp.stack(g.quat_mul_columns(cols(ja), cols(jb)), -1), g.quat_mul(ja, jb))


@pytest.mark.parametrize(("fn", "names"), ARRAY_FUNCTIONS, ids=IDS)
def test_eager_jit_and_vmap_equal_a_loop(data, fn, names):
    args = [jnp.asarray(x) for x in _inputs(data, names)]
    eager = np.asarray(fn(*args))
    np.testing.assert_allclose(np.asarray(jax.jit(fn)(*args)), eager, rtol=1e-15, atol=1e-15)
    loop = np.stack([np.asarray(fn(*(x[i] for x in args))) for i in range(N)])
    np.testing.assert_allclose(np.asarray(jax.vmap(fn)(*args)), loop, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(loop, eager, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize(("fn", "names"), DIFFERENTIABLE, ids=[f.__name__ for f, _ in DIFFERENTIABLE])
def test_grad_equals_central_difference(data, fn, names):
    """d/dx of a fixed random projection of the output, against a central difference (h = 1e-6: truncation
    ~1e-12, rounding ~1e-10), at 6 points of the data including rotation vectors of 1e-13 to 1e-9 rad."""
    rng = np.random.default_rng(3)
    args = [jnp.asarray(x[[0, 1, 2, 13, 20, 39]]) for x in _inputs(data, names)]
    proj = jnp.asarray(rng.normal(size=np.shape(fn(*args))))

    def loss(first):
        return jnp.sum(proj * fn(first, *args[1:]))

    grad = np.asarray(jax.grad(loss)(args[0]))
    assert np.all(np.isfinite(grad))
    h = 1e-6
    flat = np.asarray(args[0]).ravel()
    fd = np.zeros_like(flat)
    for k in range(flat.size):
        bump = np.zeros_like(flat)
        bump[k] = h
        up, down = (jnp.asarray((flat + s * bump).reshape(args[0].shape)) for s in (1, -1))
        fd[k] = (loss(up) - loss(down)) / (2 * h)
    np.testing.assert_allclose(grad.ravel(), fd, rtol=1e-6, atol=1e-8)


def test_gradients_at_the_identity():
    """Exactly at zero rotation the Taylor branches give the derivative: Exp(phi) ~ I + [phi]x,
    q ~ (1, phi / 2), log q ~ 2 v."""
    zero = jnp.zeros((1, 3))
    weights = jnp.arange(1.0, 10.0).reshape(1, 3, 3)
    grad = jax.grad(lambda x: jnp.sum(weights * g.so3_exp(x)))(zero)
    w = np.asarray(weights[0])
    np.testing.assert_allclose(np.asarray(grad), [[w[2, 1] - w[1, 2], w[0, 2] - w[2, 0], w[1, 0] - w[0, 1]]])
    grad = jax.grad(lambda x: jnp.sum(jnp.asarray([1.0, 2.0, 3.0, 4.0]) * g.quat_exp(x)))(zero)
    np.testing.assert_allclose(np.asarray(grad), [[1.0, 1.5, 2.0]], atol=1e-15)
    identity = jnp.asarray([[1.0, 0.0, 0.0, 0.0]])
    grad = jax.grad(lambda q: jnp.sum(g.quat_log(q) * jnp.asarray([1.0, 2.0, 3.0])))(identity)
    np.testing.assert_allclose(np.asarray(grad), [[0.0, 2.0, 4.0, 6.0]], atol=1e-15)  # log q ~ 2 v near 1
