"""jsve.core._trajectory and `jsve ape` against oracles we did not write: evo (alignment, APE), an independent
yaw-only least-squares solver, finite differences, and the real KITTI 00 ORB-SLAM estimate.

Tolerances: 1e-6 against evo is the project's contract (DESIGN section 6); observed differences are ~1e-12,
float64 rounding of two implementations of the same closed form. 1e-10 between two jsve code paths on the same
numbers (masking vs row selection, eager vs jit vs vmap) allows for different summation order only.
"""

from __future__ import annotations

import copy
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

import jsve.cli
from jsve.core._align import Transform
from jsve.core._trajectory import (
    ErrorStats,
    align,
    ape_statistics,
    batched_run_error,
    failure_reason,
    run_error,
    weighted_rmse,
)
from jsve.evaluation._aggregate import per_run_table

EVO_TOL = 1e-6  # the project's contract with evo (float64)
SAME_TOL = 1e-10  # two jsve code paths over the same numbers: summation order only
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")

pytestmark = pytest.mark.usefixtures("x64")


# ----------------------------------------------------------------------------------------------------------
# Helpers


def to_wxyz(rot: Rotation) -> np.ndarray:
    q = rot.as_quat()  # xyzw
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def from_wxyz(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def random_pair(seed: int, n_frames: int = 120, noise: float = 0.2, scale: float = 1.7):
    """A random reference trajectory and an estimate that is a noisy, similarity-transformed copy of it."""
    rng = np.random.default_rng(seed)
    ref_p = np.cumsum(rng.normal(size=(n_frames, 3)) * [1.0, 1.0, 0.3], axis=0)
    ref_rot = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.1, size=(n_frames, 3)), axis=0))
    ref_q = to_wxyz(ref_rot)
    g = Rotation.random(random_state=seed)
    t = rng.normal(scale=10.0, size=3)
    est_p = scale * g.apply(ref_p) + t + rng.normal(scale=noise, size=(n_frames, 3))
    est_q = to_wxyz(g * ref_rot * Rotation.from_rotvec(rng.normal(scale=0.02, size=(n_frames, 3))))
    return est_p, est_q, ref_p, ref_q


def evo_ape(est_p, est_q, ref_p, ref_q, *, mode: str, n: int = -1):
    """evo's APE (translation part) after evo's alignment: its statistics and the aligned positions."""
    stamps = np.arange(len(ref_p), dtype=float)
    ref = PoseTrajectory3D(positions_xyz=ref_p, orientations_quat_wxyz=ref_q, timestamps=stamps)
    est = PoseTrajectory3D(positions_xyz=est_p, orientations_quat_wxyz=est_q, timestamps=stamps)
    if mode == "origin":
        est.align_origin(ref)
    elif mode in ("se3", "sim3"):
        est.align(ref, correct_scale=mode == "sim3", n=n)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_all_statistics(), est.positions_xyz


def assert_stats_match_evo(stats: ErrorStats, evo_stats: dict, count: int):
    for name in STATS:
        np.testing.assert_allclose(
            float(getattr(stats, name)), evo_stats[name], rtol=0, atol=EVO_TOL, err_msg=name
        )
    assert int(stats.count) == count


