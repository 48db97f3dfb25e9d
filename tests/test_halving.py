"""jsve.fitting._halving: successive halving over runs and the per-run result cache shared by folds.

Oracles: the exhaustive search (jsve.fitting._search.search over every run), the kernel re-run on each
fold's training runs alone, and logs whose best inlier thresholds are known (tests/knownanswer.py).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pandas as pd
import pytest

from jsve.core._objective import ObjectiveConfig
from jsve.fitting._crossval import cross_validate, kfold
from jsve.fitting._data import FitData
from jsve.fitting._designs import sobol
from jsve.fitting._fit import FitConfig, fit, fit_cache, search_design
from jsve.fitting._halving import (
    RunLossCache,
    halving_search,
    halving_searches,
    rung_sizes,
    stratified_order,
)
from jsve.fitting._kernel import search_chunk
from jsve.fitting._packing import subset_parts
from jsve.fitting._search import search
from jsve.fitting._space import inlier_space, sve_space

K = 40
COAST = ObjectiveConfig(switch_model="imu-coast")  # where a threshold at K helps (tests/test_fit.py)
TOL = 1e-12  # m, float64: the same per-run losses summed in another order (or another batch shape)


@pytest.fixture(scope="module")
def counts_data():
    """18 "counts" runs, each with a bad episode (frames with fewer than K inliers and a gross visual
    error): 2 of the first 20 seeds have none and are skipped."""
    seeds = [
        s for s in range(20) if np.any(ka.make_run("counts", s, n_frames=400, k_min=K).frames.n_inliers < K)
    ]
    assert len(seeds) == 18
    return FitData.from_runs(ka.make_study("counts", seeds, n_frames=400, k_min=K), COAST)


def _float64(build):
    """Data built in float64 (the tests using it turn x64 on for their own run too)."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        return build()
    finally:
        jax.config.update("jax_enable_x64", previous)


@pytest.fixture(scope="module")
def counts64():
    runs = ka.make_study("counts", range(12), n_frames=300, k_min=K)
    return _float64(lambda: FitData.from_runs(runs, COAST, dtype=jnp.float64))


@pytest.fixture(scope="module")
def occlusion64():
    runs = ka.make_study("occlusion", range(12), n_frames=300)
    return _float64(lambda: FitData.from_runs(runs, dtype=jnp.float64))


def _design(space, n: int, seed: int = 0) -> np.ndarray:
    return np.asarray(space.values_from_unit(sobol(n, space.dim, seed=seed)), np.float64)


def _cache(data: FitData, space, values) -> RunLossCache:
    return RunLossCache(data.scorer, space, values)


def _exhaustive(data: FitData, space, values):
    return search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)


def _fields(res):
    return (res.values, res.loss, res.failed, res.rmse, res.coverage, res.unsupported, res.included)


# ---------------------------------------------------------------------------------------------------
# Rungs and the order of runs


def test_rung_sizes():
    assert rung_sizes(81, 90, 3, 1 / 9) == [(81, 10), (27, 30), (9, 90)]
    assert rung_sizes(2051, 3410, 3, 1 / 9) == [(2051, 379), (684, 1137), (228, 3410)]
    assert rung_sizes(100, 50, 3, 1.0) == [(100, 50)]
    assert rung_sizes(10, 4, 2, 0.1) == [(10, 1), (5, 1), (3, 2), (2, 4)]  # at least one run a rung
    for s, r, eta, f0 in [(2048, 93, 3, 1 / 9), (500, 1000, 2, 0.05), (7, 3, 4, 0.3), (64, 64, 2.5, 1 / 27)]:
        sizes = rung_sizes(s, r, eta, f0)
        assert sizes[-1][1] == r and all(1 <= n <= r for _, n in sizes)
        assert [n for _, n in sizes] == sorted(n for _, n in sizes)
        assert [k for k, _ in sizes] == [math.ceil(s / eta**i) for i in range(len(sizes))]
    with pytest.raises(ValueError, match="eta > 1"):
        rung_sizes(10, 10, 1, 0.5)
    with pytest.raises(ValueError, match="initial_fraction"):
        FitConfig(search="halving", initial_fraction=0.0)
    with pytest.raises(ValueError, match="exhaustive"):
        FitConfig(search="bisection")


