"""Alignment methods: the transform that maps an estimated trajectory onto its reference.

The one home of alignment in jsve. `ALIGNERS` is the registry of methods (`ALIGN_METHODS` its names, the
command line's choices); a least-squares method is a solver from the weighted moments of the selected
point pairs, so the same code serves `jsve.core._trajectory.align` (moments from the points), the objective
(through `align`) and the fused search kernel (moments from its running sums, jsve.fitting._kernel). A new
least-squares method is one solver and one registry entry here.

Conventions: positions are rows `(T, 3)` in metres, world frame; quaternions are wxyz (body in world, T_wb).
The estimate is mapped onto the reference: `aligned = scale * R @ est + t`. Solvers broadcast over leading
axes of the moments (the kernel solves [settings, runs] alignments at once).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, Bool, Float

from jsve.core._geometry import columns, matrix_to_quat, quat_mul, quat_normalize, quat_to_matrix
from jsve.core._numerics import safe_divide, safe_sqrt

MIN_ALIGNMENT_FRAMES = 3
"""Fewer frames than this make a Umeyama alignment degenerate (and a run failed)."""

# A point set whose spread (RMS distance to its centroid) is below this many machine epsilons of its RMS
# distance to the origin is "all points identical": the centroid's rounding error alone is about one epsilon.
_IDENTICAL_POINTS_EPS = 64.0


class Transform(eqx.Module):
    """A similarity transform mapping estimate coordinates to reference coordinates: `p -> scale * R p + t`.

    Attributes:
        rotation: [*batch, 3, 3] rotation matrix R (det +1), estimate world frame -> reference world frame.
        translation: [*batch, 3] translation t, metres, reference world frame.
        scale: [*batch] scale factor (1 except for sim3), dimensionless.
        degenerate: [*batch] True when the alignment was not possible (fewer than 3 frames, or all estimated
            or all reference points identical; for "origin", no frame at all). The transform is then the
            identity and the caller must flag the result (run_error marks the run failed).
    `batch` is empty for one transform; leading axes hold one transform per run (or per setting and run).
    """

    rotation: Float[Array, "*batch 3 3"]
    translation: Float[Array, "*batch 3"]
    scale: Float[Array, "*batch"]
    degenerate: Bool[Array, "*batch"]

    @classmethod
    def identity(cls, dtype: DTypeLike = float) -> Transform:
        """The identity transform (not degenerate)."""
        return cls(jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype), jnp.ones((), dtype), jnp.zeros((), bool))

    def apply(self, p: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Map points (metres, estimate frame) into the reference frame: scale * R p + t."""
        return jnp.stack(apply_columns(self, columns(p)), axis=-1)

    def apply_quat(self, q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
        """Map orientations (wxyz, body in estimate world) into the reference world: q_R * q."""
        return cast(Array, quat_mul(matrix_to_quat(self.rotation), q))

    def matrix(self) -> Float[Array, "4 4"]:
        """Homogeneous 4x4 matrix [[scale R, t], [0, 1]]."""
        top = jnp.concatenate([self.scale * self.rotation, self.translation[:, None]], axis=1)
        bottom = jnp.zeros((1, 4), top.dtype).at[0, 3].set(1.0)
        return jnp.concatenate([top, bottom], axis=0)


def apply_columns(transform: Transform, cols) -> list[Array]:
    """scale * R p + t on coordinate columns; for one transform or one per frame (leaves with a leading T)."""
    r, t, c = transform.rotation, transform.translation, transform.scale
    return [
        c * (r[..., i, 0] * cols[0] + r[..., i, 1] * cols[1] + r[..., i, 2] * cols[2]) + t[..., i]
        for i in range(3)
    ]


class Moments(eqx.Module):
    """Weighted first and second moments of point pairs (x_i estimated, y_i reference), the sufficient
    statistics of a least-squares alignment (Umeyama 1991, eqs. 34-38, each average weighted).

    Attributes:
        count: [...] frames with positive weight.
        mu_x, mu_y: [..., 3] weighted means, metres.
        var_x, var_y: [...] weighted variances sum_i w_i |x_i - mu_x|^2 / sum_i w_i, square metres.
        cov: [..., 3, 3] Sigma_xy = sum_i w_i (y_i - mu_y)(x_i - mu_x)^T / sum_i w_i, square metres.
    """

    count: Array
    mu_x: Float[Array, "... 3"]
    mu_y: Float[Array, "... 3"]
    var_x: Float[Array, ...]
    var_y: Float[Array, ...]
    cov: Float[Array, "... 3 3"]


def moments_from_points(x: Float[Array, "T 3"], y: Float[Array, "T 3"], w: Float[Array, " T"]) -> Moments:
    """The weighted moments of the pairs (x_i, y_i), weights w_i >= 0 (0/1 weights select rows)."""
    total = jnp.sum(w)
    wn = w / jnp.where(total > 0, total, 1.0)
    xs, ys = columns(x), columns(y)
    mu_x = jnp.stack([jnp.sum(wn * c) for c in xs])  # Umeyama (1991), eq. 34
    mu_y = jnp.stack([jnp.sum(wn * c) for c in ys])  # eq. 35
    xc = [c - m for c, m in zip(xs, mu_x, strict=True)]
    yc = [c - m for c, m in zip(ys, mu_y, strict=True)]
    var_x = sum(jnp.sum(wn * c * c) for c in xc)  # eq. 36
    var_y = sum(jnp.sum(wn * c * c) for c in yc)
    # eq. 38: Sigma_xy = sum_i w_i (y_i - mu_y)(x_i - mu_x)^T
    cov = jnp.stack([jnp.stack([jnp.sum(wn * yc[i] * xc[j]) for j in range(3)]) for i in range(3)])
    return Moments(jnp.sum(w > 0), mu_x, mu_y, jnp.asarray(var_x), jnp.asarray(var_y), cov)


def is_degenerate(m: Moments) -> Bool[Array, ...]:
    """Fewer than MIN_ALIGNMENT_FRAMES frames, or all estimated or all reference points identical."""
    eps = jnp.finfo(m.var_x.dtype).eps
    # "All points identical" is relative to the coordinates' magnitude (the centroid carries rounding error):
    # the mean squared norm is |mu|^2 + sigma^2, no extra pass over the frames needed.
    ms_x = jax.lax.stop_gradient(jnp.sum(m.mu_x * m.mu_x, axis=-1) + m.var_x)
    ms_y = jax.lax.stop_gradient(jnp.sum(m.mu_y * m.mu_y, axis=-1) + m.var_y)
    tol = (_IDENTICAL_POINTS_EPS * eps) ** 2
    return (m.count < MIN_ALIGNMENT_FRAMES) | (m.var_x <= tol * ms_x) | (m.var_y <= tol * ms_y)


# ----------------------------------------------------------------------------------------------------------
# Least-squares solvers: (moments, degenerate) -> (rotation [..., 3, 3], scale [...]).

Solver = Callable[[Moments, Array], tuple[Array, Array]]


def _det3(m: Float[Array, "... 3 3"]) -> Float[Array, ...]:
    """Determinant of 3x3 matrices (triple product; cheaper to compile than an LU factorisation)."""
    return jnp.sum(m[..., 0, :] * jnp.cross(m[..., 1, :], m[..., 2, :]), axis=-1)


def _umeyama_rotation(m: Moments, degenerate: Array) -> tuple[Array, Array]:
    """R = U S V^T maximising tr(R^T Sigma_xy), and tr(D S) (Umeyama 1991, eqs. 39-43)."""
    # A fixed matrix with distinct singular values stands in for a degenerate covariance, so that the
    # SVD's derivative (it divides by differences of singular values) stays finite off the taken branch.
    stand_in = jnp.diag(jnp.array([3.0, 2.0, 1.0], m.cov.dtype))
    u, d, vt = jnp.linalg.svd(jnp.where(degenerate[..., None, None], stand_in, m.cov))  # Sigma_xy = U D V^T
    # Reflection fix, eq. 43 (as evo): S = diag(1, 1, -1) when det(U) det(V) < 0, else I.
    flip = _det3(jax.lax.stop_gradient(u)) * _det3(jax.lax.stop_gradient(vt)) < 0
    one = jnp.ones_like(d[..., 0])
    s = jnp.stack([one, one, jnp.where(flip, -1.0, 1.0)], axis=-1)
    return (u * s[..., None, :]) @ vt, jnp.sum(d * s, axis=-1)  # eq. 40: R = U S V^T


def _solve_se3(m: Moments, degenerate: Array) -> tuple[Array, Array]:
    rotation, _ = _umeyama_rotation(m, degenerate)
    return rotation, jnp.ones_like(m.var_x)


def _solve_sim3(m: Moments, degenerate: Array) -> tuple[Array, Array]:
    rotation, trace_ds = _umeyama_rotation(m, degenerate)
    return rotation, safe_divide(
        trace_ds, jnp.where(degenerate, 1.0, m.var_x)
    )  # eq. 42: c = tr(DS) / sigma_x^2


def _solve_posyaw(m: Moments, degenerate: Array) -> tuple[Array, Array]:
    # 4-DoF (rpg_trajectory_evaluation's "posyaw"): R = Rz(theta), c = 1: a yaw about the world z axis,
    # which assumes z is the vertical in both worlds (gravity along -z, as in EuRoC and VIO estimates); in a
    # y-down world (KITTI's camera frame, see y_is_vertical) it rotates about a horizontal axis instead.
    # With S the covariance,
    # sum_i w_i yc_i^T R xc_i = const + cos(theta) (S00 + S11) + sin(theta) (S10 - S01), maximal at
    # theta = atan2(S10 - S01, S00 + S11); z is untouched by the yaw.
    a = m.cov[..., 0, 0] + m.cov[..., 1, 1]
    b = m.cov[..., 1, 0] - m.cov[..., 0, 1]
    has_xy = (a * a + b * b > 0) & ~degenerate
    r = safe_sqrt(jnp.where(has_xy, a * a + b * b, 1.0))
    cos_t = jnp.where(has_xy, a / r, 1.0)
    sin_t = jnp.where(has_xy, b / r, 0.0)
    zero, one = jnp.zeros_like(cos_t), jnp.ones_like(cos_t)
    rotation = jnp.stack(
        [
            jnp.stack([cos_t, -sin_t, zero], axis=-1),
            jnp.stack([sin_t, cos_t, zero], axis=-1),
            jnp.stack([zero, zero, one], axis=-1),
        ],
        axis=-2,
    )
    return rotation, one


# A trajectory whose positions spread this little across their plane of motion (smallest over middle
# standard deviation of the positions) moves in a plane; KITTI's sequences measure 0.004-0.05, EuRoC's
# flights 0.1-0.5.
_PLANAR_RATIO = 0.25
# The plane's normal within 30 degrees of the y axis: y is the vertical.
_Y_VERTICAL_COS = 0.866


def y_is_vertical(p: Float[Array, "T 3"], mask: Bool[Array, " T"]) -> Bool[Array, ""]:
    """Whether the masked positions move in a plane whose normal is within 30 degrees of the y axis.

    Such a trajectory is a ground vehicle in a y-down (or y-up) world: KITTI's left-camera frame, where
    gravity lies along y. posyaw's yaw about the world z axis is then a tilt of the road plane, not a
    heading: the 4-DoF alignment is meaningless there (use se3).

    Arguments:
        p: [T, 3] positions, metres, world frame.
        mask: [T] the frames to look at.

    Returns:
        True when the positions are planar (smallest standard deviation below 0.25 of the middle one) and the
        plane's normal is within 30 degrees of y; False otherwise and for fewer than 3 frames. A straight
        road has no plane to find (KITTI 04 is not flagged; the other ten odometry sequences are).
    """
    w = mask.astype(p.dtype)
    n = jnp.sum(w)
    mu = jnp.sum(w[:, None] * p, axis=0) / jnp.maximum(n, 1.0)
    c = (p - mu) * w[:, None]
    variance, axes = jnp.linalg.eigh(c.T @ c / jnp.maximum(n, 1.0))  # ascending
    planar = variance[0] < _PLANAR_RATIO**2 * variance[1]
    return (n >= MIN_ALIGNMENT_FRAMES) & planar & (jnp.abs(axes[1, 0]) > _Y_VERTICAL_COS)


def fit_moments(m: Moments, solve: Solver) -> Transform:
    """The least-squares transform of a solver from the moments; the identity (flagged) where degenerate.

    The translation is the least-squares one for the solver's rotation and scale: t = mu_y - c R mu_x
    (Umeyama 1991, eq. 41).
    """
    dtype = m.cov.dtype
    degenerate = is_degenerate(m)
    rotation, scale = solve(m, degenerate)
    translation = m.mu_y - scale[..., None] * (rotation @ m.mu_x[..., None])[..., 0]
    return Transform(
        rotation=jnp.where(degenerate[..., None, None], jnp.eye(3, dtype=dtype), rotation),
        translation=jnp.where(degenerate[..., None], 0.0, translation),
        scale=jnp.where(degenerate, 1.0, scale).astype(dtype),
        degenerate=degenerate,
    )


def first_pose_transform(
    est_r: Float[Array, "3 3"],
    est_p: Float[Array, " 3"],
    ref_r: Float[Array, "3 3"],
    ref_p: Float[Array, " 3"],
    degenerate: Bool[Array, ""],
) -> Transform:
    """The rigid transform that maps the estimated pose (est_r, est_p) onto the reference pose (ref_r, ref_p).

    As evo's `align_origin`: T = T_ref T_est^-1, i.e. R = R_ref R_est^T, t = p_ref - R p_est (evo inverts a
    pose by transposing its rotation, whether or not a file's digits left it exactly orthogonal; so does
    this). The identity, flagged, where `degenerate`.
    """
    dtype = est_p.dtype
    rotation = ref_r @ est_r.T
    translation = ref_p - rotation @ est_p
    return Transform(
        rotation=jnp.where(degenerate, jnp.eye(3, dtype=dtype), rotation),
        translation=jnp.where(degenerate, 0.0, translation),
        scale=jnp.ones((), dtype),
        degenerate=degenerate,
    )


def fit_first_pose(
    x: Float[Array, "T 3"],
    y: Float[Array, "T 3"],
    w: Float[Array, " T"],
    est_q: Float[Array, "T 4"],
    ref_q: Float[Array, "T 4"],
) -> Transform:
    """The rigid transform that maps the first selected estimated pose onto the first selected reference pose
    (`first_pose_transform`, orientations given as quaternions)."""
    selected = w > 0
    first = jnp.argmax(selected)
    r_est = cast(Array, quat_to_matrix(quat_normalize(est_q[first])))
    r_ref = cast(Array, quat_to_matrix(quat_normalize(ref_q[first])))
    return first_pose_transform(r_est, x[first], r_ref, y[first], ~jnp.any(selected))


# ----------------------------------------------------------------------------------------------------------
# The registry.


@dataclass(frozen=True)
class Aligner:
    """How one alignment method finds its transform (an entry of ALIGNERS).

    Attributes:
        solve: the least-squares rotation and scale from the moments of the selected frames (the
            translation follows, see `fit_moments`); None for the methods that do not fit the moments.
        first_pose: the method maps the first selected pose onto the reference's instead, which needs the
            orientations (no solve; the search kernel, which keeps only moments, cannot run it).
    A method with neither is the identity (no alignment).
    """

    solve: Solver | None = None
    first_pose: bool = False

    @property
    def identity(self) -> bool:
        return self.solve is None and not self.first_pose


ALIGNERS: dict[str, Aligner] = {
    "se3": Aligner(_solve_se3),  # rotation + translation (Umeyama; evo's default)
    "sim3": Aligner(_solve_sim3),  # rotation, translation and scale (monocular)
    "posyaw": Aligner(_solve_posyaw),  # yaw about world z + translation, 4-DoF (rpg's VIO convention)
    "origin": Aligner(first_pose=True),  # the first pose onto the reference's (evo's align_origin)
    "none": Aligner(),
}
"""Alignment methods by name (jsve.core._trajectory.align documents each)."""

ALIGN_METHODS: tuple[str, ...] = tuple(ALIGNERS)
"""The names of the alignment methods, in ALIGNERS' order."""

AlignMethod = Literal["se3", "sim3", "posyaw", "origin", "none"]
"""The alignment methods for type checkers (tests/test_align.py checks that it lists ALIGN_METHODS)."""


def restrict_first(w: Float[Array, " T"], n_first: int | None) -> Float[Array, " T"]:
    """Keep the weights of the first n_first frames with positive weight; zero the rest (None: keep all)."""
    if n_first is None:
        return w
    rank = jnp.cumsum(w > 0)  # 1-based rank of each selected frame, in time order
    return jnp.where(rank <= n_first, w, 0.0)


def fit(
    est_p: Float[Array, "T 3"],
    ref_p: Float[Array, "T 3"],
    w: Float[Array, " T"],
    method: str,
    est_q: Float[Array, "T 4"] | None,
    ref_q: Float[Array, "T 4"] | None,
    n_first: int | None,
) -> Transform:
    """The transform of `method` fitted on the frames with positive weight (the first n_first of them).

    est_q and ref_q are read only by first-pose methods; n_first restricts only least-squares ones (the
    first selected pose is the same whatever it is).
    """
    aligner = ALIGNERS[method]
    if aligner.first_pose:
        if est_q is None or ref_q is None:
            raise ValueError(f"align method {method!r} needs est_q and ref_q (the first poses' orientations)")
        return fit_first_pose(est_p, ref_p, w, est_q, ref_q)
    if aligner.solve is None:
        return Transform.identity(est_p.dtype)
    return fit_moments(moments_from_points(est_p, ref_p, restrict_first(w, n_first)), aligner.solve)


__all__ = [
    "ALIGNERS",
    "ALIGN_METHODS",
    "MIN_ALIGNMENT_FRAMES",
    "AlignMethod",
    "Aligner",
    "Moments",
    "Transform",
    "apply_columns",
    "first_pose_transform",
    "fit",
    "fit_moments",
    "is_degenerate",
    "y_is_vertical",
]