def rz(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_oracle(x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Yaw + translation minimising sum ||y - Rz(theta) x - t||^2: dense search, then root of the derivative.

    Independent of jsve's closed form: a 0.1 degree grid brackets the minimum of the cost, and Brent's method
    finds the zero of d cost / d theta (to machine precision, which a search on the flat cost cannot reach).
    For a fixed rotation the best t is the difference of the centroids (normal equations in t).
    """
    xc, yc = x - x.mean(0), y - y.mean(0)

    def cost(theta):
        return np.sum((yc - xc @ rz(theta).T) ** 2)

    def dcost(theta):
        c, s = np.cos(theta), np.sin(theta)
        d_rz = np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])
        return -2.0 * np.sum((yc - xc @ rz(theta).T) * (xc @ d_rz.T))

    grid = np.linspace(-np.pi, np.pi, 3601)
    best = grid[np.argmin([cost(g) for g in grid])]
    step = grid[1] - grid[0]
    theta = brentq(dcost, best - step, best + step, xtol=1e-15, rtol=4 * np.finfo(float).eps)
    t = y.mean(0) - rz(theta) @ x.mean(0)
    return theta, t


def jnp_all(*arrays):
    return tuple(jnp.asarray(a) for a in arrays)


def tree_allclose(a, b, atol=SAME_TOL):
    leaves_a, leaves_b = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


# ----------------------------------------------------------------------------------------------------------
# evo equivalence


def fit(est_p, ref_p, mask, method, *, n_first=None, est_q=None, ref_q=None):
    """align, passing quaternions only where the method needs them (fewer distinct compilations)."""
    quats = {}
    if method == "origin" or method == "none":
        quats = dict(est_q=jnp.asarray(est_q), ref_q=jnp.asarray(ref_q))
    return align(*jnp_all(est_p, ref_p, mask), method=method, n_first=n_first, **quats)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("method", ["se3", "sim3"])
@pytest.mark.parametrize("n_first", [None, 25])
def test_umeyama_matches_evo_on_random_trajectories(seed, method, n_first):
    est_p, est_q, ref_p, ref_q = random_pair(seed)
    evo_stats, evo_aligned = evo_ape(
        est_p, est_q, ref_p, ref_q, mode=method, n=-1 if n_first is None else n_first
    )
    mask = np.ones(len(est_p), bool)
    aligned, _, transform = fit(est_p, ref_p, mask, method, n_first=n_first)
    np.testing.assert_allclose(np.asarray(aligned), evo_aligned, rtol=0, atol=EVO_TOL)
    assert not bool(transform.degenerate)
    assert_stats_match_evo(ape_statistics(aligned, jnp.asarray(ref_p), mask), evo_stats, len(est_p))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_origin_matches_evo_align_origin(seed):
    est_p, est_q, ref_p, ref_q = random_pair(seed, scale=1.0)
    evo_stats, evo_aligned = evo_ape(est_p, est_q, ref_p, ref_q, mode="origin")
    mask = np.ones(len(est_p), bool)
    aligned, aligned_q, _ = fit(est_p, ref_p, mask, "origin", est_q=est_q, ref_q=ref_q)
    np.testing.assert_allclose(np.asarray(aligned), evo_aligned, rtol=0, atol=EVO_TOL)
    # The first aligned pose is the first reference pose (orientation up to the quaternion sign).
    np.testing.assert_allclose(np.asarray(aligned[0]), ref_p[0], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.asarray(aligned_q[0]) @ ref_q[0]), 1.0, atol=1e-12)
    assert_stats_match_evo(ape_statistics(aligned, jnp.asarray(ref_p), mask), evo_stats, len(est_p))


@pytest.mark.parametrize("method", ["se3", "sim3"])
def test_reflected_and_planar_input_match_evo(method):
    """A mirrored estimate (det(U) det(V) < 0) and an exactly planar pair (rank-2 covariance) match evo."""
    est_p, est_q, ref_p, ref_q = random_pair(7)
    mirrored = est_p * np.array([-1.0, 1.0, 1.0])
    planar_est, planar_ref = est_p.copy(), ref_p.copy()
    planar_est[:, 2] = 0.0
    planar_ref[:, 2] = 0.0
    mask = np.ones(len(est_p), bool)
    for e, r in ((mirrored, ref_p), (planar_est, planar_ref)):
        evo_stats, evo_aligned = evo_ape(e, est_q, r, ref_q, mode=method)
        aligned, _, transform = fit(e, r, mask, method)
        np.testing.assert_allclose(np.asarray(aligned), evo_aligned, rtol=0, atol=EVO_TOL)
        np.testing.assert_allclose(np.linalg.det(np.asarray(transform.rotation)), 1.0, atol=1e-12)
        assert_stats_match_evo(ape_statistics(aligned, jnp.asarray(r), mask), evo_stats, len(e))


@pytest.fixture(scope="module")
def kitti(shared_data):
    """KITTI 00: ground truth, the ORB-SLAM estimate, and that estimate with 0.5 m noise on its positions."""
    root = shared_data / "kitti"
    ref = file_interface.read_kitti_poses_file(root / "odometry_poses" / "00.txt")
    est = file_interface.read_kitti_poses_file(root / "orbslam_estimate_00.txt")
    poses = np.stack(est.poses_se3)
    poses[:, :3, 3] += np.random.default_rng(9).normal(scale=0.5, size=(est.num_poses, 3))
    noisy = type(est)(poses_se3=list(poses))
    return root, ref, est, noisy


def _evo_stats(ref, est, mode):
    est = copy.deepcopy(est)
    if mode == "origin":
        est.align_origin(ref)
    else:
        est.align(ref, correct_scale=mode == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_all_statistics()


@pytest.mark.parametrize("method", ["se3", "sim3"])
def test_kitti00_orbslam_matches_evo(kitti, method):
    """The real ORB-SLAM estimate of KITTI 00 (4541 poses) and a noisier copy, batched: equal to evo."""
    _, ref, est, noisy = kitti
    n = est.num_poses
    trajs = (est, noisy)
    ones = jnp.ones((2, n), bool)
    result = batched_run_error(
        jnp.asarray(np.stack([t.positions_xyz for t in trajs])),
        jnp.asarray(np.stack([t.orientations_quat_wxyz for t in trajs])),
        ones,
        jnp.zeros((2, n), jnp.int32),
        jnp.asarray(np.stack([ref.positions_xyz] * 2)),
        jnp.asarray(np.stack([ref.orientations_quat_wxyz] * 2)),
        ones,
        ones,
        align=method,
        n_first=None,  # as `jsve ape` calls it: the CLI test below reuses this compilation
    )
    for i, traj in enumerate(trajs):
        stats = jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], result.stats)
        assert_stats_match_evo(stats, _evo_stats(ref, traj, method), n)
    assert not np.any(np.asarray(result.failed)) and np.all(np.asarray(result.coverage) == 1.0)
    assert np.all(np.asarray(result.n_segments) == 1)


# ----------------------------------------------------------------------------------------------------------
# posyaw against an independent solver


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_posyaw_matches_independent_yaw_search(seed):
    rng = np.random.default_rng(100 + seed)
    _, _, ref_p, _ = random_pair(seed)
    yaw = rng.uniform(-np.pi, np.pi)
    tilt = Rotation.from_rotvec(rng.normal(scale=0.05, size=3)).as_matrix()  # roll/pitch 4-DoF cannot fit
    offset = rng.normal(scale=5.0, size=3)
    est_p = ref_p @ (rz(yaw) @ tilt).T + offset + rng.normal(scale=0.3, size=ref_p.shape)

    theta, t = yaw_oracle(est_p, ref_p)
    aligned, _, transform = fit(est_p, ref_p, np.ones(len(est_p), bool), "posyaw")
    np.testing.assert_allclose(np.asarray(transform.rotation), rz(theta), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(transform.translation), t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(aligned), est_p @ rz(theta).T + t, rtol=0, atol=1e-9)
    assert float(transform.scale) == 1.0
    # The optimum recovers the inverse of the applied yaw up to the tilt and noise.
    assert abs(np.angle(np.exp(1j * (theta + yaw)))) < 0.1


# ----------------------------------------------------------------------------------------------------------
# Masks, weights, n_first, degenerate input


def _transform_arrays(tf: Transform):
    return np.asarray(tf.rotation), np.asarray(tf.translation), np.asarray(tf.scale)


@pytest.mark.parametrize("method", ["sim3", "posyaw", "origin"])  # se3 is sim3's code path with scale 1
def test_masked_alignment_equals_selected_rows(method):
    est_p, est_q, ref_p, ref_q = random_pair(11)
    keep = np.random.default_rng(5).random(len(est_p)) < 0.6
    keep[0] = False  # the first selected frame is not frame 0 (matters for origin)
    aligned, _, tf_mask = fit(est_p, ref_p, keep, method, est_q=est_q, ref_q=ref_q)
    rows = np.ones(keep.sum(), bool)
    _, _, tf_rows = fit(est_p[keep], ref_p[keep], rows, method, est_q=est_q[keep], ref_q=ref_q[keep])
    for a, b in zip(_transform_arrays(tf_mask), _transform_arrays(tf_rows), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=SAME_TOL)
    # Unmasked frames are mapped by the same transform.
    np.testing.assert_allclose(
        np.asarray(tf_rows.apply(jnp.asarray(est_p))), np.asarray(aligned), atol=SAME_TOL
    )

    if method == "origin":
        return  # origin uses the first selected frame whatever n_first is
    # n_first counts masked frames only: the first 25 selected rows equal the first 25 rows of the selection.
    _, _, tf_first = fit(est_p, ref_p, keep, method, n_first=25, est_q=est_q, ref_q=ref_q)
    first = rows & (np.arange(len(rows)) < 25)
    _, _, tf_rows25 = fit(est_p[keep], ref_p[keep], first, method, est_q=est_q[keep], ref_q=ref_q[keep])
    for a, b in zip(_transform_arrays(tf_first), _transform_arrays(tf_rows25), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=SAME_TOL)
    assert not np.allclose(np.asarray(tf_first.translation), np.asarray(tf_mask.translation))


@pytest.mark.parametrize("method", ["sim3"])  # posyaw and se3 share the weighted moments with sim3
def test_integer_weights_equal_repeated_rows(method):
    est_p, _, ref_p, _ = random_pair(12)
    weights = np.random.default_rng(6).integers(0, 4, size=len(est_p))
    _, _, tf_weighted = fit(est_p, ref_p, weights.astype(float), method)
    rows = np.repeat(np.arange(len(est_p)), weights)
    _, _, tf_rows = fit(est_p[rows], ref_p[rows], np.ones(len(rows), bool), method)
    for a, b in zip(_transform_arrays(tf_weighted), _transform_arrays(tf_rows), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=SAME_TOL)


@pytest.mark.parametrize("method", ["se3", "sim3", "posyaw"])
def test_degenerate_input_gives_identity_not_nan(method):
    est_p, _, ref_p, _ = random_pair(13)
    n = len(est_p)
    two = np.zeros(n, bool)
    two[[4, 9]] = True
    same_est = np.tile(est_p[:1], (n, 1))
    same_ref = np.tile(ref_p[:1], (n, 1))
    cases = [
        (est_p, ref_p, two),
        (est_p, ref_p, np.zeros(n, bool)),
        (same_est, ref_p, np.ones(n, bool)),
        (est_p, same_ref, np.ones(n, bool)),
    ]
    for e, r, m in cases:
        aligned, _, tf = fit(e, r, m, method)
        assert bool(tf.degenerate)
        np.testing.assert_array_equal(np.asarray(tf.rotation), np.eye(3))
        np.testing.assert_array_equal(np.asarray(aligned), e)
        stats = ape_statistics(aligned, jnp.asarray(r), jnp.asarray(m))
        assert all(np.isfinite(float(getattr(stats, s))) for s in STATS)
    # Far from the origin, a non-degenerate trajectory is not mistaken for identical points.
    _, _, tf = fit(est_p + 1e5, ref_p + 1e5, np.ones(n, bool), method)
    assert not bool(tf.degenerate)


def test_origin_and_none_edge_cases(unchecked):
    est_p, est_q, ref_p, ref_q = random_pair(14)
    n = len(est_p)
    _, _, tf = fit(est_p, ref_p, np.zeros(n, bool), "origin", est_q=est_q, ref_q=ref_q)
    assert bool(tf.degenerate)
    aligned, aligned_q, tf = fit(est_p, ref_p, np.ones(n, bool), "none", est_q=est_q, ref_q=ref_q)
    np.testing.assert_array_equal(np.asarray(aligned), est_p)
    np.testing.assert_allclose(np.asarray(aligned_q), est_q, atol=1e-15)
    assert not bool(tf.degenerate)
    with pytest.raises(ValueError, match="needs est_q and ref_q"):
        align(*jnp_all(est_p, ref_p), jnp.ones(n, bool), method="origin")
    with pytest.raises(ValueError, match="method must be one of"):
        align(*jnp_all(est_p, ref_p), jnp.ones(n, bool), method="sim(3)")
    with unchecked(), pytest.raises(ValueError, match="ref_p has 9 frames"):
        align(*jnp_all(est_p, ref_p[:9]), jnp.ones(n, bool), method="se3")
    with pytest.raises(ValueError, match="n_first"):
        align(*jnp_all(est_p, ref_p), jnp.ones(n, bool), method="se3", n_first=0)


def test_statistics_definitions_on_hand_made_errors():
    """Errors 3, 4, 12 and 1 (masked out: 100) along x: numpy's definitions, even-count median."""
    n = 120  # the shape the other tests compile for
    err = np.zeros(n)
    err[:5] = [3.0, 100.0, 4.0, 12.0, 1.0]
    ref = np.zeros((n, 3))
    est = np.stack([err, np.zeros(n), np.zeros(n)], axis=1)
    mask = np.zeros(n, bool)
    mask[:5] = [True, False, True, True, True]
    s = ape_statistics(*jnp_all(est, ref), jnp.asarray(mask))
    e = err[mask]
    expected = dict(
        rmse=np.sqrt(np.mean(e**2)),
        mean=e.mean(),
        median=3.5,
        std=e.std(ddof=0),
        min=1.0,
        max=12.0,
        sse=np.sum(e**2),
    )
    for name, value in expected.items():
        np.testing.assert_allclose(float(getattr(s, name)), value, rtol=1e-14, err_msg=name)
    assert int(s.count) == 4
    odd = ape_statistics(*jnp_all(est, ref), jnp.asarray(mask & (err != 1.0)))
    assert float(odd.median) == 4.0
    empty = ape_statistics(*jnp_all(est, ref), jnp.zeros(n, bool))
    assert int(empty.count) == 0 and all(float(getattr(empty, name)) == 0.0 for name in STATS)


# ----------------------------------------------------------------------------------------------------------
# eager == jit == vmap, and gradients


def _batch(n_runs=3, n_frames=120):
    """Stacked random runs; 120 frames like the single-run tests, so that their compilations are reused."""
    pairs = [random_pair(20 + i, n_frames=n_frames) for i in range(n_runs)]
    est_p, est_q, ref_p, ref_q = (np.stack(x) for x in zip(*pairs, strict=True))
    mask = np.random.default_rng(3).random((n_runs, n_frames)) < 0.8
    return jnp_all(est_p, est_q, ref_p, ref_q, mask)


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def test_weighted_rmse_definition_jit_vmap_and_grad():
    """The objective's RMSE: sqrt(sum w |e|^2 / sum w) as numpy computes it, under jit and vmap (a loop),
    equal to ape_statistics' rmse for 0/1 weights, 0 for no weight, differentiable (central difference)."""
    est_p, _, ref_p, _ = random_pair(40, n_frames=12, noise=0.5)
    rng = np.random.default_rng(40)
    weights = np.stack([rng.uniform(0, 1, 12), (rng.uniform(0, 1, 12) > 0.3).astype(float), np.zeros(12)])
    expected = [np.sqrt(w @ np.sum((est_p - ref_p) ** 2, -1) / w.sum()) if w.any() else 0.0 for w in weights]
    e, r, ws = jnp_all(est_p, ref_p, weights)
    direct = [float(weighted_rmse(e, r, w)) for w in ws]
    np.testing.assert_allclose(direct, expected, rtol=1e-12)
    np.testing.assert_allclose(
        jax.vmap(jax.jit(weighted_rmse), in_axes=(None, None, 0))(e, r, ws), direct, rtol=1e-15
    )
    mask = jnp.asarray(weights[1] > 0)
    np.testing.assert_allclose(direct[1], float(ape_statistics(e, r, mask).rmse), rtol=1e-12)
    h = 1e-6  # central difference: truncation ~h^2, rounding ~1e-16 x loss / h (~1e-9 for metres)
    bumps = h * jnp.eye(36).reshape(36, 12, 3)
    loss = functools.partial(weighted_rmse, ref_p=r, weight=ws[0])
    fd = (jax.vmap(loss)(e + bumps) - jax.vmap(loss)(e - bumps)) / (2 * h)
    np.testing.assert_allclose(
        np.asarray(jax.grad(loss)(e)), np.asarray(fd).reshape(12, 3), rtol=1e-6, atol=1e-8
    )
    assert np.all(np.asarray(jax.grad(loss)(r)) == 0.0)  # zero error: a finite (zero) gradient, not NaN


def test_align_and_statistics_direct_jit_vmap():
    """A direct call per run == jit(vmap) over runs, for each alignment code path (se3 is sim3 without c).

    The public functions are jit-compiled themselves: the direct call is what a user runs outside jit; the
    vmapped kernel traces them inside an outer jit and a batch transformation.
    """
    est_p, est_q, ref_p, ref_q, mask = _batch()

    def kernel(ep, eq, rp, rq, m):
        out = {}
        for method, n_first in (("sim3", 25), ("posyaw", 25), ("origin", None), ("none", None)):
            quats = dict(est_q=eq, ref_q=rq) if method in ("origin", "none") else {}
            aligned, aligned_q, tf = align(ep, rp, m, method=method, n_first=n_first, **quats)
            out[method] = (aligned, aligned_q, tf, ape_statistics(aligned, rp, m))
        return out

    stacked = _stack([kernel(est_p[i], est_q[i], ref_p[i], ref_q[i], mask[i]) for i in range(len(est_p))])
    tree_allclose(jax.jit(jax.vmap(kernel))(est_p, est_q, ref_p, ref_q, mask), stacked)


def _segmented_batch():
    """Three 100-frame runs: one segment; two segments with a gap; three segments (40, 30, 20 frames)."""
    est_p, est_q, ref_p, ref_q, _ = _batch(n_runs=3, n_frames=100)
    segment = np.zeros((3, 100), np.int32)
    segment[1, 60:] = 1
    segment[2, 20:] = 2
    segment[2, 60:] = 3
    has = np.ones((3, 100), bool)
    has[1, 50:60] = False
    ref_valid = np.ones((3, 100), bool)
    ref_valid[0, :10] = False
    valid = np.ones((3, 100), bool)
    valid[2, 80:] = False  # run 2: segments of 20, 40 and 20 valid frames
    return est_p, est_q, jnp.asarray(has), jnp.asarray(segment), ref_p, ref_q, *jnp_all(ref_valid, valid)


@pytest.mark.parametrize(("method", "segments"), [("sim3", "largest"), ("origin", "all")])
def test_run_error_direct_vmap(method, segments):
    est_p, est_q, has, segment, ref_p, ref_q, ref_valid, valid = _segmented_batch()
    if method != "origin":
        est_q = ref_q = None  # as the single-run tests call it (their compilation is reused)
    args = (est_p, est_q, has, segment, ref_p, ref_q, ref_valid, valid)
    kw = dict(align=method, segments=segments, min_coverage=0.5)
    if segments == "all":
        kw["max_segments"] = 2
    runs = [run_error(*(None if a is None else a[i] for a in args), **kw) for i in range(3)]
    stacked = _stack(runs)
    # One vmapped block, or (origin-all) blocks of 2 runs one after another with a remainder block of 1.
    block = dict(runs_per_block=2) if segments == "all" else {}
    tree_allclose(batched_run_error(*args, **kw, **block), stacked)
    assert list(np.asarray(stacked.failed)) == [False, True, True]  # runs 1 and 2 have several segments
    assert list(np.asarray(stacked.n_segments)) == [1, 2, 3]
    # "all" with max_segments=2 aligns run 2's two largest segments (40 + 20 frames); "largest" the 40.
    assert int(stacked.stats.count[2]) == (60 if segments == "all" else 40)
    np.testing.assert_allclose(float(stacked.coverage[0]), 1.0)


def _loss(est_p, ref_p, mask, est_q, ref_q, method):
    aligned, _, _ = align(est_p, ref_p, mask, method=method, est_q=est_q, ref_q=ref_q)
    s = ape_statistics(aligned, ref_p, mask)
    return s.rmse + 0.5 * s.mean + 0.25 * s.std + 0.1 * s.median + 0.1 * s.max


@functools.cache
def _grad_and_fd(method: str, n_frames: int):
    """Compiled once per method: (jax.grad of _loss, its central difference), for [n_frames, 3] positions."""
    h = 1e-6  # central difference: truncation ~h^2, rounding ~1e-16 / h; both far below the tolerance
    bumps = h * jnp.eye(3 * n_frames).reshape(3 * n_frames, n_frames, 3)

    def both(est_p, ref_p, mask, est_q, ref_q):
        loss = functools.partial(_loss, ref_p=ref_p, mask=mask, est_q=est_q, ref_q=ref_q, method=method)
        fd = (jax.vmap(loss)(est_p + bumps) - jax.vmap(loss)(est_p - bumps)) / (2 * h)
        return jax.grad(loss)(est_p), fd.reshape(n_frames, 3)

    return jax.jit(both)


@pytest.mark.parametrize("method", ["sim3", "posyaw", "origin"])  # se3's path is sim3's without the scale
def test_grad_equals_central_difference(method):
    est_p, est_q, ref_p, ref_q = jnp_all(*random_pair(30, n_frames=12, noise=0.5))
    mask = jnp.ones(12, bool).at[3].set(False)
    grad, fd = _grad_and_fd(method, 12)(est_p, ref_p, mask, est_q, ref_q)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(fd), rtol=1e-6, atol=1e-8)
    assert np.all(np.asarray(grad)[3] == 0.0)  # an unmasked frame does not move the error


@pytest.mark.parametrize("method", ["sim3", "posyaw", "origin"])
def test_grad_is_finite_for_degenerate_input(method):
    est_p, est_q, ref_p, ref_q = jnp_all(*random_pair(31, n_frames=12))
    padded_est = est_p.at[6:].set(0.0)
    padded_ref = ref_p.at[6:].set(
        0.0
    )  # padding: zero error outside the mask, where a plain norm has NaN grad
    same = jnp.tile(est_p[:1], (12, 1))
    grad_fn = _grad_and_fd(method, 12)
    for n_masked in (0, 1, 2, 12):
        mask = jnp.arange(12) < n_masked
        for e, r in ((est_p, ref_p), (padded_est, padded_ref), (same, ref_p)):
            grad, _ = grad_fn(e, r, mask, est_q, ref_q)
            assert np.all(np.isfinite(np.asarray(grad))), (method, n_masked)


def test_run_error_grad_equals_central_difference():
    est_p, est_q, ref_p, ref_q = jnp_all(*random_pair(32, n_frames=10, noise=0.5))
    n = 10
    segment = jnp.zeros(n, jnp.int32).at[7:].set(1)
    ones = jnp.ones(n, bool)
    h = 1e-6
    bumps = h * jnp.eye(3 * n).reshape(3 * n, n, 3)

    def loss(p):
        return run_error(
            p, est_q, ones, segment, ref_p, ref_q, ones, ones, align="sim3", segments="all"
        ).stats.rmse

    @jax.jit
    def both(p):
        return jax.grad(loss)(p), (jax.vmap(loss)(p + bumps) - jax.vmap(loss)(p - bumps)) / (2 * h)

    grad, fd = both(est_p)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(fd).reshape(n, 3), rtol=1e-6, atol=1e-8)
    assert np.all(np.isfinite(np.asarray(grad)))


