"""Multi-fidelity search: successive halving over runs, on a cache of per-run losses.

The exhaustive search (jsve.fitting._search.search) scores every setting of a design on every run. Most
settings are clearly worse than the best after a fraction of the runs, so successive halving (Jamieson &
Talwalkar 2016, "Non-stochastic best arm identification and hyperparameter optimization") scores all
settings on a stratified random subset of the runs, keeps the best 1/eta of them, scores those on eta
times as many runs, and so on until the survivors are scored on every run:

    rung k:  ceil(S / eta^k) settings  x  min(1, f0 eta^k) of the runs        (k = 0 .. K, the last: all)

At f0 = 1/eta^K every rung costs about S R / eta^K setting-runs, so the search costs (K + 1) / eta^K of
the exhaustive one (eta = 3, f0 = 1/9: a third). Every rung uses the fit's own objective: the same
fused kernel (jsve.fitting._search.search, run on a sub-batch of the runs), the same run weights and
the same included-run mean (SearchResult.objective: penalised losses, the support policy). With f0 = 1
there is one rung over all runs and the result is the exhaustive search's, exactly.

The subsets are prefixes of one seeded order of the runs, stratified by group (sequence, disturbance,
level where the metadata has them): a random permutation within each group, then one run of every
group in turn (groups in a random order), so every prefix is as balanced over the groups as its length
allows. Nested prefixes mean a rung re-scores its survivors only on the runs the previous rung did not
score them on.

`RunLossCache` keeps every (setting, run) result computed so far ([S, R] arrays and a mask), so that
cross-validation folds, each halving over its own training runs (in the same global order, held-out
runs skipped), recompute only the pairs no fold has scored yet: the per-run losses are scored once,
and each fold's objective is a weighted sum of them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from jsve._memory import release_memory
from jsve.fitting._scorer import Scorer
from jsve.fitting._search import RESULT_FIELDS, SearchResult

log = logging.getLogger(__name__)

STRATA = ("sequence", "disturbance", "level")
"""Metadata columns whose groups stratify the halving's subsets of runs (those the metadata has)."""

MAX_CACHE_BYTES = 2 * 1024**3
"""Largest per-run result cache (settings x runs x ~14 bytes) kept across folds; above it every fold
halves on its own (the same results, recomputed)."""


def stratified_order(meta: pd.DataFrame | None, n_runs: int, *, seed: int = 0, strata=STRATA) -> np.ndarray:
    """A seeded order of the runs [R] whose every prefix is as balanced over the groups as it can be.

    Arguments:
        meta: one row per run (data order); its `strata` columns that exist define the groups (none:
            one group, a plain permutation).
        seed: numpy Generator seed.
    Returns:
        [R] run indices: within each group a random permutation, then one run of each group in turn
        (the groups in a random order), groups that run out dropping out of the turn.
    """
    rng = np.random.default_rng(seed)
    columns = [c for c in strata if meta is not None and c in meta.columns]
    if columns:
        # Each column as text, joined column by column (a row-wise join is slow in pandas, and a
        # cross-validation orders runs a dozen times); the same keys, so the same groups.
        text = meta[columns].astype(str)
        keys = text[columns[0]].to_numpy(dtype=object)
        for column in columns[1:]:
            keys = keys + "\x1f" + text[column].to_numpy(dtype=object)
        _, group = np.unique(keys, return_inverse=True)
    else:
        group = np.zeros(n_runs, int)
    if len(group) != n_runs:
        raise ValueError(f"stratified_order: meta has {len(group)} rows but there are {n_runs} runs")
    members = [rng.permutation(np.flatnonzero(group == g)) for g in range(group.max(initial=-1) + 1)]
    turn = rng.permutation(len(members))
    depth = max((len(m) for m in members), default=0)
    return np.asarray([members[g][i] for i in range(depth) for g in turn if i < len(members[g])], np.int64)


