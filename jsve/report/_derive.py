"""The report's derived numbers, each computed from the folder's tables by one function.

- `scored_runs`: the per-run table with each run's loss under the objective (the fit's penalty and
  support policy) and its weight (the fit's run weighting);
- `rule_overview`: per rule over all runs: the objective, failures, coverage, and how often the rule
  switches (frames rejected, runs that reach LOST);
- `level_table`: the same per disturbance and level, with the ATE of the runs that kept tracking;
- `heldout_rows`: the held-out comparison with the presets once (they are not fitted: their rows are equal
  in every fold kind);
- `recommend`: the fitted rule the report recommends, and why;
- `parameter_table`: the fitted parameters with identifiability flags.

Nothing here reads files: `jsve.report._report` reads the tables and passes them in, so every function is
testable on tables made by hand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from jsve.core._rules import BASELINES, PRESETS, preset, rule_params
from jsve.evaluation import aggregate, group_weights, run_loss
from jsve.fitting._fit import fitted_rule_name

NOT_IDENTIFIED_SPAN = 0.5
"""A parameter whose 95 % bootstrap interval spans at least this share of its search range is flagged:
the data do not pin it down."""
AT_BOUND_SHARE = 0.01
"""A fitted value within this share of its search range from a bound is flagged as at the bound: the
optimum may lie outside the box."""
MIN_PLAUSIBLE_INLIERS = 10
"""Inlier thresholds below this are flagged as physically implausible: ORB-SLAM3's lowest is 10
(Tracking::TrackLocalMap's recovery test), and Tracking::Relocalization drops a PnP pose with fewer than
10 inliers (nGood < 10)."""
FAIL_BELOW = ("imu_init", "not_init", "reloc")
"""Thresholds of a test "fail when score < t" (jsve.core._rules.Thresholds); `recovery` is "OK when
score > t"."""
COUNT_FAMILIES = frozenset({"inliers"})
"""Families whose score is a count (the inlier count), so that only integer thresholds mean anything."""


# ---------------------------------------------------------------------------------------------------
# Scoring runs as the fit does


@dataclass(frozen=True)
class Scoring:
    """How runs are scored: the fit's objective settings (study.json), or jsve's defaults for a folder
    of `jsve evaluate` (which fits nothing).

    Attributes:
        penalty: metres charged for a failed run.
        support: "penalise" (a run out of the log's support counts as failed) or "exclude" (it leaves
            the mean).
        balance_by: metadata columns whose groups count equally ([]: every run 1).
        loss: "bounded" (a tracked run costs at most the penalty) or "raw" (jsve.core._objective.LOSSES).
        failure: what failed a run, "coverage" or "strict" (jsve.core._objective.FAILURE_DEFINITIONS).
    """

    penalty: float
    support: str
    balance_by: tuple[str, ...]
    loss: str = "bounded"
    failure: str = "coverage"


def scored_runs(runs: pd.DataFrame, scoring: Scoring) -> pd.DataFrame:
    """The per-run table with `objective_failed` (failed, or out of the log's support), `loss` (metres:
    the penalty where objective_failed, else the ATE RMSE, capped at the penalty under loss="bounded"),
    `included` (False for a run out of support
    under "exclude") and `weight` (group weights within each rule's runs, jsve.evaluation.group_weights)."""
    out = runs.copy()
    unsupported = out["unsupported_fraction"] > 0 if "unsupported_fraction" in out else False
    out["objective_failed"] = out["failed"].astype(bool) | unsupported
    out["loss"] = run_loss(out.assign(failed=out["objective_failed"]), scoring.penalty, scoring.loss)
    out["included"] = ~unsupported if scoring.support == "exclude" else True
    by = [c for c in scoring.balance_by if c in out.columns]
    out["weight"] = np.nan
    for _, index in out.groupby("rule", sort=False).groups.items():
        out.loc[index, "weight"] = group_weights(out.loc[index], by)
    return out


def _wmean(values, weights) -> float:
    v, w = np.asarray(values, np.float64), np.asarray(weights, np.float64)
    keep = np.isfinite(v) & (w > 0)
    return float(np.sum(v[keep] * w[keep]) / np.sum(w[keep])) if keep.any() else float("nan")


def _overview(g: pd.DataFrame) -> dict:
    inc = g[g["included"]]
    ok = inc[~inc["objective_failed"]]
    row = {
        "n_runs": len(g),
        "objective": _wmean(inc["loss"], inc["weight"]),
        "failure_rate": _wmean(inc["objective_failed"], inc["weight"]),
        "coverage": _wmean(inc["coverage"], inc["weight"]),
        "ate_tracking": _wmean(ok["rmse"], ok["weight"]),
        "n_tracking": len(ok),
    }
    if "accepted_fraction" in g:
        row["rejected"] = 1.0 - _wmean(g["accepted_fraction"], g["weight"])
    if "lost_any" in g:
        row["reached_lost"] = _wmean(g["lost_any"], g["weight"])
    for event in ("resets", "new_maps"):
        if event in g:  # events, never failures by themselves
            row[event] = _wmean(g[event], g["weight"])
    if "unsupported_fraction" in g:
        row["unsupported_runs"] = _wmean(g["unsupported_fraction"] > 0, g["weight"])
    if "changed_fraction" in g:
        row["changed"] = _wmean(g["changed_fraction"], g["weight"])
    return row


def rule_order(present) -> list[str]:
    """Fitted rules first (jsve.core's families), then the presets in PRESETS order, then the rest."""
    present = list(dict.fromkeys(present))
    fitted = [fitted_rule_name(f) for f in BASELINES]
    known = [r for r in fitted + list(PRESETS) if r in present]
    return known + sorted(r for r in present if r not in known)


def rule_overview(scored: pd.DataFrame) -> pd.DataFrame:
    """Per rule over all runs (weighted as the fit weighs them): n_runs, objective (m), failure_rate
    (failed or out of support), coverage, ate_tracking (m, mean ATE RMSE of the runs that kept tracking)
    and n_tracking, rejected (share of frames not tracked: 1 - accepted_fraction), reached_lost (share of
    runs that reached LOST), resets and new_maps (the replay's, per run), unsupported_runs, changed
    (share of frames whose replayed state differs from the recorded one: how far the replay reaches from
    what was recorded)."""
    rows = [{"rule": rule, **_overview(g)} for rule, g in scored.groupby("rule", sort=False)]
    table = pd.DataFrame(rows)
    return table.set_index("rule").loc[rule_order(table["rule"])].reset_index()


def level_table(scored: pd.DataFrame) -> pd.DataFrame:
    """Per (disturbance, level, rule): the objective, failure rate (failed or out of support), coverage
    and ATE of the runs that kept tracking as `rule_overview` computes them, with n_runs, n_failed (the
    replay's failures), rmse_std_nonfailed and the support columns of jsve.evaluation.aggregate."""
    keys = ["disturbance", "level", "rule"]
    rows = [
        {**dict(zip(keys, key, strict=True)), **_overview(g)} for key, g in scored.groupby(keys, sort=True)
    ]
    mine = pd.DataFrame(rows).rename(columns={"failure_rate": "objective_failure_rate"})
    mine = mine.drop(columns=["n_runs", "rejected", "reached_lost", "unsupported_runs"], errors="ignore")
    stats = aggregate(scored, keys, ci=False)
    wanted = ["n_runs", "n_failed", "rmse_std_nonfailed", *LEVEL_SUPPORT_COLUMNS]
    stats = stats[keys + [c for c in wanted if c in stats.columns]]
    return mine.merge(stats, on=keys, how="left")


LEVEL_SUPPORT_COLUMNS = ("mean_changed", "mean_unsupported", "share_unsupported_runs")
"""The support columns of jsve.evaluation.aggregate the per-level tables show."""


# ---------------------------------------------------------------------------------------------------
# Held-out comparison


def _equal_rows(part: pd.DataFrame) -> bool:
    numbers = part.drop(columns=["fold_kind"]).select_dtypes("number").to_numpy(np.float64)
    return bool(np.allclose(numbers, numbers[:1], rtol=1e-9, atol=0, equal_nan=True))


def heldout_rows(summary: pd.DataFrame) -> pd.DataFrame:
    """The held-out comparison (compare's table) with every fitted rule per fold kind and every preset
    once: a preset is not fitted, so its row is the same in every fold kind (fold_kind "-"); where the
    rows differ (support "exclude" scores each fold kind on other runs) the preset keeps one per kind.
    Fitted rules first (rule_order), fold kinds in the table's order."""
    kinds = list(dict.fromkeys(summary["fold_kind"]))
    parts = []
    for rule in rule_order(summary["rule"]):
        part = summary[summary["rule"] == rule]
        part = part.iloc[np.argsort([kinds.index(k) for k in part["fold_kind"]], kind="stable")]
        if rule in PRESETS and _equal_rows(part):
            part = part.iloc[:1].assign(fold_kind="-")
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


@dataclass(frozen=True)
class Recommendation:
    """The recommended fitted rule.

    Attributes:
        rule: its name ("fitted-sve"); family: its family ("sve").
        worst: its largest held-out objective over the fold kinds (m), the criterion.
        reason: why, in a sentence.
    """

    rule: str
    family: str
    worst: float
    reason: str


def recommend(summary: pd.DataFrame, families) -> Recommendation | None:
    """The fitted rule whose held-out objective is lowest in its worst fold kind (a rule must transfer to
    held-out sequences and disturbances, not only to held-out runs), ties to the lower k-fold value, then
    to the family with fewer parameters (inliers). None without a fitted rule in the table."""
    candidates = []
    for family in families:
        rows = summary[summary["rule"] == fitted_rule_name(family)]
        if rows.empty:
            continue
        worst = float(rows["mean_loss"].max())
        first = float(rows["mean_loss"].iloc[0])
        simple = 0 if family in COUNT_FAMILIES else 1
        candidates.append((round(worst, 6), round(first, 6), simple, family, worst, rows))
    if not candidates:
        return None
    candidates.sort(key=lambda c: c[:4])
    *_, family, worst, rows = candidates[0]
    kinds = list(rows["fold_kind"])
    if len(candidates) == 1:
        reason = "the only fitted rule"
    elif len(kinds) > 1:
        reason = "its held-out objective is the lowest of the fitted rules in its worst fold kind"
    else:
        reason = "its held-out objective is the lowest of the fitted rules"
    return Recommendation(fitted_rule_name(family), family, worst, reason)


def verdict(low, high) -> str:
    """A paired difference's interval in words: "better" (entirely below 0), "worse" (above), "no clear
    difference" (it contains 0)."""
    if not (np.isfinite(low) and np.isfinite(high)):
        return "not comparable"
    if high < 0:
        return "better"
    if low > 0:
        return "worse"
    return "no clear difference"


# ---------------------------------------------------------------------------------------------------
# Parameters and identifiability


def acts_as(family: str, parameter: str, value: float) -> str:
    """What a count threshold means for an integer score: "fail below 3" becomes "needs >= 3 inliers"
    (score < 2.75 fails exactly the counts 0-2); recovery "> 3.42" becomes "recovers from 4 inliers".
    '' for other parameters."""
    if family not in COUNT_FAMILIES or not np.isfinite(value):
        return ""
    if parameter in FAIL_BELOW:
        return f">= {max(0, math.ceil(value))} inliers"
    if parameter == "recovery":
        return f">= {max(0, math.floor(value) + 1)} inliers"
    return ""


def _bounds(fitted: dict, family: str, parameter: str) -> tuple[float, float] | None:
    free = (fitted.get(family) or {}).get("space", {}).get("free", {})
    if parameter in free:
        lo, hi = free[parameter]
        return float(lo), float(hi)
    if parameter.startswith("weight_"):
        return 0.0, 1.0  # simplex weights (jsve.fitting._space.ParamSpace.derived)
    return None


def _baseline_value(family: str, parameter: str) -> float | None:
    base = BASELINES.get(family)
    if base is None:
        return None
    params = rule_params(preset(base))
    return float(params[parameter]) if parameter in params else None


def parameter_table(params: pd.DataFrame, fitted: dict) -> tuple[pd.DataFrame, list[str]]:
    """The fitted parameters with what they mean and what is wrong with them.

    Arguments:
        params: the study's params table (family, parameter, value, ci_low, ci_high, boot_std).
        fitted: fitted_<family>.json records by family (their search boxes, "space").
    Returns:
        (table, notes): one row per family and parameter with value, ci_low, ci_high, lo, hi (the search
        box, NaN where unknown), ci_share (interval width / box width), baseline (the family's preset's
        value), acts_as (count thresholds as integers) and flags ("kind: detail" strings: not identified,
        at a bound, outside its interval, implausible); derived rows equal to a parameter row (weight_a
        = w_a) are dropped, and `notes` says so.
    """
    rows, notes = [], []
    for family, part in params.groupby("family", sort=False):
        seen: dict[tuple, str] = {}
        for rec in part.to_dict("records"):
            name = rec["parameter"]
            key = (round(rec["value"], 12), round(rec["ci_low"], 12), round(rec["ci_high"], 12))
            if name.startswith("weight_") and key in seen:
                notes.append(f"{family}'s {name} is {seen[key]}")
                continue
            seen.setdefault(key, name)
            bounds = _bounds(fitted, family, name)
            lo, hi = bounds if bounds else (float("nan"), float("nan"))
            span = hi - lo
            value, low, high = float(rec["value"]), float(rec["ci_low"]), float(rec["ci_high"])
            share = (high - low) / span if bounds and span > 0 else float("nan")
            flags = []
            if np.isfinite(share) and share >= NOT_IDENTIFIED_SPAN:
                flags.append(
                    f"not identified: its 95 % interval spans {100 * share:.0f} % of the search range"
                )
            if bounds and span > 0 and not name.startswith("weight_"):
                if value - lo <= AT_BOUND_SHARE * span:
                    flags.append("at a bound: the lower bound of the search range")
                elif hi - value <= AT_BOUND_SHARE * span:
                    flags.append("at a bound: the upper bound of the search range")
            tol = 1e-9 * (span if bounds and span > 0 else 1.0)
            if np.isfinite(low) and np.isfinite(high) and not low - tol <= value <= high + tol:
                flags.append("outside its interval: the fit lies outside its own bootstrap interval")
            if family in COUNT_FAMILIES and name in (*FAIL_BELOW, "recovery"):
                if value < MIN_PLAUSIBLE_INLIERS:
                    flags.append(
                        f"implausible: below {MIN_PLAUSIBLE_INLIERS} inliers, ORB-SLAM3's lowest threshold"
                    )
            rows.append(
                {
                    "family": family,
                    "parameter": name,
                    "value": value,
                    "ci_low": low,
                    "ci_high": high,
                    "lo": lo,
                    "hi": hi,
                    "ci_share": share,
                    "baseline": _baseline_value(family, name),
                    "acts_as": acts_as(family, name, value),
                    "flags": flags,
                }
            )
    return pd.DataFrame(rows), notes
