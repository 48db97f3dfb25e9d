"""jsve.fitting._polish: Nelder-Mead on a stratified subset of runs packed into one part.

The packed part must score every run exactly as the run's own length bucket does (its padding to the
longest part's frames changes nothing), and a fit that polishes on a subset must judge on all runs."""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.fitting import _packing
from jsve.fitting._crossval import cross_validate, kfold, rule_results
from jsve.fitting._data import FitData
from jsve.fitting._fit import FitConfig, fit, search_all, search_design
from jsve.fitting._optimise import hard_objective, nelder_mead
from jsve.fitting._packing import frame_classes, pack_runs, packing, subset_parts
from jsve.fitting._polish import polish_in_lockstep, polish_runs
from jsve.fitting._search import search
from jsve.fitting._space import ParamSpace, inlier_space
from jsve.sim import _config as sim_config
from jsve.sim import _simulate as sim
from jsve.sim import _trajectory as st


@pytest.fixture(scope="module")
def data() -> FitData:
    """18 runs of three lengths (three parts of different frame counts), on three sequences: 12
    known-answer runs and 6 simulated ones under heavy blur (lost tracking, new maps, IMU initialisation
    along the run: what the padding of a packed run must not disturb)."""
    runs = []
    for k, n_frames in enumerate((150, 320)):
        runs += ka.make_study("occlusion", range(10 * k, 10 * k + 6), n_frames=n_frames)
    config = sim_config.SimConfig(flight=st.FlightProfile(duration_s=(30.0, 30.0)))
    runs += [sim.simulate_run(f"proc_0{i % 3}", "blur", 40, run=i, seed=3, config=config) for i in range(6)]
    data = FitData.from_runs(runs)
    assert len({p.n_frames for p in data.parts}) == 3
    return data


def _space() -> ParamSpace:
    return inlier_space()


@pytest.fixture(scope="module")
def whole(data):
    """64 random settings scored on the study's own parts: what the tests of the packed layouts compare
    each packed run with (one search of one settings count: every layout's compiled scans are shared)."""
    space = _space()
    values = np.asarray(space.values_from_unit(np.random.default_rng(2).random((64, space.dim))))
    return search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)


def test_a_packed_part_scores_each_run_as_its_own_bucket(data, whole):
    """Per-run loss, failure, RMSE and coverage of a packed subset (runs from every part, padded to the
    longest part) equal the same runs' results on their own parts, for many settings."""
    space, values = _space(), whole.values
    runs = np.array([0, 3, 7, 8, 12, 17])
    packed = pack_runs(data.parts, data.run_counts, runs)
    assert packed.n_runs == len(runs) and packed.n_frames == max(p.n_frames for p in data.parts)
    part = search([packed], space, values, data.config, progress=False)
    for key in ("loss", "rmse", "coverage", "failed", "included"):
        np.testing.assert_allclose(getattr(part, key), getattr(whole, key)[:, runs], rtol=1e-5, atol=1e-6)
    # both outcomes among the packed runs' results, or the test would not test the padding of a failure
    assert np.any(whole.failed[:, runs]) and np.any(~whole.failed[:, runs])


def test_a_subset_is_packed_by_length_class_and_scores_as_its_own_parts(data, whole, monkeypatch):
    """subset_parts: a part whose runs are all selected is passed as it is; the other selected runs are
    packed by length class into parts of at most PACK_RUNS runs, a power of 2 with padding; every
    selected run scores as on its own part, and the columns name the runs in the order scored."""
    space, values = _space(), whole.values
    starts = np.cumsum([0, *data.run_counts])
    # all runs of the first part, all but the first of each other part
    runs = np.concatenate(
        [np.arange(data.run_counts[0])]
        + [np.arange(a + 1, b) for a, b in zip(starts[1:-1], starts[2:], strict=True)]
    )
    assert all(n > 5 for n in data.run_counts[1:])
    monkeypatch.setattr(_packing, "PACK_RUNS", 4)  # a class of more than 4 selected runs fills two parts
    frames = [p.n_frames for p in data.parts]
    layout = packing(data.run_counts, [(p.n_frames, p.n_runs) for p in data.parts], runs)
    assert layout[0].whole and layout[0].frames == frames[0] and layout[0].n_real == data.run_counts[0]
    assert all(not item.whole and item.n_real <= 4 for item in layout[1:])
    assert all(item.runs == _packing.padded_runs(item.n_real) for item in layout[1:])
    assert sum(item.n_real for item in layout) == len(runs) and len(layout) >= 4
    classes = frame_classes(frames, [p.n_runs for p in data.parts])
    for item in layout[1:]:  # a packed part has the frames of its class's longest part
        (c,) = {classes[p] for p, _ in item.picks}
        assert item.frames == max(f for f, k in zip(frames, classes, strict=True) if k == c)
    parts, counts, columns = subset_parts(data.parts, data.run_counts, runs)
    assert sorted(columns) == sorted(runs) and counts == [item.n_real for item in layout]
    assert parts[0] is data.parts[0]
    sub = search(parts, space, values, data.config, run_counts=counts, progress=False)
    for key in ("loss", "rmse", "coverage", "failed", "included"):
        np.testing.assert_allclose(getattr(sub, key), getattr(whole, key)[:, columns], rtol=1e-5, atol=1e-6)