# ----------------------------------------------------------------------------------------------------------
# run_error on hand-made runs


def _two_segment_run(noise=0.05):
    """100 frames; segment 0 = frames 0-39, no estimate 40-49 (lost), segment 1 = frames 50-99.

    Each segment is the reference seen through its own similarity transform, as a new map would be.
    """
    rng = np.random.default_rng(40)
    _, _, ref_p, ref_q = random_pair(40, n_frames=100)
    est_p = np.zeros_like(ref_p)
    g0, g1 = Rotation.random(random_state=1), Rotation.random(random_state=2)
    est_p[:40] = g0.apply(ref_p[:40]) + [5.0, 0.0, 0.0]
    est_p[50:] = 0.5 * g1.apply(ref_p[50:]) + [0.0, -3.0, 1.0]
    est_p += rng.normal(scale=noise, size=est_p.shape)
    has = np.ones(100, bool)
    has[40:50] = False
    segment = np.zeros(100, np.int32)
    segment[50:] = 1
    segment[40:50] = -1  # ids of frames without an estimate are ignored
    return est_p, ref_p, ref_q, has, segment


def _score(est_p, ref_p, has, segment, ref_valid=None, valid=None, **kw):
    n = len(est_p)
    ref_valid = np.ones(n, bool) if ref_valid is None else ref_valid
    valid = np.ones(n, bool) if valid is None else valid
    kw.setdefault("align", "sim3")
    return run_error(
        jnp.asarray(est_p),
        None,
        jnp.asarray(has),
        jnp.asarray(segment),
        jnp.asarray(ref_p),
        None,
        jnp.asarray(ref_valid),
        jnp.asarray(valid),
        **kw,
    )


