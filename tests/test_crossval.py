"""jsve.fitting._crossval: folds, bootstrap intervals, cross-validation and the held-out comparison.

Oracles: jsve.evaluation._aggregate.bootstrap_ci (the weighted bootstrap with unit weights), the presets'
losses on all runs (a preset is not refitted per fold), and logs whose best inlier threshold is K.
"""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import preset
from jsve.evaluation._aggregate import bootstrap_ci
from jsve.fitting._crossval import bootstrap_weighted_mean, compare, cross_validate, kfold, leave_one_out
from jsve.fitting._data import FitData
from jsve.fitting._fit import FitConfig
from jsve.fitting._search import search
from jsve.fitting._space import inlier_space

K = 40


# The known answer (ORB-SLAM3's rule with imu_init = K rejects exactly the bad frames, and rejecting them
# lowers the error) holds for a front-end that drops a rejected frame's visual update: under "orbslam3"
# a rejected frame keeps its logged pose and no rule can lower the error (docs/state-machine.md).
COAST = ObjectiveConfig(switch_model="imu-coast")


@pytest.fixture(scope="module")
def counts_data():
    return FitData.from_runs(ka.make_study("counts", range(16), n_frames=500, k_min=K), COAST)


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
    """With unit weights and the same seed it is jsve.evaluation._aggregate.bootstrap_ci of the mean,
    exactly."""
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
    config = FitConfig(n_search=32, n_starts=1, nm_steps=10)
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