def test_stratified_order_covers_every_group_in_every_prefix():
    """One run of every group before a second of any; no group two runs ahead of another that has
    runs left, in every prefix."""
    meta = pd.DataFrame({"sequence": list("AAAAABBBCC"), "level": [0, 0, 1, 1, 1, 0, 0, 0, 1, 1]})
    order = stratified_order(meta, 10, seed=3)
    assert sorted(order) == list(range(10))
    groups = (meta["sequence"] + meta["level"].astype(str)).to_numpy()
    sizes = pd.Series(groups).value_counts()
    assert len(set(groups[order[: len(sizes)]])) == len(sizes)  # one of each of the 4 groups first
    for n in range(1, 11):
        counts = pd.Series(groups[order[:n]]).value_counts()
        open_groups = [g for g in sizes.index if counts.get(g, 0) < sizes[g]]
        if open_groups:
            assert counts.max() - min(counts.get(g, 0) for g in open_groups) <= 1
    # The study's metadata: every (sequence, disturbance, level) group within the first rung of 1/9.
    rng = np.random.default_rng(0)
    study = pd.DataFrame(
        {"sequence": rng.choice(list("ABCDE"), 900), "disturbance": rng.choice(["blur", "noise"], 900)}
    )
    study["level"] = rng.integers(0, 9, 900)
    first = stratified_order(study, 900, seed=1)[:100]
    key = study[["sequence", "disturbance", "level"]].astype(str).agg("/".join, axis=1)
    assert set(key.iloc[first]) == set(key)
    assert not np.array_equal(stratified_order(study, 900, seed=2)[:100], first)


def test_stratified_order_without_groups_is_a_permutation():
    order = stratified_order(None, 7, seed=0)
    assert sorted(order) == list(range(7))
    with pytest.raises(ValueError, match="meta has 3 rows"):
        stratified_order(pd.DataFrame({"sequence": list("ABC")}), 4)


# ---------------------------------------------------------------------------------------------------
# The kernel on a subset of the runs


def test_subset_parts_give_the_full_batch_columns_eagerly_and_under_jit(counts64, x64):
    """The search kernel on a gathered, padded subset of the runs equals its columns of the full batch,
    called eagerly (the host picks the scan) and under jax.jit (the traced lax.cond): to 1e-12 m."""
    space = inlier_space()
    values = _design(space, 8, seed=2)
    rules = space.rule(jnp.asarray(values))
    runs = np.array([0, 3, 4, 9, 10])  # 5 real runs, padded to 8
    parts, counts, columns = subset_parts(counts64.parts, counts64.run_counts, runs)
    np.testing.assert_array_equal(columns, runs)
    assert counts == [5] and parts[0].n_runs == 8
    full = search_chunk(counts64.parts[0], rules, counts64.config)
    eager = search_chunk(parts[0], rules, counts64.config)
    jitted = jax.jit(search_chunk, static_argnums=2)(parts[0], rules, counts64.config)
    for out in (eager, jitted):
        for name in ("loss", "rmse", "coverage"):
            a, b = np.asarray(getattr(out, name))[:, :5], np.asarray(getattr(full, name))[:, runs]
            np.testing.assert_allclose(a, b, rtol=0, atol=TOL, equal_nan=True)
        for name in ("failed", "unsupported", "included"):
            np.testing.assert_array_equal(
                np.asarray(getattr(out, name))[:, :5], np.asarray(getattr(full, name))[:, runs]
            )


# ---------------------------------------------------------------------------------------------------
# Halving against the exhaustive search


