"""jsve.core._rules: presets, rule descriptions, and machine_step against the oracle's single step.

machine_step is compared with oracle_orbslam3.step on every combination of mode, score class
(below, at and above each threshold), logged imu_init, IMU delay (before, at, after), relocalisation
window (inside, last frame, first frame after) and timer (before, at, after 5 s), for three threshold
orders and two fps (20, 20.5): 8,748 cases in one vmapped call. Whole runs: tests/test_replay.py.
"""

from __future__ import annotations

import dataclasses
import itertools
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import oracle_orbslam3 as oracle
import pytest

from jsve.core._machine import (
    MODE_LOST,
    MODE_OK,
    MODE_RECENTLY_LOST,
    TIME_RECENTLY_LOST_S,
    HardLogic,
    MachineState,
    SoftLogic,
    initial_state,
    machine_step,
    tracking_succeeds,
)
from jsve.core._rules import (
    BASELINES,
    PRESETS,
    RULE_KINDS,
    InlierRule,
    SVERule,
    Thresholds,
    param_names,
    preset,
    rule_from_dict,
    rule_from_params,
    rule_kind,
    rule_params,
    rule_static,
    rule_to_dict,
)
from jsve.core._sve import Combination, FrameFeatures, frame_features

TH_ORDERS = {
    "orbslam3": dict(imu_init=15.0, not_init=50.0, reloc=50.0, recovery=10.0),
    # recovery above imu_init and reloc below not_init: the success test's later branches decide
    "shuffled": dict(imu_init=15.0, not_init=49.0, reloc=16.0, recovery=30.0),
    # reloc above not_init: tells a new map's window test from its not_init test
    "strict_reloc": dict(imu_init=10.0, not_init=16.0, reloc=50.0, recovery=15.0),
}
SCORES = (9.0, 10.0, 11.0, 15.0, 16.0, 30.0, 49.0, 50.0, 51.0)
FPS_VALUES = (20.0, 20.5)  # ORB-SLAM3's window is int(fps) frames: 20.5 must act as 20


# ------------------------------------------------------------------------------------------------
# Presets and descriptions


def features_grid():
    """A few frames' features covering clamps and zero denominators."""
    rng = np.random.default_rng(0)
    ext = np.array([1000, 1000, 1000, 0, 500, 800, 1000, 300])
    inl = np.array([0, 50, 400, 0, 100, 15, 1000, 300])
    fru = np.array([200, 0, 300, 0, 80, 60, 900, 300])
    bins = np.stack([rng.multinomial(int(n * 0.95), rng.dirichlet(np.full(64, a))) for n, a in
                     zip(ext, [0.1, 1, 5, 1, 0.5, 2, 50, 0.05], strict=True)])  # fmt: skip
    return ext, inl, fru, bins


def test_orbslam3_preset_is_15_50_50_10_on_inliers():
    rule = preset("orbslam3")
    assert isinstance(rule, InlierRule)
    th = rule.thresholds
    assert (float(th.imu_init), float(th.not_init), float(th.reloc), float(th.recovery)) == (15, 50, 50, 10)
    ext, inl, fru, bins = features_grid()
    assert np.array_equal(np.asarray(rule.score(frame_features(ext, inl, fru, bins))), inl)


