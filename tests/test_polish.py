"""jsve.fitting._polish: Nelder-Mead on a stratified subset of runs packed into one part.

The packed part must score every run exactly as the run's own length bucket does (its padding to the
longest part's frames changes nothing), and a fit that polishes on a subset must judge on all runs."""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.fitting._fit import FitConfig, FitData, fit, hard_objective
from jsve.fitting._polish import pack_runs, polish_runs
from jsve.fitting._search import search
from jsve.fitting._space import ParamSpace, inlier_space
from jsve.sim import _motion as sm
from jsve.sim import _simulate as sim


@pytest.fixture(scope="module")
def data() -> FitData:
    """18 runs of three lengths (three parts of different frame counts), on three sequences: 12
    known-answer runs and 6 simulated ones under heavy blur (lost tracking, new maps, IMU initialisation
    along the run: what the padding of a packed run must not disturb)."""
    runs = []
    for k, n_frames in enumerate((150, 320)):
        runs += ka.make_study("occlusion", range(10 * k, 10 * k + 6), n_frames=n_frames)
    config = sim.SimConfig(flight=sm.FlightProfile(duration_s=(30.0, 30.0)))
    runs += [sim.simulate_run(f"proc_0{i % 3}", "blur", 40, run=i, seed=3, config=config) for i in range(6)]
    data = FitData.from_runs(runs)
    assert len({p.n_frames for p in data.parts}) == 3
    return data


def _space() -> ParamSpace:
    return inlier_space()


def test_a_packed_part_scores_each_run_as_its_own_bucket(data):
    """Per-run loss, failure, RMSE and coverage of a packed subset (runs from every part, padded to the
    longest part) equal the same runs' results on their own parts, for many settings."""
    space = _space()
    unit = np.random.default_rng(0).random((16, space.dim))
    values = np.asarray(space.values_from_unit(unit), np.float64)
    runs = np.array([0, 3, 7, 8, 12, 17])
    whole = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)
    packed = pack_runs(data.parts, data.run_counts, runs)
    assert packed.n_runs == len(runs) and packed.n_frames == max(p.n_frames for p in data.parts)
    part = search([packed], space, values, data.config, progress=False)
    for key in ("loss", "rmse", "coverage", "failed", "included"):
        np.testing.assert_allclose(getattr(part, key), getattr(whole, key)[:, runs], rtol=1e-5, atol=1e-6)
    # both outcomes among the packed runs' results, or the test would not test the padding of a failure
    assert np.any(whole.failed[:, runs]) and np.any(~whole.failed[:, runs])


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
