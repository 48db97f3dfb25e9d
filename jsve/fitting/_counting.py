"""A study's work, counted by running its own stages against a scorer that computes nothing.

    work = plan(size, config, done)       # jsve.fitting._study's stages, every request counted

`CountingScorer` implements the Scorer seam (jsve.fitting._scorer): each request is priced as the replay
lays it out (jsve.fitting._estimate.search_cost: its part shapes, calls and devices, and the
computations it compiles) and answered with a flat objective, every setting the same loss on every run.
On it every optimiser takes a path fixed by its configuration: halving keeps its rung sizes,
Nelder-Mead on a plateau takes its reflections as they tie and stops after its first window (or runs to
its step limit without the stall test), the bootstrap race keeps every setting (its most work), the heat
map scores its grid. So the plan follows the stages' control flow as it is, not a restatement of it.

What the scorer does not see is counted beside the stages: the evaluation (jsve.evaluation's replay of
every preset and fitted rule, run-frames per rule, its table stood in by a flat one the
cross-validation reads as the real one), the bootstrap's matrix product, and the relaxed fit (off by
default; its objectives per BFGS step are an assumed figure, and its extra candidate in the verdict is
left out).
"""

from __future__ import annotations

import tempfile
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pandas as pd

from jsve.fitting._estimate import BFGS_EVALS_PER_STEP, Plan, StudySize, Work, search_cost
from jsve.fitting._scorer import Meter, picked_runs
from jsve.fitting._search import SearchResult

FLAT_LOSS = 0.05
"""The loss (m) the counting scorer gives every setting on every run."""


@dataclass
class Tally:
    """Work and compilations counted so far, and the stage they are counted under (None: not counted,
    a stage the study has done already)."""

    stage: str | None = None
    work: dict[tuple[str, str, str], float] = field(default_factory=dict)
    compiles: dict[tuple[str, str], set] = field(default_factory=dict)

    def add(self, kind: str, family: str, units: float, keys=()) -> None:
        if self.stage is None:
            return
        if units:
            key = (self.stage, kind, family)
            self.work[key] = self.work.get(key, 0.0) + float(units)
        if keys:
            self.compiles.setdefault((kind, family), set()).update(keys)

    def plan(self) -> Plan:
        return Plan(
            work=tuple(Work(*key, units) for key, units in self.work.items()),
            compiles={k: frozenset(v) for k, v in self.compiles.items()},
        )


def flat_results(values: np.ndarray, n_runs: int) -> SearchResult:
    """[S, n_runs] results of a flat objective: FLAT_LOSS everywhere, tracked, covered, included
    (read-only broadcast views: no memory for the matrices)."""
    shape = (len(values), n_runs)
    full = lambda v: np.broadcast_to(np.asarray(v), shape)  # noqa: E731
    return SearchResult(
        values=np.asarray(values, np.float64), loss=full(FLAT_LOSS), failed=full(False), rmse=full(FLAT_LOSS),
        coverage=full(1.0), unsupported=full(False), included=full(True),
    )  # fmt: skip


@dataclass
class CountingScorer:
    """A Scorer that prices each request as ReplayScorer would run it and answers with `flat_results`.

    Attributes:
        size: the study's shapes. tally: where the work goes.
        columns: for a view (`on`), the study's runs it holds; None for the whole study.
        layout_for: a view's settings per request its runs are laid out for (subset_layout).
    """

    size: StudySize
    tally: Tally
    columns: np.ndarray | None = None
    layout_for: int = 0
    meter: Meter = field(default_factory=Meter)

    @property
    def n_runs(self) -> int:
        return self.size.n_runs if self.columns is None else len(self.columns)

    @property
    def runs(self) -> np.ndarray:
        return np.arange(self.size.n_runs) if self.columns is None else self.columns

    def score(self, space, values, runs=None, *, progress: bool = False, desc: str = "score") -> SearchResult:
        values = np.asarray(values, np.float64)
        picked = picked_runs(runs, self.n_runs)
        n_runs = self.n_runs if picked is None else len(picked)
        self.meter.add(len(values), n_runs)
        if self.columns is None:  # the whole study, or its runs `picked` packed by length class
            units, keys = search_cost(self.size, len(values), picked)
        elif picked is None:  # a view: its runs as laid out for its requests
            units, keys = search_cost(self.size, len(values), self.columns, layout_for=self.layout_for)
        else:
            units, keys = search_cost(self.size, len(values), self.columns[picked])
        self.tally.add("search", space.kind, units, keys)
        return flat_results(values, n_runs)

    def on(self, runs: Sequence[int] | np.ndarray, n_settings: int) -> CountingScorer:
        columns = self.runs[np.unique(np.asarray(runs, np.int64))]
        return CountingScorer(self.size, self.tally, columns, max(int(n_settings), 1), self.meter)


@dataclass
class CountingData:
    """What the stages read of a FitData, from a StudySize: runs, metadata, the parts' shapes and
    dtype, the objective, and the counting scorer."""

    size: StudySize
    config: object
    tally: Tally

    def __post_init__(self):
        dtype = np.dtype(self.size.dtype)
        self.parts = [SimpleNamespace(n_frames=f, n_runs=r, t=np.zeros(0, dtype)) for f, r in self.size.parts]
        self._scorer = CountingScorer(self.size, self.tally)

    @property
    def scorer(self) -> CountingScorer:
        return self._scorer

    @property
    def n_runs(self) -> int:
        return self.size.n_runs

    @property
    def run_counts(self) -> tuple[int, ...]:
        return self.size.run_counts

    @property
    def meta(self) -> pd.DataFrame:
        return self.size.meta


