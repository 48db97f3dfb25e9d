"""Where a large fit's time goes: the search, the polishes and the verdicts, with the compilations each
triggers counted and timed (JAX's backend compile events).

    python benchmarks/profile_fit.py study.parquet --family sve [--folds 19]

On a Parquet study (`jsve ingest`), the steps one family's fit and its cross-validation run
(jsve.fitting: `fit_search`, `polish`, `judge`), each timed on its own, its compilations apart:

- the fit's search (halving or exhaustive, as `jsve fit` resolves it for the study's size);
- the polishes of one fit (FitConfig.n_starts Nelder-Mead runs on `polish_runs` packed runs), twice: the
  first compiles;
- the polishes of the cross-validation's folds (the study's folds: k-fold and leave-one-out, each from
  the full fit's search under its training weights), all in lockstep (`polish_fits`), against the
  one fit's polishes times the folds (one fit after the other, as before);
- the verdict of one fit (its candidates on every run), and the verdict of `--folds` fits at once (the
  cross-validation's), against as many one-setting passes over the study as the folds made before
  (4 a fold: two polishes' verdicts, the fitted setting's results, its held-out scoring).

JAX's persistent compilation cache is not used (every shape compiles, as on a first `jsve fit`).
Results are discarded: nothing is written.
"""

from __future__ import annotations

import argparse
import time


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", help="a Parquet study (jsve ingest)")
    parser.add_argument("--family", default="sve", choices=("sve", "inliers"))
    parser.add_argument("--folds", type=int, default=19, help="fits judged together (cross-validation)")
    args = parser.parse_args(argv)

    from jsve.cli import use_all_cores

    use_all_cores()  # one XLA CPU device per core, as jsve fit
    import jax.monitoring
    import numpy as np

    compiles: list[float] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **_: (
            compiles.append(secs) if name == "/jax/core/compile/backend_compile_duration" else None
        )
    )
    from jsve.core import ObjectiveConfig
    from jsve.evaluation import group_weights
    from jsve.fitting import FitConfig, FitData, StudyConfig, inlier_space, search, sve_space
    from jsve.fitting._fit import fit_search, judge, polish, polish_fits, resolve_search
    from jsve.fitting._study import study_folds

    def timed(label: str, fn):
        before, started = len(compiles), time.perf_counter()
        out = fn()
        seconds = time.perf_counter() - started
        print(
            f"{label}: {seconds:.1f} s, {len(compiles) - before} compilations "
            f"({sum(compiles[before:]):.1f} s)",
            flush=True,
        )
        return out, seconds

    data, _ = timed("load", lambda: FitData.from_parquet(args.study, ObjectiveConfig()))
    print(f"{data.n_runs} runs, {len(data.parts)} parts, {data.n_frames:,} frames", flush=True)
    weights = group_weights(data.meta)
    space = {"sve": sve_space(), "inliers": inlier_space()}[args.family]
    config = resolve_search(FitConfig(), data.n_runs)
    print(f"search: {config.search}, first rung {config.initial_fraction:.4f} of the runs", flush=True)
    (searched, _, _), _ = timed(
        f"search {args.family}", lambda: fit_search(data, space, weights, config, progress=False)
    )
    timed("polishes of one fit (first: compiles)", lambda: polish(data, space, weights, searched, config))
    polished, one = timed(
        "polishes of one fit (again)", lambda: polish(data, space, weights, searched, config)
    )
    steps = [s.get("steps") for s in polished.stages[1:]]
    print(f"  Nelder-Mead steps: {steps}", flush=True)
    study_fold_list = study_folds(data.meta, StudyConfig())
    trains = [weights * ~fold.test for fold in study_fold_list]
    fold_fits, together = timed(
        f"polishes of {len(trains)} folds in lockstep",
        lambda: polish_fits(data, space, [(t, searched) for t in trains], config, progress=True),
    )
    fold_steps = [s["steps"] for f in fold_fits for s in f.stages[1:]]
    print(
        f"  {len(fold_steps)} simplexes, steps {min(fold_steps)}-{max(fold_steps)}"
        f" (mean {np.mean(fold_steps):.1f});"
        f" one fit after another: ~{len(trains) * one:.1f} s ({len(trains) * one / together:.1f}x)",
        flush=True,
    )
    timed("verdict of one fit (first: compiles)", lambda: judge(data, space, [polished]))
    timed("verdict of one fit (again)", lambda: judge(data, space, [polished]))
    folds = [polished] * args.folds
    timed(f"verdict of {args.folds} fits at once (first)", lambda: judge(data, space, folds))
    _, together = timed(f"verdict of {args.folds} fits at once (again)", lambda: judge(data, space, folds))
    values = np.asarray(polished.candidates[0][1])[None]

    def one_pass():
        return search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)

    timed("one setting on every run (first: compiles)", one_pass)
    _, single = timed("one setting on every run (again)", one_pass)
    print(
        f"before: {4 * args.folds} one-setting passes for {args.folds} folds,"
        f" ~{4 * args.folds * single:.1f} s;"
        f" now one verdict, {together:.1f} s ({4 * args.folds * single / together:.1f}x)",
        flush=True,
    )


if __name__ == "__main__":
    main()
