"""`jsve demo`: simulate a study, evaluate the presets, fit, cross-validate and write the threshold report.

Everything in one output folder, without ../shared (procedural EuRoC-like flights):

    OUT/logs/           the simulated format-v1 logs and logs/study.parquet (jsve.sim._study.write_study)
    OUT/*.parquet|csv   every table of the study (jsve.fitting._study)
    OUT/report.md|html  the report (jsve.report._report), OUT/figures/

Each stage is resumable: a rerun with the same configuration skips simulated logs and finished stages.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

from jsve.fitting._config import StudyConfig
from jsve.fitting._fit import FitConfig

log = logging.getLogger(__name__)

DEMO_STUDY = StudyConfig(
    fit=FitConfig(n_search=1024, n_starts=1, nm_steps=60, relaxed=False),
    kfold=5,
    leave_one_out=("sequence", "disturbance"),
    n_boot=1000,
    n_local=512,
    heatmap=("imu_init", "recovery", 21),
)
"""The demo's study: a 1,024-point Sobol search and one Nelder-Mead polish per family and fold, 5-fold and
leave-one-sequence/disturbance-out cross-validation, 1,000 bootstrap resamples (sweeps/demo.toml)."""


@dataclass(frozen=True)
class DemoConfig:
    """The simulated study of the demo and the study run on it.

    Attributes:
        sequences: procedural EuRoC-like flights. runs: runs per (sequence, setting).
        duration_s: range of flight lengths, s (equal by default: one padded shape, one compilation).
        disturbances: settings spec ("seed": the seed's 31).
        seed: simulator seed. study: jsve.fitting._config.StudyConfig.
    """

    sequences: int = 3
    runs: int = 2
    duration_s: tuple[float, float] = (60.0, 60.0)
    disturbances: str = "seed"
    seed: int = 0
    study: StudyConfig = field(default_factory=lambda: DEMO_STUDY)

    @classmethod
    def from_dict(cls, spec: dict, source: str = "<config>") -> DemoConfig:
        """From a parsed TOML file: a [demo] table for the simulation, the rest a StudyConfig."""
        spec = dict(spec)
        demo = dict(spec.pop("demo", {}))
        known = {f.name for f in fields(cls)} - {"study"}
        bad = sorted(set(demo) - known)
        if bad:
            raise ValueError(f"{source}: unknown [demo] settings {bad}; known: {sorted(known)}")
        if "duration_s" in demo:
            demo["duration_s"] = tuple(demo["duration_s"])
        return cls(**demo, study=StudyConfig.merged(spec, DEMO_STUDY, source))


def run_demo(
    out_dir: str | os.PathLike = "jsve-demo",
    config: DemoConfig = DemoConfig(),
    *,  # noqa: B008
    progress: bool = True,
    workers: int | None = None,
    force: bool = False,
) -> dict:
    """Simulate, fit, cross-validate and report into `out_dir`; returns the seconds of each part.

    A rerun resumes: the logs are kept under an equal generator key (write_study) and the study's stages
    under an equal configuration and data fingerprint (run_study). Where `out_dir` holds logs or a study
    of another configuration the demo stops with StaleOutputError before writing anything, unless
    `force`, which discards them and recomputes.
    """
    from jsve.fitting._data import FitData
    from jsve.fitting._study import run_study
    from jsve.report._report import write_report
    from jsve.sim._config import SimConfig
    from jsve.sim._study import write_study
    from jsve.sim._trajectory import FlightProfile

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    started = time.perf_counter()
    sim = SimConfig(flight=FlightProfile(duration_s=tuple(config.duration_s)))
    log.info(
        "simulating %d sequences x %s settings x %d runs", config.sequences, config.disturbances, config.runs
    )
    study = write_study(
        out / "logs",
        procedural=config.sequences,
        disturbances=config.disturbances,
        runs=config.runs,
        seed=config.seed,
        config=sim,
        workers=workers,
        progress=progress,
        parquet=True,
        force=force,
    )
    timings["simulate"] = time.perf_counter() - started

    t = time.perf_counter()
    data = FitData.from_parquet(study.parquet, config.study.objective())
    description = {
        "source": "jsve simulator (procedural EuRoC-like flights)",
        "sequences": config.sequences,
        "settings": config.disturbances,
        "runs per setting": config.runs,
        "flight length, s": list(config.duration_s),
        "simulator seed": config.seed,
    }
    stages = run_study(data, out, config.study, progress=progress, data_description=description, force=force)
    timings["study"] = time.perf_counter() - t
    t = time.perf_counter()
    write_report(out, title="jsve demo: fitted switching rules on a simulated study")
    timings["report"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - started
    timings["stages"] = {k: v.get("seconds") for k, v in stages.items()}
    return timings


__all__ = ["DemoConfig", "DEMO_STUDY", "run_demo"]
