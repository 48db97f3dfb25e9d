"""jsve.fitting._kernel and _search: the fused search kernel (designs: tests/test_designs.py; its IMU columns:
tests/test_imu.py).

Oracles: the rules' own score for the score columns, and jsve.core._objective.run_losses (replay +
alignment, itself checked against jsve.evaluation._evaluate) for the kernel, setting by setting.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import jax
import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pytest

from jsve.core._machine import SWITCH_MODELS
from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, ObjectiveConfig, run_losses, weighted_objective
from jsve.core._replay import batch_features, replay
from jsve.core._rules import Thresholds
from jsve.core._sve import feature_logs
from jsve.fitting._data import FitData
from jsve.fitting._designs import sobol
from jsve.fitting._kernel import _compiled_scan_sums, prepare, scan_sums, score_columns, search_chunk
from jsve.fitting._search import LANES_PER_CALL, call_size, lanes_per_call, search
from jsve.fitting._space import inlier_space, sve_space
from jsve.io._batching import from_runs

# ---------------------------------------------------------------------------------------------------
# The kernel
#
# Most of this module's time is XLA compiling one program per (static arguments, shape). Its tests share
# one shape of logs (six runs of 300 frames, `_study`) and call the oracle as one compiled function of the
# batch (`_run_losses`), so that a kernel or oracle compiled for one test serves the others with the same
# settings: the same computations on other data, not fewer checks.


@functools.cache
def _study(kind: str = "occlusion") -> tuple:
    """Six known-answer runs of 300 frames (read only: tests that edit a run copy its frames)."""
    return tuple(ka.make_study(kind, range(6), n_frames=300))


@functools.partial(jax.jit, static_argnames="config")
def _run_losses(batch, rules, features, config):
    """The oracle: run_losses of every setting of `rules` (leaves [S]; vmap = a loop over them). The batch
    is an argument, not a constant of the computation: one compilation per shape and config."""
    return jax.vmap(lambda rule: run_losses(batch, rule, features, config))(rules)


@functools.partial(jax.jit, static_argnames="switch_model")
def _has_estimate(batch, rules, features, switch_model):
    """replay's has_estimate of every setting of `rules` ([S, R, F])."""
    return jax.vmap(lambda rule: replay(batch, rule, features, switch_model=switch_model).has_estimate)(rules)


def test_score_columns_match_the_rules_score(x64):
    """score_columns (the kernel's score from shared feature logs) is the rule's own score, for 8 Sobol
    settings: to 1e-12 (float64; the log-domain form rounds differently, a few ulp measured)."""
    batch = from_runs(_study(), dtype=jnp.float64).batch
    f = batch_features(batch)
    space = sve_space()
    values = space.values_from_unit(jnp.asarray(sobol(8, space.dim, seed=2)))
    for i in range(8):
        rule = space.rule(values[i])
        logs = feature_logs(f.inlier_ratio, f.s_b, f.s_c)
        np.testing.assert_allclose(
            np.asarray(score_columns(rule, f.n_inliers, *logs)),
            np.asarray(rule.score(f)),
            rtol=1e-12,
            atol=1e-14,
        )


def test_objectives_that_score_the_sums_apart_share_one_compiled_scan():
    """The scan reads only the switch model and RECENTLY_LOST's time (kernel.scan_config): objectives with
    another penalty, alignment, loss or support run the scan compiled for the first, and still score
    as their own (the penalty on every failed run); another time in RECENTLY_LOST compiles its own."""
    batch = from_runs(_study(), dtype=jnp.float32).batch
    sb = prepare(batch, batch_features(batch))
    space = sve_space()
    values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
    thresholds = [space.names.index(field.name) for field in dataclasses.fields(Thresholds)]
    values[-3:, thresholds] = 2.0 * space.score_scale * 1e3  # thresholds no frame passes: runs fail
    rules = space.rule(jnp.asarray(values, jnp.float32))
    compiled = _compiled_scan_sums._cache_size
    first = search_chunk(sb, rules, ObjectiveConfig(failure_penalty=3.0))
    n_first = compiled()
    other = ObjectiveConfig(failure_penalty=5.0, align="sim3", loss="raw", support="exclude")
    again = search_chunk(sb, rules, other)
    assert compiled() == n_first
    assert np.array_equal(np.asarray(again.failed), np.asarray(first.failed))
    failed = np.asarray(again.failed)
    assert 0 < failed.mean() < 1 and np.all(np.asarray(again.loss)[failed] == 5.0)
    search_chunk(sb, rules, ObjectiveConfig(failure_penalty=3.0, time_recently_lost=1.0))
    assert compiled() > n_first


