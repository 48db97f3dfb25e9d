"""Replay against re-run: does replaying a log predict what a rule does when the front-end runs it?

Two per-run tables in `jsve.evaluation.evaluate`'s form (one row per run and rule) go in:

    replayed   every recording (a `record`-mode run, or any rule's own run) replayed under each rule;
    reruns     each rule's own runs of the front-end, scored by replaying them under their own rule
               (their logged decisions, jsve's scorer: the same ATE as the replayed rows).

ORB-SLAM3 is not deterministic (threads, RANSAC), so a replayed run is compared with the distribution
of the rule's re-runs of the same setting, never with one run. Every number is on the run loss the fit
minimises (jsve.evaluation._aggregate.run_loss, its one home), the bounded loss: the ATE RMSE (m) of
a run's saved trajectory, capped at `penalty`, where the run succeeded, `penalty` for a failed one or
one whose replay left the log's support (never a mean over the part a failed run tracked):

    d_i        = loss(replay_i) - mean loss(re-runs)            per replayed run of a (setting, rule)
    bias       = mean d_i;   limits of agreement = bias -+ 1.96 sd(d_i)       (Bland & Altman 1986)
    in_band    = share of replays with q05 <= loss(replay_i) <= q95 of the re-runs' losses
    tau        = Kendall's tau-b between the rules' mean replayed loss and mean re-run loss, per level
    regret@1   = mean re-run loss of the rule the replay ranks first (ties share) - the best mean re-run loss
    fitted regret@1 = mean re-run loss of the fitted rule - the best mean re-run loss

Intervals are percentile bootstraps that resample, within each setting, the re-runs of every rule and
the recordings (one draw of recordings shared by every rule, so the rules stay paired on them); a
statistic pooled over levels is the mean over levels, its interval that of the mean of the levels'
draws (`Draws`, `pool_draws`). The verdict (`ranking_verdict`) and the trust region of the replay
(`agreement_by_changed_share`, `trusted_changed_share`) follow criteria named below as constants;
docs/validation.md gives the reasons.
"""

from __future__ import annotations

import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M as DEFAULT_PENALTY_M
from jsve.evaluation._aggregate import run_loss

SETTING = ("sequence", "disturbance", "level")
"""Columns that name a setting: one sequence under one disturbance level."""

BAND = (0.05, 0.95)
"""Quantiles of the re-runs' losses that bound the band a replay should land in."""

REGRET_TOLERANCE_M = 0.05
"""Largest fitted regret@1 (m, upper end of its interval) the verdict accepts: 5 % of the 1 m failure
penalty, what one more failed run in 20 costs."""

MIN_RULES_FOR_VERDICT = 3
"""Rules with re-runs a level needs before a verdict rests on it: over 2 rules tau is a sign."""

MIN_IN_BAND_RATIO = 0.5
"""Trust region: a changed-share bin agrees when its replays land in the re-runs' band at least half as
often as another re-run would (`expected_in_band`)."""

MAX_ABS_BIAS_M = 0.05
"""Trust region: a bin agrees when its mean replay - re-run loss is within 5 cm (one failure in 20 at the
1 m penalty), or not significantly beyond it: |bias| - 1.96 se <= 5 cm. A re-run that diverges (metres
of ATE without failing, which ORB-SLAM3 does now and then) moves a setting's mean re-run loss by
decimetres; the standard error keeps that noise from reading as disagreement."""

MIN_REPLAYS_PER_BIN = 10
"""Trust region: a bin with fewer replays is no evidence either way (skipped)."""