def _by_hand(ext, inl, fru, bins, rho, clamped=True, n_features=1000.0):
    """(S_a, S_b, S_c) of the counts written out: jsve's clamped inputs, or the authors' unclamped
    ones (S_a original = N / nFeatures when rho is None, else the clamped inlier ratio over rho)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if rho is None:
            sa = ext / n_features
        else:
            sa = np.where(ext > 0, np.clip(inl / (rho * ext), 0, 1), 0.0)
        e = ext[:, None] / 64.0
        sb = np.where(ext > 0, 1.0 - np.sum((bins - e) ** 2 / e, axis=-1) / (7.0 * ext), 0.0)
        sc = np.where(fru > 0, inl / fru, 0.0)
    if clamped:
        np.testing.assert_allclose(np.clip(sb, 0, 1), oracle.s_b_numpy(bins, ext), atol=1e-14)
        sb, sc = np.clip(sb, 0, 1), np.clip(sc, 0, 1)
    return sa, sb, sc


@pytest.mark.parametrize(
    "name, thresholds, formula, rho, clamped",
    [
        ("sve-option2", (0.06, 0.2, 0.2, 0.04), lambda a, b, c: np.sqrt(a * (0.5 * b + 0.5 * c)), 0.25, True),
        ("sve-eq1", (0.1, 0.3, 0.3, 0.1), lambda a, b, c: 0.2 * a + 0.4 * b + 0.4 * c, None, False),
        ("sve-option1", (0.1, 0.3, 0.3, 0.1), lambda a, b, c: 0.5 * a + 0.25 * b + 0.25 * c, 0.5, False),
        ("jsve-eq1", (0.1, 0.3, 0.3, 0.1), lambda a, b, c: 0.2 * a + 0.4 * b + 0.4 * c, 0.5, True),
        ("jsve-option1", (0.1, 0.3, 0.3, 0.1), lambda a, b, c: 0.5 * a + 0.25 * b + 0.25 * c, 0.5, True),
    ],
)
def test_sve_presets(x64, name, thresholds, formula, rho, clamped):
    """Scores equal the seed's formulas written out by hand to 1e-12 (float64 rounding of a few
    operations on values up to ~10; the geometric mean is evaluated as exp(mean log)): Option 2 and
    jsve's variants on the clamped metrics, the authors' Eq.1 and Option 1 on the unclamped S_b, S_c
    (Eq.1 with S_a = N / nFeatures), with the thresholds of their builds."""
    rule = preset(name)
    assert isinstance(rule, SVERule)
    th = rule.thresholds
    np.testing.assert_allclose([float(th.imu_init), float(th.not_init), float(th.reloc), float(th.recovery)],
                               thresholds, rtol=0, atol=1e-15)  # fmt: skip
    if rho is not None:
        assert float(rule.combination.rho) == rho
    ext, inl, fru, bins = features_grid()
    got = np.asarray(rule.score(frame_features(ext, inl, fru, bins)))
    sa, sb, sc = _by_hand(ext, inl, fru, bins, rho, clamped)
    np.testing.assert_allclose(got, formula(sa, sb, sc), rtol=0, atol=1e-12)
    assert got[3] == 0.0  # a frame without features scores 0
    if clamped:
        assert ((got >= 0) & (got <= 1)).all()
    else:  # the grid has frames whose unclamped S_b is negative or S_c above 1: the score leaves [0, 1]
        assert (sb < 0).any() and (sc > 1).any() and ((got < 0) | (got > 1)).any()


def test_presets_name_their_inputs():
    """The authors' builds combine their own inputs, jsve's presets the clamped ones (docs/sve.md)."""
    inputs = {name: preset(name).combination.inputs for name in PRESETS if name != "orbslam3"}
    assert inputs == {
        "sve-eq1": "authors-eq1",
        "sve-option1": "authors-option1",
        "sve-option2": "jsve",
        "jsve-eq1": "jsve",
        "jsve-option1": "jsve",
    }
    # the same weights and thresholds on either inputs
    for ours, theirs in (("jsve-eq1", "sve-eq1"), ("jsve-option1", "sve-option1")):
        assert rule_params(preset(ours)).keys() == rule_params(preset(theirs)).keys()
        for key, value in rule_params(preset(ours)).items():
            if key != "rho" or theirs == "sve-option1":  # Eq.1's authors' S_a has no rho
                assert float(value) == float(rule_params(preset(theirs))[key]), key


def test_unknown_preset_names_the_choices():
    with pytest.raises(ValueError, match="sve-option2"):
        preset("sve-option3")
    assert PRESETS == ("orbslam3", "sve-eq1", "sve-option1", "sve-option2", "jsve-eq1", "jsve-option1")


@pytest.mark.parametrize("float64", [False, True])
@pytest.mark.parametrize("name", PRESETS)
def test_rule_dict_round_trip(name, float64):
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", float64)
    try:
        rule = preset(name)
        spec = rule_to_dict(rule)
        again = rule_from_dict(json.loads(json.dumps(spec)))  # JSON-ready, and back
        assert type(again) is type(rule)
        assert rule_to_dict(again) == spec and rule_static(again) == rule_static(rule)
        for a, b in zip(jax.tree.leaves(rule), jax.tree.leaves(again), strict=True):
            assert a.dtype == b.dtype and float(a) == float(b)
        # the inputs are written only when they are not jsve's, and read back
        authors = {"sve-eq1": "authors-eq1", "sve-option1": "authors-option1"}
        assert spec.get("combination", {}).get("inputs") == authors.get(name)
    finally:
        jax.config.update("jax_enable_x64", previous)


def test_rule_json_without_inputs_reads_as_jsve(x64):
    """A description written before Combination.inputs existed (no "inputs" key) is a jsve rule; with
    the key it is the authors' build, and the two score differently (float64: the floats come back
    exactly)."""
    old = {"kind": "sve", "combination": {"w_a": 0.2, "u_b": 0.5, "p": 1.0, "q": 1.0, "rho": 0.5},
           "thresholds": {"imu_init": 0.1, "not_init": 0.3, "reloc": 0.3, "recovery": 0.1}}  # fmt: skip
    rule = rule_from_dict(json.loads(json.dumps(old)))
    assert rule.combination.inputs == "jsve" and rule_to_dict(rule) == rule_to_dict(preset("jsve-eq1")) == old
    new = {**old, "combination": {**old["combination"], "inputs": "authors-eq1"}}
    assert rule_to_dict(rule_from_dict(new)) == rule_to_dict(preset("sve-eq1")) == new
    ext, inl, fru, bins = features_grid()
    f = frame_features(ext, inl, fru, bins)
    assert not np.allclose(np.asarray(rule_from_dict(new).score(f)), np.asarray(rule.score(f)))


def test_rule_from_dict_errors_name_source_and_key():
    good = rule_to_dict(preset("sve-option2"))
    with pytest.raises(ValueError, match=r"params\.json: .*'recovery'"):
        rule_from_dict({**good, "thresholds": {"imu_init": 1, "not_init": 1, "reloc": 1}}, "params.json")
    with pytest.raises(ValueError, match=r"params\.json: .*'kind'"):
        rule_from_dict({"thresholds": good["thresholds"]}, "params.json")
    with pytest.raises(ValueError, match=r"params\.json: .*'rho'"):
        combo = {k: v for k, v in good["combination"].items() if k != "rho"}
        rule_from_dict({**good, "combination": combo}, "params.json")
    with pytest.raises(ValueError, match=r"params\.json: rule kind must be 'inliers' or 'sve', got 'linear'"):
        rule_from_dict({**good, "kind": "linear"}, "params.json")
    with pytest.raises(ValueError, match=r"params\.json: bad rule description"):
        rule_from_dict({**good, "thresholds": {**good["thresholds"], "reloc": "high"}}, "params.json")
    with pytest.raises(ValueError, match=r"<dict>: "):
        rule_from_dict([1, 2, 3])
    eq1 = rule_to_dict(preset("sve-eq1"))
    with pytest.raises(ValueError, match=r"params\.json: bad rule description: .*inputs must be one of"):
        rule_from_dict({**eq1, "combination": {**eq1["combination"], "inputs": "authors-eq3"}}, "params.json")
    with pytest.raises(ValueError, match=r"params\.json: bad rule description: .*needs p = 1, got 0\.0"):
        rule_from_dict({**eq1, "combination": {**eq1["combination"], "p": 0.0}}, "params.json")


def test_parameter_names_are_the_modules_fields():
    """A family's parameters are its Modules' fields (SVE: the combination's, then the thresholds'),
    the JSON description's tables are the same fields, and every family has a preset baseline."""
    leaves = lambda cls: tuple(f.name for f in dataclasses.fields(cls) if not f.metadata.get("static"))  # noqa: E731
    assert param_names("inliers") == leaves(Thresholds) == ("imu_init", "not_init", "reloc", "recovery")
    assert param_names("sve") == leaves(Combination) + leaves(Thresholds)
    assert [f.name for f in dataclasses.fields(Combination) if f.metadata.get("static")] == ["inputs"]
    assert "inputs" not in param_names("sve")  # a static field is never a fitted parameter
    for name in PRESETS:
        rule = preset(name)
        kind = rule_kind(rule)
        assert isinstance(rule, RULE_KINDS[kind])
        assert tuple(rule_params(rule)) == param_names(kind)
        assert set(rule_static(rule)) == ({"inputs"} if kind == "sve" else set())
        spec = rule_to_dict(rule)
        written = [k for part in spec if part != "kind" for k in spec[part]]
        statics = [k for k, v in rule_static(rule).items() if v != "jsve"]  # only non-defaults are written
        names, n_combination = list(param_names(kind)), len(leaves(Combination)) if kind == "sve" else 0
        assert written == names[:n_combination] + statics + names[n_combination:]
    assert set(BASELINES) == set(RULE_KINDS) and set(BASELINES.values()) <= set(PRESETS)
    assert all(rule_kind(preset(name)) == kind for kind, name in BASELINES.items())
    with pytest.raises(ValueError, match="rule kind must be 'inliers' or 'sve', got 'linear'"):
        param_names("linear")
    with pytest.raises(TypeError, match="not a jsve rule"):
        rule_kind(Thresholds(1, 2, 3, 4))