@pytest.fixture(scope="module")
def occlusion_data():
    return FitData.from_runs(ka.make_study("occlusion", range(8), n_frames=400))


@pytest.mark.parametrize(
    ("align", "dtype"),
    [("se3", jnp.float64), ("se3", jnp.float32)]
    + [
        pytest.param(a, d, marks=pytest.mark.slow)
        for a in ("sim3", "posyaw", "none")
        for d in (jnp.float64, jnp.float32)
    ],
)
def test_search_kernel_equals_replay_objective(x64, align, dtype):
    """Setting by setting, the kernel's loss is run_losses' (replay + alignment + RMSE): to 1e-12 m in
    float64; in float32 to 1e-4 relative (the moment form's error budget, ~1e-5 measured) with the same
    failed flags. Both families, 24 Sobol settings each, failing and succeeding runs, under both switch
    models."""
    batch = from_runs(_study(), dtype=dtype).batch
    f = batch_features(batch)
    sb = prepare(batch, f)
    configs = [ObjectiveConfig(align=align, failure_penalty=3.0, switch_model=m) for m in SWITCH_MODELS]
    for config, space in itertools.product(configs, (inlier_space(), sve_space())):
        values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
        thresholds = [space.names.index(field.name) for field in dataclasses.fields(Thresholds)]
        values[-3:, thresholds] = 2.0 * space.score_scale * 1e3  # thresholds no frame passes: runs fail
        rules = space.rule(jnp.asarray(values, dtype))
        got = search_chunk(sb, rules, config)
        ref = _run_losses(batch, rules, f, config)
        failed = np.asarray(ref.failed)
        assert np.array_equal(np.asarray(got.failed), failed)
        assert 0 < failed.mean() < 1  # both kinds of runs are checked
        if dtype == jnp.float64:
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=0, atol=1e-12)
        else:
            # float32 positions of a few metres carry ~2e-7 m of rounding each, in both computations
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=1e-4, atol=2e-6)
        np.testing.assert_allclose(np.asarray(got.coverage)[~failed], 1.0)
        np.testing.assert_allclose(np.asarray(got.coverage), np.asarray(ref.coverage), rtol=0, atol=1e-6)
        assert np.isnan(np.asarray(got.rmse)[failed]).all()


def test_inputs_without_imu_columns_score_the_same_and_refuse_imu_coast():
    """prepare(..., imu=False) (what FitData loads for the "orbslam3" switch model) leaves out the IMU's
    columns: the orbslam3 kernel's results are bit for bit those with them, an imu-coast search on
    them raises a clear error, and the kernel's per-frame inputs are 70 bytes in float32 (142 with the
    IMU; 230 when every column was a float32)."""
    batch = from_runs(_study(), dtype=jnp.float32).batch
    f = batch_features(batch)
    full, slim = prepare(batch, f), prepare(batch, f, imu=False)
    assert slim.imu is None and full.imu is not None
    space = sve_space()
    rules = space.rule(jnp.asarray(space.values_from_unit(sobol(16, space.dim, seed=5)), jnp.float32))
    for a, b in zip(
        jax.tree.leaves(search_chunk(full, rules)), jax.tree.leaves(search_chunk(slim, rules)), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="imu-coast.*without its columns"):
        search_chunk(slim, rules, ObjectiveConfig(switch_model="imu-coast"))

    def frame_bytes(sb):
        leaves = [x for x in jax.tree.leaves(sb) if x.ndim == 2 and x.shape == sb.t.shape]
        return sum(x.dtype.itemsize for x in leaves)

    assert (frame_bytes(slim), frame_bytes(full)) == (70, 142)


