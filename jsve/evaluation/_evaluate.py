"""Evaluate a switching rule over logs: replay, align, score, and one row per run.

`evaluate_batch` is the jit-compiled core (features, replay and trajectory error for one LogBatch, one
XLA computation); `evaluate` drives it over length buckets and fixed-size chunks of runs cut on the
host, with progress, and returns the per-run table that `jsve.evaluation._aggregate.aggregate`
summarises. Bucket lengths and chunk sizes come from ladders (jsve.core._batch), so a study compiles
a handful of shapes, and JAX's persistent cache (jsve._jax_cache) keeps them for the next process.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from jaxtyping import Array, Bool, Float
from tqdm.auto import tqdm

from jsve._memory import RELEASE_ABOVE_BYTES, release_memory, resident_bytes
from jsve.core._batch import LogBatch, iter_chunks, ladder_chunk_size, runs_per_chunk_for
from jsve.core._machine import TIME_RECENTLY_LOST_S
from jsve.core._objective import (
    DEFAULT_MIN_COVERAGE,
    FAILURE_DEFINITIONS,
    ObjectiveConfig,
    RunLoss,
    replay_losses,
)
from jsve.core._replay import as_logged_mode, batch_features, replay
from jsve.core._rules import Rule
from jsve.core._sve import FrameFeatures
from jsve.core._trajectory import RunError, batched_run_error
from jsve.evaluation._aggregate import RUN_COLUMNS, per_run_table
from jsve.io._batching import Bucket, recorded_mode

LOST_REASON = "lost tracking (a reset, an expiry to LOST or a recorded map loss; failure='strict')"
"""The failure_reason of a run that lost tracking in the replay under failure="strict", before the
trajectory's own causes."""


class Evaluation(eqx.Module):
    """Per-run outcome of one rule (leaves of shape [R]).

    Attributes:
        error: APE statistics and coverage of the saved trajectory (jsve.core._trajectory.RunError; one
            segment: ReplayResult.in_trajectory).
        accepted_fraction: share of valid frames tracked (OK with a tracked pose).
        coasting_fraction: share of valid frames in RECENTLY_LOST with an estimate (the logged pose
            under the "orbslam3" switch model, the IMU prediction under "imu-coast").
        changed_fraction: share of valid frames whose replayed mode differs from the recorded state.
        unsupported_fraction: share of valid frames where the replay needs a recorded pose that does
            not exist (the rule kept tracking where the recorded run had lost its map).
        resets: [R] int, the replay's map resets (before inertial BA2).
        new_maps: [R] int, maps the replay started after its first (after an expiry to LOST, a reset,
            or where the recorded run started one).
        lost_any: tracking was lost at least once (a reset, an expiry, a recorded map loss): an event,
            a failure only under failure="strict".
        failed: error.failed (no saved trajectory, coverage below min_coverage, ...), or lost_any under
            failure="strict".
        objective: the run's term in the fit's objective (jsve.core._objective.replay_losses) from the
            same replay, where `evaluate_batch` was given an ObjectiveConfig; else None.
    """

    error: RunError
    accepted_fraction: Float[Array, " R"]
    coasting_fraction: Float[Array, " R"]
    changed_fraction: Float[Array, " R"]
    unsupported_fraction: Float[Array, " R"]
    resets: Array
    new_maps: Array
    lost_any: Bool[Array, " R"]
    failed: Bool[Array, " R"]
    objective: RunLoss | None = None


def evaluate_batch(
    batch: LogBatch,
    rule: Rule,
    features: FrameFeatures | None = None,
    *,
    align: str = "se3",
    n_first: int | None = None,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    failure: str = "coverage",
    time_recently_lost: float = TIME_RECENTLY_LOST_S,
    switch_model: str = "orbslam3",
    objective: ObjectiveConfig | None = None,
) -> Evaluation:
    """Replay `rule` over `batch` and score every run against its ground truth (one compiled call).

    Arguments:
        batch: padded logs. rule: any jsve rule (array leaves; a new value does not recompile). It is
            checked here, on the host (Rule.check_defined), not inside the compiled call.
        features: the batch's FrameFeatures when already computed (sweeps share them).
        align, n_first, min_coverage: see jsve.core._trajectory.run_error (min_coverage: the share of
            frames with ground truth the saved trajectory must cover, DEFAULT_MIN_COVERAGE).
        failure: "coverage" (default) or "strict" (also fail every run that lost tracking once;
            jsve.core._objective.FAILURE_DEFINITIONS).
        switch_model: "orbslam3" or "imu-coast" (docs/state-machine.md).
        objective: also score each run as the fit's objective does (Evaluation.objective), from the
            same replay: its switch model and time_recently_lost must be the evaluation's.
    """
    rule.check_defined()
    _check_objective(objective, switch_model, time_recently_lost)
    if failure not in FAILURE_DEFINITIONS:
        raise ValueError(f"failure must be one of {FAILURE_DEFINITIONS}, got {failure!r}")
    return _evaluate_compiled(batch, rule, features, align=align, n_first=n_first, failure=failure,
                              min_coverage=min_coverage, time_recently_lost=time_recently_lost,
                              switch_model=switch_model, objective=objective)  # fmt: skip


