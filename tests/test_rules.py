"""jsve.core._rules: presets and rule descriptions; jsve.core._machine: machine_step row by row.

machine_step is checked on every row of docs/state-machine.md's table (hard, in float32 and float64),
eagerly, under jit and vmap, and relaxed (SoftLogic: convergence to the hard step, conservation of
probability). Whole runs: tests/test_replay.py; randomized comparisons with the plain-Python oracle
written from Tracking.cc: tests/test_oracle.py.
"""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

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
    FrameData,
    HardLogic,
    MachineState,
    RunConstants,
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
# machine_step: the table of docs/state-machine.md, row by row

ORB_TH = dict(imu_init=15.0, not_init=50.0, reloc=50.0, recovery=10.0)
MODES = {"O": (1.0, 0.0, 0.0), "R": (0.0, 1.0, 0.0), "L": (0.0, 0.0, 1.0)}
CLOCKS = ("lost_ready", "t_lost", "map_start_t", "reloc_k", "lost_reloc_k", "segment")  # and the ready mass
DECISIONS = ("tracked", "coasting", "new_map", "loss", "reset")


def _machine_inputs(mode, clocks, frame, run, dtype=jnp.float64):
    """MachineState, FrameData and RunConstants of one frame at t = 10 s, k = 200 (fps 20) in the log's
    first map (started at t = 0, window from frame 0), IMU initialised, BA2 done, posed, no recorded
    start, unless `clocks`, `frame` or `run` say otherwise."""
    arr = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    ok, rl, lost = MODES[mode]
    state = dict(ok=ok, recently_lost=rl, lost=lost, lost_ready=0.0, t_lost=0.0, map_start_t=0.0, reloc_k=0.0,
                 segment=0.0) | clocks  # fmt: skip
    state = {"lost_reloc_k": state["reloc_k"]} | state  # the hard machine has one mnLastRelocFrameId
    data = dict(t=10.0, k=200.0, imu_init=1.0, imu_ba2=1.0, has_pose=1.0, init_keys=0.0, init_matches=0.0,
                rec_start=0.0, rec_loss=0.0, rec_start_t=0.0, rec_reloc=-1.0) | frame  # fmt: skip
    constants = dict(fps=20.0, imu_init_delay=0.0, ba2_delay=0.0, stereo=0.0) | run
    return (
        MachineState(**{k: arr(v) for k, v in state.items()}),
        FrameData(**{k: arr(v) for k, v in data.items()}),
        RunConstants(**{k: arr(v) for k, v in constants.items()}),
    )


def _row(name, mode, score, then, decided=(), *, clocks=None, frame=None, run=None, changed=None):
    """One row: from `mode` with `clocks`, the frame (`frame`, `run` overrides) and `score` lead to mode
    `then` with the decisions `decided` set (the others 0) and the clocks `changed` (the others kept)."""
    changed = dict(changed or {})
    if "reloc_k" in changed:  # the hard machine has one mnLastRelocFrameId: both mass clocks follow it
        changed.setdefault("lost_reloc_k", changed["reloc_k"])
    overrides = dict(clocks=clocks or {}, frame=frame or {}, run=run or {}, changed=changed)
    return SimpleNamespace(name=name, mode=mode, score=score, then=then, decided=set(decided), **overrides)


