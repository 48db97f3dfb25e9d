"""Exhaustive search, successive halving and Optuna's TPE on one simulated study, side by side.

    pip install -e '.[bench]'                        # optuna
    python benchmarks/bench_fit_search.py              # 3 EuRoC sequences x 31 settings x 1 run (93 logs)
    python benchmarks/bench_fit_search.py --full       # the 3,410-log EuRoC study (11 x 31 x 10)

The study is simulated once (jsve.sim.write_study, kept in --study-dir and reused). Each method then
runs in its own process, so that its peak RSS is its own: it fits every family on all runs (the fit a
user gets) and in k folds over runs (held-out objective), each fit the search stage alone by default
(`--starts N` adds N Nelder-Mead polishes to every fit). The three searches share the objective (the
hard objective of jsve fit: failed runs at the penalty, runs weighted so every sequence x disturbance x
level group counts equally) and the runs:

- exhaustive: a Sobol design of --settings settings on every training run. Folds reuse the search over
  all runs (a fold only reweights it), as `jsve fit` does.
- halving: the same design, successive halving over runs (--eta, --initial-fraction); the folds reuse
  the full fit's cache of per-run results.
- tpe: optuna's TPESampler over the same box, each trial scored on every training run, in batches of
  --tpe-batch trials (ask/tell), with as many trials as halving's cost in setting-runs buys (its rungs'
  nominal cost on the fold's training runs divided by their number). Folds share nothing.

Printed per family: the held-out objective (mean over runs of each fold's fitted rule on its held-out
runs, 95% bootstrap CI over runs) and its paired difference to the exhaustive search; wall time of the
fit on all runs and of the k folds; setting-runs scored; peak RSS of the process. Wall times include
JAX's compilation (fresh processes, no persistent cache), or, with --warm, are those of each method's
second run with the persistent compilation cache its first filled (what a second `jsve fit` costs);
they depend on the machine's load: the script prints the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EUROC = "MH_01,MH_02,MH_03,MH_04,MH_05,V1_01,V1_02,V1_03,V2_01,V2_02,V2_03"
METHODS = ("exhaustive", "halving", "tpe")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--full", action="store_true", help="the 3,410-log study: 11 EuRoC sequences x 31 x 10 runs"
    )
    p.add_argument("--sequences", default="MH_01,V1_01,V2_01", help="EuRoC sequences (default: %(default)s)")
    p.add_argument("--runs", type=int, default=1, help="runs per sequence and setting (default: %(default)s)")
    p.add_argument(
        "--euroc-gt",
        default=str(Path(__file__).resolve().parents[2] / "shared/data/euroc/groundtruth_left_cam"),
    )
    p.add_argument(
        "--study-dir", help="where the simulated logs are kept (default: a folder in /tmp per size)"
    )
    p.add_argument("--families", default="sve,inliers", help="rule families (default: %(default)s)")
    p.add_argument("--settings", type=int, default=1024, help="design size (default: %(default)s)")
    p.add_argument("--folds", type=int, default=3, help="k of the k-fold over runs (default: %(default)s)")
    p.add_argument("--starts", type=int, default=0, help="Nelder-Mead polishes per fit (default: 0)")
    p.add_argument("--eta", type=float, default=3.0)
    p.add_argument("--initial-fraction", type=float, default=1 / 9)
    p.add_argument("--tpe-batch", type=int, default=16, help="TPE trials asked per kernel call")
    p.add_argument("--methods", default=",".join(METHODS), help="(default: %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--warm",
        action="store_true",
        help="time each method's second run, with JAX's persistent compilation cache filled by its first "
        "(as a second `jsve fit`); default: fresh processes that compile everything",
    )
    p.add_argument("--json", help="write every figure here")
    p.add_argument("--child", help=argparse.SUPPRESS)  # a method run in its own process
    p.add_argument("--logs", help=argparse.SUPPRESS)
    p.add_argument("--jax-cache", help=argparse.SUPPRESS)
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    if args.full:
        args.sequences, args.runs = EUROC, 10
    if args.child:
        return _child(args)
    try:
        import optuna  # noqa: F401
    except ImportError:
        print(
            "bench_fit_search: optuna is not installed; install the benchmark extra: "
            "pip install -e '.[bench]'",
            file=sys.stderr,
        )
        return 2
    logs = _simulate(args)
    load = os.getloadavg()
    results = {}
    with tempfile.TemporaryDirectory(prefix="jsve-bench-jax-") as jax_cache:
        for method in args.methods.split(","):
            child = [sys.executable, __file__, *(argv if argv is not None else sys.argv[1:])]
            child += ["--child", method, "--logs", str(logs)]
            if args.warm:  # a first run fills the cache, the second is timed
                child += ["--jax-cache", str(Path(jax_cache) / method)]
                print(f"running {method} (to fill the compilation cache) ...", flush=True)
                subprocess.run(child, check=True, capture_output=True, text=True)
            print(f"running {method} ...", flush=True)
            out = subprocess.run(child, check=True, capture_output=True, text=True).stdout
            results[method] = json.loads(out.strip().splitlines()[-1])
    load_after = os.getloadavg()
    print(f"load average (1, 5, 15 min) before: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; after: "
          f"{load_after[0]:.1f} {load_after[1]:.1f} {load_after[2]:.1f}; {os.cpu_count()} cores")  # fmt: skip
    summary = _summarise(results, args)
    if args.json:
        Path(args.json).write_text(
            json.dumps({"args": vars(args), "load": [load, load_after], **summary}, indent=1)
        )
    return 0


# ---------------------------------------------------------------------------------------------------
# The study


def _simulate(args) -> Path:
    """The study's Parquet file (simulated once per size and kept)."""
    from jsve.sim import write_study

    names = args.sequences.split(",")
    folder = Path(args.study_dir or f"/tmp/jsve-bench-fit-search/{len(names)}seq-{args.runs}runs")
    t = time.perf_counter()
    result = write_study(
        folder,
        names,
        euroc_gt=args.euroc_gt,
        runs=args.runs,
        seed=args.seed,
        workers=2,
        progress=False,
        parquet=True,
    )
    seconds = time.perf_counter() - t
    print(
        f"study: {len(names)} sequences x 31 settings x {args.runs} runs in {folder} "
        f"({result.written} logs simulated, {result.skipped} kept, {seconds:.0f} s)",
        flush=True,
    )
    return folder / "study.parquet"