def _check_objective(objective: ObjectiveConfig | None, switch_model: str, time_recently_lost: float) -> None:
    """The objective's terms come from the evaluation's replay: they must describe the same replay."""
    if objective is None:
        return
    if (objective.switch_model, objective.time_recently_lost) != (switch_model, time_recently_lost):
        raise ValueError(
            f"evaluate: the objective replays under switch_model={objective.switch_model!r}, "
            f"time_recently_lost={objective.time_recently_lost} s, the evaluation under "
            f"{switch_model!r}, {time_recently_lost} s: its terms would describe another replay"
        )


@functools.partial(
    jax.jit,
    static_argnames=("align", "n_first", "failure", "time_recently_lost", "switch_model", "objective"),
)
def _evaluate_compiled(
    batch,
    rule,
    features,
    *,
    align,
    n_first,
    failure,
    min_coverage,
    time_recently_lost,
    switch_model,
    objective,
) -> Evaluation:
    """evaluate_batch's computation, free of host callbacks so that JAX's persistent cache keeps it."""
    # No traced checks (host callbacks): a computation holding one is never kept in JAX's persistent
    # cache, and this is the one every evaluation compiles. The rule is checked on the host instead
    # (`evaluate`), and the replay's segment ids lie in [0, T) by construction.
    result = replay(batch, rule, features, switch_model=switch_model, time_recently_lost=time_recently_lost,
                    checked=False)  # fmt: skip
    # The saved trajectory is in one world frame (its map's), whatever replay segments it spans.
    error = batched_run_error(
        result.position, result.quaternion, result.in_trajectory, jnp.zeros_like(result.segment),
        batch.gt_p, batch.gt_q, batch.gt_valid, batch.valid,
        align=align, n_first=n_first, min_coverage=min_coverage, check_segments=False,
    )  # fmt: skip
    n_valid = jnp.maximum(jnp.sum(batch.valid, axis=-1), 1)
    share = lambda flags: jnp.sum(flags & batch.valid, axis=-1) / n_valid  # noqa: E731
    return Evaluation(
        error=error,
        accepted_fraction=share(result.accepted),
        coasting_fraction=share(result.coasting),
        changed_fraction=share(as_logged_mode(result) != recorded_mode(batch.state)),
        unsupported_fraction=share(result.out_of_support),
        resets=jnp.sum(result.reset & batch.valid, axis=-1),
        new_maps=jnp.maximum(jnp.max(result.segment, axis=-1), 0),
        lost_any=result.lost_any,
        failed=error.failed | (result.lost_any & (failure == "strict")),
        objective=None if objective is None else replay_losses(result, batch, objective),
    )


def evaluate(
    buckets: Iterable[Bucket],
    rule: Rule,
    *,
    rule_name: str = "rule",
    align: str = "se3",
    n_first: int | None = None,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    failure: str = "coverage",
    switch_model: str = "orbslam3",
    runs_per_chunk: int | None = None,
    progress: bool = True,
    n_runs: int | None = None,
) -> pd.DataFrame:
    """Per-run table of `rule` over every run of every bucket (metadata + errors + decisions).

    Arguments:
        buckets: from jsve.io._batching.buckets (or a single from_runs Bucket in a list), or streamed
            from Parquet (jsve.io._stream.iter_buckets: chunk-sized buckets, read as they are needed).
        rule_name: value of the `rule` column.
        switch_model: "orbslam3" or "imu-coast" (docs/state-machine.md); the `switch_model` column.
        runs_per_chunk: at most this many runs per compiled call; default: as many as fit
            jsve.core._batch.DEVICE_BUDGET_BYTES (1.5 GB) of working set.
            A bucket's chunks all have one size (`ladder_chunk_size`), so each bucket compiles once.
        n_runs: runs in all buckets, for the progress bar's total when `buckets` is an iterator.
    Returns:
        One row per run: meta columns, `rule`, rmse ... count (metres), coverage, n_segments, failed,
        failure_reason (LOST_REASON and jsve.core._trajectory.FAILURE_CAUSES in words, '; '-joined;
        '' when not failed), accepted_fraction, coasting_fraction, changed_fraction,
        unsupported_fraction, lost_any.
    """
    return evaluate_rules(buckets, [(rule_name, rule)], align=align, n_first=n_first, failure=failure,
                          min_coverage=min_coverage, switch_model=switch_model, runs_per_chunk=runs_per_chunk,
                          progress=progress, n_runs=n_runs)  # fmt: skip