RESET = {"reloc_k": 200.0}  # a reset at frame 200: the window counts from it
NO_IMU, NO_BA2, STEREO = {"imu_init": 0.0}, {"imu_ba2": 0.0}, {"stereo": 1.0}
READY, INIT = {"lost_ready": 1.0}, {"init_keys": 1.0, "init_matches": 1.0}
TABLE = [
    _row("OK passes", "O", 20.0, "O", ["tracked"]),
    _row("OK passes at imu_init", "O", 15.0, "O", ["tracked"]),
    _row("OK fails with IMU and BA2: timer set", "O", 14.0, "R", ["coasting"], changed={"t_lost": 10.0}),
    _row("OK fails before IMU initialisation: reset", "O", 49.0, "L", ["loss", "reset"], frame=NO_IMU,
         changed=RESET),
    _row("OK fails before BA2: reset", "O", 14.0, "L", ["loss", "reset"], frame=NO_BA2, changed=RESET),
    _row("stereo before IMU initialisation: imu_init decides", "O", 20.0, "O", ["tracked"], frame=NO_IMU,
         run=STEREO),
    _row("stereo below imu_init before IMU initialisation: reset", "O", 14.0, "L", ["loss", "reset"],
         frame=NO_IMU, run=STEREO, changed=RESET),
    _row("window of int(fps) frames from reloc_k: inside", "O", 49.0, "R", ["coasting"],
         clocks={"reloc_k": 181.0}, run={"fps": 20.5}, changed={"t_lost": 10.0}),
    _row("window: first frame after", "O", 49.0, "O", ["tracked"], clocks={"reloc_k": 180.0},
         run={"fps": 20.5}),
    _row("a map younger than the recorded one waits for the IMU delay", "O", 20.0, "L", ["loss", "reset"],
         clocks={"map_start_t": 9.0}, run={"imu_init_delay": 1.5}, changed=RESET),
    _row("... and for the BA2 delay", "O", 14.0, "L", ["loss", "reset"], clocks={"map_start_t": 9.0},
         run={"ba2_delay": 1.5}, changed=RESET),
    _row("... until it is as old", "O", 14.0, "R", ["coasting"], clocks={"map_start_t": 8.5},
         run={"imu_init_delay": 1.5, "ba2_delay": 1.5}, changed={"t_lost": 10.0}),
    _row("RECENTLY_LOST recovers above recovery", "R", 11.0, "O", ["tracked"], clocks={"t_lost": 8.0}),
    _row("RECENTLY_LOST fails: timer kept", "R", 10.0, "R", ["coasting"], clocks={"t_lost": 8.0}),
    _row("RECENTLY_LOST at exactly 5 s is not expired", "R", 11.0, "O", ["tracked"], clocks={"t_lost": 5.0}),
    _row("RECENTLY_LOST after 5 s: LOST, no recovery tried", "R", 200.0, "L", ["loss"],
         clocks={"t_lost": 4.75}),
    _row("RECENTLY_LOST without IMU: no estimate, no recovery", "R", 200.0, "R", clocks={"t_lost": 8.0},
         frame=NO_IMU),
    _row("LOST with a reference: a frame with keypoints, matches and a pose initialises a map", "L", 0.0, "O",
         ["tracked", "new_map"], clocks=READY, frame=INIT, changed={"lost_ready": 0.0, "map_start_t": 10.0,
         "segment": 1.0}),
    _row("LOST without a reference: the frame becomes the reference", "L", 200.0, "L", frame=INIT,
         changed={"lost_ready": 1.0}),
    _row("... not with 100 keypoints or fewer", "L", 200.0, "L", frame={"init_matches": 1.0}),
    _row("LOST with a reference: too few matches drop it, the frame is no reference", "L", 200.0, "L",
         clocks=READY, frame={"init_keys": 1.0}, changed={"lost_ready": 0.0}),
    _row("... as does a frame without a recorded pose", "L", 200.0, "L", clocks=READY,
         frame=INIT | {"has_pose": 0.0}, changed={"lost_ready": 0.0}),
    _row("stereo LOST: a frame with keypoints and a pose initialises, no reference", "L", 0.0, "O",
         ["tracked", "new_map"], frame=INIT, run=STEREO, changed={"map_start_t": 10.0, "segment": 1.0}),
    _row("stereo LOST: not without the keypoints", "L", 0.0, "L", frame={"init_matches": 1.0}, run=STEREO),
    _row("a recorded reset: a new map, the window from the recorded reset", "R", 0.0, "O",
         ["tracked", "new_map", "loss"], clocks={"t_lost": 8.0},
         frame={"rec_start": 1.0, "rec_loss": 1.0, "rec_reloc": 190.0, "rec_start_t": 10.0},
         changed={"map_start_t": 10.0, "reloc_k": 190.0, "segment": 1.0}),
    _row("a recorded new map whatever the rule, no window", "O", 0.0, "O", ["tracked", "new_map", "loss"],
         frame={"rec_start": 1.0, "rec_loss": 1.0, "rec_start_t": 10.0},
         changed={"map_start_t": 10.0, "segment": 1.0}),
]  # fmt: skip


def _row_inputs(row, dtype=jnp.float64):
    state, data, constants = _machine_inputs(row.mode, row.clocks, row.frame, row.run, dtype)
    return state, jnp.asarray(row.score, dtype), data, constants