# ---------------------------------------------------------------------------------------------------
# One method, in its own process


def _rss_mb() -> float:
    """Current resident set size, MB (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _child(args) -> int:
    from jsve.cli import use_all_cores

    use_all_cores()  # as jsve fit: one XLA CPU device per core
    if args.jax_cache:  # JAX's persistent compilation cache, as jsve fit sets it (every computation)
        import jax

        jax.config.update("jax_compilation_cache_dir", args.jax_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    from jsve.evaluation import group_weights
    from jsve.fitting import FitConfig, FitData, StudyConfig, inlier_space, kfold, sve_space
    from jsve.io import read_parquet

    study = StudyConfig()
    data = FitData.from_runs(read_parquet(args.logs), study.objective())
    by = [c for c in study.balance_by if c in data.meta.columns]
    weights = group_weights(data.meta, by)
    rss_loaded = _rss_mb()
    folds = kfold(data.n_runs, args.folds, seed=args.seed)
    config = FitConfig(
        n_search=args.settings,
        seed=args.seed,
        include_presets=False,  # the same box and nothing else for all three searches
        n_starts=args.starts,
        search="halving" if args.child == "halving" else "exhaustive",
        eta=args.eta,
        initial_fraction=args.initial_fraction,
    )
    spaces = {"sve": sve_space(), "inliers": inlier_space()}
    out = {"method": args.child, "runs": data.n_runs, "frames": data.n_frames, "rss_loaded_mb": rss_loaded}
    out["families"] = {}
    for family in args.families.split(","):
        space = spaces[family]
        run = _tpe_family if args.child == "tpe" else _jsve_family
        out["families"][family] = run(data, space, family, weights, folds, config, args)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(out))
    return 0


def _heldout_rows(folds, fitted, weights) -> list[dict]:
    """Per held-out run: fold, run index, weight, and the loss, failure and coverage of that fold's fitted
    setting (fitted: per fold a [1, R] SearchResult)."""
    rows = []
    for fold, res in zip(folds, fitted, strict=True):
        for i in np.flatnonzero(fold.test):
            rows.append(_row(fold.name, i, weights[i], res.loss[0, i], res.failed[0, i], res.coverage[0, i]))
    return rows


def _row(fold: str, run: int, weight: float, loss: float, failed: bool, coverage: float) -> dict:
    return {
        "fold": fold,
        "run_index": int(run),
        "weight": float(weight),
        "loss": float(loss),
        "failed": bool(failed),
        "coverage": float(coverage),
    }


def _jsve_family(data, space, family, weights, folds, config, args) -> dict:
    """The exhaustive or halving search, through jsve.fitting.fit and cross_validate (as jsve fit)."""
    from jsve.fitting import cross_validate, fit
    from jsve.fitting._fit import fitted_rule_name

    t = time.perf_counter()
    full = fit(data, space, weights, config, progress=False)
    t_full = time.perf_counter() - t
    cost_full = full.cache.evaluations if full.cache is not None else config.n_search * data.n_runs
    t = time.perf_counter()
    reuse = (
        {"caches": {family: full.cache}} if full.cache is not None else {"searches": {family: full.search}}
    )
    cv = cross_validate(data, {family: space}, folds, weights, config, presets=(), progress=False, **reuse)
    t_cv = time.perf_counter() - t
    cost_cv = full.cache.evaluations - cost_full if full.cache is not None else 0
    held = cv.heldout[cv.heldout["rule"] == fitted_rule_name(family)]
    rows = [_row(r.fold, r.run_index, r.weight, r.loss, r.failed, r.coverage) for r in held.itertuples()]
    return {
        "objective_all_runs": full.objective,
        "seconds_full": t_full,
        "seconds_cv": t_cv,
        "setting_runs_full": int(cost_full),
        "setting_runs_cv": int(cost_cv),
        "heldout": rows,
    }


def _tpe_search(data, space, weights, n_trials: int, batch: int, seed: int):
    """optuna's TPE over the space's box on the hard objective with run weights; returns (values, objective,
    setting-runs scored)."""
    import optuna

    from jsve.fitting import search

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
    names, lo, hi = list(space.names), np.asarray(space.lo), np.asarray(space.hi)
    runs = int(np.sum(weights > 0))
    done = 0
    while done < n_trials:
        trials = [study.ask() for _ in range(min(batch, n_trials - done))]
        values = np.asarray(
            [
                [t.suggest_float(n, float(a), float(b)) for n, a, b in zip(names, lo, hi, strict=True)]
                for t in trials
            ]
        )
        objective = search(
            data.parts, space, values, data.config, run_counts=data.run_counts, progress=False
        ).objective(weights)
        for trial, value in zip(trials, objective, strict=True):
            study.tell(trial, float(value))
        done += len(trials)
    best = study.best_trial
    return np.asarray([best.params[n] for n in names]), float(best.value), n_trials * runs


def _tpe_budget(n_settings: int, n_train: int, eta: float, f0: float) -> int:
    """Trials that halving's nominal cost on n_train runs buys: sum over rungs of settings x runs new to
    the rung, divided by n_train (each trial is scored on every training run)."""
    from jsve.fitting._halving import rung_sizes

    cost, seen = 0, 0
    for settings, runs in rung_sizes(n_settings, n_train, eta, f0):
        cost += settings * (runs - seen)
        seen = runs
    return math.ceil(cost / n_train)


def _tpe_family(data, space, family, weights, folds, config, args) -> dict:
    """TPE on all runs, then on each fold's training runs (nothing shared), scored on the held-out runs."""
    from jsve.fitting import nelder_mead, search

    def fit_tpe(w):
        n_train = int(np.sum(w > 0))
        trials = _tpe_budget(args.settings, n_train, args.eta, args.initial_fraction)
        values, value, cost = _tpe_search(data, space, w, trials, args.tpe_batch, args.seed)
        if args.starts:  # a polish as jsve's fits get (one start: TPE's best)
            values, value, _ = nelder_mead(
                data, space, values, w, max_steps=config.nm_steps, step=config.nm_step
            )
        return values, value, cost

    t = time.perf_counter()
    _, objective, cost_full = fit_tpe(weights)
    t_full = time.perf_counter() - t
    t, fitted, cost_cv = time.perf_counter(), [], 0
    for fold in folds:
        values, _, cost = fit_tpe(weights * ~fold.test)
        res = search(data.parts, space, values[None], data.config, run_counts=data.run_counts, progress=False)
        fitted.append(res)
        cost_cv += cost
    t_cv = time.perf_counter() - t
    return {
        "objective_all_runs": objective,
        "seconds_full": t_full,
        "seconds_cv": t_cv,
        "setting_runs_full": int(cost_full),
        "setting_runs_cv": int(cost_cv),
        "heldout": _heldout_rows(folds, fitted, weights),
    }