CHANGED_SHARE_EDGES = (0.0, 0.001, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
"""Bin edges of the replay's changed share (the first bin, 0 to 0.1 %, holds the replays that change
no decision of a 700-frame run): fine where the presets' replays lie (0-5 % of the frames)."""

REPLAY_TRUSTED_CHANGED_SHARE = {"orbslam3": 0.001, "imu-coast": 0.01}
"""Per switch model (jsve.core's SWITCH_MODELS): the largest share of changed decisions
(`changed_fraction`: frames whose replayed state differs from the recording's) up to which replays
agreed with re-runs of the real ORB-SLAM3 (`trusted_changed_share`), with recordings made in `record`
mode under that switch model.

The replay-vs-re-run validation study sets them (docs/validation.md: rendered V1_01 and V2_01, blur
0-40 and occlusion 200/350, 4 rules under 2 switch models, 5 re-runs per setting; its bins:
docs/data/validation_trust.csv):
- `orbslam3` (stock ORB-SLAM3 v1.0, the default): 0.1 %, less than one frame of a 700-frame run, so in
  effect only a replay that changes no decision. Beyond it the `record-orbslam3` replays land in the
  re-runs' band less often than another re-run does, with a bias of about a metre.
- `imu-coast` (the hooked front-end that coasts on the IMU): 1 % on its own recordings
  (`record-imu-coast`; the bins beyond it hold too few replays to extend the region).
`jsve fit` warns, and its report says, when a fitted rule changes more than its switch model's share
(`trusted_share`).
"""


def trusted_share(switch_model: str) -> float:
    """REPLAY_TRUSTED_CHANGED_SHARE of a switch model; a ValueError naming the known ones otherwise
    (a model the validation did not cover has no trust region)."""
    try:
        return REPLAY_TRUSTED_CHANGED_SHARE[switch_model]
    except KeyError:
        raise ValueError(
            f"no validated trust region for switch model {switch_model!r}; "
            f"measured: {', '.join(REPLAY_TRUSTED_CHANGED_SHARE)}"
        ) from None


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
        rerun_q05=("loss", lambda x: float(np.quantile(x, BAND[0]))),
        rerun_q95=("loss", lambda x: float(np.quantile(x, BAND[1]))),
        rerun_failed=("failed", "mean"),
        rerun_coverage=("coverage", "mean"),
    ).reset_index()


def expected_in_band(n_reruns) -> np.ndarray:
    """The share of replays inside the re-runs' 5-95 % band that a replay drawn from the re-runs' own
    distribution reaches: 0.9 (n - 1) / (n + 1) for n re-runs with continuous losses.

    numpy's linear quantile q_p of n draws lies at order position 1 + p (n - 1), and the k-th of n draws
    has expected CDF k / (n + 1), so E[F(q95) - F(q05)] = 0.9 (n - 1) / (n + 1): 0.6 for 5 re-runs, not
    0.9. Ties (failed runs all at the penalty) only raise it. NaN for no re-runs.
    """
    n = np.asarray(n_reruns, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (BAND[1] - BAND[0]) * (n - 1) / (n + 1), np.nan)


def replay_rows(
    replayed: pd.DataFrame, reruns: pd.DataFrame, keys: Sequence[str], penalty: float = DEFAULT_PENALTY_M
) -> pd.DataFrame:
    """Each replay with a key that has re-runs, joined with their summary (`rerun_summary`).

    Adds: loss (m), d = loss - rerun_loss (m), inside (within the re-runs' band), expected_in_band,
    failure_agreement (the chance that a random re-run fails exactly when the replay does) and
    coverage_diff (replay coverage - mean re-run coverage, fraction of frames)."""
    keys = list(keys)
    summary = rerun_summary(reruns, keys, penalty)
    t = replayed.assign(loss=run_loss(replayed, penalty), failed=replayed["failed"].astype(bool))
    t = t.merge(summary, on=keys, how="inner")
    t["d"] = t["loss"] - t["rerun_loss"]
    t["inside"] = (t["loss"] >= t["rerun_q05"]) & (t["loss"] <= t["rerun_q95"])
    t["expected_in_band"] = expected_in_band(t["reruns"])
    t["failure_agreement"] = np.where(t["failed"], t["rerun_failed"], 1.0 - t["rerun_failed"])
    t["coverage_diff"] = t["coverage"].astype(float) - t["rerun_coverage"]
    return t


