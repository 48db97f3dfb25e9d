"""A tuning's study: TuneStudy, one typed object read from a TOML file (`jsve tune STUDY.toml`).

    [tune]
    frontend = "orbslam3"              # or "simulator": jsve's stand-in, to rehearse a tuning
    build = "~/.cache/jsve/orbslam3"   # `jsve frontend build`'s folder (orbslam3)
    vocabulary = "data/voc.txt"
    settings = "Monocular-Inertial.yaml"
    family = "sve"                     # the rule family tuned: "sve" or "inliers"
    switch_model = "imu-coast"         # the front-end the rules run in: "orbslam3" or "imu-coast"
    train = ["data/disturbed/V1_01/blur-20", ...]        # datasets the rule is chosen on
    heldout = ["data/disturbed/V2_02/blur-20", ...]      # datasets of other sequences, for verify
    seeds_per_round = 3                # the seeds a round records and races on (fresh each round)
    verify_seeds = 10                  # fresh seeds of the held-out check
    budget = 400                       # front-end runs in all (the check's runs are reserved first)

Relative paths are read from the TOML file's folder; the datasets and the vocabulary from `root`
(a [tune] key, or `jsve tune --root`) when it is given. A simulator study names its datasets
"SEQUENCE" or "SEQUENCE:DISTURBANCE=LEVEL" (jsve.sim's settings) instead of folders.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

from jsve.core._machine import check_switch_model
from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, DEFAULT_MIN_COVERAGE
from jsve.core._rules import PRESETS, RULE_KINDS

FRONTENDS = ("orbslam3", "simulator")
"""What runs a rule in the loop: the hooked ORB-SLAM3 (jsve frontend), or jsve's simulator."""

DEFAULT_BASELINES = ("orbslam3@orbslam3", "sve-option2@orbslam3")
"""What the tuned rule is verified against: stock ORB-SLAM3 v1.0, and the seed's final SVE build."""

_PATH_FIELDS = ("build", "vocabulary", "settings")
_RESUMABLE = ("workers", "scheduler", "timeout_s", "budget", "verify_seeds")