# ---------------------------------------------------------------------------------------------------
# The table


def _summarise(results: dict, args) -> dict:
    import pandas as pd

    from jsve.fitting import compare

    first = next(iter(results.values()))
    print(
        f"\n{first['runs']} runs, {first['frames']:,} frames; design {args.settings} settings; "
        f"{args.folds}-fold over runs; halving eta {args.eta:g}, initial fraction "
        f"{args.initial_fraction:.3g}; Nelder-Mead starts {args.starts}"
    )
    summary = {}
    for family in args.families.split(","):
        rows = []
        for method, res in results.items():
            for r in res["families"][family]["heldout"]:
                rows.append({**r, "rule": method, "fold_kind": "kfold"})
        table = compare(pd.DataFrame(rows), baselines=("exhaustive",), seed=args.seed)
        base = results.get("exhaustive", {}).get("families", {}).get(family)
        print(f"\n{family}: held-out objective (m, 95% CI over runs), paired difference to exhaustive, cost")
        header = ("method", "held-out objective", "vs exhaustive", "fit s", "folds s", "total s",
                  "time ratio", "setting-runs", "peak RSS GB")  # fmt: skip
        print(" | ".join(header))
        summary[family] = {}
        for method, res in results.items():
            fam = res["families"][family]
            row = table[table["rule"] == method].iloc[0]
            total = fam["seconds_full"] + fam["seconds_cv"]
            ratio = total / (base["seconds_full"] + base["seconds_cv"]) if base else float("nan")
            diff = (
                f"{row['diff_vs_exhaustive']:+.4f} [{row['diff_vs_exhaustive_ci_low']:+.4f}, "
                f"{row['diff_vs_exhaustive_ci_high']:+.4f}]"
                if method != "exhaustive" and "diff_vs_exhaustive" in row
                else ""
            )
            cost = fam["setting_runs_full"] + fam["setting_runs_cv"]
            print(" | ".join([
                method,
                f"{row['mean_loss']:.4f} [{row['ci_low']:.4f}, {row['ci_high']:.4f}]",
                diff,
                f"{fam['seconds_full']:.1f}",
                f"{fam['seconds_cv']:.1f}",
                f"{total:.1f}",
                f"{ratio:.2f}",
                f"{cost:,}",
                f"{res['peak_rss_mb'] / 1024:.2f}",
            ]))  # fmt: skip
            summary[family][method] = {
                **{k: v for k, v in fam.items() if k != "heldout"},
                "heldout_mean": float(row["mean_loss"]),
                "heldout_ci": [float(row["ci_low"]), float(row["ci_high"])],
                "diff_vs_exhaustive": None if method == "exhaustive" else float(row["diff_vs_exhaustive"]),
                "diff_ci": None
                if method == "exhaustive"
                else [float(row["diff_vs_exhaustive_ci_low"]), float(row["diff_vs_exhaustive_ci_high"])],
                "time_ratio": ratio,
                "peak_rss_mb": res["peak_rss_mb"],
                "rss_loaded_mb": res["rss_loaded_mb"],
            }
    return summary


if __name__ == "__main__":
    sys.exit(main())