def test_the_layout_is_the_cheapest_of_one_part_and_length_classes(data, whole):
    """subset_layout packs a subset into one part or by 2 or 4 length classes, whichever scan_cost prices
    lowest (a call's steps dominate a narrow call: few settings favour one part; many settings the
    classes, which pad less); every layout scores every run as its own part does."""
    space = _space()
    shapes = [(p.n_frames, p.n_runs) for p in data.parts]
    starts = np.cumsum([0, *data.run_counts])
    runs = np.concatenate([np.arange(a, a + 2) for a in starts[:-1]])  # 2 runs of each part
    whole_values = whole.values
    few, many = 1, 4096
    assert _packing.cheapest_layout(data.run_counts, shapes, runs, few) == 0
    chosen = _packing.cheapest_layout(data.run_counts, shapes, runs, many)
    costs = {k: _packing.scan_cost(_packing.layout_shapes(data.run_counts, shapes, runs, k), many)
             for k in (0, *_packing.LAYOUT_CLASSES)}  # fmt: skip
    assert chosen in _packing.LAYOUT_CLASSES and costs[chosen] == min(costs.values()) < costs[0]
    # by hand for one setting (one call of one lane-setting per part): frames x (step lanes + runs)
    classes = [(item.frames, item.runs) for item in packing(data.run_counts, shapes, runs)]
    longest = max(f for f, _ in shapes)
    assert _packing.layout_shapes(data.run_counts, shapes, runs, 0) == [(longest, len(runs))]
    assert _packing.layout_shapes(data.run_counts, shapes, runs, _packing.FRAME_CLASSES) == classes
    assert _packing.scan_cost([(longest, len(runs))], 1) == longest * (_packing.SCAN_STEP_LANES + len(runs))
    assert _packing.scan_cost(classes, 1) == sum(f * (_packing.SCAN_STEP_LANES + r) for f, r in classes)
    for n_settings in (few, many):
        parts, counts, columns = _packing.subset_layout(data.parts, data.run_counts, runs[::-1], n_settings)
        k = _packing.cheapest_layout(data.run_counts, shapes, runs, n_settings)
        assert [(p.n_frames, p.n_runs) for p in parts] == _packing.layout_shapes(
            data.run_counts, shapes, runs, k
        )
        assert sorted(columns) == sorted(runs) and sum(counts) == len(runs)
    for k in _packing.LAYOUT_CLASSES:  # every class count scores the runs as their own parts do
        parts, counts, columns = _packing.subset_parts(data.parts, data.run_counts, runs, k)
        assert len(parts) == len(_packing.layout_shapes(data.run_counts, shapes, runs, k))
        scored = search(list(parts), space, whole_values, data.config, run_counts=counts, progress=False)
        for key in ("loss", "rmse", "coverage", "failed", "included"):
            np.testing.assert_allclose(
                getattr(scored, key), getattr(whole, key)[:, columns], rtol=1e-5, atol=1e-6
            )
    one, counts, columns = _packing.subset_layout(data.parts, data.run_counts, runs, few)
    scored = search(list(one), space, whole_values, data.config, run_counts=counts, progress=False)
    np.testing.assert_allclose(scored.loss, whole.loss[:, columns], rtol=1e-5, atol=1e-6)
    # one part pads every run to the longest: never for more than ONE_PART_RUNS runs
    assert (
        _packing.cheapest_layout(
            [1000, 1000], [(100, 1000), (100, 1000)], np.arange(_packing.ONE_PART_RUNS + 1), 1
        )
        != 0
    )


