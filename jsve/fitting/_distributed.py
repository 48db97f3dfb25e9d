"""The fit's search over rule settings as Dask tasks: settings sharded across workers, each worker
streaming the same Parquet study.

`search` (jsve.fitting._search) scores S settings on R runs in one process; its cost is S x R
setting-runs and every setting is independent of the others. `ShardedSearch` cuts the settings into
shards of `settings_per_task` and submits one task per shard through jsve.io._scheduler's executor (an
embedded LocalCluster, a process pool, or a running Dask cluster by address or scheduler file, as the
front-end sweeps do). A worker loads the study once (FitData.from_parquet: the search layout only,
streamed chunk by chunk) and keeps it for every later task of the same file and objective, then runs
the same `search` on its shard, on all runs or on the subset of runs a halving rung asks for. The
driver checks that each worker read the content it read itself (FitData.content_digest, sha256 of every
streamed leaf), so a worker that sees another file under the same path fails the fit instead of mixing
studies, and concatenates the shards in the design's order: the result equals the local search's, bit
for bit (the same kernel on the same runs; tests/test_distributed_search.py).

Used by `jsve fit --scheduler ...` for the search stages (exhaustive, the halving rungs, the folds'
rungs); Nelder-Mead, the bootstrap and the heat map stay in the driver (a polish is sequential, the
others score packed subsets). A worker holds the study's search layout (about 70 bytes a frame in
float32) on top of the driver's, so on one machine the in-process search, which already runs on every
core, stays the default.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from jsve.core._objective import ObjectiveConfig
from jsve.fitting._search import RESULT_FIELDS, SearchResult
from jsve.fitting._space import ParamSpace
from jsve.io import _scheduler

SETTINGS_PER_TASK = 256
"""Settings per task: enough setting-runs for a task to outweigh its scheduling (a few ms) and the
transfer of its [settings, R] results (256 settings x 3,400 runs x ~30 B is about 26 MB), few enough
that a design of 2,048 settings keeps 8 workers busy."""


MIN_SETTING_RUNS = 65536
"""Requests of fewer settings x runs are scored in the driver's process (jsve.fitting._scorer): eight
kernel calls' worth of lanes on a CPU, less than a round trip of tasks to the workers and their
results back; a fit's verdict of a few settings stays local, its searches go out."""


@functools.lru_cache(maxsize=1)
def _worker_data(source: str, config: ObjectiveConfig, stamp: tuple[int, int]):
    """The study as this worker process holds it (one at a time): loaded by the first task, reused by
    the next (stamp: the file's size and mtime, so a rewritten file is loaded again)."""
    from jsve.fitting._data import FitData

    return FitData.from_parquet(source, config)


def _stamp(source: str) -> tuple[int, int]:
    stat = Path(source).stat()
    return stat.st_size, stat.st_mtime_ns


def search_task(
    source: str, config: ObjectiveConfig, space: ParamSpace, values: np.ndarray, runs: np.ndarray | None
) -> tuple[str | None, dict[str, np.ndarray]]:
    """One shard on a worker: `search` of `values` on the study's runs (all, or the global indices
    `runs`, in increasing order). Returns (the content digest the worker read, the [s, R] arrays)."""
    data = _worker_data(source, config, _stamp(source))
    result = data.scorer.score(space, values, runs)  # the worker's own scorer: in its process
    return data.content_digest, {name: getattr(result, name) for name in RESULT_FIELDS}


@dataclass
class ShardedSearch:
    """The search of a Parquet study's settings across the workers of `scheduler`.

    The workers (a LocalCluster or process pool is started by the first call) are kept until `close`
    (or the end of a `with` block), so that each loads the study once for all the fit's searches.

    Attributes:
        source: the Parquet study (made absolute: workers open it by this path).
        config: the objective the runs are scored under (the driver's FitData.config).
        digest: the driver's FitData.content_digest, which every worker's must equal.
        scheduler: "local" (an embedded LocalCluster of `workers` processes), "processes", or a Dask
            scheduler address or scheduler file (jsve.io._scheduler).
        workers: processes of a local cluster or pool.
        settings_per_task: settings per task (SETTINGS_PER_TASK).
        min_setting_runs: smaller requests are scored in the driver's process (MIN_SETTING_RUNS).
    """

    source: str
    config: ObjectiveConfig
    digest: str | None
    scheduler: str = _scheduler.LOCAL
    workers: int = 2
    settings_per_task: int = SETTINGS_PER_TASK
    min_setting_runs: int = MIN_SETTING_RUNS
    _stack: contextlib.ExitStack | None = field(default=None, init=False, repr=False, compare=False)
    _pool: concurrent.futures.Executor | None = field(default=None, init=False, repr=False, compare=False)

    def __enter__(self) -> ShardedSearch:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the workers a local scheduler started (a remote cluster's keep running)."""
        stack, self._stack, self._pool = self._stack, None, None
        if stack is not None:
            stack.close()

    def _executor(self) -> concurrent.futures.Executor:
        if self._pool is None:
            self._stack = contextlib.ExitStack()
            self._pool = self._stack.enter_context(_scheduler.executor(max(1, self.workers), self.scheduler))
        return self._pool

    @classmethod
    def of(cls, data, scheduler: str | None, workers: int = 2, **kwargs) -> ShardedSearch:
        """The sharded search of FitData `data`, which must come from a Parquet study."""
        if data.source is None:
            raise ValueError("a sharded search needs FitData streamed from a Parquet study (from_parquet)")
        return cls(
            _scheduler.absolute(data.source.path),
            data.config,
            data.content_digest,
            _scheduler.check_scheduler(scheduler),
            int(workers),
            **kwargs,
        )

    def __call__(
        self,
        space: ParamSpace,
        values,
        runs: Sequence[int] | np.ndarray | None = None,
        *,
        progress: bool = False,
        desc: str = "search",
    ) -> SearchResult:
        """`search` of `values` ([S, d] free values of `space`) on every run, or on the global run
        indices `runs` (their results in increasing run order), as the local search returns it."""
        values = np.asarray(values, np.float64)
        picked = None if runs is None else np.unique(np.asarray(runs, np.int64))
        size = max(1, int(self.settings_per_task))
        shards = [slice(i, min(i + size, len(values))) for i in range(0, len(values), size)]
        out: list[dict | None] = [None] * len(shards)
        n_runs = None if picked is None else len(picked)
        pool = self._executor()
        futures = {
            pool.submit(search_task, self.source, self.config, space, values[sl], picked): k
            for k, sl in enumerate(shards)
        }
        try:
            with tqdm(total=len(values), desc=desc, unit="setting", disable=not progress) as bar:
                for future in concurrent.futures.as_completed(futures):
                    k = futures[future]
                    digest, arrays = future.result()
                    if digest != self.digest:
                        raise RuntimeError(
                            f"a worker read other content at {self.source} (digest {digest} against "
                            f"{self.digest}): every worker must see the same file"
                        )
                    out[k] = arrays
                    bar.update(shards[k].stop - shards[k].start)
        except BaseException:
            for future in futures:
                future.cancel()
            raise
        shards_out = [o for o in out if o is not None]
        assert len(shards_out) == len(shards)
        if n_runs is not None and shards_out[0]["loss"].shape[1] != n_runs:
            raise RuntimeError(f"a shard returned {shards_out[0]['loss'].shape[1]} runs, not {n_runs}")
        arrays = {name: np.concatenate([o[name] for o in shards_out]) for name in RESULT_FIELDS}
        return SearchResult(values=values, **arrays)


__all__ = ["ShardedSearch", "search_task", "SETTINGS_PER_TASK", "MIN_SETTING_RUNS"]