@dataclass
class RunLossCache:
    """Per-run results of a fixed design's settings, filled on demand by a scorer.

    Attributes:
        scorer: what scores settings on runs (jsve.fitting._scorer.Scorer).
        values: [S, d] the design (free values of `space`).
        known: [S, R] which pairs are computed; the SearchResult fields [S, R] hold them (undefined
            elsewhere).
        evaluations: setting-runs this cache had computed (the cost, in the kernel's unit).
    """

    scorer: Scorer
    space: object
    values: np.ndarray
    arrays: dict = field(default_factory=dict)
    known: np.ndarray | None = None
    evaluations: int = 0

    @property
    def n_runs(self) -> int:
        return int(self.scorer.n_runs)

    @staticmethod
    def fits(n_settings: int, n_runs: int, max_bytes: int = MAX_CACHE_BYTES) -> bool:
        """Whether a cache of n_settings x n_runs stays under max_bytes (float64 loss, rmse, coverage;
        4 flags and the mask: 28 bytes a pair at most)."""
        return n_settings * n_runs * 28 <= max_bytes

    def fill(self, settings: np.ndarray, runs: np.ndarray, *, progress: bool = False, desc: str = "") -> None:
        """Compute the pairs (settings x runs) not yet known (fill_pairs of that rectangle)."""
        need = np.zeros((len(self.values), self.n_runs), bool)
        need[np.ix_(np.asarray(settings, np.int64), np.asarray(runs, np.int64))] = True
        self.fill_pairs(need, progress=progress, desc=desc)

    def fill_pairs(self, need: np.ndarray, *, progress: bool = False, desc: str = "") -> None:
        """Compute the pairs of the [S, R] mask `need` not yet known; a pair already known is never
        overwritten (so a result never changes once read).

        The kernel scores rectangles (settings x runs), so the missing pairs are covered by at most two:
        the settings that miss most of the missing runs (new survivors: all of them), and the settings
        that miss a few (runs other searches did not screen them on: the union of those). Within one
        halving the missing pairs are one rectangle exactly (every survivor misses the rung's new runs);
        for folds halving together the split keeps the few-missing settings off the many-missing runs.
        """
        if self.known is None:
            self.known = np.zeros((len(self.values), self.n_runs), bool)
        missing = np.asarray(need, bool) & ~self.known
        rows = np.flatnonzero(missing.any(axis=1))
        if not len(rows):
            return
        counts = missing[rows].sum(axis=1)
        many = 2 * counts > missing[rows].any(axis=0).sum()
        for group in (rows[many], rows[~many]):
            if len(group):
                self._compute(group, np.flatnonzero(missing[group].any(axis=0)), progress, desc)

    def _compute(self, settings: np.ndarray, runs: np.ndarray, progress: bool, desc: str) -> None:
        """Score settings x runs and store the pairs not known yet."""
        columns = np.unique(np.asarray(runs, np.int64))
        res = self.scorer.score(
            self.space, self.values[settings], columns, progress=progress, desc=desc or "search"
        )
        self.evaluations += len(settings) * len(columns)
        block = np.ix_(settings, columns)
        new = ~self.known[block]
        for name in RESULT_FIELDS:
            x = getattr(res, name)
            if name not in self.arrays:
                self.arrays[name] = np.zeros((len(self.values), self.n_runs), x.dtype)
            self.arrays[name][block] = np.where(new, x, self.arrays[name][block])
        self.known[block] = True

    def result(self, settings: np.ndarray, runs: np.ndarray | None = None) -> SearchResult:
        """The SearchResult of the given settings on the given runs (default all; every pair known)."""
        settings = np.asarray(settings, np.int64)
        runs = np.arange(self.n_runs) if runs is None else np.asarray(runs, np.int64)
        if self.known is None or not self.known[np.ix_(settings, runs)].all():
            raise ValueError("RunLossCache.result: some pairs are not computed (fill them first)")
        return SearchResult(
            values=self.values[settings],
            **{name: self.arrays[name][np.ix_(settings, runs)] for name in RESULT_FIELDS},
        )


@dataclass(frozen=True)
class Rung:
    """One rung of a halving search: its settings and runs, and the best objective on them (metres)."""

    settings: int
    runs: int
    best: float


@dataclass(frozen=True)
class HalvingResult:
    """A halving search: `search` holds the final survivors on every run; `rungs` how they were found.

    Attributes:
        scored: per rung, the design indices of the settings it scored (the last: `search`'s settings).
        evaluations: setting-runs the kernel computed for this search (pairs another search had already
            put in the cache cost nothing).
    """

    search: SearchResult
    rungs: tuple[Rung, ...]
    evaluations: int
    scored: tuple[np.ndarray, ...] = ()

    def as_dict(self) -> dict:
        return {"rungs": [dataclasses.asdict(r) for r in self.rungs], "evaluations": self.evaluations}


def rung_sizes(n_settings: int, n_runs: int, eta: float, initial_fraction: float) -> list[tuple[int, int]]:
    """(settings, runs) of each rung: ceil(S / eta^k) settings on ceil(f0 eta^k R) runs (at least 1, at
    most R), the last rung (the first to reach it) on all R runs.

    Arguments:
        eta: > 1, the factor by which settings shrink and runs grow each rung.
        initial_fraction: f0 in (0, 1], the first rung's share of the runs (1: one rung, exhaustive).
    """
    if not eta > 1:
        raise ValueError(f"halving needs eta > 1, got {eta}")
    if not 0 < initial_fraction <= 1:
        raise ValueError(f"halving needs 0 < initial_fraction <= 1, got {initial_fraction}")
    # K more rungs after the first, until f0 eta^K reaches 1 (the 1e-9 absorbs f0 = 1/eta^K in floats)
    k_max = max(0, math.ceil(math.log(1 / initial_fraction) / math.log(eta) - 1e-9))
    sizes = []
    for k in range(k_max + 1):
        runs = n_runs if k == k_max else min(n_runs, max(1, math.ceil(initial_fraction * eta**k * n_runs)))
        sizes.append((max(1, math.ceil(n_settings / eta**k)), runs))
        if runs == n_runs:  # rounding up reached every run early: this rung is the last
            break
    return sizes


