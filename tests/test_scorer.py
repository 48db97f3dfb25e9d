"""jsve.fitting._scorer: the one seam between the optimisers and the kernel.

Oracle: the search kernel over the study's own length buckets (`search` on FitData.parts), which
tests/test_search.py checks against the reference replay and evo; a scorer must give each run that
run's results whatever layout, subset or view it picks, in the order it states.
"""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.fitting._data import FitData
from jsve.fitting._scorer import Meter, ReplayScorer
from jsve.fitting._search import RESULT_FIELDS, SearchResult, search
from jsve.fitting._space import inlier_space


@pytest.fixture(scope="module")
def data() -> FitData:
    """12 known-answer runs of two lengths (two parts)."""
    runs = []
    for k, n_frames in enumerate((150, 320)):
        runs += ka.make_study("occlusion", range(10 * k, 10 * k + 6), n_frames=n_frames)
    return FitData.from_runs(runs)


@pytest.fixture(scope="module")
def values() -> np.ndarray:
    space = inlier_space()
    return np.asarray(space.values_from_unit(np.random.default_rng(0).random((12, space.dim))), np.float64)


@pytest.fixture(scope="module")
def whole(data, values) -> SearchResult:
    return search(data.parts, inlier_space(), values, data.config, run_counts=data.run_counts, progress=False)


def _close(a: SearchResult, b: SearchResult, columns=None) -> None:
    for name in RESULT_FIELDS:
        expected = getattr(b, name) if columns is None else getattr(b, name)[:, columns]
        np.testing.assert_allclose(getattr(a, name), expected, rtol=1e-5, atol=1e-6, err_msg=name)


def test_every_run_is_the_kernel_on_the_studys_parts(data, values, whole):
    got = data.scorer.score(inlier_space(), values)
    for name in RESULT_FIELDS:  # the same call: bit for bit
        np.testing.assert_array_equal(getattr(got, name), getattr(whole, name))


def test_a_subset_comes_back_in_run_order_whatever_order_it_is_asked_in(data, values, whole):
    runs = np.array([11, 0, 7, 3, 6])  # from both parts, out of order
    got = data.scorer.score(inlier_space(), values, runs)
    assert got.loss.shape == (len(values), len(runs))
    _close(got, whole, np.sort(runs))
    assert np.unique(whole.loss[:, np.sort(runs)].round(6), axis=1).shape[1] == len(runs)  # a swap would show


def test_a_view_scores_its_runs_in_the_order_it_states(data, values, whole):
    space = inlier_space()
    for n_settings in (1, 400):  # one packed part for few settings, length classes for many
        view = data.scorer.on([9, 2, 5, 10, 1], n_settings)
        assert sorted(view.runs.tolist()) == [1, 2, 5, 9, 10] and view.n_runs == 5
        _close(view.score(space, values), whole, view.runs)
        some = view.score(space, values, [4, 0])  # the view's own indices
        _close(some, whole, view.runs[[0, 4]])


def test_large_requests_go_to_the_workers_and_views_never(data, values):
    calls = []

    class Workers:
        min_setting_runs = 20

        def __call__(self, space, v, runs, *, progress=False, desc=""):
            calls.append((len(v), None if runs is None else runs.tolist()))
            n = data.n_runs if runs is None else len(runs)
            return SearchResult(v, *(np.zeros((len(v), n)) for _ in RESULT_FIELDS))

    scorer = ReplayScorer(data.parts, data.run_counts, data.config, Workers())
    space = inlier_space()
    scorer.score(space, values[:10], [3, 1])  # 20 setting-runs: to the workers
    scorer.score(space, values[:9], [3, 1])  # 18: in this process
    scorer.score(space, values[:2])  # 2 x 12: to the workers
    scorer.on([1, 2, 3], len(values)).score(space, values)  # a view: in this process
    assert calls == [(10, [1, 3]), (2, None)]


def test_the_meter_counts_every_request_of_a_scorer_and_its_views(data, values):
    meter = Meter()
    scorer = ReplayScorer(data.parts, data.run_counts, data.config, meter=meter)
    space = inlier_space()
    scorer.score(space, values[:3])
    scorer.score(space, values[:2], [0, 5, 5])
    scorer.on([0, 1, 2, 3], 2).score(space, values[:2])
    assert (meter.calls, meter.settings) == (3, 7)
    assert meter.setting_runs == 3 * data.n_runs + 2 * 2 + 2 * 4
