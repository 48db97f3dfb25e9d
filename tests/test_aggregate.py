"""jsve.evaluation._aggregate: per-run tables and group summaries, against sums computed by hand in numpy."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from jsve.core._trajectory import ErrorStats, RunError
from jsve.evaluation._aggregate import (
    RUN_COLUMNS,
    aggregate,
    bootstrap_ci,
    failure_counts,
    per_run_table,
)


def _run_errors(rng: np.random.Generator, n_runs: int) -> RunError:
    """A batched RunError with per-run statistics that are mutually consistent (sse = rmse^2 count)."""
    count = rng.integers(3, 200, size=n_runs).astype(np.int32)
    count[2] = 0  # a run that evaluated nothing
    rmse = rng.uniform(0.1, 3.0, size=n_runs)
    mean = rmse * rng.uniform(0.7, 0.95, size=n_runs)
    zeros_if_empty = np.where(count > 0, 1.0, 0.0)
    stats = ErrorStats(
        rmse=jnp.asarray(rmse * zeros_if_empty),
        mean=jnp.asarray(mean * zeros_if_empty),
        median=jnp.asarray(mean * 0.9 * zeros_if_empty),
        std=jnp.asarray(np.sqrt(np.maximum(rmse**2 - mean**2, 0.0)) * zeros_if_empty),
        min=jnp.asarray(0.01 * zeros_if_empty),
        max=jnp.asarray(rmse * 3.0 * zeros_if_empty),
        sse=jnp.asarray(rmse**2 * count),
        count=jnp.asarray(count),
    )
    failed = rng.random(n_runs) < 0.3
    failed[2] = True
    failed[0] = False
    return RunError(
        stats=stats,
        coverage=jnp.asarray(np.where(failed, 0.4, 1.0)),
        n_segments=jnp.asarray(np.where(failed, 2, 1).astype(np.int32)),
        failed=jnp.asarray(failed),
        segment=jnp.zeros(n_runs, jnp.int32),
        failure=jnp.asarray(np.where(failed, 1, 0).astype(np.int32)),  # bit 0: several map segments
    )


@pytest.fixture
def table():
    rng = np.random.default_rng(0)
    n_runs = 24
    meta = pd.DataFrame(
        {
            "sequence": np.repeat(["MH_04", "V1_01"], n_runs // 2),
            "level": np.tile([5, 15, 25], n_runs // 3),
            "run": np.arange(n_runs),
        },
        index=np.arange(100, 100 + n_runs),  # a non-default index must not misalign the columns
    )
    return per_run_table(_run_errors(rng, n_runs), meta), meta


def test_per_run_table_columns_and_empty_runs(table):
    t, meta = table
    assert list(t.columns) == list(meta.columns) + list(RUN_COLUMNS)
    assert len(t) == len(meta) and list(t["run"]) == list(meta["run"])
    assert t.loc[2, "count"] == 0 and np.isnan(t.loc[2, "rmse"]) and np.isnan(t.loc[2, "sse"])  # not 0
    assert t["failed"].dtype == bool and t["count"].dtype == np.int64
    with pytest.raises(ValueError, match="meta has 3 rows but run_errors holds 24 runs"):
        per_run_table(_run_errors(np.random.default_rng(0), 24), meta.iloc[:3])
    with pytest.raises(ValueError, match="columns that per_run_table writes"):
        per_run_table(_run_errors(np.random.default_rng(0), 24), meta.assign(rmse=1.0))


def test_pooled_rmse_is_computed_over_all_frames(table):
    t, _ = table
    summary = aggregate(t, ["sequence"], ci=False)
    assert list(summary["sequence"]) == ["MH_04", "V1_01"]
    for _, row in summary.iterrows():
        group = t[t["sequence"] == row["sequence"]]
        sse = np.nansum(group["sse"].to_numpy())
        count = group["count"].to_numpy().sum()
        np.testing.assert_allclose(row["pooled_rmse_all"], np.sqrt(sse / count), rtol=1e-12)
        assert row["pooled_count_all"] == count
        ok = group[~group["failed"]]
        np.testing.assert_allclose(
            row["pooled_rmse_nonfailed"], np.sqrt(ok["sse"].sum() / ok["count"].sum()), rtol=1e-12
        )
        mean_by_hand = np.nansum(group["mean"] * group["count"]) / count
        np.testing.assert_allclose(row["pooled_mean_all"], mean_by_hand, rtol=1e-12)
        # Per-run RMSE summaries: over runs that evaluated frames, and over the non-failed ones.
        rmse = group["rmse"].dropna().to_numpy()
        np.testing.assert_allclose(row["rmse_mean_all"], rmse.mean(), rtol=1e-12)
        np.testing.assert_allclose(row["rmse_median_all"], np.median(rmse), rtol=1e-12)
        np.testing.assert_allclose(row["rmse_std_all"], rmse.std(ddof=1), rtol=1e-12)
        assert row["rmse_min_all"] == rmse.min() and row["rmse_max_all"] == rmse.max()
        np.testing.assert_allclose(row["rmse_mean_nonfailed"], ok["rmse"].mean(), rtol=1e-12)
        assert row["n_runs"] == len(group) and row["n_failed"] == group["failed"].sum()
        np.testing.assert_allclose(row["failure_rate"], group["failed"].mean())
        np.testing.assert_allclose(row["mean_coverage"], group["coverage"].mean())


def test_aggregate_groups_and_whole_table(table):
    t, _ = table
    by_two = aggregate(t, ["sequence", "level"], ci=False)
    assert len(by_two) == 6 and by_two["n_runs"].sum() == len(t)
    whole = aggregate(t, [], ci=False)
    assert len(whole) == 1 and whole.loc[0, "n_runs"] == len(t)
    np.testing.assert_allclose(
        whole.loc[0, "pooled_rmse_all"], np.sqrt(np.nansum(t["sse"]) / t["count"].sum()), rtol=1e-12
    )
    with pytest.raises(ValueError, match="lacks columns"):
        aggregate(t.drop(columns="sse"), ["sequence"])


def test_bootstrap_ci_deterministic_and_sensible():
    values = np.random.default_rng(1).normal(loc=2.0, scale=0.5, size=60)
    a = bootstrap_ci(values, seed=3)
    assert a == bootstrap_ci(values, seed=3)
    assert a != bootstrap_ci(values, seed=4)
    low, high = a
    assert low < values.mean() < high
    # The percentile interval of the mean is about +-1.96 standard errors wide.
    se = values.std(ddof=1) / np.sqrt(len(values))
    assert 0.8 * 3.92 * se < high - low < 1.2 * 3.92 * se
    # A statistic without an axis argument gives the same interval resample by resample.
    assert bootstrap_ci(values, stat=lambda x: float(np.mean(x)), seed=3) == pytest.approx(a, rel=1e-12)
    assert all(np.isnan(bootstrap_ci([1.0])))
    with pytest.raises(ValueError, match="level"):
        bootstrap_ci(values, level=1.5)


def test_aggregate_ci_columns_match_bootstrap(table):
    t, _ = table
    summary = aggregate(t, ["sequence"], n_boot=200, seed=7)
    again = aggregate(t, ["sequence"], n_boot=200, seed=7)
    pd.testing.assert_frame_equal(summary, again)
    for _, row in summary.iterrows():
        rmse = t.loc[t["sequence"] == row["sequence"], "rmse"].to_numpy()
        low, high = bootstrap_ci(rmse, n_boot=200, seed=7)
        assert (row["rmse_mean_all_ci_low"], row["rmse_mean_all_ci_high"]) == (low, high)
        assert low <= row["rmse_mean_all"] <= high


def test_failure_counts_count_the_failed_runs_of_each_reason_per_group():
    reasons = ["", "a", "b; c", "a", "", "a", "b; c", "a"]
    table = pd.DataFrame(
        {
            "rule": ["r2", "r2", "r2", "r2", "r1", "r1", "r1", "r1"],
            "failed": [False, True, True, True, False, True, True, False],  # the last "a" did not fail
            "failure_reason": reasons,
        }
    )
    counts = failure_counts(table)
    assert counts.to_dict("records") == [
        {"rule": "r1", "failure_reason": "a", "n_runs": 1},
        {"rule": "r1", "failure_reason": "b; c", "n_runs": 1},  # a tie: by reason
        {"rule": "r2", "failure_reason": "a", "n_runs": 2},  # the most frequent reason first
        {"rule": "r2", "failure_reason": "b; c", "n_runs": 1},
    ]
    # Per group, the counts add up to aggregate's n_failed.
    n_failed = aggregate(table.assign(rmse=1.0, mean=1.0, sse=1.0, count=1, coverage=1.0), ["rule"], ci=False)
    assert counts.groupby("rule")["n_runs"].sum().to_dict() == dict(
        zip(n_failed["rule"], n_failed["n_failed"], strict=True)
    )
    assert failure_counts(table, []).to_dict("records") == [
        {"failure_reason": "a", "n_runs": 3},
        {"failure_reason": "b; c", "n_runs": 2},
    ]
    assert failure_counts(table[~table["failed"]]).empty
    with pytest.raises(ValueError, match=r"lacks columns \['failure_reason'\]"):
        failure_counts(table.drop(columns="failure_reason"))


# --------------------------------------------------------------------------------------------------
# The objective column: what the fit minimises, per group


def _with_one_map(run):
    """knownanswer's run with one recorded map whose IMU and inertial BA2 are done from frame 0 (as in
    tests/test_objective.py: a failed frame goes to RECENTLY_LOST, never to a reset)."""
    frames = run.frames.copy()
    frames["map_id"] = frames["map_id"].fillna(0)
    frames["imu_ba2"] = frames["imu_ba2"].fillna(frames["imu_init"])
    return type(run)(meta=run.meta, frames=frames, source=run.source)


@pytest.fixture(scope="module")
def lossy_runs():
    """8 runs: 2 whose recorded map is lost on the last 20 frames (a rule that keeps tracking leaves the
    log's support), 2 lost on the last 60 without matches, 4 as recorded. (Runs, not a batch: a
    module-scoped batch would be made before the test's x64 fixture turns float64 on.)"""
    import knownanswer as ka

    runs = ka.make_study("counts", range(8), n_frames=400)
    runs = (
        [ka.lose_map(r, 380, blind=False) for r in runs[:2]]
        + [ka.lose_map(r, 340) for r in runs[2:4]]
        + list(runs[4:])
    )
    return [_with_one_map(r) for r in runs]


OBJECTIVE_RULES = {
    "at K": dict(imu_init=39.5, not_init=49.5, reloc=49.5, recovery=38.5),  # keeps tracking: unsupported runs
    "reject all": dict(imu_init=1e6, not_init=0.0, reloc=0.0, recovery=1e6),  # every run fails
}


@pytest.mark.parametrize("support", ["penalise", "exclude"])
@pytest.mark.parametrize("name", OBJECTIVE_RULES)
def test_objective_is_what_the_fit_minimises(x64, lossy_runs, name, support):
    """aggregate's `objective` over a group equals jsve.core._objective.objective with equal weights (to
    1e-12 m in float64: the same RMSEs, another order of summation), on runs that fail, leave the log's
    support or succeed; never a mean RMSE over the part a failed run tracked."""
    from jsve.core._objective import ObjectiveConfig, objective
    from jsve.core._replay import batch_features
    from jsve.core._rules import InlierRule, Thresholds
    from jsve.evaluation._evaluate import evaluate
    from jsve.io._batching import from_runs

    rule = InlierRule(Thresholds(**OBJECTIVE_RULES[name]))
    bucket = from_runs(lossy_runs, dtype=jnp.float64)
    batch = bucket.batch
    per_run = evaluate([bucket], rule, rule_name=name, progress=False)
    config = ObjectiveConfig(failure_penalty=2.5, support=support)
    expected = objective(batch, rule, jnp.ones(batch.n_runs), batch_features(batch), config)
    row = aggregate(per_run, [], failure_penalty=2.5, support=support, ci=False).iloc[0]
    np.testing.assert_allclose(row["objective"], float(expected.value), rtol=0, atol=1e-12)
    unsupported = per_run["unsupported_fraction"].to_numpy() > 0
    charged = per_run["failed"].to_numpy() | unsupported
    assert row["share_penalised"] == charged.mean()
    if name == "at K":
        assert unsupported[:2].all() and not per_run["failed"].any()  # the replay's own facts: no failure
        assert row["objective"] > row["rmse_mean_all"]  # the unsupported runs cost the penalty
    else:
        assert row["failure_rate"] == 1.0 and row["objective"] == 2.5


def test_objective_ci_brackets_the_objective():
    table = pd.DataFrame(
        {
            "rule": ["a"] * 6,
            "rmse": [0.1, 0.2, 0.15, 0.05, np.nan, 0.3],
            "mean": [0.1] * 6,
            "sse": [1.0] * 6,
            "count": [10, 10, 10, 10, 0, 10],
            "coverage": [1.0] * 6,
            "failed": [False, False, False, False, True, True],
        }
    )
    row = aggregate(table, ["rule"], failure_penalty=1.0).iloc[0]
    np.testing.assert_allclose(row["objective"], (0.1 + 0.2 + 0.15 + 0.05 + 1.0 + 1.0) / 6, rtol=1e-12)
    assert row["share_penalised"] == pytest.approx(2 / 6)
    assert row["objective_ci_low"] <= row["objective"] <= row["objective_ci_high"]
    assert row["rmse_mean_all"] < row["objective"]  # the failed run's tracked part (0.3 m) hides its failure
