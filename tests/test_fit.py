"""jsve.fitting._fit, jsve.fitting._search, jsve.fitting._space and jsve.fitting._crossval.

Known answers: logs where visual tracking is catastrophic below K inliers (fitting ORB-SLAM3's thresholds
finds K), and logs where the failures come from features concentrated in few bins (an SVE rule, fitted,
beats the tuned inlier rule on held-out runs). Oracles: scipy's Sobol and Halton sequences,
jsve.core._sve.power_mean, jsve.core._replay.imu_predict, jsve.core._objective.run_losses (replay + alignment, itself
checked against jsve.evaluation._evaluate) for the search kernel, jsve.evaluation._aggregate.bootstrap_ci.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pytest

from jsve.core._objective import ObjectiveConfig, run_losses
from jsve.core._replay import batch_features, imu_predict
from jsve.core._rules import InlierRule, SVERule, preset
from jsve.core._sve import feature_logs, power_mean, power_mean2
from jsve.evaluation._aggregate import bootstrap_ci
from jsve.fitting._crossval import bootstrap_weighted_mean, compare, cross_validate, kfold, leave_one_out
from jsve.fitting._fit import FitConfig, FitData, fit, hard_objective, nelder_mead, preset_values, relaxed_fit
from jsve.fitting._search import (
    grid_design,
    halton,
    imu_predict_columns,
    prepare,
    score_columns,
    search,
    search_chunk,
    sobol,
)
from jsve.fitting._space import ParamSpace, RuleParams, inlier_space, space_from_dict, sve_space
from jsve.io._batching import from_runs

K = 40

# ---------------------------------------------------------------------------------------------------
# Designs


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


# ---------------------------------------------------------------------------------------------------
# Parameter spaces


def test_param_space_coordinates_and_rules():
    space = sve_space()
    rng = np.random.default_rng(0)
    values = np.asarray(space.values_from_unit(rng.random((5, space.dim))))
    z = space.z_from_values(values)
    np.testing.assert_allclose(np.asarray(space.values_from_z(z)), values, rtol=1e-6, atol=1e-6)
    rules = space.rule(jnp.asarray(values))
    assert isinstance(rules, SVERule) and rules.combination.w_a.shape == (5,)
    np.testing.assert_allclose(np.asarray(rules.thresholds.recovery), values[:, -1])
    # every z maps into the box (float32 rounding of the bounds aside): weights on the simplex, thresholds
    # within their ranges
    wild = np.asarray(space.values_from_z(jnp.asarray(rng.normal(scale=30, size=(100, space.dim)))))
    slack = 1e-6 * (np.asarray(space.hi) - np.asarray(space.lo))
    assert np.all(wild >= np.asarray(space.lo) - slack) and np.all(wild <= np.asarray(space.hi) + slack)
    for name, v in preset_values(space).items():
        np.testing.assert_allclose(space.values_of(space.rule(jnp.asarray(v))), v, rtol=1e-6)
        assert name.startswith("sve-")
    assert list(preset_values(inlier_space())) == ["orbslam3"]
    fixed = space.fix(rho=0.25, p=0.0)
    assert fixed.dim == 7 and dict(fixed.fixed) == {"rho": 0.25, "p": 0.0}
    assert float(fixed.rule(jnp.zeros(7)).combination.rho) == 0.25
    assert set(preset_values(fixed)) == {"sve-option2"}  # the only preset with rho 0.25 and p = 0
    assert space_from_dict(fixed.describe()) == fixed
    params = RuleParams.from_values(inlier_space(), [15, 50, 50, 10])
    assert isinstance(params.rule(), InlierRule)
    np.testing.assert_allclose(np.asarray(params.values()), [15, 50, 50, 10], rtol=1e-5)
    with pytest.raises(ValueError, match="free or fixed exactly once"):
        ParamSpace("inliers", ("imu_init",), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="lo < hi"):
        inlier_space(imu_init=(5.0, 5.0))
    with pytest.raises(ValueError, match="not in the 'sve' family"):
        space.values_of(preset("orbslam3"))


# ---------------------------------------------------------------------------------------------------
# The search kernel


def test_two_entry_power_mean_is_power_mean(x64):
    """power_mean2 is jsve.core._sve.power_mean on two columns: to 1e-13 in float64 over exponents from -4
    to 4, p near and at 0, zero entries and zero weights."""
    rng = np.random.default_rng(1)
    n = 4000
    x1, x2 = rng.random(n), rng.random(n)
    x1[::7] = 0.0
    x2[::11] = 0.0
    w = rng.random(n)
    w[::13] = 0.0
    w[::17] = 1.0
    p = rng.uniform(-4, 4, n)
    p[::5] = 0.0
    p[::9] = rng.uniform(-2e-6, 2e-6, len(p[::9]))
    ours = power_mean2(jnp.asarray(x1), jnp.asarray(x2), jnp.asarray(w), jnp.asarray(p))
    ref = jax.vmap(power_mean)(
        jnp.stack([jnp.asarray(x1), jnp.asarray(x2)], -1),
        jnp.stack([jnp.asarray(w), 1 - jnp.asarray(w)], -1),
        jnp.asarray(p),
    )
    np.testing.assert_allclose(np.asarray(ours), np.asarray(ref), rtol=1e-13, atol=1e-15)


def test_score_and_prediction_columns_match_the_replay(x64):
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
    rng = np.random.default_rng(0)
    p, v, dp, dv, g = (rng.normal(size=(50, 3)) for _ in range(5))
    q, dq = (
        x / np.linalg.norm(x, axis=1, keepdims=True) for x in (rng.normal(size=(50, 4)) for _ in range(2))
    )
    dt = rng.uniform(0, 0.1, 50)
    ref = imu_predict(*(jnp.asarray(a) for a in (p, v, q, dt, dp, dv, dq, g)))
    cols = lambda a: tuple(jnp.asarray(a[:, i]) for i in range(a.shape[1]))  # noqa: E731
    ours = imu_predict_columns(
        cols(p), cols(v), cols(q), jnp.asarray(dt), cols(dp), cols(dv), cols(dq), cols(g)
    )
    for a, b in zip(ours, ref, strict=True):
        np.testing.assert_allclose(
            np.stack([np.asarray(c) for c in a], -1), np.asarray(b), rtol=0, atol=1e-13
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
    failed flags. Both families, 24 Sobol settings each, failing and succeeding runs."""
    runs = ka.make_study("occlusion", range(6), n_frames=300)
    batch = from_runs(runs, dtype=dtype).batch
    f = batch_features(batch)
    sb = prepare(batch, f)
    config = ObjectiveConfig(align=align, failure_penalty=3.0)
    for space in (inlier_space(), sve_space()):
        values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
        values[-3:, -4:] = 2.0 * space.score_scale * 1e3  # thresholds no frame passes: runs fail
        rules = space.rule(jnp.asarray(values, dtype))
        got = search_chunk(sb, rules, config)
        ref = jax.jit(jax.vmap(lambda r: run_losses(batch, r, f, config)))(rules)
        failed = np.asarray(ref.failed)
        assert np.array_equal(np.asarray(got.failed), failed)
        assert 0 < failed.mean() < 1  # both kinds of runs are checked
        if dtype == jnp.float64:
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=0, atol=1e-12)
        else:
            # float32 positions of a few metres carry ~2e-7 m of rounding each, in both computations
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=1e-4, atol=2e-6)
        np.testing.assert_allclose(np.asarray(got.coverage)[~failed], 1.0)
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