def test_rule_from_params_round_trip_jit_vmap_grad(x64):
    """rule_from_params inverts rule_params for every preset (the same leaves, exactly), under jit too;
    built from stacked values it is a stack of rules whose vmapped score equals a loop; and the score of
    a rule built from named values has the gradient of central differences (h = 1e-6, smooth interior
    point: 1e-6 relative)."""
    ext, inl, fru, bins = features_grid()
    f = frame_features(ext, inl, fru, bins)
    for name in PRESETS:
        rule = preset(name)
        kind = rule_kind(rule)
        params, static = rule_params(rule), rule_static(rule)
        jitted = jax.jit(lambda p, kind=kind, static=static: rule_from_params(kind, p, static))(params)
        for again in (rule_from_params(kind, params, static), jitted):
            assert type(again) is type(rule) and rule_static(again) == static
            for a, b in zip(jax.tree.leaves(rule), jax.tree.leaves(again), strict=True):
                assert float(a) == float(b)
        # without the static fields, their defaults: jsve's inputs
        assert all(v == "jsve" for v in rule_static(rule_from_params(kind, params)).values())
    with pytest.raises(ValueError, match="sve rules have no static field 'input'"):
        rule_from_params("sve", rule_params(preset("sve-eq1")), {"input": "authors-eq1"})
    rng = np.random.default_rng(5)
    stacked = {k: jnp.asarray(rng.uniform(0.1, 0.9, 3)) for k in param_names("sve")}
    rules = rule_from_params("sve", stacked)
    scores = np.asarray(jax.vmap(lambda r: r.score(f))(rules))
    for i in range(3):
        one = rule_from_params("sve", {k: v[i] for k, v in stacked.items()})
        np.testing.assert_allclose(scores[i], np.asarray(one.score(f)), rtol=1e-14, atol=1e-15)

    for name in ("jsve-option1", "sve-option1", "sve-eq1"):
        static = rule_static(preset(name))

        def score(w_a, name=name, static=static):
            params = {**rule_params(preset(name)), "w_a": w_a}
            return rule_from_params("sve", params, static).score(f)[5]  # S_a, S_b, S_c of this frame: (0, 1)

        fd = (float(score(0.5 + 1e-6)) - float(score(0.5 - 1e-6))) / 2e-6
        np.testing.assert_allclose(float(jax.grad(score)(0.5)), fd, rtol=1e-6, err_msg=name)


