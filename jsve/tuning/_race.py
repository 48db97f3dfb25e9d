"""Paired comparisons of rules run in the loop, on the bounded loss (metres), by (dataset, seed).

    paired_losses      two candidates' losses on the instances both ran
    worse_p            one-sided Wilcoxon signed-rank p that a candidate's loss exceeds another's
    holm               Holm's step-down adjustment of p-values (scipy.stats has none)
    eliminate          one racing step: who is significantly worse than the best, Holm over the rest
    better_than        which challengers beat the incumbent, Holm over the challengers
    mean_intervals     the mean of paired differences with its 95 % t and BCa intervals, Wilcoxon p
    lost_runs          which runs lost track: failed, or diverged past the loss's cap
    failure_test       paired losses of track: the discordant pairs and the exact McNemar p
    paired_difference  a - b on the bounded loss, its lost runs and its tracked pairs apart (the check)
    check_verdict      the word for a check's row: better or worse only where BCa and t agree

The tests are scipy.stats.wilcoxon (signed ranks, zero differences dropped; every difference zero
gives p = 1), scipy.stats.ttest_1samp and scipy.stats.bootstrap for the intervals, and scipy.stats.
binomtest on the discordant pairs for the failures (the exact McNemar test).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

KEY = ("dataset", "seed")
"""What runs are paired by."""


def paired_losses(rows: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Columns a and b: the two candidates' loss_m on every (dataset, seed) both ran, in key order."""
    wide = rows[rows.candidate.isin([a, b])].pivot_table(
        index=list(KEY), columns="candidate", values="loss_m", aggfunc="first"
    )
    if a not in wide or b not in wide:
        return pd.DataFrame({a: [], b: []})
    return wide[[a, b]].dropna()


def worse_p(d: np.ndarray) -> float:
    """One-sided p of the Wilcoxon signed-rank test that the differences d (a - b) lie above zero (a is
    worse than b); 1 when no difference is non-zero."""
    d = np.asarray(d, np.float64)
    if np.count_nonzero(d) == 0:
        return 1.0
    return float(stats.wilcoxon(d, alternative="greater").pvalue)


