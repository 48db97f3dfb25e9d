"""The fit's search in this process against the same search sharded over Dask workers (`jsve fit
--scheduler`): wall time of a first call (workers start and load the study), of a second call (the
study held), and whether the results are equal.

    python benchmarks/bench_sharded_search.py STUDY.parquet [--settings 512] [--scheduler local]
        [--workers 2] [--family sve]

On one machine the local search already runs on every core (one XLA CPU device per core), so the
sharded one can only add its overhead there; on a cluster its second call divides by the workers.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from jsve.cli import use_all_cores
from jsve.fitting import FitData, StudyConfig, design
from jsve.fitting._distributed import ShardedSearch
from jsve.fitting._fit import search_all


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("study", help="a Parquet study (jsve ingest)")
    parser.add_argument("--settings", type=int, default=512)
    parser.add_argument("--scheduler", default="local")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--family", default="sve", choices=("sve", "inliers"))
    args = parser.parse_args(argv)
    use_all_cores()
    config = StudyConfig()
    t = time.perf_counter()
    data = FitData.from_parquet(args.study, config.objective())
    print(f"loaded {data.n_runs} runs, {data.n_frames:,} frames in {time.perf_counter() - t:.1f} s")
    space = config.space(args.family)
    values = np.asarray(space.values_from_unit(design("sobol", args.settings, space.dim, seed=1)))
    setting_runs = args.settings * data.n_runs

    t = time.perf_counter()
    search_all(data, space, values, progress=False)  # compiles
    t = time.perf_counter()
    local = search_all(data, space, values, progress=False)
    local_s = time.perf_counter() - t
    print(f"local (compiled): {local_s:.1f} s, {setting_runs / local_s:,.0f} setting-runs/s")

    with ShardedSearch.of(data, args.scheduler, args.workers) as sharded:
        times = []
        for _ in range(2):
            t = time.perf_counter()
            result = sharded(space, values)
            times.append(time.perf_counter() - t)
        equal = all(
            np.array_equal(getattr(result, k), getattr(local, k), equal_nan=True)
            for k in ("loss", "failed", "rmse", "coverage", "unsupported", "included")
        )
    print(
        f"sharded on {args.scheduler} ({args.workers} workers): first call {times[0]:.1f} s (workers load "
        f"and compile), second {times[1]:.1f} s ({setting_runs / times[1]:,.0f} setting-runs/s, "
        f"{times[1] / local_s:.2f}x the local search's time); equal to the local search: {equal}"
    )
    return 0 if equal else 1


if __name__ == "__main__":
    raise SystemExit(main())