@dataclass(frozen=True)
class TuneStudy:
    """Everything a tuning depends on (module docstring has the TOML form).

    Attributes:
        frontend: one of FRONTENDS.
        build, vocabulary, settings: the hooked ORB-SLAM3 (orbslam3 front-end only).
        family: the rule family tuned ("sve" or "inliers").
        switch_model: the front-end's switch model the candidates run under.
        train, heldout: datasets (folders, or simulator settings); no held-out sequence may be trained.
        baselines: "RULE@SWITCH_MODEL" presets the tuned rule is verified against.
        incumbent: the rule the first round records, a preset (ORB-SLAM3's own by default).
        seeds_per_round: seeds per round; round r races on seeds r * seeds_per_round onwards.
        min_seeds: seeds every candidate runs before a paired test may eliminate it.
        max_rounds: rounds at most (record, propose, race).
        verify_seeds: seeds of the held-out check, from verify_seed_base.
        budget: front-end runs in all, the check's included.
        alpha: level of every paired test (Holm-corrected over the candidates tested at once).
        record: also run the permissive `record` rule (jsve.frontend._run.RECORD_THRESHOLDS) on each
            round's seeds and propose from its logs, which support every rule (one more run per
            training run); otherwise the proposals replay the incumbent's own logs.
        perturbations: candidates drawn around the incumbent each round; perturbation_scale: their
            spread in the family's unit cube (a normal's standard deviation).
        design: settings of the replay's search on the incumbent's logs; shortlist: how many of the
            best it checks against the trust region.
        failure_penalty, min_coverage: the bounded loss of a run (metres; share of frames saved).
        lockstep: runs in lockstep (deterministic under their seed; docs/frontend.md section 7).
        workers: runs at once; scheduler: where they run (jsve.io._scheduler; None: embedded Dask).
        timeout_s: a run's wall-clock limit (its outcome is then "timeout", a failed run).
        seed: seeds the design and the perturbations (and the simulator's study).
        flight_s: the simulator's flights' length, s (None: its default, 80-180 s).
        source: the TOML file read, for messages.
    """

    train: tuple[str, ...]
    heldout: tuple[str, ...]
    frontend: str = "orbslam3"
    build: str = ""
    vocabulary: str = ""
    settings: str = ""
    family: str = "sve"
    switch_model: str = "orbslam3"
    baselines: tuple[str, ...] = DEFAULT_BASELINES
    incumbent: str = "orbslam3"
    seeds_per_round: int = 3
    min_seeds: int = 2
    max_rounds: int = 2
    verify_seeds: int = 10
    verify_seed_base: int = 1000
    budget: int = 400
    alpha: float = 0.05
    record: bool = False
    perturbations: int = 2
    perturbation_scale: float = 0.1
    design: int = 512
    shortlist: int = 24
    failure_penalty: float = DEFAULT_FAILURE_PENALTY_M
    min_coverage: float = DEFAULT_MIN_COVERAGE
    lockstep: bool = True
    workers: int = 2
    scheduler: str | None = None
    timeout_s: float | None = 900.0
    seed: int = 0
    flight_s: float | None = None
    source: str = field(default="<study>", compare=False)

    def __post_init__(self):
        where = self.source
        if self.frontend not in FRONTENDS:
            raise ValueError(f"{where}: frontend {self.frontend!r}: expected one of {', '.join(FRONTENDS)}")
        if self.family not in RULE_KINDS:
            raise ValueError(f"{where}: family {self.family!r}: expected one of {', '.join(RULE_KINDS)}")
        check_switch_model(self.switch_model)
        if not self.train or not self.heldout:
            raise ValueError(f"{where}: train and heldout each need at least one dataset")
        for name in (self.incumbent, *(b.split("@")[0] for b in self.baselines)):
            if name not in PRESETS:
                raise ValueError(f"{where}: {name!r} is not a preset ({', '.join(PRESETS)})")
        for b in self.baselines:
            if "@" in b:
                check_switch_model(b.split("@", 1)[1])
        for key in ("seeds_per_round", "max_rounds", "verify_seeds", "budget", "workers"):
            if getattr(self, key) < 1:
                raise ValueError(f"{where}: {key} must be at least 1, got {getattr(self, key)}")
        if not 1 <= self.min_seeds <= self.seeds_per_round:
            raise ValueError(f"{where}: min_seeds must be in [1, seeds_per_round], got {self.min_seeds}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"{where}: alpha must be in (0, 1), got {self.alpha}")
        if self.verify_seed_base < self.max_rounds * self.seeds_per_round:
            raise ValueError(
                f"{where}: verify_seed_base {self.verify_seed_base} overlaps the training seeds "
                f"0..{self.max_rounds * self.seeds_per_round - 1}: the check needs fresh seeds"
            )
        if self.frontend == "orbslam3":
            missing = [k for k in _PATH_FIELDS if not getattr(self, k)]
            if missing:
                raise ValueError(f"{where}: the orbslam3 front-end needs {', '.join(missing)}")

    @property
    def baseline_pairs(self) -> tuple[tuple[str, str], ...]:
        """(rule, switch model) of every baseline; a baseline without "@" runs under the study's model."""
        return tuple(
            (b.split("@", 1)[0], b.split("@", 1)[1] if "@" in b else self.switch_model)
            for b in self.baselines
        )

    def round_seeds(self, r: int) -> list[int]:
        """The seeds round r records and races on."""
        return list(range(r * self.seeds_per_round, (r + 1) * self.seeds_per_round))

    @property
    def check_seeds(self) -> list[int]:
        return list(range(self.verify_seed_base, self.verify_seed_base + self.verify_seeds))

    @property
    def check_runs(self) -> int:
        """Runs the held-out check takes (reserved from the budget before any round): every arm (the
        tuned rule and each baseline) on every held-out dataset and check seed."""
        return (1 + len(self.baseline_pairs)) * len(self.heldout) * self.verify_seeds

    def with_check_seeds(self, verify_seeds: int) -> TuneStudy:
        """This study with a held-out check of `verify_seeds` seeds and the budget moved by the runs that
        adds, so its rounds keep the runs they had (budget less the check's) and a finished tuning
        resumed with it runs the new check seeds alone."""
        if verify_seeds < 1:
            raise ValueError(f"{self.source}: verify_seeds must be >= 1, got {verify_seeds}")
        wider = dataclasses.replace(self, verify_seeds=verify_seeds)
        return dataclasses.replace(wider, budget=self.budget + wider.check_runs - self.check_runs)

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out.pop("source")
        return out

    def digest(self) -> str:
        """sha256 of what the tuning's rounds depend on: every field but where and how fast runs go
        (workers, scheduler, timeout_s) and how far the tuning may go (budget, verify_seeds), so a
        resumed tuning may be given more runs."""
        spec = {k: v for k, v in self.to_dict().items() if k not in _RESUMABLE}
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()

    @classmethod
    def from_toml(
        cls, path: str | os.PathLike, *, root: str | os.PathLike | None = None, **overrides
    ) -> TuneStudy:
        """The study of a TOML file's [tune] table, with `overrides` (None values ignored) on top.

        Paths are read from the file's folder; the datasets and the vocabulary from `root` when given
        (the table's own `root` key otherwise), so one study file serves data kept anywhere.

        Raises:
            ValueError naming the file and the key for an unknown key or a bad value.
        """
        path = Path(path)
        try:
            table = tomllib.loads(path.read_text()).get("tune")
        except tomllib.TOMLDecodeError as err:
            raise ValueError(f"{path}: not TOML: {err}") from None
        if not isinstance(table, dict):
            raise ValueError(f"{path}: no [tune] table")
        table = {**table, **{k: v for k, v in overrides.items() if v is not None}}
        own_root = path.parent / Path(str(table.pop("root", "."))).expanduser()
        data_root = Path(root).expanduser() if root is not None else own_root
        known = {f.name for f in dataclasses.fields(cls)} - {"source"}
        if unknown := sorted(set(table) - known):
            raise ValueError(
                f"{path}: unknown key {unknown[0]!r} in [tune] (known: {', '.join(sorted(known))})"
            )
        simulated = table.get("frontend", "orbslam3") == "simulator"

        def resolve(p: str, base: Path = path.parent) -> str:
            return str((base / Path(p).expanduser()).resolve()) if p else p

        for key in _PATH_FIELDS:
            if key in table:
                table[key] = resolve(str(table[key]), data_root if key == "vocabulary" else path.parent)
        for key in ("train", "heldout", "baselines"):
            if key in table:
                if not isinstance(table[key], list) or not all(isinstance(x, str) for x in table[key]):
                    raise ValueError(f"{path}: [tune] {key} must be a list of strings")
                if key != "baselines" and not simulated:
                    table[key] = [resolve(x, data_root) for x in table[key]]
                table[key] = tuple(table[key])
        try:
            return cls(**table, source=str(path))
        except TypeError as err:
            raise ValueError(f"{path}: [tune]: {err}") from None


__all__ = ["DEFAULT_BASELINES", "FRONTENDS", "TuneStudy"]