def holm(p: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error control for any dependence)."""
    p = np.asarray(p, np.float64)
    m = len(p)
    if m == 0:
        return p
    order = np.argsort(p, kind="stable")
    adjusted = np.maximum.accumulate(np.minimum(1.0, (m - np.arange(m)) * p[order]))
    out = np.empty(m)
    out[order] = adjusted
    return out


def _means(rows: pd.DataFrame, names: Sequence[str]) -> pd.Series:
    """Mean loss of each candidate over the instances every one of them ran."""
    wide = rows[rows.candidate.isin(names)].pivot_table(
        index=list(KEY), columns="candidate", values="loss_m", aggfunc="first"
    )
    return wide.reindex(columns=list(names)).dropna().mean()


def _worse_than(rows: pd.DataFrame, a: str, b: str) -> dict:
    """pairs, mean_diff_m (a - b, metres) and p, the one-sided p that a is worse than b."""
    pair = paired_losses(rows, a, b)
    d = (pair[a] - pair[b]).to_numpy()
    return {"pairs": len(d), "mean_diff_m": float(d.mean()) if len(d) else np.nan, "p": worse_p(d)}


def eliminate(rows: pd.DataFrame, alive: Sequence[str], alpha: float) -> tuple[list[str], pd.DataFrame]:
    """One racing step: the best candidate (lowest mean loss over the instances all of `alive` ran)
    against each other one, one-sided Wilcoxon (the other is worse), Holm-adjusted over the others.

    Returns:
        (the candidates kept, in their order; a table per candidate tested: best, pairs, mean_diff_m,
        p, p_holm, eliminated).
    """
    means = _means(rows, alive)
    best = str(means.idxmin())
    tests = []
    for name in alive:
        if name != best:
            tests.append({"candidate": name, "best": best, **_worse_than(rows, name, best)})
    table = pd.DataFrame(tests, columns=["candidate", "best", "pairs", "mean_diff_m", "p"])
    table["p_holm"] = holm(table["p"].to_numpy())
    table["eliminated"] = table["p_holm"] < alpha
    out = set(table.loc[table.eliminated, "candidate"])
    return [n for n in alive if n not in out], table


def better_than(
    rows: pd.DataFrame, incumbent: str, challengers: Sequence[str], alpha: float
) -> tuple[str | None, pd.DataFrame]:
    """Which challengers beat the incumbent: one-sided Wilcoxon (the incumbent is worse), Holm-adjusted
    over the challengers; the winner is the one of lowest mean loss among those that do.

    Returns:
        (the winner or None; a table per challenger: pairs, mean_diff_m (challenger - incumbent), p,
        p_holm, beats).
    """
    tests = []
    for name in challengers:
        test = _worse_than(rows, incumbent, name)
        tests.append({"candidate": name, "incumbent": incumbent, **test, "mean_diff_m": -test["mean_diff_m"]})
    table = pd.DataFrame(tests, columns=["candidate", "incumbent", "pairs", "mean_diff_m", "p"])
    table["p_holm"] = holm(table["p"].to_numpy())
    table["beats"] = table["p_holm"] < alpha
    winners = table[table.beats].sort_values("mean_diff_m", kind="stable")
    return (None if winners.empty else str(winners.iloc[0].candidate)), table


RESOLUTION_M = 0.03
"""The half-width (metres) of a 95 % interval that decides a difference worth a tuning."""


def pairs_for_half_width(sd_m: float, half_width_m: float = RESOLUTION_M, level: float = 0.95) -> int:
    """The fewest pairs whose t interval of the mean difference is at most `half_width_m` wide on each
    side when the differences spread as `sd_m` (metres): n with t(level, n - 1) sd / sqrt(n) <= h."""
    if not np.isfinite(sd_m) or sd_m <= 0:
        return 2
    # t exceeds the normal quantile, so the normal's answer is where the search starts
    n = max(2, int(np.ceil((stats.norm.ppf(0.5 + level / 2) * sd_m / half_width_m) ** 2)))
    while stats.t.ppf(0.5 + level / 2, n - 1) * sd_m / np.sqrt(n) > half_width_m:
        n += 1
    return n


def mean_intervals(d: np.ndarray, *, n_resamples: int = 9999) -> dict:
    """The mean of paired differences d (metres) with its 95 % t interval (ttest_1samp, the same as
    ttest_rel on the pairs) and BCa bootstrap interval, and the two-sided Wilcoxon p. NaN with no pair;
    an interval of zero width at the common value when every difference is the same."""
    d = np.asarray(d, np.float64)
    out = dict.fromkeys(
        ("mean_diff_m", "t_low_m", "t_high_m", "bca_low_m", "bca_high_m", "wilcoxon_p"), np.nan
    )
    if len(d) == 0:
        return out
    out["mean_diff_m"] = float(d.mean())
    if np.ptp(d) == 0:
        wilcoxon = 1.0 if d[0] == 0 else np.nan
        return {
            **out,
            "t_low_m": d[0],
            "t_high_m": d[0],
            "bca_low_m": d[0],
            "bca_high_m": d[0],
            "wilcoxon_p": wilcoxon,
        }
    ci = stats.ttest_1samp(d, 0.0).confidence_interval(0.95)
    boot = stats.bootstrap((d,), np.mean, method="BCa", n_resamples=n_resamples, random_state=0)
    return {
        **out,
        "t_low_m": float(ci.low),
        "t_high_m": float(ci.high),
        "bca_low_m": float(boot.confidence_interval.low),
        "bca_high_m": float(boot.confidence_interval.high),
        "wilcoxon_p": float(stats.wilcoxon(d).pvalue) if np.count_nonzero(d) else 1.0,
    }


def lost_runs(rows: pd.DataFrame, name: str, index: pd.Index) -> np.ndarray:
    """[n] bool: whether candidate `name`'s run on each (dataset, seed) of `index` was lost: it failed,
    or it tracked with an ATE above what its loss was capped at (a diverged run, ate_m > loss_m, where
    rows carry ate_m). False where it has no run."""
    own = rows[rows.candidate == name].set_index(list(KEY)).reindex(index)
    lost = own["failed"].fillna(False).to_numpy(bool)
    if "ate_m" in own:
        lost = lost | (own["ate_m"] > own["loss_m"]).fillna(False).to_numpy(bool)
    return lost


def failure_test(lost_a: np.ndarray, lost_b: np.ndarray) -> dict:
    """Paired losses of track of two rules ([n] bool, one per pair, lost_runs): the pairs where only a
    and only b lost the run, and the exact McNemar p (two-sided binomial test of the discordant pairs,
    scipy.stats.binomtest; 1 with none)."""
    only_a = int(np.sum(lost_a & ~lost_b))
    only_b = int(np.sum(~lost_a & lost_b))
    p = float(stats.binomtest(only_a, only_a + only_b).pvalue) if only_a + only_b else 1.0
    return {"rule_only_lost": only_a, "baseline_only_lost": only_b, "lost_p": p}


def paired_difference(rows: pd.DataFrame, a: str, b: str, *, n_resamples: int = 9999) -> dict:
    """a - b on the bounded loss over the instances both ran (mean_intervals: mean, t and BCa 95 %
    intervals, Wilcoxon p), its median, how often a did better, each side's failed runs, and the two
    questions a heavy-tailed loss mixes: does a lose track less often than b (failed or diverged runs,
    lost_runs; failure_test, exact McNemar) and, on the pairs neither lost, is it more accurate
    (tracked_*: the same intervals over those pairs only)."""
    sub = rows[rows.candidate.isin([a, b])]
    pair = paired_losses(rows, a, b)
    d = (pair[a] - pair[b]).to_numpy()
    failed = sub.pivot_table(index=list(KEY), columns="candidate", values="failed", aggfunc="first")
    failed = failed.reindex(pair.index)
    failed_a, failed_b = (
        failed[n].fillna(False).to_numpy(bool) if n in failed else np.zeros(len(d), bool) for n in (a, b)
    )
    lost_a, lost_b = lost_runs(sub, a, pair.index), lost_runs(sub, b, pair.index)
    tracked = ~lost_a & ~lost_b
    both = mean_intervals(d[tracked], n_resamples=n_resamples)
    sd = float(d.std(ddof=1)) if len(d) >= 2 else np.nan
    return {
        "rule": a,
        "baseline": b,
        "pairs": len(d),
        **mean_intervals(d, n_resamples=n_resamples),
        "median_diff_m": float(np.median(d)) if len(d) else np.nan,
        "better": int((d < 0).sum()),
        "worse": int((d > 0).sum()),
        "rule_failed": int(failed_a.sum()),
        "baseline_failed": int(failed_b.sum()),
        "rule_mean_m": float(pair[a].mean()) if len(d) else np.nan,
        "baseline_mean_m": float(pair[b].mean()) if len(d) else np.nan,
        "sd_diff_m": sd,
        "pairs_for_resolution": pairs_for_half_width(sd) if len(d) >= 2 else None,
        **failure_test(lost_a, lost_b),
        "tracked_pairs": int(tracked.sum()),
        **{f"tracked_{k}": both[k] for k in ("mean_diff_m", "bca_low_m", "bca_high_m", "wilcoxon_p")},
    }


def check_verdict(row) -> str:
    """The word for a row of paired_difference (rule - baseline): "better" or "worse" when both its 95 %
    intervals of the mean, BCa and t, exclude 0 on that side (BCa alone where the t interval is
    undefined), "unsettled (BCa and t disagree)" when only one excludes 0 (a heavy tail: the bootstrap
    of a few outlying pairs and the normal approximation tell different stories), "no clear difference"
    when neither does, "undetermined" without pairs."""
    bca = (row["bca_low_m"], row["bca_high_m"])
    if not np.isfinite(bca).all():
        return "undetermined"
    t = (row["t_low_m"], row["t_high_m"])
    t = t if np.isfinite(t).all() else bca
    sides = {("better" if high < 0 else "worse" if low > 0 else "") for low, high in (bca, t)}
    if sides == {""}:
        return "no clear difference"
    if len(sides) == 1:
        return sides.pop()
    return "unsettled (BCa and t disagree)"


__all__ = [
    "KEY",
    "RESOLUTION_M",
    "pairs_for_half_width",
    "better_than",
    "eliminate",
    "holm",
    "mean_intervals",
    "lost_runs",
    "failure_test",
    "paired_difference",
    "check_verdict",
    "paired_losses",
    "worse_p",
]
