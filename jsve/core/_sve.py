"""Scene Visibility Estimation (SVE) metrics S_a, S_b, S_c and their combinations.

Reference definitions from the authors' public code (see docs/sve.md):
Haggart & Aitken 2021 (ORB-SLAM2/3) and Rugg-Gunn & Aitken 2022 (the seed paper, ORB-SLAM3).
All functions are elementwise over leading axes, jit/vmap-safe and differentiable where noted.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jsve.core._numerics import safe_divide

N_BINS = 64
WORST_CASE_FRACTION = 1.0 / 8.0
"""Fraction f of bins holding all points in the worst case; chi2_w = N (1 - f) / f = 7 N."""


def s_a_original(n_extracted: ArrayLike, n_features: ArrayLike) -> Float[Array, ...]:
    """Feature quantity, Haggart's original: N_extracted / nFeatures (unclamped)."""
    return safe_divide(jnp.asarray(n_extracted, float), jnp.asarray(n_features, float))


def inlier_ratio(n_inliers: ArrayLike, n_extracted: ArrayLike) -> Float[Array, ...]:
    """N_inliers / N_extracted, 0 when nothing was extracted; S_a before the rho scaling."""
    return safe_divide(jnp.asarray(n_inliers, float), jnp.asarray(n_extracted, float))


def s_a(n_inliers: ArrayLike, n_extracted: ArrayLike, rho: ArrayLike = 0.25) -> Float[Array, ...]:
    """Feature quantity, ORB-SLAM3 variant (Rugg-Gunn): clamp(N_inliers / (rho N_extracted), 0, 1).

    rho = 0.25 in the seed's final code (Option 2), 0.5 in Option 1. Zero when N_extracted = 0.
    """
    return s_a_from_ratio(inlier_ratio(n_inliers, n_extracted), rho)


def s_a_from_ratio(ratio: ArrayLike, rho: ArrayLike) -> Float[Array, ...]:
    """S_a from a precomputed inlier ratio, so that rho can be swept without touching the counts."""
    return jnp.clip(safe_divide(jnp.asarray(ratio, float), jnp.asarray(rho, float)), 0.0, 1.0)


def s_b(bins: ArrayLike, n_extracted: ArrayLike, clamp: bool = True) -> Float[Array, ...]:
    """Feature homogeneity over the 8 x 8 SVE bins: 1 - chi2 / chi2_w.

    E = N / 64 with N all extracted keypoints (also those outside the grid, as in the authors' code);
    chi2 = sum_i (n_i - E)^2 / E; chi2_w = 7 N is the worst case of all points spread evenly over
    1/8 of the bins. Clamped to [0, 1] by default (Haggart's original is unclamped).

    Arguments:
        bins: keypoints per bin, shape (..., 64).
        n_extracted: N, shape (...).
    Returns:
        S_b, shape (...); 0 when N = 0 (no features: no evidence of spread).
    """
    bins = jnp.asarray(bins, float)
    n = jnp.asarray(n_extracted, float)
    expected = n[..., None] / N_BINS
    sum_sq = jnp.sum((bins - expected) ** 2, axis=-1)
    # chi2 / chi2_w = [sum (n_i - E)^2 / E] / (7 N) = 64 sum (n_i - E)^2 / (7 N^2)
    worst = (1.0 - WORST_CASE_FRACTION) / WORST_CASE_FRACTION
    ratio = safe_divide(N_BINS * sum_sq, worst * n * n)
    value = jnp.where(n > 0, 1.0 - ratio, 0.0)
    return jnp.clip(value, 0.0, 1.0) if clamp else value


def s_c(n_inliers: ArrayLike, n_frustum: ArrayLike, clamp: bool = True) -> Float[Array, ...]:
    """Tracked vs expected: N_inliers / N_frustum (nToMatch), 0 when N_frustum = 0; clamped to [0, 1].

    Unclamped (clamp=False) it is Haggart's version, which can exceed 1.
    """
    value = safe_divide(jnp.asarray(n_inliers, float), jnp.asarray(n_frustum, float))
    return jnp.clip(value, 0.0, 1.0) if clamp else value