# ---------------------------------------------------------------------------------------------------
# Known answers


@pytest.fixture(scope="module")
def counts_data():
    return FitData.from_runs(ka.make_study("counts", range(16), n_frames=500, k_min=K))


def test_fitting_orbslam3_thresholds_recovers_k(counts_data):
    """Visual tracking is exact with K or more inliers and grossly wrong below. Frames have integer
    counts, so the hard objective is flat for imu_init in (K - 1, K]: the fit must land there (tolerance:
    that interval, i.e. within 1 inlier of K). Recovery must not let a bad frame back in: > K - 1 - 1e-6.
    The fit is also strictly better than ORB-SLAM3's own thresholds (15 / 10 accept the gross frames)."""
    space = inlier_space()
    result = fit(counts_data, space, config=FitConfig(n_search=512, n_starts=2, nm_steps=120), progress=False)
    p = result.params()
    assert K - 1 < p["imu_init"] <= K, p
    assert p["recovery"] >= K - 1 - 1e-6, p
    assert result.failure_rate == 0.0
    own = hard_objective(counts_data, space, space.values_of(preset("orbslam3")))
    assert result.objective < 0.25 * own, (result.objective, own)
    # the stages record a non-increasing objective, and the result is the hard objective of the values
    assert result.stages[1]["objective"] <= result.stages[0]["objective"] + 1e-7
    assert result.objective == pytest.approx(hard_objective(counts_data, space, result.values), rel=1e-6)
    # one inlier on either side is measurably worse
    for delta in (-1.0, 1.0):
        shifted = np.array(result.values)
        shifted[0] = K - 0.5 + delta
        assert hard_objective(counts_data, space, shifted) > result.objective + 1e-5


def test_fitted_sve_beats_the_tuned_inlier_rule_on_held_out_occlusion():
    """Most bad frames have as many inliers as good ones but their keypoints sit in 3-6 of 64 bins:
    S_b ~ 0. Fitted on 16 runs and scored on 16 others, the SVE rule beats ORB-SLAM3's rule with its
    thresholds fitted the same way, by a factor of 3 or more, and the paired bootstrap interval of the
    difference lies below 0."""
    train = FitData.from_runs(ka.make_study("occlusion", range(16), n_frames=500))
    test = FitData.from_runs(ka.make_study("occlusion", range(100, 116), n_frames=500))
    config = FitConfig(n_search=1024, n_starts=1, nm_steps=80)
    per_run = {}
    for space in (sve_space(), inlier_space()):
        result = fit(train, space, config=config, progress=False)
        res = search(
            test.parts, space, result.values[None], test.config, run_counts=test.run_counts, progress=False
        )
        per_run[space.kind] = res.loss[0]
    sve, inl = per_run["sve"], per_run["inliers"]
    assert sve.mean() * 3 < inl.mean(), (sve.mean(), inl.mean())
    diff, low, high = bootstrap_weighted_mean(sve - inl, n_boot=2000, seed=0)
    assert high < 0, (diff, low, high)


