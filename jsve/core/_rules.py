"""Switching rules: a score per frame and the four thresholds of ORB-SLAM3's success test.

A rule turns per-frame features into a score (the inlier count, or an SVE combination) and carries
the four thresholds of Tracking::TrackLocalMap's success test; the state machine that applies them
is jsve.core._machine. Presets, the parameter names of each rule family and the JSON form live here.
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

from jsve.core._sve import EQ1, OPTION1, OPTION2, Combination, FrameFeatures


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

    def score(self, features: FrameFeatures) -> Float[Array, ...]:
        return features.n_inliers


class SVERule(eqx.Module):
    """An SVE rule: the score is a combination of S_a, S_b, S_c in [0, 1]."""

    combination: Combination
    thresholds: Thresholds

    def score(self, features: FrameFeatures) -> Float[Array, ...]:
        return self.combination(features.inlier_ratio, features.s_b, features.s_c)


Rule = InlierRule | SVERule

RULE_KINDS: dict[str, type[InlierRule] | type[SVERule]] = {"inliers": InlierRule, "sve": SVERule}
"""A rule family's name (the "kind" of `rule_to_dict`, the families of jsve.fitting) -> its rule class."""


def rule_kind(rule: Rule) -> str:
    """The family name of a rule ("inliers" or "sve")."""
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


def param_names(kind: str) -> tuple[str, ...]:
    """Every parameter of a rule family by name, in order: the fields of its parameter Modules (for SVE
    rules the Combination's, then the Thresholds'). Names are unique across a rule's parts."""
    return tuple(f.name for part in _parts(_rule_class(kind)).values() for f in dataclasses.fields(part))


def rule_params(rule: Rule) -> dict[str, Array]:
    """Every parameter of a rule by name (the leaves of its Modules), in `param_names` order."""
    return {
        f.name: getattr(getattr(rule, part), f.name)
        for part, module in _parts(type(rule)).items()
        for f in dataclasses.fields(module)
    }


def rule_from_params(kind: str, params: Mapping[str, ArrayLike]) -> Rule:
    """The rule of a family from its parameters by name (`param_names(kind)`, e.g. flat values of a
    jsve.fitting.ParamSpace); leaves of any shape give a stack of rules."""
    cls = _rule_class(kind)
    return cls(**{part: module(**{f.name: params[f.name] for f in dataclasses.fields(module)})
                  for part, module in _parts(cls).items()})  # fmt: skip


SEED_EARLY_THRESHOLDS = dict(imu_init=0.1, not_init=0.3, reloc=0.3, recovery=0.1)
"""The earlier seed code / the paper's thresholds for the linear Eq.1 and Option 1."""
SEED_CODE_THRESHOLDS = dict(imu_init=0.06, not_init=0.2, reloc=0.2, recovery=0.04)
"""The seed's final code for Option 2 (IMU_MONOCULAR): 15/250 = 0.06 and 10/250 = 0.04. The paper's
text says 0.04 for "15 features"; the code uses 0.06 for that test and 0.04 for recovery."""


def preset(name: str) -> Rule:
    """A named rule: 'orbslam3', 'sve-eq1', 'sve-option1' or 'sve-option2'."""
    if name == "orbslam3":
        return InlierRule(Thresholds(imu_init=15, not_init=50, reloc=50, recovery=10))
    combos = {"sve-eq1": (EQ1, SEED_EARLY_THRESHOLDS), "sve-option1": (OPTION1, SEED_EARLY_THRESHOLDS),
              "sve-option2": (OPTION2, SEED_CODE_THRESHOLDS)}  # fmt: skip
    if name not in combos:
        raise ValueError(f"unknown rule preset {name!r}; choose one of {', '.join(PRESETS)}")
    combination, thresholds = combos[name]
    return SVERule(Combination(**combination), Thresholds(**thresholds))


PRESETS = ("orbslam3", "sve-eq1", "sve-option1", "sve-option2")

BASELINES = {"inliers": "orbslam3", "sve": "sve-option2"}
"""The preset each rule family is compared with: ORB-SLAM3's own rule, and the seed's final code."""


def rule_to_dict(rule: Rule) -> dict:
    """JSON-ready description of a rule (the format of `--rule params.json`): its kind, then each
    parameter Module as a table of its fields: {"kind": "sve", "combination": {...}, "thresholds": {...}}."""
    out: dict = {"kind": rule_kind(rule)}
    for part, module in _parts(type(rule)).items():
        values = getattr(rule, part)
        out[part] = {f.name: float(getattr(values, f.name)) for f in dataclasses.fields(module)}
    return out


def rule_from_dict(spec: Any, source: str = "<dict>") -> Rule:  # parsed JSON; wrong shapes get a ValueError
    """Inverse of `rule_to_dict`; errors name the source and the offending key."""
    try:
        kind = spec["kind"]
        if kind in RULE_KINDS:
            parts = _parts(RULE_KINDS[kind]).items()
            params = {f.name: float(spec[part][f.name]) for part, m in parts for f in dataclasses.fields(m)}
            return rule_from_params(kind, params)
    except KeyError as err:
        raise ValueError(f"{source}: rule description lacks key {err}") from None
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: bad rule description: {err}") from None
    raise ValueError(f"{source}: rule kind must be {' or '.join(map(repr, RULE_KINDS))}, got {kind!r}")
