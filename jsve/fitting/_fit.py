"""Fit a switching rule's weights and thresholds to minimise position error over many logs.

Three stages, all on the same replay (docs/fitting.md):

1. Batched search (jsve.fitting._search): a quasi-random design of thousands of settings (Sobol by default,
   the seed's presets added) evaluated on every run at once; the per-run loss matrix is kept, so that
   cross-validation folds and bootstrap resamples reweight it instead of replaying again.
2. Nelder-Mead on the exact (hard) objective (jsve's own driver, jsve.fitting._simplex, moving many
   simplexes in lockstep), started from the best searched points, in the unconstrained coordinates of
   jsve.fitting._space (so every iterate is a valid rule).
3. Optionally, optimistix BFGS on the relaxed objective (SoftLogic with a temperature, annealed towards
   0; jsve.core._objective), whose result is kept only when the hard objective agrees it is better.

    data = FitData.from_runs(runs)
    result = fit(data, sve_space(), group_weights(data.meta))
    result.rule            # an SVERule; jsve.core._rules.rule_to_dict(result.rule) for JSON
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import jax.numpy as jnp
import numpy as np

from jsve._memory import release_memory
from jsve.fitting._data import FitData, _default_weights
from jsve.fitting._designs import design
from jsve.fitting._halving import RunLossCache, halving_search, rung_sizes, stratified_order
from jsve.fitting._optimise import (
    DEFAULT_TEMPERATURES,
    relaxed_fit,
)
from jsve.fitting._polish import polish_in_lockstep
from jsve.fitting._search import SearchResult
from jsve.fitting._space import ParamSpace, preset_values

log = logging.getLogger(__name__)


def fitted_rule_name(family: str) -> str:
    """The name of a family's fitted rule in every table, beside the presets' names: "fitted-<family>".

    Arguments:
        family: a rule family ("sve" or "inliers", jsve.core's rule kinds).
    Returns:
        "fitted-sve", "fitted-inliers".
    """
    return f"fitted-{family}"


# ---------------------------------------------------------------------------------------------------
# The whole fit


@dataclass(frozen=True)
class FitConfig:
    """How `fit` searches and optimises.

    Attributes:
        design: "sobol", "halton" or "random"; n_search: its number of settings; seed: its seed (and
            the halving's order of runs).
        search: "exhaustive" (every setting on every run), "halving" (successive halving over runs,
            jsve.fitting._halving: all settings on a stratified share `initial_fraction` of the runs,
            the best 1/eta on eta times as many, ..., the last ones on all runs) or "auto" (the
            default: `resolve_search` picks one by the study's size, and halving's initial_fraction).
        include_presets: add the family's presets (and `starts`) to the design.
        n_starts: Nelder-Mead runs, from the best searched settings; nm_steps: their step limit;
            nm_step: initial simplex size in unconstrained coordinates; nm_window, nm_ftol: a run stops
            once nm_window steps improve its best value by at most nm_ftol metres (0: no stall test;
            jsve.fitting._simplex); polish_runs: where more runs
            have weight, Nelder-Mead moves on that many of them (a stratified subset packed into one
            part, jsve.fitting._polish) and its result is judged on all; 0: on every run.
        relaxed: also run the annealed BFGS on the relaxed objective from the best point so far.
        temperatures, bfgs_steps: its schedule (SVE units) and step limit per temperature.
    """

    design: str = "sobol"
    n_search: int = 2048
    seed: int = 0
    search: str = "auto"
    eta: float = 3.0
    initial_fraction: float = 1 / 9
    include_presets: bool = True
    n_starts: int = 2
    nm_steps: int = 200
    nm_step: float = 0.5
    nm_window: int = 25
    nm_ftol: float = 1e-4
    polish_runs: int = 256
    relaxed: bool = False
    temperatures: tuple[float, ...] = DEFAULT_TEMPERATURES
    bfgs_steps: int = 40

    def __post_init__(self):
        if self.search not in SEARCH_METHODS:
            raise ValueError(f"FitConfig.search must be one of {SEARCH_METHODS}, got {self.search!r}")
        if not (isinstance(self.polish_runs, int) and self.polish_runs >= 0):
            raise ValueError(
                f"FitConfig.polish_runs must be a count >= 0 (0: every run), got {self.polish_runs!r}"
            )
        if not (isinstance(self.nm_window, int) and self.nm_window >= 0):
            raise ValueError(
                f"FitConfig.nm_window must be a step count >= 0 (0: no stall test), got {self.nm_window!r}"
            )
        if not self.nm_ftol >= 0:
            raise ValueError(f"FitConfig.nm_ftol must be >= 0 metres, got {self.nm_ftol!r}")
        if self.search == "halving":
            rung_sizes(1, 1, self.eta, self.initial_fraction)  # checks eta > 1, 0 < initial_fraction <= 1


SEARCH_METHODS = ("auto", "exhaustive", "halving")

AUTO_HALVING_RUNS = 300
"""search = "auto": the fewest runs it halves on. On a few hundred runs halving chooses the exhaustive
search's rules but, on a first run, is no faster (its rungs' compilations cost what it saves;
docs/fitting.md), so below 300 runs "auto" is the exhaustive search."""

AUTO_FIRST_RUNG_RUNS = 40
"""search = "auto": the fewest runs the halving's first rung screens every setting on. A first rung of a
few dozen runs already keeps the settings that the exhaustive search (or a larger first rung) would
fit, in the full fit and in every fold, for a fraction of the setting-runs (docs/fitting.md,
"Successive halving")."""


def resolve_search(config: FitConfig, n_runs: int) -> FitConfig:
    """The concrete search of `config` for a study of n_runs runs.

    "auto" becomes the exhaustive search below AUTO_HALVING_RUNS runs, else halving with the smallest
    initial_fraction eta^-K (K >= 1) whose first rung still screens on AUTO_FIRST_RUNG_RUNS runs (the
    exhaustive search where no K >= 1 does); the cost of halving's search is then about (K + 1) / eta^K
    of the exhaustive one's (e.g. 4,000 runs, eta 3: K = 4, f0 = 1/81, about 6 %). "exhaustive" and
    "halving" are returned as given. Resolved on the study's runs (not a fold's), so that every fold
    halves on the same rungs.
    """
    if config.search != "auto":
        return config
    ratio = n_runs / AUTO_FIRST_RUNG_RUNS
    k = math.floor(math.log(ratio) / math.log(config.eta) + 1e-9) if ratio >= 1 else 0
    if k < 1 or n_runs < AUTO_HALVING_RUNS:
        return replace(config, search="exhaustive")
    return replace(config, search="halving", initial_fraction=float(config.eta) ** -k)


@dataclass
class FitResult:
    """A fitted rule and how it was found.

    Attributes:
        space: the ParamSpace. values: [d] fitted free values. rule: the fitted rule.
        objective: hard objective (metres) on the fitting weights; failure_rate, coverage: weighted,
            over the runs the objective includes.
        stages: one dict per stage (search, nelder_mead, relaxed) with its objective and values.
        search: the batched search (per-run matrices), for reuse.
        unsupported_rate: weighted share of the fitting runs on which the fitted rule's replay leaves
            the log's support; n_unsupported: how many runs (of those with weight > 0).
        n_excluded: runs (with weight > 0) dropped from the objective (support="exclude"; else 0).
        cache: under the halving search, the per-run results it computed (cross-validation folds reuse
            them: jsve.fitting._crossval.cross_validate's `caches`); not saved with the study.
        results: the fitted setting's per-run results on every run ([1, R]: `judge`); not saved.
    """

    space: ParamSpace
    values: np.ndarray
    objective: float
    failure_rate: float
    coverage: float
    stages: list[dict]
    search: SearchResult | None = None
    unsupported_rate: float = 0.0
    n_unsupported: int = 0
    n_excluded: int = 0
    cache: RunLossCache | None = None
    results: SearchResult | None = None

    @property
    def rule(self):
        return self.space.rule(jnp.asarray(self.values))

    def params(self) -> dict[str, float]:
        """Every parameter of the rule by name (fixed, then free)."""
        return self.space.params(self.values)


def search_design(space: ParamSpace, config: FitConfig, starts: Sequence[np.ndarray] = ()) -> np.ndarray:
    """The fit's design: config.n_search points of the named design, plus presets and given starts."""
    values = np.asarray(
        space.values_from_unit(design(config.design, config.n_search, space.dim, seed=config.seed))
    )
    extra = list(preset_values(space).values()) if config.include_presets else []
    extra += [np.asarray(s, np.float64) for s in starts]
    if extra:
        values = np.concatenate([values, np.stack(extra)])
    return values


def fit_cache(data: FitData, space: ParamSpace, config: FitConfig) -> RunLossCache:
    """An empty cache of per-run results of the fit's design (search_design) on `data`."""
    return RunLossCache(data.scorer, space, search_design(space, config))


def search_all(data: FitData, space: ParamSpace, values, *, progress: bool = True, desc: str = "search"):
    """Every setting of `values` scored on every run of `data` (its scorer)."""
    return data.scorer.score(space, values, progress=progress, desc=desc)


def fit(
    data: FitData,
    space: ParamSpace,
    weights=None,
    config: FitConfig = FitConfig(),  # noqa: B008
    *,
    search_result: SearchResult | None = None,
    cache: RunLossCache | None = None,
    pool=None,
    progress: bool = True,
) -> FitResult:
    """Fit the free parameters of `space` to minimise the weighted hard objective over `data`.

    Arguments:
        weights: [R] run weights (jsve.evaluation.group_weights; 0 excludes a run, e.g. a held-out fold).
        search_result: a search already run on these data (cross-validation reuses one for all folds).
        cache: under config.search == "halving", per-run results of the fit's design computed so far
            (cross-validation shares one between folds); default a new one.
        pool: [R] the run weights Nelder-Mead's runs are drawn from (a fold: the study's weights, so it
            polishes on the full fit's polish runs less its held-out ones); default `weights`.
    Returns:
        FitResult; its stages record the objective after the search, Nelder-Mead and the relaxed fit.
    """
    w = _default_weights(data, weights)
    config = resolve_search(config, data.n_runs)
    t0 = time.perf_counter()
    if search_result is None:
        search_result, screening, cache = fit_search(data, space, w, config, cache=cache, progress=progress)
        method = config.search
    else:
        screening, method = {}, "given"
    pending = polish(
        data, space, w, search_result, config, method=method, search_seconds=time.perf_counter() - t0,
        screening=screening, pool=pool,
    )  # fmt: skip
    (result,) = judge(data, space, [pending], cache=cache)
    return result


def fit_search(
    data: FitData,
    space: ParamSpace,
    weights: np.ndarray,
    config: FitConfig,
    *,
    cache: RunLossCache | None = None,
    progress: bool = True,
) -> tuple[SearchResult, dict, RunLossCache | None]:
    """The fit's search under run weights: halving (on `cache`, a new one by default) or exhaustive, as
    config.search says once resolved for the study's size.

    Returns:
        (the search: every setting, or halving's survivors, on every run; halving's record of its rungs
        ({} for the exhaustive search); the cache of per-run results, None for the exhaustive search).
    """
    config = resolve_search(config, data.n_runs)
    if config.search != "halving":
        values = search_design(space, config)
        return search_all(data, space, values, progress=progress, desc=f"search {space.kind}"), {}, None
    if cache is None:
        cache = fit_cache(data, space, config)
    elif not np.array_equal(cache.values, search_design(space, config)):
        raise ValueError("fit: the cache holds another design than this fit's (search_design)")
    halving = halving_search(
        cache,
        np.asarray(weights, np.float64),
        eta=config.eta,
        initial_fraction=config.initial_fraction,
        order=stratified_order(data.meta, data.n_runs, seed=config.seed),
        progress=progress,
        desc=f"halving {space.kind}",
    )
    return halving.search, halving.as_dict(), cache


@dataclass
class PolishedFit:
    """A fit before its verdict: its search, its polishes' values, and the stages that record them.

    Attributes:
        weights: [R] the fit's run weights. search: the search it started from.
        stages: the search's, Nelder-Mead's and the relaxed fit's records (their objectives are set by
            `judge`, on every run with weight).
        candidates: (stage index, values [d]): the search's best (stage 0) and each polish's result.
    """

    weights: np.ndarray
    search: SearchResult
    stages: list[dict]
    candidates: list[tuple[int, np.ndarray]]


def polish(
    data: FitData,
    space: ParamSpace,
    weights: np.ndarray,
    search_result: SearchResult,
    config: FitConfig,
    *,
    method: str = "given",
    search_seconds: float = 0.0,
    screening: dict | None = None,
    pool=None,
) -> PolishedFit:
    """Nelder-Mead from the best searched settings (and the relaxed fit from the best so far), each
    moving on its own runs (`polish_runs`, drawn from `pool`); none of them judged on every run yet
    (`judge`)."""
    record = {"method": method, "seconds": search_seconds, **(screening or {})}
    return polish_fits(data, space, [(weights, search_result)], config, records=[record], pool=pool)[0]


def polish_fits(
    data: FitData,
    space: ParamSpace,
    searched: Sequence[tuple[np.ndarray, SearchResult]],
    config: FitConfig,
    *,
    records: Sequence[dict] | None = None,
    pool: np.ndarray | None = None,
    progress: bool = False,
    desc: str | None = None,
) -> list[PolishedFit]:
    """`polish` of many fits at once: the Nelder-Mead runs of all of them (config.n_starts a fit, from
    its search's best settings under its own weights) move in lockstep, each on its own polish runs
    (jsve.fitting._polish.polish_in_lockstep), so each step is one batched search for all of them.

    Arguments:
        searched: (run weights [R], its search) of each fit. records: extra fields of each fit's
            search stage (its method, seconds, halving record); default {"method": "given"}.
        pool: [R] the run weights every fit's polish runs are drawn from (the study's, for
            cross-validation folds: jsve.fitting._polish.polish_runs); default each fit's own.
    Returns:
        One PolishedFit per fit, in order; each Nelder-Mead stage records the lockstep's wall time
        (`seconds`, shared by `simplexes` runs).
    """
    records = list(records) if records is not None else [{"method": "given"}] * len(searched)
    pending, starts = [], []
    for f, ((weights, search_result), record) in enumerate(zip(searched, records, strict=True)):
        w = np.asarray(weights, np.float64)
        obj = search_result.objective(w)
        order = np.argsort(obj, kind="stable")
        best_values, best = search_result.values[order[0]], float(obj[order[0]])
        stage = {"stage": "search", "objective": best, "values": best_values.tolist(), "settings": len(obj),
                 "method": "given", "seconds": 0.0, **record}  # fmt: skip
        log.info("%s search: best %.5f m over %d settings", space.kind, best, len(obj))
        pending.append(PolishedFit(w, search_result, [stage], [(0, np.asarray(best_values, np.float64))]))
        starts += [(f, start) for start in search_result.values[order[: max(config.n_starts, 0)]]]
    release_memory()  # the searches' executables (one per part and rung shape) are not needed again
    if starts:
        ended = polish_in_lockstep(
            data, space, [p.weights for p in pending], starts, n_runs=config.polish_runs, seed=config.seed,
            step=config.nm_step, max_steps=config.nm_steps, window=config.nm_window, ftol=config.nm_ftol,
            pool=pool, progress=progress, desc=desc or f"Nelder-Mead {space.kind}, {len(starts)} simplexes",
        )  # fmt: skip
        counts = dict.fromkeys(range(len(pending)), 0)
        for k, (f, _) in enumerate(starts):
            fit_ = pending[f]
            fit_.candidates.append((len(fit_.stages), ended.values[k]))
            fit_.stages.append(
                {
                    "stage": f"nelder_mead_{counts[f]}",
                    "values": ended.values[k].tolist(),
                    "steps": int(ended.steps[k]),
                    "polish_runs": int(ended.polish_runs[k]),
                    "seconds": ended.seconds,
                    "simplexes": len(starts),
                }
            )
            counts[f] += 1
    if config.relaxed:
        for fit_ in pending:
            t1 = time.perf_counter()
            # from the best candidate so far, judged on every run (it starts where the simplex ended)
            start = judge(data, space, [fit_])[0].values
            values, history = relaxed_fit(
                data,
                space,
                start,
                fit_.weights,
                temperatures=config.temperatures,
                max_steps=config.bfgs_steps,
            )
            seconds = time.perf_counter() - t1
            fit_.candidates.append((len(fit_.stages), values))
            fit_.stages.append(
                {"stage": "relaxed", "values": values.tolist(), "history": history, "seconds": seconds}
            )
    return pending


def judge(
    data: FitData,
    space: ParamSpace,
    fits: Sequence[PolishedFit],
    *,
    cache: RunLossCache | None = None,
    progress: bool = False,
) -> list[FitResult]:
    """The verdict of many fits at once: every candidate of every fit (its search's best and each
    polish's result) scored on every run in one batched search, each fit's setting the candidate with the
    lowest objective on its own weights (ties to the earlier: the search's best before a polish). A
    polish that moved on a subset of the runs is judged on all of them.

    One search of all the distinct candidates fills the kernel's lanes (settings x runs):
    cross-validation's folds are judged together, not one setting per fold and pass over the study
    (docs/fitting.md).

    Returns:
        One FitResult per fit, in order, with `results`: the fitted setting's per-run results on every
        run ([1, R] matrices), which cross-validation scores its held-out runs by.
    """
    values = np.stack([v for f in fits for _, v in f.candidates])
    # Folds often share candidates (the same search best; a polish that ended where it started): each
    # distinct setting is scored once.
    distinct, inverse = np.unique(values, axis=0, return_inverse=True)
    scored = data.scorer.score(
        space,
        distinct,
        progress=progress,
        desc=f"verdict {space.kind}, {len(fits)} fits, {len(distinct)} settings",
    )
    everything = _rows(scored, np.asarray(inverse).reshape(-1))
    out, row = [], 0
    for f in fits:
        rows = np.arange(row, row + len(f.candidates))
        row += len(f.candidates)
        judged = everything.objective(f.weights)[rows]
        stages = [dict(stage) for stage in f.stages]
        best = 0
        for k, (stage, _) in enumerate(f.candidates):
            if stage > 0:
                stages[stage]["objective"] = float(judged[k])
                log.info("%s %s: %.5f m", space.kind, stages[stage]["stage"], judged[k])
            if judged[k] < judged[best]:
                best = k
        final = _rows(everything, rows[best : best + 1])
        w = f.weights
        weighted = w > 0
        n_unsupported = int(np.sum(final.unsupported[0] & weighted))
        n_excluded = int(np.sum(~final.included[0] & weighted))
        if n_unsupported:
            log.info(
                "%s fit: the fitted rule leaves the logs' support on %d of %d runs (%s: %d excluded)",
                space.kind, n_unsupported, int(weighted.sum()), data.config.support, n_excluded,
            )  # fmt: skip
        out.append(
            FitResult(
                space=space,
                values=np.asarray(f.candidates[best][1], np.float64),
                objective=float(final.objective(w)[0]),
                failure_rate=float(final.failure_rate(w)[0]),
                coverage=float(final.coverage_mean(w)[0]),
                stages=stages,
                search=f.search,
                unsupported_rate=float(final.unsupported_rate(w)[0]),
                n_unsupported=n_unsupported,
                n_excluded=n_excluded,
                cache=cache,
                results=final,
            )
        )
    return out


def _rows(result: SearchResult, rows: np.ndarray) -> SearchResult:
    return SearchResult(*(x[rows] for x in result.as_tuple()))


__all__ = [
    "FitConfig",
    "FitResult",
    "fit",
    "fit_search",
    "polish",
    "polish_fits",
    "judge",
    "PolishedFit",
    "search_design",
    "fit_cache",
    "search_all",
    "SEARCH_METHODS",
    "AUTO_FIRST_RUNG_RUNS",
    "AUTO_HALVING_RUNS",
    "resolve_search",
    "fitted_rule_name",
]