_step = jax.jit(
    lambda state, score, data, run: machine_step(HardLogic(), state, score, data, run, Thresholds(**ORB_TH))
)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("row", TABLE, ids=[row.name for row in TABLE])
def test_machine_step_follows_the_table(row, dtype, request):
    """Each row of docs/state-machine.md's table (Tracking.cc locations there): the next mode, the
    decisions, and which clocks change (all others are kept), exactly, in float32 and float64."""
    if dtype == jnp.float64:
        request.getfixturevalue("x64")  # the suite's one way of switching float64 on and back off
    state, score, data, run = _row_inputs(row, dtype)
    nxt, decision = _step(state, score, data, run)
    assert nxt.ok.dtype == dtype
    assert (float(nxt.ok), float(nxt.recently_lost), float(nxt.lost)) == MODES[row.then]
    assert {k for k in DECISIONS if float(getattr(decision, k)) == 1.0} == row.decided
    assert all(float(getattr(decision, k)) in (0.0, 1.0) for k in DECISIONS)
    for clock in CLOCKS:
        assert float(getattr(nxt, clock)) == row.changed.get(clock, float(getattr(state, clock))), clock


def test_machine_step_eager_jit_vmap_agree(x64):
    """Op by op (jax.disable_jit), under jit, and vmapped over the table's rows: identical outputs, bit
    for bit (a step is exact {0, 1} arithmetic and selections of the inputs)."""
    rows = [_row_inputs(row) for row in TABLE]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *rows)
    batched = jax.jit(jax.vmap(lambda *a: machine_step(HardLogic(), *a, Thresholds(**ORB_TH))))(*stacked)
    for i, one in enumerate(rows):
        with jax.disable_jit():
            eager = machine_step(HardLogic(), *one, Thresholds(**ORB_TH))
        for out in (_step(*one), eager):
            for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(batched), strict=True):
                assert float(a) == float(b[i]), TABLE[i].name


def test_initial_state_waits_for_the_first_map():
    """No map before the log's first recorded map start (LOST, segment -1, window from frame 0); that
    start begins map 0 and is no loss."""
    s = initial_state()
    assert (float(s.ok), float(s.recently_lost), float(s.lost)) == (0.0, 0.0, 1.0)
    assert float(s.segment) == -1 and float(s.reloc_k) == 0
    _, data, run = _machine_inputs("L", {}, {"t": 0.0, "k": 0.0, "rec_start": 1.0}, {}, jnp.float32)
    nxt, decision = machine_step(HardLogic(), s, jnp.asarray(0.0), data, run, Thresholds(**ORB_TH))
    assert float(nxt.ok) == 1.0 and float(nxt.segment) == 0 and float(decision.new_map) == 1.0
    assert float(decision.loss) == 0.0 and float(nxt.reloc_k) == 0
    assert (MODE_OK, MODE_RECENTLY_LOST, MODE_LOST) == (0, 1, 2)
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
    """The table's rows whose score does not tie a threshold (>= 1 inlier from each): as the temperature
    falls the relaxed step tends to the hard one; at T = 0.003 each sigmoid is within e^-333 of its
    limit and the clocks (times ~10 s, frame indices ~200) match to their rounding."""
    rows = [row for row in TABLE if row.score not in ORB_TH.values()]
    assert len(rows) >= 15
    inputs = jax.tree.map(lambda *x: jnp.stack(x), *[_row_inputs(row) for row in rows])
    th = Thresholds(**ORB_TH)
    hard = jax.vmap(lambda *a: machine_step(HardLogic(), *a, th))(*inputs)
    errors = []
    for temperature in (3.0, 0.3, 0.03, 0.003):
        logic = SoftLogic(jnp.asarray(temperature))
        soft = jax.vmap(lambda *a, lg=logic: machine_step(lg, *a, th))(*inputs)
        pairs = zip(jax.tree.leaves(soft), jax.tree.leaves(hard), strict=True)
        errors.append(max(float(jnp.max(jnp.abs(a - b))) for a, b in pairs))
    assert errors[0] > 0.1, errors
    assert all(b <= a for a, b in zip(errors, errors[1:], strict=False)), errors
    assert errors[-1] < 1e-12, errors


