"""jsve.fitting._space: the design point, from free values in a box to named values to the rule.

Oracles: the rule Modules' own fields (jsve.core._rules.param_names), the presets (jsve.core._rules.preset),
and the combination itself for the derived simplex weights (with p = q = 1 the score is their weighted sum).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jsve.core._rules import PRESETS, InlierRule, SVERule, Thresholds, param_names, preset, rule_to_dict
from jsve.core._sve import Combination
from jsve.fitting._space import (
    BOUNDS,
    SCORE_SCALE,
    ParamSpace,
    RuleParams,
    family_space,
    inlier_space,
    is_space_point,
    preset_point,
    preset_values,
    space_from_dict,
    sve_space,
)


def test_names_and_boxes_come_from_the_rule_modules():
    """The free names of a family's full space are its Modules' fields, in order; every name has a box
    and a score scale (a parameter added to Thresholds or Combination without a box fails here)."""
    static = lambda f: f.metadata.get("static", False)  # noqa: E731 - e.g. Combination.inputs, not fitted
    fields = lambda cls: tuple(f.name for f in dataclasses.fields(cls) if not static(f))  # noqa: E731
    assert sve_space().names == fields(Combination) + fields(Thresholds) == param_names("sve")
    assert inlier_space().names == fields(Thresholds) == param_names("inliers")
    for kind, boxes in BOUNDS.items():
        assert set(boxes) == set(param_names(kind)), kind
        assert kind in SCORE_SCALE
        assert family_space(kind) == space_from_dict({"kind": kind})
    with pytest.raises(ValueError, match="space kind must be 'sve' or 'inliers', got 'linear'"):
        family_space("linear")
    with pytest.raises(ValueError, match="ParamSpace kind must be"):
        ParamSpace("linear", ("a",), (0.0,), (1.0,))


def test_param_space_coordinates_and_rules():
    space = sve_space()
    rng = np.random.default_rng(0)
    values = np.asarray(space.values_from_unit(rng.random((5, space.dim))))
    z = space.z_from_values(values)
    np.testing.assert_allclose(np.asarray(space.values_from_z(z)), values, rtol=1e-6, atol=1e-6)
    rules = space.rule(jnp.asarray(values))
    assert isinstance(rules, SVERule) and rules.combination.w_a.shape == (5,)
    recovery = values[:, space.names.index("recovery")]
    np.testing.assert_allclose(np.asarray(rules.thresholds.recovery), recovery)
    # every z maps into the box (float32 rounding of the bounds aside): weights on the simplex, thresholds
    # within their ranges
    wild = np.asarray(space.values_from_z(jnp.asarray(rng.normal(scale=30, size=(100, space.dim)))))
    slack = 1e-6 * (np.asarray(space.hi) - np.asarray(space.lo))
    assert np.all(wild >= np.asarray(space.lo) - slack) and np.all(wild <= np.asarray(space.hi) + slack)
    fixed = space.fix(rho=0.25, p=0.0)
    assert fixed.dim == space.dim - 2 and dict(fixed.fixed) == {"rho": 0.25, "p": 0.0}
    assert float(fixed.rule(jnp.zeros(fixed.dim)).combination.rho) == 0.25
    assert space_from_dict(fixed.describe()) == fixed
    orbslam3 = inlier_space().values_of(preset("orbslam3"))  # 15, 50, 50, 10 inliers
    params = RuleParams.from_values(inlier_space(), orbslam3)
    assert isinstance(params.rule(), InlierRule)
    # float32; a value on a box edge would come back 1e-6 of its box inside (the logit's clip)
    np.testing.assert_allclose(np.asarray(params.values()), orbslam3, rtol=1e-5, atol=1e-6 * 200)
    with pytest.raises(ValueError, match="free or fixed exactly once"):
        ParamSpace("inliers", ("imu_init",), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="lo < hi"):
        inlier_space(imu_init=(5.0, 5.0))
    with pytest.raises(ValueError, match="not in the 'sve' family"):
        space.values_of(preset("orbslam3"))
    with pytest.raises(ValueError, match="values have 3 coordinates"):
        space.rule(jnp.zeros(3))


def test_named_values_fixed_then_free():
    """`params` names every parameter: the fixed ones, then the free ones in coordinate order (the
    order of the study's fitted_*.json and cv_params tables)."""
    space = sve_space().fix(rho=0.25, p=0.0)
    values = np.linspace(0.1, 0.7, space.dim)
    params = space.params(values)
    assert list(params) == ["rho", "p", *space.names]
    assert [params[k] for k in space.names] == pytest.approx(values.tolist(), rel=0, abs=0)
    assert rule_to_dict(space.rule(jnp.asarray(values)))["combination"]["p"] == 0.0


def test_presets_as_points():
    """Every preset is a point of its family's full space that maps back to the preset's own rule
    (float32 leaves: 1e-6 relative), and the presets kept by a narrowed space are those inside it."""
    for name in PRESETS:
        if not is_space_point(preset(name)):  # the authors' Eq.1 / Option 1 combine other inputs
            with pytest.raises(ValueError, match=f"preset '{name}' combines .*no point of a ParamSpace"):
                preset_point(name)
            assert name not in preset_values(sve_space())
            continue
        space, values = preset_point(name)
        assert space.contains(values)
        again = rule_to_dict(space.rule(jnp.asarray(values)))
        want = rule_to_dict(preset(name))
        assert again["kind"] == want["kind"]
        for part in want:
            if part != "kind":
                np.testing.assert_allclose(list(again[part].values()), list(want[part].values()), rtol=1e-6)
    space = sve_space()
    for name, v in preset_values(space).items():
        np.testing.assert_allclose(space.values_of(space.rule(jnp.asarray(v))), v, rtol=1e-6)
        assert name.startswith(("sve-", "jsve-"))
    assert list(preset_values(inlier_space())) == ["orbslam3"]
    assert set(preset_values(space.fix(rho=0.25, p=0.0))) == {"sve-option2"}  # rho 0.25 and p = 0
    assert preset_values(inlier_space(imu_init=(20.0, 30.0))) == {}  # 15 lies outside


def test_derived_simplex_weights_are_the_flat_combination(x64):
    """With p = q = 1 the nested mean is the weighted sum of (S_a, S_b, S_c) with the derived weights:
    to 1e-14 (the combination runs in the log domain: log1p, exp and a division add a few roundings;
    measured 1.3e-15). Without both w_a and u_b free there is nothing to derive."""
    space = sve_space()
    rng = np.random.default_rng(2)
    values = np.array(space.values_from_unit(rng.random((6, space.dim))))
    values[:, space.names.index("p")] = values[:, space.names.index("q")] = 1.0
    derived = space.derived(values)
    assert list(derived) == ["weight_a", "weight_b", "weight_c"]
    weights = np.stack(list(derived.values()), -1)
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=0, atol=1e-15)
    ratio, sb, sc = 0.05, 0.4, 0.9
    for v, w in zip(values, weights, strict=True):
        rule = space.rule(jnp.asarray(v))
        s_a = min(ratio / float(rule.combination.rho), 1.0)
        score = float(rule.combination(ratio, sb, sc))
        np.testing.assert_allclose(score, w @ [s_a, sb, sc], rtol=0, atol=1e-14)
    assert space.fix(u_b=0.5).derived(values[:, 1:]) == {}
    assert inlier_space().derived(np.zeros(4)) == {}


