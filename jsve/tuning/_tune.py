"""`jsve tune`: the replay proposes, the real front-end decides, held-out sequences verify.

    round r (seeds r * n .. r * n + n - 1 of the training datasets):
      record    the incumbent in the loop (ORB-SLAM3's own rule first); with `record`, also the
                permissive record rule, whose logs support every rule
      propose   from those logs: the replay's fit in the trust region, presets, perturbations
      race      seed by seed, every candidate still in on every training dataset; from min_seeds on, a
                candidate significantly worse than the best (paired Wilcoxon, Holm) is out
      decide    the survivor of lowest mean loss among those that beat the incumbent (paired, Holm)
                becomes the incumbent; none: the tuning stops
    check       the tuned rule (or, when ORB-SLAM3's rule stayed, the best challenger) against the
                baselines on the held-out datasets with fresh seeds: paired differences, 95 % intervals

The folder DIR holds tune.json (the study, every round's decision, the result), rules/<name>.json (every
rule raced or chosen), runs.csv (every run used: one row per rule, switch model, dataset and seed),
rounds/<r>/ (proposal.json, predictions.csv, race.csv, decision.csv), check.csv, agreement.csv and
progress.json. Every file is written whole (renamed into place). A re-run resumes: runs are found in the
pool and never repeated, a round's proposal is read back, and every decision is recomputed from the runs.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import rule_from_dict, rule_to_dict
from jsve.frontend._run import record_rule
from jsve.io import _atomic
from jsve.io._resume import StaleOutputError
from jsve.tuning._frontend import (
    RUN_COLUMNS,
    Candidate,
    FrontendScorer,
    Instance,
    OrbSlam3Frontend,
    Request,
    SimulatedFrontend,
)
from jsve.tuning._propose import Proposal, propose
from jsve.tuning._race import better_than, eliminate, paired_difference
from jsve.tuning._study import TuneStudy

LEVEL = ("disturbance", "level")


def make_frontend(study: TuneStudy, pool: Path):
    """The study's front-end over the pool of runs."""
    if study.frontend == "simulator":
        return SimulatedFrontend(pool, study.verify_seed_base, study.seed, study.flight_s)
    return OrbSlam3Frontend(
        pool,
        Path(study.build),
        Path(study.vocabulary),
        Path(study.settings),
        study.verify_seed_base,
        study.lockstep,
        study.workers,
        study.scheduler,
        study.timeout_s,
    )


@dataclass
class Ledger:
    """Every run the tuning used, written to runs.csv as each one finishes, and its progress."""

    out: Path
    budget: int
    workers: int
    show: bool = True
    rows: dict = field(default_factory=dict)
    phase: str = "start"
    planned: int = 0
    started: float = field(default_factory=time.monotonic)
    started_at: float = field(default_factory=time.time)
    made: int = 0

    def add(self, row: dict) -> None:
        """Keep a finished run's row (once); a run whose summary was written since the tuning started
        counts as made now, else as found in the pool."""
        key = (row["candidate"], row["switch_model"], row["dataset"], row["seed"])
        if key not in self.rows:
            self.rows[key] = row
            self.planned = max(0, self.planned - 1)
            summary = Path(row["log"]).with_suffix(".summary.json")
            self.made += int(summary.is_file() and summary.stat().st_mtime >= self.started_at)
            self.write()

    def plan(self, phase: str, runs: int) -> None:
        self.phase, self.planned = phase, runs
        self.write()

    @property
    def table(self) -> pd.DataFrame:
        return pd.DataFrame(list(self.rows.values()), columns=list(RUN_COLUMNS))

    def eta_s(self, runs: int) -> float | None:
        """Seconds `runs` more runs take at the mean wall time of the runs made so far."""
        walls = [r["wall_s"] for r in self.rows.values() if r.get("wall_s")]
        return None if not walls else runs * float(np.mean(walls)) / max(1, self.workers)

    def write(self) -> None:
        eta, most = self.eta_s(self.planned), self.eta_s(max(0, self.budget - len(self.rows)))
        state = {
            "phase": self.phase,
            "runs_used": len(self.rows),
            "runs_made_now": self.made,
            "runs_left_in_step": self.planned,
            "runs_left_in_budget": max(0, self.budget - len(self.rows)),
            "budget": self.budget,
            "eta_step_s": None if eta is None else round(eta, 1),
            "eta_budget_s": None if most is None else round(most, 1),
            "elapsed_s": round(time.monotonic() - self.started, 1),
        }
        _atomic.write_text(self.out / "progress.json", json.dumps(state, indent=2) + "\n")
        table = self.table.sort_values(["switch_model", "candidate", "dataset", "seed"], kind="stable")
        _atomic.write_text(self.out / "runs.csv", table.to_csv(index=False))
        if self.show:
            when = "" if eta is None else f", ETA {eta / 60:.0f} min (the whole budget: {most / 60:.0f} min)"
            print(
                f"jsve tune: {self.phase}: {len(self.rows)} runs used ({self.made} made now), "
                f"{self.planned} left in this step, {state['runs_left_in_budget']} in the budget{when}",
                file=sys.stderr,
                flush=True,
            )