def test_soft_step_conserves_probability(x64):
    """From any mixed state (probabilities summing to 1) and any frame, the next mode flags sum to 1
    too, tracked + coasting <= 1 (the rest has no estimate), and tracked is the next OK mass."""
    rng = np.random.default_rng(1)
    n = 500
    w = rng.dirichlet(np.ones(3), n)
    arr = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    flag = lambda p: arr(rng.random(n) < p)  # noqa: E731
    state = MachineState(
        ok=arr(w[:, 0]), recently_lost=arr(w[:, 1]), lost=arr(w[:, 2]),
        t_lost=arr(rng.uniform(0, 10, n)), map_start_t=arr(rng.uniform(0, 10, n)),
        lost_ready=arr(w[:, 2] * rng.random(n)), reloc_k=arr(rng.integers(0, 200, n)),
        lost_reloc_k=arr(rng.integers(0, 200, n)),
        segment=arr(rng.uniform(0, 3, n)),
    )  # fmt: skip
    rec_start = flag(0.1)
    rec_reloc = jnp.where(flag(0.5) > 0, arr(rng.integers(150, 200, n)), -1.0)
    data = FrameData(
        t=arr(rng.uniform(10, 16, n)), k=arr(rng.integers(200, 300, n)), imu_init=flag(0.7),
        imu_ba2=flag(0.6), has_pose=flag(0.9), init_keys=flag(0.7), init_matches=flag(0.6),
        rec_start=rec_start,
        rec_loss=rec_start * flag(0.8), rec_start_t=arr(rng.uniform(0, 10, n)), rec_reloc=rec_reloc,
    )  # fmt: skip
    run = RunConstants(fps=arr(rng.choice([10.0, 20.0, 20.5], n)), imu_init_delay=arr(rng.uniform(0, 3, n)),
                       ba2_delay=arr(rng.uniform(0, 6, n)), stereo=flag(0.3))  # fmt: skip
    logic = SoftLogic(jnp.asarray(2.0))
    th = Thresholds(**ORB_TH)
    nxt, decision = jax.vmap(lambda s, sc, d, r: machine_step(logic, s, sc, d, r, th))(
        state, arr(rng.uniform(0, 60, n)), data, run
    )
    total = np.asarray(nxt.ok + nxt.recently_lost + nxt.lost)
    np.testing.assert_allclose(total, 1.0, atol=1e-14)  # a few roundings of products of [0, 1] values
    tracked, coasting = np.asarray(decision.tracked), np.asarray(decision.coasting)
    assert (tracked >= 0).all() and (coasting >= 0).all() and (tracked + coasting <= 1 + 1e-14).all()
    np.testing.assert_allclose(tracked, np.asarray(nxt.ok), atol=1e-15)
    ready, lost = np.asarray(nxt.lost_ready), np.asarray(nxt.lost)
    assert (ready >= 0).all() and (ready <= lost + 1e-15).all() and ready.max() > 0.1  # a part of LOST
    assert 0.05 < tracked.mean() < 0.95 and coasting.max() > 0.1  # mixed: not a trivial case


def test_tracking_succeeds_branch_order():
    """The success test's order (ORB-SLAM3 v1.0 Tracking::TrackLocalMap, l.3027-3064): the
    relocalisation window first, then the recovery rule in RECENTLY_LOST, then the IMU / no-IMU
    threshold; stereo sensors use the IMU threshold whatever the IMU state."""
    th = Thresholds(**ORB_TH)
    hard = HardLogic()

    def ok(score, rl, imu, reloc, stereo=0.0):
        return float(tracking_succeeds(hard, jnp.asarray(score), th, rl, imu, reloc, stereo))

    assert ok(30.0, 1.0, 1.0, 1.0) == 0.0  # window beats recovery: 30 > 10 but < 50
    assert ok(11.0, 1.0, 0.0, 0.0) == 1.0  # recovery beats the no-IMU threshold: 11 < 50
    assert ok(10.0, 1.0, 1.0, 0.0) == 0.0  # recovery is strict, then 10 < 15 fails
    assert ok(15.0, 0.0, 1.0, 0.0) == 1.0 and ok(14.0, 0.0, 1.0, 0.0) == 0.0  # fail only below
    assert ok(49.0, 0.0, 0.0, 0.0) == 0.0 and ok(50.0, 0.0, 0.0, 1.0) == 1.0
    assert ok(20.0, 0.0, 0.0, 0.0, stereo=1.0) == 1.0 and ok(14.0, 0.0, 0.0, 0.0, stereo=1.0) == 0.0
    assert ok(40.0, 0.0, 0.0, 1.0, stereo=1.0) == 0.0  # the window still applies


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