def test_run_error_segment_selection_and_coverage():
    est_p, ref_p, _, has, segment = _two_segment_run()
    largest = _score(est_p, ref_p, has, segment)
    assert int(largest.segment) == 1 and int(largest.n_segments) == 2 and bool(largest.failed)
    assert int(largest.stats.count) == 50 and float(largest.coverage) == 0.5
    first = _score(est_p, ref_p, has, segment, segments="first")
    assert int(first.segment) == 0 and int(first.stats.count) == 40 and float(first.coverage) == 0.4

    # "all": each segment aligned on its own, errors pooled; equals aligning the two row sets by masks.
    pooled = _score(est_p, ref_p, has, segment, segments="all")
    errs = []
    for rows in (np.arange(100) < 40, np.arange(100) >= 50):
        aligned, _, _ = fit(est_p, ref_p, rows, "sim3")
        errs.append(np.linalg.norm(np.asarray(aligned) - ref_p, axis=1)[rows])
    e = np.concatenate(errs)
    assert int(pooled.stats.count) == 90 and float(pooled.coverage) == 0.9 and int(pooled.segment) == -1
    np.testing.assert_allclose(float(pooled.stats.rmse), np.sqrt(np.mean(e**2)), atol=SAME_TOL)
    np.testing.assert_allclose(float(pooled.stats.median), np.median(e), atol=SAME_TOL)
    assert bool(pooled.failed)  # more than one segment: still failed
    # One alignment across both maps would be far worse: segments matter.
    across, _, _ = fit(est_p, ref_p, has, "sim3")
    across_rmse = float(ape_statistics(across, jnp.asarray(ref_p), jnp.asarray(has)).rmse)
    assert across_rmse > 10 * float(pooled.stats.rmse)