def test_one_rung_over_all_runs_is_the_exhaustive_search(counts_data):
    """initial_fraction = 1: one rung, every setting on every run, the same kernel calls: equal bit for
    bit, and so is the fit from it."""
    space = inlier_space()
    values = _design(space, 48)
    exhaustive = _exhaustive(counts_data, space, values)
    halving = halving_search(
        _cache(counts_data, space, values), np.ones(counts_data.n_runs), eta=3, initial_fraction=1.0
    )
    assert len(halving.rungs) == 1 and halving.evaluations == 48 * counts_data.n_runs
    for a, b in zip(_fields(exhaustive), _fields(halving.search), strict=True):
        np.testing.assert_array_equal(a, b)
    config = dict(n_search=48, n_starts=0, include_presets=False)
    by_halving = fit(counts_data, space, None, FitConfig(search="halving", initial_fraction=1.0, **config))
    by_search = fit(counts_data, space, None, FitConfig(**config))
    np.testing.assert_array_equal(by_halving.values, by_search.values)
    assert by_halving.objective == by_search.objective
    # the search stage records the method that ran ("auto" resolves to exhaustive below 300 runs)
    assert by_halving.stages[0]["method"] == "halving" and by_search.stages[0]["method"] == "exhaustive"
    given = fit(counts_data, space, None, FitConfig(**config), search_result=by_search.search)
    assert given.stages[0]["method"] == "given"


@pytest.mark.parametrize("kind", ["counts", "occlusion"])
def test_every_rung_keeps_the_best_by_the_exhaustive_matrix(kind, counts64, occlusion64, x64):
    """Each rung keeps the ceil(S / eta^(k+1)) settings that the exhaustive search's per-run losses rank
    best on that rung's runs (a stratified prefix of the weighted runs; unequal weights, 3 runs held out),
    and the survivors' results on all runs equal the exhaustive search's rows: objectives to 1e-12 m in
    float64, flags exactly. Ties are allowed in either order (a kept setting is never worse than a
    dropped one by more than 1e-12 m)."""
    data, space = (counts64, inlier_space()) if kind == "counts" else (occlusion64, sve_space())
    values = _design(space, 60, seed=5)
    exhaustive = _exhaustive(data, space, values)
    w = np.linspace(0.5, 2.0, data.n_runs)
    w[[1, 5, 8]] = 0.0
    order = stratified_order(data.meta, data.n_runs, seed=9)
    halving = halving_search(_cache(data, space, values), w, eta=2, initial_fraction=0.25, order=order)
    # rung k: the study's rung-k prefix of the order (sizes over all 12 runs) less the held-out runs
    sizes = rung_sizes(len(values), data.n_runs, 2, 0.25)
    assert sizes == [(60, 3), (30, 6), (15, 12)]
    prefixes = [np.sort(order[:n])[w[np.sort(order[:n])] > 0] for _, n in sizes]
    expected = [(s, len(p)) for (s, _), p in zip(sizes, prefixes, strict=True)]
    assert [(r.settings, r.runs) for r in halving.rungs] == expected
    for k in range(len(sizes) - 1):
        runs = prefixes[k]
        rows = halving.scored[k]
        kept = np.isin(rows, halving.scored[k + 1])
        obj = exhaustive.objective(np.where(np.isin(np.arange(data.n_runs), runs), w, 0.0))[rows]
        assert kept.sum() == sizes[k + 1][0]
        assert obj[kept].max() <= obj[~kept].min() + TOL
        assert halving.rungs[k].best == pytest.approx(obj.min(), abs=TOL)
    final = halving.scored[-1]
    np.testing.assert_array_equal(halving.search.values, values[final])
    np.testing.assert_allclose(halving.search.objective(w), exhaustive.objective(w)[final], rtol=0, atol=TOL)
    np.testing.assert_allclose(halving.search.loss, exhaustive.loss[final], rtol=0, atol=TOL)
    for name in ("failed", "unsupported", "included"):
        np.testing.assert_array_equal(getattr(halving.search, name), getattr(exhaustive, name)[final])
    # each pair once: all 60 on rung 0's runs, then the survivors on the runs new to them (held-out
    # ones last)
    first, second = len(prefixes[0]), len(prefixes[1])
    assert halving.evaluations == 60 * first + 30 * (second - first) + 15 * (data.n_runs - second)


