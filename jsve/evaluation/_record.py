"""The record of an evaluation folder (`jsve evaluate -o DIR`): how its runs were scored and which rules.

`DIR/evaluation.json` sits beside runs.parquet, runs.csv and summary.csv, so that whoever reads the folder
later (`jsve report DIR`, jsve.report._evaluation_report) scores the rules as `jsve evaluate` did, with its
failure penalty and support policy, and says which alignment, switch model and rules produced the runs,
instead of assuming jsve's defaults. A folder written before the record existed has none:
`read_evaluation_record` returns None and the reader says it falls back to the defaults.

    {
      "align": "se3", "n_to_align": null, "segments": "saved", "min_coverage": 0.5, "failure": "coverage",
      "loss": "bounded", "switch_model": "orbslam3", "failure_penalty": 1.0, "support": "penalise",
      "by": ["sequence", "disturbance", "level", "rule"], "float64": false, "logs": "study.parquet",
      "rules": [{"name": "orbslam3", "file": null, "rule": {"kind": "inliers", "thresholds": {...}}}, ...]
    }
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, DEFAULT_MIN_COVERAGE
from jsve.core._rules import PRESETS, Rule, rule_to_dict
from jsve.io._atomic import write_json

EVALUATION_RECORD = "evaluation.json"
"""The record's file name in an evaluation folder."""


@dataclass(frozen=True)
class RuleRecord:
    """One rule an evaluation replayed.

    Attributes:
        name: its name in the `rule` column of runs.parquet (a preset's name, or a rule file's stem).
        file: the rule file as given to `--rule` (None for a preset).
        rule: the rule as jsve.core.rule_to_dict writes it (kind, parameter tables in the rule's score
            units: inliers for the inlier rule, the SVE score in [0, 1] for SVE thresholds).
    """

    name: str
    file: str | None
    rule: dict


@dataclass(frozen=True)
class EvaluationRecord:
    """How `jsve evaluate` scored the runs of a folder (its options, resolved to their values).

    Attributes:
        align: alignment to the ground truth (jsve.core._align.ALIGN_METHODS).
        n_to_align: frames the alignment used (the first N evaluated ones); None: all.
        segments: what of a run was scored: "saved", the trajectory the front-end saves (records written
            before it was scored: a map segment, jsve.core._trajectory.SEGMENT_MODES).
        min_coverage: share of frames (0 to 1) the scored trajectory must cover, else the run failed.
        failure: what failed a run (jsve.core._objective.FAILURE_DEFINITIONS; records without the key
            were written under "strict").
        loss: a tracked run's loss, "bounded" or "raw" (records without the key: "raw").
        switch_model: the replay's switch model (jsve.core._machine.SWITCH_MODELS).
        failure_penalty: metres charged for a failed run in the objective.
        support: what the objective did with a run out of the log's support, "penalise" or "exclude".
        by: the metadata keys summary.csv is aggregated by.
        float64: whether the replay ran in float64 (float32 otherwise).
        logs: the LOGS argument as given (a folder, a log or a Parquet file).
        rules: every rule replayed, in the order of --rule.
    """

    align: str = "se3"
    n_to_align: int | None = None
    segments: str = "saved"
    min_coverage: float = DEFAULT_MIN_COVERAGE
    failure: str = "coverage"
    loss: str = "bounded"
    switch_model: str = "orbslam3"
    failure_penalty: float = DEFAULT_FAILURE_PENALTY_M
    support: str = "penalise"
    by: tuple[str, ...] = ()
    float64: bool = False
    logs: str = ""
    rules: tuple[RuleRecord, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        """The JSON form (what evaluation.json holds)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, spec: dict, source: str = "<record>") -> EvaluationRecord:
        """Inverse of `to_dict`; keys left out take their defaults, unknown keys are an error naming
        them (a record of a later jsve is read, not misread)."""
        known = {f.name for f in dataclasses.fields(cls)}
        if unknown := sorted(set(spec) - known):
            raise ValueError(f"{source}: unknown keys {unknown}; known: {sorted(known)}")
        values = dict(spec)
        # A record without `failure` scored a map segment, strictly, with the raw loss and no floor.
        if "failure" not in values:
            values.setdefault("segments", "largest")
            values.setdefault("min_coverage", 0.0)
            values.setdefault("loss", "raw")
            values["failure"] = "strict"
        if "by" in values:
            values["by"] = tuple(values["by"])
        if "rules" in values:
            try:
                values["rules"] = tuple(RuleRecord(**r) for r in values["rules"])
            except TypeError as err:
                raise ValueError(f"{source}: bad rule entry: {err}") from None
        return cls(**values)


def rule_records(pairs: Iterable[tuple[str, Rule]], given: Iterable[str] | None) -> tuple[RuleRecord, ...]:
    """RuleRecords of jsve.io.load_rules's (name, rule) pairs and the --rule values they came from
    (None: every preset, as load_rules reads it); a value that is not a preset's name is a file."""
    pairs = list(pairs)
    given = list(given) if given else [name for name, _ in pairs]
    if len(given) != len(pairs):
        raise ValueError(f"{len(given)} --rule values for {len(pairs)} rules")
    return tuple(
        RuleRecord(name=name, file=None if value in PRESETS else str(value), rule=rule_to_dict(rule))
        for value, (name, rule) in zip(given, pairs, strict=True)
    )


def write_evaluation_record(record: EvaluationRecord, folder: str | os.PathLike) -> Path:
    """Write `folder/evaluation.json` atomically (jsve.io._atomic); returns its path."""
    return write_json(Path(folder) / EVALUATION_RECORD, record.to_dict())


def read_evaluation_record(folder: str | os.PathLike) -> EvaluationRecord | None:
    """The record of an evaluation folder, or None where it has none (written before the record existed).

    Raises:
        ValueError: the file is not valid JSON or not a record (the message names the file).
    """
    path = Path(folder) / EVALUATION_RECORD
    if not path.is_file():
        return None
    try:
        spec = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: not an evaluation record (a JSON object)")
    return EvaluationRecord.from_dict(spec, source=str(path))