def test_sve_rule_scores_its_combination():
    ext, inl, fru, bins = features_grid()
    f = frame_features(ext, inl, fru, bins)
    for name in PRESETS[1:]:
        rule = preset(name)
        assert np.array_equal(np.asarray(rule.score(f)), np.asarray(rule.combination.score(f)))
    rule = preset("jsve-eq1")  # jsve's inputs: the three-argument form is the same score
    assert np.array_equal(
        np.asarray(rule.score(f)), np.asarray(rule.combination(f.inlier_ratio, f.s_b, f.s_c))
    )


# ------------------------------------------------------------------------------------------------
# machine_step against the oracle's step, exhaustively


def _cases():
    """Every combination, as (oracle state, frame inputs) pairs. Times are exact in binary."""
    cases = []
    modes = (oracle.OK, oracle.RECENTLY_LOST, oracle.LOST)
    for th_name, fps, mode, score, imu, delay_rel, window_rel, timer_rel in itertools.product(
        TH_ORDERS, FPS_VALUES, modes, SCORES, (0, 1), (-1, 0, 1), (-1, 0, 1), (-1, 0, 1)
    ):
        map_start_k, map_start_t = 40, 2.0
        k = map_start_k + int(fps) - 1 + window_rel  # inside, the window's last frame, the first after
        t = 10.0
        delay = (t - map_start_t) - 0.25 * delay_rel  # usable when t - map_start_t >= delay
        t_lost = t - TIME_RECENTLY_LOST_S - 0.25 * timer_rel  # expired when t - t_lost > 5
        state = oracle.State(
            mode=mode, t_lost=t_lost, map_start_t=map_start_t, map_start_k=map_start_k, segment=3
        )
        cases.append((th_name, state, score, t, k, imu, delay, fps))
    return cases