def _write_json(path: Path, value) -> None:
    _atomic.write_text(path, json.dumps(value, indent=2, default=_plain) + "\n")


def _plain(x):
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"{type(x).__name__} is not JSON")


def _start(out: Path, study: TuneStudy, force: bool) -> dict:
    """tune.json of the folder: a fresh one, or the one a killed run of the same study left.

    Raises:
        StaleOutputError when the folder holds a tuning of another study (unless `force`).
    """
    path = out / "tune.json"
    if path.is_file():
        state = json.loads(path.read_text())
        if state.get("digest") != study.digest() and not force:
            raise StaleOutputError(out, "the study differs from the one this folder was tuned with")
    state = {"study": study.to_dict(), "digest": study.digest(), "status": "running", "rounds": []}
    _write_json(path, state)
    return state


def _keep_rule(out: Path, candidate: Candidate) -> None:
    path = out / "rules" / f"{candidate.name}.json"
    if not path.is_file():
        _write_json(path, rule_to_dict(candidate.rule))


def _proposal(folder: Path, out: Path, make) -> Proposal:
    """The round's proposal, read back when a killed run of the tuning wrote it, else made and kept."""
    path = folder / "proposal.json"
    if path.is_file():
        spec = json.loads(path.read_text())
        candidates = [
            Candidate(
                c["name"],
                rule_from_dict(json.loads((out / "rules" / f"{c['name']}.json").read_text())),
                c["origin"],
                c["round"],
            )
            for c in spec["candidates"]
        ]
        return Proposal(
            candidates, pd.read_csv(folder / "predictions.csv"), spec["trust_share"], spec["note"]
        )
    proposal = make()
    for c in proposal.candidates:
        _keep_rule(out, c)
    _atomic.write_text(folder / "predictions.csv", proposal.predictions.to_csv(index=False))
    _write_json(
        path,
        {
            "candidates": [
                {"name": c.name, "origin": c.origin, "round": c.round} for c in proposal.candidates
            ],
            "trust_share": proposal.trust_share,
            "note": proposal.note,
        },
    )
    return proposal


def _prediction_rows(table: pd.DataFrame, sources: dict[str, Instance]) -> pd.DataFrame:
    """The replay's table with each log's (dataset, seed)."""
    keep = ["candidate", "source", "predicted_loss_m", "predicted_failed", "changed_fraction"]
    out = table[keep].copy()
    out["dataset"] = [sources[s].dataset for s in out["source"]]
    out["seed"] = [sources[s].seed for s in out["source"]]
    return out.drop(columns="source")


