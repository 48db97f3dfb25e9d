"""The design point: one home for a fitted rule's parameters, from a vector to the rule.

    free values [d] (in a box)  <->  named values {name: value}  <->  Rule (jsve.core._rules)
    unit cube u (designs), unconstrained z (optimisers)    presets as points    bounds per family

A `ParamSpace` names the free parameters of one rule family with a box [lo, hi] for each, and holds the
values of the parameters it keeps fixed. The names are the fields of the rule's Modules
(jsve.core._rules.param_names: Combination's, then Thresholds'), never typed here:

- "sve": the nested power mean SVE = M_p([S_a, M_q([S_b, S_c]; u_b)]; w_a) with S_a scaled by rho
  (jsve.core._sve.Combination) and its four thresholds. (w_a, u_b) are the stick-breaking coordinates of the
  simplex weights (w_a, (1 - w_a) u_b, (1 - w_a)(1 - u_b)) of (S_a, S_b, S_c) in the flat case p = q.
- "inliers": ORB-SLAM3's rule (the inlier count) and its four thresholds, so that the baseline is
  tuned as fairly as the SVE rules.

Search designs live in the unit cube [0, 1]^d (value = lo + (hi - lo) u). Optimisers work in unconstrained
coordinates z (value = lo + (hi - lo) sigmoid(z)), which keep every iterate inside the box: weights on the
simplex, |p|, |q| bounded, rho > 0, thresholds within their range. `RuleParams` is that point, an
eqx.Module with one array leaf.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jsve.core._rules import (
    PRESETS,
    RULE_KINDS,
    Rule,
    param_names,
    preset,
    rule_from_params,
    rule_kind,
    rule_params,
    rule_static,
)

SVE_BOUNDS = {
    "w_a": (0.0, 1.0),
    "u_b": (0.0, 1.0),
    "p": (-4.0, 4.0),
    "q": (-4.0, 4.0),
    "rho": (0.05, 1.0),
    "imu_init": (0.0, 0.6),
    "not_init": (0.0, 0.8),
    "reloc": (0.0, 0.8),
    "recovery": (0.0, 0.6),
}
"""Default boxes of the SVE family. The exponents span harmonic-like (-4) to max-like (4) means; the
thresholds the useful part of [0, 1] (the seed's values are 0.04-0.3)."""

INLIER_BOUNDS = {
    "imu_init": (0.0, 100.0),
    "not_init": (0.0, 200.0),
    "reloc": (0.0, 200.0),
    "recovery": (0.0, 100.0),
}
"""Default boxes of ORB-SLAM3's thresholds, inliers (its own values: 15, 50, 50, 10; nFeatures 1000).
Wider boxes cost search resolution where it matters: 1,024 Sobol points put ~6 levels on each axis."""

BOUNDS = {"sve": SVE_BOUNDS, "inliers": INLIER_BOUNDS}
"""Default boxes of every family (jsve.core._rules.RULE_KINDS), by parameter name."""

SCORE_SCALE = {"sve": 1.0, "inliers": 250.0}
"""Score units per SVE unit, for temperatures given in SVE units: the seed's conversion 15 inliers = 0.06."""

_EDGE = 1e-6
"""Unit-cube coordinates are kept in [_EDGE, 1 - _EDGE] before the logit, so box edges map to finite z."""


@dataclass(frozen=True)
class ParamSpace:
    """The free parameters of a rule family with their boxes, and the fixed ones (hashable, static).

    Attributes:
        kind: the rule family, "sve" or "inliers" (jsve.core._rules.RULE_KINDS).
        names: free parameter names, in coordinate order.
        lo, hi: box of each free parameter (parameter units: SVE units, inliers, exponents).
        fixed: (name, value) of every parameter of the family that is not free.
    """

    kind: str
    names: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    fixed: tuple[tuple[str, float], ...] = field(default=())

    def __post_init__(self):
        if self.kind not in RULE_KINDS:
            kinds = " or ".join(map(repr, RULE_KINDS))
            raise ValueError(f"ParamSpace kind must be {kinds}, got {self.kind!r}")
        family = param_names(self.kind)
        if not self.names:
            raise ValueError("ParamSpace needs at least one free parameter")
        if not (len(self.names) == len(self.lo) == len(self.hi)):
            raise ValueError(
                f"names, lo and hi differ in length: {len(self.names)}, {len(self.lo)}, {len(self.hi)}"
            )
        covered = list(self.names) + [k for k, _ in self.fixed]
        if sorted(covered) != sorted(family):
            raise ValueError(
                f"{self.kind} parameters must each be free or fixed exactly once; got free "
                f"{list(self.names)}, fixed {[k for k, _ in self.fixed]}, need {list(family)}"
            )
        for name, a, b in zip(self.names, self.lo, self.hi, strict=True):
            if not (np.isfinite(a) and np.isfinite(b) and a < b):
                raise ValueError(f"bounds of {name!r} must be finite with lo < hi, got [{a}, {b}]")

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def score_scale(self) -> float:
        return SCORE_SCALE[self.kind]

    # -- coordinates -------------------------------------------------------------------------------
    def values_from_unit(self, u: Float[Array, "... d"]) -> Float[Array, "... d"]:
        """Parameter values of unit-cube points."""
        lo, hi = jnp.asarray(self.lo), jnp.asarray(self.hi)
        return lo + (hi - lo) * jnp.asarray(u)

    def unit_from_values(self, values: Float[Array, "... d"]) -> Float[Array, "... d"]:
        lo, hi = jnp.asarray(self.lo), jnp.asarray(self.hi)
        return (jnp.asarray(values) - lo) / (hi - lo)

    def values_from_z(self, z: Float[Array, "... d"]) -> Float[Array, "... d"]:
        """Parameter values of unconstrained coordinates (inside the box for every z; at |z| > ~17 float32
        rounds them onto its edges)."""
        return self.values_from_unit(jax.nn.sigmoid(z))

    def z_from_values(self, values: Float[Array, "... d"]) -> Float[Array, "... d"]:
        """Unconstrained coordinates of values (clipped a hair inside the box first)."""
        u = jnp.clip(self.unit_from_values(values), _EDGE, 1 - _EDGE)
        return jnp.log(u) - jnp.log1p(-u)

    # -- rules -------------------------------------------------------------------------------------
    def rule(self, values: Float[Array, "... d"]) -> Rule:
        """The rule with these free values (leaves of shape values.shape[:-1]: a stack of rules)."""
        values = jnp.asarray(values)
        if values.shape[-1] != self.dim:
            raise ValueError(
                f"values have {values.shape[-1]} coordinates, the space has {self.dim} ({self.names})"
            )
        batch = values.shape[:-1]
        full = {name: jnp.full(batch, value, values.dtype) for name, value in self.fixed}
        for i, name in enumerate(self.names):
            full[name] = values[..., i]
        return rule_from_params(self.kind, full)

    def values_of(self, rule: Rule) -> np.ndarray:
        """The free values of a rule of this family (e.g. a preset as a starting point), float64 [d]."""
        if rule_kind(rule) != self.kind:
            raise ValueError(f"a {type(rule).__name__} is not in the {self.kind!r} family")
        params = rule_params(rule)
        return np.array([float(params[k]) for k in self.names])

    def params(self, values) -> dict[str, float]:
        """Every parameter by name at these free values [d]: the fixed ones, then the free ones."""
        out = dict(self.fixed)
        out.update({k: float(v) for k, v in zip(self.names, np.asarray(values), strict=True)})
        return out

    def derived(self, values) -> dict[str, np.ndarray]:
        """Quantities of a report derived from free values [..., d]: with w_a and u_b both free, the flat
        simplex weights of (S_a, S_b, S_c) of the stick-breaking coordinates,
        (w_a, (1 - w_a) u_b, (1 - w_a)(1 - u_b)), as weight_a, weight_b, weight_c; else none."""
        if self.kind != "sve" or not {"w_a", "u_b"} <= set(self.names):
            return {}
        v = np.asarray(values)
        w_a, u_b = v[..., self.names.index("w_a")], v[..., self.names.index("u_b")]
        return {"weight_a": w_a, "weight_b": (1 - w_a) * u_b, "weight_c": (1 - w_a) * (1 - u_b)}

    def contains(self, values) -> bool:
        v = np.asarray(values, float)
        return bool(np.all(v >= np.asarray(self.lo)) and np.all(v <= np.asarray(self.hi)))

    def fix(self, **values: float) -> ParamSpace:
        """The same space with some free parameters fixed at the given values."""
        unknown = [k for k in values if k not in self.names]
        if unknown:
            raise ValueError(f"cannot fix {unknown}: not free in this space ({self.names})")
        keep = [i for i, k in enumerate(self.names) if k not in values]
        return replace(
            self,
            names=tuple(self.names[i] for i in keep),
            lo=tuple(self.lo[i] for i in keep),
            hi=tuple(self.hi[i] for i in keep),
            fixed=self.fixed + tuple((k, float(v)) for k, v in values.items()),
        )

    def bounded(self, **boxes: tuple[float, float]) -> ParamSpace:
        """The same space with new boxes for some free parameters."""
        lo, hi = list(self.lo), list(self.hi)
        for k, (a, b) in boxes.items():
            if k not in self.names:
                raise ValueError(f"{k!r} is not free in this space ({self.names})")
            i = self.names.index(k)
            lo[i], hi[i] = float(a), float(b)
        return replace(self, lo=tuple(lo), hi=tuple(hi))

    def describe(self) -> dict:
        """JSON-ready description (for reports and resumable outputs)."""
        return {
            "kind": self.kind,
            "free": {k: [a, b] for k, a, b in zip(self.names, self.lo, self.hi, strict=True)},
            "fixed": dict(self.fixed),
        }


def family_space(kind: str, **bounds: tuple[float, float]) -> ParamSpace:
    """A rule family with every parameter free, in the rule's parameter order (default boxes, BOUNDS,
    overridable by name)."""
    if kind not in BOUNDS:
        raise ValueError(f"space kind must be {' or '.join(map(repr, BOUNDS))}, got {kind!r}")
    names = param_names(kind)
    b = {**BOUNDS[kind], **bounds}
    return ParamSpace(kind, names, tuple(b[k][0] for k in names), tuple(b[k][1] for k in names))


def sve_space(**bounds: tuple[float, float]) -> ParamSpace:
    """The SVE family with all nine parameters free (default boxes, SVE_BOUNDS, overridable)."""
    return family_space("sve", **bounds)


def inlier_space(**bounds: tuple[float, float]) -> ParamSpace:
    """ORB-SLAM3's rule with its four thresholds free (default boxes, INLIER_BOUNDS, overridable)."""
    return family_space("inliers", **bounds)


def space_from_dict(spec: dict) -> ParamSpace:
    """Inverse of ParamSpace.describe (the `[space]` table of a sweep config; `free` and `fixed` may
    be left out: the family's defaults)."""
    base = family_space(spec.get("kind"))
    free = spec.get("free")
    if free is not None:
        base = base.bounded(**{k: tuple(v) for k, v in free.items()})
    fixed = spec.get("fixed") or {}
    return base.fix(**fixed) if fixed else base


# ---------------------------------------------------------------------------------------------------
# Presets as points


def is_space_point(rule) -> bool:
    """Whether a space can express the rule: its static fields (e.g. the SVE inputs) are those every
    ParamSpace rule has. The authors' `sve-eq1` / `sve-option1` combine other inputs, so no point of a
    space is them: they are scored by replay, never by a point that would carry their name."""
    return rule_static(rule) == rule_static(rule_from_params(rule_kind(rule), rule_params(rule)))


def preset_values(space: ParamSpace) -> dict[str, np.ndarray]:
    """The presets (jsve.core._rules.PRESETS) of the space's family that are points of it (see
    `is_space_point`), lie inside its box and agree with its fixed values, as free values [d] by name."""
    out = {}
    for name in PRESETS:
        rule = preset(name)
        if rule_kind(rule) != space.kind or not is_space_point(rule):
            continue
        params = rule_params(rule)
        values = space.values_of(rule)
        if all(np.isclose(float(params[k]), v) for k, v in space.fixed) and space.contains(values):
            out[name] = values
    return out


def preset_point(name: str) -> tuple[ParamSpace, np.ndarray]:
    """A preset as a point: its family's full space (default boxes) and its values there.

    Raises:
        ValueError for a preset no point of a space is (`is_space_point`).
    """
    rule = preset(name)
    if not is_space_point(rule):
        raise ValueError(f"preset {name!r} combines {rule_static(rule)}: no point of a ParamSpace is it")
    space = family_space(rule_kind(rule))
    return space, space.values_of(rule)


class RuleParams(eqx.Module):
    """A point of a ParamSpace in unconstrained coordinates: what the optimisers move.

    Attributes:
        z: [d] unconstrained coordinates (value = lo + (hi - lo) sigmoid(z)).
        space: the ParamSpace (static).
    """

    z: Float[Array, " d"]
    space: ParamSpace = eqx.field(static=True)

    @classmethod
    def from_values(cls, space: ParamSpace, values) -> RuleParams:
        return cls(z=space.z_from_values(jnp.asarray(values, float)), space=space)

    def values(self) -> Float[Array, " d"]:
        return self.space.values_from_z(self.z)

    def rule(self) -> Rule:
        return self.space.rule(self.values())
