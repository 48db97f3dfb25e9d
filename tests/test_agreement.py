"""Replay against re-run statistics (jsve.evaluation._agreement) on tables with known answers; Kendall's
tau against scipy's."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import kendalltau

from jsve.evaluation._agreement import (
    agreement_table,
    kendall_tau,
    ranking_table,
    rerun_summary,
    run_loss,
    unmatched,
)

KEYS = ["sequence", "disturbance", "level", "rule", "switch_model"]


def _table(rule, rmse, failed=None, coverage=1.0, level=0, sequence="V101"):
    n = len(rmse)
    return pd.DataFrame({
        "sequence": sequence, "disturbance": "blur", "level": level, "rule": rule, "switch_model": "orbslam3",
        "rmse": rmse, "failed": failed if failed is not None else [False] * n, "coverage": coverage,
    })  # fmt: skip


def test_a_failed_run_costs_the_penalty_never_its_partial_error():
    t = _table("a", [0.05, 0.02, np.nan], failed=[False, True, False])
    np.testing.assert_array_equal(run_loss(t, 1.0), [0.05, 1.0, 1.0])


def test_a_replay_out_of_support_costs_the_penalty_as_in_the_fit():
    # the fit's objective charges a replay that needed a pose the log lacks (penalise policy): so must the
    # validation, which shares the one run loss
    t = _table("a", [0.05, 0.02], failed=[False, False]).assign(unsupported_fraction=[0.0, 0.3])
    np.testing.assert_array_equal(run_loss(t, 2.0), [0.05, 2.0])
    s = rerun_summary(t, KEYS, penalty=2.0).iloc[0]
    assert s["rerun_loss"] == pytest.approx(1.025)


def test_bias_limits_and_band_on_known_numbers():
    reruns = _table("a", [0.1, 0.2, 0.3, 0.4, 0.5])
    replayed = _table("a", [0.2, 0.4, 1.0], failed=[False, False, True])
    s = rerun_summary(reruns, KEYS).iloc[0]
    assert s["rerun_loss"] == pytest.approx(0.3) and s["rerun_q05"] == pytest.approx(0.12)
    assert s["rerun_q95"] == pytest.approx(0.48)
    row = agreement_table(replayed, reruns, KEYS).iloc[0]
    d = np.array([0.2, 0.4, 1.0]) - 0.3
    assert row["bias"] == pytest.approx(d.mean()) and row["sd"] == pytest.approx(d.std(ddof=1))
    assert row["loa_low"] == pytest.approx(d.mean() - 1.96 * d.std(ddof=1))
    assert row["in_band"] == pytest.approx(2 / 3)  # 0.2 and 0.4 inside [0.12, 0.48]; the failure is not
    assert row["replay_failed"] == pytest.approx(1 / 3) and row["rerun_failed"] == 0.0


def test_settings_without_the_other_side_are_listed():
    reruns = _table("a", [0.1, 0.2])
    replayed = pd.concat([_table("a", [0.1]), _table("b", [0.3])])
    assert list(agreement_table(replayed, reruns, KEYS)["rule"]) == ["a"]
    gone = unmatched(replayed, reruns, KEYS)
    assert list(gone["rule"]) == ["b"] and list(gone["side"]) == ["no re-runs"]


@pytest.mark.parametrize("seed", range(5))
def test_kendall_tau_b_equals_scipy_with_ties(seed):
    rng = np.random.default_rng(seed)
    x, y = rng.integers(0, 4, 9).astype(float), rng.integers(0, 4, 9).astype(float)
    assert kendall_tau(x, y) == pytest.approx(kendalltau(x, y).statistic, abs=1e-12)
    assert np.isnan(kendall_tau([1, 1, 1], [1, 2, 3]))


def test_ranking_and_regret_at_1():
    reruns = pd.concat([_table("a", [0.30, 0.30]), _table("b", [0.10, 0.12]), _table("c", [0.20, 0.22])])
    # the replay ranks c first, then b, then a: b and c swapped
    replayed = pd.concat([_table("a", [0.5]), _table("b", [0.2]), _table("c", [0.1])])
    table = agreement_table(replayed, reruns, KEYS)
    rank = ranking_table(table, ["sequence", "disturbance", "level", "switch_model"]).iloc[0]
    assert rank["rules"] == 3 and rank["replay_best"] == "c" and rank["rerun_best"] == "b"
    assert rank["regret_at_1"] == pytest.approx(0.21 - 0.11)
    assert rank["tau"] == pytest.approx(1 / 3)  # 2 concordant pairs, 1 discordant
