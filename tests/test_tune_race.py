"""The race's statistics (jsve.tuning._race): Holm's adjustment against its definition worked by hand,
the one-sided tests and intervals against scipy.stats called directly, and the racing steps on tables
whose answer is known."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from jsve.tuning._race import (
    better_than,
    check_verdict,
    eliminate,
    failure_test,
    holm,
    paired_difference,
    paired_losses,
    pairs_for_half_width,
    worse_p,
)


def _rows(losses: dict[str, np.ndarray], datasets=("a", "b")) -> pd.DataFrame:
    """Runs of each candidate on (dataset, seed) instances, the losses in instance order."""
    rows = []
    for name, values in losses.items():
        for k, loss in enumerate(values):
            instance = {"dataset": datasets[k % len(datasets)], "seed": k // len(datasets)}
            rows.append({"candidate": name, **instance,
                         "loss_m": float(loss), "failed": bool(loss >= 1.0)})  # fmt: skip
    return pd.DataFrame(rows)


def test_holm_multiplies_the_kth_smallest_p_by_m_minus_k_and_keeps_the_order():
    # sorted 0.01, 0.03, 0.04 -> 3 * 0.01 = 0.03, 2 * 0.03 = 0.06, 1 * 0.04 -> max(0.06, 0.04) = 0.06
    assert holm([0.04, 0.01, 0.03]) == pytest.approx([0.06, 0.03, 0.06])
    assert holm([0.5, 0.9]) == pytest.approx([1.0, 1.0])  # capped at 1
    assert holm([]).shape == (0,)


def test_worse_p_is_scipys_one_sided_wilcoxon_and_one_when_nothing_differs():
    rng = np.random.default_rng(0)
    d = rng.normal(0.02, 0.05, 30)
    assert worse_p(d) == stats.wilcoxon(d, alternative="greater").pvalue
    assert worse_p(np.zeros(12)) == 1.0
    assert worse_p(-np.abs(d)) > 0.99  # better, never "worse"


def test_pairs_are_the_instances_both_candidates_ran():
    rows = _rows({"x": np.arange(6) * 0.1, "y": np.ones(4)})
    pair = paired_losses(rows, "x", "y")
    assert len(pair) == 4
    assert sorted(pair["x"]) == pytest.approx([0.0, 0.1, 0.2, 0.3])  # in (dataset, seed) order


def test_a_clearly_worse_candidate_is_eliminated_and_a_tied_one_is_not():
    rng = np.random.default_rng(1)
    base = rng.uniform(0.01, 0.05, 20)
    rows = _rows({"inc": base, "tie": base.copy(), "bad": base + rng.uniform(0.02, 0.2, 20)})
    alive, table = eliminate(rows, ["inc", "tie", "bad"], alpha=0.05)
    assert alive == ["inc", "tie"]
    bad = table.set_index("candidate").loc["bad"]
    assert bad.eliminated and bad.p_holm == pytest.approx(min(1.0, 2 * bad.p))  # Holm over two tests
    assert table.set_index("candidate").loc["tie"].p == 1.0


def test_the_winner_is_the_best_of_the_challengers_that_beat_the_incumbent():
    rng = np.random.default_rng(2)
    inc = rng.uniform(0.1, 0.3, 24)
    rows = _rows(
        {"inc": inc, "good": inc - 0.05, "better": inc - 0.08, "same": inc + rng.normal(0, 1e-3, 24)}
    )
    winner, table = better_than(rows, "inc", ["good", "better", "same"], alpha=0.05)
    assert winner == "better"
    assert list(table.set_index("candidate").beats[["good", "better", "same"]]) == [True, True, False]
    assert table.set_index("candidate").loc["better"].mean_diff_m == pytest.approx(-0.08)


def test_nobody_wins_when_no_challenger_is_significantly_better():
    rng = np.random.default_rng(3)
    inc = rng.uniform(0.1, 0.3, 10)
    rows = _rows({"inc": inc, "noisy": inc + rng.normal(0, 0.05, 10)})
    winner, _ = better_than(rows, "inc", ["noisy"], alpha=0.001)
    assert winner is None


def test_paired_difference_reports_scipys_intervals_and_counts():
    rng = np.random.default_rng(4)
    b = rng.uniform(0.02, 0.1, 16)
    a = b + rng.normal(-0.01, 0.02, 16)
    a[3] = 1.0  # a failure of the rule
    rows = _rows({"rule": a, "base": b})
    out = paired_difference(rows, "rule", "base", n_resamples=999)
    pair = paired_losses(rows, "rule", "base")  # the sample in (dataset, seed) order, as resampled
    a, b = pair["rule"].to_numpy(), pair["base"].to_numpy()
    d = a - b
    ci = stats.ttest_rel(a, b).confidence_interval(0.95)
    boot = stats.bootstrap((d,), np.mean, method="BCa", n_resamples=999, random_state=0).confidence_interval
    assert out["pairs"] == 16 and out["mean_diff_m"] == pytest.approx(d.mean())
    assert (out["t_low_m"], out["t_high_m"]) == pytest.approx((ci.low, ci.high))
    assert (out["bca_low_m"], out["bca_high_m"]) == pytest.approx((boot.low, boot.high))
    assert out["wilcoxon_p"] == pytest.approx(stats.wilcoxon(d).pvalue)
    assert (out["better"], out["worse"]) == (int((d < 0).sum()), int((d > 0).sum()))
    assert (out["rule_failed"], out["baseline_failed"]) == (1, 0)


def test_the_failure_test_is_the_exact_mcnemar_test_worked_by_hand():
    # 6 discordant pairs, all failures of a alone: two-sided exact p = 2 x 0.5^6 = 0.03125; concordant
    # pairs (both failed, neither failed) do not enter it
    a = np.array([True] * 6 + [True, True] + [False] * 4)
    b = np.array([False] * 6 + [True, True] + [False] * 4)
    assert failure_test(a, b) == {"rule_only_lost": 6, "baseline_only_lost": 0, "lost_p": 0.03125}
    # 3 against 1: P(X <= 1) + P(X >= 3) for X ~ B(4, 1/2) = (1 + 4 + 4 + 1) / 16 = 0.625
    out = failure_test(np.array([1, 1, 1, 0, 0], bool), np.array([0, 0, 0, 1, 0], bool))
    assert (out["rule_only_lost"], out["baseline_only_lost"]) == (3, 1)
    assert out["lost_p"] == pytest.approx(0.625)
    assert failure_test(a, a)["lost_p"] == 1.0  # no discordant pair: no evidence either way


def test_the_tracked_difference_leaves_out_every_pair_where_either_rule_failed():
    rng = np.random.default_rng(5)
    b = rng.uniform(0.02, 0.1, 20)
    a = b + rng.normal(-0.01, 0.01, 20)
    a[[2, 7]], b[[7, 11]] = 1.0, 1.0  # a fails on 2 and 7, b on 7 and 11
    out = paired_difference(_rows({"rule": a, "base": b}), "rule", "base", n_resamples=999)
    pair = paired_losses(_rows({"rule": a, "base": b}), "rule", "base")
    kept = (pair["rule"] < 1.0) & (pair["base"] < 1.0)
    d = (pair["rule"] - pair["base"])[kept].to_numpy()
    boot = stats.bootstrap((d,), np.mean, method="BCa", n_resamples=999, random_state=0).confidence_interval
    assert out["tracked_pairs"] == 17 == len(d)
    assert out["tracked_mean_diff_m"] == pytest.approx(d.mean()) and out["tracked_mean_diff_m"] < 0
    assert (out["tracked_bca_low_m"], out["tracked_bca_high_m"]) == pytest.approx((boot.low, boot.high))
    assert (out["rule_only_lost"], out["baseline_only_lost"]) == (1, 1)
    assert out["mean_diff_m"] == pytest.approx((pair["rule"] - pair["base"]).mean())  # all pairs, failures in


def test_a_diverged_run_is_lost_like_a_failed_one_but_counts_as_tracked_in_rule_failed():
    rng = np.random.default_rng(6)
    b = rng.uniform(0.02, 0.1, 12)
    a = b + rng.normal(-0.005, 0.002, 12)
    rows = _rows({"rule": a, "base": b})
    rows["ate_m"] = rows["loss_m"]
    diverged = (rows.candidate == "base") & (rows.seed == 2) & (rows.dataset == "a")
    rows.loc[diverged, ["ate_m", "loss_m"]] = [1.67, 1.0]  # tracked, its ATE above the 1 m cap
    out = paired_difference(rows, "rule", "base", n_resamples=999)
    assert (out["rule_failed"], out["baseline_failed"]) == (0, 0)  # it did not fail ...
    assert (out["rule_only_lost"], out["baseline_only_lost"]) == (0, 1)  # ... but it lost track
    kept = ~((np.arange(12) // 2 == 2) & (np.arange(12) % 2 == 0))  # instance 4: dataset a, seed 2
    assert out["tracked_pairs"] == 11
    assert out["tracked_mean_diff_m"] == pytest.approx((a - b)[kept].mean())


@pytest.mark.parametrize(
    ("bca", "t", "word"),
    [
        ((-0.13, -0.01), (-0.08, -0.02), "better"),
        ((0.01, 0.2), (0.005, 0.1), "worse"),
        ((-0.13, -0.001), (-0.08, 0.024), "unsettled (BCa and t disagree)"),  # one outlier's bootstrap
        ((-0.01, 0.02), (-0.01, 0.02), "no clear difference"),
        ((0.001, 0.2), (np.nan, np.nan), "worse"),  # no t interval: the BCa decides alone
        ((np.nan, np.nan), (np.nan, np.nan), "undetermined"),
    ],
)
def test_the_checks_word_needs_both_intervals_on_one_side(bca, t, word):
    row = {"bca_low_m": bca[0], "bca_high_m": bca[1], "t_low_m": t[0], "t_high_m": t[1]}
    assert check_verdict(row) == word


def test_identical_arms_give_a_zero_width_interval_not_nan():
    b = np.linspace(0.01, 0.05, 8)
    out = paired_difference(_rows({"rule": b, "base": b}), "rule", "base")
    assert out["mean_diff_m"] == 0 and out["bca_low_m"] == out["bca_high_m"] == 0 and out["wilcoxon_p"] == 1


@pytest.mark.parametrize("sd", [0.005, 0.05, 0.2, 0.5])
def test_pairs_for_a_half_width_are_the_fewest_whose_t_interval_is_that_narrow(sd):
    n = pairs_for_half_width(sd, 0.03)
    half = lambda k: stats.t.ppf(0.975, k - 1) * sd / np.sqrt(k)  # noqa: E731
    assert half(n) <= 0.03 and (n == 2 or half(n - 1) > 0.03)
