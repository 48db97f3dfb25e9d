"""A subset of runs in one packed part against 2 and 4 length classes: seconds of a search of S settings
on the study's first N polish runs (jsve.fitting._polish.polish_runs), each layout timed on a second
call (the first compiles), with what jsve.fitting._packing.scan_cost predicts and what subset_layout
chooses (cheapest_layout).

    python benchmarks/bench_layout.py study.parquet [--family sve] [--runs 256 512] [--settings 2 10 38 400]

The measurements behind SCAN_STEP_LANES (docs/fitting.md, "Nelder-Mead on a subset of the runs").
Prints one line per (runs, settings): each layout's seconds and its cost-model units relative to one
part's, and the layout chosen.
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", help="a Parquet study (jsve ingest)")
    parser.add_argument("--family", default="sve")
    parser.add_argument("--runs", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--settings", type=int, nargs="+", default=[2, 10, 38, 100, 400])
    args = parser.parse_args(argv)

    from jsve.cli import use_all_cores

    use_all_cores()
    import numpy as np

    from jsve.core import ObjectiveConfig
    from jsve.fitting import FitData, design, search, space_from_dict
    from jsve.fitting._packing import (
        LAYOUT_CLASSES,
        cheapest_layout,
        layout_shapes,
        pack_runs,
        scan_cost,
        subset_parts,
    )
    from jsve.fitting._polish import polish_runs

    data = FitData.from_parquet(args.study, ObjectiveConfig())
    space = space_from_dict({"kind": args.family})
    values = np.asarray(
        space.values_from_unit(design("sobol", max(args.settings), space.dim, seed=0)), np.float64
    )
    shapes = [(p.n_frames, p.n_runs) for p in data.parts]

    def timed(parts, counts, v) -> float:
        search(parts, space, v, data.config, run_counts=counts, progress=False)  # compiles
        start = time.perf_counter()
        search(parts, space, v + 1e-4, data.config, run_counts=counts, progress=False)
        return time.perf_counter() - start

    for n_runs in args.runs:
        runs = polish_runs(data.meta, np.ones(data.n_runs), n_runs)
        if runs is None:
            print(f"{n_runs} runs: the study has no more, nothing to pack")
            continue
        layouts = {0: ([pack_runs(data.parts, data.run_counts, runs)], [len(runs)])}
        for k in LAYOUT_CLASSES:
            parts, counts, _ = subset_parts(data.parts, data.run_counts, runs, k)
            layouts[k] = (list(parts), counts)
        names = {k: "one part" if k == 0 else f"{k} classes" for k in layouts}
        print(
            f"{n_runs} runs: "
            + ", ".join(f"{names[k]} {layout_shapes(data.run_counts, shapes, runs, k)}" for k in layouts),
            flush=True,
        )
        for n in args.settings:
            v = values[:n]
            seconds = {k: timed(parts, counts, v) for k, (parts, counts) in layouts.items()}
            cost = {k: scan_cost(layout_shapes(data.run_counts, shapes, runs, k), n) for k in layouts}
            chosen = names[cheapest_layout(data.run_counts, shapes, runs, n)]
            cells = [f"{names[k]} {seconds[k]:6.2f} s ({seconds[k] / seconds[0]:4.2f}; "
                     f"model {cost[k] / cost[0]:4.2f})" for k in layouts]  # fmt: skip
            print(f"  {n:4d} settings: " + ", ".join(cells) + f"; chosen: {chosen}", flush=True)


if __name__ == "__main__":
    main()