@pytest.mark.slow
def test_search_kernel_eager_equals_jit(x64):
    """Op by op (jax.disable_jit) and compiled, the kernel gives the same results (to 1e-12 m)."""
    runs = ka.make_study("occlusion", range(2), n_frames=60)
    batch = from_runs(runs, dtype=jnp.float64).batch
    sb = prepare(batch, batch_features(batch))
    space = sve_space()
    rules = space.rule(jnp.asarray(space.values_from_unit(sobol(2, space.dim, seed=3))))
    # under an enclosing jit (as a Nelder-Mead objective runs it) the kernel chooses its scan in the trace
    jitted = jax.jit(lambda sb, rules: search_chunk(sb, rules))(sb, rules)
    with jax.disable_jit():
        eager = search_chunk(sb, rules)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=0, atol=1e-12)


def test_search_chunks_and_vmap_equal_a_loop(occlusion_data):
    """search() over chunks of settings (padded) equals one kernel call per setting (vmap = loop), to
    float32 rounding."""
    data = occlusion_data
    space = inlier_space()
    values = np.asarray(space.values_from_unit(sobol(13, space.dim, seed=5)))
    a = search(
        data.parts,
        space,
        values,
        data.config,
        run_counts=data.run_counts,
        settings_per_call=4,
        progress=False,
    )
    b = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)
    np.testing.assert_array_equal(a.loss, b.loss)
    for i in (0, 6, 12):
        one = search_chunk(
            data.parts[0], space.rule(jnp.asarray(values[i : i + 1], jnp.float32)), data.config
        )
        # float32: XLA contracts multiply-adds differently for other lane counts; an RMSE near 0 m carries
        # ~3e-7 m of rounding from metre-scale positions (both sides)
        np.testing.assert_allclose(
            a.loss[i], np.asarray(one.loss[0, : data.run_counts[0]]), rtol=1e-4, atol=1e-6
        )
    w = np.arange(1, data.n_runs + 1, dtype=float)
    np.testing.assert_allclose(a.objective(w), (a.loss @ w) / w.sum())
    np.testing.assert_allclose(a.objective(np.stack([w, w])), np.stack([a.objective(w)] * 2))


