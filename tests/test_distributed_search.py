"""jsve.fitting._distributed: the fit's search sharded over Dask workers that each stream the same
Parquet study equals the search in this process, setting by setting and run by run."""

from __future__ import annotations

import dataclasses
import logging

import knownanswer as ka
import numpy as np
import pytest

from jsve.fitting._data import FitData
from jsve.fitting._distributed import ShardedSearch
from jsve.fitting._fit import FitConfig, fit
from jsve.fitting._packing import subset_parts
from jsve.fitting._search import search
from jsve.fitting._space import inlier_space, sve_space
from jsve.io._logs import write_log
from jsve.io._parquet import ingest

FIELDS = ("loss", "failed", "rmse", "coverage", "unsupported", "included")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """14 known-answer runs of two lengths (two parts), ingested into one Parquet file."""
    tmp = tmp_path_factory.mktemp("sharded")
    runs = ka.make_study("occlusion", range(8), n_frames=300)
    runs += ka.make_study("counts", range(6), n_frames=520)
    paths = [write_log(run, tmp / "logs" / f"r{i:02d}.csv") for i, run in enumerate(runs)]
    ingest(paths, tmp / "s.parquet", workers=1, progress=False)
    data = FitData.from_parquet(tmp / "s.parquet")
    assert len(data.parts) == 2
    return data


@pytest.fixture(scope="module")
def address():
    """A Dask cluster of two single-threaded worker processes reached through its scheduler's address
    on loopback, as `dask scheduler` + `dask worker` would make one."""
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=":0",
        scheduler_kwargs={"dashboard": False}, silence_logs=logging.ERROR,
    )  # fmt: skip
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close(timeout=30)


@pytest.fixture(scope="module")
def pool(study):
    """The study's sharded search on a process pool of 2 workers, 16 settings a task, started by its
    first search and kept for the module's tests (each worker imports jsve, loads the study and
    compiles its kernels once)."""
    with ShardedSearch.of(study, "processes", settings_per_task=16) as sharded:
        yield sharded


def _values(space, n: int, seed: int = 0) -> np.ndarray:
    unit = np.random.default_rng(seed).random((n, space.dim))
    return np.asarray(space.values_from_unit(unit), np.float64)


def _equal(a, b) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_shards_on_two_workers_equal_the_local_search(study, address):
    space = sve_space()
    values = _values(space, 21)
    sharded = ShardedSearch.of(study, address, settings_per_task=8)  # 3 tasks, the last of 5 settings
    local = search(study.parts, space, values, study.config, run_counts=study.run_counts, progress=False)
    _equal(sharded(space, values), local)
    # a halving rung's subset of the runs: the same columns, in increasing run order
    runs = np.array([13, 0, 2, 9, 5])
    parts, counts, columns = subset_parts(study.parts, study.run_counts, runs)
    assert list(columns) == sorted(runs)
    on_subset = search(parts, space, values, study.config, run_counts=counts, progress=False)
    _equal(sharded(space, values, runs), on_subset)


def test_a_fit_whose_searches_run_on_workers_fits_what_a_local_fit_fits(study, pool):
    """The halving search's rungs (all runs and subsets) and the polish on a process pool of 2 workers:
    the same rule, objective and search stage as in this process."""
    space = inlier_space()
    config = FitConfig(n_search=40, search="halving", initial_fraction=1 / 3, n_starts=1, nm_steps=10)
    local = fit(study, space, config=config, progress=False)
    sharded, calls = pool, []

    def searcher(space, values, runs, **kwargs):
        calls.append((len(values), None if runs is None else len(runs)))
        return sharded(space, values, runs, **kwargs)

    remote = fit(dataclasses.replace(study, searcher=searcher), space, config=config, progress=False)
    # every rung went through the workers (a plain callable takes every request): all 41 settings (40 +
    # the preset) on a third of the runs, then each rung's survivors on the runs they were not scored on
    # yet (one rectangle a rung), then the verdict on every run; the polish ran here (a view)
    rungs = len(remote.stages[0]["rungs"])
    assert calls[0] == (41, 5) and rungs > 1 and len(calls) == rungs + 1 and calls[-1][1] is None
    np.testing.assert_array_equal(remote.values, local.values)
    assert remote.objective == local.objective
    assert remote.stages[0]["rungs"] == local.stages[0]["rungs"]


def test_a_worker_that_reads_other_content_fails_the_search(pool, monkeypatch):
    """The driver's digest against the workers' (the workers of `pool`: a search of the fit's verdict's
    size, whose kernels a worker compiled for the fit above when that test ran first)."""
    monkeypatch.setattr(pool, "digest", "0" * 64)
    space = inlier_space()
    with pytest.raises(RuntimeError, match="a worker read other content"):
        pool(space, _values(space, 2))


def test_only_a_parquet_study_can_be_sharded():
    runs = ka.make_study("occlusion", range(2), n_frames=200)
    with pytest.raises(ValueError, match="streamed from a Parquet study"):
        ShardedSearch.of(FitData.from_runs(runs), "processes")


def test_jsve_fit_refuses_a_scheduler_it_cannot_use(tmp_path, capsys):
    """--scheduler shards the Parquet study's searches: a log folder, or a value that names no scheduler,
    stops with one line before anything is computed."""
    from jsve.cli import main

    logs = tmp_path / "logs"
    for i, run in enumerate(ka.make_study("occlusion", range(2), n_frames=200)):
        write_log(run, logs / f"r{i}.csv")
    assert main(["fit", str(logs), "-o", str(tmp_path / "out"), "--scheduler", "local", "--no-progress"]) == 2
    assert "--scheduler needs a Parquet study" in capsys.readouterr().err
    assert main(["fit", str(logs), "-o", str(tmp_path / "out"), "--scheduler", "no such thing"]) == 2
    assert "no such thing" in capsys.readouterr().err
