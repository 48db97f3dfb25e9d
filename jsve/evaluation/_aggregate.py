"""Host-side aggregation of per-run trajectory errors (pandas): per-run tables, group summaries, CIs.

The JAX side (`jsve.core._trajectory.batched_run_error`) returns one `RunError` per run; these functions
turn it into a table with one row per run and summarise groups of runs (per sequence / disturbance / level /
rule): first the objective the fit minimises (`run_loss`: a failed run costs the failure penalty, never
the RMSE of the part it tracked) with the failure rate and coverage, then the literature's mean, median,
std, min and max of per-run RMSE, and statistics pooled over all frames of the group. Errors are in metres.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, check_loss, check_support
from jsve.core._trajectory import RunError, failure_reason

STAT_COLUMNS: tuple[str, ...] = ("rmse", "mean", "median", "std", "min", "max", "sse", "count")
"""APE statistics per run, as evo names them (metres; sse in square metres; count in frames)."""

RUN_COLUMNS: tuple[str, ...] = STAT_COLUMNS + ("coverage", "n_segments", "failed", "failure_reason")
"""The columns `per_run_table` adds to the run metadata."""


def per_run_table(run_errors: RunError, meta: pd.DataFrame) -> pd.DataFrame:
    """One row per run: the metadata columns followed by the error statistics and the failure facts.

    Arguments:
        run_errors: a batched RunError (every leaf of shape [R], as `batched_run_error` returns it).
        meta: R rows of run metadata (sequence, disturbance, level, rule, run, ...), in the same order.

    Returns:
        A DataFrame with meta's columns (index reset) and rmse, mean, median, std, min, max (metres),
        sse (m^2), count (frames), coverage (fraction), n_segments, failed, failure_reason (why, in
        words: jsve.core._trajectory.FAILURE_CAUSES joined by '; '; '' when not failed). The statistics
        of a run with no evaluated frame (count 0) are NaN here, not the finite zeros of the JAX side;
        those of a run failed for non-finite statistics are as computed (NaN or inf), never a number.
    """
    stats = run_errors.stats
    columns = {name: np.atleast_1d(np.asarray(getattr(stats, name))) for name in STAT_COLUMNS}
    columns["coverage"] = np.atleast_1d(np.asarray(run_errors.coverage))
    columns["n_segments"] = np.atleast_1d(np.asarray(run_errors.n_segments))
    columns["failed"] = np.atleast_1d(np.asarray(run_errors.failed)).astype(bool)
    columns["failure_reason"] = np.array(
        [failure_reason(bits) for bits in np.atleast_1d(np.asarray(run_errors.failure))], dtype=object
    )
    n_runs = len(columns["rmse"])
    if len(meta) != n_runs:
        raise ValueError(f"meta has {len(meta)} rows but run_errors holds {n_runs} runs")
    clash = sorted(set(meta.columns) & set(RUN_COLUMNS))
    if clash:
        raise ValueError(f"meta has columns that per_run_table writes: {clash}")

    table = meta.reset_index(drop=True).copy()
    empty = columns["count"] == 0
    for name in STAT_COLUMNS:
        values = columns[name]
        if name == "count":
            table[name] = values.astype(np.int64)
        else:
            table[name] = np.where(empty, np.nan, values.astype(np.float64))
    for name in ("coverage", "n_segments", "failed", "failure_reason"):
        table[name] = columns[name]
    return table


def run_loss(
    table: pd.DataFrame, failure_penalty: float = DEFAULT_FAILURE_PENALTY_M, loss: str = "bounded"
) -> pd.Series:
    """Each run's loss in the objective the fit minimises (jsve.core._objective, the hard replay): its
    ATE RMSE (metres) when it succeeded, capped at `failure_penalty` under loss="bounded", and
    `failure_penalty` (metres) when it failed, has no finite RMSE, or left the log's support
    (`unsupported_fraction` > 0, where the table has that column).

    Arguments:
        table: a per-run table (per_run_table, jsve.evaluation.evaluate).
        failure_penalty: metres charged for a failed run (ObjectiveConfig's default).
        loss: "bounded" (default) or "raw" (jsve.core._objective.LOSSES).
    """
    check_loss(loss)
    rmse = table["rmse"].astype(float)
    if loss == "bounded":
        rmse = rmse.clip(upper=float(failure_penalty))
    return rmse.where(~_charged(table), float(failure_penalty))


def _charged(table: pd.DataFrame) -> pd.Series:
    """The runs that cost the failure penalty: failed, without a finite RMSE, or out of support."""
    charged = table["failed"].astype(bool) | ~np.isfinite(table["rmse"].astype(float))
    if "unsupported_fraction" in table:
        charged |= table["unsupported_fraction"].astype(float) > 0
    return charged


def bootstrap_ci(
    values: Sequence[float] | np.ndarray,
    stat: Callable[..., float] = np.mean,
    n_boot: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of `stat(values)`.

    Arguments:
        values: the sample (NaN entries are dropped first).
        stat: the statistic; called as stat(resamples, axis=-1) when it takes an axis, else once per resample.
        n_boot: number of resamples (with replacement, each of the sample's size).
        level: confidence level in (0, 1).
        seed: seed of numpy's default generator; the same seed gives the same interval.

    Returns:
        (low, high): the (1 - level) / 2 and (1 + level) / 2 percentiles of the resampled statistic;
        (NaN, NaN) for fewer than 2 values, where a bootstrap says nothing.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    if n_boot < 1:
        raise ValueError(f"n_boot must be positive, got {n_boot}")
    x = np.asarray(values, dtype=np.float64)
    x = x[~np.isnan(x)]
    if x.size < 2:
        return (float("nan"), float("nan"))
    rng = np.random.default_rng(seed)
    resamples = x[rng.integers(0, x.size, size=(n_boot, x.size))]
    try:
        boot = np.asarray(stat(resamples, axis=-1), dtype=np.float64)
    except TypeError:
        boot = np.array([stat(r) for r in resamples], dtype=np.float64)
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(boot, [alpha, 1.0 - alpha])
    return (float(low), float(high))


def _nan_stats(x: np.ndarray, suffix: str) -> dict[str, float]:
    """Mean, median, std (ddof 1), min and max of the non-NaN values, NaN where there are too few."""
    r = x[~np.isnan(x)]
    n = r.size
    return {
        f"rmse_mean_{suffix}": float(r.mean()) if n else np.nan,
        f"rmse_median_{suffix}": float(np.median(r)) if n else np.nan,
        f"rmse_std_{suffix}": float(r.std(ddof=1)) if n > 1 else np.nan,
        f"rmse_min_{suffix}": float(r.min()) if n else np.nan,
        f"rmse_max_{suffix}": float(r.max()) if n else np.nan,
    }


def _pooled(count: np.ndarray, sse: np.ndarray, mean: np.ndarray, suffix: str) -> dict[str, float]:
    """Statistics of all frames of the runs together (NaN sums skipped, as runs without frames have)."""
    total = int(count.sum())
    finite_sse, weighted = ~np.isnan(sse), mean * count
    sse_sum = float(sse[finite_sse].sum()) if finite_sse.any() else np.nan
    weighted_ok = ~np.isnan(weighted)
    weighted_sum = float(weighted[weighted_ok].sum()) if weighted_ok.any() else np.nan
    return {
        f"pooled_rmse_{suffix}": float(np.sqrt(sse_sum / total)) if total > 0 else np.nan,
        f"pooled_mean_{suffix}": float(weighted_sum / total) if total > 0 else np.nan,
        f"pooled_count_{suffix}": total,
    }


def _group_rows(table: pd.DataFrame, by: list[str]) -> tuple[list[tuple], list[np.ndarray]]:
    """The groups of `by` in sorted order (NaN keys kept): their keys and their rows' positions."""
    if not by:
        return [()], [np.arange(len(table))]
    grouped = table.groupby(by, sort=True, dropna=False)
    codes = grouped.ngroup().to_numpy()
    keys = [k if isinstance(k, tuple) else (k,) for k in grouped.size().index]
    order = np.argsort(codes, kind="stable")
    return keys, np.split(order, np.cumsum(np.bincount(codes, minlength=len(keys)))[:-1])


def aggregate(
    table: pd.DataFrame,
    by: Sequence[str],
    *,
    ci: bool = True,
    n_boot: int = 1000,
    level: float = 0.95,
    seed: int = 0,
    failure_penalty: float = DEFAULT_FAILURE_PENALTY_M,
    support: str = "penalise",
    loss: str = "bounded",
) -> pd.DataFrame:
    """Summarise per-run errors per group: the objective, with failure and coverage next to every error.

    Arguments:
        table: the output of `per_run_table` (or any table with its columns).
        by: the metadata columns that define a group (e.g. ["sequence", "disturbance", "level", "rule"]);
            an empty list summarises the whole table as one group.
        ci: add percentile bootstrap confidence intervals of the mean per-run RMSE.
        n_boot, level, seed: passed to `bootstrap_ci` (the same seed for every group, so results are
            reproducible).
        failure_penalty: metres charged for a failed (or unsupported) run in `objective`.
        support: "penalise" or "exclude", the objective's policy for runs that left the log's support
            (jsve.core._objective.SUPPORT_POLICIES).
        loss: "bounded" (default: a tracked run costs at most the penalty) or "raw" (`run_loss`).

    Returns:
        One row per group (the `by` columns first), with
        n_runs, n_failed, failure_rate, mean_coverage;
        objective: the mean `run_loss` of the group's runs, metres, as jsve.core._objective.objective
            computes it with equal weights (under "exclude" the mean over the supported runs, the
            penalty when there is none); share_penalised: the share of runs charged the penalty
            (failed, non-finite or unsupported);
        mean_resets, mean_new_maps: the replay's map resets and new maps per run, where the table has
            them (events: a run fails by its coverage, not by them);
        mean_changed, mean_unsupported, share_unsupported_runs: when the table has the support columns
            of jsve.evaluation._evaluate (the mean share of frames whose replayed mode differs from the
            recorded state, the mean share out of the log's support, the share of runs with any);
        rmse_{mean,median,std,min,max}_all: over the per-run RMSE of all runs that evaluated any frame
            (std across runs with ddof = 1);
        rmse_{mean,median,std,min,max}_nonfailed: the same over the runs whose failed flag is False;
        pooled_{rmse,mean,count}_{all,nonfailed}: over all frames of the runs, pooled_rmse =
            sqrt(sum sse / sum count), pooled_mean = sum(mean * count) / sum count, pooled_count = sum count;
        with ci: objective_ci_{low,high} and rmse_mean_{all,nonfailed}_ci_{low,high}.
        The rmse_*_all columns average a failed run's RMSE over the part it tracked, so a rule that fails
        every run can look best by them: read them beside failure_rate, or read `objective`.
    """
    check_support(support)
    by = list(by)
    missing = sorted(set(by + ["rmse", "mean", "sse", "count", "coverage", "failed"]) - set(table.columns))
    if missing:
        raise ValueError(f"table lacks columns {missing} (expected a per_run_table result)")

    # Columns to numpy once, then numpy per group: pandas per group costs ~20 ms a group, which a
    # study with one group per run and setting (thousands) pays in minutes.
    col = {c: table[c].to_numpy(np.float64) for c in ("rmse", "mean", "sse", "count", "coverage")}
    failed_all = table["failed"].to_numpy(bool)
    loss_all = run_loss(table, failure_penalty, loss).to_numpy(np.float64)
    charged_all = _charged(table).to_numpy(bool)
    support_columns = "changed_fraction" in table
    if support_columns:
        changed_all = table["changed_fraction"].to_numpy(np.float64)
        unsupported_all = table["unsupported_fraction"].to_numpy(np.float64)
    rows = []
    for key, idx in zip(*_group_rows(table, by), strict=True):
        failed = failed_all[idx]
        ok = idx[~failed]
        row: dict[str, object] = dict(zip(by, key, strict=True))
        row["n_runs"] = len(idx)
        row["n_failed"] = int(failed.sum())
        row["failure_rate"] = float(failed.mean())
        coverage = col["coverage"][idx]
        row["mean_coverage"] = float(np.nanmean(coverage)) if (~np.isnan(coverage)).any() else np.nan
        scored = loss_all[idx]
        if support == "exclude" and support_columns:
            scored = scored[~(unsupported_all[idx] > 0)]
        row["objective"] = float(scored.mean()) if len(scored) else float(failure_penalty)
        row["share_penalised"] = float(charged_all[idx].mean())
        for event in ("resets", "new_maps"):
            if event in table:  # events of the replay, never failures by themselves
                row[f"mean_{event}"] = float(table[event].to_numpy(np.float64)[idx].mean())
        if support_columns:
            row["mean_changed"] = float(changed_all[idx].mean())
            row["mean_unsupported"] = float(unsupported_all[idx].mean())
            row["share_unsupported_runs"] = float((unsupported_all[idx] > 0).mean())
        row.update(_nan_stats(col["rmse"][idx], "all"))
        row.update(_nan_stats(col["rmse"][ok], "nonfailed"))
        row.update(_pooled(col["count"][idx], col["sse"][idx], col["mean"][idx], "all"))
        row.update(_pooled(col["count"][ok], col["sse"][ok], col["mean"][ok], "nonfailed"))
        if ci:
            low, high = bootstrap_ci(scored, np.mean, n_boot, level, seed)
            row["objective_ci_low"], row["objective_ci_high"] = low, high
            for suffix, part in (("all", idx), ("nonfailed", ok)):
                low, high = bootstrap_ci(col["rmse"][part], np.mean, n_boot, level, seed)
                row[f"rmse_mean_{suffix}_ci_low"] = low
                row[f"rmse_mean_{suffix}_ci_high"] = high
        rows.append(row)
    return pd.DataFrame(rows)


def failure_counts(table: pd.DataFrame, by: Sequence[str] = ("rule",)) -> pd.DataFrame:
    """How many runs failed for each reason, per group: what the failure_rate of `aggregate` is made of.

    Arguments:
        table: a per-run table with `failed` and `failure_reason` (per_run_table, jsve.evaluate).
        by: the columns that define a group (default: one group per rule); [] counts over the table.

    Returns:
        One row per group and failure_reason among the failed runs: the `by` columns, failure_reason and
        n_runs, groups in order and, within one, the most frequent reason first (ties by reason). No row
        for a group without a failed run.
    """
    by = list(by)
    missing = sorted(set(by + ["failed", "failure_reason"]) - set(table.columns))
    if missing:
        raise ValueError(f"table lacks columns {missing} (expected a per_run_table result)")
    failed = pd.DataFrame(table.loc[table["failed"].astype(bool), [*by, "failure_reason"]])
    counts = failed.value_counts(dropna=False).reset_index(name="n_runs")
    counts = counts.sort_values(
        [*by, "n_runs", "failure_reason"], ascending=[*(True,) * len(by), False, True]
    )
    return counts.reset_index(drop=True)


def group_weights(
    meta: pd.DataFrame, by: Sequence[str] | None = ("sequence", "disturbance", "level")
) -> np.ndarray:
    """Run weights under which every group of `by` counts equally (mean weight 1).

    Arguments:
        meta: one row per run (host metadata, e.g. Bucket.meta).
        by: metadata columns defining a group; None or [] gives every run weight 1.
    Returns:
        float64 [R]: n_runs / (n_groups x size of the run's group).
    """
    n = len(meta)
    if not by:
        return np.ones(n)
    missing = [k for k in by if k not in meta.columns]
    if missing:
        raise ValueError(f"group_weights: metadata lacks {missing}; has {list(meta.columns)}")
    keys = meta[list(by)].astype(str).agg("\x1f".join, axis=1)
    sizes = keys.map(keys.value_counts())
    n_groups = keys.nunique()
    return (n / (n_groups * sizes.to_numpy(np.float64))).astype(np.float64)