def test_lanes_per_call_default_and_override_change_call_size_not_results(occlusion_data, monkeypatch):
    """The lanes a call holds: LANES_PER_CALL on CPU, JSVE_LANES_PER_CALL when set (the GPU benchmark's
    knob). The call size follows it; the search's results do not depend on it."""
    monkeypatch.delenv("JSVE_LANES_PER_CALL", raising=False)
    assert jax.default_backend() == "cpu" and lanes_per_call() == LANES_PER_CALL
    assert call_size(64, 10_000) == LANES_PER_CALL // 64
    # at most the settings rounded up to the power of 2 or multiple of 8 above them, the smaller
    assert [call_size(64, n) for n in (1, 2, 3, 10, 17, 38, 100)] == [1, 2, 4, 16, 24, 40, 104]
    assert call_size(100, 10_000) == 64  # the power of 2 at or below 8192 / 100
    data = occlusion_data
    space = inlier_space()
    values = np.asarray(space.values_from_unit(sobol(13, space.dim, seed=5)))
    default = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)
    part_runs = data.parts[0].n_runs
    monkeypatch.setenv("JSVE_LANES_PER_CALL", str(2 * part_runs))
    assert lanes_per_call() == 2 * part_runs and call_size(part_runs, 13) == 2
    narrow = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)
    # float32: other lane counts contract multiply-adds differently (as above)
    np.testing.assert_allclose(narrow.loss, default.loss, rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(narrow.failed, default.failed)
    for bad in ("0", "-5", "many", "1e5"):
        monkeypatch.setenv("JSVE_LANES_PER_CALL", bad)
        with pytest.raises(ValueError, match="JSVE_LANES_PER_CALL must be a positive integer"):
            lanes_per_call()


# ---------------------------------------------------------------------------------------------------
# Logs whose replay can leave the support


def _lossy_runs() -> list:
    """Occlusion runs (`_study`'s) whose recorded run lost its map: at the end (3 s without matches; 1 s
    with its counts, where every tracking rule needs poses the log lacks), in the middle followed by a new
    map, and two runs that never lost it."""
    runs, n_frames = _study(), 300
    return [
        ka.lose_map(runs[0], n_frames - 60),
        ka.lose_map(runs[1], 150, 200),
        ka.lose_map(runs[2], n_frames - 20, blind=False),
        runs[3],
        ka.lose_map(runs[4], n_frames - 50),
        runs[5],
    ]


@pytest.mark.parametrize("dtype", [jnp.float64, pytest.param(jnp.float32, marks=pytest.mark.slow)])
def test_search_kernel_equals_replay_objective_out_of_support(x64, dtype):
    """On logs whose recorded run lost its map, setting by setting, the kernel equals run_losses (loss
    to 1e-12 m in float64, 1e-4 relative in float32; failed, unsupported, included and coverage
    identical) under both switch models and both support policies. Both supported and unsupported
    runs occur; an unsupported run always costs the penalty, counts as failed, and is left out exactly
    under "exclude". Under "imu-coast" runs that keep tracking also coast on the IMU over frames
    without a recorded pose (in support: a prediction needs no pose), which the kernel's fixed
    alignment statistics do not cover: its corrections do (the kernel refused such runs before)."""
    batch = from_runs(_lossy_runs(), dtype=dtype).batch
    f = batch_features(batch)
    sb = prepare(batch, f)
    cases = itertools.product(SWITCH_MODELS, ("penalise", "exclude"), (inlier_space(), sve_space()))
    for model, support, space in cases:
        config = ObjectiveConfig(failure_penalty=3.0, switch_model=model, support=support)
        values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
        thresholds = [space.names.index(field.name) for field in dataclasses.fields(Thresholds)]
        values[-3:, thresholds] = 2.0 * space.score_scale * 1e3  # LOST before the recorded run: supported
        rules = space.rule(jnp.asarray(values, dtype))
        got = search_chunk(sb, rules, config)
        ref = _run_losses(batch, rules, f, config)
        unsupported = np.asarray(ref.unsupported)
        assert 0 < unsupported.mean() < 1, (model, space.kind)
        assert np.array_equal(np.asarray(got.unsupported), unsupported)
        assert np.array_equal(np.asarray(got.failed), np.asarray(ref.failed))
        assert np.array_equal(np.asarray(got.included), np.asarray(ref.included) > 0.5)
        assert np.asarray(got.failed)[unsupported].all()
        np.testing.assert_array_equal(np.asarray(got.loss)[unsupported], 3.0)
        expected_included = ~unsupported if support == "exclude" else np.ones_like(unsupported)
        assert np.array_equal(np.asarray(got.included), expected_included)
        if dtype == jnp.float64:
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=0, atol=1e-12)
        else:
            np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=1e-4, atol=2e-6)
        np.testing.assert_allclose(np.asarray(got.coverage), np.asarray(ref.coverage), rtol=0, atol=1e-6)
        if model == "imu-coast":
            estimated = np.asarray(_has_estimate(batch, rules, f, "imu-coast"))
            off_pose = (estimated & ~np.asarray(batch.has_pose)[None] & np.asarray(batch.gt_valid)[None]).any(
                -1
            )
            assert (off_pose & ~np.asarray(ref.failed)).sum() >= 10, space.kind