def evaluated_units(size: StudySize, structures: Sequence[str]) -> tuple[float, set]:
    """Run-frames and compiled computations of jsve.evaluation's pass over the study for rules of these
    tree structures (one each), cut in the chunks of size.chunks."""
    units = sum(n * runs * frames for n, runs, frames in size.chunks) * len(structures)
    keys = {(s, runs, frames) for s in structures for _, runs, frames in size.chunks}
    return units, keys


def counted_evaluate(study, size: StudySize, tally: Tally) -> None:
    """The evaluate stage, counted: its run-frames for every preset and fitted rule, and a flat runs
    table in its place (the objective's terms the cross-validation reads for the presets)."""
    from jsve.core._rules import PRESETS, preset
    from jsve.evaluation._evaluate import OBJECTIVE_COLUMNS
    from jsve.fitting._fit import fitted_rule_name
    from jsve.fitting._stages import write_table

    rules = [(name, preset(name)) for name in PRESETS]
    rules += [(fitted_rule_name(f), r.rule) for f, r in study.fits.items()]
    units, keys = evaluated_units(size, [str(jax.tree_util.tree_structure(rule)) for _, rule in rules])
    tally.add("evaluate", "", units, keys)
    flat = dict.fromkeys(OBJECTIVE_COLUMNS, FLAT_LOSS) | {
        "objective_failed": False, "objective_coverage": 1.0, "objective_unsupported": False,
        "objective_included": True,
    }  # fmt: skip
    ids = size.meta["run_id"].astype(str).to_numpy()
    table = pd.concat([pd.DataFrame({"run_id": ids, "rule": name, **flat}) for name, _ in rules])
    write_table(table.reset_index(drop=True), study.out, "runs")


def relaxed_work(size: StudySize, fit, family: str, n_fits: int, tally: Tally) -> None:
    """The relaxed fit of n_fits fits: its start (each fit's candidates judged on every run), then per
    temperature BFGS_EVALS_PER_STEP relaxed objectives a BFGS step (bfgs_steps) and one more, and the
    hard objective (a one-setting search on every run)."""
    units, keys = search_cost(size, 1 + max(fit.n_starts, 0))
    tally.add("search", family, n_fits * units, keys)
    temps = len(fit.temperatures)
    tally.add("relaxed", family, n_fits * temps * (BFGS_EVALS_PER_STEP * fit.bfgs_steps + 1), {family})
    units, keys = search_cost(size, 1)
    tally.add("search", family, n_fits * temps * units, keys)
    tally.compiles.setdefault(("bfgs", family), set()).add(family)


def plan(size: StudySize, config, done: Collection[str] = ()) -> Plan:
    """The study's work under StudyConfig `config`: jsve.fitting._study's stages run against the
    counting scorer (module docstring), leaving out the work of the stages in `done` (stage names; a
    done fit is still run, uncounted, and its halving cache dropped, as a resumed study reads it)."""
    from jsve.evaluation._aggregate import group_weights
    from jsve.fitting._study import Study, stages

    if size.meta is None:
        raise ValueError("plan: the StudySize carries no run metadata (study_size(data, config) sets it)")
    tally = Tally()
    resolved = config.resolved(size.n_runs)
    # the bootstrap's resamples are a matrix product counted beside (flops), not a scorer's request
    without_relaxed = replace(resolved, n_boot=2, fit=replace(resolved.fit, relaxed=False))
    data = CountingData(size, config.objective(), tally)
    by = [c for c in config.balance_by if c in size.meta.columns]
    spaces = {f: without_relaxed.space(f) for f in without_relaxed.families}
    with tempfile.TemporaryDirectory(prefix="jsve-plan-") as out:
        study = Study(data, Path(out), without_relaxed, group_weights(size.meta, by), spaces, progress=False)
        for stage in stages(study):
            counting = stage.name not in done
            tally.stage = ("fit" if stage.name.startswith("fit_") else stage.name) if counting else None
            if stage.name == "evaluate":
                counted_evaluate(study, size, tally)
            else:
                stage.run()
            if stage.name.startswith("fit_") and not counting:
                study.caches.pop(stage.name.removeprefix("fit_"), None)
            if stage.after is not None:
                stage.after()
            _beside(stage.name, study, size, resolved, tally)
        steps = tuple(int(s["steps"]) for f in study.fits.values() for s in f.stages if "steps" in s)
    return replace(tally.plan(), nelder_mead_steps=steps)


def _beside(name: str, study, size: StudySize, resolved, tally: Tally) -> None:
    """The work of stage `name` the scorer does not see: the relaxed fits and the bootstrap's product."""
    from jsve.fitting._stages import read_table

    if tally.stage is None:
        return
    if resolved.fit.relaxed and name.startswith("fit_"):
        relaxed_work(size, resolved.fit, name.removeprefix("fit_"), 1, tally)
    if resolved.fit.relaxed and name == "cross_validation":
        for family in study.spaces:
            relaxed_work(size, resolved.fit, family, len(size.folds), tally)
    if name == "parameter_bootstrap":
        params = read_table(study.out, "params").drop_duplicates("family").set_index("family")
        for family, fit in study.fits.items():
            settings = len(fit.search.values) + int(params.loc[family, "local_scored"])
            tally.add("flops", "", 2 * resolved.n_boot * size.n_runs * settings)


__all__ = ["plan", "CountingScorer", "CountingData", "Tally", "flat_results", "FLAT_LOSS"]
