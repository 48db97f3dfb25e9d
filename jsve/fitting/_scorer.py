"""The one seam between the optimisers and what scores a rule: `Scorer.score(space, values, runs)`.

    Scorer              the interface: [S, R] per-run results of settings on runs, and a meter
    ReplayScorer        the replay: jsve's search kernel over the study's logs (layout, devices, Dask)
    Meter               what a scorer has been asked for: calls, settings, setting-runs

Every optimiser (the search and its halving, Nelder-Mead, the verdict, cross-validation, the bootstrap
race, the heat map) asks a Scorer for the per-run results of settings, and reduces them itself with the
run weights it owns (SearchResult.objective). A scorer alone decides how the work is laid out and where
it runs: ReplayScorer picks the kernel's layout of the runs (jsve.fitting._packing), its devices, and
whether a large request goes to Dask workers (jsve.fitting._distributed). A scorer that runs the real
front-end implements the same two methods.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import jax
import numpy as np

from jsve.core._objective import ObjectiveConfig
from jsve.fitting._kernel import SearchBatch
from jsve.fitting._packing import subset_layout, subset_parts
from jsve.fitting._search import RESULT_FIELDS, SearchResult, search


@dataclass
class Meter:
    """What a scorer has been asked to compute.

    Attributes:
        calls: score requests. settings: settings over all requests. setting_runs: settings x runs.
    """

    calls: int = 0
    settings: int = 0
    setting_runs: int = 0

    def add(self, n_settings: int, n_runs: int) -> None:
        self.calls += 1
        self.settings += n_settings
        self.setting_runs += n_settings * n_runs


class Scorer(Protocol):
    """Per-run results of rule settings.

    Attributes:
        n_runs: runs the scorer can score (global run indices 0 .. n_runs - 1, FitData.meta's order).
        meter: what it has been asked for.
    """

    n_runs: int
    meter: Meter

    def score(
        self, space, values: np.ndarray, runs: Sequence[int] | np.ndarray | None = None, *,
        progress: bool = False, desc: str = "score",
    ) -> SearchResult:  # fmt: skip
        """[S, R'] results of `values` ([S, d] free values of `space`) on `runs` (global indices; their
        results in increasing run order) or on every run."""
        ...

    def on(self, runs: Sequence[int] | np.ndarray, n_settings: int) -> Scorer:
        """A scorer of the runs `runs` only, prepared for many requests of about n_settings settings (an
        optimiser's steps); its `runs` attribute gives this scorer's index of each of its runs."""
        ...


@dataclass
class ReplayScorer:
    """The replay of logged runs by jsve's search kernel.

    Attributes:
        parts: the kernel's layout of the runs (FitData.parts: length buckets of the study).
        run_counts: real runs of each part (the rest is padding).
        config: the objective the runs are scored under.
        sharded: Dask workers holding the same study (jsve.fitting._distributed.ShardedSearch), or None;
            a request of the whole study or a subset of its runs goes there when its settings x runs
            reach the workers' `min_setting_runs` (0 for a plain callable). Results are the same
            either way.
        columns: for a view (`on`), the study's index of each run of `parts` in their order; None for the
            study's runs in order.
        meter: what it has been asked for (shared with its views).
    """

    parts: Sequence[SearchBatch]
    run_counts: Sequence[int]
    config: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    sharded: object | None = None
    columns: np.ndarray | None = None
    meter: Meter = field(default_factory=Meter)

    @property
    def n_runs(self) -> int:
        return int(sum(self.run_counts))

    @property
    def runs(self) -> np.ndarray:
        """The study's index of each of this scorer's runs: a view's in the order of its layout."""
        return np.arange(self.n_runs) if self.columns is None else self.columns

    def score(
        self, space, values: np.ndarray, runs: Sequence[int] | np.ndarray | None = None, *,
        progress: bool = False, desc: str = "score",
    ) -> SearchResult:  # fmt: skip
        values = np.asarray(values, np.float64)
        picked = picked_runs(runs, self.n_runs)
        n_runs = self.n_runs if picked is None else len(picked)
        self.meter.add(len(values), n_runs)
        if self._to_workers(len(values) * n_runs):
            return self.sharded(space, values, picked, progress=progress, desc=desc)
        if picked is None:
            return search(self.parts, space, values, self.config, run_counts=self.run_counts,
                          progress=progress, desc=desc)  # fmt: skip
        parts, counts, scanned = subset_parts(self.parts, self.run_counts, picked)
        result = search(parts, space, values, self.config, run_counts=counts, progress=progress, desc=desc)
        return _in_run_order(result, scanned)

    def _to_workers(self, setting_runs: int) -> bool:
        """Whether a request of this many setting-runs goes to the workers: never from a view (its runs
        are packed and placed in this process for an optimiser's many small steps)."""
        if self.sharded is None or self.columns is not None:
            return False
        return setting_runs >= getattr(self.sharded, "min_setting_runs", 0)

    def on(self, runs: Sequence[int] | np.ndarray, n_settings: int) -> ReplayScorer:
        """A view of the runs `runs` (this scorer's indices), packed once as `subset_layout` says scores
        n_settings settings fastest, each part placed on the device `search` runs its calls on (every
        request scans them again). The view's runs are in the order of that layout (`runs`)."""
        packed, counts, scanned = subset_layout(self.parts, self.run_counts, runs, n_settings)
        devices = jax.local_devices()
        placed = [jax.device_put(part, devices[p % len(devices)]) for p, part in enumerate(packed)]
        return ReplayScorer(placed, counts, self.config, None, self.runs[scanned], self.meter)


def picked_runs(runs, n_runs: int) -> np.ndarray | None:
    """A request's runs (a scorer's indices) sorted and without repeats; None where they are all of
    its n_runs runs (or none were named)."""
    picked = None if runs is None else np.unique(np.asarray(runs, np.int64))
    return None if picked is not None and len(picked) == n_runs else picked


def _in_run_order(result: SearchResult, index: np.ndarray) -> SearchResult:
    """The result's columns, the scorer's runs `index` in the order they were scanned, in increasing
    run order."""
    order = np.argsort(index, kind="stable")
    if np.array_equal(order, np.arange(len(order))):
        return result
    return SearchResult(values=result.values, **{n: getattr(result, n)[:, order] for n in RESULT_FIELDS})


__all__ = ["Meter", "Scorer", "ReplayScorer"]