def power_mean(x: Float[ArrayLike, "... k"], w: Float[ArrayLike, " k"], p: ArrayLike) -> Float[Array, ...]:
    """Weighted power mean (sum_i w_i x_i^p)^(1/p) of non-negative x, weights summing to 1.

    p = 1 arithmetic, p -> 0 geometric (exp sum w log x), p = -1 harmonic. A zero entry with positive
    weight gives 0 for p <= 0. Gradients stay finite at x = 0 and p = 0 (double where).
    """
    x = jnp.asarray(x, float)
    w = jnp.asarray(w, x.dtype)
    p = jnp.asarray(p, x.dtype)
    positive = x > 0
    x_safe = jnp.where(positive, x, 1.0)
    has_zero = jnp.any(~positive & (w > 0), axis=-1)
    near_zero_p = jnp.abs(p) < 1e-6
    p_safe = jnp.where(near_zero_p, 1.0, p)
    # Near p = 0: M_p = G exp(p Var_w(log x) / 2) + O(p^2) (cumulant expansion of log sum w e^(p log x)),
    # so that the value and d/dp at p = 0 are right; the plain geometric mean G has d/dp = 0.
    logs = jnp.log(x_safe)
    mean_log = jnp.sum(w * logs, axis=-1)
    var_log = jnp.sum(w * (logs - mean_log[..., None]) ** 2, axis=-1)
    geometric = jnp.exp(mean_log + 0.5 * p * var_log)
    # sum_i w_i x_i^p - 1 = sum_i w_i expm1(p log x_i) (weights sum to 1; x_i = 0 contributes -w_i):
    # expm1/log1p keep float32 accurate for small |p|, where inner**(1/p) cancels catastrophically.
    excess = jnp.sum(w * jnp.where(positive, jnp.expm1(p_safe * logs), -1.0), axis=-1)
    inner_ok = excess > -1
    powered = jnp.where(inner_ok, jnp.exp(jnp.log1p(jnp.where(inner_ok, excess, 0.0)) / p_safe), 0.0)
    value = jnp.where(near_zero_p, geometric, powered)
    # A zero entry with p <= 0 gives 0 (x^p -> inf in the sum); for 0 < p < 1e-6 the mean is
    # (sum of the other weights)^(1/p) -> 0 as well, which the expansion above does not know.
    return jnp.where(has_zero & (near_zero_p | (p <= 0)), 0.0, value)


def log_power_mean2(l1, pos1, l2, pos2, w, p):
    """log M_p([x1, x2]; [w, 1 - w]) from l_i = log x_i (where pos_i: x_i > 0), and whether M is 0.

    `power_mean`'s definition (the same p -> 0 expansion and zero rules) in the log domain, on two
    columns: the combinations are nested two-entry means, so a nested mean passes its log on without
    an exp/log round trip, and sweeps share the logs of the features across settings. Separate
    columns rather than a stacked axis of 2: several times faster on CPU (tests/test_fit.py checks
    this kernel against `power_mean`).
    Returns:
        (log M, M == 0), elementwise.
    """
    l1 = jnp.where(pos1, l1, 0.0)
    l2 = jnp.where(pos2, l2, 0.0)
    w2 = 1 - w
    near_zero_p = jnp.abs(p) < 1e-6
    p_safe = jnp.where(near_zero_p, 1.0, p)
    mean_log = w * l1 + w2 * l2
    # Near p = 0: log M = mean log x + p Var(log x) / 2 (cumulant expansion, as in power_mean).
    log_geometric = mean_log + 0.5 * p * (w * (l1 - mean_log) ** 2 + w2 * (l2 - mean_log) ** 2)
    excess = (w * jnp.where(pos1, jnp.expm1(p_safe * l1), -1.0)
              + w2 * jnp.where(pos2, jnp.expm1(p_safe * l2), -1.0))  # fmt: skip
    inner_ok = excess > -1
    log_powered = jnp.log1p(jnp.where(inner_ok, excess, 0.0)) / p_safe
    has_zero = (~pos1 & (w > 0)) | (~pos2 & (w2 > 0))
    zero = (has_zero & (near_zero_p | (p <= 0))) | (~near_zero_p & ~inner_ok)
    return jnp.where(near_zero_p, log_geometric, log_powered), zero


def power_mean2(x1, x2, w, p):
    """M_p([x1, x2]; [w, 1 - w]) elementwise for non-negative columns (the log-domain kernel)."""
    pos1, pos2 = x1 > 0, x2 > 0
    log_m, zero = log_power_mean2(
        jnp.log(jnp.where(pos1, x1, 1.0)), pos1, jnp.log(jnp.where(pos2, x2, 1.0)), pos2, w, p
    )
    return jnp.where(zero, 0.0, jnp.exp(jnp.where(zero, 0.0, log_m)))


def feature_logs(ratio, s_b, s_c):
    """(log ratio, log S_b, log S_c, ratio > 0, S_b > 0, S_c > 0); logs are 0 where the feature is 0.

    `ratio` is N_inliers / N_extracted (S_a before rho). Computed once per frame, shared by rules.
    """
    log_ratio, log_s_b, log_s_c = (jnp.log(jnp.where(x > 0, x, 1.0)) for x in (ratio, s_b, s_c))
    return log_ratio, log_s_b, log_s_c, ratio > 0, s_b > 0, s_c > 0


