"""jsve.core._sve: S_a, S_b, S_c, the power mean and the combination family (DESIGN section 3).

Expected values are worked out by hand from the authors' definitions; tolerances are float64
rounding of a handful of operations unless stated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jsve.core._sve import (
    COMBINATIONS,
    EQ1,
    INPUTS,
    JSVE_EQ1,
    JSVE_OPTION1,
    OPTION1,
    OPTION2,
    Combination,
    FrameFeatures,
    combination_from_logs,
    feature_logs,
    feature_metrics,
    frame_features,
    inlier_ratio,
    power_mean,
    power_mean2,
    s_a,
    s_a_from_ratio,
    s_a_original,
    s_b,
    s_c,
    sve_table,
)

EXACT = 1e-15  # a few roundings of values in [0, 1]


# ------------------------------------------------------------------------------------------------
# S_b


def test_s_b_uniform_bins_is_one(x64):
    for per_bin in (1, 3, 15):
        bins = np.full(64, per_bin)
        n = 64 * per_bin
        assert float(s_b(bins, n)) == 1.0
        assert float(s_b(bins, n, clamp=False)) == 1.0


def test_s_b_worst_case_is_zero_and_worse_is_negative_unclamped(x64):
    # All points spread evenly over 8 of the 64 bins (f = 1/8): chi2 = chi2_w = 7 N, S_b = 0.
    rng = np.random.default_rng(0)
    for n_per in (1, 10, 125):
        bins = np.zeros(64)
        bins[rng.choice(64, 8, replace=False)] = n_per
        n = 8 * n_per
        np.testing.assert_allclose(float(s_b(bins, n, clamp=False)), 0.0, atol=EXACT)
        np.testing.assert_allclose(float(s_b(bins, n)), 0.0, atol=EXACT)
    # All points in one bin: sum (n_i - E)^2 = N^2 (63/64)^2 + 63 (N/64)^2 = 63 N^2 / 64, so
    # chi2 = 63 N and S_b = 1 - 63 N / 7 N = -8 unclamped (Haggart's version), 0 clamped.
    bins = np.zeros(64)
    bins[17] = 640
    np.testing.assert_allclose(float(s_b(bins, 640, clamp=False)), -8.0, atol=1e-13)
    assert float(s_b(bins, 640)) == 0.0
    # Half of the bins: chi2 = N, S_b = 1 - 1/7.
    bins = np.tile([2.0, 0.0], 32)
    np.testing.assert_allclose(float(s_b(bins, 64)), 6 / 7, atol=EXACT)


def test_s_b_counts_keypoints_outside_the_grid_in_n(x64):
    # One keypoint per bin but N = 128 (half outside the grid): E = 2, chi2 = 64 * 1 / 2 = 32,
    # chi2_w = 7 * 128 = 896, S_b = 1 - 32 / 896 (the authors divide by all extracted keypoints).
    np.testing.assert_allclose(float(s_b(np.ones(64), 128)), 1 - 32 / 896, atol=EXACT)


def test_s_b_without_features_is_zero_not_nan(x64):
    assert float(s_b(np.zeros(64), 0)) == 0.0
    assert float(s_b(np.zeros(64), 0, clamp=False)) == 0.0
    g = jax.grad(lambda b: s_b(b, jnp.sum(b)))(jnp.zeros(64))
    assert np.isfinite(np.asarray(g)).all()


# ------------------------------------------------------------------------------------------------
# S_a, S_c


def test_s_a(x64):
    assert float(s_a(100, 1000)) == pytest.approx(0.4, abs=EXACT)  # rho = 0.25 by default
    assert float(s_a(100, 1000, rho=0.5)) == pytest.approx(0.2, abs=EXACT)
    assert float(s_a(300, 1000)) == 1.0  # 1.2 clamped
    assert float(s_a(0, 1000)) == 0.0
    assert float(s_a(0, 0)) == 0.0 and float(s_a(5, 0)) == 0.0  # no features: 0, not NaN
    assert float(inlier_ratio(250, 1000)) == 0.25 and float(inlier_ratio(3, 0)) == 0.0
    assert float(s_a_from_ratio(0.1, 0.25)) == pytest.approx(0.4, abs=EXACT)


def test_s_a_original(x64):
    assert float(s_a_original(379, 1000)) == pytest.approx(0.379, abs=EXACT)
    assert float(s_a_original(1200, 1000)) == pytest.approx(1.2, abs=EXACT)  # unclamped, as Haggart's
    assert float(s_a_original(10, 0)) == 0.0


def test_s_c(x64):
    assert float(s_c(50, 200)) == 0.25
    assert float(s_c(300, 200)) == 1.0
    assert float(s_c(300, 200, clamp=False)) == 1.5  # Haggart's unclamped version exceeds 1
    assert float(s_c(10, 0)) == 0.0 and float(s_c(10, 0, clamp=False)) == 0.0
    assert float(s_c(0, 0)) == 0.0


# ------------------------------------------------------------------------------------------------
# Power mean and combinations

X = np.array([0.3, 0.8, 0.55])
W = np.array([0.2, 0.5, 0.3])


def test_power_mean_special_cases(x64):
    np.testing.assert_allclose(float(power_mean(X, W, 1.0)), np.sum(W * X), atol=EXACT)
    np.testing.assert_allclose(float(power_mean(X, W, -1.0)), 1 / np.sum(W / X), atol=EXACT)
    np.testing.assert_allclose(float(power_mean(X, W, 2.0)), np.sqrt(np.sum(W * X**2)), atol=EXACT)
    np.testing.assert_allclose(float(power_mean(X, W, 0.0)), np.exp(np.sum(W * np.log(X))), atol=EXACT)


def test_power_mean_is_continuous_at_p_zero(x64):
    """M_p -> the geometric mean G as p -> 0, with slope G Var_w(log x) / 2 (cumulant expansion),
    from inside and outside the |p| < 1e-6 band where the expansion is used."""
    log = np.log(X)
    g = np.exp(np.sum(W * log))
    slope = g * 0.5 * (np.sum(W * log**2) - np.sum(W * log) ** 2)
    for p in (-1e-3, -1e-5, -1e-7, 1e-7, 1e-5, 1e-3):
        exact = np.sum(W * X**p) ** (1 / p)
        # the float64 power formula itself loses ~eps / |p| relative: compare to the expansion,
        # whose error is O(p^2) ~ 1e-6 * 1e-2 at |p| = 1e-3
        np.testing.assert_allclose(float(power_mean(X, W, p)), g + slope * p, rtol=0, atol=1e-7)
        if abs(p) >= 1e-5:
            np.testing.assert_allclose(float(power_mean(X, W, p)), exact, rtol=1e-9)
    # and the derivative in p at 0 is that slope (it used to be 0: the geometric branch ignored p)
    np.testing.assert_allclose(float(jax.grad(lambda p: power_mean(X, W, p))(0.0)), slope, rtol=1e-12)


def test_power_mean_with_zero_entries(x64):
    x = np.array([0.0, 0.5])
    w = np.array([0.5, 0.5])
    assert float(power_mean(x, w, 1.0)) == 0.25
    np.testing.assert_allclose(float(power_mean(x, w, 0.5)), (0.5 * np.sqrt(0.5)) ** 2, atol=EXACT)
    for p in (0.0, -1.0, -1e-7, 5e-7):  # a zero with positive weight: 0 for p <= 0 and p -> 0+
        assert float(power_mean(x, w, p)) == 0.0, p
    # a zero entry with zero weight does not count
    np.testing.assert_allclose(float(power_mean(x, np.array([0.0, 1.0]), 0.0)), 0.5, atol=EXACT)
    assert float(power_mean(np.zeros(2), w, 1.0)) == 0.0
    # gradients stay finite at zero entries and p = 0
    for p in (0.0, 1.0, -1.0, 0.5):
        gx, gp = jax.grad(lambda x, p: power_mean(x, w, p), argnums=(0, 1))(jnp.asarray(x), p)
        assert np.isfinite(np.asarray(gx)).all() and np.isfinite(float(gp)), p


def _abc(n=200, seed=0):
    """Random (inlier ratio, S_b, S_c) with exact zeros, exact ones and clamped S_a."""
    rng = np.random.default_rng(seed)
    ratio, sb, sc = rng.uniform(0, 0.7, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    ratio[:5], sb[5:10], sc[10:15], sb[15:20] = 0.0, 0.0, 0.0, 1.0
    return ratio, sb, sc


@pytest.mark.parametrize(
    "params, by_hand",
    [
        (JSVE_EQ1, lambda a, b, c: 0.2 * a + 0.4 * b + 0.4 * c),
        (JSVE_OPTION1, lambda a, b, c: 0.5 * a + 0.25 * b + 0.25 * c),
        (OPTION2, lambda a, b, c: np.sqrt(a * (0.5 * b + 0.5 * c))),
    ],
)
def test_combination_presets_equal_the_formulas(x64, params, by_hand):
    ratio, sb, sc = _abc()
    a = np.clip(ratio / params["rho"], 0, 1)
    got = np.asarray(Combination(**params)(jnp.asarray(ratio), jnp.asarray(sb), jnp.asarray(sc)))
    np.testing.assert_allclose(got, by_hand(a, sb, sc), rtol=0, atol=1e-12)  # exp/log route for Option 2


def test_combination_with_p_equal_q_is_the_flat_power_mean(x64):
    ratio, sb, sc = _abc()
    w, u, p = 0.3, 0.6, 2.5
    a = np.clip(ratio / 0.4, 0, 1)
    flat = (w * a**p + (1 - w) * u * sb**p + (1 - w) * (1 - u) * sc**p) ** (1 / p)
    got = Combination(w_a=w, u_b=u, p=p, q=p, rho=0.4)(jnp.asarray(ratio), jnp.asarray(sb), jnp.asarray(sc))
    np.testing.assert_allclose(np.asarray(got), flat, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# eager = jit = vmap; gradients


def _metrics(ext, inl, fru, bins, combo):
    f = frame_features(ext, inl, fru, bins)
    return jnp.stack([s_a(inl, ext), s_b(bins, ext), s_c(inl, fru), combo(f.inlier_ratio, f.s_b, f.s_c)])


def test_eager_jit_vmap_agree(x64):
    """Per frame eagerly, jitted, and vmapped over frames: equal to 1e-15 (XLA may fuse exp/log
    differently under jit: a few ulp, as measured)."""
    rng = np.random.default_rng(3)
    ext = rng.integers(0, 1000, 40).astype(float)
    ext[:3] = 0
    inl = np.floor(ext * rng.uniform(0, 0.6, 40))
    fru = rng.integers(0, 400, 40).astype(float)
    bins = np.stack([rng.multinomial(int(n), rng.dirichlet(np.ones(64))) for n in ext]).astype(float)
    combo = Combination(**OPTION2)
    batched = np.asarray(jax.vmap(lambda *a: _metrics(*a, combo))(ext, inl, fru, bins))
    jitted = jax.jit(lambda *a: _metrics(*a, combo))
    for i in range(40):
        eager = np.asarray(_metrics(ext[i], inl[i], fru[i], bins[i], combo))
        np.testing.assert_allclose(
            np.asarray(jitted(ext[i], inl[i], fru[i], bins[i])), eager, rtol=0, atol=EXACT
        )
        np.testing.assert_allclose(batched[i], eager, rtol=0, atol=EXACT)
    whole = np.asarray(_metrics(ext, inl, fru, bins, combo))  # elementwise over leading axes
    np.testing.assert_allclose(whole.T, batched, rtol=0, atol=EXACT)


def _central(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def test_metric_gradients_match_finite_differences(x64):
    """Interior points (no clamp active): S_a and S_c against their analytic slopes, S_b (quadratic
    in the bins, so a central difference is exact up to rounding, ~eps / h = 1e-12) against
    central differences with h = 1e-4. Tolerance 1e-7 relative."""
    tol = dict(rtol=1e-7, atol=1e-10)
    d = jax.grad(lambda n: s_a(n, 1000.0))(100.0)
    np.testing.assert_allclose(float(d), 1 / 250, **tol)
    d = jax.grad(lambda n: s_c(n, 400.0))(100.0)
    np.testing.assert_allclose(float(d), 1 / 400, **tol)
    rng = np.random.default_rng(4)
    bins = jnp.asarray(rng.multinomial(900, rng.dirichlet(np.ones(64))).astype(float))
    g = jax.grad(lambda b: s_b(b, 1000.0))(bins)
    for k in (0, 17, 63):
        e = jnp.zeros(64).at[k].set(1.0)
        fd = _central(lambda h, e=e: s_b(bins + h * e, 1000.0), 0.0, 1e-4)
        np.testing.assert_allclose(float(g[k]), float(fd), **tol)


@pytest.mark.parametrize(
    "params", [JSVE_EQ1, JSVE_OPTION1, OPTION2, dict(w_a=0.35, u_b=0.7, p=-0.6, q=1.7, rho=0.3)]
)
def test_combination_gradients_match_finite_differences(x64, params):
    """d score / d (inputs and parameters) at an interior point, including p = 0 (Option 2),
    against central differences with h = 1e-4. The differences converge to the gradient as h^2
    (measured: at most 6e-7 relative, on the inlier ratio, where sqrt(S_a ...) curves most);
    a smaller h is worse at p = 0, where the power formula just outside the |p| < 1e-6 expansion
    band carries ~eps / h relative error. Tolerance 2e-6 relative: a wrong term is O(1)."""
    ratio, sb, sc = 0.06, 0.45, 0.7  # S_a = ratio / rho < 1: no clamp active

    def score(v):
        c = Combination(w_a=v[3], u_b=v[4], p=v[5], q=v[6], rho=v[7])
        return c(v[0], v[1], v[2])

    v = jnp.asarray([ratio, sb, sc, params["w_a"], params["u_b"], params["p"], params["q"], params["rho"]])
    g = np.asarray(jax.grad(score)(v))
    for j in range(8):
        e = jnp.zeros(8).at[j].set(1.0)
        fd = float(_central(lambda h, e=e: score(v + h * e), 0.0, 1e-4))
        np.testing.assert_allclose(g[j], fd, rtol=2e-6, atol=1e-10, err_msg=f"argument {j}")
    assert np.all(g[:3] > 0)  # more visibility, higher score


def test_gradients_finite_at_zero_features(x64):
    for params in (JSVE_EQ1, JSVE_OPTION1, OPTION2):
        combo = Combination(**params)
        g = jax.grad(lambda x, combo=combo: combo(x[0], x[1], x[2]))(jnp.zeros(3))
        assert np.isfinite(np.asarray(g)).all()
        gp = jax.grad(lambda c: c(0.0, 0.0, 0.0))(combo)
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(gp))
    # and through the counts, with nothing extracted and an empty frustum
    g = jax.grad(lambda n: jnp.sum(_metrics(n[0], n[1], n[2], jnp.zeros(64), Combination(**OPTION2))))(
        jnp.zeros(3)
    )
    assert np.isfinite(np.asarray(g)).all()
    # and the authors' presets, through every count (their features are ratios with safe zeros too)
    for params in (EQ1, OPTION1):
        combo = Combination(**params)
        g = jax.grad(
            lambda n, combo=combo: combo.score(frame_features(n[0], n[1], n[2], jnp.zeros(64), n[3]))
        )(jnp.asarray([0.0, 0.0, 0.0, 1000.0]))
        assert np.isfinite(np.asarray(g)).all()


def test_sve_table_columns(x64):
    rng = np.random.default_rng(5)
    ext = np.array([1000, 0, 379])
    inl = np.array([100, 0, 300])
    fru = np.array([200, 0, 100])
    bins = np.stack([rng.multinomial(int(n), np.full(64, 1 / 64)) for n in ext])
    table = sve_table(ext, inl, fru, bins)
    np.testing.assert_allclose(np.asarray(table["s_a_original"]), [1.0, 0.0, 0.379], atol=EXACT)
    np.testing.assert_allclose(np.asarray(table["s_a_rho025"]), [0.4, 0.0, 1.0], atol=EXACT)
    np.testing.assert_allclose(np.asarray(table["s_c_unclamped"]), [0.5, 0.0, 3.0], atol=EXACT)
    np.testing.assert_allclose(np.asarray(table["s_c"]), [0.5, 0.0, 1.0], atol=EXACT)
    assert np.all(np.asarray(table["s_b_unclamped"]) <= np.asarray(table["s_b"]) + EXACT)
    f = frame_features(ext, inl, fru, bins)
    np.testing.assert_allclose(
        np.asarray(table["sve_option2"]),
        np.asarray(Combination(**OPTION2)(f.inlier_ratio, f.s_b, f.s_c)),
        atol=0,
    )
    # one score column per preset combination, each its Combination's score of the features
    assert list(table)[-len(COMBINATIONS) :] == [
        "sve_eq1",
        "sve_option1",
        "sve_option2",
        "jsve_eq1",
        "jsve_option1",
    ]
    for name, params in COMBINATIONS.items():
        want = np.asarray(Combination(**params).score(f))
        np.testing.assert_array_equal(np.asarray(table[name.replace("-", "_")]), want)
    # n_features reaches S_a original and the authors' Eq.1
    other = sve_table(ext, inl, fru, bins, n_features=500)
    np.testing.assert_allclose(np.asarray(other["s_a_original"]), [2.0, 0.0, 0.758], atol=EXACT)
    np.testing.assert_allclose(
        np.asarray(other["sve_eq1"]) - np.asarray(table["sve_eq1"]),
        0.2 * np.array([1.0, 0.0, 0.379]),
        atol=1e-15,
    )


def test_two_entry_power_mean_is_power_mean(x64):
    """power_mean2 (the log-domain kernel of the combinations) is power_mean on two columns: to 1e-13
    in float64 over exponents from -4 to 4, p near and at 0, zero entries and zero weights."""
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


# ------------------------------------------------------------------------------------------------
# The metrics of FrameFeatures


def test_feature_metrics_follow_the_fields(x64):
    """S_a at rho, then every FrameFeatures field after the count and the ratio, by field name; S_a is
    s_a of the counts (to 1e-15) and the others are the fields themselves."""
    rng = np.random.default_rng(6)
    ext = np.array([1000.0, 0.0, 379.0, 640.0])
    inl = np.array([100.0, 0.0, 300.0, 12.0])
    fru = np.array([200.0, 0.0, 100.0, 0.0])
    bins = np.stack([rng.multinomial(int(n), rng.dirichlet(np.ones(64))) for n in ext]).astype(float)
    f = frame_features(ext, inl, fru, bins)
    metrics = feature_metrics(f, 0.4)
    fields = [k for k in FrameFeatures.__dataclass_fields__ if k not in ("n_inliers", "inlier_ratio")]
    assert list(metrics) == ["s_a", *fields] and {"s_b", "s_c"} <= set(fields)
    np.testing.assert_allclose(np.asarray(metrics["s_a"]), np.asarray(s_a(inl, ext, 0.4)), rtol=0, atol=EXACT)
    for name in fields:
        assert metrics[name] is getattr(f, name)
    # one JAX function of the features and rho: eager = jit = vmap over frames; d S_a / d rho = -ratio / rho^2
    fn = lambda feats, rho: jnp.stack(list(feature_metrics(feats, rho).values()))  # noqa: E731
    whole = np.asarray(fn(f, 0.4))
    np.testing.assert_allclose(np.asarray(jax.jit(fn)(f, 0.4)), whole, rtol=0, atol=EXACT)
    per_frame = np.asarray(jax.vmap(fn, in_axes=(0, None))(f, 0.4))
    np.testing.assert_allclose(per_frame.T, whole, rtol=0, atol=EXACT)
    d = jax.grad(lambda rho: feature_metrics(f, rho)["s_a"][0])(0.4)  # 0.1 / 0.4 < 1: no clamp
    np.testing.assert_allclose(float(d), -0.1 / 0.4**2, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# The authors' builds: unclamped inputs (docs/sve.md, "Presets")


def _authors_counts():
    """Two runs of three frames whose authors' features are worked out by hand (in `_authors_expected`):
    run 0 with nFeatures 1000, run 1 with 1200. Bins hold the keypoints inside the grid; N may be larger."""
    ext = np.array([[640.0, 64.0, 0.0], [1100.0, 1280.0, 640.0]])
    inl = np.array([[300.0, 40.0, 0.0], [220.0, 0.0, 64.0]])
    fru = np.array([[100.0, 0.0, 0.0], [200.0, 50.0, 32.0]])
    bins = np.zeros((2, 3, 64))
    bins[0, 0, 17] = 640  # all in one bin
    bins[0, 1] = np.tile([2.0, 0.0], 32)  # every other bin
    bins[1, 0] = 16  # uniform, 1024 of the 1100 inside the grid
    bins[1, 1, :8] = 160  # evenly over 8 of the 64 bins: the worst case
    bins[1, 2, [0, 63]] = 320  # two opposite corners
    return ext, inl, fru, bins, np.array([[1000.0], [1200.0]])


def _authors_expected():
    """The features of `_authors_counts` by hand. S_b = 1 - 64 sum_i (n_i - E)^2 / (7 N^2), E = N / 64:
    one bin: sum = 63 N^2 / 64, S_b = -8. Every other bin (N = 64): sum = 64, S_b = 6/7. Uniform 16 with
    N = 1100: E = 17.1875, sum = 64 * 1.1875^2 = 90.25, S_b = 1 - 5776 / 8470000. Worst case: 0. Two
    corners of 320 (N = 640, E = 10): sum = 2 * 310^2 + 62 * 100 = 198400, S_b = 1 - 31/7 = -24/7."""
    s_a_original = np.array([[0.64, 0.064, 0.0], [1100 / 1200, 1280 / 1200, 640 / 1200]])
    s_b = np.array([[-8.0, 6 / 7, 0.0], [1 - 5776 / 8470000, 0.0, -24 / 7]])
    s_c = np.array([[3.0, 0.0, 0.0], [1.1, 0.0, 2.0]])
    ratio = np.array([[300 / 640, 40 / 64, 0.0], [0.2, 0.0, 0.1]])
    return s_a_original, s_b, s_c, ratio


def _authors_s_b(bins, n):
    """S_b normalised as Frame::AssignFeaturesToGrid writes the worst case (domRG/ORB_SLAM3_SVE): all N
    points evenly in a fraction f = 1/8 of the 64 bins, chi2_w = E (1 - f) 64 + (f 64 / E) (N / (f 64) - E)^2,
    which is 7 N; unclamped, as in the original and Option 1 builds."""
    e = n / 64.0
    chi2 = np.sum((bins - e) ** 2 / e)
    worst = e * (1 - 1 / 8) * 64 + (64 / 8 / e) * (n / 8 - e) ** 2
    return 1 - chi2 / worst


def test_frame_features_carry_the_authors_variants(x64):
    """The unclamped variants and S_a original against the hand values (1e-15: a few roundings of
    values up to 8; -24/7 and 6/7 are not binary), the clamped ones are their clips, and the authors'
    chi2_w form gives the same S_b (1e-13: its terms reach 1e6)."""
    ext, inl, fru, bins, n_features = _authors_counts()
    s_a_original, s_b_u, s_c_u, ratio = _authors_expected()
    f = frame_features(ext, inl, fru, bins, n_features)
    np.testing.assert_allclose(np.asarray(f.s_a_original), s_a_original, rtol=0, atol=EXACT)
    np.testing.assert_allclose(np.asarray(f.s_b_unclamped), s_b_u, rtol=0, atol=4 * EXACT)
    np.testing.assert_allclose(np.asarray(f.s_c_unclamped), s_c_u, rtol=0, atol=4 * EXACT)
    np.testing.assert_allclose(np.asarray(f.inlier_ratio), ratio, rtol=0, atol=EXACT)
    np.testing.assert_array_equal(np.asarray(f.s_b), np.clip(np.asarray(f.s_b_unclamped), 0, 1))
    np.testing.assert_array_equal(np.asarray(f.s_c), np.clip(np.asarray(f.s_c_unclamped), 0, 1))
    assert float(f.s_b_unclamped[0, 0]) < -7.99 and float(f.s_a_original[1, 1]) > 1.0  # not clamped
    for r, k in ((0, 0), (0, 1), (1, 0), (1, 1), (1, 2)):
        np.testing.assert_allclose(
            float(f.s_b_unclamped[r, k]), _authors_s_b(bins[r, k], ext[r, k]), atol=1e-13
        )
    # a scalar nFeatures is the same for every run; a per-run [R] vector does not broadcast to [R, F]
    same = frame_features(ext, inl, fru, bins, 1000.0)
    np.testing.assert_allclose(np.asarray(same.s_a_original), ext / 1000, rtol=0, atol=EXACT)
    with pytest.raises(ValueError, match=r"n_features has shape \(2,\).*\(2, 3\)"):
        frame_features(ext, inl, fru, bins, np.array([1000.0, 1200.0]))


def test_authors_presets_from_counts(x64):
    """Eq.1 (0.2 a + 0.4 b + 0.4 c of S_a original and the unclamped S_b, S_c) and Option 1 (0.5 a +
    0.25 b + 0.25 c, S_a = clamp(ratio / 0.5, 0, 1), S_b and S_c unclamped), frame by frame by hand, with
    scores below 0 and above 1. 1e-14: a few roundings of values up to 8."""
    ext, inl, fru, bins, n_features = _authors_counts()
    f = frame_features(ext, inl, fru, bins, n_features)
    s_b_uniform = 1 - 5776 / 8470000
    eq1 = np.array(
        [
            [0.2 * 0.64 + 0.4 * -8 + 0.4 * 3, 0.2 * 0.064 + 0.4 * 6 / 7, 0.0],  # -1.872, 0.3556...
            [0.2 * 1100 / 1200 + 0.4 * s_b_uniform + 0.4 * 1.1, 0.2 * 1280 / 1200,
             0.2 * 640 / 1200 + 0.4 * -24 / 7 + 0.4 * 2],
        ]
    )  # fmt: skip
    option1 = np.array(
        [
            [0.5 * 0.9375 + 0.25 * -8 + 0.25 * 3, 0.5 * 1.0 + 0.25 * 6 / 7, 0.0],  # -0.78125; S_a 1.25 -> 1
            [0.5 * 0.4 + 0.25 * s_b_uniform + 0.25 * 1.1, 0.0, 0.5 * 0.2 + 0.25 * -24 / 7 + 0.25 * 2],
        ]
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(Combination(**EQ1).score(f)), eq1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(Combination(**OPTION1).score(f)), option1, rtol=0, atol=1e-14)
    assert eq1.min() < -1.8 and eq1.max() > 0.9  # the authors' Eq.1 is not confined to [0, 1]
    # jsve's clamped variants of the same weights stay in [0, 1] and differ where clamps act
    for params in (JSVE_EQ1, JSVE_OPTION1, OPTION2):
        got = np.asarray(Combination(**params).score(f))
        np.testing.assert_array_equal(got, np.asarray(Combination(**params)(f.inlier_ratio, f.s_b, f.s_c)))
        assert ((got >= 0) & (got <= 1)).all()
    np.testing.assert_allclose(float(Combination(**JSVE_EQ1).score(f)[0, 0]), 0.2 * 0.9375 + 0.4, atol=1e-15)


def test_unclamped_inputs_refuse_nonlinear_exponents(x64):
    """With the authors' inputs only p = q = 1 is defined: concrete exponents are refused when the
    Combination is made, traced ones when it scores; a traced 1 scores as the concrete one."""
    ext, inl, fru, bins, n_features = _authors_counts()
    f = frame_features(ext, inl, fru, bins, n_features)
    for params in (EQ1, OPTION1):
        with pytest.raises(ValueError, match=r"needs p = 1, got 0\.0.*linear mean"):
            Combination(**{**params, "p": 0.0})
        with pytest.raises(ValueError, match=r"needs q = 1, got \[1\. 2\.\]"):
            Combination(**{**params, "q": np.array([1.0, 2.0])})  # a stack with one bad entry
        with pytest.raises(RuntimeError, match=r"only defined for p = q = 1"):
            jax.jit(lambda p, params=params: Combination(**{**params, "p": p}).score(f))(0.5)
        with pytest.raises(RuntimeError, match=r"only defined for p = q = 1"):
            jax.vmap(lambda q, params=params: Combination(**{**params, "q": q}).score(f))(
                jnp.asarray([1.0, 3.0])
            )
        ok = jax.jit(lambda p, params=params: Combination(**{**params, "p": p}).score(f))(1.0)
        np.testing.assert_array_equal(np.asarray(ok), np.asarray(Combination(**params).score(f)))
        # the three-argument form carries neither S_a original nor the unclamped S_b, S_c
        combo = Combination(**params)
        with pytest.raises(ValueError, match=r"call \.score\(features\)"):
            combo(f.inlier_ratio, f.s_b, f.s_c)
        with pytest.raises(ValueError, match=r"inputs='authors-"):
            combination_from_logs(combo, *feature_logs(f.inlier_ratio, f.s_b, f.s_c))
    Combination(**{**OPTION2, "p": -2.0})  # jsve's clamped inputs take any exponent
    with pytest.raises(ValueError, match=r"inputs must be one of 'jsve', 'authors-eq1', 'authors-option1'"):
        Combination(inputs="authors-option2")
    assert INPUTS == ("jsve", "authors-eq1", "authors-option1")


def test_authors_scores_eager_jit_vmap_agree(x64):
    """Frame by frame eagerly, jitted over the batch, and vmapped over runs (n_features per run):
    identical to 1e-15 (a handful of multiply-adds)."""
    ext, inl, fru, bins, n_features = _authors_counts()

    def scores(e, i, fr, b, n):
        f = frame_features(e, i, fr, b, n)
        return jnp.stack([Combination(**c).score(f) for c in COMBINATIONS.values()])

    whole = np.asarray(scores(ext, inl, fru, bins, n_features))
    np.testing.assert_allclose(
        np.asarray(jax.jit(scores)(ext, inl, fru, bins, n_features)), whole, atol=EXACT
    )
    per_run = np.asarray(jax.vmap(scores)(ext, inl, fru, bins, n_features[:, 0]))  # [R, presets, F]
    np.testing.assert_allclose(np.moveaxis(per_run, 0, 1), whole, rtol=0, atol=EXACT)
    for r in range(2):
        for k in range(3):
            one = np.asarray(scores(ext[r, k], inl[r, k], fru[r, k], bins[r, k], n_features[r, 0]))
            np.testing.assert_allclose(one, whole[:, r, k], rtol=0, atol=EXACT)


def test_authors_scores_gradients(x64):
    """Linear in the weights: d Eq.1 / d w_a = a - (u b + (1 - u) c) and d / d u_b = (1 - w)(b - c),
    exactly, at the frame with S_b = -8; through the counts (Option 1, S_a = 0.4 inside its clamp) the
    gradient is the analytic one and a central difference's (h = 1e-3 on counts ~1000; the score is
    smooth there: 1e-8 relative)."""
    ext, inl, fru, bins, n_features = _authors_counts()
    f = frame_features(ext, inl, fru, bins, n_features)
    a, b, c = 0.64, -8.0, 3.0

    def eq1(w_a, u_b):
        return Combination(**{**EQ1, "w_a": w_a, "u_b": u_b}).score(f)[0, 0]

    g_w, g_u = jax.grad(eq1, argnums=(0, 1))(0.2, 0.5)
    np.testing.assert_allclose(float(g_w), a - (0.5 * b + 0.5 * c), rtol=1e-14)
    np.testing.assert_allclose(float(g_u), 0.8 * (b - c), rtol=1e-14)

    def option1(counts):  # n_inliers, n_extracted, n_frustum of run 1, frame 0
        feats = frame_features(counts[1], counts[0], counts[2], bins[1, 0], 1200.0)
        return Combination(**OPTION1).score(feats)

    x = jnp.asarray([220.0, 1100.0, 200.0])
    g = np.asarray(jax.grad(option1)(x))
    fd = np.array(
        [(float(option1(x.at[j].add(1e-3))) - float(option1(x.at[j].add(-1e-3)))) / 2e-3 for j in range(3)]
    )
    np.testing.assert_allclose(g, fd, rtol=1e-8)
    # d/d n_inliers = 0.5 / (0.5 N) + 0.25 / N_frustum
    np.testing.assert_allclose(g[0], 0.5 / 550 + 0.25 / 200, rtol=1e-14)