def _jax_state(states, dtype):
    arr = lambda xs: jnp.asarray(np.array(xs, float), dtype)  # noqa: E731
    return MachineState(
        ok=arr([s.mode == oracle.OK for s in states]),
        recently_lost=arr([s.mode == oracle.RECENTLY_LOST for s in states]),
        lost=arr([s.mode == oracle.LOST for s in states]), t_lost=arr([s.t_lost for s in states]),
        map_start_t=arr([s.map_start_t for s in states]), map_start_k=arr([s.map_start_k for s in states]),
        segment=arr([s.segment for s in states]),
    )  # fmt: skip


def _inputs(cases, dtype):
    arr = lambda xs: jnp.asarray(np.array(xs, float), dtype)  # noqa: E731
    th = Thresholds(**{key: arr([TH_ORDERS[c[0]][key] for c in cases]) for key in TH_ORDERS["orbslam3"]})
    return dict(state=_jax_state([c[1] for c in cases], dtype), score=arr([c[2] for c in cases]),
                t=arr([c[3] for c in cases]), k=arr([c[4] for c in cases]), imu=arr([c[5] for c in cases]),
                th=th, delay=arr([c[6] for c in cases]), fps=arr([c[7] for c in cases]))  # fmt: skip


def _step(logic, state, score, t, k, imu, th, delay, fps):
    return machine_step(logic, state, score, t, k, imu, th, fps, delay)


def _expected(cases):
    out = []
    for th_name, state, score, t, k, imu, delay, fps in cases:
        nxt, visual, predicted = oracle.step(state, score, t, k, imu, TH_ORDERS[th_name], fps, delay)
        out.append((nxt, visual, predicted))
    return out


def _check_against_oracle(next_state, decision, cases, expected):
    s = {
        k: np.asarray(getattr(next_state, k)).tolist()
        for k in ("ok", "recently_lost", "lost", "segment", "map_start_t", "map_start_k", "t_lost")
    }
    d = {k: np.asarray(getattr(decision, k)).tolist() for k in ("accepted", "predicted", "new_map")}
    bad = []
    for i, (case, (nxt, visual, predicted)) in enumerate(zip(cases, expected, strict=True)):
        got = ([s["ok"][i], s["recently_lost"][i], s["lost"][i]], d["accepted"][i], d["predicted"][i],
               s["segment"][i], s["map_start_t"][i], s["map_start_k"][i], d["new_map"][i])  # fmt: skip
        want_mode = [float(nxt.mode == m) for m in (oracle.OK, oracle.RECENTLY_LOST, oracle.LOST)]
        want = (want_mode, float(visual), float(predicted), float(nxt.segment), float(nxt.map_start_t),
                float(nxt.map_start_k), float(nxt.segment != case[1].segment))  # fmt: skip
        if got != want:
            bad.append(f"case {case}: got {got}, oracle {want}")
        elif nxt.mode == oracle.RECENTLY_LOST and s["t_lost"][i] != nxt.t_lost:
            bad.append(f"case {case}: t_lost {s['t_lost'][i]}, oracle {nxt.t_lost}")
    return bad


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_machine_step_matches_oracle_step_exhaustively(dtype):
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", dtype == jnp.float64)
    try:
        cases = _cases()
        inputs = _inputs(cases, dtype)
        step = jax.jit(jax.vmap(lambda *a: _step(HardLogic(), *a)))
        next_state, decision = step(*inputs.values())
        assert next_state.ok.dtype == dtype
        bad = _check_against_oracle(next_state, decision, cases, _expected(cases))
    finally:
        jax.config.update("jax_enable_x64", previous)
    assert len(cases) == 8748
    assert not bad, f"{len(bad)} of {len(cases)} cases differ:\n" + "\n".join(bad[:10])


