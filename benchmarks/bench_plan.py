"""The study's work counted by jsve.fitting._counting.plan (its stages against the counting scorer) at
the size of the 3,410-log EuRoC study, and how long the counting takes, without any logs: 11 sequences
of EuRoC's lengths x the seed's 31 settings x 10 runs, one part of 512 runs (310 real) per sequence.

    python benchmarks/bench_plan.py [--config sweeps/fit.toml]

Prints, per (stage, kind, family), the units (jsve.fitting._estimate.UNITS) and the Nelder-Mead steps
the count saw, then the seconds the count took (docs/fitting.md, "How long a fit takes").
"""

from __future__ import annotations

import argparse
import math
import time

import tomllib

EUROC_FRAMES = {
    "MH_01": 3682, "MH_02": 3040, "MH_03": 2700, "MH_04": 2033, "MH_05": 2273, "V1_01": 2912,
    "V1_02": 1710, "V1_03": 2149, "V2_01": 2280, "V2_02": 2348, "V2_03": 1922,
}  # fmt: skip
"""Frames of each EuRoC sequence (cam0, 20 Hz)."""


def euroc_size(config, runs_per_setting: int = 10):
    """A StudySize of the 3,410-log study's shape: every sequence x (clean + 10 levels of each of the
    three disturbances) x runs_per_setting runs."""
    import jax
    import pandas as pd

    from jsve.core._batch import ladder_chunk_size, runs_per_chunk_for
    from jsve.fitting._estimate import StudySize
    from jsve.fitting._fit import search_design
    from jsve.fitting._study import study_folds

    settings = [("none", "0")] + [(d, str(k)) for d in ("blur", "downsample", "occlusion") for k in range(10)]
    rows = [
        (f"{seq}-{dist}-{level}-{k}", seq, dist, level)
        for seq in EUROC_FRAMES
        for dist, level in settings
        for k in range(runs_per_setting)
    ]
    meta = pd.DataFrame(rows, columns=["run_id", "sequence", "disturbance", "level"])
    per_sequence = len(settings) * runs_per_setting
    chunks = []
    for frames in EUROC_FRAMES.values():
        size = ladder_chunk_size(per_sequence, runs_per_chunk_for(frames))
        chunks.append((math.ceil(per_sequence / size), size, frames))
    padded = 1 << (per_sequence - 1).bit_length()
    return StudySize(
        n_runs=len(meta),
        n_frames=per_sequence * sum(EUROC_FRAMES.values()),
        run_counts=(per_sequence,) * len(EUROC_FRAMES),
        parts=tuple((frames, padded) for frames in EUROC_FRAMES.values()),
        chunks=tuple(chunks),
        n_devices=len(jax.local_devices()),
        designs={f: len(search_design(config.space(f), config.fit)) for f in config.families},
        folds=tuple(fold.test for fold in study_folds(meta, config)),
        meta=meta,
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", help="a study's TOML (default: jsve fit's defaults)")
    args = parser.parse_args(argv)

    from jsve.fitting._config import StudyConfig
    from jsve.fitting._counting import plan

    config = StudyConfig()
    if args.config:
        with open(args.config, "rb") as f:
            config = StudyConfig.from_dict(tomllib.load(f), source=args.config)
    size = euroc_size(config)
    started = time.perf_counter()
    work = plan(size, config)
    seconds = time.perf_counter() - started
    print(f"{size.n_runs:,} runs, {size.n_frames:,} frames, {len(size.folds)} folds")
    for w in work.work:
        print(f"  {w.stage:20s} {w.kind:9s} {w.family:8s} {w.units:12.4g}")
    steps = sorted(set(work.nelder_mead_steps))
    print(f"Nelder-Mead steps a run: {steps}; counted in {seconds:.1f} s")


if __name__ == "__main__":
    main()