def evaluate_rules(
    buckets: Iterable[Bucket],
    rules: Sequence[tuple[str, Rule]],
    *,
    align: str = "se3",
    n_first: int | None = None,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    failure: str = "coverage",
    switch_model: str = "orbslam3",
    runs_per_chunk: int | None = None,
    progress: bool = True,
    n_runs: int | None = None,
    objective: ObjectiveConfig | None = None,
    on_chunk: Callable[[pd.DataFrame, LogBatch, FrameFeatures], None] | None = None,
) -> pd.DataFrame:
    """`evaluate` of several (name, rule) pairs in one pass over the buckets: each chunk is scored
    under every rule while it is in memory, so a streamed study is read once. Rows come rule by rule
    (the order of `rules`), each rule's runs in bucket order.

    A chunk's features (jsve.core._replay.batch_features) are computed once and shared by its rules.

    Arguments:
        objective: also give every row the run's term in the fit's objective, from the same replay
            (`OBJECTIVE_COLUMNS`; evaluate_batch's `objective`).
        on_chunk: called once per chunk with the metadata of its real runs, the chunk (host arrays,
            padding runs after the real ones) and its features: a pass of its own over the study's
            frames (jsve.fitting's SVE level table) rides on this one.
    """
    if not rules:
        raise ValueError("evaluate_rules: no rules given")
    if n_runs is None and isinstance(buckets, Sequence):
        n_runs = sum(len(b.meta) for b in buckets)
    total = None if n_runs is None else n_runs * len(rules)
    done: list[tuple[pd.DataFrame, list[list[Evaluation]]]] = []  # per bucket: meta, parts per rule
    last_frames = None
    in_flight: list[tuple[list[Evaluation], Evaluation, int]] = []
    with tqdm(total=total, desc="evaluate " + ", ".join(n for n, _ in rules), unit="run",
              disable=not progress) as bar:  # fmt: skip

        def collect():
            # Results to the host one computation late: JAX dispatches asynchronously, so the next
            # chunk is read and cut on the host, or the next rule dispatched, while this one computes.
            for parts, ev, n in in_flight:
                parts.append(jax.tree.map(lambda x, n=n: np.asarray(x)[:n], ev))
                bar.update(n)
            in_flight.clear()

        for bucket in buckets:
            if last_frames not in (None, bucket.batch.n_frames) and _holds_too_much():
                # the last length's executables: buckets by length (iter_buckets' by_length) never need
                # them again; in the order chunks fill, a length may come back and is reloaded
                release_memory()
            last_frames = bucket.batch.n_frames
            cap = runs_per_chunk or runs_per_chunk_for(bucket.batch.n_frames)
            size = ladder_chunk_size(bucket.batch.n_runs, cap)
            # Chunks are cut and padded on the host (numpy), so the only computation JAX compiles is
            # evaluate_batch (features, replay and statistics together), once per chunk shape.
            host = jax.tree.map(np.asarray, bucket.batch)
            parts: list[list[Evaluation]] = [[] for _ in rules]
            done.append((bucket.meta, parts))
            for runs, chunk in iter_chunks(host, size):
                n = max(0, min(runs.stop, len(bucket.meta)) - runs.start)  # streamed chunks end in padding
                features = batch_features(chunk)
                if on_chunk is not None:
                    on_chunk(bucket.meta.iloc[runs.start : runs.start + n], chunk, features)
                for k, (_, rule) in enumerate(rules):
                    ev = evaluate_batch(chunk, rule, features, align=align, n_first=n_first,
                                        failure=failure, min_coverage=min_coverage,
                                        switch_model=switch_model, objective=objective)  # fmt: skip
                    # At most two computations in flight, whatever the number of rules: each holds a
                    # chunk's working set (runs_per_chunk_for's budget), and the CPU runs dispatched
                    # ones side by side (every rule dispatched at once would multiply the peak).
                    collect()
                    in_flight.append((parts[k], ev, n))
        collect()
    tables = [
        _run_table(jax.tree.map(lambda *xs: np.concatenate(xs), *parts[k]), meta, name, switch_model, failure)
        for k, (name, _) in enumerate(rules)
        for meta, parts in done
    ]
    return pd.concat(tables, ignore_index=True)