def _accepting_all(space, n: int, seed: int) -> np.ndarray:
    """Sobol settings of the inlier thresholds with imu_init in [0, K - 30]: while tracking they accept
    every frame of the "counts" logs (bad frames have K - 30 or more inliers), bad ones included."""
    values = _design(space, n, seed=seed)
    i = space.names.index("imu_init")
    values[:, i] = (values[:, i] - space.lo[i]) * (K - 30) / (space.hi[i] - space.lo[i])
    return values


def test_halving_finds_a_clearly_best_setting(counts_data):
    """On the "counts" logs a frame's visual pose is right exactly when it has K or more inliers, and
    off by 0.3-1 m when it has fewer. The planted setting (imu_init, reloc and recovery in (K - 1, K])
    tracks every good frame and coasts on the IMU over every bad one (at most 2.5 s: centimetres);
    every other setting of the design accepts the bad frames, and every run has some. So the planted
    one is the best on every run by construction (by more than 10x, checked on the exhaustive search),
    hence on any subset of runs, and halving from 2 runs must keep it on every rung and select it; with
    the ranking reversed it would be dropped on the first rung."""
    space = inlier_space()
    values = _accepting_all(space, 80, seed=3)
    planted = values[37].copy()
    for name, value in (("imu_init", K - 0.5), ("reloc", K - 0.5), ("recovery", K)):
        planted[space.names.index(name)] = value
    values = np.concatenate([values[:37], planted[None], values[37:]])
    exhaustive = _exhaustive(counts_data, space, values)
    others = np.delete(np.arange(81), 37)
    assert np.all(10 * exhaustive.loss[37] < exhaustive.loss[others].min(axis=0)), "not best on every run"
    w = np.ones(counts_data.n_runs)
    obj = exhaustive.objective(w)
    halving = halving_search(
        _cache(counts_data, space, values),
        w,
        eta=3,
        initial_fraction=1 / 9,
        order=stratified_order(counts_data.meta, counts_data.n_runs),
    )
    assert [(r.settings, r.runs) for r in halving.rungs] == [(81, 2), (27, 6), (9, 18)]
    assert all(37 in rung for rung in halving.scored)
    np.testing.assert_array_equal(halving.search.values[np.argmin(halving.search.objective(w))], planted)
    assert halving.rungs[-1].best == pytest.approx(obj[37], rel=1e-6)
    # nested prefixes: every pair is computed once, a third of the exhaustive search's 81 x 18
    assert halving.evaluations == 81 * 2 + 27 * 4 + 9 * 12 == 378 < 81 * 18 / 3.8


# ---------------------------------------------------------------------------------------------------
# Reuse across cross-validation folds


def test_fold_objectives_from_reused_losses_equal_the_kernel_per_fold(counts64, x64):
    """Each fold's training objective as a weighted sum of per-run losses scored once (the exhaustive
    search's matrix, and the halving cache that earlier folds filled) equals the kernel re-run on that
    fold's training runs alone: to 1e-12 m in float64 (summation order only)."""
    data, space = counts64, inlier_space()
    values = _design(space, 16, seed=1)
    full = _exhaustive(data, space, values)
    cache = _cache(data, space, values)
    w = np.linspace(0.5, 2.0, data.n_runs)  # unequal run weights
    order = stratified_order(data.meta, data.n_runs, seed=4)
    for fold in kfold(data.n_runs, 4, seed=2):
        train = np.flatnonzero(~fold.test)
        parts, counts, columns = subset_parts(data.parts, data.run_counts, train)
        np.testing.assert_array_equal(columns, train)
        alone = search(parts, space, values, data.config, run_counts=counts, progress=False)
        expected = alone.objective(w[train])
        np.testing.assert_allclose(full.objective(w * ~fold.test), expected, rtol=0, atol=TOL)
        halving_search(cache, w * ~fold.test, eta=2, initial_fraction=0.25, order=order)
        cache.fill(np.arange(16), train)
        reused = cache.result(np.arange(16), train).objective(w[train])
        np.testing.assert_allclose(reused, expected, rtol=0, atol=TOL)


