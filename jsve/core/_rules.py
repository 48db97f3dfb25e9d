"""Switching rules: a score per frame and the four thresholds of ORB-SLAM3's success test.

A rule turns per-frame features into a score (the inlier count, or an SVE combination) and carries
the four thresholds of Tracking::TrackLocalMap's success test; the state machine that applies them
is jsve.core._machine. Presets, the parameter names of each rule family and the JSON form live here.

A rule's parameter Modules hold array leaves (the parameters: `param_names`, `rule_params`, what
fitting moves) and static fields (settings that pick code paths, such as Combination.inputs: never
fitted, carried by `rule_static`, written to JSON only when they differ from their default).
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jsve.core._sve import COMBINATIONS, Combination, FrameFeatures


class Thresholds(eqx.Module):
    """The four thresholds of the success test, in the rule's score units (array leaves).

    Attributes:
        imu_init: fail when score < imu_init with the IMU initialised (ORB-SLAM3: 15 inliers).
        not_init: fail when score < not_init before IMU initialisation (50 inliers).
        reloc: fail when score < reloc within fps frames of the map's start (50 inliers).
        recovery: RECENTLY_LOST -> OK when score > recovery (10 inliers).
    """

    imu_init: Float[Array, ""]
    not_init: Float[Array, ""]
    reloc: Float[Array, ""]
    recovery: Float[Array, ""]

    def __init__(self, imu_init, not_init, reloc, recovery):
        self.imu_init = jnp.asarray(imu_init, float)
        self.not_init = jnp.asarray(not_init, float)
        self.reloc = jnp.asarray(reloc, float)
        self.recovery = jnp.asarray(recovery, float)


class InlierRule(eqx.Module):
    """ORB-SLAM3's own rule: the score is the tracked inlier count (mnMatchesInliers)."""

    thresholds: Thresholds

    def score(self, features: FrameFeatures, *, checked: bool = True) -> Float[Array, ...]:
        return features.n_inliers

    def check_defined(self) -> None:
        """Every inlier rule is defined (the counterpart of SVERule.check_defined)."""


class SVERule(eqx.Module):
    """An SVE rule: the score is a combination of S_a, S_b, S_c (in [0, 1] for jsve's clamped inputs)."""

    combination: Combination
    thresholds: Thresholds

    def score(self, features: FrameFeatures, *, checked: bool = True) -> Float[Array, ...]:
        """checked: see Combination.score (False only after `check_defined`)."""
        return self.combination.score(features, checked=checked)

    def check_defined(self) -> None:
        """Refuse (ValueError) a combination that is not defined for its inputs (concrete leaves)."""
        self.combination.check_defined()


Rule = InlierRule | SVERule

RULE_KINDS: dict[str, type[InlierRule] | type[SVERule]] = {"inliers": InlierRule, "sve": SVERule}
"""A rule family's name (the "kind" of `rule_to_dict`, the families of jsve.fitting) -> its rule class."""


def rule_kind(rule: object) -> str:
    """The family name of a rule ("inliers" or "sve"); a TypeError naming the type for anything else."""
    for kind, cls in RULE_KINDS.items():
        if isinstance(rule, cls):
            return kind
    raise TypeError(f"not a jsve rule: {type(rule).__name__}")


@functools.cache
def _parts(cls: type) -> dict[str, Any]:
    """The parameter Modules of a rule class by field name, e.g. {"combination": Combination,
    "thresholds": Thresholds} (read from the class's annotations, so a new part needs no list here)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _rule_class(kind: str) -> type[InlierRule] | type[SVERule]:
    if kind not in RULE_KINDS:
        raise ValueError(f"rule kind must be {' or '.join(map(repr, RULE_KINDS))}, got {kind!r}")
    return RULE_KINDS[kind]


def _leaf_fields(module: type) -> tuple[dataclasses.Field, ...]:
    """The parameters of a parameter Module: its fields that are array leaves (not static)."""
    return tuple(f for f in dataclasses.fields(module) if not f.metadata.get("static", False))


def _static_fields(module: type) -> tuple[dataclasses.Field, ...]:
    """The static fields of a parameter Module (settings such as Combination.inputs, never fitted)."""
    return tuple(f for f in dataclasses.fields(module) if f.metadata.get("static", False))


def param_names(kind: str) -> tuple[str, ...]:
    """Every parameter of a rule family by name, in order: the array-leaf fields of its parameter
    Modules (for SVE rules the Combination's, then the Thresholds'). Static fields are not parameters
    (`rule_static`). Names are unique across a rule's parts."""
    return tuple(f.name for part in _parts(_rule_class(kind)).values() for f in _leaf_fields(part))


def rule_params(rule: Rule) -> dict[str, Array]:
    """Every parameter of a rule by name (the leaves of its Modules), in `param_names` order."""
    return {
        f.name: getattr(getattr(rule, part), f.name)
        for part, module in _parts(type(rule)).items()
        for f in _leaf_fields(module)
    }


def rule_static(rule: Rule) -> dict[str, Any]:
    """Every static field of a rule by name, e.g. {"inputs": "authors-eq1"} for the authors' Eq.1;
    with `rule_params` it rebuilds the rule (`rule_from_params(kind, params, static)`)."""
    return {
        f.name: getattr(getattr(rule, part), f.name)
        for part, module in _parts(type(rule)).items()
        for f in _static_fields(module)
    }


