"""How long a fitting study will take: its work counted in the units of a few compiled computations (the
cost model), priced by a short timing probe of those computations on the study's own data.

    size = study_size(data, config)       # shapes, designs, folds: no computation
    work = plan(size, config)             # the cost model: arithmetic on the sizes
    rates = probe(data, config)           # the real computations on a few settings, compiled first
    estimate = price(work, rates)         # seconds of computing, and of compiling apart
    print(estimate.line())

The cost model (`plan`). Every long stage of `jsve.fitting.run_study` is a number of calls of five
computations, each costing time in proportion to the frames it scans:

- **search** (the batched kernel, jsve.fitting._search.search): one call scans the F frames of a part of
  R runs (padding included) for `size` settings at once (`call_size`: about `lanes_per_call()` = size x R
  lanes), and the calls of a part are spread over the D devices, so S settings on a part cost
  ceil(ceil(S / size) / D) x size x F x R lane-frames per device. Unit: lane-frames per device.
  - the fit's search, exhaustive: the family's design (n_search + its presets) on every part;
  - halving (jsve.fitting._halving): rung k scores its ceil(S / eta^k) settings on the runs new to
    it (the prefix of the stratified order, `rung_sizes`), packed by length class into parts of a
    power of 2 of runs (jsve.fitting._packing); a cross-validation fold's rungs are the same prefixes
    less its held-out runs, so on the full fit's cache they add nothing (assuming the folds keep the
    full fit's survivors, which they mostly do); on a resumed study without the fit's cache, all their pairs;
  - the parameter bootstrap's local design (n_local + 1 settings): on every part, or raced over
    prefixes of bootstrap_screen_runs x RACE_ETA^k runs of the stratified order, each rung scoring the
    settings left on its new runs and keeping BOOTSTRAP_KEPT_SHARE of them, the last survivors scored
    on the remaining runs (jsve.fitting._crossval.bootstrap_race);
    the heat map's grid (n^2 settings), on every part or on `heatmap_runs` runs laid out as
    jsve.fitting._packing.subset_layout chooses (one part, or length classes where cheaper).
- **Nelder-Mead** (jsve.fitting._polish.polish_in_lockstep) is **search** work too: the runs of all the
  fits of a stage (n_starts for the full fit; folds x n_starts in the cross-validation) move in
  lockstep on the union of their polish runs (the study's first `polish_runs` runs in the stratified
  order, each fold's less its held-out ones: the union is those runs), laid out once for a step's
  points (subset_layout: in one part for a few simplexes, else by length class). Per
  step one search of their reflections and one of the NM_MOVED_SHARE of them that expand or contract;
  first the initial simplexes, d + 1 points each.
  Without the stall test (nm_window = 0) they run to the step limit nm_steps (the hard objective is
  piecewise constant, so the convergence test rarely stops them); with it, to `nm_expected_steps`
  (NM_STALL_WINDOWS windows). The verdict on every run is a search as well: each fit's candidates
  (its search's best and each polish's result), of all the cross-validation's folds at once
  (jsve.fitting._fit.judge), whose rows also score each fold's fitted rule on its held-out runs.
- **objective** (`[fit] relaxed = true` only): the hard objective of one setting on every run
  (`_optimise._hard_jit`), the relaxed fit's value after each temperature.
- **evaluate**: jsve.evaluation.evaluate of one rule over the study (run-frames of its chunks): the
  presets and the fitted rules, in one pass that also gives the cross-validation the presets' held-out
  rows (the objective's terms of every run) and the SVE level table.
- **relaxed** (`[fit] relaxed = true`): the relaxed objective of one setting on every run; a BFGS step
  costs BFGS_EVALS_PER_STEP of them (value and gradient), up to bfgs_steps per temperature.
- **flops**: the parameter bootstrap's resample weights times the per-run losses, 2 x n_boot x R x S.

Seconds = sum over (stage, kind) of units x the probe's seconds per unit. Compilation is counted apart:
every distinct computation the study compiles (per family: the search kernel per part shape, call size
and device; with the relaxed fit, the objective; per rule structure and chunk shape, evaluate) costs
what the probe's compile of its kind took; what the probe compiled is already paid. With JAX's
persistent cache warm (a second `jsve fit` of the same shapes) the probe's compilations are cache
loads, and so the estimate's. Left out: loading the logs and preparing
FitData (done before the probe), tables, summaries and the report (seconds).

The probe (`probe`) runs, after compiling each, the same calls the study makes first: per family one
round of search calls on the first part (one per device, the search's call size) (with the relaxed
fit, one objective evaluation and one relaxed one); one evaluate chunk of the first bucket; a matrix
product.
Each is timed twice, the first call's extra time being its compilation; results are discarded, so the
study's results do not change, and the compiled computations are those the study then reuses.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

NM_STALL_WINDOWS = 1
"""Windows of moves a Nelder-Mead run with the stall test typically takes (jsve.fitting._simplex) after
its initial simplex. A polish that starts from a search's best on a plateau of the hard objective
improves nothing in its first window and stops there; one that keeps improving takes more, and the
estimate is then low by up to a window a polish (docs/fitting.md, "How long a fit takes")."""


def nm_expected_steps(fit) -> float:
    """Steps the cost model expects a Nelder-Mead run of FitConfig `fit` to take: its step limit without
    the stall test, else the initial simplex and NM_STALL_WINDOWS windows (at most the limit)."""
    if fit.nm_window <= 0:
        return float(fit.nm_steps)
    return float(min(fit.nm_steps, 1 + NM_STALL_WINDOWS * fit.nm_window))


BOOTSTRAP_KEPT_SHARE = 0.7
"""Share of the settings left in the parameter bootstrap's race that a rung keeps (jsve.fitting.
_crossval.bootstrap_race, plausible_winners). How many a rung keeps depends on how flat the local
objective is: under half where it is sharp, all of them on a plateau, where almost any setting can
win a resample; 0.7 lies between (docs/fitting.md, Validation)."""

NM_MOVED_SHARE = 0.05
"""Share of Nelder-Mead steps whose reflection is followed by an expansion or a contraction (a second
point scored); shrinks (d + 1 points) are left out. Around a start on a plateau of the hard objective
few steps do (a reflection that ties is taken as it is); a polish that descends expands or contracts on
most of its steps, up to all of them (docs/fitting.md, "How long a fit takes")."""

BFGS_EVALS_PER_STEP = 4.0
"""Relaxed-objective evaluations per BFGS step (value and gradient by reverse mode, about 3 values, and
the line search's trial); an assumed figure, the relaxed stage being off by default."""

BFGS_COMPILE = 4.0
"""Compile time of a family's annealed BFGS over that of its relaxed objective (the gradient through
the scan); an assumed figure, as BFGS_EVALS_PER_STEP."""

STAGES = (
    "fit",
    "evaluate",
    "cross_validation",
    "parameter_bootstrap",
    "heatmap",
)
"""The study's stages in order (jsve.fitting._study.run_study; "fit" stands for fit_<family>)."""

UNITS = {
    "search": "lane-frames per device",
    "objective": "evaluations",
    "evaluate": "run-frames",
    "relaxed": "evaluations",
    "flops": "flops",
}
"""The unit of each kind of work."""


# ---------------------------------------------------------------------------------------------------
# The study's size


@dataclass(frozen=True)
class StudySize:
    """What the cost model needs to know about the data and the configuration, read without computing.

    Attributes:
        n_runs, n_frames: real runs; valid frames.
        run_counts: real runs per part (FitData.run_counts).
        parts: (frames, runs with padding) per part: the search kernel's shapes.
        chunks: per bucket, jsve.evaluation.evaluate's (chunks, runs per chunk, frames).
        n_devices: local JAX devices (the search spreads its calls over them).
        designs: family -> settings of its search design (n_search + presets).
        dims: family -> free parameters.
        heatmap: family -> whether the heat map's two axes are free parameters of its space.
        presets: (name, rule structure, family whose space holds it or "") per preset.
        structures: family -> the rule structure of its fitted rule.
        folds: held-out masks ([R] bool) of the cross-validation's folds.
        order: [R] the halving's stratified order of the runs.
    """

    n_runs: int
    n_frames: int
    run_counts: tuple[int, ...]
    parts: tuple[tuple[int, int], ...]
    chunks: tuple[tuple[int, int, int], ...]
    n_devices: int
    designs: dict[str, int]
    dims: dict[str, int]
    heatmap: dict[str, bool] = field(default_factory=dict)
    presets: tuple[tuple[str, str, str], ...] = ()
    structures: dict[str, str] = field(default_factory=dict)
    folds: tuple[np.ndarray, ...] = ()
    order: np.ndarray | None = None


def study_size(data, config) -> StudySize:
    """The StudySize of FitData `data` under StudyConfig `config` (shapes and counts only)."""
    import jax

    from jsve.core._batch import ladder_chunk_size, runs_per_chunk_for
    from jsve.core._rules import PRESETS, preset
    from jsve.fitting._fit import search_design
    from jsve.fitting._halving import stratified_order
    from jsve.fitting._space import is_space_point, preset_point
    from jsve.fitting._study import study_folds

    # the study's evaluation streams a Parquet study in the buckets its parts were cut from
    if data.buckets:
        buckets = [(b.batch.n_runs, b.batch.n_frames) for b in data.buckets]
    else:
        buckets = [(n, p.n_frames) for n, p in zip(data.run_counts, data.parts, strict=True)]
    chunks = []
    for n, frames in buckets:
        size = ladder_chunk_size(n, runs_per_chunk_for(frames))
        chunks.append((math.ceil(n / size), size, frames))
    spaces = {f: config.space(f) for f in config.families}
    x, y = config.heatmap[:2] if config.heatmap else (None, None)
    presets = []
    for name in PRESETS:
        rule = preset(name)
        family = preset_point(name)[0].kind if is_space_point(rule) else ""
        presets.append((name, str(jax.tree_util.tree_structure(rule)), family))
    structures = {}
    for family, space in spaces.items():
        unit = np.full(space.dim, 0.5)
        structures[family] = str(jax.tree_util.tree_structure(space.rule(space.values_from_unit(unit))))
    return StudySize(
        n_runs=data.n_runs,
        n_frames=data.n_frames,
        run_counts=tuple(int(n) for n in data.run_counts),
        parts=tuple((p.n_frames, p.n_runs) for p in data.parts),
        chunks=tuple(chunks),
        n_devices=len(jax.local_devices()),
        designs={f: len(search_design(s, config.fit)) for f, s in spaces.items()},
        dims={f: s.dim for f, s in spaces.items()},
        heatmap={f: x in s.names and y in s.names for f, s in spaces.items()},
        presets=tuple(presets),
        structures=structures,
        folds=tuple(fold.test for fold in study_folds(data.meta, config)),
        order=stratified_order(data.meta, data.n_runs, seed=config.fit.seed),
    )


# ---------------------------------------------------------------------------------------------------
# The cost model


@dataclass(frozen=True)
class Work:
    """Work of one kind in one stage: `units` of UNITS[kind] for `family` ("" when shared)."""

    stage: str
    kind: str
    family: str
    units: float


@dataclass(frozen=True)
class Plan:
    """A study's work, and the computations it compiles: (kind, family) -> keys of distinct
    computations (kinds "search", "objective", "nelder_mead", "evaluate", "relaxed", "bfgs")."""

    work: tuple[Work, ...]
    compiles: dict[tuple[str, str], frozenset]

    def units(self, kind: str, family: str = "", stage: str | None = None) -> float:
        """Total units of a kind (and family, stage) of work."""
        return sum(
            w.units
            for w in self.work
            if w.kind == kind and w.family == family and (stage is None or w.stage == stage)
        )


def search_cost(
    size: StudySize, n_settings: int, runs: np.ndarray | None = None, *, family: str = "", layout_for: int = 0
) -> tuple[int, set]:
    """Lane-frames per device of `search` scoring n_settings settings on `runs` (global indices; None:
    all), and the keys of the computations it compiles: (frames, runs, call size, device).
    layout_for: > 0 where the runs are laid out by jsve.fitting._packing.subset_layout for that many
    settings (Nelder-Mead's simplexes, the heat map's grid): in one part or by length class; else by
    length class (halving's rungs, `packing`).

    ceil(S / size) calls per part, ceil(calls / D) rounds on the D devices, each scanning
    size x runs x frames lane-frames.
    """
    from jsve.fitting._packing import cheapest_layout, layout_shapes, packing
    from jsve.fitting._search import call_size

    if runs is None:
        shapes = list(size.parts)
    elif layout_for > 0:
        n_classes = cheapest_layout(size.run_counts, size.parts, runs, layout_for)
        shapes = layout_shapes(size.run_counts, size.parts, runs, n_classes)
    else:
        shapes = [(item.frames, item.runs) for item in packing(size.run_counts, size.parts, runs)]
    units, keys = 0, set()
    for frames, r in shapes:
        if n_settings < 1:
            continue
        per_call = call_size(r, n_settings)
        calls = math.ceil(n_settings / per_call)
        units += math.ceil(calls / size.n_devices) * per_call * r * frames
        keys |= {(frames, r, per_call, d) for d in range(min(calls, size.n_devices))}
    return units, keys


def halving_rectangles(
    size: StudySize, family: str, eta: float, initial_fraction: float, *, cached: bool = True
) -> tuple[list[tuple[int, np.ndarray]], list[tuple[int, np.ndarray]]]:
    """The (settings, runs) rectangles halving scores: the fit on all runs, and what the folds add.

    Arguments:
        cached: the folds halve on the full fit's cache (run_study in one process); False: on a new one
            (a resumed study whose fit stage is done), so every pair they need is scored again.
    Returns:
        (the full fit's rectangles, the folds' rectangles), runs as global indices.
    """
    from jsve.fitting._halving import rung_sizes

    n_settings, n_runs = size.designs[family], size.n_runs
    order = np.arange(n_runs) if size.order is None else np.asarray(size.order)
    everything = np.arange(n_runs)

    rungs = rung_sizes(n_settings, n_runs, eta, initial_fraction)

    def prefixes(train: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """A search's rungs: the full study's prefixes of `order`, less the runs outside `train`."""
        last = len(rungs) - 1
        return [
            (s, everything if k == last else np.sort(np.intersect1d(order[:r], train)))
            for k, (s, r) in enumerate(rungs)
        ]

    fit_rungs = prefixes(order)
    fit_rects, seen = [], np.zeros(n_runs, bool)
    for n, runs in fit_rungs:
        new = runs[~seen[runs]]
        fit_rects.append((n, new))
        seen[runs] = True
    fold_rungs = [prefixes(order[~np.asarray(test)[order]]) for test in size.folds]
    fold_rects = []
    known = np.zeros(n_runs, bool)  # runs the rung's settings are known on (the full fit's, earlier rungs')
    for k in range(max((len(r) for r in fold_rungs), default=0)):
        union = np.zeros(n_runs, bool)
        for rungs in fold_rungs:
            if k < len(rungs):
                union[rungs[k][1]] = True
        if cached:
            if k < len(fit_rungs):
                known[fit_rungs[k][1]] = True
            if k >= len(fit_rungs) - 1:  # the full fit's survivors are known on every run
                known[:] = True
        n = fit_rungs[min(k, len(fit_rungs) - 1)][0]
        new = np.flatnonzero(union & ~known)
        if len(new):
            fold_rects.append((n, new))
        known |= union
    return fit_rects, fold_rects


def plan(size: StudySize, config, done: Collection[str] = ()) -> Plan:
    """The study's work (cost model, module docstring) under StudyConfig `config`, leaving out the
    stages in `done` (names of jsve.fitting._study's stages: fit_<family> for the fits)."""
    from jsve.fitting._crossval import RACE_ETA

    fit = config.resolved(size.n_runs).fit
    work: dict[tuple[str, str, str], float] = {}  # (stage, kind, family) -> units, in order of first use
    compiles: dict[tuple[str, str], set] = {}

    def add(stage: str, kind: str, family: str, units: float) -> None:
        if units:
            work[stage, kind, family] = work.get((stage, kind, family), 0.0) + float(units)

    def compile_(kind: str, family: str, keys) -> None:
        compiles.setdefault((kind, family), set()).update(keys)

    def search(stage: str, family: str, n_settings: int, runs=None, layout_for: int = 0) -> None:
        units, keys = search_cost(size, n_settings, runs, family=family, layout_for=layout_for)
        add(stage, "search", family, units)
        compile_("search", family, keys)

    def fit_stages(stage: str, family: str, train_runs: Sequence[int]) -> None:
        """Nelder-Mead and the relaxed fit once per fit of `train_runs` training runs, then the verdict
        of every fit's candidates (its search's best and each polish) in one search on every run
        (jsve.fitting._fit.judge); a fit of more than polish_runs polishes on a packed subset
        (jsve.fitting._polish)."""
        folds = len(train_runs)
        candidates = 1 + max(fit.n_starts, 0)
        if fit.n_starts > 0:
            order = np.arange(size.n_runs) if size.order is None else np.asarray(size.order)
            union = size.n_runs if fit.polish_runs <= 0 else fit.polish_runs
            runs = np.sort(order[: min(size.n_runs, union)])
            simplexes = folds * fit.n_starts
            # (the runs laid out once for a step's points, about one per simplex: jsve.fitting._polish)
            cost = functools.partial(search_cost, size, runs=runs, family=family, layout_for=simplexes)
            search(stage, family, simplexes * (size.dims[family] + 1), runs, layout_for=simplexes)
            reflections, _ = cost(simplexes)
            moved, keys = cost(math.ceil(NM_MOVED_SHARE * simplexes))
            add(stage, "search", family, nm_expected_steps(fit) * (reflections + moved))
            compile_("search", family, keys | cost(simplexes)[1])
        if fit.relaxed:
            temps = len(fit.temperatures)
            search(stage, family, folds * candidates)  # the relaxed fit's start: the best so far
            add(stage, "relaxed", family, folds * temps * (BFGS_EVALS_PER_STEP * fit.bfgs_steps + 1))
            add(stage, "objective", family, folds * temps)
            compile_("relaxed", family, {family})
            compile_("bfgs", family, {family})
            compile_("objective", family, {family})
            candidates += 1
        search(stage, family, folds * candidates)  # the verdict, all fits' candidates at once

    def evaluate(stage: str, structures: Sequence[str]) -> None:
        units = sum(n * runs * frames for n, runs, frames in size.chunks)
        add(stage, "evaluate", "", units * len(structures))
        compile_("evaluate", "", {(s, runs, frames) for s in structures for _, runs, frames in size.chunks})

    families = list(config.families)
    halving = fit.search == "halving"
    for family in families:
        if f"fit_{family}" in done:
            continue
        if halving:
            for n, runs in halving_rectangles(size, family, fit.eta, fit.initial_fraction)[0]:
                search("fit", family, n, runs)
        else:
            search("fit", family, size.designs[family])
        fit_stages("fit", family, [size.n_runs])
    if "evaluate" not in done:  # presets and fitted rules in one pass; the presets' held-out rows too
        evaluate("evaluate", [s for _, s, _ in size.presets] + [size.structures[f] for f in families])
    if "cross_validation" not in done and size.folds:
        stage = "cross_validation"
        for family in families:
            if halving:
                cached = f"fit_{family}" not in done
                rects = halving_rectangles(size, family, fit.eta, fit.initial_fraction, cached=cached)[1]
                for n, runs in rects:
                    search(stage, family, n, runs)
            # the verdict's rows hold each fold's fitted rule on its held-out runs too
            fit_stages(stage, family, [size.n_runs - int(np.sum(f)) for f in size.folds])
    if "parameter_bootstrap" not in done:
        screen = config.bootstrap_screen_runs if 0 < config.bootstrap_screen_runs < size.n_runs else 0
        screen = screen if config.n_local > 0 else 0  # the fit alone: no race, on every run
        for family in families:
            if screen:  # the race over growing prefixes, then its survivors on the other runs
                order = np.arange(size.n_runs) if size.order is None else np.asarray(size.order)
                n, scored, prefix = config.n_local + 1, 0, screen
                while prefix < size.n_runs:
                    search("parameter_bootstrap", family, n, np.sort(order[scored:prefix]))
                    n, scored, prefix = math.ceil(BOOTSTRAP_KEPT_SHARE * n), prefix, prefix * RACE_ETA
                search("parameter_bootstrap", family, n, np.sort(order[scored:]))
            else:
                search("parameter_bootstrap", family, config.n_local + 1)
            if halving:  # the survivors of the last rung
                kept = halving_rectangles(size, family, fit.eta, fit.initial_fraction)[0][-1][0]
            else:
                kept = size.designs[family]
            flops = 2 * config.n_boot * size.n_runs * (kept + config.n_local + 1)
            add("parameter_bootstrap", "flops", "", flops)
    if "heatmap" not in done and config.heatmap:
        n = int(config.heatmap[2])
        order = np.arange(size.n_runs) if size.order is None else np.asarray(size.order)
        subset = np.sort(order[: config.heatmap_runs]) if 0 < config.heatmap_runs < size.n_runs else None
        for family in families:
            if size.heatmap.get(family):
                search("heatmap", family, n * n, subset, layout_for=n * n)
    return Plan(
        work=tuple(Work(*key, units) for key, units in work.items()),
        compiles={k: frozenset(v) for k, v in compiles.items()},
    )


# ---------------------------------------------------------------------------------------------------
# Pricing


@dataclass(frozen=True)
class Rates:
    """What the probe measured.

    Attributes:
        seconds: (kind, family) -> seconds per unit of work (UNITS).
        compile: (kind, family) -> seconds to compile one computation of that kind.
        compiled: (kind, family) -> keys of the computations the probe compiled (already paid).
        probe_seconds: the probe's wall time, compile_seconds: the part of it spent compiling.
    """

    seconds: dict[tuple[str, str], float]
    compile: dict[tuple[str, str], float]
    compiled: dict[tuple[str, str], frozenset] = field(default_factory=dict)
    probe_seconds: float = 0.0
    compile_seconds: float = 0.0


@dataclass(frozen=True)
class Estimate:
    """Expected seconds of a study: per stage, compiling apart.

    Attributes:
        stages: stage -> seconds of computing (STAGES' names, "fit" for the fits).
        compile: seconds of compiling still to come.
        probe_seconds, probe_compile: the probe's wall time and its compilation (already spent).
        basis: the study's size in words.
        caveat: what the estimate is known to miss on this machine ("" when nothing).
    """

    stages: dict[str, float]
    compile: float
    probe_seconds: float = 0.0
    probe_compile: float = 0.0
    basis: str = ""
    caveat: str = ""

    @property
    def compute(self) -> float:
        return float(sum(self.stages.values()))

    @property
    def total(self) -> float:
        """Expected wall time from the estimate on: computing and compiling."""
        return self.compute + self.compile

    def line(self) -> str:
        """One line for people: the expected wall time, what it is made of, and its basis."""
        parts = ", ".join(f"{k} {duration(v)}" for k, v in self.stages.items() if v >= 0.5)
        probe = duration(self.probe_seconds - self.probe_compile)
        return (
            f"expected wall time {duration(self.total)} ({duration(self.compute)} computing"
            f"{': ' + parts if parts else ''}; "
            f"{duration(self.compile)} compiling) for {self.basis}; from a probe of {probe} after "
            f"{duration(self.probe_compile)} compiling{'; ' + self.caveat if self.caveat else ''}"
        )

    def as_dict(self) -> dict:
        return {
            "expected_s": self.total,
            "compute_s": self.compute,
            "compile_s": self.compile,
            "stages_s": dict(self.stages),
            "probe_s": self.probe_seconds,
            "probe_compile_s": self.probe_compile,
            "basis": self.basis,
            "caveat": self.caveat,
        }


def price(work: Plan, rates: Rates, *, basis: str = "") -> Estimate:
    """Seconds of a Plan at the probe's Rates: units x seconds per unit per stage, and the compilations
    the plan needs and the probe did not do, each at its kind's compile time. A kind the probe did not
    time (a family it skipped) costs nothing."""
    stages: dict[str, float] = {}
    for w in work.work:
        stages[w.stage] = stages.get(w.stage, 0.0) + w.units * rates.seconds.get((w.kind, w.family), 0.0)
    compile_s = 0.0
    for (kind, family), keys in work.compiles.items():
        left = keys - rates.compiled.get((kind, family), frozenset())
        compile_s += len(left) * compile_rate(rates, kind, family)
    return Estimate(
        stages={s: stages[s] for s in STAGES if s in stages},
        compile=compile_s,
        probe_seconds=rates.probe_seconds,
        probe_compile=rates.compile_seconds,
        basis=basis,
    )


def compile_rate(rates: Rates, kind: str, family: str) -> float:
    """Seconds to compile one computation of a kind: measured, or a measured kind times its factor."""
    if kind == "bfgs":
        return BFGS_COMPILE * rates.compile.get(("relaxed", family), 0.0)
    return rates.compile.get((kind, family), 0.0)


def describe(size: StudySize, config) -> str:
    """The study's size in words, the basis of an estimate: runs, frames, settings, search, folds."""
    fit = config.resolved(size.n_runs).fit
    settings = " + ".join(f"{f} {size.designs[f]:,}" for f in config.families)
    words = [
        f"{size.n_runs:,} runs",
        f"{size.n_frames:,} frames",
        f"{settings} settings ({fit.search}"
        + (f", first rung 1/{round(1 / fit.initial_fraction)} of the runs" if fit.search == "halving" else "")
        + ")",
        f"{len(size.folds)} folds",
        f"Nelder-Mead {fit.n_starts} x {nm_expected_steps(fit):.0f} steps a fit"
        + (f" on {fit.polish_runs:,} of the runs" if 0 < fit.polish_runs < size.n_runs else ""),
    ]
    if fit.relaxed:
        words.append(f"relaxed BFGS {len(fit.temperatures)} x {fit.bfgs_steps} steps")
    return ", ".join(words)


def duration(seconds: float) -> str:
    """A duration for people: 40 s, 3.5 min, 1.2 h."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


# ---------------------------------------------------------------------------------------------------
# The probe


def _timed(fn) -> float:
    import jax

    started = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - started


def _twice(fn, spent: list[float]) -> tuple[float, float]:
    """(compile seconds, run seconds) of a computation: its first call less its second, its second; the
    compile seconds are appended to `spent`."""
    first = _timed(fn)
    second = _timed(fn)
    spent.append(max(first - second, 0.0))
    return spent[-1], second


def probe(data, config, *, progress: bool = False) -> Rates:
    """Time the study's computations on its own data (module docstring): per family a round of search
    calls, a one-setting search and an objective evaluation (and the relaxed objective where the fit
    runs it); an evaluate chunk; a matrix product.

    Arguments:
        data: FitData; config: StudyConfig (its objective must be data's).
        progress: a bar over the probe's steps on stderr.
    Returns:
        Rates, with what the probe compiled.
    """
    import jax
    import jax.numpy as jnp
    from tqdm.auto import tqdm

    from jsve.core._batch import iter_chunks, ladder_chunk_size, runs_per_chunk_for
    from jsve.core._rules import BASELINES, preset
    from jsve.evaluation._evaluate import evaluate_batch
    from jsve.fitting._fit import search_design
    from jsve.fitting._optimise import _hard_jit, _relaxed_jit
    from jsve.fitting._search import call_size, search

    n_devices = len(jax.local_devices())
    seconds: dict[tuple[str, str], float] = {}
    compile_s: dict[tuple[str, str], float] = {}
    compiled: dict[tuple[str, str], set] = {}
    started, spent = time.perf_counter(), []
    families = list(config.families)
    steps = (3 if config.fit.relaxed else 1) * len(families) + 2
    weights = data.split_weights(np.ones(data.n_runs))
    part, n_real = data.parts[0], data.run_counts[0]
    with tqdm(total=steps, desc="timing probe", unit="step", disable=not progress) as bar:
        for family in families:
            space = config.space(family)
            values = search_design(space, config.fit)
            # a round of the search's calls on the first part: one per device, at the search's call size
            per_call = call_size(part.n_runs, len(values))
            calls = min(n_devices, math.ceil(len(values) / per_call))
            run = functools.partial(
                search, [part], space, values[: calls * per_call], data.config, run_counts=[n_real],
                settings_per_call=per_call, progress=False,
            )  # fmt: skip
            c, s = _twice(run, spent)
            keys = {(part.n_frames, part.n_runs, per_call, d) for d in range(calls)}
            seconds["search", family] = s / (per_call * part.n_runs * part.n_frames)
            compile_s["search", family] = c / len(keys)
            compiled["search", family] = keys
            bar.update(1)

            if config.fit.relaxed:  # the relaxed fit's objectives (jsve.fitting._optimise.relaxed_fit)
                z = space.z_from_values(jnp.asarray(values[0], part.t.dtype))
                run = functools.partial(_hard_jit, z, data.parts, weights, space, data.config)
                compile_s["objective", family], seconds["objective", family] = _twice(run, spent)
                compiled["objective", family] = {family}
                bar.update(1)
                tau = jnp.asarray(config.fit.temperatures[0], z.dtype)
                run = functools.partial(_relaxed_jit, z, *data.slim(), weights, tau, space, data.config)
                compile_s["relaxed", family], seconds["relaxed", family] = _twice(run, spent)
                compiled["relaxed", family] = {family}
                bar.update(1)

        # evaluate's first chunk, as jsve.evaluation.evaluate_rules cuts it (a streamed study reads its
        # first bucket), with the objective's terms the study's evaluation adds
        buckets = iter(data.full_buckets())
        first = next(buckets, None)
        getattr(buckets, "close", lambda: None)()  # stop a stream after its first bucket
        if first is not None:
            batch = first.batch
            per_chunk = ladder_chunk_size(batch.n_runs, runs_per_chunk_for(batch.n_frames))
            _, chunk = next(iter(iter_chunks(jax.tree.map(np.asarray, batch), per_chunk)))
            rule = preset(BASELINES.get("sve", "orbslam3"))
            run = functools.partial(
                evaluate_batch, chunk, rule, align=config.align, min_coverage=config.min_coverage,
                failure=config.failure, switch_model=config.switch_model, objective=config.objective(),
            )  # fmt: skip
            compile_s["evaluate", ""], s = _twice(run, spent)
            seconds["evaluate", ""] = s / (per_chunk * batch.n_frames)
            compiled["evaluate", ""] = {(str(jax.tree_util.tree_structure(rule)), per_chunk, batch.n_frames)}
        bar.update(1)

        a, b = np.ones((256, data.n_runs)), np.ones((data.n_runs, 512))
        seconds["flops", ""] = _timed(functools.partial(np.matmul, a, b)) / (2 * a.size * b.shape[1])
        bar.update(1)
    return Rates(
        seconds=seconds,
        compile=compile_s,
        compiled={k: frozenset(v) for k, v in compiled.items()},
        probe_seconds=time.perf_counter() - started,
        compile_seconds=float(sum(spent)),
    )


def estimate(data, config, *, done: Collection[str] = (), progress: bool = False) -> Estimate | None:
    """The expected wall time of run_study(data, out, config) from here, by the cost model priced by the
    probe; `done`: stages already finished (a resumed study), left out. None when nothing is left to
    do (no probe is run)."""
    size = study_size(data, config)
    work = plan(size, config, done)
    if not work.work:
        return None
    rates = probe(data, config, progress=progress)
    import jax

    estimate = price(work, rates, basis=describe(size, config))
    return replace(estimate, caveat=backend_caveat(jax.default_backend()))


ACCELERATOR_CAVEAT = (
    "on {backend} it may be far too low: the cost model prices scanned lane-frames, while an accelerator's "
    "scans cost a launch latency per frame step whatever their width (measured on an NVIDIA H200: 3.7 min "
    "expected, the fit still in its second family after 4.3 min; docs/fitting.md)"
)
"""What the estimate misses on an accelerator (`backend_caveat`)."""


def backend_caveat(backend: str) -> str:
    """The caveat an estimate on JAX backend `backend` carries: none on CPU, where the cost model's
    prices hold (docs/performance.md), ACCELERATOR_CAVEAT elsewhere."""
    return "" if backend == "cpu" else ACCELERATOR_CAVEAT.format(backend=backend)


__all__ = [
    "StudySize",
    "study_size",
    "Work",
    "Plan",
    "plan",
    "search_cost",
    "halving_rectangles",
    "Rates",
    "Estimate",
    "price",
    "probe",
    "estimate",
    "describe",
    "duration",
    "backend_caveat",
    "NM_MOVED_SHARE",
    "NM_STALL_WINDOWS",
    "nm_expected_steps",
]