AGREEMENT_COLUMNS = (
    "replays", "replay_loss", "bias", "sd", "loa_low", "loa_high", "in_band", "expected_in_band",
    "replay_failed", "replay_coverage", "failure_agreement", "coverage_bias",
)  # fmt: skip
"""The columns `agreement_summary` gives each group of replays."""


def _agreement(g: pd.DataFrame) -> dict[str, float]:
    """Agreement of a group of replay rows: the Bland-Altman and band statistics of `agreement_summary`."""
    sd = float(np.std(g["d"], ddof=1)) if len(g) > 1 else float("nan")
    bias = float(g["d"].mean())
    return {
        "replays": len(g),
        "replay_loss": float(g["loss"].mean()),
        "bias": bias,
        "sd": sd,
        "loa_low": bias - 1.96 * sd,
        "loa_high": bias + 1.96 * sd,
        "in_band": float(g["inside"].mean()),
        "expected_in_band": float(g["expected_in_band"].mean()),
        "replay_failed": float(g["failed"].mean()),
        "replay_coverage": float(g["coverage"].mean()),
        "failure_agreement": float(g["failure_agreement"].mean()),
        "coverage_bias": float(g["coverage_diff"].mean()),
    }


def agreement_summary(rows: pd.DataFrame, by: Sequence[str]) -> pd.DataFrame:
    """Per group of `by` over `replay_rows` (every row as one group for no `by`): replays, replay_loss,
    bias, sd, limits of agreement (m), in_band and expected_in_band, the replays' failure rate and
    coverage, failure_agreement and coverage_bias (AGREEMENT_COLUMNS)."""
    by = list(by)
    if by:
        groups = rows.groupby(by, dropna=False, sort=True)
    else:
        groups = [((), rows)] if len(rows) else []
    out = []
    for key, g in groups:
        key = key if isinstance(key, tuple) else (key,)
        out.append({**dict(zip(by, key, strict=True)), **_agreement(g)})
    return pd.DataFrame(out, columns=[*by, *AGREEMENT_COLUMNS])


def agreement_table(
    replayed: pd.DataFrame, reruns: pd.DataFrame, keys: Sequence[str], penalty: float = DEFAULT_PENALTY_M
) -> pd.DataFrame:
    """Per key present in both tables: the replays' count and mean loss, the re-runs' summary, the bias
    and limits of agreement of replay - re-run mean, the share of replays inside the re-runs' 5-95 %
    band (and the share another re-run would reach), and failure rate and coverage of each side with
    their agreement. Keys with no re-runs (or no replays) are left out of the join and reported by
    `unmatched`."""
    keys = list(keys)
    out = agreement_summary(replay_rows(replayed, reruns, keys, penalty), keys)
    return out.merge(rerun_summary(reruns, keys, penalty), on=keys, how="left")


def unmatched(replayed: pd.DataFrame, reruns: pd.DataFrame, keys: Sequence[str]) -> pd.DataFrame:
    """Keys with replays but no re-runs, or re-runs but no replays (`side` says which): left out of
    every agreement figure, and listed, never silently."""
    keys = list(keys)
    a = replayed[keys].drop_duplicates()
    b = reruns[keys].drop_duplicates()
    both = a.merge(b, on=keys, how="outer", indicator=True)
    side = both["_merge"].map({"left_only": "no re-runs", "right_only": "no replays"})
    return both.assign(side=side).loc[both["_merge"] != "both", [*keys, "side"]].reset_index(drop=True)