def test_run_error_coverage_counts_ground_truth_and_padding():
    est_p, ref_p, _, has, segment = _two_segment_run()
    ref_valid = np.ones(100, bool)
    ref_valid[:20] = False  # no ground truth: neither evaluated nor in the denominator
    valid = np.ones(100, bool)
    valid[90:] = False  # padding
    r = _score(est_p, ref_p, has, segment, ref_valid, valid)
    # Both segments have 40 estimated frames inside the run; segment 1 has more with ground truth (40 vs 20).
    assert int(r.segment) == 1 and int(r.stats.count) == 40
    np.testing.assert_allclose(float(r.coverage), 40 / 70, rtol=1e-15)  # frames 20-89 have ground truth


def test_run_error_failed_flag():
    est_p, ref_p, _, _, _ = _two_segment_run()
    segment = np.ones(100, np.int32)
    gt = np.arange(100) >= 50  # ground truth only where the (single) segment lies: full coverage
    has = gt.copy()
    clean = _score(est_p, ref_p, has, segment, gt)
    assert not bool(clean.failed) and int(clean.n_segments) == 1 and float(clean.coverage) == 1.0
    assert not bool(_score(est_p, ref_p, has, segment, gt, min_coverage=1.0).failed)
    short = gt & (np.arange(100) < 60)
    low = _score(est_p, ref_p, short, segment, gt, min_coverage=0.5)
    assert bool(low.failed) and float(low.coverage) == 0.2
    assert not bool(_score(est_p, ref_p, short, segment, gt, min_coverage=0.1).failed)
    two = gt & (np.arange(100) < 52)
    tiny = _score(est_p, ref_p, two, segment, gt)
    assert bool(tiny.failed) and int(tiny.stats.count) == 0  # degenerate segment: nothing evaluated
    tiny_none = _score(est_p, ref_p, two, segment, gt, align="none")
    assert bool(tiny_none.failed) and int(tiny_none.stats.count) == 2  # scored, but fewer than 3 frames
    nothing = _score(est_p, ref_p, np.zeros(100, bool), segment)
    assert bool(nothing.failed) and int(nothing.n_segments) == 0 and float(nothing.coverage) == 0.0