def halving_search(
    cache: RunLossCache,
    weights,
    *,
    eta: float = 3.0,
    initial_fraction: float = 1 / 9,
    order: np.ndarray | None = None,
    progress: bool = False,
    desc: str = "halving",
) -> HalvingResult:
    """Successive halving of the cache's design over the runs with weight > 0.

    Arguments:
        cache: RunLossCache of the design (shared between calls: pairs already computed are reused).
        weights: [R] run weights; runs of weight 0 (a held-out fold) are never screened on, but the final
            survivors are scored on every run, so `search` is a complete [S_final, R] SearchResult.
        order: [R] the runs' order (stratified_order); the rungs take its prefixes of weighted runs.
    Returns:
        HalvingResult; ties keep the design's order (a stable sort).
    """
    return halving_searches(
        cache,
        [weights],
        eta=eta,
        initial_fraction=initial_fraction,
        order=order,
        progress=progress,
        desc=desc,
    )[0]


def _rung_runs(prefix: np.ndarray, weights: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The runs a search with run weights `weights` screens a rung on: the rung's prefix of the order
    less its runs of weight 0; where that leaves none (a fold holding out the whole prefix), its own
    first len(prefix) weighted runs of the order, so that no rung selects on an empty mean."""
    own = prefix[weights[prefix] > 0]
    if len(own):
        return own
    weighted = order[weights[order] > 0]
    return np.sort(weighted[: len(prefix)])


def halving_searches(
    cache: RunLossCache,
    weights: Sequence,
    *,
    eta: float = 3.0,
    initial_fraction: float = 1 / 9,
    order: np.ndarray | None = None,
    progress: bool = False,
    desc: str = "halving",
) -> list[HalvingResult]:
    """Several halving searches of one design in step (cross-validation folds): each is
    `halving_search(cache, w)` for its weights w and selects exactly what it would alone, but every rung
    fills the pairs all of them need at once (at most two rectangles of settings x runs per rung), so
    the folds' nearly equal prefixes and survivors cost one batch of kernel calls, not one per fold.

    Arguments:
        weights: one [R] weight vector per search.
    Returns:
        One HalvingResult per search; `evaluations` is the setting-runs of the whole call (shared).
    """
    ws = [np.asarray(w, np.float64) for w in weights]
    for w in ws:
        if w.shape != (cache.n_runs,):
            raise ValueError(f"weights must have shape ({cache.n_runs},), got {w.shape}")
    order = np.arange(cache.n_runs) if order is None else np.asarray(order, np.int64)
    if any(not np.any(w > 0) for w in ws):
        raise ValueError("halving_search: no run has a weight > 0")
    n_settings, before = len(cache.values), cache.evaluations
    # Every search's rung k screens on the same prefix of `order` (the search over all runs' rung k),
    # less its runs of weight 0: a fold's rungs are then subsets of the full fit's, whose pairs the
    # cache holds, instead of prefixes reaching past them (new pairs for every setting of the design).
    sizes = rung_sizes(n_settings, cache.n_runs, eta, initial_fraction)
    alive = [np.arange(n_settings) for _ in ws]
    rungs, scored = [[] for _ in ws], [[] for _ in ws]
    n_rungs = len(sizes)
    for k in range(n_rungs):
        active = list(range(len(ws)))
        prefix = np.sort(order[: sizes[k][1]])
        last = k == n_rungs - 1
        runs = {i: np.arange(cache.n_runs) if last else _rung_runs(prefix, ws[i], order) for i in active}
        need = np.zeros((n_settings, cache.n_runs), bool)
        for i in active:
            need[np.ix_(alive[i], runs[i])] = True
        cache.fill_pairs(need, progress=progress, desc=f"{desc} rung {k + 1}/{n_rungs}")
        release_memory()  # the rung's subsets were shapes of their own, not compiled again (jsve._memory)
        for i in active:
            obj = cache.result(alive[i], runs[i]).objective(ws[i][runs[i]])
            rank = np.argsort(obj, kind="stable")
            best = float(obj[rank[0]])
            rungs[i].append(Rung(settings=len(alive[i]), runs=int(np.sum(ws[i][runs[i]] > 0)), best=best))
            scored[i].append(alive[i])
            if k < n_rungs - 1:  # the best ceil(S / eta^(k+1)), back in the design's order
                alive[i] = np.sort(alive[i][rank[: sizes[k + 1][0]]])
        log.info(
            "%s rung %d: %d searches, best %.5f m", desc, k + 1, len(active), min(r[-1].best for r in rungs)
        )
    cost = cache.evaluations - before
    return [
        HalvingResult(cache.result(alive[i]), tuple(rungs[i]), cost, tuple(scored[i])) for i in range(len(ws))
    ]


__all__ = [
    "RunLossCache",
    "HalvingResult",
    "Rung",
    "halving_search",
    "halving_searches",
    "rung_sizes",
    "stratified_order",
]
