"""jsve.core._align: the registry of alignment methods and the least-squares solve from weighted moments.

evo checks every method through `align` (tests/test_trajectory.py) and the search kernel checks its moments
against the objective (tests/test_search.py); here: the moments against numpy's weighted formulas, the
solvers broadcast over leading axes (the kernel's [settings, runs]) as a loop would, and a method added to
the registry alone reaches `align`, the objective and the search kernel, with the right answer.

Tolerances: 1e-12 between numpy and JAX in float64 (summation order); 1e-10 between two jsve code paths
(batched vs looped solves); the kernel in float64 to 1e-12 m against the objective, as tests/test_search.py.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pytest

from jsve.core._align import (
    ALIGN_METHODS,
    ALIGNERS,
    Aligner,
    AlignMethod,
    Moments,
    fit_moments,
    is_degenerate,
    moments_from_points,
)
from jsve.core._objective import ObjectiveConfig, run_losses
from jsve.core._replay import batch_features, replay
from jsve.core._trajectory import align
from jsve.fitting._kernel import prepare, search_chunk
from jsve.fitting._space import inlier_space
from jsve.io._batching import from_runs

pytestmark = pytest.mark.usefixtures("x64")


def test_method_names_come_from_the_registry():
    assert ALIGN_METHODS == tuple(ALIGNERS) == typing.get_args(AlignMethod)
    assert [name for name, a in ALIGNERS.items() if a.first_pose] == ["origin"]
    assert [name for name, a in ALIGNERS.items() if a.identity] == ["none"]


def _points(seed: int, n: int = 50):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)) * [3.0, 2.0, 0.5] + 10.0
    y = x @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T * 1.3 + rng.normal(size=(n, 3)) * 0.1 - 4.0
    w = rng.uniform(0.0, 1.0, n) * (rng.uniform(size=n) > 0.2)
    return x, y, w


def test_moments_are_the_weighted_averages():
    x, y, w = _points(0)
    m = moments_from_points(*map(jnp.asarray, (x, y, w)))
    wn = w / w.sum()
    mu_x, mu_y = wn @ x, wn @ y
    np.testing.assert_allclose(np.asarray(m.mu_x), mu_x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(m.mu_y), mu_y, rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(m.var_x), wn @ np.sum((x - mu_x) ** 2, -1), rtol=1e-12)
    np.testing.assert_allclose(float(m.var_y), wn @ np.sum((y - mu_y) ** 2, -1), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(m.cov), ((y - mu_y) * wn[:, None]).T @ (x - mu_x), atol=1e-12)
    assert int(m.count) == int(np.sum(w > 0))


def test_degeneracy():
    x, y, w = map(jnp.asarray, _points(1))
    assert not bool(is_degenerate(moments_from_points(x, y, w)))
    two = jnp.zeros_like(w).at[:2].set(1.0)  # fewer than MIN_ALIGNMENT_FRAMES
    assert bool(is_degenerate(moments_from_points(x, y, two)))
    same = jnp.broadcast_to(x[:1], x.shape) + 1e-14  # identical points, relative to their size
    assert bool(is_degenerate(moments_from_points(same, y, w)))
    assert bool(is_degenerate(moments_from_points(x, same, w)))


@pytest.mark.parametrize("method", [m for m, a in ALIGNERS.items() if a.solve is not None])
def test_batched_solve_equals_a_loop(method):
    """The kernel solves [settings, runs] alignments at once: leading axes broadcast as a loop, and vmap."""
    solve = ALIGNERS[method].solve
    assert solve is not None
    each = [moments_from_points(*map(jnp.asarray, _points(seed))) for seed in range(6)]
    stack = lambda *trees: jax.tree.map(lambda *xs: jnp.stack(xs), *trees)  # noqa: E731
    flat = stack(*each)  # a leading axis of 6
    grid = jax.tree.map(lambda x: x.reshape((2, 3) + x.shape[1:]), flat)  # [settings, runs]
    looped = stack(*(fit_moments(m, solve) for m in each))
    batched = jax.jit(fit_moments, static_argnums=1)(grid, solve)
    batched = jax.tree.map(lambda x: x.reshape((6,) + x.shape[2:]), batched)
    vmapped = jax.vmap(fit_moments, in_axes=(0, None))(flat, solve)
    for result in (batched, vmapped):
        for got, expected in zip(jax.tree.leaves(result), jax.tree.leaves(looped), strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0, atol=1e-10)


def _translation_only(m: Moments, degenerate):
    """A least-squares method that is not built in: rotation I, scale 1 (the translation then follows)."""
    return jnp.broadcast_to(jnp.eye(3, dtype=m.cov.dtype), m.cov.shape), jnp.ones_like(m.var_x)


def test_a_registered_method_reaches_align_the_objective_and_the_kernel(monkeypatch):
    monkeypatch.setitem(ALIGNERS, "translation", Aligner(_translation_only))
    # align: the estimate shifted by the weighted mean offset
    x, y, w = _points(2)
    aligned, _, tf = align(*map(jnp.asarray, (x, y, w)), method="translation")
    offset = (w / w.sum()) @ (y - x)
    np.testing.assert_allclose(np.asarray(aligned), x + offset, atol=1e-12)
    assert not bool(tf.degenerate)
    # the objective and the search kernel, setting by setting
    runs = ka.make_study("occlusion", range(3), n_frames=120)
    batch = from_runs(runs, dtype=jnp.float64).batch
    features = batch_features(batch)
    config = ObjectiveConfig(align="translation", failure_penalty=3.0)
    space = inlier_space()
    rules = space.rule(
        jnp.asarray(space.values_from_unit(jnp.linspace(0.1, 0.9, 4)[:, None] * jnp.ones(space.dim)))
    )
    got = search_chunk(prepare(batch, features), rules, config)
    expected = jax.vmap(lambda r: run_losses(batch, r, features, config))(rules)
    np.testing.assert_array_equal(np.asarray(got.failed), np.asarray(expected.failed))
    np.testing.assert_allclose(np.asarray(got.loss), np.asarray(expected.loss), rtol=0, atol=1e-12)
    # and the objective's RMSE is the translation-only residual of the replayed trajectory
    ok = ~np.asarray(expected.failed)
    assert ok.any()
    result = replay(batch, jax.tree.map(lambda leaf: leaf[0], rules), features)
    for r in np.flatnonzero(ok[0]):
        sel = np.asarray(batch.gt_valid[r] & batch.valid[r])
        est, gt = np.asarray(result.position[r])[sel], np.asarray(batch.gt_p[r])[sel]
        residual = est + (gt - est).mean(axis=0) - gt
        np.testing.assert_allclose(
            float(expected.rmse[0, r]), np.sqrt(np.mean(np.sum(residual**2, -1))), rtol=1e-10
        )


# ----------------------------------------------------------------------------------------------------------
# posyaw's vertical: y_is_vertical


def _planar_walk(n: int, seed: int, normal_axis: int, lift: float = 0.02) -> np.ndarray:
    """A random walk in the plane normal to `normal_axis`, with `lift` metres of noise along it."""
    rng = np.random.default_rng(seed)
    p = np.cumsum(rng.normal(scale=1.0, size=(n, 3)), axis=0)
    p[:, normal_axis] = rng.normal(scale=lift, size=n)
    return p


def test_y_is_vertical_on_synthetic_paths():
    from jsve.core._align import y_is_vertical

    ones = jnp.ones(300, bool)
    assert bool(y_is_vertical(jnp.asarray(_planar_walk(300, 1, normal_axis=1)), ones))  # KITTI-like: y down
    assert not bool(y_is_vertical(jnp.asarray(_planar_walk(300, 2, normal_axis=2)), ones))  # z up
    assert not bool(y_is_vertical(jnp.asarray(_planar_walk(300, 3, normal_axis=1, lift=5.0)), ones))  # 3-D
    # a masked-out excursion along y does not count; fewer than 3 frames is never vertical
    p = _planar_walk(300, 4, normal_axis=1)
    p[250:, 1] += 100.0
    mask = jnp.arange(300) < 250
    assert bool(y_is_vertical(jnp.asarray(p), mask)) and not bool(y_is_vertical(jnp.asarray(p), ones))
    assert not bool(y_is_vertical(jnp.asarray(p), jnp.arange(300) < 2))


def test_y_is_vertical_eager_jit_and_vmap_equal_a_loop():
    from jsve.core._align import y_is_vertical

    paths = jnp.asarray(np.stack([_planar_walk(120, s, normal_axis=s % 3) for s in range(6)]))
    masks = jnp.arange(120)[None, :] < jnp.asarray([120, 100, 80, 60, 40, 2])[:, None]
    loop = [bool(y_is_vertical(p, m)) for p, m in zip(paths, masks, strict=True)]
    assert loop == [bool(jax.jit(y_is_vertical)(p, m)) for p, m in zip(paths, masks, strict=True)]
    assert np.asarray(jax.vmap(y_is_vertical)(paths, masks)).tolist() == loop
    assert loop[1] and not loop[0] and not loop[5]  # normals along y (s=1), x (s=0); 2 frames


def test_y_is_vertical_on_real_trajectories(shared_data):
    """Every KITTI odometry ground truth (left camera frame: y down) is flagged but 04, a straight road
    (0.17 m of spread across it, 2.25 m along y: no plane to find); no EuRoC flight (z up) is."""
    from evo.tools import file_interface

    from jsve.core._align import y_is_vertical

    def flagged(positions) -> bool:
        return bool(y_is_vertical(jnp.asarray(positions), jnp.ones(len(positions), bool)))

    kitti = sorted((shared_data / "kitti" / "odometry_poses").glob("*.txt"))
    euroc = sorted((shared_data / "euroc" / "groundtruth_left_cam").glob("*.txt"))
    assert len(kitti) == 11 and len(euroc) == 11
    found = [p.stem for p in kitti if flagged(file_interface.read_kitti_poses_file(p).positions_xyz)]
    assert found == [p.stem for p in kitti if p.stem != "04"]
    assert not any(flagged(file_interface.read_euroc_csv_trajectory(p).positions_xyz) for p in euroc)