def test_run_error_names_its_failure_causes():
    est_p, ref_p, _, has_two, segment_two = _two_segment_run()
    segment = np.ones(100, np.int32)
    gt = np.arange(100) >= 50
    causes = {
        "": _score(est_p, ref_p, gt, segment, gt),
        "coverage below min_coverage": _score(
            est_p, ref_p, gt & (np.arange(100) < 60), segment, gt, min_coverage=0.5
        ),
        "fewer than 3 evaluated frames; degenerate alignment": _score(
            est_p, ref_p, gt & (np.arange(100) < 52), segment, gt
        ),
        "several map segments": _score(est_p, ref_p, has_two, segment_two),
    }
    for reason, r in causes.items():
        assert failure_reason(r.failure) == reason and bool(r.failed) == bool(reason)


@pytest.mark.parametrize("align", ["sim3", "se3", "origin", "none"])
@pytest.mark.parametrize("how", ["overflow", "nan"])
def test_a_non_finite_intermediate_fails_the_run_and_never_scores_a_number(align, how):
    # Issue 12: float32 squares of 1e20 m overflow to inf, and the guards turned the NaN that followed
    # into an RMSE of 0.0 m, a perfect score. Now the statistics stay non-finite and the run fails.
    _, _, ref_p, ref_q = random_pair(7, n_frames=50)
    est_p = (ref_p + 0.01).astype(np.float32)
    if how == "overflow":
        est_p[10] = 1e20
    else:
        est_p[10, 1] = np.nan
    q = jnp.asarray(ref_q, jnp.float32)
    ones = jnp.ones(50, bool)
    args = (
        jnp.asarray(est_p),
        q,
        ones,
        jnp.zeros(50, jnp.int32),
        jnp.asarray(ref_p, jnp.float32),
        q,
        ones,
        ones,
    )
    r = run_error(*args, align=align)
    # (an inf moment makes the alignment degenerate: nothing is evaluated, and the table says NaN)
    assert bool(r.failed) and "non-finite error statistics" in failure_reason(r.failure)
    table = per_run_table(jax.tree.map(lambda x: x[None], r), pd.DataFrame({"run": [0]}))
    assert bool(table["failed"][0]) and "non-finite" in table["failure_reason"][0]
    assert not np.isfinite(table["rmse"][0])
    est_p[10] = ref_p[10] + 0.01  # the same run without the bad value scores its 1 cm
    clean = run_error(jnp.asarray(est_p), *args[1:], align=align)
    assert not bool(clean.failed) and failure_reason(clean.failure) == ""