def kendall_tau(x, y):
    """Kendall's tau-b of two equally long sequences (ties in either counted as in scipy's kendalltau);
    NaN when fewer than two items or when either sequence is constant.

    Arguments:
        x, y: shape (..., n); leading axes are a batch (e.g. bootstrap draws), each row ranked alone.
    Returns:
        A float for 1-D input, else an array of the batch shape.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape != y.shape:
        raise ValueError(f"kendall_tau: x has shape {x.shape} but y {y.shape}")
    i, j = np.triu_indices(x.shape[-1], k=1)
    dx, dy = np.sign(x[..., i] - x[..., j]), np.sign(y[..., i] - y[..., j])
    concordant_minus_discordant = np.sum(dx * dy, axis=-1)
    n_x, n_y = np.sum(dx != 0, axis=-1), np.sum(dy != 0, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = np.where((n_x > 0) & (n_y > 0), concordant_minus_discordant / np.sqrt(n_x * n_y), np.nan)
    return float(tau) if tau.ndim == 0 else tau


def ranking_table(agreement: pd.DataFrame, level_keys: Sequence[str]) -> pd.DataFrame:
    """Per level (e.g. sequence, disturbance, level, switch model): how many rules, Kendall's tau-b between
    the rules' mean replayed loss and mean re-run loss, the rule the replay ranks first (rules it ties for
    first joined by '='), and its regret@1 (its mean re-run loss minus the best mean re-run loss, m; 0
    when the replay picks the best; tied rules share the pick)."""
    rows = []
    for key, part in agreement.groupby(list(level_keys), dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        best = part["replay_loss"] == part["replay_loss"].min()
        rows.append(
            {
                **dict(zip(level_keys, key, strict=True)),
                "rules": len(part),
                "tau": kendall_tau(part["replay_loss"], part["rerun_loss"]),
                "replay_best": "=".join(part.loc[best, "rule"]),
                "rerun_best": part.loc[part["rerun_loss"].idxmin(), "rule"],
                "regret_at_1": float(_regret(part["replay_loss"].to_numpy(), part["rerun_loss"].to_numpy())),
            }
        )
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------------
# Bootstrap intervals


@dataclass(frozen=True)
class Draws:
    """Point estimates and their bootstrap draws.

    Attributes:
        table: one row per unit (a level, a level and baseline), with the point estimate of every
            statistic of `boot` in the column of its name.
        boot: statistic name -> draws of shape [len(table), n_boot] (NaN where a draw leaves it undefined).
    """

    table: pd.DataFrame
    boot: dict[str, np.ndarray]

    def with_ci(self, level: float = 0.95) -> pd.DataFrame:
        """`table` with <statistic>_low and <statistic>_high: percentile intervals of the draws."""
        out = self.table.copy()
        for name, draws in self.boot.items():
            out[f"{name}_low"], out[f"{name}_high"] = _percentiles(draws, level)
        return out


def _percentiles(draws: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) percentile bounds along the last axis, ignoring NaN draws; NaN where all are NaN."""
    alpha = (1.0 - level) / 2.0
    if draws.size == 0:
        return np.full(draws.shape[:-1], np.nan), np.full(draws.shape[:-1], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: NaN, said by the value
        low, high = np.nanquantile(draws, [alpha, 1.0 - alpha], axis=-1)
    return low, high


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN slice is NaN, which is what it means
        return np.nanmean(a, axis=axis)


def pool_draws(draws: Draws, by: Sequence[str], level: float = 0.95) -> pd.DataFrame:
    """Per group of `by`: each statistic's mean over the group's units where it is defined, with the
    interval of that mean over the draws (units resampled independently, so the draws of a group are the
    means of its units' draws), and `units_<statistic>`: how many units entered the mean."""
    by = list(by)
    rows = []
    table = draws.table.reset_index(drop=True)  # positions index the draws' rows
    for key, part in table.groupby(by, dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(by, key, strict=True))
        idx = part.index.to_numpy()
        for name, boot in draws.boot.items():
            point = part[name].to_numpy(np.float64)
            used = np.isfinite(point)
            row[f"units_{name}"] = int(used.sum())
            row[name], low, high = (float("nan"),) * 3
            if used.any():
                row[name] = float(point[used].mean())
                low, high = _percentiles(_nanmean(boot[idx[used]], axis=0), level)
            row[f"{name}_low"], row[f"{name}_high"] = float(low), float(high)
        rows.append(row)
    return pd.DataFrame(rows)


def _rng(seed: int, key) -> np.random.Generator:
    """A generator for one unit: seeded by `seed` and the unit's key, so a unit's draws do not move when
    other units come or go (a sweep that adds settings)."""
    return np.random.default_rng([seed, zlib.crc32(repr(tuple(key)).encode())])


def _mean_draws(values: np.ndarray, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """Means of `n_boot` resamples (with replacement, each of the sample's size) of `values`: [n_boot]."""
    return values[rng.integers(0, len(values), size=(n_boot, len(values)))].mean(axis=1)


def _regret(replay_means: np.ndarray, rerun_means: np.ndarray) -> np.ndarray:
    """Re-run loss of the rule each row's replay ranks first minus the row's best re-run loss: [...].
    Rules the replay ties for first (equal replayed losses, common under switch model `orbslam3`, where
    a rule changes the loss only through LOST) share the pick: their mean re-run loss counts."""
    replay = np.where(np.isnan(replay_means), np.inf, replay_means)
    first = replay <= replay.min(axis=-1, keepdims=True)
    picked = np.sum(np.where(first, rerun_means, 0.0), axis=-1) / np.sum(first, axis=-1)
    return picked - np.min(rerun_means, axis=-1)


def _loss_above_best(rerun_means: np.ndarray, rule: int | None) -> np.ndarray:
    """Re-run loss of rule number `rule` minus the best rule's, per row: [...]; NaN for no rule."""
    if rule is None:
        return np.full(rerun_means.shape[:-1], np.nan)
    return rerun_means[..., rule] - np.min(rerun_means, axis=-1)


def bootstrap_ranking(
    replayed: pd.DataFrame,
    reruns: pd.DataFrame,
    level_keys: Sequence[str],
    *,
    split_by: Sequence[str] = (),
    fitted: str | None = None,
    recording: str = "source",
    n_boot: int = 1000,
    seed: int = 0,
    penalty: float = DEFAULT_PENALTY_M,
) -> Draws:
    """Kendall's tau-b of the rule ranking, regret@1 of the replay's choice and of the fitted rule per
    level, with their bootstrap draws.

    Rank rules on recordings every rule is replayed on (`record`-mode runs): where each rule's replays
    come from other recordings (other rules' runs, never its own), the ranking ranks the recordings.

    Arguments:
        replayed: replays (evaluate's rows) with `level_keys`, `split_by`, rule and `recording` columns.
        reruns: the rules' own runs with `level_keys` and rule.
        level_keys: the columns that name a level in both tables (e.g. setting and switch model).
        split_by: columns of `replayed` only that split a level further (e.g. the recording protocol).
        fitted: the fitted rule's name (its regret@1 is NaN where it has no re-runs at a level).
        recording: the column naming the recording a replay came from (resampled as a unit).
        n_boot, seed: draws per level; each level's generator is seeded by `seed` and its key.

    Returns:
        Draws over one row per level (level keys, split keys, rules: how many have both replays and
        re-runs there, replay_best (rules the replay ties for first joined by '='), rerun_best, tau,
        regret_at_1, fitted_regret (m)). A rule without
        re-runs at a level takes no part in it (`unmatched` lists it); a level with one rule has tau
        NaN. Each draw resamples, per rule, its re-runs and, shared by the rules, the recordings (a
        rule's missing replay of a drawn recording is left out of its mean).
    """
    level_keys, split_by = list(level_keys), list(split_by)
    summary = rerun_summary(reruns, [*level_keys, "rule"], penalty)[[*level_keys, "rule"]]
    rep = replayed.assign(loss=run_loss(replayed, penalty)).merge(summary, on=[*level_keys, "rule"])
    losses = reruns.assign(loss=run_loss(reruns, penalty)).groupby([*level_keys, "rule"])["loss"]
    rows, boot = [], {"tau": [], "regret_at_1": [], "fitted_regret": []}
    for key, part in rep.groupby([*level_keys, *split_by], dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        matrix = part.pivot_table(index=recording, columns="rule", values="loss", aggfunc="mean")
        rules = list(matrix.columns)
        m = matrix.to_numpy(np.float64)  # recordings x rules, NaN where a recording lacks a rule's replay
        level_key = key[: len(level_keys)]
        samples = [losses.get_group((*level_key, r)).to_numpy(np.float64) for r in rules]
        rng = _rng(seed, key)
        replay_draws = _nanmean(m[rng.integers(0, len(m), size=(n_boot, len(m)))], axis=1)
        rerun_draws = np.stack([_mean_draws(s, n_boot, rng) for s in samples], axis=-1)
        replay_means, rerun_means = _nanmean(m, axis=0), np.array([s.mean() for s in samples])
        f = rules.index(fitted) if fitted in rules else None
        rows.append(
            {
                **dict(zip([*level_keys, *split_by], key, strict=True)),
                "rules": len(rules),
                "replay_best": "=".join(
                    r for r, m in zip(rules, replay_means, strict=True) if m == np.nanmin(replay_means)
                ),  # fmt: skip
                "rerun_best": rules[int(np.argmin(rerun_means))],
                "tau": kendall_tau(replay_means, rerun_means),
                "regret_at_1": float(_regret(replay_means, rerun_means)),
                "fitted_regret": float(_loss_above_best(rerun_means, f)),
            }
        )
        boot["tau"].append(kendall_tau(replay_draws, rerun_draws))
        boot["regret_at_1"].append(_regret(replay_draws, rerun_draws))
        boot["fitted_regret"].append(_loss_above_best(rerun_draws, f))
    table = pd.DataFrame(rows, columns=[*level_keys, *split_by, "rules", "replay_best", "rerun_best", *boot])
    return Draws(table, {k: np.array(v).reshape(len(table), n_boot) for k, v in boot.items()})


def deploy_differences(
    reruns: pd.DataFrame,
    fitted: str,
    baselines: Sequence[str],
    level_keys: Sequence[str],
    *,
    n_boot: int = 1000,
    seed: int = 0,
    penalty: float = DEFAULT_PENALTY_M,
) -> Draws:
    """The deploy loop: per level and baseline, the fitted rule's mean re-run loss minus the baseline's
    (m; negative: fitting on replays improved the real system there), with bootstrap draws.

    The two sides of a level are independent runs of the same data (no run pairs with another), so a
    level's difference is a difference of means, drawn by resampling each side's re-runs; levels pair
    the rules (`pool_draws` over levels gives the paired, level-stratified difference).

    Arguments:
        reruns: every rule's own runs (rmse, failed, rule and `level_keys` columns).
        fitted: the fitted rule's name; baselines: the rules it is compared with.
        level_keys: the columns that name a level (e.g. setting and switch model).

    Returns:
        Draws over one row per level where the fitted rule and a baseline both have re-runs: level keys,
        baseline, fitted_runs, baseline_runs, fitted_loss, baseline_loss, diff (m).
    """
    level_keys = list(level_keys)
    t = reruns.assign(loss=run_loss(reruns, penalty))
    rows, boot = [], []
    for key, part in t.groupby(level_keys, dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        mine = part.loc[part["rule"] == fitted, "loss"].to_numpy(np.float64)
        if not len(mine):
            continue
        rng = _rng(seed, key)
        mine_draws = _mean_draws(mine, n_boot, rng)  # one draw of the fitted rule against every baseline
        for base in baselines:
            theirs = part.loc[part["rule"] == base, "loss"].to_numpy(np.float64)
            if not len(theirs):
                continue
            rows.append(
                {
                    **dict(zip(level_keys, key, strict=True)),
                    "baseline": base,
                    "fitted_runs": len(mine),
                    "baseline_runs": len(theirs),
                    "fitted_loss": float(mine.mean()),
                    "baseline_loss": float(theirs.mean()),
                    "diff": float(mine.mean() - theirs.mean()),
                }
            )
            boot.append(mine_draws - _mean_draws(theirs, n_boot, rng))
    columns = [*level_keys, "baseline", "fitted_runs", "baseline_runs", "fitted_loss", "baseline_loss"]
    table = pd.DataFrame(rows, columns=[*columns, "diff"])
    return Draws(table, {"diff": np.array(boot).reshape(len(rows), n_boot)})


# ---------------------------------------------------------------------------------------------------
# Verdict and trust region


def ranking_verdict(pooled: pd.Series) -> tuple[str, str]:
    """The verdict on a pooled ranking row (`pool_draws` of `bootstrap_ranking`, with `max_rules`: the
    most rules any of its levels has): ("trusted" | "not trusted" | "incomplete", a sentence).

    Criteria: a verdict needs a level with at least MIN_RULES_FOR_VERDICT rules and the fitted rule's
    re-runs; it is "trusted" when the interval of the pooled tau lies above 0 (the replay ranks rules
    as the re-runs do, beyond chance) and the upper end of the fitted rule's regret@1 interval is at
    most REGRET_TOLERANCE_M; else "not trusted", naming the criterion that failed.
    """
    tau = f"tau {pooled['tau']:.2f} [{pooled['tau_low']:.2f}, {pooled['tau_high']:.2f}]"
    if not np.isfinite(pooled["tau"]):
        tau = "tau undefined (the replays or the re-runs tie at every level)"
    cm = lambda x: f"{100 * x:.1f}"  # noqa: E731
    regret = (
        f"the fitted rule's regret@1 {cm(pooled['fitted_regret'])} cm "
        f"[{cm(pooled['fitted_regret_low'])}, {cm(pooled['fitted_regret_high'])}]"
    )
    if not pooled.get("max_rules", 0) >= MIN_RULES_FOR_VERDICT:
        return "incomplete", (
            f"at most {int(pooled.get('max_rules', 0))} rules with re-runs at a level (a verdict needs "
            f"{MIN_RULES_FOR_VERDICT}); so far {tau}"
        )
    if not np.isfinite(pooled["tau_low"]):
        return "incomplete", "no level where the rules' re-runs differ (tau undefined)"
    if not np.isfinite(pooled["fitted_regret_high"]):
        return "incomplete", f"no re-runs of the fitted rule yet; so far {tau}"
    ranks = pooled["tau_low"] > 0
    close = pooled["fitted_regret_high"] <= REGRET_TOLERANCE_M
    tolerance = f"{cm(REGRET_TOLERANCE_M)} cm"
    if ranks and close:
        return "trusted", f"replay ranks rules as the re-runs do: {tau}; {regret}, within {tolerance}"
    reasons = [] if ranks else [f"{tau}: its interval reaches 0"]
    reasons += [] if close else [f"{regret}, beyond {tolerance}"]
    return "not trusted", "; ".join(reasons)


def agreement_by_changed_share(
    rows: pd.DataFrame,
    edges: Sequence[float] = CHANGED_SHARE_EDGES,
    *,
    min_in_band_ratio: float = MIN_IN_BAND_RATIO,
    max_abs_bias: float = MAX_ABS_BIAS_M,
    min_replays: int = MIN_REPLAYS_PER_BIN,
    cluster: Sequence[str] = (),
) -> pd.DataFrame:
    """Agreement of replays with re-runs per bin of the replay's changed share.

    Arguments:
        rows: `replay_rows` with `changed_fraction` (share of frames whose replayed state differs from the
            recording's).
        edges: bin edges in [0, 1]; bins are (low, high], the first also holds `low`.
        cluster: columns whose values group replays that share their re-runs (setting, rule, switch
            model): their differences share one re-run mean, so the bias's standard error is
            cluster-robust over these groups; () counts every replay as its own.

    Returns:
        One row per bin: changed_low, changed_high, replays, in_band, expected_in_band,
        in_band_ratio (in_band / expected_in_band), bias and its standard error bias_se (m), and
        evidence: "agrees" (in_band_ratio >= min_in_band_ratio and |bias| - 1.96 bias_se <=
        max_abs_bias), "disagrees", or "too few" (fewer than min_replays replays).
    """
    edges = np.asarray(edges, dtype=np.float64)
    bins = pd.cut(rows["changed_fraction"].astype(float), edges, include_lowest=True)
    out = []
    for k, (low, high) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        part = rows[bins.cat.codes == k]
        n = len(part)
        in_band = float(part["inside"].mean()) if n else float("nan")
        expected = float(part["expected_in_band"].mean()) if n else float("nan")
        bias = float(part["d"].mean()) if n else float("nan")
        se = _cluster_se(part, list(cluster)) if n > 1 else float("nan")
        ratio = in_band / expected if n and expected > 0 else float("nan")
        if n < min_replays:
            evidence = "too few"
        elif ratio >= min_in_band_ratio and abs(bias) - 1.96 * se <= max_abs_bias:
            evidence = "agrees"
        else:
            evidence = "disagrees"
        out.append(
            {"changed_low": low, "changed_high": high, "replays": n, "in_band": in_band,
             "expected_in_band": expected, "in_band_ratio": ratio, "bias": bias, "bias_se": se,
             "evidence": evidence}
        )  # fmt: skip
    return pd.DataFrame(out)


def _cluster_se(rows: pd.DataFrame, cluster: list[str]) -> float:
    """Cluster-robust standard error of the mean of `d` (m): sqrt(G / (G - 1) sum_g e_g^2) / n, e_g the
    sum of a cluster's deviations from the mean (Liang & Zeger 1986, with the small-sample factor); with
    every row its own cluster, the usual sd / sqrt(n)."""
    dev = rows["d"].to_numpy(np.float64) - rows["d"].mean()
    groups = rows.groupby(cluster, dropna=False).ngroup().to_numpy() if cluster else np.arange(len(rows))
    sums = np.bincount(groups, weights=dev)
    g = len(sums)
    if g < 2:
        return float("nan")
    return float(np.sqrt(g / (g - 1) * np.sum(sums**2)) / len(rows))


def trusted_changed_share(bins: pd.DataFrame) -> float:
    """The largest changed share up to which the replay agrees: the upper edge of the last bin that agrees
    before the first bin that disagrees (bins with too few replays neither extend nor end the region).

    Arguments:
        bins: `agreement_by_changed_share`'s table, in order of changed share.
    Returns:
        A share in [0, 1]; 0 when the first bin with evidence disagrees; NaN when no bin has evidence.
    """
    evidence = bins[bins["evidence"] != "too few"]
    if evidence.empty:
        return float("nan")
    trusted = 0.0
    for _, b in evidence.iterrows():
        if b["evidence"] != "agrees":
            break
        trusted = float(b["changed_high"])
    return trusted


def trust_region_warning(
    rule: str, changed_share: float, *, switch_model: str = "orbslam3", threshold: float | None = None
) -> str | None:
    """The sentence `jsve fit` warns with and its report's caveats carry when a rule's replays change more
    decisions than the replay was validated for under its switch model; None inside the region.

    Arguments:
        rule: the rule's name. changed_share: its mean share of frames whose replayed state differs from
            the recording's (`changed_fraction`). switch_model: the replay's. threshold: the share
            trusted (default `trusted_share(switch_model)`).
    """
    limit = trusted_share(switch_model) if threshold is None else threshold
    if not changed_share > limit:
        return None
    return (
        f"`{rule}` changes {100 * changed_share:.1f} % of the recordings' decisions, more than the "
        f"{100 * limit:.1f} % up to which replays under switch model `{switch_model}` agreed with "
        "re-runs of the real ORB-SLAM3 (docs/validation.md): its replayed scores are extrapolated; "
        "re-run it in the front-end before trusting them"
    )
