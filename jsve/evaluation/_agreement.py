"""Replay against re-run: does replaying a log predict what a rule does when the front-end runs it?

Two per-run tables in `jsve.evaluation.evaluate`'s form (one row per run and rule) go in:

    replayed   every recording (a `record`-mode run, or any rule's own run) replayed under each rule;
    reruns     each rule's own runs of the front-end, scored by replaying them under their own rule
               (their logged decisions, jsve's scorer: the same ATE as the replayed rows).

ORB-SLAM3 is not deterministic (threads, RANSAC), so a replayed run is compared with the distribution
of the rule's re-runs of the same setting, never with one run. Every number is on the run loss the fit
minimises (jsve.evaluation._aggregate.run_loss, its one home): the ATE RMSE (m) of a run that
succeeded, `penalty` for a failed one or one whose replay left the log's support (never a mean over
the part a failed run tracked):

    d_i        = loss(replay_i) - mean loss(re-runs)            per replayed run of a (setting, rule)
    bias       = mean d_i;   limits of agreement = bias -+ 1.96 sd(d_i)       (Bland & Altman 1986)
    in_band    = share of replays with q05 <= loss(replay_i) <= q95 of the re-runs' losses
    tau        = Kendall's tau-b between the rules' mean replayed loss and mean re-run loss, per level
    regret@1   = mean re-run loss of the rule the replay ranks first - the best mean re-run loss
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M as DEFAULT_PENALTY_M
from jsve.evaluation._aggregate import run_loss

SETTING = ("sequence", "disturbance", "level")
"""Columns that name a setting: one sequence under one disturbance level."""


def rerun_summary(
    reruns: pd.DataFrame, keys: Sequence[str], penalty: float = DEFAULT_PENALTY_M
) -> pd.DataFrame:
    """Per key (e.g. setting, rule, switch model): the re-runs' count, mean loss, 5 and 95 % quantiles of
    the loss, failure rate and mean coverage."""
    t = reruns.assign(loss=run_loss(reruns, penalty), failed=reruns["failed"].astype(bool))
    g = t.groupby(list(keys), dropna=False)
    return g.agg(
        reruns=("loss", "size"),
        rerun_loss=("loss", "mean"),
        rerun_q05=("loss", lambda x: float(np.quantile(x, 0.05))),
        rerun_q95=("loss", lambda x: float(np.quantile(x, 0.95))),
        rerun_failed=("failed", "mean"),
        rerun_coverage=("coverage", "mean"),
    ).reset_index()


def agreement_table(
    replayed: pd.DataFrame, reruns: pd.DataFrame, keys: Sequence[str], penalty: float = DEFAULT_PENALTY_M
) -> pd.DataFrame:
    """Per key present in both tables: the replays' count and mean loss, the re-runs' summary, the bias
    and limits of agreement of replay - re-run mean, the share of replays inside the re-runs' 5-95 %
    band, and failure rate and coverage of each side. Keys with no re-runs (or no replays) are left out
    of the join and reported by `unmatched`."""
    keys = list(keys)
    summary = rerun_summary(reruns, keys, penalty)
    t = replayed.assign(loss=run_loss(replayed, penalty), failed=replayed["failed"].astype(bool))
    t = t.merge(summary, on=keys, how="inner")
    t["d"] = t["loss"] - t["rerun_loss"]
    t["inside"] = (t["loss"] >= t["rerun_q05"]) & (t["loss"] <= t["rerun_q95"])
    g = t.groupby(keys, dropna=False)
    out = g.agg(
        replays=("loss", "size"),
        replay_loss=("loss", "mean"),
        bias=("d", "mean"),
        sd=("d", lambda x: float(np.std(x, ddof=1)) if len(x) > 1 else float("nan")),
        in_band=("inside", "mean"),
        replay_failed=("failed", "mean"),
        replay_coverage=("coverage", "mean"),
    ).reset_index()
    out["loa_low"] = out["bias"] - 1.96 * out["sd"]
    out["loa_high"] = out["bias"] + 1.96 * out["sd"]
    return out.merge(summary, on=keys, how="left")


def unmatched(replayed: pd.DataFrame, reruns: pd.DataFrame, keys: Sequence[str]) -> pd.DataFrame:
    """Keys with replays but no re-runs, or re-runs but no replays (`side` says which): left out of
    every agreement figure, and listed, never silently."""
    keys = list(keys)
    a = replayed[keys].drop_duplicates()
    b = reruns[keys].drop_duplicates()
    both = a.merge(b, on=keys, how="outer", indicator=True)
    side = both["_merge"].map({"left_only": "no re-runs", "right_only": "no replays"})
    return both.assign(side=side).loc[both["_merge"] != "both", [*keys, "side"]].reset_index(drop=True)


def kendall_tau(x: Sequence[float], y: Sequence[float]) -> float:
    """Kendall's tau-b of two equally long sequences (ties in either counted as in scipy's kendalltau);
    NaN when fewer than two items or when either sequence is constant."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) != len(y):
        raise ValueError(f"kendall_tau: {len(x)} and {len(y)} items")
    i, j = np.triu_indices(len(x), k=1)
    dx, dy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
    concordant_minus_discordant = float(np.sum(dx * dy))
    n_x, n_y = float(np.sum(dx != 0)), float(np.sum(dy != 0))
    if n_x == 0 or n_y == 0:
        return float("nan")
    return concordant_minus_discordant / np.sqrt(n_x * n_y)


def ranking_table(agreement: pd.DataFrame, level_keys: Sequence[str]) -> pd.DataFrame:
    """Per level (e.g. sequence, disturbance, level, switch model): how many rules, Kendall's tau-b between
    the rules' mean replayed loss and mean re-run loss, the rule the replay ranks first, and its regret@1
    (its mean re-run loss minus the best mean re-run loss, m; 0 when the replay picks the best)."""
    rows = []
    for key, part in agreement.groupby(list(level_keys), dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        chosen = part.loc[part["replay_loss"].idxmin()]
        rows.append(
            {
                **dict(zip(level_keys, key, strict=True)),
                "rules": len(part),
                "tau": kendall_tau(part["replay_loss"], part["rerun_loss"]),
                "replay_best": chosen["rule"],
                "rerun_best": part.loc[part["rerun_loss"].idxmin(), "rule"],
                "regret_at_1": float(chosen["rerun_loss"] - part["rerun_loss"].min()),
            }
        )
    return pd.DataFrame(rows)