def in_run_order(per_run: pd.DataFrame, position) -> pd.DataFrame:
    """`evaluate_rules`' rows rule by rule (as evaluated), each rule's runs by `position` (one number per
    row, e.g. the run's place in the file or in a fit's run table), whatever order the chunks came in."""
    rule_rank = {name: k for k, name in enumerate(dict.fromkeys(per_run["rule"]))}
    order = np.lexsort((np.asarray(position), per_run["rule"].map(rule_rank).to_numpy()))
    return per_run.iloc[order].reset_index(drop=True)


TABLE_COLUMNS: tuple[str, ...] = (
    "rule",
    "switch_model",
    *RUN_COLUMNS,
    "accepted_fraction",
    "coasting_fraction",
    "changed_fraction",
    "unsupported_fraction",
    "resets",
    "new_maps",
    "lost_any",
)
"""The columns `evaluate_rules` writes after the runs' metadata, in order (then OBJECTIVE_COLUMNS where
it is given an objective)."""


def _run_table(
    ev: Evaluation, meta: pd.DataFrame, rule_name: str, switch_model: str, failure: str
) -> pd.DataFrame:
    """One row per run of `meta`: its metadata, the rule, the errors and the decisions."""
    table = per_run_table(ev.error, meta)
    table.insert(len(meta.columns), "rule", rule_name)
    table.insert(len(meta.columns) + 1, "switch_model", switch_model)
    table["failed"] = np.asarray(ev.failed)
    lost = np.asarray(ev.lost_any)
    lost_failed = lost & (failure == "strict")
    table["failure_reason"] = [
        "; ".join(filter(None, (LOST_REASON if lost_k else "", reason)))
        for lost_k, reason in zip(lost_failed, table["failure_reason"], strict=True)
    ]
    for column in ("accepted", "coasting", "changed", "unsupported"):
        table[f"{column}_fraction"] = np.asarray(getattr(ev, f"{column}_fraction"))
    table["resets"] = np.asarray(ev.resets).astype(np.int64)
    table["new_maps"] = np.asarray(ev.new_maps).astype(np.int64)
    table["lost_any"] = np.asarray(ev.lost_any)
    if ev.objective is not None:
        terms = ev.objective
        failed = np.asarray(terms.failed, bool)
        table["objective_loss"] = np.asarray(terms.loss)
        table["objective_rmse"] = np.where(failed, np.nan, np.asarray(terms.rmse))  # no number for a failure
        table["objective_failed"] = failed
        table["objective_coverage"] = np.asarray(terms.coverage)
        table["objective_unsupported"] = np.asarray(terms.unsupported, bool)
        table["objective_included"] = np.asarray(terms.included) > 0.5
    return table


OBJECTIVE_COLUMNS = (
    "objective_loss",
    "objective_rmse",
    "objective_failed",
    "objective_coverage",
    "objective_unsupported",
    "objective_included",
)
"""The run's term in the fit's objective (jsve.core._objective), which `evaluate_rules(objective=...)` adds:
its loss (metres; the penalty where the objective fails it, its bounded or raw RMSE otherwise), its RMSE
over the saved trajectory (NaN where failed), failed, coverage, whether its replay left the log's support
and whether the support policy keeps it in the mean. Both score the same saved trajectory, so `rmse`
and `objective_rmse` agree wherever neither failed."""


def _holds_too_much() -> bool:
    """The process holds more than RELEASE_ABOVE_BYTES resident (jsve._memory). The executables of every
    chunk shape and rule structure of a pass stay loaded until it ends: on a large study they double
    what `jsve fit`'s evaluation holds; dropped where the frame length changes once above the
    threshold, they cost a reload only where a length comes back (never when the buckets come by
    length, as `jsve fit` streams them)."""
    held = resident_bytes()
    return held is not None and held > RELEASE_ABOVE_BYTES