def run_round(study, out, frontend, ledger, incumbent: Candidate, r: int, reserve: int, history: list):
    """One round: record, propose, race, decide. Returns (its summary, its candidates by name); the
    summary's winner is None where nobody beat the incumbent, its `stopped` why the race ended early
    (None: it did not). None when the budget cannot pay for the round's recording."""
    folder = out / "rounds" / f"{r}"
    seeds = study.round_seeds(r)
    instances = [Instance(d, s) for s in seeds for d in study.train]
    scorer = FrontendScorer(
        frontend, instances, study.switch_model, study.failure_penalty, study.min_coverage, ledger.add
    )
    recorder = Candidate("record", record_rule(), "record", r) if study.record else incumbent
    recording = [incumbent, recorder] if study.record else [incumbent]
    left = study.budget - reserve - len(ledger.rows)
    if left < len(recording) * len(instances):
        return None
    ledger.plan(
        f"round {r}: record {' and '.join(c.name for c in recording)}", len(recording) * len(instances)
    )
    scorer.score_candidates(recording)
    own = [
        Instance(d, s)
        for d in study.train
        for s in range(0, (r + 1) * study.seeds_per_round)
        if (recorder.name, study.switch_model, d, s) in ledger.rows
    ]
    requests = [Request(recorder, study.switch_model, i) for i in own]
    config = ObjectiveConfig(
        failure_penalty=study.failure_penalty,
        min_coverage=study.min_coverage,
        switch_model=study.switch_model,
    )
    ledger.plan(f"round {r}: propose from {len(own)} logs of {recorder.name}", 0)

    def make() -> Proposal:
        logs = [frontend.read_log(q) for q in requests]
        p = propose(
            logs,
            incumbent,
            study.family,
            config,
            round=r,
            design=study.design,
            shortlist=study.shortlist,
            perturbations=study.perturbations,
            perturbation_scale=study.perturbation_scale,
            seed=study.seed,
        )
        sources = {str(log.source): q.instance for log, q in zip(logs, requests, strict=True)}
        return Proposal(p.candidates, _prediction_rows(p.predictions, sources), p.trust_share, p.note)

    proposal = _proposal(folder, out, make)
    by_name = {c.name: c for c in proposal.candidates}
    alive, tests, stopped = list(by_name), [], None
    for b, seed in enumerate(seeds):
        runs = [k for k, i in enumerate(instances) if i.seed == seed]
        need = sum(
            (n, study.switch_model, instances[k].dataset, seed) not in ledger.rows
            for n in alive
            for k in runs
        )
        if need > study.budget - reserve - len(ledger.rows):
            stopped = f"budget (before seed {seed})"
            break
        ledger.plan(f"round {r}: race seed {seed} ({len(alive)} rules)", need)
        scorer.score_candidates([by_name[n] for n in alive], runs)
        if b + 1 >= study.min_seeds and len(alive) > 1:
            rows = _race_rows(ledger, study, alive, seeds[: b + 1])
            alive, step = eliminate(rows, alive, study.alpha)
            tests.append(step.assign(round=r, after_seed=seed))
    rows = _race_rows(ledger, study, list(by_name), seeds)
    winner, decision = better_than(
        rows, incumbent.name, [n for n in alive if n != incumbent.name], study.alpha
    )
    race = pd.concat(tests, ignore_index=True) if tests else pd.DataFrame()
    _atomic.write_text(folder / "race.csv", race.to_csv(index=False))
    _atomic.write_text(folder / "decision.csv", decision.to_csv(index=False))
    means = rows.groupby("candidate")["loss_m"].mean()
    challengers = [n for n in alive if n != incumbent.name]
    best = min(challengers, key=lambda n: means.get(n, np.inf)) if challengers else None
    summary = {
        "round": r,
        "seeds": seeds,
        "incumbent": incumbent.name,
        "candidates": [
            {"name": c.name, "origin": c.origin, "mean_loss_m": means.get(c.name)}
            for c in proposal.candidates
        ],
        "note": proposal.note,
        "survivors": alive,
        "winner": winner,
        "best_challenger": best,
        "stopped": stopped,
    }
    history.append(summary)
    return summary, by_name


def _race_rows(ledger: Ledger, study: TuneStudy, names, seeds) -> pd.DataFrame:
    t = ledger.table
    return t[
        (t.switch_model == study.switch_model)
        & t.candidate.isin(list(names))
        & t.seed.isin(list(seeds))
        & t.dataset.isin(list(study.train))
    ]


def check(study: TuneStudy, frontend, ledger: Ledger, tuned: Candidate) -> pd.DataFrame:
    """The tuned rule against each baseline on the held-out datasets with fresh seeds: paired differences
    over every held-out run and per level (disturbance, level)."""
    arms = [(tuned, study.switch_model)] + [
        (Candidate.preset(n, "baseline"), m) for n, m in study.baseline_pairs
    ]
    rows_of = FrontendScorer(frontend, [], study.switch_model, study.failure_penalty, study.min_coverage)
    # seed by seed, every arm on every held-out dataset: a check cut short holds whole pairs
    for seed in study.check_seeds:
        requests = [Request(c, m, Instance(d, seed)) for c, m in arms for d in study.heldout]
        ledger.plan(
            f"check: seed {seed} ({len(arms)} rules on {len(study.heldout)} held-out datasets)", len(requests)
        )
        frontend.run(requests, lambda request, summary: ledger.add(rows_of.row(request, summary)))
    return check_table(ledger.table, study, tuned.name)


def check_table(runs: pd.DataFrame, study: TuneStudy, tuned: str) -> pd.DataFrame:
    """check.csv from the runs' table (runs.csv): the rule named `tuned` against each baseline on the
    held-out datasets' check seeds, paired_difference over all of them and per (disturbance, level)."""
    t = runs[runs.dataset.isin(list(study.heldout)) & runs.seed.isin(study.check_seeds)].copy()
    t["candidate"] = t["candidate"] + "@" + t["switch_model"]
    name = f"{tuned}@{study.switch_model}"
    rows = []
    for b, model in study.baseline_pairs:
        base = f"{b}@{model}"
        if base == name:
            continue
        rows.append({"scope": "all held-out", **paired_difference(t, name, base)})
        for (dist, level), g in t.groupby(list(LEVEL)):
            rows.append({"scope": f"{dist} {level:g}", **paired_difference(g, name, base)})
    return pd.DataFrame(rows)


