"""Replay against re-run statistics (jsve.evaluation._agreement) on tables with known answers; Kendall's
tau against scipy's."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import kendalltau

from jsve.evaluation import (
    MIN_RULES_FOR_VERDICT,
    REGRET_TOLERANCE_M,
    REPLAY_TRUSTED_CHANGED_SHARE,
    agreement_by_changed_share,
    agreement_table,
    bootstrap_ranking,
    deploy_differences,
    expected_in_band,
    kendall_tau,
    pool_draws,
    ranking_table,
    ranking_verdict,
    rerun_summary,
    run_loss,
    trust_region_warning,
    trusted_changed_share,
    trusted_share,
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


# --- expected band share, bootstrap intervals, verdict, trust region, deploy loop ---------------------

LEVEL = ["sequence", "disturbance", "level", "switch_model"]


@pytest.mark.parametrize("n", [2, 5, 10])
def test_expected_in_band_is_what_a_draw_from_the_reruns_reaches(n):
    # a replay exchangeable with the re-runs lands in their 5-95 % band 0.9 (n-1)/(n+1) of the time
    rng = np.random.default_rng(n)
    reruns, replay = rng.random((100_000, n)), rng.random(100_000)
    q05, q95 = np.quantile(reruns, [0.05, 0.95], axis=1)
    share = np.mean((replay >= q05) & (replay <= q95))
    # 100,000 draws: the share's standard error is below 0.0016, 0.006 is four of them
    assert expected_in_band(n) == pytest.approx(share, abs=0.006)
    assert np.isnan(expected_in_band(0))


def test_kendall_tau_batches_rows_as_single_calls():
    rng = np.random.default_rng(3)
    x, y = rng.random((7, 5)), rng.random((7, 5))
    np.testing.assert_allclose(kendall_tau(x, y), [kendall_tau(a, b) for a, b in zip(x, y, strict=True)])


def _study(replay_means, rerun_means, *, sd, rerun_sd=None, n_reruns=5, n_recordings=5, rng, level=0,
           offset_sd=0.0):  # fmt: skip
    """One level: every recording replayed under every rule (a shared per-recording offset plus noise of
    sd `sd`), n_reruns re-runs per rule (noise of sd `rerun_sd`, default `sd`); losses are plain numbers
    (no failure)."""
    rerun_sd = sd if rerun_sd is None else rerun_sd
    rules = [chr(ord("a") + k) for k in range(len(replay_means))]
    offsets = rng.normal(0.0, offset_sd, n_recordings)
    replayed = pd.concat([
        _table(r, m + offsets + rng.normal(0, sd, n_recordings), level=level).assign(
            source=[f"rec{k}" for k in range(n_recordings)])
        for r, m in zip(rules, replay_means, strict=True)
    ])  # fmt: skip
    reruns = pd.concat([
        _table(r, m + rng.normal(0, rerun_sd, n_reruns), level=level)
        for r, m in zip(rules, rerun_means, strict=True)
    ])  # fmt: skip
    return replayed, reruns


def test_bootstrap_interval_of_tau_covers_the_population_tau():
    # replay and re-run means rank four rules with one pair swapped: the population tau is 2/3; the
    # re-runs' noise flips the sample ranking now and then, and the 95 % interval must still hold 2/3 in
    # most studies (an interval that did not resample the re-runs would miss it whenever they flip)
    replay_means, rerun_means = [0.10, 0.20, 0.30, 0.40], [0.20, 0.10, 0.30, 0.40]
    rng = np.random.default_rng(11)
    covered, widths = [], []
    for _ in range(60):
        replayed, reruns = _study(replay_means, rerun_means, sd=0.01, rerun_sd=0.08, rng=rng)
        draws = bootstrap_ranking(replayed, reruns, LEVEL, n_boot=400, seed=1)
        row = draws.with_ci().iloc[0]
        covered.append(row["tau_low"] <= 2 / 3 <= row["tau_high"])
        widths.append(row["tau_high"] - row["tau_low"])
    # percentile intervals of a discrete statistic from 5 re-runs: in 60 studies at least 90 % covered
    # (59 of 60 with this seed; 51 with intervals that hold the re-runs fixed, zero-width in most studies)
    assert np.mean(covered) >= 0.9 and np.median(widths) > 0


def test_recordings_are_drawn_once_for_every_rule():
    # a recording's offset is shared by the rules it is replayed under, so it never reorders them: with
    # exact re-runs, every draw ranks as the sample does (independent draws per rule would scramble it)
    rng = np.random.default_rng(5)
    replayed, reruns = _study([0.1, 0.2, 0.3], [0.1, 0.2, 0.3], sd=0.0, offset_sd=1.0, rng=rng)
    row = bootstrap_ranking(replayed, reruns, LEVEL, n_boot=300, seed=0).with_ci().iloc[0]
    assert row["tau"] == 1.0 and row["tau_low"] == 1.0 and row["tau_high"] == 1.0


def test_fitted_regret_and_pooling_over_levels():
    rng = np.random.default_rng(2)
    parts = [_study([0.1, 0.2, 0.3], [0.1, 0.2, 0.3 + 0.1 * lv], sd=0.0, rng=rng, level=lv) for lv in (0, 1)]
    replayed = pd.concat([p[0] for p in parts]).replace({"rule": {"c": "fit"}})
    reruns = pd.concat([p[1] for p in parts]).replace({"rule": {"c": "fit"}})
    draws = bootstrap_ranking(replayed, reruns, LEVEL, fitted="fit", n_boot=50, seed=0)
    np.testing.assert_allclose(draws.table["fitted_regret"], [0.2, 0.3])  # fit's loss minus a's
    pooled = pool_draws(draws, ["switch_model"]).iloc[0]
    assert pooled["fitted_regret"] == pytest.approx(0.25) and pooled["units_fitted_regret"] == 2
    assert pooled["fitted_regret_low"] == pytest.approx(0.25)  # exact losses: every draw is the sample


def test_a_rule_without_reruns_takes_no_part_and_no_fitted_reruns_leave_regret_undefined():
    rng = np.random.default_rng(4)
    replayed, reruns = _study([0.1, 0.2, 0.3], [0.1, 0.2, 0.3], sd=0.01, rng=rng)
    reruns = reruns[reruns["rule"] != "c"]
    row = bootstrap_ranking(replayed, reruns, LEVEL, fitted="c", n_boot=50).with_ci().iloc[0]
    assert row["rules"] == 2 and np.isnan(row["fitted_regret"]) and np.isnan(row["fitted_regret_high"])


def _pooled(tau=0.8, tau_low=0.5, tau_high=1.0, regret=0.01, regret_low=0.0, regret_high=0.03, rules=4):
    return pd.Series({"tau": tau, "tau_low": tau_low, "tau_high": tau_high, "fitted_regret": regret,
                      "fitted_regret_low": regret_low, "fitted_regret_high": regret_high,
                      "max_rules": rules})  # fmt: skip


def test_verdict_criteria():
    assert ranking_verdict(_pooled())[0] == "trusted"
    assert "tau 0.80 [0.50, 1.00]" in ranking_verdict(_pooled())[1]
    # the tau interval must lie above 0: touching it is not enough
    status, reason = ranking_verdict(_pooled(tau=0.3, tau_low=0.0))
    assert status == "not trusted" and "reaches 0" in reason
    # the regret's upper end may reach the tolerance, not pass it
    assert ranking_verdict(_pooled(regret_high=REGRET_TOLERANCE_M))[0] == "trusted"
    status, reason = ranking_verdict(_pooled(regret_high=REGRET_TOLERANCE_M + 1e-6))
    assert status == "not trusted" and "beyond" in reason
    assert ranking_verdict(_pooled(rules=MIN_RULES_FOR_VERDICT - 1))[0] == "incomplete"
    assert ranking_verdict(_pooled(regret=np.nan, regret_low=np.nan, regret_high=np.nan))[0] == "incomplete"


def _rows(changed, inside, d, n_reruns=5):
    return pd.DataFrame({"changed_fraction": changed, "inside": inside, "d": d,
                         "expected_in_band": expected_in_band(n_reruns)})  # fmt: skip


def test_trust_threshold_from_constructed_agreement():
    n = 20
    rows = pd.concat([
        _rows([0.0] * n, [True] * 12 + [False] * 8, [0.01] * n),  # in band 0.6 = another re-run's
        _rows([0.004] * n, [True] * 8 + [False] * 12, [-0.02] * n),  # 0.4 / 0.6 = 0.67 >= 0.5, -2 cm
        _rows([0.008] * 3, [False] * 3, [0.5] * 3),  # too few to say anything: skipped
        _rows([0.02] * n, [True] * 7 + [False] * 13, [0.04] * n),  # (0.01, 0.02]: agrees
        _rows([0.04] * n, [True] * 3 + [False] * 17, [0.01] * n),  # 0.15 / 0.6 = 0.25: disagrees
        _rows([0.3] * n, [True] * n, [0.0] * n),  # agrees, but beyond a disagreeing bin
    ])  # fmt: skip
    bins = agreement_by_changed_share(rows)
    assert list(bins["replays"]) == [n, n, 3, n, n, 0, 0, n, 0]
    assert trusted_changed_share(bins) == pytest.approx(0.02)
    # a bias beyond the tolerance disagrees too
    biased = rows.assign(d=np.where(rows["changed_fraction"] == 0.004, 0.06, rows["d"]))
    assert trusted_changed_share(agreement_by_changed_share(biased)) == pytest.approx(0.001)
    # a noisy bias counts only where it is significantly beyond the tolerance: 7 cm +- 2.2 (sd 10 cm,
    # 20 replays) reaches into 5 cm; 15 cm +- 2.2 does not
    second = (rows["changed_fraction"] == 0.004).to_numpy()
    for mean, trusted in ((0.07, 0.02), (0.15, 0.001)):
        d = rows["d"].to_numpy().copy()
        d[second] = mean + np.tile([-0.1, 0.1], n // 2)
        assert trusted_changed_share(agreement_by_changed_share(rows.assign(d=d))) == pytest.approx(trusted)
    # the first bin with evidence disagreeing: nothing is trusted; no evidence: undefined
    assert trusted_changed_share(agreement_by_changed_share(rows[rows["changed_fraction"] >= 0.04])) == 0.0
    assert np.isnan(trusted_changed_share(agreement_by_changed_share(rows.iloc[:5])))


def test_trust_region_warning_fires_above_the_threshold_only():
    assert trust_region_warning("fitted-sve", 0.03, threshold=0.02).startswith("`fitted-sve` changes 3.0 %")
    assert trust_region_warning("fitted-sve", 0.02, threshold=0.02) is None
    assert trust_region_warning("fitted-sve", 0.01, threshold=0.02) is None
    limit = REPLAY_TRUSTED_CHANGED_SHARE["orbslam3"]
    assert trust_region_warning("x", limit * 1.01) is not None  # the default model: stock ORB-SLAM3


def test_each_switch_model_has_its_own_measured_trust_region():
    """docs/data/validation_trust.csv: replays under `orbslam3` agreed up to 0.1 % of changed decisions,
    under `imu-coast` on its own recordings up to 1 %; a model the study did not cover has none."""
    assert REPLAY_TRUSTED_CHANGED_SHARE == {"orbslam3": 0.001, "imu-coast": 0.01}
    assert trusted_share("imu-coast") == 0.01
    assert trust_region_warning("fitted-sve", 0.005, switch_model="imu-coast") is None
    assert trust_region_warning("fitted-sve", 0.005, switch_model="orbslam3") is not None
    line = trust_region_warning("fitted-sve", 0.02, switch_model="imu-coast")
    assert line is not None
    assert "more than the 1.0 % up to which replays under switch model `imu-coast`" in line
    with pytest.raises(ValueError, match="no validated trust region for switch model 'other'"):
        trust_region_warning("fitted-sve", 0.5, switch_model="other")


def test_deploy_difference_equals_a_hand_computation():
    reruns = pd.concat([
        _table("fit", [0.10, 0.12, 0.14], level=0), _table("orbslam3", [0.20, 0.30], level=0),
        _table("fit", [0.05, 1.00], failed=[False, True], level=1),
        _table("orbslam3", [0.07, 0.09, 0.11], level=1),
        _table("orbslam3", [0.5], level=2),  # no fitted re-runs here: no difference
    ])  # fmt: skip
    draws = deploy_differences(reruns, "fit", ["orbslam3", "sve-option2"], LEVEL, n_boot=2000, seed=0)
    table = draws.with_ci()
    # the failed run costs the 1 m penalty, never its rmse
    expected = [np.mean([0.10, 0.12, 0.14]) - 0.25, np.mean([0.05, 1.0]) - 0.09]
    np.testing.assert_allclose(table["diff"], expected)
    assert list(table["level"]) == [0, 1] and list(table["baseline"]) == ["orbslam3"] * 2
    assert (table["diff_low"] <= table["diff"]).all() and (table["diff"] <= table["diff_high"]).all()
    # level 0's draws: (mean of 3 fitted re-runs) - (mean of 2 presets'), both resampled: the widest
    # possible draw is 0.14 - 0.20 to 0.10 - 0.30
    assert -0.20 <= table["diff_low"].iloc[0] and table["diff_high"].iloc[0] <= -0.06
    pooled = pool_draws(draws, ["switch_model", "baseline"]).iloc[0]
    assert pooled["diff"] == pytest.approx(np.mean(expected)) and pooled["units_diff"] == 2
    assert pooled["diff_low"] < pooled["diff"] < pooled["diff_high"]


def test_rules_the_replay_ties_for_first_share_the_pick():
    # under switch model orbslam3 two rules often replay to the same loss: neither is the replay's pick
    # alone, so regret@1 is their mean re-run loss minus the best (not whichever sorts first)
    reruns = pd.concat([_table("a", [0.30]), _table("b", [0.10]), _table("c", [0.50])])
    replayed = pd.concat([_table("a", [0.2]), _table("b", [0.2]), _table("c", [0.4])])
    rank = ranking_table(agreement_table(replayed, reruns, KEYS), LEVEL).iloc[0]
    assert rank["replay_best"] == "a=b" and rank["regret_at_1"] == pytest.approx(0.2 - 0.1)
    draws = bootstrap_ranking(replayed.assign(source="rec0"), reruns, LEVEL, n_boot=20)
    assert draws.table["replay_best"].iloc[0] == "a=b"
    assert draws.table["regret_at_1"].iloc[0] == pytest.approx(0.1)


def test_replays_sharing_their_reruns_count_as_one_cluster_in_the_bias_error():
    # two settings, ten replays each: one setting's 15 cm above the 15 cm mean, the other's 15 cm below;
    # a setting's replays share one re-run mean, so the bias's error is that of 2 draws, not of 20
    rows = _rows([0.0] * 20, [True] * 20, [0.3] * 10 + [0.0] * 10).assign(setting=[0] * 10 + [1] * 10)
    plain = agreement_by_changed_share(rows).iloc[0]
    clustered = agreement_by_changed_share(rows, cluster=["setting"]).iloc[0]
    assert plain["bias_se"] == pytest.approx(np.std(rows["d"], ddof=1) / np.sqrt(20))
    # sqrt(G / (G - 1) * sum of squared cluster sums of deviations) / n = sqrt(2 * 2 * 1.5**2) / 20
    assert clustered["bias_se"] == pytest.approx(0.15)
    assert plain["evidence"] == "disagrees" and clustered["evidence"] == "agrees"
