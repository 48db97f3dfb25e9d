"""Peak memory of the fit's large steps on a Parquet study, with jsve's memory release on and off.

Runs, each in a fresh process (so that peaks are its own): load the study (FitData.from_parquet), the
fit of one family with its search (the default `search = "auto"`, no polish), then the cross-validation
folds' halving searches in step, as `jsve fit` runs them; the resident set size is sampled every 0.5 s
during the folds' halving. `--release off` sets JSVE_RELEASE_MEMORY=0 (jsve._memory: executables and
freed heap kept).

    python benchmarks/bench_fit_memory.py STUDY.parquet [--family inliers]

Measured on the 3,410-log study (docs/fitting.md, Limits): 19 folds' halving of the inlier family
peaked at 3.67 GB and left 2.61 GB with the release, 4.21 and 4.21 GB without.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import threading
import time


def _resident_gb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def measure(study: str, family: str) -> None:
    """The measurement, in this process (one line on stdout)."""
    from jsve.cli import use_all_cores
    from jsve.evaluation import group_weights
    from jsve.fitting import FitData, StudyConfig, fit
    from jsve.fitting._fit import resolve_search
    from jsve.fitting._halving import halving_searches, stratified_order
    from jsve.fitting._study import study_folds

    use_all_cores()
    config = StudyConfig()
    data = FitData.from_parquet(study, config.objective())
    loaded = _resident_gb()
    weights = group_weights(data.meta, [c for c in config.balance_by if c in data.meta.columns])
    fit_config = resolve_search(config.fit, data.n_runs)
    if fit_config.search != "halving":
        raise SystemExit(f"{data.n_runs} runs: the default search is {fit_config.search}, not halving")
    t = time.perf_counter()
    no_polish = dataclasses.replace(fit_config, n_starts=0)
    result = fit(data, config.space(family), weights, no_polish, progress=False)
    searched, search_s = _resident_gb(), time.perf_counter() - t
    assert result.cache is not None
    folds = study_folds(data.meta, config)
    peak, stop = [0.0], threading.Event()

    def sample():
        while not stop.is_set():
            peak[0] = max(peak[0], _resident_gb())
            time.sleep(0.5)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t = time.perf_counter()
    halving_searches(
        result.cache,
        [weights * ~f.test for f in folds],
        eta=fit_config.eta,
        initial_fraction=fit_config.initial_fraction,
        order=stratified_order(data.meta, data.n_runs, seed=fit_config.seed),
    )
    stop.set()
    sampler.join()
    print(
        f"loaded {loaded:.2f} GB; {family} search {search_s:.0f} s, then {searched:.2f} GB; {len(folds)} "
        f"folds' halving {time.perf_counter() - t:.0f} s: peak {peak[0]:.2f} GB, "
        f"after {_resident_gb():.2f} GB",
        flush=True,
    )


def main(argv=None) -> int:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("study")
    parser.add_argument("--family", default="inliers", choices=("sve", "inliers"))
    parser.add_argument("--release", choices=("on", "off", "both"), default="both")
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.inner:
        measure(args.study, args.family)
        return 0
    for release in ("on", "off") if args.release == "both" else (args.release,):
        env = {**os.environ, "JSVE_RELEASE_MEMORY": "1" if release == "on" else "0"}
        print(f"release {release}: ", end="", flush=True)
        cmd = [sys.executable, __file__, args.study, "--family", args.family, "--inner"]
        done = subprocess.run(cmd, env=env, check=False)
        if done.returncode:
            return done.returncode
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
