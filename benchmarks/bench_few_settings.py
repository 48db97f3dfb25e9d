"""Searches of few settings on a large study: a cross-validation verdict (11 settings on every run) and
a Nelder-Mead step of 19 folds x 2 starts (38 settings on the 256 polish runs packed by length class),
each timed three times after a first call that compiles.

    python benchmarks/bench_few_settings.py study.parquet

Such a search is one kernel call a part; where the parts sit decides how many cores run them
(jsve.fitting.search sends a part of one call to the XLA devices in turn). Prints seconds per search.
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", help="a Parquet study (jsve ingest)")
    parser.add_argument("--family", default="sve")
    args = parser.parse_args(argv)

    from jsve.cli import use_all_cores

    use_all_cores()
    import numpy as np

    from jsve.core import ObjectiveConfig
    from jsve.fitting import FitData, design, search, space_from_dict
    from jsve.fitting._halving import stratified_order
    from jsve.fitting._packing import subset_parts

    data = FitData.from_parquet(args.study, ObjectiveConfig())
    space = space_from_dict({"kind": args.family})
    values = np.asarray(space.values_from_unit(design("sobol", 64, space.dim, seed=0)), np.float64)
    # the polish runs of a fit on every run (jsve.fitting._polish.polish_runs): the first 256 in the order
    runs = np.sort(stratified_order(data.meta, data.n_runs, seed=0)[:256])
    packed, counts, _ = subset_parts(data.parts, data.run_counts, runs)
    parts = list(packed)
    for rep in range(4):
        t0 = time.perf_counter()
        search(parts, space, values[:38], data.config, run_counts=counts, progress=False)
        t1 = time.perf_counter()
        search(data.parts, space, values[:11], data.config, run_counts=data.run_counts, progress=False)
        t2 = time.perf_counter()
        label = "compiling" if rep == 0 else f"repeat {rep}"
        print(f"{label}: 38 settings x 256 packed runs {t1 - t0:.2f} s; 11 settings x {data.n_runs:,} runs "
              f"{t2 - t1:.2f} s", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