def combination_from_logs(c, log_ratio, log_s_b, log_s_c, pos_ratio, pos_s_b, pos_s_c):
    """The SVE score of Combination `c` from `feature_logs` (any broadcastable shapes).

    S_a = clip(ratio / rho, 0, 1) is min(log ratio - log rho, 0) in the log domain. Only for
    `inputs="jsve"`: the logs are of the clamped features (the fitted family's inputs).
    """
    if c.inputs != "jsve":
        raise ValueError(
            f"combination_from_logs takes the clamped features of inputs='jsve', got a Combination with "
            f"inputs={c.inputs!r}: use Combination.score(features)"
        )
    rho_ok = c.rho > 0
    log_s_a = jnp.minimum(log_ratio - jnp.log(jnp.where(rho_ok, c.rho, 1.0)), 0.0)
    pos_s_a = pos_ratio & rho_ok
    log_inner, inner_zero = log_power_mean2(log_s_b, pos_s_b, log_s_c, pos_s_c, c.u_b, c.q)
    log_m, zero = log_power_mean2(log_s_a, pos_s_a, log_inner, ~inner_zero, c.w_a, c.p)
    return jnp.where(zero, 0.0, jnp.exp(jnp.where(zero, 0.0, log_m)))


INPUTS = ("jsve", "authors-eq1", "authors-option1")
"""What a Combination combines (its static field `inputs`); docs/sve.md has the sources.

- "jsve": S_a = clamp(N_inliers / (rho N_extracted), 0, 1), clamped S_b and S_c. The seed's final
  build (Option 2) and the family jsve fits.
- "authors-eq1": the seed's original build (Haggart's metrics): S_a = N_extracted / nFeatures,
  unclamped S_b and S_c; rho is not used.
- "authors-option1": the seed's Option 1 build: S_a = clamp(N_inliers / (rho N_extracted), 0, 1),
  unclamped S_b and S_c.

Unclamped S_b reaches -8 (all keypoints in one bin) and S_c exceeds 1, so a power mean of them is
only defined for p = q = 1: the authors' inputs are combined linearly and other exponents refused.
"""


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)  # pyright: ignore[reportAttributeAccessIssue] - public, untyped