def test_machine_step_eager_jit_vmap_agree(x64):
    """Op by op (jax.disable_jit), under jit, and vmapped: identical outputs, bit for bit (a step is
    exact {0, 1} arithmetic and selections of the inputs)."""
    cases = _cases()[::97]  # 91 cases spread over the grid
    inputs = _inputs(cases, jnp.float64)
    batched = jax.jit(jax.vmap(lambda *a: _step(HardLogic(), *a)))(*inputs.values())
    jitted = jax.jit(lambda *a: _step(HardLogic(), *a))
    for i in range(len(cases)):
        one = jax.tree.map(lambda x, i=i: x[i], tuple(inputs.values()))
        with jax.disable_jit():
            eager = _step(HardLogic(), *one)
        for out in (jitted(*one), eager):
            for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(batched), strict=True):
                assert float(a) == float(b[i])


def test_initial_state_is_ok_in_map_zero():
    s = initial_state()
    assert (float(s.ok), float(s.recently_lost), float(s.lost)) == (1.0, 0.0, 0.0)
    assert float(s.segment) == 0 and float(s.map_start_k) == 0 and float(s.map_start_t) == 0
    assert (MODE_OK, MODE_RECENTLY_LOST, MODE_LOST) == (oracle.OK, oracle.RECENTLY_LOST, oracle.LOST)
    assert TIME_RECENTLY_LOST_S == 5.0  # ORB-SLAM3 v1.0 Tracking::time_recently_lost


# ------------------------------------------------------------------------------------------------
# SoftLogic


def test_soft_comparisons_tend_to_hard_ones(x64):
    x = jnp.asarray([-2.0, -0.1, 0.0, 0.1, 2.0])
    hard = HardLogic()
    for temperature, tol in ((1.0, 0.5), (0.01, 5e-5), (0.001, 1e-40)):
        soft = SoftLogic(jnp.asarray(temperature))
        for name in ("less", "greater"):
            s, h = np.asarray(getattr(soft, name)(x, 0.0)), np.asarray(getattr(hard, name)(x, 0.0))
            off_tie = x != 0
            assert np.abs(s - h)[off_tie].max() <= tol + 1e-300, (name, temperature)
            assert s[~off_tie] == 0.5  # an exact tie is undecided at every temperature
    # greater = 1 - less away from ties, monotone in x
    soft = SoftLogic(jnp.asarray(0.3))
    np.testing.assert_allclose(np.asarray(soft.less(x, 0.0) + soft.greater(x, 0.0)), 1.0, atol=1e-15)
    assert np.all(np.diff(np.asarray(soft.less(x, 0.0))) < 0)
    q = jnp.asarray([2.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(soft.normalize_quat(q)), [1, 0, 0, 0])
    assert np.array_equal(np.asarray(hard.normalize_quat(q)), np.asarray(q))


def test_soft_step_converges_to_hard_step_off_ties(x64):
    cases = [c for c in _cases() if c[2] not in TH_ORDERS[c[0]].values()]
    inputs = _inputs(cases, jnp.float64)
    hard_state, hard_decision = jax.vmap(lambda *a: _step(HardLogic(), *a))(*inputs.values())
    previous = None
    for temperature in (3.0, 0.3, 0.03, 0.003):
        logic = SoftLogic(jnp.asarray(temperature))
        soft_state, soft_decision = jax.vmap(lambda *a, lg=logic: _step(lg, *a))(*inputs.values())
        soft_leaves = jax.tree.leaves((soft_state, soft_decision))
        hard_leaves = jax.tree.leaves((hard_state, hard_decision))
        err = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(soft_leaves, hard_leaves, strict=True))
        assert previous is None or err <= previous
        previous = err
    # scores are >= 1 inlier from every threshold: at T = 0.003 each sigmoid is within e^-333 of
    # its limit; the clocks (times ~10 s, frame indices ~60) then match to their rounding.
    assert previous < 1e-12


