"""Rotation algebra: quaternions (wxyz, Hamilton convention, active rotations), rotation matrices and vectors.

The one home of rotation algebra in jsve: replay, alignment, the search kernel and the simulator use these.
Every function works on the trailing axis and broadcasts over leading axes, in the array namespace `xp`:

- jax.numpy (the default): jit, vmap and grad; the double-`where` idiom keeps gradients finite at the
  identity rotation;
- numpy (`xp=np`): host code that needs float64 without dispatching to JAX, the simulator
  (jsve.sim._trajectory), whose worker processes never start a JAX backend.

The product and the rotation of vectors are also written on coordinate columns (`quat_mul_columns`,
`quat_rotate_columns`: tuples of arrays, one per coordinate), the form in which the fused search kernel keeps
its state (jsve.fitting._kernel); `quat_mul` and `quat_rotate` are those column formulas stacked, so every
form performs the same floating-point operations in the same order.
"""

from __future__ import annotations

from types import ModuleType

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

AnyArray = Array | np.ndarray
"""A JAX or a numpy array: the functions below return the kind of their namespace `xp`."""


def columns(x: AnyArray) -> tuple:
    """The trailing axis of x as a tuple of arrays, one per coordinate.

    XLA on CPU vectorises elementwise work over the leading (frame) axes well, but small [T, 3] x [3, 3]
    products and reductions over a trailing axis of 3 poorly (a rotation applied to a run's rows is
    tens of times faster column-wise than as a product), so hot paths spell out the coordinates.
    """
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _cross_columns(a, b) -> tuple:
    # numpy.cross's and jax.numpy.cross's operation order
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def quat_mul_columns(a, b) -> tuple:
    """Hamilton product a * b of wxyz quaternions given as columns (w, x, y, z); apply b first, then a."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_rotate_columns(q, v) -> tuple:
    """R(q) v for a unit quaternion q = (w, x, y, z) and a vector v = (x, y, z) given as columns."""
    w, u = q[0], q[1:]
    # v' = v + 2 w (u x v) + 2 u x (u x v): R(q) v without forming the matrix
    uv = _cross_columns(u, v)
    uuv = _cross_columns(u, uv)
    return tuple(vi + 2.0 * (w * a + b) for vi, a, b in zip(v, uv, uuv, strict=True))


def quat_mul(
    a: Float[AnyArray, "... 4"], b: Float[AnyArray, "... 4"], *, xp: ModuleType = jnp
) -> Float[AnyArray, "... 4"]:
    """Hamilton product a * b of wxyz quaternions (apply b first, then a)."""
    return xp.stack(quat_mul_columns(columns(a), columns(b)), axis=-1)


def quat_conj(q: Float[AnyArray, "... 4"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 4"]:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * xp.asarray([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_normalize(q: Float[AnyArray, "... 4"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 4"]:
    """Unit quaternion with non-negative w; the zero quaternion maps to the identity (finite gradient)."""
    sq = xp.sum(q * q, axis=-1, keepdims=True)
    safe = sq > 0
    norm = xp.sqrt(xp.where(safe, sq, 1.0))
    unit = xp.where(safe, q / norm, xp.asarray([1.0, 0.0, 0.0, 0.0], dtype=q.dtype))
    return xp.where(unit[..., :1] < 0, -unit, unit)


def quat_rotate(
    q: Float[AnyArray, "... 4"], v: Float[AnyArray, "... 3"], *, xp: ModuleType = jnp
) -> Float[AnyArray, "... 3"]:
    """Rotate vectors v by unit quaternions q: R(q) v, without forming the matrix."""
    return xp.stack(quat_rotate_columns(columns(q), columns(v)), axis=-1)


def quat_to_matrix(q: Float[AnyArray, "... 4"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 3 3"]:
    """Rotation matrix of a unit quaternion (wxyz)."""
    w, x, y, z = columns(q)
    return xp.stack(
        [
            xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            xp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            xp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quat(m: Float[AnyArray, "... 3 3"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 4"]:
    """Unit quaternion (wxyz, w >= 0) of a rotation matrix; Shepperd's method, branch-free."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    s01, d01 = m[..., 0, 1] + m[..., 1, 0], m[..., 1, 0] - m[..., 0, 1]
    s02, d02 = m[..., 0, 2] + m[..., 2, 0], m[..., 0, 2] - m[..., 2, 0]
    s12, d12 = m[..., 1, 2] + m[..., 2, 1], m[..., 2, 1] - m[..., 1, 2]
    # Four candidate solutions; each is well conditioned where its leading term is the largest.
    cands = xp.stack(
        [
            xp.stack([1 + trace, d12, d02, d01], -1),
            xp.stack([d12, 1 + m00 - m11 - m22, s01, s02], -1),
            xp.stack([d02, s01, 1 - m00 + m11 - m22, s12], -1),
            xp.stack([d01, s02, s12, 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    lead = xp.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = xp.argmax(lead, axis=-1)
    q = xp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    return quat_normalize(q, xp=xp)


def nearest_rotation(
    m: Float[AnyArray, "... 3 3"], *, iterations: int = 5, xp: ModuleType = jnp
) -> Float[AnyArray, "... 3 3"]:
    """The rotation nearest to m in the Frobenius norm (the orthogonal factor of its polar decomposition,
    U V^T of m = U S V^T), for a matrix with det > 0 that is nearly a rotation (pose files written with
    6 digits).

    Newton's iteration X <- (X + X^-T) / 2 (Higham 1986, eq. 3.1), which converges quadratically: an input
    1e-3 off orthogonal is within rounding of the polar factor after 4 steps. X^-T = cof(X) / det(X), the
    cofactor rows being cross products of X's rows. scipy's Rotation.from_matrix (>= 1.15) projects with an
    SVD instead; both give the polar factor.
    """
    x = m
    for _ in range(iterations):
        r0, r1, r2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
        cof = xp.stack([xp.cross(r1, r2), xp.cross(r2, r0), xp.cross(r0, r1)], axis=-2)
        det = xp.sum(r0 * cof[..., 0, :], axis=-1)[..., None, None]
        x = 0.5 * (x + cof / xp.where(det != 0, det, 1.0))
    return x


def rotation_angle(m: Float[AnyArray, "... 3 3"], *, xp: ModuleType = jnp) -> Float[AnyArray, ...]:
    """The angle of rotation matrices, radians in [0, pi]: |Log(R)|, the norm of the rotation vector.

    As scipy's Rotation.from_matrix(R).magnitude() (which evo's so3_log_angle takes): the nearest rotation
    (`nearest_rotation`: a matrix read from a file is orthogonal to its digits only, and scipy projects
    it), its quaternion by Shepperd's method, then 2 atan2(|v|, w), well conditioned at 0 and at pi (arccos
    of the trace is not); |v| is 0 with a zero gradient at the identity.
    """
    q = matrix_to_quat(nearest_rotation(m, xp=xp), xp=xp)
    s2 = xp.sum(q[..., 1:] * q[..., 1:], axis=-1)
    positive = s2 > 0
    s = xp.where(positive, xp.sqrt(xp.where(positive, s2, 1.0)), 0.0)
    return 2.0 * xp.arctan2(s, q[..., 0])


def yaw_rotation(yaw: Float[AnyArray, ...], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 3 3"]:
    """Rotation about the world z axis by `yaw` radians."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    zero, one = xp.zeros_like(yaw), xp.ones_like(yaw)
    return xp.stack(
        [xp.stack([c, -s, zero], -1), xp.stack([s, c, zero], -1), xp.stack([zero, zero, one], -1)], -2
    )


def skew(v: Float[AnyArray, "... 3"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 3 3"]:
    """The cross-product matrix [v]x, with [v]x u = v x u."""
    x, y, z = columns(v)
    zero = xp.zeros_like(x)
    return xp.stack(
        [xp.stack([zero, -z, y], -1), xp.stack([z, zero, -x], -1), xp.stack([-y, x, zero], -1)], -2
    )


def so3_exp(phi: Float[AnyArray, "... 3"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 3 3"]:
    """Rotation matrix Exp(phi) of a rotation vector phi (radians): Rodrigues' formula, Taylor near 0."""
    theta2 = xp.sum(phi * phi, axis=-1)[..., None, None]
    small = theta2 < 1e-12
    theta = xp.sqrt(xp.where(small, 1.0, theta2))
    a = xp.where(small, 1.0 - theta2 / 6.0, xp.sin(theta) / theta)  # sin(t) / t
    b = xp.where(small, 0.5 - theta2 / 24.0, (1.0 - xp.cos(theta)) / (theta * theta))  # (1 - cos(t)) / t^2
    k = skew(phi, xp=xp)
    return xp.eye(3, dtype=phi.dtype) + a * k + b * (k @ k)


def quat_exp(phi: Float[AnyArray, "... 3"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 4"]:
    """Unit quaternion (wxyz) of a rotation vector phi (radians)."""
    theta2 = xp.sum(phi * phi, axis=-1, keepdims=True)
    small = xp.sqrt(theta2) < 1e-8  # no gradient flows through a comparison
    theta = xp.sqrt(xp.where(small, 1.0, theta2))
    half = 0.5 * theta
    w = xp.where(small, 1.0 - theta2 / 8.0, xp.cos(half))  # cos(t / 2)
    scale = xp.where(small, 0.5 - theta2 / 48.0, xp.sin(half) / theta)  # sin(t / 2) / t
    return xp.concatenate([w, scale * phi], axis=-1)


def quat_log(q: Float[AnyArray, "... 4"], *, xp: ModuleType = jnp) -> Float[AnyArray, "... 3"]:
    """Rotation vector (radians) of a unit quaternion (wxyz): the shorter of the two rotations."""
    q = xp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s2 = xp.sum(v * v, axis=-1, keepdims=True)
    small = xp.sqrt(s2) < 1e-12
    s = xp.sqrt(xp.where(small, 1.0, s2))
    angle = 2.0 * xp.arctan2(s, q[..., :1])
    return xp.where(small, 2.0 * v, v * angle / s)