class Combination(eqx.Module):
    """The nested power-mean family of SVE combinations.

        SVE = M_p( [S_a, M_q([S_b, S_c]; [u, 1-u])]; [w, 1-w] )

    It contains the seed's three: Eq.1 (w=0.2, u=0.5, p=q=1, i.e. 0.2a + 0.4b + 0.4c), Option 1
    (w=0.5, u=0.5, p=q=1, i.e. 0.5a + 0.25b + 0.25c) and Option 2 (w=0.5, u=0.5, p=0, q=1, i.e.
    sqrt(a (0.5b + 0.5c))); with p = q it is the flat weighted power mean of (a, b, c). rho scales S_a.
    The five numbers are array leaves so sweeps can vmap over them; `inputs` (one of INPUTS) is
    static: which S_a, S_b, S_c variants are combined. With the authors' unclamped inputs only
    p = q = 1 is defined (refused otherwise: here when p, q are concrete, in `score` when traced).
    """

    w_a: Float[Array, ""]
    u_b: Float[Array, ""]
    p: Float[Array, ""]
    q: Float[Array, ""]
    rho: Float[Array, ""]
    inputs: str = eqx.field(static=True, default="jsve")

    def __init__(self, w_a=0.5, u_b=0.5, p=1.0, q=1.0, rho=0.25, inputs="jsve"):
        if inputs not in INPUTS:
            raise ValueError(
                f"Combination inputs must be one of {', '.join(map(repr, INPUTS))}, got {inputs!r}"
            )
        self.w_a = jnp.asarray(w_a, float)
        self.u_b = jnp.asarray(u_b, float)
        self.p = jnp.asarray(p, float)
        self.q = jnp.asarray(q, float)
        self.rho = jnp.asarray(rho, float)
        self.inputs = inputs
        self.check_defined()

    def check_defined(self) -> None:
        """Refuse exponents other than 1 with the authors' inputs, where they are concrete (ValueError);
        traced ones are checked by `score`. Callers that score with checked=False call this first."""
        if self.inputs == "jsve":
            return
        for name in ("p", "q"):
            value = getattr(self, name)
            if _is_concrete(value) and np.any(np.asarray(value) != 1.0):
                raise ValueError(
                    f"Combination(inputs={self.inputs!r}) needs {name} = 1, got {np.asarray(value)}: "
                    "its unclamped S_b and S_c can be negative, so only the linear mean (p = q = 1) "
                    "is defined"
                )

    def __call__(self, ratio: ArrayLike, sb: ArrayLike, sc: ArrayLike) -> Float[Array, ...]:
        """SVE score from the inlier ratio (N_inliers / N_extracted), S_b and S_c (same shapes); the
        clamped features of inputs="jsve" only (`score` serves every `inputs`)."""
        if self.inputs != "jsve":
            raise ValueError(
                f"Combination(inputs={self.inputs!r}) combines S_a, S_b, S_c variants that "
                "(inlier ratio, S_b, S_c) do not carry: call .score(features)"
            )
        ratio, sb, sc = (jnp.asarray(x, float) for x in (ratio, sb, sc))
        return combination_from_logs(self, *feature_logs(ratio, sb, sc))

    def score(self, features: FrameFeatures, *, checked: bool = True) -> Float[Array, "*batch"]:
        """SVE score of every frame of `features`, from the S_a, S_b, S_c variants `inputs` names.

        checked=False leaves out the traced check of p = q = 1 for the authors' inputs: that check is a
        host callback, and a computation holding one is never kept in JAX's persistent compilation cache.
        Pass it only for a rule `check_defined` has passed with concrete leaves.
        """
        if self.inputs == "jsve":
            return self(features.inlier_ratio, features.s_b, features.s_c)
        if self.inputs == "authors-eq1":
            a = features.s_a_original
        else:  # "authors-option1"
            a = s_a_from_ratio(features.inlier_ratio, self.rho)
        b, c = features.s_b_unclamped, features.s_c_unclamped
        # M_1([a, M_1([b, c]; u)]; w): the linear combination the authors' builds compute
        # (Tracking::TrackLocalMap, "visibility" of the Option 1 build)
        value = self.w_a * a + (1.0 - self.w_a) * (self.u_b * b + (1.0 - self.u_b) * c)
        if not checked:
            return value
        nonlinear = (self.p != 1.0) | (self.q != 1.0)
        return eqx.error_if(
            value, nonlinear, f"Combination(inputs={self.inputs!r}) is only defined for p = q = 1"
        )


EQ1 = dict(w_a=0.2, u_b=0.5, p=1.0, q=1.0, rho=0.5, inputs="authors-eq1")
"""Eq.1 as the authors built it: 0.2 a + 0.4 b + 0.4 c of Haggart's S_a = N_extracted / nFeatures and
the unclamped S_b, S_c (rho is not used; 0.5 is only a placeholder leaf)."""
OPTION1 = dict(w_a=0.5, u_b=0.5, p=1.0, q=1.0, rho=0.5, inputs="authors-option1")
"""Eq.2 "Option 1" as the authors built it: 0.5 a + 0.25 b + 0.25 c with S_a clamped at rho = 0.5,
S_b and S_c unclamped."""
OPTION2 = dict(w_a=0.5, u_b=0.5, p=0.0, q=1.0, rho=0.25)
"""Eq.3 "Option 2": sqrt(a (0.5 b + 0.5 c)) with rho = 0.25 and every input clamped (the seed's final
code; jsve's inputs are that build's)."""
JSVE_EQ1 = dict(w_a=0.2, u_b=0.5, p=1.0, q=1.0, rho=0.5)
"""Eq.1's weights on jsve's clamped inputs, S_a at rho = 0.5 (jsve's choice; no build has it)."""
JSVE_OPTION1 = dict(w_a=0.5, u_b=0.5, p=1.0, q=1.0, rho=0.5)
"""Option 1's weights on jsve's clamped inputs (the authors' build leaves S_b and S_c unclamped)."""

COMBINATIONS = {
    "sve-eq1": EQ1,
    "sve-option1": OPTION1,
    "sve-option2": OPTION2,
    "jsve-eq1": JSVE_EQ1,
    "jsve-option1": JSVE_OPTION1,
}
"""The combination of every SVE rule preset by preset name (jsve.core._rules adds the thresholds)."""