def agreement(ledger: Ledger, out: Path, study: TuneStudy) -> pd.DataFrame:
    """Per raced candidate and round: the replay's predicted loss (from the incumbent's logs) against its
    measured loss on the same (dataset, seed), both as differences to the incumbent, on each half of the
    round's seeds (even, odd): pick on one half, score on the other."""
    rows = []
    runs = ledger.table
    runs = runs[runs.switch_model == study.switch_model]
    for folder in sorted((out / "rounds").glob("*"), key=lambda p: int(p.name)):
        spec = json.loads((folder / "proposal.json").read_text())
        pred = pd.read_csv(folder / "predictions.csv")
        incumbent = spec["candidates"][0]["name"]
        measured = runs.pivot_table(
            index=["dataset", "seed"], columns="candidate", values="loss_m", aggfunc="first"
        )
        seeds = TuneStudy.round_seeds(study, int(folder.name))
        for c in spec["candidates"][1:]:
            p = pred[pred.candidate == c["name"]].set_index(["dataset", "seed"])["predicted_loss_m"]
            p0 = pred[pred.candidate == incumbent].set_index(["dataset", "seed"])["predicted_loss_m"]
            if c["name"] not in measured or incumbent not in measured:
                continue
            m = (measured[c["name"]] - measured[incumbent]).dropna()
            d = (p - p0).dropna()
            both = m.index.intersection(d.index)
            both = [k for k in both if k[1] in seeds]
            if not both:
                continue
            row = {
                "round": int(folder.name),
                "candidate": c["name"],
                "origin": c["origin"],
                "pairs": len(both),
                "predicted_diff_m": float(d.loc[both].mean()),
                "measured_diff_m": float(m.loc[both].mean()),
            }
            for half, parity in (("even", 0), ("odd", 1)):
                keys = [k for k in both if k[1] % 2 == parity]
                row[f"predicted_diff_{half}_m"] = float(d.loc[keys].mean()) if keys else np.nan
                row[f"measured_diff_{half}_m"] = float(m.loc[keys].mean()) if keys else np.nan
            rows.append(row)
    return pd.DataFrame(rows)


def tune(study: TuneStudy, out, *, pool=None, force: bool = False, progress: bool = True) -> dict:
    """Run (or resume) a tuning into the folder `out`; every run goes to `pool` (default out/runs).

    Returns:
        tune.json's content: the study, the rounds, the tuned rule, the check and the runs spent.
    Raises:
        StaleOutputError: `out` holds a tuning of another study (unless `force`).
        ValueError: a held-out dataset is of a sequence the tuning trains on.
    """
    out = _atomic.make_dir(out)
    pool = Path(pool) if pool is not None else out / "runs"
    frontend = make_frontend(study, pool)
    trained = {frontend.describe(d)[0] for d in study.train}
    if leaked := sorted({frontend.describe(d)[0] for d in study.heldout} & trained):
        raise ValueError(f"{study.source}: held-out sequence {leaked[0]} is also trained on")
    state = _start(out, study, force)
    ledger = Ledger(out, study.budget, study.workers, show=progress)
    reserve = study.check_runs
    incumbent = Candidate.preset(study.incumbent, "incumbent")
    _keep_rule(out, incumbent)
    history: list = []
    stopped = "rounds"
    for r in range(study.max_rounds):
        result = run_round(study, out, frontend, ledger, incumbent, r, reserve, history)
        if result is None:
            stopped = "budget"
            break
        summary, by_name = result
        state["rounds"] = history
        _write_json(out / "tune.json", state)
        if summary["winner"] is None:
            stopped = "no candidate beat the incumbent" if summary["stopped"] is None else summary["stopped"]
            break
        incumbent = by_name[summary["winner"]]
    last = history[-1] if history else {}
    changed = incumbent.name != study.incumbent
    tuned = (
        incumbent if changed or not last.get("best_challenger") else _candidate(out, last["best_challenger"])
    )
    _keep_rule(out, tuned)
    _atomic.write_text(out / "tuned_rule.json", json.dumps(rule_to_dict(tuned.rule), indent=2) + "\n")
    table = check(study, frontend, ledger, tuned)
    _atomic.write_text(out / "check.csv", table.to_csv(index=False))
    _atomic.write_text(out / "agreement.csv", agreement(ledger, out, study).to_csv(index=False))
    state.update(
        status="done",
        stopped=stopped,
        tuned=tuned.name,
        tuned_is_incumbent=changed,
        runs_used=len(ledger.rows),
        check=table.to_dict("records"),
    )
    ledger.plan("done", 0)
    _write_json(out / "tune.json", state)
    return state


def _candidate(out: Path, name: str) -> Candidate:
    return Candidate(
        name, rule_from_dict(json.loads((out / "rules" / f"{name}.json").read_text())), "challenger"
    )


__all__ = ["agreement", "check", "check_table", "make_frontend", "run_round", "tune"]