def test_frame_classes_cut_parts_by_length_into_classes_of_about_equal_runs():
    classes = frame_classes([300, 100, 200, 400], [10, 10, 10, 10], 2)
    np.testing.assert_array_equal(classes, [1, 0, 0, 1])
    assert np.array_equal(frame_classes([100, 200], [1, 100], 4), [0, 0])  # a part is never split
    assert len(set(frame_classes(np.arange(27) * 64 + 1900, np.full(27, 126)))) == 4


def test_the_subset_is_stratified_weighted_and_sorted(data):
    w = np.ones(data.n_runs)
    assert polish_runs(data.meta, w, 0) is None and polish_runs(data.meta, w, data.n_runs) is None
    subset = polish_runs(data.meta, w, 6)
    assert np.all(np.diff(subset) > 0) and len(subset) == 6
    # 3 sequences x 2 levels: a 6-run prefix of the stratified order takes one run of each group
    groups = data.meta.iloc[subset][["sequence", "level"]].astype(str).agg("/".join, axis=1)
    assert groups.nunique() == 6
    w[:9] = 0  # a held-out fold: its runs are never polished on
    assert np.all(polish_runs(data.meta, w, 6) >= 9)
    assert polish_runs(data.meta, w, 9) is None


def test_folds_polish_on_the_full_fits_polish_runs_less_their_held_out_ones(data):
    """With the study's weights as the pool, a fold's polish runs are the full fit's less its held-out
    runs, so folds moving in lockstep scan the full fit's runs only (not a union of 6 runs a fold)."""
    w = np.ones(data.n_runs)
    full = polish_runs(data.meta, w, 6)
    folds = kfold(data.n_runs, 3, seed=1)
    for fold in folds:
        own = polish_runs(data.meta, w * ~fold.test, 6, pool=w)
        np.testing.assert_array_equal(own, full[~fold.test[full]])
        alone = polish_runs(data.meta, w * ~fold.test, 6)  # without the pool: its own first 6
        assert len(alone) == 6 and not np.any(fold.test[alone])
    space = _space()
    start = space.values_from_unit(np.full(space.dim, 0.5))
    trains = [w * ~fold.test for fold in folds]
    starts = [(k, np.asarray(start, np.float64)) for k in range(len(folds))]
    common = dict(n_runs=6, seed=0, step=0.5, max_steps=3, window=0, ftol=0.0)
    pooled = polish_in_lockstep(data, space, trains, starts, pool=w, **common)
    assert pooled.runs_scanned == 6
    assert list(pooled.polish_runs) == [int((~fold.test[full]).sum()) for fold in folds]
    assert polish_in_lockstep(data, space, trains, starts, **common).runs_scanned > 6
    with pytest.raises(ValueError, match="pool has shape"):
        polish_runs(data.meta, w, 6, pool=w[:-1])


def test_a_fit_polished_on_a_subset_is_judged_on_every_run(data):
    """With polish_runs below the runs, Nelder-Mead moves on the subset; the fit's objective is the hard
    objective of its values over every run, never worse than the search's best, and the stage records
    how many runs it polished on."""
    space = _space()
    config = FitConfig(n_search=32, n_starts=1, nm_steps=15, polish_runs=6)
    result = fit(data, space, config=config, progress=False)
    (polish,) = [s for s in result.stages if s["stage"].startswith("nelder_mead")]
    assert polish["polish_runs"] == 6
    assert polish["objective"] == pytest.approx(hard_objective(data, space, polish["values"]), rel=1e-6)
    assert result.objective == pytest.approx(hard_objective(data, space, result.values), rel=1e-6)
    assert result.objective <= result.stages[0]["objective"] + 1e-9
    config = FitConfig(n_search=32, n_starts=1, nm_steps=15, polish_runs=0)
    on_all = fit(data, space, config=config, progress=False)
    (polish_all,) = [s for s in on_all.stages if s["stage"].startswith("nelder_mead")]
    assert polish_all["polish_runs"] == data.n_runs


@pytest.mark.parametrize("bad", [-1, 2.5, "all"])
def test_a_wrong_polish_runs_is_refused(bad):
    with pytest.raises(ValueError, match="polish_runs must be a count"):
        FitConfig(polish_runs=bad)


