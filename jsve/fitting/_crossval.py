"""Cross-validation, held-out comparison and bootstrap confidence intervals for fitted rules.

Folds are boolean masks of held-out runs: k-fold over runs, or leave-one-group-out over a metadata
column (sequence, disturbance). For every fold each family is fitted on the other runs (jsve.fitting._fit.fit,
reusing one batched search over all runs: a fold only reweights its per-run loss matrix; under the halving
search each fold halves over its training runs on one shared cache of per-run results) and scored on the
held-out runs; the presets are scored on every run. Every run is held out once per fold kind, so the
held-out table compares fitted rules and presets on the same runs, run by run.

Confidence intervals are percentile bootstraps over runs (resampled with replacement, the run weights
kept): for each rule's weighted mean held-out loss, for paired differences against a baseline (the same
resampled runs for both rules), and for the fitted parameters (refitting on each resample; to make that
affordable the refit is the best setting of a dense design around the fit, see `parameter_bootstrap`).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from jsve._memory import release_memory
from jsve.core._objective import run_losses
from jsve.core._rules import BASELINES, PRESETS, preset
from jsve.evaluation._evaluate import OBJECTIVE_COLUMNS
from jsve.fitting._data import FitData
from jsve.fitting._designs import sobol
from jsve.fitting._fit import (
    FitConfig,
    FitResult,
    fit_cache,
    fit_search,
    fitted_rule_name,
    judge,
    polish_fits,
    resolve_search,
    search_all,
    search_design,
)
from jsve.fitting._halving import RunLossCache, halving_searches, stratified_order
from jsve.fitting._search import RESULT_FIELDS, SearchResult
from jsve.fitting._space import ParamSpace, is_space_point, preset_point

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Fold:
    """One split: `test` marks the held-out runs ([R] bool, data order)."""

    kind: str
    name: str
    test: np.ndarray


def kfold(n_runs: int, k: int, *, seed: int = 0) -> list[Fold]:
    """k folds of (nearly) equal size over randomly permuted runs (deterministic under the seed)."""
    if not 2 <= k <= n_runs:
        raise ValueError(f"k-fold needs 2 <= k <= number of runs ({n_runs}), got k={k}")
    order = np.random.default_rng(seed).permutation(n_runs)
    folds = []
    for i, held in enumerate(np.array_split(order, k)):
        test = np.zeros(n_runs, bool)
        test[held] = True
        folds.append(Fold("kfold", f"fold {i + 1}/{k}", test))
    return folds


def leave_one_out(meta: pd.DataFrame, column: str) -> list[Fold]:
    """One fold per value of a metadata column (leave-one-sequence-out, leave-one-disturbance-out)."""
    if column not in meta.columns:
        raise ValueError(f"leave_one_out: metadata has no column {column!r}; has {list(meta.columns)}")
    values = meta[column].astype(str).to_numpy()
    groups = sorted(set(values))
    if len(groups) < 2:
        raise ValueError(f"leave-one-{column}-out needs at least 2 values of {column!r}, got {groups}")
    return [Fold(f"leave-one-{column}-out", g, values == g) for g in groups]


# ---------------------------------------------------------------------------------------------------
# Bootstrap


def bootstrap_weighted_mean(
    values,
    weights=None,
    *,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
    index: np.ndarray | None = None,
) -> tuple[float, float, float]:
    """Weighted mean of `values` and its percentile bootstrap interval over resampled runs.

    Arguments:
        values: [R] per-run values (NaN not allowed: failed runs carry their penalty).
        weights: [R] run weights (default 1).
        index: [n_boot, R] resampled run indices to use (paired comparisons share them); drawn from the
            seed when None.
    Returns:
        (mean, low, high); low = high = NaN for fewer than 2 runs.
    """
    x = np.asarray(values, np.float64)
    w = np.ones_like(x) if weights is None else np.asarray(weights, np.float64)
    if np.isnan(x).any():
        raise ValueError("bootstrap_weighted_mean: values contain NaN")
    mean = float(np.sum(w * x) / np.sum(w))
    if x.size < 2:
        return mean, float("nan"), float("nan")
    if index is None:
        index = np.random.default_rng(seed).integers(0, x.size, size=(n_boot, x.size))
    ws = w[index]
    boot = np.sum(ws * x[index], axis=1) / np.maximum(np.sum(ws, axis=1), 1e-300)
    alpha = (1 - level) / 2
    low, high = np.quantile(boot, [alpha, 1 - alpha])
    return mean, float(low), float(high)


# ---------------------------------------------------------------------------------------------------
# Cross-validation


@dataclass
class CrossValidation:
    """Held-out results.

    Attributes:
        heldout: one row per (fold kind, run, rule): run metadata, fold_kind, fold, rule, weight, loss,
            rmse (NaN where failed), failed, coverage, unsupported (the rule's replay left the log's
            support), included. Under support="exclude" a pair that is not included has a NaN loss:
            `compare` then scores every rule on the runs all of them support. Fitted rules are named by
            `fitted_rule_name` ("fitted-<family>").
        params: one row per (fold kind, fold, family): the fitted parameter values and training objective.
    """

    heldout: pd.DataFrame
    params: pd.DataFrame


def rule_results(data: FitData, space: ParamSpace, values) -> SearchResult:
    """Per-run results of one setting (free values in `space`) on every run: [1, R] matrices."""
    return data.scorer.score(space, np.asarray(values, np.float64)[None])


_run_losses = eqx.filter_jit(run_losses)


def preset_results(
    data: FitData,
    names: Sequence[str],
    *,
    known: Mapping[str, SearchResult] | None = None,
    progress: bool = False,
) -> dict[str, SearchResult]:
    """Per-run results of presets by name: those in `known` as given (`objective_results` of an
    evaluation that scored the objective), by the search kernel where a preset is a point of its
    family's space, else by the replay objective (jsve.core._objective.run_losses), which scores any
    rule, on one pass over the parts' slim batches (FitData.iter_slim: streamed again where they were
    not kept)."""
    known = dict(known or {})
    out = {name: known[name] for name in names if name in known}
    out |= {name: rule_results(data, *preset_point(name)) for name in names
            if name not in out and is_space_point(preset(name))}  # fmt: skip
    others = [name for name in names if name not in out]
    per_part = {name: [] for name in others}
    if others:
        parts = tqdm(
            data.iter_slim(), total=len(data.parts), desc=f"replay {', '.join(others)}", unit="part",
            disable=not progress,
        )  # fmt: skip
        for batch, features, n in parts:
            for name in others:
                losses = _run_losses(batch, preset(name), features, data.config)
                per_part[name].append(jax.tree.map(lambda x, n=n: np.asarray(x)[:n], losses))
    for name in others:
        losses = jax.tree.map(lambda *xs: np.concatenate(xs)[None], *per_part[name])
        out[name] = SearchResult(
            values=np.zeros((1, 0)), loss=losses.loss, failed=losses.failed,
            rmse=np.where(losses.failed, np.nan, losses.rmse), coverage=losses.coverage,
            unsupported=losses.unsupported, included=losses.included > 0.5,
        )  # fmt: skip
    return {name: out[name] for name in names}


def objective_results(
    runs: pd.DataFrame, meta: pd.DataFrame, names: Sequence[str]
) -> dict[str, SearchResult]:
    """[1, R] per-run results of the rules `names` from a per-run evaluation table that carries the
    objective's terms (jsve.evaluation._evaluate.OBJECTIVE_COLUMNS), in the run order of `meta` (by
    run_id): what `preset_results` would compute, without replaying. Rules the table lacks, or a table
    without those columns, give nothing; a rule the table holds for only some of the runs is an error.
    """
    if not set(OBJECTIVE_COLUMNS) <= set(runs.columns) or "run_id" not in meta.columns:
        return {}
    out = {}
    ids = meta["run_id"].astype(str).to_numpy()
    for name in names:
        rows = runs[runs["rule"] == name]
        if rows.empty:
            continue
        rows = rows.set_index(rows["run_id"].astype(str))
        if missing := [rid for rid in ids if rid not in rows.index]:
            raise ValueError(
                f"the evaluation table scores {name!r} on {len(rows)} runs and lacks {len(missing)} of the "
                f"study's (first: {missing[0]})"
            )
        rows = rows.loc[ids]
        column = lambda c, dtype, rows=rows: rows[c].to_numpy(dtype)[None]  # noqa: E731
        out[name] = SearchResult(
            values=np.zeros((1, 0)), loss=column("objective_loss", np.float64),
            failed=column("objective_failed", bool), rmse=column("objective_rmse", np.float64),
            coverage=column("objective_coverage", np.float64),
            unsupported=column("objective_unsupported", bool), included=column("objective_included", bool),
        )  # fmt: skip
    return out


def cross_validate(
    data: FitData,
    spaces: Mapping[str, ParamSpace],
    folds: Sequence[Fold],
    weights=None,
    config: FitConfig = FitConfig(),  # noqa: B008
    *,
    presets: Sequence[str] = PRESETS,
    searches: Mapping[str, SearchResult] | None = None,
    caches: Mapping[str, RunLossCache] | None = None,
    replayed: Mapping[str, SearchResult] | None = None,
    progress: bool = True,
) -> CrossValidation:
    """Fit every family on each fold's training runs and score it, and the presets, on its held-out runs.

    Arguments:
        spaces: family name -> ParamSpace (e.g. {"sve": sve_space(), "inliers": inlier_space()}).
        folds: from `kfold` / `leave_one_out` (any mix of kinds).
        weights: [R] run weights (default 1); training uses them, the held-out table carries them.
        searches: batched searches over all runs already done (by family name), reused by the
            exhaustive search (config.search == "exhaustive").
        caches: per-run results of the halving search already computed (by family name; FitResult.cache
            of the fit on all runs, whose design is the folds'), reused and filled by the halving search.
        replayed: per-run results of presets already scored on every run (`objective_results` of the
            study's evaluation), used instead of replaying them again (`preset_results`).
    """
    w = np.ones(data.n_runs) if weights is None else np.asarray(weights, np.float64)
    config = resolve_search(config, data.n_runs)  # the full fit's rungs, which the folds' caches hold
    meta = data.meta.reset_index(drop=True)
    searches = dict(searches or {})
    caches = dict(caches or {})
    screened = {}  # family -> one halving result per fold
    for name, space in spaces.items():
        if config.search == "halving":
            # Each fold halves over its own training runs (screening on held-out runs would leak them into
            # the fit). The folds halve in step on one cache of per-run results (the full fit's where
            # given): a (setting, run) pair is scored once whichever folds need it, and each rung's new
            # pairs for all folds are one batch of kernel calls.
            if name not in caches and RunLossCache.fits(len(search_design(space, config)), data.n_runs):
                caches[name] = fit_cache(data, space, config)
            if name in caches:
                screened[name] = halving_searches(
                    caches[name],
                    [w * ~fold.test for fold in folds],
                    eta=config.eta,
                    initial_fraction=config.initial_fraction,
                    order=stratified_order(data.meta, data.n_runs, seed=config.seed),
                    progress=progress,
                    desc=f"halving {name}, {len(folds)} folds",
                )
            else:
                log.info("cross-validation of %s: per-run results do not fit memory, folds halve alone", name)
        elif name not in searches:
            searches[name] = search_all(
                data, space, search_design(space, config), progress=progress, desc=f"search {name}"
            )
    per_rule = preset_results(data, presets, known=replayed, progress=progress)

    # Each fold's fit polishes on the full fit's polish runs less its held-out ones (pool=w); all folds
    # of a family move in lockstep (each Nelder-Mead step is one batched search for all of them,
    # `polish_fits`); then all folds of a family are judged on every run in one batched search, whose
    # rows also hold each fold's fitted rule on its held-out runs (`judge`).
    polished = {}
    for name, space in spaces.items():
        searched = []
        for k, fold in enumerate(folds):
            train = w * ~fold.test
            if not np.any(train > 0):
                raise ValueError(f"fold {fold.kind}/{fold.name} leaves no training run")
            search_result = _fold_search(name, k, screened, searches, config)
            if search_result is None:  # the fold searches alone (per-run results do not fit memory)
                search_result = fit_search(data, space, train, config, progress=False)[0]
            searched.append((train, search_result))
        polished[name] = polish_fits(
            data, space, searched, config, pool=w, progress=progress,
            desc=f"Nelder-Mead {name}, {len(folds)} folds x {config.n_starts} starts",
        )  # fmt: skip
        release_memory()  # the polishes' executables (jsve._memory)
    fits = {name: judge(data, spaces[name], polished[name], progress=progress) for name in spaces}

    rows, params = [], []
    for k, fold in enumerate(folds):
        fitted = {}
        for name in spaces:
            result = fits[name][k]
            fitted[fitted_rule_name(name)] = result.results
            params.append(
                {
                    "fold_kind": fold.kind,
                    "fold": fold.name,
                    "family": name,
                    "train_objective": result.objective,
                    **result.params(),
                }
            )
        for rule, res in {**fitted, **per_rule}.items():
            held = np.flatnonzero(fold.test)
            table = meta.iloc[held].copy()
            table.insert(0, "run_index", held)
            table["fold_kind"], table["fold"], table["rule"] = fold.kind, fold.name, rule
            table["weight"] = w[held]
            for key in ("loss", "rmse", "failed", "coverage", "unsupported", "included"):
                table[key] = getattr(res, key)[0, held]
            table["loss"] = table["loss"].where(table["included"])
            rows.append(table)
    return CrossValidation(heldout=pd.concat(rows, ignore_index=True), params=pd.DataFrame(params))


def _fold_search(name: str, k: int, screened: dict, searches: dict, config: FitConfig) -> SearchResult | None:
    """The search fold k's fit of family `name` starts from: its halving survivors, the exhaustive search
    over all runs, or None (the fit halves alone; never a search whose survivors saw held-out runs)."""
    if name in screened:
        return screened[name][k].search
    return searches.get(name) if config.search == "exhaustive" else None


def _weighted_mean(values: pd.Series, weight: np.ndarray) -> float:
    """sum w x / sum w of a column (booleans as 0 / 1); NaN without runs."""
    if not len(values):
        return float("nan")
    return float(np.sum(weight * values.to_numpy(np.float64)) / np.sum(weight))


def compare(
    heldout: pd.DataFrame,
    *,
    baselines: Sequence[str] = tuple(BASELINES.values()),
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> pd.DataFrame:
    """Held-out comparison per fold kind: every rule's weighted mean loss with a bootstrap CI, its failure
    rate and coverage, and its paired difference to each baseline (negative: better than the baseline).

    The bootstrap resamples runs (one set of resamples per fold kind, shared by all rules: paired). Only
    runs every rule was scored on count (a NaN loss, a pair excluded for leaving the log's support,
    drops the run for every rule); `n_runs` says how many. `unsupported` is each rule's weighted share of
    all the fold kind's runs on which its replay left the log's support (when the table says).
    """
    out = []
    for kind, part in heldout.groupby("fold_kind", sort=False):
        pivot = lambda col, p=part: p.pivot_table(  # noqa: E731
            index="run_index", columns="rule", values=col, aggfunc="first", dropna=False
        )
        wide, fail, cov = pivot("loss"), pivot("failed"), pivot("coverage")
        all_weight = part.groupby("run_index")["weight"].first()
        unsupported = pivot("unsupported") if "unsupported" in part else None
        wide = wide.dropna(axis=0)  # runs every rule was scored on
        weight = all_weight.reindex(wide.index).to_numpy()
        index = np.random.default_rng(seed).integers(0, max(len(wide), 1), size=(n_boot, len(wide)))
        for rule in wide.columns:
            x = wide[rule].to_numpy()
            if len(x):
                mean, low, high = bootstrap_weighted_mean(x, weight, index=index, level=level)
            else:  # no run is supported by every rule (support="exclude")
                mean = low = high = float("nan")
            row = {
                "fold_kind": kind,
                "rule": rule,
                "n_runs": len(x),
                "mean_loss": mean,
                "ci_low": low,
                "ci_high": high,
                "failure_rate": _weighted_mean(fail.loc[wide.index, rule], weight),
                "coverage": _weighted_mean(cov.loc[wide.index, rule], weight),
            }
            if unsupported is not None:
                row["unsupported"] = _weighted_mean(
                    unsupported[rule], all_weight.reindex(unsupported.index).to_numpy()
                )
            for base in baselines:
                if base in wide.columns and base != rule and len(x):
                    d, dl, dh = bootstrap_weighted_mean(
                        x - wide[base].to_numpy(), weight, index=index, level=level
                    )
                    row[f"diff_vs_{base}"], row[f"diff_vs_{base}_ci_low"], row[f"diff_vs_{base}_ci_high"] = (
                        d,
                        dl,
                        dh,
                    )
            out.append(row)
    return pd.DataFrame(out)


# ---------------------------------------------------------------------------------------------------
# Parameters


def local_design(space: ParamSpace, center, n: int, *, fraction: float = 0.15, seed: int = 0) -> np.ndarray:
    """n Sobol points in the box of half-width `fraction` x each parameter's range around `center`,
    clipped to the space's box."""
    lo, hi = np.asarray(space.lo), np.asarray(space.hi)
    half = fraction * (hi - lo)
    a = np.maximum(lo, np.asarray(center) - half)
    b = np.minimum(hi, np.asarray(center) + half)
    return a + (b - a) * sobol(n, space.dim, seed=seed)


def plausible_winners(
    loss: np.ndarray, weights: np.ndarray, n_eff_full: float, *, z: float = 4.0
) -> np.ndarray:
    """Which settings could win a bootstrap resample of the whole study, judged on a subset of its runs.

    A setting s beats the fit (row -1) on a resample of the study only where its paired mean difference
    d_s = loss_s - loss_fit comes out below 0; over resamples that difference has a spread of about
    sd_s / sqrt(n_eff_full). Its mean is estimated on the subset to within sd_s / sqrt(n_eff_subset).
    A setting is kept unless even the optimistic end of its subset estimate is more than z resampling
    spreads above 0:  mean_s - z sd_s / sqrt(n_subset) <= z sd_s / sqrt(n_full).  With z = 4 a
    setting that is dropped wins a resample with a chance of the order of 1e-5 (normal tails),
    the screen of a race (Maron & Moore 1994, "Hoeffding races").

    Arguments:
        loss: [S, m] per-run losses on the subset's runs, the fit in the last row.
        weights: [m] the subset's run weights (> 0).
        n_eff_full: the effective number of runs of the whole study, (sum w)^2 / sum w^2.
        z: the screen's width in standard errors.
    Returns:
        [S] bool, the fit's row always True.
    """
    w = np.asarray(weights, np.float64) / np.sum(weights)
    d = np.asarray(loss, np.float64) - np.asarray(loss, np.float64)[-1]
    mean = d @ w
    sd = np.sqrt(np.maximum(((d - mean[:, None]) ** 2) @ w, 0.0))
    n_eff_subset = 1.0 / np.sum(w**2)
    keep = mean - z * sd / np.sqrt(n_eff_subset) <= z * sd / np.sqrt(n_eff_full)
    keep[-1] = True
    return keep


def effective_runs(weights: np.ndarray) -> float:
    """Kish's effective number of runs of a weighting: (sum w)^2 / sum w^2."""
    w = np.asarray(weights, np.float64)
    return float(np.sum(w) ** 2 / np.sum(w**2))


RACE_ETA = 3
"""Growth of the bootstrap race's prefix of runs from rung to rung (`bootstrap_race`)."""

TIE_RTOL = 1e-9
"""Objectives within this relative distance of a resample's best are ties (`resample_winners`): settings
with the same decisions on every run have the same per-run losses, and so means equal up to rounding."""


def resample_winners(objective: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Each bootstrap resample's refit: the setting with the lowest objective, a tie drawn at random.

    The hard objective is piecewise constant, so many settings of a design tie on a plateau (they take
    the same decisions on every run). Taking the first of them, as argmin does, picked the fit itself in
    every resample (it comes first) and gave intervals of zero width on a plateau, hiding that the data
    cannot tell those settings apart. A tie is broken by a key drawn from each setting's values and the
    resample's index, so the choice is uniform over the tied settings and does not depend on their
    order or on which other settings were scored (a screened design refits as the full one).

    Arguments:
        objective: [n_boot, S] each setting's objective under each resample's weights.
        values: [S, d] the settings.
    Returns:
        [n_boot] the index of each resample's setting.
    """
    best = objective.min(axis=1, keepdims=True)
    tied = objective <= best + TIE_RTOL * np.maximum(np.abs(best), 1e-300)
    keys = np.stack([_tie_keys(v, len(objective)) for v in np.asarray(values, np.float64)], axis=1)
    return np.argmin(np.where(tied, keys, np.inf), axis=1)


def _tie_keys(values: np.ndarray, n: int) -> np.ndarray:
    """n uniform keys seeded by a setting's values (its bytes): the same setting, the same keys."""
    seed = int.from_bytes(hashlib.sha256(np.ascontiguousarray(values).tobytes()).digest()[:8], "little")
    return np.random.default_rng(seed).random(n)


def bootstrap_race(
    data: FitData,
    space: ParamSpace,
    local: np.ndarray,
    weights: np.ndarray,
    screen_runs: int,
    *,
    seed: int = 0,
    progress: bool = False,
) -> tuple[SearchResult, list[int]]:
    """The settings of `local` (the fit in the last row) that could win a bootstrap resample of the whole
    study, scored on every run, found by a race over growing prefixes of the study's stratified order.

    Rung k scores the settings still in the race on the runs of the first screen_runs x RACE_ETA^k
    weighted runs that the earlier rungs did not score (packed by length class), then drops those that
    cannot win on the prefix (`plausible_winners`); the survivors of the last rung are scored on the
    remaining runs. A prefix tells a setting's loss from the fit's more precisely than the one before
    it (its standard error falls as 1/sqrt(runs)), so each rung drops settings the first could not: the
    share of the design scored on every run falls with the study's size instead of staying fixed.
    screen_runs 0, at least the weighted runs, or a single setting (nothing to drop): every setting on
    every run.

    Returns:
        (the surviving settings' results on every run, the settings in the race at each rung and at the
        end: [len(local), ...]).
    """
    w = np.asarray(weights, np.float64)
    ordered = stratified_order(data.meta, data.n_runs, seed=seed)
    ordered = ordered[w[ordered] > 0]
    if not 0 < screen_runs < len(ordered) or len(local) == 1:
        everything = data.scorer.score(space, local, progress=progress, desc=f"bootstrap design {space.kind}")
        return everything, [len(local)]
    n_full = effective_runs(w[w > 0])
    fields = dict.fromkeys(RESULT_FIELDS)  # SearchResult's matrices, filled rung by rung
    keep = np.arange(len(local))
    kept, done, prefix = [len(local)], np.zeros(data.n_runs, bool), screen_runs

    def score(runs: np.ndarray, desc: str) -> None:
        columns = np.unique(runs)
        piece = data.scorer.score(space, local[keep], columns, progress=progress, desc=desc)
        for name in fields:
            block = getattr(piece, name)
            if fields[name] is None:
                fields[name] = np.zeros((len(local), data.n_runs), block.dtype)
            fields[name][np.ix_(keep, columns)] = block
        done[columns] = True

    while prefix < len(ordered):
        runs = ordered[:prefix]
        score(runs[~done[runs]], f"bootstrap race {space.kind}, {prefix:,} runs")
        columns = np.sort(runs)
        survive = plausible_winners(fields["loss"][np.ix_(keep, columns)], w[columns], n_full)
        keep = keep[survive]
        kept.append(len(keep))
        log.info("bootstrap %s: %d of %d local settings could win a resample (%d runs)",
                 space.kind, len(keep), len(local), prefix)  # fmt: skip
        prefix *= RACE_ETA
    score(np.flatnonzero(~done), f"bootstrap design {space.kind}")
    return SearchResult(local[keep], *(fields[name][keep] for name in fields)), kept


def parameter_bootstrap(
    data: FitData,
    space: ParamSpace,
    result: FitResult,
    weights=None,
    *,
    n_local: int = 1024,
    fraction: float = 0.15,
    n_boot: int = 500,
    level: float = 0.95,
    seed: int = 0,
    screen_runs: int = 0,
    progress: bool = True,
) -> pd.DataFrame:
    """Bootstrap confidence intervals of the fitted parameters.

    Each resample of runs (with replacement, weights kept) is refitted by taking the best setting, under
    the resample's weights, of the fit's own search design plus a dense local design around the fit and
    the fit itself: a refit that costs a matrix-vector product. Its resolution is the local design's
    (n_local points in a box of +-fraction of each range); with n_local 0 there is none, and a refit
    chooses between the search's settings (under halving, its last rung's survivors) and the fit: a
    coarse interval (the default study's), at the cost of scoring the fit on every run.

    screen_runs: where more runs have weight, the local design races over growing prefixes of the
    study's stratified order, from screen_runs runs (`bootstrap_race`), and only the settings that could
    still win a resample of the whole study (`plausible_winners`) are scored on every run; 0: every
    setting on every run. The bootstrap itself is always over every run.

    Returns:
        One row per free parameter: parameter, value (the fit), ci_low, ci_high, boot_std, n_boot,
        local (settings of the local design, the fit included), local_scored (those scored on every
        run) and race (the settings in the race at each rung, "1025>831>540"), plus the same for the
        derived simplex weights (weight_a, weight_b, weight_c) of an SVE fit.
    """
    w = np.ones(data.n_runs) if weights is None else np.asarray(weights, np.float64)
    around = [local_design(space, result.values, n_local, fraction=fraction, seed=seed)] if n_local else []
    local = np.concatenate([*around, result.values[None]])
    n_local_design = len(local)
    res, kept = bootstrap_race(data, space, local, w, screen_runs, seed=seed, progress=progress)
    if result.search is not None:
        res = result.search.concat(res)
    rng = np.random.default_rng(seed)
    n = data.n_runs
    counts = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(n_boot)]).astype(
        np.float64
    )
    objective = res.objective(counts * w[None])  # [n_boot, S]
    picks = res.values[resample_winners(objective, res.values)]  # [n_boot, d]
    names, fitted = list(space.names), list(result.values)
    derived = space.derived(picks)
    if derived:
        picks = np.concatenate([picks, np.stack(list(derived.values()), -1)], axis=1)
        fitted += list(np.stack(list(space.derived(result.values).values()), -1))
        names += list(derived)
    alpha = (1 - level) / 2
    low, high = np.quantile(picks, [alpha, 1 - alpha], axis=0)
    return pd.DataFrame(
        {
            "family": space.kind,
            "parameter": names,
            "value": fitted,
            "ci_low": low,
            "ci_high": high,
            "boot_std": picks.std(axis=0),
            "n_boot": n_boot,
            "local": n_local_design,
            "local_scored": len(res.values) - (0 if result.search is None else len(result.search.values)),
            "race": ">".join(str(k) for k in kept),
        }
    )


__all__ = [
    "Fold",
    "kfold",
    "leave_one_out",
    "bootstrap_weighted_mean",
    "CrossValidation",
    "cross_validate",
    "compare",
    "local_design",
    "parameter_bootstrap",
    "plausible_winners",
    "bootstrap_race",
    "resample_winners",
    "effective_runs",
    "rule_results",
    "objective_results",
    "preset_results",
]