def test_folds_share_the_cache_without_changing_results(counts64, x64):
    """Folds halving on one shared cache (the full fit's first), or in step (halving_searches), select
    what each would on its own, with the same results to 1e-12 m, and compute far fewer pairs."""
    data, space = counts64, inlier_space()
    values = _design(space, 64, seed=5)
    order = stratified_order(data.meta, data.n_runs, seed=0)
    shared = _cache(data, space, values)
    full_cost = halving_search(shared, np.ones(data.n_runs), order=order).evaluations  # the full fit
    folds = [(~fold.test).astype(float) for fold in kfold(data.n_runs, 3, seed=0)]
    in_step = halving_searches(_cache(data, space, values), folds, order=order)
    folds_cost = 0
    for w, joint in zip(folds, in_step, strict=True):
        with_shared = halving_search(shared, w, order=order)
        alone = halving_search(_cache(data, space, values), w, order=order)
        folds_cost += alone.evaluations
        for a, b, c in zip(with_shared.scored, alone.scored, joint.scored, strict=True):
            np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(c, b)
        np.testing.assert_allclose(with_shared.search.loss, alone.search.loss, rtol=0, atol=TOL)
        np.testing.assert_allclose(joint.search.loss, alone.search.loss, rtol=0, atol=TOL)
    assert shared.evaluations < 0.5 * (full_cost + folds_cost)
    assert in_step[0].evaluations < 0.7 * folds_cost  # in step: each pair once for all folds


def test_cross_validation_with_the_shared_cache_fits_as_without(counts64, x64, monkeypatch):
    """cross_validate under the halving search: the folds' fits (values, training objectives) and
    held-out losses with one cache shared by the folds and the full fit equal those of folds halving
    alone (the cache refused as too large): values exactly, objectives to 1e-12 m."""
    data, space = counts64, {"inliers": inlier_space()}
    config = FitConfig(search="halving", n_search=64, n_starts=0, eta=2, initial_fraction=0.25)
    folds = kfold(data.n_runs, 3, seed=1)
    full = fit(data, space["inliers"], None, config, progress=False)
    assert full.cache is not None and full.cache.evaluations < 64 * data.n_runs
    before = full.cache.evaluations
    shared = cross_validate(
        data, space, folds, None, config, presets=(), caches={"inliers": full.cache}, progress=False
    )
    added = full.cache.evaluations - before
    monkeypatch.setattr(RunLossCache, "fits", staticmethod(lambda *a, **k: False))
    alone = cross_validate(data, space, folds, None, config, presets=(), progress=False)
    names = list(space["inliers"].names)
    np.testing.assert_array_equal(shared.params[names].to_numpy(), alone.params[names].to_numpy())
    np.testing.assert_allclose(shared.params["train_objective"], alone.params["train_objective"], atol=TOL)
    np.testing.assert_allclose(shared.heldout["loss"], alone.heldout["loss"], atol=TOL)
    assert added < before  # the folds scored fewer new pairs than the full fit did
    with pytest.raises(ValueError, match="another design"):
        fit(data, space["inliers"], None, FitConfig(search="halving", n_search=32), cache=full.cache)
    assert np.array_equal(
        fit_cache(data, space["inliers"], config).values, search_design(space["inliers"], config)
    )


