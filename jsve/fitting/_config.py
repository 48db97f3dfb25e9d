"""A study's configuration: StudyConfig, one typed object from a TOML file and command-line flags.

StudyConfig.from_toml(path, thorough=False, **overrides)   what `jsve fit --config` reads
StudyConfig.merged(table, base)                            a parsed table over a base (`jsve demo`)
THOROUGH                                                   what `--thorough` adds
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import tomllib

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, DEFAULT_MIN_COVERAGE, ObjectiveConfig
from jsve.fitting._fit import FitConfig, resolve_search
from jsve.fitting._space import ParamSpace, space_from_dict

GROUP_COLUMNS = ("sequence", "disturbance", "level")
"""The metadata columns whose groups count equally in a study's objective by default."""


@dataclass(frozen=True)
class StudyConfig:
    """Everything a study's results depend on besides the logs (a sweep's TOML file sets it).

    Attributes:
        families: the rule families to fit ("sve", "inliers"); spaces: their ParamSpace descriptions
            (None: the defaults of jsve.fitting._space).
        balance_by: metadata columns whose groups count equally in the objective ([]: every run 1).
        failure_penalty, align, min_coverage, failure, loss, switch_model, support: the objective
            (jsve.core._objective.ObjectiveConfig; failure: what fails a run, "coverage" or "strict";
            loss: "bounded" or "raw"; switch_model: docs/state-machine.md; support: what the fit does
            with a run whose replay leaves the log's support, "penalise" or "exclude").
        fit: jsve.fitting._fit.FitConfig.
        kfold: folds of the k-fold cross-validation (0: none); leave_one_out: metadata columns to leave
            out one value at a time (skipped when a column has a single value; default none, THOROUGH
            leaves out each sequence and each disturbance).
        n_boot: bootstrap resamples for every CI; level: their confidence level.
        n_local, local_fraction: the local design of the parameter bootstrap (n_local 0, the default:
            none, so a resample's refit is the best of the fit's search survivors and the fit itself,
            coarse but at the cost of a matrix product; THOROUGH sets 1024); bootstrap_screen_runs:
            its settings are screened on that many runs first and only those that could win a
            resample are scored on every run (jsve.fitting._crossval.parameter_bootstrap; 0: all).
        heatmap: (x, y, n): the two thresholds of the heat map and its points per axis.
        heatmap_runs: the heat map scores its n^2 settings on the first heatmap_runs weighted runs of
            the study's stratified order, packed into one part (jsve.fitting._polish); 0: on every run.
        seed: seeds folds and bootstraps.
    """

    families: tuple[str, ...] = ("sve", "inliers")
    spaces: dict = field(default_factory=dict)
    balance_by: tuple[str, ...] = GROUP_COLUMNS
    failure_penalty: float = DEFAULT_FAILURE_PENALTY_M
    align: str = "se3"
    min_coverage: float = DEFAULT_MIN_COVERAGE
    failure: str = "coverage"
    loss: str = "bounded"
    switch_model: str = "orbslam3"
    support: str = "penalise"
    fit: FitConfig = FitConfig()
    kfold: int = 5
    leave_one_out: tuple[str, ...] = ()
    n_boot: int = 2000
    level: float = 0.95
    n_local: int = 0
    local_fraction: float = 0.15
    bootstrap_screen_runs: int = 512
    heatmap: tuple = ("imu_init", "recovery", 20)
    heatmap_runs: int = 512
    seed: int = 0

    def __post_init__(self):
        self.objective()  # the objective's settings are checked when the study is configured
        zero = {"heatmap_runs": "every run", "bootstrap_screen_runs": "every run", "n_local": "none"}
        for name, meaning in zero.items():
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
                raise ValueError(f"StudyConfig.{name} must be a count >= 0 (0: {meaning}), got {value!r}")

    def objective(self) -> ObjectiveConfig:
        return ObjectiveConfig(
            failure_penalty=self.failure_penalty,
            align=self.align,
            min_coverage=self.min_coverage,
            failure=self.failure,
            loss=self.loss,
            switch_model=self.switch_model,
            support=self.support,
        )

    def space(self, family: str) -> ParamSpace:
        """The family's ParamSpace: its description in `spaces`, else the family's defaults."""
        return space_from_dict({"kind": family, **self.spaces.get(family, {})})

    def resolved(self, n_runs: int) -> StudyConfig:
        """This study for data of n_runs runs with every "auto" setting made concrete (the fit's search
        and its first rung, jsve.fitting._fit.resolve_search): what run_study and the estimate run. The
        study's key is the configuration as asked for, so the same file keys the same study."""
        return replace(self, fit=resolve_search(self.fit, n_runs))

    def to_dict(self) -> dict:
        out = asdict(self)
        out["fit"] = asdict(self.fit)
        return out

    @classmethod
    def from_dict(cls, spec: dict, source: str = "<config>") -> StudyConfig:
        """From a parsed TOML/JSON table: top-level keys as the attributes, `[fit]` a sub-table.

        Raises:
            ValueError: an unknown key or a wrong value, the message starting with `source`.
        """
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(spec) - known)
        if unknown:
            raise ValueError(f"{source}: unknown study settings {unknown}; known: {sorted(known)}")
        spec = dict(spec)
        if "fit" in spec:
            fit_known = {f.name for f in fields(FitConfig)}
            bad = sorted(set(spec["fit"]) - fit_known)
            if bad:
                raise ValueError(f"{source}: unknown [fit] settings {bad}; known: {sorted(fit_known)}")
            fit_spec = dict(spec["fit"])
            if "temperatures" in fit_spec:
                fit_spec["temperatures"] = tuple(fit_spec["temperatures"])
            try:
                spec["fit"] = FitConfig(**fit_spec)
            except ValueError as err:
                raise ValueError(f"{source}: [fit] {err}") from None
        for key in ("families", "balance_by", "leave_one_out", "heatmap"):
            if key in spec:
                spec[key] = tuple(spec[key])
        try:
            return cls(**spec)
        except ValueError as err:
            raise ValueError(f"{source}: {err}") from None

    @classmethod
    def merged(cls, spec: dict, base: StudyConfig, source: str = "<config>") -> StudyConfig:
        """A parsed TOML/JSON table's keys over `base` (its [fit] table over base.fit's keys)."""
        spec = dict(spec)
        merged = base.to_dict()
        merged["fit"] = {**merged["fit"], **spec.pop("fit", {})}
        merged.update(spec)
        return cls.from_dict(merged, source=source)

    @classmethod
    def from_toml(
        cls, path: str | os.PathLike | None = None, *, base: StudyConfig | None = None,
        thorough: bool = False, **overrides,
    ) -> StudyConfig:  # fmt: skip
        """The study a TOML file describes (top-level study keys, a [fit] table; a [demo] table is
        `jsve demo`'s and ignored here), over `base` (default: the defaults) and THOROUGH's keys where
        `thorough`, with `overrides` (None values ignored) over all of them.

        An override names a study key or one of OVERRIDES_OF_FIT (search, eta, initial_fraction,
        relaxed), which set the [fit] table's key; `seed` seeds the study's folds and bootstraps and the
        fit's design alike. A wrong value names its source: the file, or "the command line".
        """
        spec = {}
        if path is not None:
            try:
                spec = tomllib.loads(Path(path).read_text())
            except (OSError, tomllib.TOMLDecodeError) as err:
                raise ValueError(f"{path}: {err}") from None
            spec.pop("demo", None)
        base = base or cls()
        if thorough:
            base = replace(base, **THOROUGH)
        config = cls.merged(spec, base, source=str(path) if path is not None else "<defaults>")
        given = {key: value for key, value in overrides.items() if value is not None}
        if not given:
            return config
        merged = config.to_dict()
        for key, value in given.items():
            if key in OVERRIDES_OF_FIT:
                merged["fit"][key] = value
            elif key == "seed":
                merged["seed"] = merged["fit"]["seed"] = value
            else:
                merged[key] = value
        return cls.from_dict(merged, source="the command line")


THOROUGH = {"leave_one_out": ("sequence", "disturbance"), "n_local": 1024}
"""What `jsve fit --thorough` adds to the defaults: leave-one-sequence-out and leave-one-disturbance-out
folds, and a parameter bootstrap whose refits also choose among 1,024 settings around the fit (finer
intervals). The default takes about half the time, with the same fitted rules and k-fold held-out
objective (docs/fitting.md, "The default study and `--thorough`")."""


OVERRIDES_OF_FIT = ("search", "eta", "initial_fraction", "relaxed")
"""Overrides of StudyConfig.from_toml that set a key of the [fit] table (jsve.fitting._fit.FitConfig)."""


__all__ = ["GROUP_COLUMNS", "StudyConfig", "THOROUGH", "OVERRIDES_OF_FIT"]