def test_lost_run_with_lower_error_is_still_failed():
    """evo issue #673: a run that lost tracking can score a lower APE than one that did not."""
    rng = np.random.default_rng(41)
    _, _, ref_p, _ = random_pair(41, n_frames=100)
    complete = ref_p + rng.normal(scale=0.5, size=ref_p.shape)
    lost = ref_p + rng.normal(scale=0.1, size=ref_p.shape)
    has_lost = np.arange(100) < 50
    segment = np.zeros(100, np.int32)
    r_complete = _score(complete, ref_p, np.ones(100, bool), segment, min_coverage=0.9)
    r_lost = _score(lost, ref_p, has_lost, segment, min_coverage=0.9)
    assert float(r_lost.stats.rmse) < float(r_complete.stats.rmse)
    assert bool(r_lost.failed) and not bool(r_complete.failed)
    assert float(r_lost.coverage) == 0.5


def test_run_error_rejects_bad_segment_ids_and_configuration(unchecked):
    est_p, ref_p, _, has, segment = _two_segment_run()
    bad = segment.copy()
    bad[70] = 100  # an estimated frame with an id outside [0, T)
    # Under jit, JAX re-raises equinox's error from a host callback as a runtime error (its class varies with
    # the JAX version and dispatch path); the message is what identifies it. Dispatch is asynchronous: the
    # error surfaces when the result is awaited.
    with pytest.raises(Exception, match="segment ids of frames with an estimate must lie in"):
        jax.block_until_ready(_score(est_p, ref_p, has, bad))
    with pytest.raises(ValueError, match="segments must be one of"):
        _score(est_p, ref_p, has, segment, segments="longest")
    with unchecked(), pytest.raises(ValueError, match="has_estimate must have shape"):
        _score(est_p, ref_p, has[:99], segment)


# ----------------------------------------------------------------------------------------------------------
# jsve ape


@pytest.fixture
def cli(monkeypatch):
    """jsve.cli.main with only the `ape` subcommand registered (independent of the other subcommands)."""
    monkeypatch.setattr(jsve.cli, "SUBCOMMANDS", ("ape",))
    return jsve.cli.main