def test_cross_validation_judges_its_folds_together_as_each_fold_alone(data):
    """cross_validate polishes each fold on the full fit's polish runs less its held-out ones, then judges
    all folds in one batched search (jsve.fitting._fit.judge). Each fold's fitted values and training
    objective equal a fit of that fold alone from the same search and pool, its polishes' values equal
    Nelder-Mead run alone from the same starts, and its held-out rows equal an independent one-setting
    search of its fitted values."""
    space = _space()
    config = FitConfig(n_search=32, n_starts=2, nm_steps=15, polish_runs=6, search="exhaustive")
    folds = kfold(data.n_runs, 3, seed=0)
    cv = cross_validate(data, {"inliers": space}, folds, config=config, presets=("orbslam3",), progress=False)
    searched = search_all(data, space, search_design(space, config), progress=False)
    for fold in folds:
        train = (~fold.test).astype(np.float64)
        alone = fit(
            data, space, train, config, search_result=searched, pool=np.ones(data.n_runs), progress=False
        )
        row = cv.params[cv.params["fold"] == fold.name].iloc[0]
        np.testing.assert_array_equal([row[n] for n in space.names], alone.values)
        assert row["train_objective"] == pytest.approx(alone.objective, rel=1e-12)
        assert alone.objective == pytest.approx(hard_objective(data, space, alone.values, train), rel=1e-6)
        starts = searched.values[np.argsort(searched.objective(train), kind="stable")[:2]]
        for start, stage in zip(starts, alone.stages[1:], strict=True):
            values, value, _ = nelder_mead(
                data, space, start, train, max_steps=15, window=config.nm_window, ftol=config.nm_ftol,
                on_runs=6, seed=config.seed, pool=np.ones(data.n_runs),
            )  # fmt: skip
            np.testing.assert_array_equal(stage["values"], values)
            assert stage["objective"] == pytest.approx(value, rel=1e-6)
        held = cv.heldout[(cv.heldout["fold"] == fold.name) & (cv.heldout["rule"] == "fitted-inliers")]
        oracle = rule_results(data, space, alone.values)
        np.testing.assert_array_equal(held["run_index"], np.flatnonzero(fold.test))
        np.testing.assert_allclose(held["loss"], oracle.loss[0, fold.test], rtol=1e-6)
        np.testing.assert_array_equal(held["failed"], oracle.failed[0, fold.test])


def test_the_verdict_scores_each_distinct_candidate_once(data):
    """judge scores fits that share candidates (folds with the same search best) once per distinct
    setting, and each fit's verdict is that of the fit judged alone."""
    from jsve.fitting import _fit

    space = _space()
    config = FitConfig(n_search=32, n_starts=1, nm_steps=3, polish_runs=6, search="exhaustive")
    searched = search_all(data, space, search_design(space, config), progress=False)
    weights = [np.ones(data.n_runs), np.ones(data.n_runs)]  # two fits with the same candidates
    pending = _fit.polish_fits(data, space, [(w, searched) for w in weights], config)
    calls, settings = data.meter.calls, data.meter.settings  # the scorer's meter counts every request
    both = _fit.judge(data, space, pending)
    assert data.meter.calls - calls == 1
    assert data.meter.settings - settings == len(
        np.unique(np.stack([v for _, v in pending[0].candidates]), axis=0)
    )
    alone = _fit.judge(data, space, pending[:1])
    for result in both:
        np.testing.assert_array_equal(result.values, alone[0].values)
        assert result.objective == alone[0].objective


def test_a_relaxed_fit_is_judged_with_the_polishes(data):
    """relaxed = true: the annealed BFGS starts from the best candidate so far and its result is one more
    candidate of the verdict: its stage's objective is the hard objective of its values on every run,
    and the fit keeps the lowest of all candidates."""
    space = _space()
    config = FitConfig(n_search=32, n_starts=1, nm_steps=8, polish_runs=6, relaxed=True, temperatures=(0.1,))
    result = fit(data, space, config=config, progress=False)
    assert [s["stage"] for s in result.stages] == ["search", "nelder_mead_0", "relaxed"]
    relaxed = result.stages[-1]
    assert relaxed["objective"] == pytest.approx(hard_objective(data, space, relaxed["values"]), rel=1e-6)
    assert result.objective == pytest.approx(min(s["objective"] for s in result.stages), rel=1e-9)
