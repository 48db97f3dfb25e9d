"""How long a fitting study will take: its work counted in the units of a few compiled computations,
priced by a short timing probe of those computations on the study's own data.

    size = study_size(data, config)       # shapes, metadata, folds: no computation
    work = plan(size, config)             # the study's own stages against a counting scorer
    rates = probe(data, config)           # the real computations on a few settings, compiled first
    estimate = price(work, rates)         # seconds of computing, and of compiling apart
    print(estimate.line())

The work (`jsve.fitting._counting.plan`) is what jsve.fitting._study's stages ask of their scorer when
they run against one that computes nothing: each request priced by `search_cost` as the replay lays it
out, in five kinds of work, each costing time in proportion to what it scans:

- **search** (the batched kernel, jsve.fitting._search.search): one call scans the F frames of a part of
  R runs (padding included) for `size` settings at once (`call_size`: about `lanes_per_call()` = size x R
  lanes), and the calls of a part are spread over the D devices, so S settings on a part cost
  ceil(ceil(S / size) / D) x size x F x R lane-frames per device. Unit: lane-frames per device. The
  runs of a request are the study's parts, a subset packed by length class (jsve.fitting._packing), or
  a view's subset laid out once for its requests' size (subset_layout: Nelder-Mead's steps, the heat
  map's grid, the race's rungs).
- **evaluate**: jsve.evaluation.evaluate of one rule over the study (run-frames of its chunks): the
  presets and the fitted rules, in one pass that also gives the cross-validation the presets' held-out
  rows.
- **relaxed** (`[fit] relaxed = true` only): the relaxed objective of one setting on every run; a BFGS
  step costs BFGS_EVALS_PER_STEP of them (its hard objective after each temperature is a one-setting
  search).
- **flops**: the parameter bootstrap's resample weights times the per-run losses, 2 x n_boot x R x S.

Seconds = sum over (stage, kind) of units x the probe's seconds per unit. Compilation is counted apart:
every distinct computation the study compiles (per family: the search kernel per part shape, call size
and device; with the relaxed fit, the relaxed objective; per rule structure and chunk shape, evaluate) costs
what the probe's compile of its kind took; what the probe compiled is already paid. With JAX's
persistent cache warm (a second `jsve fit` of the same shapes) the probe's compilations are cache
loads, and so the estimate's. Left out: loading the logs and preparing
FitData (done before the probe), tables, summaries and the report (seconds).

The probe (`probe`) runs, after compiling each, the same calls the study makes first: per family one
round of search calls on the first part (one per device, the search's call size) (with the relaxed
fit, one relaxed objective); one evaluate chunk of the first bucket; a matrix
product.
Each is timed twice, the first call's extra time being its compilation; results are discarded, so the
study's results do not change, and the compiled computations are those the study then reuses.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Collection
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

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
        folds: held-out masks ([R] bool) of the cross-validation's folds.
        meta: the runs' metadata (FitData.meta: the stages draw folds, orders and weights from it).
        dtype: the parts' float dtype.
    """

    n_runs: int
    n_frames: int
    run_counts: tuple[int, ...]
    parts: tuple[tuple[int, int], ...]
    chunks: tuple[tuple[int, int, int], ...]
    n_devices: int
    designs: dict[str, int]
    folds: tuple[np.ndarray, ...] = ()
    meta: pd.DataFrame | None = None
    dtype: str = "float32"


def study_size(data, config) -> StudySize:
    """The StudySize of FitData `data` under StudyConfig `config` (shapes and counts only)."""
    import jax

    from jsve.core._batch import ladder_chunk_size, runs_per_chunk_for
    from jsve.fitting._fit import search_design
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
    return StudySize(
        n_runs=data.n_runs,
        n_frames=data.n_frames,
        run_counts=tuple(int(n) for n in data.run_counts),
        parts=tuple((p.n_frames, p.n_runs) for p in data.parts),
        chunks=tuple(chunks),
        n_devices=len(jax.local_devices()),
        designs={f: len(search_design(config.space(f), config.fit)) for f in config.families},
        folds=tuple(fold.test for fold in study_folds(data.meta, config)),
        meta=data.meta.reset_index(drop=True),
        dtype=str(np.dtype(data.parts[0].t.dtype)),
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
    computations (kinds "search", "evaluate", "relaxed", "bfgs")."""

    work: tuple[Work, ...]
    compiles: dict[tuple[str, str], frozenset]
    nelder_mead_steps: tuple[int, ...] = ()  # the steps each counted Nelder-Mead run took

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


def describe(size: StudySize, config, work: Plan | None = None) -> str:
    """The study's size in words, the basis of an estimate: runs, frames, settings, search, folds, and
    the Nelder-Mead steps `work` counted."""
    fit = config.resolved(size.n_runs).fit
    settings = " + ".join(f"{f} {size.designs[f]:,}" for f in config.families)
    words = [
        f"{size.n_runs:,} runs",
        f"{size.n_frames:,} frames",
        f"{settings} settings ({fit.search}"
        + (f", first rung 1/{round(1 / fit.initial_fraction)} of the runs" if fit.search == "halving" else "")
        + ")",
        f"{len(size.folds)} folds",
        f"Nelder-Mead {fit.n_starts} x {_mean_steps(work, fit):.0f} steps a fit"
        + (f" on {fit.polish_runs:,} of the runs" if 0 < fit.polish_runs < size.n_runs else ""),
    ]
    if fit.relaxed:
        words.append(f"relaxed BFGS {len(fit.temperatures)} x {fit.bfgs_steps} steps")
    return ", ".join(words)


def _mean_steps(work: Plan | None, fit) -> float:
    """Steps a Nelder-Mead run of the plan took on average (fit.nm_steps, the limit, where none ran)."""
    steps = work.nelder_mead_steps if work is not None else ()
    return float(np.mean(steps)) if steps else float(fit.nm_steps)


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
    calls (and the relaxed objective where the fit runs it); an evaluate chunk; a matrix product.

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
    from jsve.fitting._optimise import _relaxed_jit
    from jsve.fitting._search import call_size, search

    n_devices = len(jax.local_devices())
    seconds: dict[tuple[str, str], float] = {}
    compile_s: dict[tuple[str, str], float] = {}
    compiled: dict[tuple[str, str], set] = {}
    started, spent = time.perf_counter(), []
    families = list(config.families)
    steps = (2 if config.fit.relaxed else 1) * len(families) + 2
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

            if config.fit.relaxed:  # the relaxed fit's objective (jsve.fitting._optimise.relaxed_fit)
                z = space.z_from_values(jnp.asarray(values[0], part.t.dtype))
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
    import jax

    from jsve.fitting._counting import plan

    size = study_size(data, config)
    work = plan(size, config, done)
    if not work.work:
        return None
    rates = probe(data, config, progress=progress)
    estimate = price(work, rates, basis=describe(size, config, work))
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
    "search_cost",
    "Rates",
    "Estimate",
    "price",
    "probe",
    "estimate",
    "describe",
    "duration",
    "backend_caveat",
]