def test_soft_step_conserves_probability(x64):
    """From any mixed state (probabilities summing to 1), the next mode flags sum to 1 too, and
    accepted + predicted <= 1 (the rest is LOST)."""
    rng = np.random.default_rng(1)
    n = 500
    w = rng.dirichlet(np.ones(3), n)
    state = MachineState(
        ok=jnp.asarray(w[:, 0]), recently_lost=jnp.asarray(w[:, 1]), lost=jnp.asarray(w[:, 2]),
        t_lost=jnp.asarray(rng.uniform(0, 10, n)), map_start_t=jnp.asarray(rng.uniform(0, 10, n)),
        map_start_k=jnp.asarray(rng.integers(0, 200, n).astype(float)),
        segment=jnp.asarray(rng.uniform(0, 3, n)),
    )  # fmt: skip
    th = Thresholds(**TH_ORDERS["orbslam3"])
    logic = SoftLogic(jnp.asarray(2.0))
    nxt, decision = jax.vmap(
        lambda s, sc, t, k, imu, d: machine_step(logic, s, sc, t, k, imu, th, 20.0, d)
    )(state, jnp.asarray(rng.uniform(0, 60, n)), jnp.asarray(rng.uniform(10, 16, n)),
      jnp.asarray(rng.integers(0, 300, n).astype(float)), jnp.asarray(rng.integers(0, 2, n).astype(float)),
      jnp.asarray(rng.uniform(0, 3, n)))  # fmt: skip
    total = np.asarray(nxt.ok + nxt.recently_lost + nxt.lost)
    np.testing.assert_allclose(total, 1.0, atol=1e-14)  # a few roundings of products of [0, 1] values
    both = np.asarray(decision.accepted + decision.predicted)
    assert (both <= 1 + 1e-14).all() and (np.asarray(decision.accepted) >= 0).all()
    np.testing.assert_allclose(np.asarray(decision.accepted), np.asarray(nxt.ok), atol=0)


def test_tracking_succeeds_branch_order():
    """The success test's order (ORB-SLAM3 v1.0 Tracking::TrackLocalMap): the relocalisation
    window first, then the recovery rule in RECENTLY_LOST, then the IMU / no-IMU threshold."""
    th = Thresholds(imu_init=15.0, not_init=50.0, reloc=50.0, recovery=10.0)
    hard = HardLogic()

    def ok(score, rl, imu, reloc):
        return float(tracking_succeeds(hard, jnp.asarray(score), th, rl, imu, reloc))

    assert ok(30.0, 1.0, 1.0, 1.0) == 0.0  # window beats recovery: 30 > 10 but < 50
    assert ok(11.0, 1.0, 0.0, 0.0) == 1.0  # recovery beats the no-IMU threshold: 11 < 50
    assert ok(10.0, 1.0, 1.0, 0.0) == 0.0  # recovery is strict, then 10 < 15 fails
    assert ok(15.0, 0.0, 1.0, 0.0) == 1.0 and ok(14.0, 0.0, 1.0, 0.0) == 0.0  # fail only below
    assert ok(49.0, 0.0, 0.0, 0.0) == 0.0 and ok(50.0, 0.0, 0.0, 1.0) == 1.0


def test_features_are_a_pytree_of_arrays():
    """Rules and features are eqx Modules whose leaves are arrays (sweeps vmap over them)."""
    rule = preset("sve-option2")
    assert all(isinstance(x, jax.Array) for x in jax.tree.leaves(rule))
    stacked = jax.tree.map(lambda *x: jnp.stack(x), rule, rule)
    ext, inl, fru, bins = features_grid()
    f = frame_features(ext, inl, fru, bins)
    scores = eqx.filter_vmap(lambda r: r.score(f))(stacked)
    assert scores.shape == (2, len(ext))
    assert isinstance(f, FrameFeatures)