def test_rule_of_values_eager_jit_vmap_grad(x64):
    """`ParamSpace.rule` after `values_from_z` is a JAX function of z: jitted equals eager, vmapped over
    settings equals a loop (to 1e-14 relative: XLA may vectorise or fuse exp/log differently, a few
    ulp), and the gradient of a rule's score in z equals central differences (h = 1e-5; the score is
    smooth at these interior points: 1e-7 relative)."""
    space = sve_space()
    z = jnp.asarray(np.random.default_rng(3).normal(size=(4, space.dim)))
    ratio, sb, sc = 0.05, 0.4, 0.9

    def score(zi):
        return space.rule(space.values_from_z(zi)).combination(ratio, sb, sc)

    batched = np.asarray(jax.vmap(score)(z))
    jitted = jax.jit(score)
    for i in range(4):
        eager = float(score(z[i]))
        assert float(jitted(z[i])) == pytest.approx(eager, rel=1e-14)
        assert batched[i] == pytest.approx(eager, rel=1e-14)
    g = np.asarray(jax.grad(score)(z[0]))
    for j in range(space.dim):
        e = jnp.zeros(space.dim).at[j].set(1e-5)
        fd = (float(score(z[0] + e)) - float(score(z[0] - e))) / 2e-5
        np.testing.assert_allclose(g[j], fd, rtol=1e-7, atol=1e-11, err_msg=space.names[j])
    thresholds = [space.names.index(k) for k in param_names("inliers")]
    assert np.all(g[thresholds] == 0)  # thresholds do not enter the score