class FrameFeatures(eqx.Module):
    """Per-frame quantities every rule needs, computed once per batch (shapes [..., frames]).

    Every field after the first two is an SVE metric under its own name: `feature_metrics` reads them
    from the fields, so the per-level tables of a study follow this class (a new metric is its
    function, a field here, a line in `frame_features` and a column of `sve_table`). The clamped ones
    lie in [0, 1]; the authors' unclamped variants do not (S_b down to -8, S_c and S_a original above 1).

    Attributes:
        n_inliers: tracked inliers (count, float).
        inlier_ratio: N_inliers / N_extracted (S_a before rho).
        s_b: clamped homogeneity.
        s_c: clamped tracked-vs-expected.
        s_a_original: Haggart's N_extracted / nFeatures, unclamped.
        s_b_unclamped: homogeneity as the authors' original and Option 1 builds compute it.
        s_c_unclamped: tracked-vs-expected as the authors' original and Option 1 builds compute it.
    """

    n_inliers: Float[Array, "*batch"]
    inlier_ratio: Float[Array, "*batch"]
    s_b: Float[Array, "*batch"]
    s_c: Float[Array, "*batch"]
    s_a_original: Float[Array, "*batch"]
    s_b_unclamped: Float[Array, "*batch"]
    s_c_unclamped: Float[Array, "*batch"]


def frame_features(n_extracted, n_inliers, n_frustum, bins, n_features: ArrayLike = 1000.0) -> FrameFeatures:
    """FrameFeatures from raw counts (any leading shape; bins has a trailing axis of 64).

    Arguments:
        n_extracted, n_inliers, n_frustum: counts per frame, shape (...).
        bins: keypoints per SVE bin, shape (..., 64).
        n_features: ORB nFeatures of the front-end (ORBextractor.nFeatures), broadcastable to the
            counts' shape: a scalar, or [R, 1] for a batch of R runs. 1000 (ORB-SLAM3's EuRoC
            setting) by default.
    """
    shape = np.shape(n_extracted)
    try:
        broadcast = jnp.broadcast_shapes(np.shape(n_features), shape)
    except ValueError:
        broadcast = None
    if broadcast != shape:
        raise ValueError(
            f"n_features has shape {np.shape(n_features)}, which does not broadcast to the counts' shape "
            f"{shape} (pass a scalar, or [runs, 1] for counts of shape [runs, frames])"
        )
    s_b_raw = s_b(bins, n_extracted, clamp=False)
    s_c_raw = s_c(n_inliers, n_frustum, clamp=False)
    return FrameFeatures(
        n_inliers=jnp.asarray(n_inliers, float),
        inlier_ratio=inlier_ratio(n_inliers, n_extracted),
        s_b=jnp.clip(s_b_raw, 0.0, 1.0),
        s_c=jnp.clip(s_c_raw, 0.0, 1.0),
        s_a_original=s_a_original(n_extracted, n_features),
        s_b_unclamped=s_b_raw,
        s_c_unclamped=s_c_raw,
    )


def feature_metrics(features: FrameFeatures, rho: ArrayLike) -> dict[str, Float[Array, "*batch"]]:
    """The SVE metrics of the features by name: "s_a" (the inlier ratio scaled by rho, `s_a_from_ratio`),
    then every further field of FrameFeatures ("s_b", "s_c", "s_a_original", "s_b_unclamped",
    "s_c_unclamped"), in field order.

    The authors' unclamped variants are included although they leave [0, 1]: they are what the
    authors' Eq.1 and Option 1 presets combine, and a study's per-level means of them show how far.
    """
    out = {"s_a": s_a_from_ratio(features.inlier_ratio, rho)}
    for name in metric_names()[1:]:
        out[name] = getattr(features, name)
    return out


def metric_names() -> tuple[str, ...]:
    """The keys of `feature_metrics` in its order: "s_a", then every field of FrameFeatures but the
    inlier rule's count and S_a before rho."""
    skipped = ("n_inliers", "inlier_ratio")
    return ("s_a", *(f.name for f in dataclasses.fields(FrameFeatures) if f.name not in skipped))


def sve_table(n_extracted, n_inliers, n_frustum, bins, n_features=1000) -> dict[str, Array]:
    """Every metric and preset combination for a set of frames, as named columns (for `jsve sve`):
    the metrics, then "sve_eq1", "sve_option1", "sve_option2", "jsve_eq1", "jsve_option1" (COMBINATIONS,
    "-" written "_")."""
    f = frame_features(n_extracted, n_inliers, n_frustum, bins, n_features)
    metrics = {
        "s_a_original": f.s_a_original,
        "s_a_rho025": s_a_from_ratio(f.inlier_ratio, 0.25),
        "s_a_rho050": s_a_from_ratio(f.inlier_ratio, 0.5),
        "s_b": f.s_b,
        "s_b_unclamped": f.s_b_unclamped,
        "s_c": f.s_c,
        "s_c_unclamped": f.s_c_unclamped,
    }
    scores = {name.replace("-", "_"): Combination(**c).score(f) for name, c in COMBINATIONS.items()}
    return metrics | scores