def rule_from_params(
    kind: str, params: Mapping[str, ArrayLike], static: Mapping[str, Any] | None = None
) -> Rule:
    """The rule of a family from its parameters by name (`param_names(kind)`, e.g. flat values of a
    jsve.fitting.ParamSpace); leaves of any shape give a stack of rules. `static` sets static fields
    by name (`rule_static`); those left out keep their defaults (Combination.inputs: "jsve")."""
    cls = _rule_class(kind)
    static = dict(static or {})
    known = {f.name for module in _parts(cls).values() for f in _static_fields(module)}
    if unknown := sorted(set(static) - known):
        raise ValueError(f"{kind} rules have no static field {unknown[0]!r} (static fields: {sorted(known)})")
    parts = {}
    for part, module in _parts(cls).items():
        values = {f.name: params[f.name] for f in _leaf_fields(module)}
        values |= {f.name: static[f.name] for f in _static_fields(module) if f.name in static}
        parts[part] = module(**values)
    return cls(**parts)


SEED_EARLY_THRESHOLDS = dict(imu_init=0.1, not_init=0.3, reloc=0.3, recovery=0.1)
"""The earlier seed code / the paper's thresholds for the linear Eq.1 and Option 1."""
SEED_CODE_THRESHOLDS = dict(imu_init=0.06, not_init=0.2, reloc=0.2, recovery=0.04)
"""The seed's final code for Option 2 (IMU_MONOCULAR): 15/250 = 0.06 and 10/250 = 0.04. The paper's
text says 0.04 for "15 features"; the code uses 0.06 for that test and 0.04 for recovery."""


_SVE_THRESHOLDS = {
    "sve-eq1": SEED_EARLY_THRESHOLDS,
    "sve-option1": SEED_EARLY_THRESHOLDS,
    "sve-option2": SEED_CODE_THRESHOLDS,
    "jsve-eq1": SEED_EARLY_THRESHOLDS,
    "jsve-option1": SEED_EARLY_THRESHOLDS,
}
"""The thresholds of every SVE preset (its combination: jsve.core._sve.COMBINATIONS). The authors'
Option 1 build (domRG/ORB_SLAM3_SVE@5aa5be5, Tracking::TrackLocalMap) has 0.3 / 0.1 / 0.1 / 0.3; no
stored build runs Eq.1 in the success test, and the paper gives it the same."""

PRESETS = ("orbslam3", *COMBINATIONS)
"""Every rule preset by name: ORB-SLAM3's, the seed's three as the authors built them ("sve-eq1",
"sve-option1", "sve-option2"), and jsve's clamped variants of Eq.1 and Option 1 ("jsve-eq1",
"jsve-option1"). docs/sve.md has the table."""


def preset(name: str) -> Rule:
    """A named rule, one of PRESETS."""
    if name == "orbslam3":
        return InlierRule(Thresholds(imu_init=15, not_init=50, reloc=50, recovery=10))
    if name not in COMBINATIONS:
        raise ValueError(f"unknown rule preset {name!r}; choose one of {', '.join(PRESETS)}")
    return SVERule(Combination(**COMBINATIONS[name]), Thresholds(**_SVE_THRESHOLDS[name]))


BASELINES = {"inliers": "orbslam3", "sve": "sve-option2"}
"""The preset each rule family is compared with: ORB-SLAM3's own rule, and the seed's final code."""


def rule_to_dict(rule: Rule) -> dict:
    """JSON-ready description of a rule (the format of `--rule params.json`): its kind, then each
    parameter Module as a table of its fields: {"kind": "sve", "combination": {...}, "thresholds": {...}}.
    Leaves are floats; static fields are written only when they differ from their default (e.g.
    "inputs": "authors-eq1"), so descriptions of jsve's own rules keep their form."""
    out: dict = {"kind": rule_kind(rule)}
    for part, module in _parts(type(rule)).items():
        values = getattr(rule, part)
        table = {f.name: float(getattr(values, f.name)) for f in _leaf_fields(module)}
        for f in _static_fields(module):
            if getattr(values, f.name) != f.default:
                table[f.name] = getattr(values, f.name)
        out[part] = table
    return out


def rule_from_dict(spec: Any, source: str = "<dict>") -> Rule:  # parsed JSON; wrong shapes get a ValueError
    """Inverse of `rule_to_dict`; a static field left out takes its default (descriptions written before
    Combination.inputs existed read as inputs "jsve"). Errors name the source and the offending key."""
    try:
        kind = spec["kind"]
        if kind in RULE_KINDS:
            parts = _parts(RULE_KINDS[kind]).items()
            params = {f.name: float(spec[part][f.name]) for part, m in parts for f in _leaf_fields(m)}
            static = {f.name: spec[part][f.name] for part, m in parts for f in _static_fields(m)
                      if f.name in spec[part]}  # fmt: skip
            return rule_from_params(kind, params, static)
    except KeyError as err:
        raise ValueError(f"{source}: rule description lacks key {err}") from None
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: bad rule description: {err}") from None
    raise ValueError(f"{source}: rule kind must be {' or '.join(map(repr, RULE_KINDS))}, got {kind!r}")
