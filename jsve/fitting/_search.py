"""Batched search: thousands of rule settings over the same logs, scored by the compiled kernel.

`search` evaluates the hard (exact) objective of every setting of a design on every run and returns
per-run matrices [settings, runs] (loss, failed, rmse, coverage, unsupported, included), so that any
weighting of the runs (cross-validation folds, bootstrap resamples, group balancing) is a matrix-vector
product afterwards. The kernel it calls, and the SearchBatch it scans, are jsve.fitting._kernel's: this
module cuts the settings into calls of a fixed size, spreads them over the local devices and collects
their results. tests/test_search.py checks the whole against jsve.core._objective.run_losses.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import jax
import numpy as np
from tqdm.auto import tqdm

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import Rule
from jsve.fitting._kernel import (
    SearchBatch,
    check_align,
    chunk_result,
    exact_from_start,
    needs_corrections,
    scan_sums,
)


@dataclass(frozen=True)
class SearchResult:
    """Per-run results of every setting, [S, R] numpy arrays over all runs of the data (in data order).

    Attributes:
        values: [S, d] the settings' free parameter values (in the space's order).
        loss, failed, rmse, coverage: [S, R]; rmse is NaN where failed.
        unsupported: [S, R] the setting's replay of the run left the log's support.
        included: [S, R] the pair counts in the objective (False only where unsupported under
            support="exclude"; jsve.core._objective).

    The weighted means below are over the included pairs of each setting; a setting with no included
    weight gets the mean over all runs (every loss then the penalty), as
    jsve.core._objective.weighted_objective.
    """

    values: np.ndarray
    loss: np.ndarray
    failed: np.ndarray
    rmse: np.ndarray
    coverage: np.ndarray
    unsupported: np.ndarray
    included: np.ndarray

    def _mean(self, x: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """[..., S] weighted means of x [S, R] over each setting's included runs (two matrix products,
        so bootstrap weights [n_boot, R] never make an [n_boot, S, R] array)."""
        w = np.asarray(weights, np.float64)
        x = np.asarray(x, np.float64)
        every = (w @ x.T) / w.sum(axis=-1, keepdims=True)
        if self.included.all():
            return every
        inc = self.included.astype(np.float64)
        num, den = w @ (inc * x).T, w @ inc.T
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), every)

    def objective(self, weights: np.ndarray) -> np.ndarray:
        """[S] weighted mean loss for run weights [R] (or [..., R] for many weightings: [..., S])."""
        return self._mean(self.loss, weights)

    def failure_rate(self, weights: np.ndarray) -> np.ndarray:
        return self._mean(self.failed, weights)

    def coverage_mean(self, weights: np.ndarray) -> np.ndarray:
        return self._mean(self.coverage, weights)

    def unsupported_rate(self, weights: np.ndarray) -> np.ndarray:
        """[..., S] weighted share of all runs whose replay left the log's support."""
        w = np.asarray(weights, np.float64)
        return (w @ self.unsupported.T.astype(np.float64)) / w.sum(axis=-1, keepdims=True)

    def excluded_share(self, weights: np.ndarray) -> np.ndarray:
        """[..., S] weighted share of all runs dropped from the objective (0 under "penalise")."""
        w = np.asarray(weights, np.float64)
        return 1.0 - (w @ self.included.T.astype(np.float64)) / w.sum(axis=-1, keepdims=True)

    def concat(self, other: SearchResult) -> SearchResult:
        """Both sets of settings (same runs)."""
        return SearchResult(
            *(np.concatenate([a, b]) for a, b in zip(self.as_tuple(), other.as_tuple(), strict=True))
        )

    def as_tuple(self):
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))


RESULT_FIELDS = ("loss", "failed", "rmse", "coverage", "unsupported", "included")
"""SearchResult's [S, R] matrices by name (every field but `values`)."""

LANES_PER_CALL = 8192
"""Settings x runs per kernel call on CPU: enough lanes to vectorise each frame step, few enough that the
scan's carry (~50 floats per lane, 1.6 MB) stays in a core's L2 cache (`benchmarks/bench_search.py
--lanes` compares widths)."""