@pytest.mark.slow
def test_nelder_mead_and_relaxed_fit_improve_a_poor_start(occlusion_data):
    """From the seed's Option 2 (thresholds made for real EuRoC frames), Nelder-Mead on the hard objective
    and the annealed BFGS on the relaxed one both lower the hard objective; the relaxed fit lowers its
    own objective at every temperature."""
    data = occlusion_data
    space = sve_space()
    start = space.values_of(preset("sve-option2"))
    start_value = hard_objective(data, space, start)
    values, value, steps = nelder_mead(data, space, start, max_steps=80)
    assert value < start_value - 1e-3 and steps > 0
    assert value == pytest.approx(hard_objective(data, space, values), rel=1e-6)
    from jsve.fitting._fit import relaxed_objective

    relaxed_values, history = relaxed_fit(data, space, start, temperatures=(0.1, 0.03, 0.01), max_steps=30)
    assert history[-1]["hard"] < start_value - 1e-3, (history, start_value)
    for h in history:
        assert h["relaxed"] < relaxed_objective(data, space, start, h["temperature"]), h


# ---------------------------------------------------------------------------------------------------
# Cross-validation and bootstrap


def test_folds_partition_the_runs(counts_data):
    folds = kfold(counts_data.n_runs, 5, seed=1)
    counts = np.sum([f.test for f in folds], axis=0)
    assert np.array_equal(counts, np.ones(counts_data.n_runs))
    assert sorted(f.test.sum() for f in folds) == [3, 3, 3, 3, 4]
    loso = leave_one_out(counts_data.meta, "sequence")
    assert [f.name for f in loso] == ["S0", "S1", "S2"]
    assert np.array_equal(np.sum([f.test for f in loso], axis=0), np.ones(counts_data.n_runs))
    with pytest.raises(ValueError, match="at least 2 values"):
        leave_one_out(counts_data.meta, "disturbance")
    with pytest.raises(ValueError, match="2 <= k"):
        kfold(3, 4)


def test_bootstrap_weighted_mean_matches_aggregate_bootstrap_ci():
    """With unit weights and the same seed it is jsve.evaluation._aggregate.bootstrap_ci of the mean, exactly."""
    x = np.random.default_rng(3).exponential(size=40)
    mean, low, high = bootstrap_weighted_mean(x, n_boot=500, seed=9)
    assert mean == pytest.approx(x.mean())
    assert (low, high) == bootstrap_ci(x, np.mean, n_boot=500, seed=9)
    w = np.where(np.arange(40) < 20, 3.0, 1.0)
    m2, l2, h2 = bootstrap_weighted_mean(x, w, n_boot=500, seed=9)
    assert m2 == pytest.approx(np.sum(w * x) / w.sum()) and l2 < m2 < h2


def test_cross_validation_holds_every_run_out_once(counts_data):
    data = counts_data
    folds = kfold(data.n_runs, 4, seed=0) + leave_one_out(data.meta, "sequence")
    config = FitConfig(n_search=128, n_starts=1, nm_steps=20)
    cv = cross_validate(
        data,
        {"inliers": inlier_space()},
        folds,
        config=config,
        presets=("orbslam3", "sve-option2"),
        progress=False,
    )
    h = cv.heldout
    assert set(h["rule"]) == {"fitted-inliers", "orbslam3", "sve-option2"}
    for (kind, rule), g in h.groupby(["fold_kind", "rule"]):
        assert sorted(g["run_index"]) == list(range(data.n_runs)), (kind, rule)
    # a preset is not fitted: its held-out losses are its losses on all runs
    space = inlier_space()
    full = search(
        data.parts,
        space,
        space.values_of(preset("orbslam3"))[None],
        data.config,
        run_counts=data.run_counts,
        progress=False,
    )
    g = h[(h["rule"] == "orbslam3") & (h["fold_kind"] == "kfold")].sort_values("run_index")
    np.testing.assert_allclose(g["loss"].to_numpy(), full.loss[0])
    assert len(cv.params) == len(folds)
    table = compare(h, n_boot=300)
    fitted = table[(table["rule"] == "fitted-inliers") & (table["fold_kind"] == "kfold")].iloc[0]
    assert fitted["ci_low"] <= fitted["mean_loss"] <= fitted["ci_high"]
    assert fitted["diff_vs_orbslam3_ci_high"] < 0  # K-aware thresholds beat 15 / 10 out of sample
