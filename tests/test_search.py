"""jsve.fitting._search: the fused search kernel (designs: tests/test_designs.py; its IMU columns:
tests/test_imu.py).

Oracles: the rules' own score for the score columns, and jsve.core._objective.run_losses (replay +
alignment, itself checked against jsve.evaluation._evaluate) for the kernel, setting by setting.
"""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pytest

from jsve.core._machine import SWITCH_MODELS
from jsve.core._objective import ObjectiveConfig, run_losses
from jsve.core._replay import batch_features
from jsve.core._rules import Thresholds
from jsve.core._sve import feature_logs
from jsve.fitting._designs import sobol
from jsve.fitting._fit import FitData
from jsve.fitting._search import (
    prepare,
    score_columns,
    search,
    search_chunk,
)
from jsve.fitting._space import inlier_space, sve_space
from jsve.io._batching import from_runs

# ---------------------------------------------------------------------------------------------------
# The kernel


def test_score_columns_match_the_rules_score(x64):
    """score_columns (the kernel's score from shared feature logs) is the rule's own score, for 8 Sobol
    settings: to 1e-12 (float64; the log-domain form rounds differently, a few ulp measured)."""
    runs = ka.make_study("occlusion", range(2), n_frames=200)
    batch = from_runs(runs, dtype=jnp.float64).batch
    f = batch_features(batch)
    space = sve_space()
    values = space.values_from_unit(jnp.asarray(sobol(8, space.dim, seed=2)))
    for i in range(8):
        rule = space.rule(values[i])
        logs = feature_logs(f.inlier_ratio, f.s_b, f.s_c)
        np.testing.assert_allclose(
            np.asarray(score_columns(rule, f.n_inliers, *logs)),
            np.asarray(rule.score(f)),
            rtol=1e-12,
            atol=1e-14,
        )


@pytest.fixture(scope="module")
def occlusion_data():
    return FitData.from_runs(ka.make_study("occlusion", range(8), n_frames=400))


@pytest.mark.parametrize(
    ("align", "dtype"),
    [("se3", jnp.float64), ("se3", jnp.float32)]
    + [
        pytest.param(a, d, marks=pytest.mark.slow)
        for a in ("sim3", "posyaw", "none")
        for d in (jnp.float64, jnp.float32)
    ],
)
def test_search_kernel_equals_replay_objective(x64, align, dtype):
    """Setting by setting, the kernel's loss is run_losses' (replay + alignment + RMSE): to 1e-12 m in
    float64; in float32 to 1e-4 relative (the moment form's error budget, ~1e-5 measured) with the same
    failed flags. Both families, 24 Sobol settings each, failing and succeeding runs, under both switch
    models."""
    runs = ka.make_study("occlusion", range(6), n_frames=300)
    batch = from_runs(runs, dtype=dtype).batch
    f = batch_features(batch)
    sb = prepare(batch, f)
    configs = [ObjectiveConfig(align=align, failure_penalty=3.0, switch_model=m) for m in SWITCH_MODELS]
    for config, space in itertools.product(configs, (inlier_space(), sve_space())):
        values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
        thresholds = [space.names.index(field.name) for field in dataclasses.fields(Thresholds)]
        values[-3:, thresholds] = 2.0 * space.score_scale * 1e3  # thresholds no frame passes: runs fail
        rules = space.rule(jnp.asarray(values, dtype))
        got = search_chunk(sb, rules, config)
        ref = jax.jit(jax.vmap(lambda r, c=config: run_losses(batch, r, f, c)))(rules)
        failed = np.asarray(ref.failed)
        assert np.array_equal(np.asarray(got.failed), failed)
        assert 0 < failed.mean() < 1  # both kinds of runs are checked
        if dtype == jnp.float64:
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=0, atol=1e-12)
        else:
            # float32 positions of a few metres carry ~2e-7 m of rounding each, in both computations
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=1e-4, atol=2e-6)
        np.testing.assert_allclose(np.asarray(got.coverage)[~failed], 1.0)
        np.testing.assert_allclose(np.asarray(got.coverage), np.asarray(ref.coverage), rtol=0, atol=1e-6)
        assert np.isnan(np.asarray(got.rmse)[failed]).all()


@pytest.mark.slow
def test_search_kernel_eager_equals_jit(x64):
    """Op by op (jax.disable_jit) and compiled, the kernel gives the same results (to 1e-12 m)."""
    runs = ka.make_study("occlusion", range(2), n_frames=60)
    batch = from_runs(runs, dtype=jnp.float64).batch
    sb = prepare(batch, batch_features(batch))
    space = sve_space()
    rules = space.rule(jnp.asarray(space.values_from_unit(sobol(2, space.dim, seed=3))))
    jitted = search_chunk(sb, rules)
    with jax.disable_jit():
        eager = search_chunk(sb, rules)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=0, atol=1e-12)


def test_search_chunks_and_vmap_equal_a_loop(occlusion_data):
    """search() over chunks of settings (padded) equals one kernel call per setting (vmap = loop), to
    float32 rounding."""
    data = occlusion_data
    space = inlier_space()
    values = np.asarray(space.values_from_unit(sobol(13, space.dim, seed=5)))
    a = search(
        data.parts,
        space,
        values,
        data.config,
        run_counts=data.run_counts,
        settings_per_call=4,
        progress=False,
    )
    b = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)
    np.testing.assert_array_equal(a.loss, b.loss)
    for i in (0, 6, 12):
        one = search_chunk(
            data.parts[0], space.rule(jnp.asarray(values[i : i + 1], jnp.float32)), data.config
        )
        # float32: XLA contracts multiply-adds differently for other lane counts; an RMSE near 0 m carries
        # ~3e-7 m of rounding from metre-scale positions (both sides)
        np.testing.assert_allclose(
            a.loss[i], np.asarray(one.loss[0, : data.run_counts[0]]), rtol=1e-4, atol=1e-6
        )
    w = np.arange(1, data.n_runs + 1, dtype=float)
    np.testing.assert_allclose(a.objective(w), (a.loss @ w) / w.sum())
    np.testing.assert_allclose(a.objective(np.stack([w, w])), np.stack([a.objective(w)] * 2))