def test_halving_is_deterministic_under_the_seed(counts_data):
    space = inlier_space()
    values = _design(space, 40, seed=7)

    def run(seed):
        order = stratified_order(counts_data.meta, counts_data.n_runs, seed=seed)
        return order, halving_search(
            _cache(counts_data, space, values), np.ones(counts_data.n_runs), order=order
        )

    (o1, a), (o2, b) = run(11), run(11)
    np.testing.assert_array_equal(o1, o2)
    assert a.rungs == b.rungs
    for x, y in zip(_fields(a.search), _fields(b.search), strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(run(12)[0], o1)


@pytest.mark.parametrize(
    ("n_runs", "eta", "want"),
    [
        (50, 3.0, ("exhaustive", None)),
        (299, 3.0, ("exhaustive", None)),
        (300, 3.0, ("halving", 1 / 3)),
        (3410, 3.0, ("halving", 1 / 81)),
        (10_000, 3.0, ("halving", 1 / 243)),
        (3410, 2.0, ("halving", 1 / 64)),
        (299, 2.0, ("exhaustive", None)),  # below AUTO_HALVING_RUNS whatever the first rung
    ],
)
def test_auto_search_halves_from_300_runs_with_a_first_rung_of_at_least_40_runs(n_runs, eta, want):
    from jsve.fitting._fit import AUTO_FIRST_RUNG_RUNS, resolve_search

    resolved = resolve_search(FitConfig(search="auto", eta=eta), n_runs)
    method, f0 = want
    assert resolved.search == method
    if f0 is None:
        return
    assert resolved.initial_fraction == pytest.approx(f0)
    first = rung_sizes(2051, n_runs, eta, resolved.initial_fraction)[0][1]
    assert AUTO_FIRST_RUNG_RUNS <= first < AUTO_FIRST_RUNG_RUNS * eta  # the smallest such fraction
    for given in ("halving", "exhaustive"):
        config = FitConfig(search=given, initial_fraction=0.5)
        assert resolve_search(config, n_runs) == config


class _KnownLosses:
    """A scorer whose loss of setting s on run r is values[s, 0] x (1 + 10 r / R): on the first runs
    small settings win, everywhere else as well, so survivors show which runs a rung screened on."""

    def __init__(self, n_runs: int):
        from jsve.fitting._scorer import Meter

        self.n_runs, self.meter = n_runs, Meter()

    def score(self, space, values, runs=None, **_):
        from jsve.fitting._search import SearchResult

        runs = np.arange(self.n_runs) if runs is None else np.asarray(runs)
        loss = np.asarray(values)[:, :1] * (1 + 10 * runs[None] / self.n_runs)
        flag = np.zeros(loss.shape, bool)
        return SearchResult(np.asarray(values), loss, flag, loss, np.ones(loss.shape), flag, ~flag)


def test_a_fold_holding_out_a_rungs_whole_prefix_screens_on_its_own_first_runs():
    """A fold whose weight is 0 on all of the first rung's runs screens that rung on its own first
    weighted runs of the order (a finite objective), not on none; its survivors are then the best there
    by hand, and the other fold's are unchanged."""
    n_runs, values = 81, np.linspace(1.0, 0.1, 27)[:, None]
    cache = RunLossCache(_KnownLosses(n_runs), None, values)
    order = np.arange(n_runs)
    held_first = np.ones(n_runs)
    held_first[:9] = 0  # the first rung's 9 runs (81 / 9)
    (fold, other) = halving_searches(cache, [held_first, np.ones(n_runs)], eta=3.0, initial_fraction=1 / 9,
                                     order=order)  # fmt: skip
    assert np.isfinite([r.best for r in fold.rungs]).all()
    assert fold.rungs[0].runs == 9  # runs 9..17, its own first 9 weighted runs of the order
    first = np.mean(0.1 * (1 + 10 * np.arange(9, 18) / n_runs))  # the smallest value's mean there
    assert fold.rungs[0].best == pytest.approx(first)
    assert other.rungs[0].best == pytest.approx(np.mean(0.1 * (1 + 10 * np.arange(9) / n_runs)))
    # the loss grows with the value on every run: the 9 smallest values survive the first rung in both
    assert np.array_equal(fold.scored[1], np.arange(18, 27)) and np.array_equal(
        other.scored[1], np.arange(18, 27)
    )