GPU_LANES_PER_CALL = 262144
"""Settings x runs per kernel call on an accelerator: a scan step costs a few kernel launches whatever its
width, so a call must hold enough lanes to fill the chip (the rates at 32,768 and 262,144 lanes:
docs/performance.md, "On a GPU")."""

LANES_ENV = "JSVE_LANES_PER_CALL"
"""Environment variable that overrides the lanes per call (a positive integer), for benchmarks."""


def lanes_per_call() -> int:
    """Settings x runs per kernel call: $JSVE_LANES_PER_CALL when set, else LANES_PER_CALL on CPU and
    GPU_LANES_PER_CALL on an accelerator (JAX's default backend)."""
    value = os.environ.get(LANES_ENV, "").strip()
    if value:
        if not value.isdigit() or int(value) < 1:
            raise ValueError(f"{LANES_ENV} must be a positive integer, got {value!r}")
        return int(value)
    return LANES_PER_CALL if jax.default_backend() == "cpu" else GPU_LANES_PER_CALL


SETTINGS_STEP = 8
"""A search of fewer settings than a full call holds runs them as one call padded to a multiple of this
many settings (or to the power of 2 at or above them, when smaller): Nelder-Mead's 38 reflections a
step scan as 40 settings, not 64. Few enough sizes that the compilations stay few."""