@pytest.mark.parametrize("switch_model", SWITCH_MODELS)
def test_search_kernel_reruns_exactly_where_lanes_miss_posed_frames(x64, switch_model):
    """On logs with a pose on every frame the kernel first scans without the alignment corrections
    (under either switch model); a log whose IMU flag drops for a few frames inside a map (RECENTLY_LOST
    without an initialised IMU keeps no estimate on posed frames, and recovers) leaves runs that never
    lost tracking with posed frames and no estimate: the kernel scans again with the corrections and
    equals run_losses to 1e-12 m."""
    runs = []
    for run in _study("counts"):
        frames = run.frames.copy()
        bad = np.flatnonzero(frames["n_inliers"].to_numpy() < 40)
        bad = bad[bad > 40]  # after the relocalisation window
        if bad.size:  # the frame after a bad episode's first: RECENTLY_LOST under the rule at K
            frames.loc[bad[0] + 1 : bad[0] + 6, ["imu_init", "imu_ba2"]] = 0
        runs.append(type(run)(meta=run.meta, frames=frames, source=run.source))
    batch = from_runs(runs, dtype=jnp.float64).batch
    f = batch_features(batch)
    sb = prepare(batch, f)
    space = inlier_space()
    values = np.array(space.values_from_unit(sobol(24, space.dim, seed=4)))
    values[0] = [39.5, 49.5, 49.5, 38.5]  # the known-answer rule: recovers from every bad episode
    rules = space.rule(jnp.asarray(values))
    # the penalty of test_search_kernel_equals_replay_objective: the same shapes and config, compiled once
    config = ObjectiveConfig(failure_penalty=3.0, switch_model=switch_model)
    assert bool(jnp.all(batch.has_pose | ~batch.valid))
    fast = scan_sums(sb, rules, config, exact=False)  # search_chunk's first scan
    got = search_chunk(sb, rules, config)
    ref = _run_losses(batch, rules, f, config)
    assert np.array_equal(np.asarray(got.failed), np.asarray(ref.failed))
    # scored runs that the first scan's fixed statistics do not cover: the rerun is needed
    inexact = (np.asarray(fast.lost) < 0.5) & (np.asarray(fast.n_off) > 0.5) & ~np.asarray(ref.failed)
    assert inexact.sum() >= 5, inexact.sum()
    np.testing.assert_allclose(np.asarray(got.loss), np.asarray(ref.loss), rtol=0, atol=1e-12)


def test_search_result_weighs_included_runs_only(x64):
    """search() scores logs the kernel once refused; SearchResult's weighted means equal
    jsve.core._objective.weighted_objective of run_losses under both policies, for any run weights; under
    "exclude" the objective is the mean over each setting's supported runs, and a setting supported by
    no run scores the penalty ("penalise"'s value: no evidence for it)."""
    runs = _lossy_runs()
    data = {
        s: FitData.from_runs(runs, ObjectiveConfig(support=s), dtype=jnp.float64)
        for s in ("penalise", "exclude")
    }
    space = inlier_space()
    values = np.array(space.values_from_unit(sobol(8, space.dim, seed=5)))
    values[0] = [0.5, 0.5, 0.5, 0.0]  # keeps tracking wherever there is a match: unsupported on lossy runs
    w = np.arange(1.0, len(runs) + 1)
    rules = space.rule(jnp.asarray(values))
    results = {}
    for support, d in data.items():
        res = search(d.parts, space, values, d.config, run_counts=d.run_counts, progress=False)
        results[support] = res
        # run_losses of every setting on every part, the real runs of each part in order: [S, R] leaves
        per_part = [_run_losses(b, rules, f, d.config) for b, f in zip(d.batches, d.features, strict=True)]
        all_losses = jax.tree.map(
            lambda *xs, c=d.run_counts: jnp.concatenate(
                [x[:, :n] for x, n in zip(xs, c, strict=True)], axis=1
            ),
            *per_part,
        )
        for i in range(len(values)):
            losses = jax.tree.map(lambda x, i=i: x[i], all_losses)
            ref = weighted_objective(losses, jnp.asarray(w))
            np.testing.assert_allclose(res.objective(w)[i], float(ref.value), rtol=1e-12)
            np.testing.assert_allclose(res.failure_rate(w)[i], float(ref.failure_rate), rtol=1e-12)
            np.testing.assert_allclose(res.unsupported_rate(w)[i], float(ref.unsupported_rate), rtol=1e-12)
            np.testing.assert_allclose(res.excluded_share(w)[i], float(ref.excluded), rtol=0, atol=1e-12)
    pen, exc = results["penalise"], results["exclude"]
    np.testing.assert_array_equal(pen.unsupported[0], [True, True, True, False, True, False])  # lossy runs
    assert np.array_equal(pen.unsupported, exc.unsupported)
    keep = ~exc.unsupported[0]
    np.testing.assert_allclose(exc.objective(w)[0], np.sum(w[keep] * exc.loss[0, keep]) / np.sum(w[keep]))
    assert exc.objective(w)[0] < pen.objective(w)[0]  # penalised, the unsupported runs cost 1 m each
    np.testing.assert_allclose(pen.excluded_share(w), 0.0)
    only_lossy = np.where(exc.unsupported[0], 1.0, 0.0)  # weights on the unsupported runs only
    np.testing.assert_allclose(exc.objective(only_lossy)[0], DEFAULT_FAILURE_PENALTY_M)