def test_cli_kitti_matches_evo(cli, capsys, kitti, tmp_path):
    root, ref, est, noisy = kitti
    noisy_path = tmp_path / "noisy.txt"
    file_interface.write_kitti_poses_file(noisy_path, noisy)
    est_path = root / "orbslam_estimate_00.txt"
    gt_path = root / "odometry_poses" / "00.txt"
    csv_path = tmp_path / "table.csv"
    argv = ["ape", str(gt_path), str(est_path), str(noisy_path), "--format", "kitti", "--align", "se3"]
    assert cli([*argv, "--json", "-o", str(csv_path)]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["estimate"] for r in rows] == [str(est_path), str(noisy_path)]
    for row, traj in zip(rows, (est, noisy), strict=True):
        expected = _evo_stats(ref, traj, "se3")
        for name in STATS:
            np.testing.assert_allclose(row[name], expected[name], rtol=0, atol=EVO_TOL, err_msg=name)
        assert row["count"] == est.num_poses and row["failed"] is False
    table = pd.read_csv(csv_path)
    assert list(table["estimate"]) == [str(est_path), str(noisy_path)]
    np.testing.assert_allclose(table["rmse"], [r["rmse"] for r in rows], rtol=1e-12)
    # The table printed without --json carries the same numbers (6 decimals), after evo's title and the
    # alignment used.
    assert cli(argv) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[:2] == [
        "APE w.r.t. translation part (m) (with SE(3) Umeyama alignment)",
        "aligned: SE(3) Umeyama (evo -a)",
    ]
    assert printed[2].split()[:3] == ["estimate", "rmse", "mean"]
    assert float(printed[3].split()[1]) == pytest.approx(rows[0]["rmse"], abs=1e-6)


def test_cli_tum_associates_pads_and_matches_evo(cli, capsys, kitti, tmp_path):
    """TUM files with different lengths and time offsets: evo's association, then one padded batch."""
    root, ref, est, _ = kitti
    times = np.loadtxt(root / "times_00.txt")[:600]
    n = len(times)
    ref_tum = PoseTrajectory3D(poses_se3=ref.poses_se3[:n], timestamps=times)
    est_a = PoseTrajectory3D(poses_se3=est.poses_se3[:n], timestamps=times + 0.002)
    est_b = PoseTrajectory3D(poses_se3=est.poses_se3[100:n:2], timestamps=times[100::2])
    paths = []
    for name, traj in (("ref", ref_tum), ("a", est_a), ("b", est_b)):
        paths.append(tmp_path / f"{name}.tum")
        file_interface.write_tum_trajectory_file(paths[-1], traj)
    before = jax.config.jax_enable_x64
    rc = cli(["ape", *map(str, paths), "--align", "sim3", "--json", "--n-to-align", "200"])
    assert rc == 0 and jax.config.jax_enable_x64 == before
    rows = json.loads(capsys.readouterr().out)
    ref_read = file_interface.read_tum_trajectory_file(paths[0])
    for row, path in zip(rows, paths[1:], strict=True):
        r, e = sync.associate_trajectories(
            ref_read, file_interface.read_tum_trajectory_file(path), max_diff=0.01
        )
        e.align(r, correct_scale=True, n=200)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((r, e))
        for name in STATS:
            np.testing.assert_allclose(row[name], ape.get_all_statistics()[name], rtol=0, atol=EVO_TOL)
        assert row["count"] == e.num_poses
    assert [row["count"] for row in rows] == [n, len(est_b.timestamps)]


def test_cli_unreadable_and_unmatched_files_exit_2(cli, capsys, kitti, tmp_path):
    root, _, _, _ = kitti
    gt = str(root / "odometry_poses" / "00.txt")
    assert cli(["ape", gt, str(tmp_path / "missing.txt"), "--format", "kitti"]) == 2
    assert "missing.txt" in capsys.readouterr().err
    garbage = tmp_path / "garbage.txt"
    garbage.write_text("not a pose\n1 2\n")
    assert cli(["ape", gt, str(garbage), "--format", "kitti"]) == 2
    assert "garbage.txt" in capsys.readouterr().err
    assert cli(["ape", gt, str(root / "odometry_poses" / "01.txt"), "--format", "kitti"]) == 2
    assert "same length" in capsys.readouterr().err


def test_cli_prints_why_an_estimate_failed(cli, capsys, kitti, tmp_path):
    """A failed estimate's row says why (failure_reason), in the table, the JSON and the CSV; a good one's
    reason is empty."""
    root, ref, est, _ = kitti
    times = np.loadtxt(root / "times_00.txt")[:100]
    ref_tum = PoseTrajectory3D(poses_se3=ref.poses_se3[:100], timestamps=times)
    good = PoseTrajectory3D(poses_se3=est.poses_se3[:100], timestamps=times)
    short = PoseTrajectory3D(poses_se3=est.poses_se3[:2], timestamps=times[:2])  # 2 poses: cannot align
    paths = [tmp_path / f"{name}.tum" for name in ("ref", "good", "short")]
    for path, traj in zip(paths, (ref_tum, good, short), strict=True):
        file_interface.write_tum_trajectory_file(path, traj)
    csv_path = tmp_path / "table.csv"
    assert cli(["ape", *map(str, paths), "--json", "-o", str(csv_path)]) == 0
    rows = json.loads(capsys.readouterr().out)
    reason = "fewer than 3 evaluated frames; degenerate alignment"
    assert [(r["failed"], r["failure_reason"]) for r in rows] == [(False, ""), (True, reason)]
    assert rows[1]["rmse"] is None
    assert list(pd.read_csv(csv_path, keep_default_na=False)["failure_reason"]) == ["", reason]
    assert cli(["ape", *map(str, paths)]) == 0
    _, _, header, first, second = capsys.readouterr().out.splitlines()  # after the title and alignment
    assert header.split()[-2:] == ["failed", "failure_reason"]
    assert second.endswith(reason) and not first.rstrip().endswith(reason)