def call_size(n_runs: int, n_settings: int, settings_per_call: int | None = None) -> int:
    """Settings per compiled call of `search` on a part of n_runs runs (padding runs included): the
    given settings_per_call, else the power of 2 that fills `lanes_per_call()` lanes; at most n_settings
    rounded up to the power of 2 or the multiple of SETTINGS_STEP above it, whichever is smaller. One
    size per part and search, so one compilation serves all its calls."""
    size = settings_per_call or 2 ** int(math.log2(max(1, lanes_per_call() // n_runs)))
    n = max(n_settings, 1)
    return min(size, 2 ** math.ceil(math.log2(n)), SETTINGS_STEP * math.ceil(n / SETTINGS_STEP))


def _settings_chunks(n: int, size: int) -> Iterator[slice]:
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


def search(
    parts: Sequence[SearchBatch],
    space,
    values: np.ndarray,
    config: ObjectiveConfig = ObjectiveConfig(),  # noqa: B008
    *,
    run_counts: Sequence[int] | None = None,
    settings_per_call: int | None = None,
    progress: bool = True,
    desc: str = "search",
) -> SearchResult:
    """Evaluate every setting (`values`, [S, d] in `space`) on every run of `parts`.

    Arguments:
        parts: SearchBatches (from `prepare`), each a chunk of runs; results are concatenated in order.
        space: jsve.fitting._space.ParamSpace of the values.
        run_counts: real runs of each part (the rest is padding and is dropped); default all.
        settings_per_call: settings per compiled call (default: `call_size`, `lanes_per_call()` lanes / runs
            per part as a power of 2, fixed so one compilation serves every call; the last call is padded).
        progress: a bar over the setting-runs (settings x real runs) on stderr.
    Returns:
        SearchResult with [S, R_total] matrices.
    """
    values = np.asarray(values, np.float64)
    if values.ndim != 2 or values.shape[1] != space.dim:
        raise ValueError(f"values must have shape (S, {space.dim}) for {space.names}, got {values.shape}")
    check_align(config)
    n_settings = values.shape[0]
    run_counts = list(run_counts) if run_counts is not None else [p.n_runs for p in parts]
    # The scans are dispatched asynchronously, round-robin over the local devices: with several CPU
    # devices (XLA_FLAGS=--xla_force_host_platform_device_count=N, which `jsve fit` / `jsve demo` set to
    # the number of cores) they run on all cores at once. The alignments from their sums then run one at
    # a time: the batched LAPACK SVD of an alignment may run on a worker of the thread pool the host
    # devices share and wait there for tasks of that same pool; two at once on a 2-thread pool left no
    # worker to run those tasks and the process hung (jaxlib 0.10.2, 2 devices on 2 cores). One at a
    # time, a waiting SVD leaves the other workers free. They cost ~1 % of a scan.
    devices = jax.local_devices()
    per_part: list[list] = [[] for _ in range(len(parts))]
    total = n_settings * sum(run_counts)

    def dispatch(p: int, part: SearchBatch, n_real: int) -> list:
        """Start every call of part p (JAX dispatches asynchronously) and return what collecting needs."""
        size = call_size(part.n_runs, n_settings, settings_per_call)
        # a copy of the part on each device that gets a call; a part of one call goes to the devices in
        # turn (every part built on the default device, its calls on one core: a verdict or a
        # Nelder-Mead step of a few settings used one core of two)
        n_calls = math.ceil(n_settings / size)
        if n_calls == 1:
            copies = [jax.device_put(part, devices[p % len(devices)])]
        else:
            copies = [jax.device_put(part, d) for d in devices[:n_calls]]
        calls = []
        for i, sl in enumerate(_settings_chunks(n_settings, size)):
            chunk = values[sl]
            if len(chunk) < size:
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], size - len(chunk), 0)])
            k = i % len(copies)
            on_device = jax.device_put(np.asarray(chunk, part.t.dtype), _device(copies[k]))
            rules = _rules_of(space, on_device)
            exact = exact_from_start(copies[k], config)
            sums = scan_sums(copies[k], rules, config, exact=exact)
            calls.append((p, sl, n_real, copies[k], rules, exact, sums))
        return calls

    def collect(calls: list, bar) -> None:
        for p, sl, n_real, part, rules, exact, sums in calls:
            if not exact and needs_corrections(sums, config, part.n_gt):
                sums = scan_sums(part, rules, config, exact=True)
            res = jax.block_until_ready(chunk_result(part, sums, config))
            n = sl.stop - sl.start
            per_part[p].append(jax.tree.map(lambda x, n=n, r=n_real: np.asarray(x)[:n, :r], res))
            bar.update(n * n_real)

    # The bar opens before the calls are dispatched: a call of a new shape compiles (seconds to a minute)
    # while the bar stands at 0; then the rate and the ETA follow the results. At most two parts are in
    # flight: the next part's calls run while this one's results are collected, and a part's copies
    # on the other devices and its scan sums are freed once collected. (Dispatching every part first
    # would keep all of them alive at once: gigabytes on a large study.)
    with tqdm(total=total, desc=desc, unit="setting-run", unit_scale=True, disable=not progress) as bar:
        in_flight: list[list] = []
        for p, (part, n_real) in enumerate(zip(parts, run_counts, strict=True)):
            in_flight.append(dispatch(p, part, n_real))
            if len(in_flight) > 1:
                collect(in_flight.pop(0), bar)
        for calls in in_flight:
            collect(calls, bar)
    merged = [jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *chunks) for chunks in per_part]
    merged = jax.tree.map(lambda *xs: np.concatenate(xs, axis=1), *merged)
    return SearchResult(
        values=values,
        loss=merged.loss,
        failed=merged.failed,
        rmse=merged.rmse,
        coverage=merged.coverage,
        unsupported=merged.unsupported,
        included=merged.included,
    )


@functools.partial(jax.jit, static_argnums=0)
def _rules_of(space, values) -> Rule:
    """space.rule(values), compiled once per space and shape: eagerly, its dozen array operations would
    each be dispatched (and, after jsve._memory drops executables, compiled again) one by one, on every
    call of `search` in the cross-validation's Nelder-Mead steps."""
    return space.rule(values)


def _device(tree):
    """The device a (single-device) pytree of arrays lives on."""
    (device,) = jax.tree.leaves(tree)[0].devices()
    return device


__all__ = [
    "RESULT_FIELDS",
    "search",
    "SearchResult",
    "call_size",
    "LANES_PER_CALL",
    "GPU_LANES_PER_CALL",
    "lanes_per_call",
]
