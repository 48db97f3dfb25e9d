"""Parameter spaces of the fitted rules: bounds, designs in the unit cube, unconstrained coordinates.

A `ParamSpace` names the free parameters of one rule family with a box [lo, hi] for each, and holds the
values of the parameters it keeps fixed:

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

from jsve.core._rules import InlierRule, Rule, SVERule, Thresholds
from jsve.core._sve import Combination

THRESHOLD_NAMES = ("imu_init", "not_init", "reloc", "recovery")
COMBINATION_NAMES = ("w_a", "u_b", "p", "q", "rho")
SVE_NAMES = COMBINATION_NAMES + THRESHOLD_NAMES
INLIER_NAMES = THRESHOLD_NAMES

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

SCORE_SCALE = {"sve": 1.0, "inliers": 250.0}
"""Score units per SVE unit, for temperatures given in SVE units: the seed's conversion 15 inliers = 0.06."""

_EDGE = 1e-6
"""Unit-cube coordinates are kept in [_EDGE, 1 - _EDGE] before the logit, so box edges map to finite z."""


@dataclass(frozen=True)
class ParamSpace:
    """The free parameters of a rule family with their boxes, and the fixed ones (hashable, static).

    Attributes:
        kind: "sve" or "inliers".
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
        family = SVE_NAMES if self.kind == "sve" else INLIER_NAMES if self.kind == "inliers" else None
        if family is None:
            raise ValueError(f"ParamSpace kind must be 'sve' or 'inliers', got {self.kind!r}")
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
        thresholds = Thresholds(*(full[k] for k in THRESHOLD_NAMES))
        if self.kind == "inliers":
            return InlierRule(thresholds)
        return SVERule(Combination(**{k: full[k] for k in COMBINATION_NAMES}), thresholds)

    def values_of(self, rule: Rule) -> np.ndarray:
        """The free values of a rule of this family (e.g. a preset as a starting point), float64 [d]."""
        if (self.kind == "sve") != isinstance(rule, SVERule):
            raise ValueError(f"a {type(rule).__name__} is not in the {self.kind!r} family")
        source = {k: getattr(rule.thresholds, k) for k in THRESHOLD_NAMES}
        if self.kind == "sve":
            source.update({k: getattr(rule.combination, k) for k in COMBINATION_NAMES})
        return np.array([float(source[k]) for k in self.names])

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


def sve_space(**bounds: tuple[float, float]) -> ParamSpace:
    """The SVE family with all nine parameters free (default boxes, SVE_BOUNDS, overridable)."""
    b = {**SVE_BOUNDS, **bounds}
    return ParamSpace("sve", SVE_NAMES, tuple(b[k][0] for k in SVE_NAMES), tuple(b[k][1] for k in SVE_NAMES))


def inlier_space(**bounds: tuple[float, float]) -> ParamSpace:
    """ORB-SLAM3's rule with its four thresholds free (default boxes, INLIER_BOUNDS, overridable)."""
    b = {**INLIER_BOUNDS, **bounds}
    return ParamSpace(
        "inliers", INLIER_NAMES, tuple(b[k][0] for k in INLIER_NAMES), tuple(b[k][1] for k in INLIER_NAMES)
    )


def space_from_dict(spec: dict) -> ParamSpace:
    """Inverse of ParamSpace.describe (the `[space]` table of a sweep config)."""
    kind = spec.get("kind")
    base = sve_space() if kind == "sve" else inlier_space() if kind == "inliers" else None
    if base is None:
        raise ValueError(f"space kind must be 'sve' or 'inliers', got {kind!r}")
    free = spec.get("free")
    if free is not None:
        base = base.bounded(**{k: tuple(v) for k, v in free.items()})
    fixed = spec.get("fixed") or {}
    return base.fix(**fixed) if fixed else base


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
