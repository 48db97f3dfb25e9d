"""Rules run in the loop: the real front-end (or the simulator) as a Scorer, every run a kept file.

    Candidate           a named rule (presets keep their names; others are named by their content)
    Instance            one dataset and one seed: what runs are paired by
    Request             a candidate under a switch model on an instance
    OrbSlam3Frontend    the hooked ORB-SLAM3 (jsve.frontend's plan and run_one), in lockstep
    SimulatedFrontend   jsve's simulator: the replay of its ORB-SLAM3-rule log under the rule, to rehearse
    FrontendScorer      Scorer.score(space, values, runs) by running the rules in the loop
    run_row             a finished run's summary as a row: bounded loss, failure, events, cost

Every run lives in the pool, POOL/seeds-<base>/<sequence>/<disturbance>-<level>/<rule>-<switch model>/
run_<k>.* with seed base + k (ORB-SLAM3's own rule under "orbslam3" directly in the level's folder),
so a run already made is found again by any tuning that shares the pool, and a killed tuning loses
and repeats none (jsve.frontend._run: a run is finished once its summary is written, last).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from jsve.core._rules import PRESETS, Rule, preset, rule_kind, rule_to_dict
from jsve.fitting._scorer import Meter
from jsve.fitting._search import SearchResult

RUN_COLUMNS = (
    "candidate",
    "switch_model",
    "dataset",
    "sequence",
    "disturbance",
    "level",
    "seed",
    "outcome",
    "coverage",
    "ate_m",
    "failed",
    "loss_m",
    "resets",
    "new_maps",
    "loops",
    "switches",
    "recently_lost_share",
    "wall_s",
    "cpu_s",
    "log",
)
"""The columns of a run's row (`run_row`), and of a tuning's runs.csv."""


@dataclass(frozen=True)
class Candidate:
    """A rule with its name (`candidate_name`), where it came from and the round that proposed it."""

    name: str
    rule: Rule = field(compare=False)
    origin: str = field(default="preset", compare=False)
    round: int = field(default=0, compare=False)

    @classmethod
    def of(cls, rule: Rule, origin: str, round: int = 0) -> Candidate:
        return cls(candidate_name(rule), rule, origin, round)

    @classmethod
    def preset(cls, name: str, origin: str = "preset", round: int = 0) -> Candidate:
        return cls(name, preset(name), origin, round)


def candidate_name(rule: Rule) -> str:
    """A preset's name when the rule is one, else "<family>-<8 hex digits of its JSON>": the same rule
    always gets the same name, and with it the same runs in the pool."""
    spec = rule_to_dict(rule)
    for name in PRESETS:
        if rule_to_dict(preset(name)) == spec:
            return name
    digest = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:8]
    return f"{rule_kind(rule)}-{digest}"


@dataclass(frozen=True)
class Instance:
    """What runs are paired by: one dataset (a folder, or a simulator setting) and one seed."""

    dataset: str
    seed: int


@dataclass(frozen=True)
class Request:
    candidate: Candidate
    switch_model: str
    instance: Instance


def run_row(summary: dict, penalty_m: float, min_coverage: float) -> dict:
    """A finished run's outcome on the bounded loss: failed when it ended in anything but "ok", saved
    no trajectory jsve could score, or saved one covering less than `min_coverage` of the frames; its
    loss is then `penalty_m`, else min(ATE, penalty_m) of the saved trajectory (SE(3)-aligned, metres).
    Events are counted from the log (resets include ORB-SLAM3's full resets)."""
    coverage, ate = summary.get("saved_coverage"), summary.get("ate_from_log_m")
    outcome = summary.get("outcome", "missing")
    failed = outcome != "ok" or coverage is None or ate is None or coverage < min_coverage
    events = summary.get("events") or {}
    times = summary.get("time") or {}
    return {
        "outcome": outcome,
        "coverage": coverage,
        "ate_m": ate,
        "failed": bool(failed),
        "loss_m": float(penalty_m) if failed else min(float(ate), float(penalty_m)),
        "resets": events.get("reset", 0) + events.get("reset_all", 0),
        "new_maps": events.get("new_map", 0),
        "loops": events.get("loop", 0),
        "wall_s": summary.get("wall_seconds"),
        "cpu_s": times.get("cpu_s"),
    }


def switching(log: Path) -> dict:
    """How often a run's rule switched: `switches`, the frames that went from OK to RECENTLY_LOST, and
    `recently_lost_share`, the share of its tracked frames (OK or RECENTLY_LOST) in RECENTLY_LOST, from
    the log's state column (or the partial log of a run that did not finish); NaN without either."""
    import pandas as pd

    from jsve.io import schema

    path = log if log.is_file() else log.with_name(log.name + ".partial")
    try:
        state = pd.read_csv(path, comment="#", usecols=["state"])["state"].to_numpy()
    except (OSError, ValueError):
        return {"switches": np.nan, "recently_lost_share": np.nan}
    lost = state == schema.STATE_RECENTLY_LOST
    tracked = lost | (state == schema.STATE_OK)
    return {
        "switches": int(np.count_nonzero(lost[1:] & (state[:-1] == schema.STATE_OK))),
        "recently_lost_share": float(lost.sum() / tracked.sum()) if tracked.any() else np.nan,
    }


class Frontend(Protocol):
    """What runs rules in the loop and keeps every run's files in a pool."""

    def describe(self, dataset: str) -> tuple[str, str, float]:
        """(sequence, disturbance, level) of a dataset."""
        ...

    def run(self, requests: Sequence[Request], on_done: Callable[[Request, dict], None]) -> None:
        """Run every request not yet in the pool; on_done(request, summary) for each, made or found."""
        ...

    def log_path(self, request: Request) -> Path:
        """Where the request's log is (or will be)."""
        ...

    def read_log(self, request: Request):
        """The request's finished log with ground truth (a jsve RunLog), for replays."""
        ...


def seed_base(seed: int, check_base: int) -> int:
    """The pool's seed folder of a seed: training seeds from 0, the check's from its base."""
    return check_base if seed >= check_base else 0


@dataclass
class OrbSlam3Frontend:
    """The hooked ORB-SLAM3 of `jsve frontend build`, every run in lockstep (or paced) under its seed."""

    pool: Path
    build: Path
    vocabulary: Path
    settings: Path
    check_base: int
    lockstep: bool = True
    workers: int = 2
    scheduler: str | None = None
    timeout_s: float | None = None
    _logs: dict = field(default_factory=dict, repr=False)

    def describe(self, dataset: str) -> tuple[str, str, float]:
        from jsve.frontend._run import describe_dataset

        d = describe_dataset(Path(dataset))
        return d.sequence, d.disturbance, d.level

    def _plan(self, request: Request):
        """(job or None when finished, log path) of a request, by jsve.frontend._run.plan."""
        from jsve.frontend._run import plan

        seed = request.instance.seed
        base = seed_base(seed, self.check_base)
        k = seed - base
        todo, done = plan(
            self.build,
            [Path(request.instance.dataset)],
            runs=k + 1,
            out=self.pool / f"seeds-{base}",
            vocabulary=self.vocabulary,
            settings=self.settings,
            rule=(request.candidate.name, request.candidate.rule),
            switch_model=request.switch_model,
            mode="lockstep" if self.lockstep else "no-wait",
            seed=base,
        )
        job = next((j for j in todo if j.run == k), None)
        log = job.log if job is not None else next(p for p in done if p.name == f"run_{k:03d}.csv")
        self._logs[request] = log
        return job, log

    def log_path(self, request: Request) -> Path:
        return self._logs[request] if request in self._logs else self._plan(request)[1]

    def run(self, requests: Sequence[Request], on_done: Callable[[Request, dict], None]) -> None:
        from jsve.frontend._run import run_one
        from jsve.io import _scheduler

        pending = []
        for request in requests:
            job, log = self._plan(request)
            if job is None:
                on_done(request, _summary(log))
            else:
                pending.append((request, job))
        if not pending:
            return
        driver = (self.build / "bin" / "jsve_orbslam3").absolute()
        if not driver.is_file():
            raise FileNotFoundError(f"{driver}: no driver; run `jsve frontend build -o {self.build}` first")
        with _scheduler.executor(self.workers, self.scheduler, threads=True) as pool:
            futures = {
                pool.submit(run_one, driver, self.vocabulary.absolute(), job, timeout_s=self.timeout_s): r
                for r, job in pending
            }
            for future in concurrent.futures.as_completed(futures):
                on_done(futures[future], future.result())

    def read_log(self, request: Request):
        from jsve.io._groundtruth import associate_ground_truth
        from jsve.io._logs import read_log

        gt = Path(request.instance.dataset) / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        return associate_ground_truth(read_log(self.log_path(request)), gt, "euroc")


def _summary(log: Path) -> dict:
    return json.loads(log.with_suffix(".summary.json").read_text())


def parse_setting(dataset: str) -> tuple[str, str, float]:
    """A simulator dataset "SEQUENCE" or "SEQUENCE:DISTURBANCE=LEVEL" as (sequence, disturbance, level).

    Raises:
        ValueError naming the text when it is neither.
    """
    sequence, _, setting = dataset.partition(":")
    if not setting:
        return sequence, "none", 0.0
    disturbance, eq, level = setting.partition("=")
    try:
        if not (sequence and disturbance and eq):
            raise ValueError
        return sequence, disturbance, float(level)
    except ValueError:
        raise ValueError(
            f"simulator dataset {dataset!r}: expected SEQUENCE or SEQUENCE:DISTURBANCE=LEVEL"
        ) from None


@dataclass
class SimulatedFrontend:
    """jsve's simulator in the loop's place, to rehearse a tuning and to test it: a run of a rule on
    (setting, seed) is the replay, under that rule and switch model, of the simulator's run `seed` of
    the setting (which tracks with ORB-SLAM3's rule; the simulator has no rule-in-the-loop feedback).
    Its files are those of a real run: the log, and a summary written last, atomically."""

    pool: Path
    check_base: int
    study_seed: int = 0
    flight_s: float | None = None

    def describe(self, dataset: str) -> tuple[str, str, float]:
        return parse_setting(dataset)

    def log_path(self, request: Request) -> Path:
        sequence, disturbance, level = parse_setting(request.instance.dataset)
        base = seed_base(request.instance.seed, self.check_base)
        folder = self.pool / f"seeds-{base}" / sequence / f"{disturbance}-{level:g}"
        return (
            folder
            / f"{request.candidate.name}-{request.switch_model}"
            / f"run_{request.instance.seed - base:03d}.csv"
        )

    def _simulated(self, request: Request):
        from jsve.sim._config import SimConfig
        from jsve.sim._simulate import simulate_run
        from jsve.sim._trajectory import FlightProfile

        sequence, disturbance, level = parse_setting(request.instance.dataset)
        config = (
            SimConfig()
            if self.flight_s is None
            else SimConfig(flight=FlightProfile(duration_s=(self.flight_s,) * 2))
        )
        return simulate_run(
            sequence, disturbance, level, run=request.instance.seed, seed=self.study_seed, config=config
        )

    def run(self, requests: Sequence[Request], on_done: Callable[[Request, dict], None]) -> None:
        groups: dict[tuple[str, str], list[Request]] = {}
        for request in requests:
            if not request_summary(self, request).is_file():
                groups.setdefault((request.candidate.name, request.switch_model), []).append(request)
        for group in groups.values():
            for request, summary in zip(group, self._make(group), strict=True):
                _write_atomically(request_summary(self, request), json.dumps(summary, indent=2) + "\n")
        for request in requests:
            on_done(request, json.loads(request_summary(self, request).read_text()))

    def _make(self, group: Sequence[Request]) -> list[dict]:
        """The summaries of one candidate's runs under one switch model: their logs simulated and written,
        then replayed together (one evaluation)."""
        from jsve.evaluation import evaluate_rules
        from jsve.io._batching import buckets
        from jsve.io._logs import write_log

        logs = []
        for request in group:
            path = self.log_path(request)
            log = dataclasses.replace(self._simulated(request), source=str(path))
            path.parent.mkdir(parents=True, exist_ok=True)
            write_log(log, path)
            logs.append(log)
        candidate, model = group[0].candidate, group[0].switch_model
        table = evaluate_rules(
            buckets(logs), [(candidate.name, candidate.rule)], switch_model=model, progress=False
        )
        by_source = {str(row.source): row for row in table.itertuples()}
        out = []
        for request, log in zip(group, logs, strict=True):
            row = by_source[str(log.source)]
            tracked = not bool(row.failed) and np.isfinite(row.rmse)
            out.append(
                {
                    "outcome": "ok",
                    "exit_code": 0,
                    "seed": request.instance.seed,
                    "saved_coverage": float(row.coverage),
                    "ate_from_log_m": float(row.rmse) if tracked else None,
                    "events": {},
                    "wall_seconds": 0.0,
                }
            )
        return out

    def read_log(self, request: Request):
        from jsve.io._logs import read_log

        return read_log(self.log_path(request))


def request_summary(frontend, request: Request) -> Path:
    return frontend.log_path(request).with_suffix(".summary.json")


def _write_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


@dataclass
class FrontendScorer:
    """The Scorer of jsve.fitting._scorer over rules run in the loop: settings of a space (or named
    candidates) on instances, each (setting, instance) one run of the front-end.

    Attributes:
        frontend: what runs the rules.
        instances: the runs this scorer can score (its global run indices).
        switch_model: the front-end's switch model.
        penalty_m, min_coverage: the bounded loss (run_row).
        on_row: called with every finished run's row (progress, runs.csv).
        meter: what it has been asked for.
    """

    frontend: Frontend
    instances: Sequence[Instance]
    switch_model: str
    penalty_m: float
    min_coverage: float
    on_row: Callable[[dict], None] = lambda row: None
    meter: Meter = field(default_factory=Meter)

    @property
    def n_runs(self) -> int:
        return len(self.instances)

    @property
    def runs(self) -> np.ndarray:
        return np.arange(self.n_runs)

    def score(self, space, values, runs=None, *, progress: bool = False, desc: str = "score") -> SearchResult:
        values = np.asarray(values, np.float64).reshape(-1, space.dim)
        candidates = [Candidate.of(space.rule(v), "setting") for v in values]
        result = self.score_candidates(candidates, runs)
        return SearchResult(values=values, **{k: getattr(result, k) for k in _MATRICES})

    def score_candidates(self, candidates: Sequence[Candidate], runs=None) -> SearchResult:
        """[S, R'] results of candidates on the runs `runs` (indices of `instances`, in increasing
        order; None: all), every missing run made first."""
        picked = self.runs if runs is None else np.unique(np.asarray(runs, np.int64))
        self.meter.add(len(candidates), len(picked))
        requests = [Request(c, self.switch_model, self.instances[i]) for c in candidates for i in picked]
        rows: dict[Request, dict] = {}

        def done(request: Request, summary: dict) -> None:
            row = self.row(request, summary)
            rows[request] = row
            self.on_row(row)

        self.frontend.run(requests, done)
        table = {k: np.empty((len(candidates), len(picked))) for k in ("loss", "failed", "rmse", "coverage")}
        for s, c in enumerate(candidates):
            for j, i in enumerate(picked):
                row = rows[Request(c, self.switch_model, self.instances[i])]
                table["loss"][s, j] = row["loss_m"]
                table["failed"][s, j] = row["failed"]
                table["rmse"][s, j] = np.nan if row["failed"] else row["ate_m"]
                table["coverage"][s, j] = np.nan if row["coverage"] is None else row["coverage"]
        shape = table["loss"].shape
        return SearchResult(
            values=np.zeros((len(candidates), 0)),
            loss=table["loss"],
            failed=table["failed"].astype(bool),
            rmse=table["rmse"],
            coverage=table["coverage"],
            unsupported=np.zeros(shape, bool),
            included=np.ones(shape, bool),
        )

    def row(self, request: Request, summary: dict) -> dict:
        sequence, disturbance, level = self.frontend.describe(request.instance.dataset)
        log = self.frontend.log_path(request)
        return {
            "candidate": request.candidate.name,
            "switch_model": request.switch_model,
            "dataset": request.instance.dataset,
            "sequence": sequence,
            "disturbance": disturbance,
            "level": level,
            "seed": request.instance.seed,
            **run_row(summary, self.penalty_m, self.min_coverage),
            **switching(log),
            "log": str(log),
        }

    def on(self, runs, n_settings: int) -> FrontendScorer:
        """A scorer of the instances `runs` only (a run in the loop has no layout to prepare)."""
        picked = np.unique(np.asarray(runs, np.int64))
        return FrontendScorer(
            self.frontend,
            [self.instances[i] for i in picked],
            self.switch_model,
            self.penalty_m,
            self.min_coverage,
            self.on_row,
            self.meter,
        )


_MATRICES = ("loss", "failed", "rmse", "coverage", "unsupported", "included")

__all__ = [
    "Candidate",
    "FrontendScorer",
    "Instance",
    "OrbSlam3Frontend",
    "Request",
    "SimulatedFrontend",
    "candidate_name",
    "parse_setting",
    "run_row",
]
