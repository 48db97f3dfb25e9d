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
