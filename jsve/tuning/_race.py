"""Paired comparisons of rules run in the loop, on the bounded loss (metres), by (dataset, seed).

    paired_losses      two candidates' losses on the instances both ran
    worse_p            one-sided Wilcoxon signed-rank p that a candidate's loss exceeds another's
    holm               Holm's step-down adjustment of p-values (scipy.stats has none)
    eliminate          one racing step: who is significantly worse than the best, Holm over the rest
    better_than        which challengers beat the incumbent, Holm over the challengers
    paired_difference  a - b with its 95 % t and BCa intervals, Wilcoxon p and counts (the check)

The tests are scipy.stats.wilcoxon (signed ranks, zero differences dropped; every difference zero
gives p = 1) and scipy.stats.ttest_rel and scipy.stats.bootstrap for the intervals.
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


def paired_difference(rows: pd.DataFrame, a: str, b: str, *, n_resamples: int = 9999) -> dict:
    """a - b on the bounded loss over the instances both ran: mean and median (metres), the mean's 95 %
    t interval (ttest_rel) and BCa bootstrap interval, two-sided Wilcoxon p, how often a did better, and
    each side's failed runs. Intervals are NaN with fewer than 2 pairs or no spread."""
    sub = rows[rows.candidate.isin([a, b])]
    pair = paired_losses(rows, a, b)
    d = (pair[a] - pair[b]).to_numpy()
    failed = sub.pivot_table(index=list(KEY), columns="candidate", values="failed", aggfunc="first")
    failed = failed.reindex(pair.index)
    out = {
        "rule": a,
        "baseline": b,
        "pairs": len(d),
        "mean_diff_m": np.nan,
        "median_diff_m": np.nan,
        "t_low_m": np.nan,
        "t_high_m": np.nan,
        "bca_low_m": np.nan,
        "bca_high_m": np.nan,
        "wilcoxon_p": np.nan,
        "better": int((d < 0).sum()),
        "worse": int((d > 0).sum()),
        "rule_failed": int(failed[a].sum()) if a in failed else 0,
        "baseline_failed": int(failed[b].sum()) if b in failed else 0,
        "rule_mean_m": float(pair[a].mean()) if len(d) else np.nan,
        "baseline_mean_m": float(pair[b].mean()) if len(d) else np.nan,
        "sd_diff_m": float(d.std(ddof=1)) if len(d) >= 2 else np.nan,
        "pairs_for_resolution": pairs_for_half_width(float(d.std(ddof=1))) if len(d) >= 2 else None,
    }
    if len(d) == 0:
        return out
    out.update(mean_diff_m=float(d.mean()), median_diff_m=float(np.median(d)))
    if len(d) >= 2 and np.ptp(d) > 0:
        ci = stats.ttest_rel(pair[a], pair[b]).confidence_interval(0.95)
        boot = stats.bootstrap((d,), np.mean, method="BCa", n_resamples=n_resamples, random_state=0)
        out.update(
            t_low_m=float(ci.low),
            t_high_m=float(ci.high),
            bca_low_m=float(boot.confidence_interval.low),
            bca_high_m=float(boot.confidence_interval.high),
            wilcoxon_p=float(stats.wilcoxon(d).pvalue) if np.count_nonzero(d) else 1.0,
        )
    elif len(d) >= 1 and np.ptp(d) == 0:
        out.update(
            t_low_m=float(d[0]),
            t_high_m=float(d[0]),
            bca_low_m=float(d[0]),
            bca_high_m=float(d[0]),
            wilcoxon_p=1.0 if d[0] == 0 else np.nan,
        )
    return out


__all__ = [
    "KEY",
    "RESOLUTION_M",
    "pairs_for_half_width",
    "better_than",
    "eliminate",
    "holm",
    "paired_difference",
    "paired_losses",
    "worse_p",
]
