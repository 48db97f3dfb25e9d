"""jsve.core._replay against the plain-Python oracle (tests/oracle_orbslam3.py), decision for decision.

Thousands of random logs are replayed in one batched, jitted call per rule and compared run by run
with the oracle. The logs (oracle_orbslam3.random_logs) put scores at and next to the thresholds,
with exact ties, make bad stretches outlast the 5 s timer, switch imu_init on mid-run, delay new
maps' IMU, and vary fps (fractional too). Then the must-shows of DESIGN section 5: accept-all is the
visual trajectory bit for bit, reject-all is IMU dead reckoning, and dead reckoning on noise-free
preintegration built from EuRoC V1_01's ground truth stays on the ground truth.
"""

from __future__ import annotations

import dataclasses
import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import oracle_orbslam3 as oracle
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jsve.core._batch import LogBatch
from jsve.core._machine import MachineState, SoftLogic, initial_state, machine_step
from jsve.core._replay import MODE_LOST, MODE_OK, MODE_RECENTLY_LOST, batch_features, replay, replay_run
from jsve.core._rules import InlierRule, SVERule, Thresholds, preset
from jsve.core._sve import FrameFeatures

ORBSLAM3_TH = dict(imu_init=15.0, not_init=50.0, reloc=50.0, recovery=10.0)
SVE_CODE_TH = dict(imu_init=0.06, not_init=0.2, reloc=0.2, recovery=0.04)
# Recovery above the IMU threshold and a reloc threshold below not_init: orders the presets never
# use, so that every branch of the success test decides some frames.
SHUFFLED_TH = dict(imu_init=15.0, not_init=49.0, reloc=16.0, recovery=50.0)
ACCEPT_ALL_TH = dict(imu_init=-math.inf, not_init=-math.inf, reloc=-math.inf, recovery=math.inf)
REJECT_ALL_TH = dict(imu_init=math.inf, not_init=math.inf, reloc=math.inf, recovery=math.inf)

N_INLIER_LOGS = 2000
N_SVE_LOGS = 400
N_POSE_LOGS = 300
N_FLOAT32_LOGS = 1000

replay_jit = eqx.filter_jit(replay)


def to_batch(logs: dict, dtype, with_bins: bool) -> LogBatch:
    """LogBatch from oracle_orbslam3.random_logs arrays (cast to `dtype` like jsve.core._batch does)."""
    R, F = logs["t"].shape
    f = lambda key: jnp.asarray(logs[key], dtype)  # noqa: E731
    bins = logs["bins"] if with_bins else np.zeros((R, 1, 64))
    return LogBatch(
        t=f("t"), valid=jnp.asarray(logs["valid"]), state=jnp.zeros((R, F), jnp.int8),
        imu_init=jnp.asarray(logs["imu_init"]), n_extracted=jnp.asarray(logs["n_extracted"], jnp.int32),
        n_inliers=jnp.asarray(logs["n_inliers"], jnp.int32),
        n_frustum=jnp.asarray(logs["n_frustum"], jnp.int32),
        bins=jnp.asarray(bins, jnp.uint16), vis_p=f("vis_p"), vis_q=f("vis_q"), vis_v=f("vis_v"),
        imu_dt=f("imu_dt"), imu_dp=f("imu_dp"), imu_dv=f("imu_dv"), imu_dq=f("imu_dq"),
        gt_p=jnp.zeros((R, F, 3), dtype), gt_q=jnp.zeros((R, F, 4), dtype).at[..., 0].set(1.0),
        gt_valid=jnp.zeros((R, F), bool), fps=f("fps"), gravity=f("gravity"),
        imu_init_delay=f("imu_init_delay"), run_index=jnp.arange(R, dtype=jnp.int32),
    )  # fmt: skip


def inlier_features(batch: LogBatch) -> FrameFeatures:
    """Features for an InlierRule without the [R, F, 64] S_b temporaries (it reads n_inliers only)."""
    zeros = jnp.zeros(batch.t.shape, batch.t.dtype)
    # Every other metric zero, whatever FrameFeatures holds (its fields are the one list of metrics).
    others = {name: zeros for name in FrameFeatures.__dataclass_fields__}
    return FrameFeatures(**others | {"n_inliers": batch.n_inliers.astype(batch.t.dtype)})


def result_numpy(res) -> dict:
    keys = ("accepted", "predicted", "has_estimate", "mode", "segment", "lost_any", "position", "quaternion",
            "velocity")  # fmt: skip
    return {k: np.asarray(getattr(res, k)) for k in keys}


def oracle_runs(logs, scores, thresholds, runs, *, real=float, poses=False):
    out = []
    for i in runs:
        n = int(logs["length"][i])
        pose_arrays = None
        if poses:
            keys = ("vis_p", "vis_q", "vis_v", "imu_dt", "imu_dp", "imu_dv", "imu_dq")
            pose_arrays = {k: logs[k][i, :n] for k in keys}
            pose_arrays["gravity"] = logs["gravity"][i]
        args = (
            scores[i, :n],
            logs["t"][i, :n],
            logs["imu_init"][i, :n],
            logs["fps"][i],
            logs["imu_init_delay"][i],
        )
        out.append(oracle.replay_run(*args, thresholds, poses=pose_arrays, real=real))
    return out


def decision_mismatches(res: dict, logs: dict, runs, expected) -> list[str]:
    """Every run whose decisions differ from the oracle's, with the first differing frame."""
    bad = []
    for i, ref in zip(runs, expected, strict=True):
        n = int(logs["length"][i])
        got = {key: res[key][i, :n] for key in ("accepted", "predicted", "has_estimate", "mode", "segment")}
        for key, value in got.items():
            want = getattr(ref, key)
            if not np.array_equal(value, want):
                k = int(np.flatnonzero(value != want)[0])
                bad.append(f"run {i} frame {k}: {key} replay={value[k]} oracle={want[k]} "
                           f"(oracle modes {ref.mode[max(k - 3, 0) : k + 2]})")  # fmt: skip
                break
        else:
            if bool(res["lost_any"][i]) != ref.lost_any:
                bad.append(f"run {i}: lost_any replay={res['lost_any'][i]} oracle={ref.lost_any}")
            pad = slice(n, None)
            if (
                (res["mode"][i, pad] != -1).any()
                or res["has_estimate"][i, pad].any()
                or res["accepted"][i, pad].any()
            ):
                bad.append(f"run {i}: padding frames carry decisions")
    return bad


def event_counts(expected) -> dict:
    """How often the oracle saw each transition: evidence that the random logs exercise the machine."""
    counts = dict(ok_to_rl=0, rl_to_ok=0, expired=0, reset=0, new_map=0)
    for ref in expected:
        prev = np.concatenate([[oracle.OK], ref.mode[:-1]])
        counts["ok_to_rl"] += int(np.sum((prev == oracle.OK) & (ref.mode == oracle.RECENTLY_LOST)))
        counts["rl_to_ok"] += int(np.sum((prev == oracle.RECENTLY_LOST) & (ref.mode == oracle.OK)))
        counts["expired"] += int(np.sum((prev == oracle.RECENTLY_LOST) & (ref.mode == oracle.LOST)))
        counts["reset"] += int(np.sum((prev == oracle.OK) & (ref.mode == oracle.LOST)))
        counts["new_map"] += int(np.sum(np.diff(ref.segment) > 0))
    return counts


@pytest.fixture(scope="module")
def inlier_case():
    """2,000 random logs replayed in float64 with the orbslam3 preset and a shuffled-threshold rule."""
    logs = oracle.random_logs(seed=20240611, n_runs=N_INLIER_LOGS, kind="inliers")
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        batch = to_batch(logs, jnp.float64, with_bins=False)
        features = inlier_features(batch)
        results = {}
        for name, th in (("orbslam3", ORBSLAM3_TH), ("shuffled", SHUFFLED_TH), ("accept_all", ACCEPT_ALL_TH)):
            rule = preset("orbslam3") if name == "orbslam3" else InlierRule(Thresholds(**th))
            assert rule.thresholds.imu_init.dtype == jnp.float64
            results[name] = result_numpy(replay_jit(batch, rule, features))
        results["vis"] = {k: np.asarray(getattr(batch, k)) for k in ("vis_p", "vis_q", "vis_v")}
    finally:
        jax.config.update("jax_enable_x64", previous)
    return logs, results


@pytest.fixture(scope="module")
def sve_case():
    """400 random SVE logs replayed in float64 with sve-option2 and a rule whose thresholds are
    scores that recur in the logs (exact ties)."""
    logs = oracle.random_logs(seed=7, n_runs=N_SVE_LOGS, kind="sve")
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        batch = to_batch(logs, jnp.float64, with_bins=True)
        rule = preset("sve-option2")
        features = batch_features(batch)
        scores = np.asarray(rule.score(features))
        # Thresholds at the Option 2 scores of palette tuples, which many edge frames reuse.
        values, counts = np.unique(
            scores[logs["valid"] & (scores > 0.02) & (scores < 0.3)], return_counts=True
        )
        common = np.sort(values[np.argsort(counts)[-4:]])
        tie_th = dict(imu_init=common[1], not_init=common[3], reloc=common[2], recovery=common[0])
        # Exact ties need the very scores the replay compares. Option 2 evaluated inside jit differs
        # from the eager evaluation by an ulp on about a third of the frames (XLA fuses exp/log), so
        # the tie rule is handed the scores themselves: an InlierRule scores features.n_inliers.
        as_scores = dataclasses.replace(features, n_inliers=jnp.asarray(scores))
        results = {
            "option2": result_numpy(replay_jit(batch, rule)),  # the default path computes the features
            "ties": result_numpy(replay_jit(batch, InlierRule(Thresholds(**tie_th)), as_scores)),
        }
    finally:
        jax.config.update("jax_enable_x64", previous)
    return logs, scores, tie_th, results


@pytest.mark.parametrize("name", ["orbslam3", "shuffled"])
def test_inlier_rules_match_oracle(inlier_case, name):
    logs, results = inlier_case
    th = ORBSLAM3_TH if name == "orbslam3" else SHUFFLED_TH
    runs = range(N_INLIER_LOGS)
    expected = oracle_runs(logs, logs["n_inliers"].astype(float), th, runs)
    bad = decision_mismatches(results[name], logs, runs, expected)
    assert not bad, f"{len(bad)} of {N_INLIER_LOGS} runs differ from the oracle:\n" + "\n".join(bad[:10])
    # The comparison only means something if the logs drive the machine through every transition,
    # with exact ties at the thresholds.
    counts = event_counts(expected)
    assert min(counts.values()) >= 100, counts
    ties = np.isin(logs["n_inliers"][logs["valid"]], list(th.values())).sum()
    assert ties > 10_000


def test_sve_rules_match_oracle(sve_case):
    logs, scores, tie_th, results = sve_case
    runs = range(N_SVE_LOGS)
    for name, th in (("option2", SVE_CODE_TH), ("ties", tie_th)):
        expected = oracle_runs(logs, scores, th, runs)
        bad = decision_mismatches(results[name], logs, runs, expected)
        assert not bad, f"{name}: {len(bad)} of {N_SVE_LOGS} runs differ:\n" + "\n".join(bad[:10])
        counts = event_counts(expected)
        assert min(counts.values()) >= 20, (name, counts)
    ties = np.isin(scores[logs["valid"]], list(tie_th.values())).sum()
    assert ties > 1_000


def test_sve_scores_equal_option2_by_hand(sve_case):
    """The scores the replay compares are Option 2 written out by hand (1e-12: float64 rounding of
    a sqrt of products of ratios, about 10 ulp; the geometric mean is evaluated as exp(mean log))."""
    logs, scores, _, _ = sve_case
    by_hand = oracle.option2_numpy(logs["n_extracted"], logs["n_inliers"], logs["n_frustum"], logs["bins"])
    valid = logs["valid"]
    np.testing.assert_allclose(scores[valid], by_hand[valid], rtol=0, atol=1e-12)
    # The generator's clustering worked: many scores within 0.01 of each threshold.
    for edge in (0.04, 0.06, 0.2):
        assert np.sum(np.abs(by_hand[valid] - edge) < 0.01) > 1_000


def test_poses_match_oracle(inlier_case):
    """Poses to 1e-9 (float64): the oracle integrates the same PredictStateIMU with its own
    quaternion algebra, so only rounding differs; over at most 5 s (100 frames at 20 fps) of dead
    reckoning on metre-scale states that is ~1e-13, and 1e-9 would still catch any term of the
    prediction being wrong (the smallest, 0.5 g dt^2 at 30 fps, is 5e-3 m)."""
    logs, results = inlier_case
    res = results["orbslam3"]
    runs = range(N_POSE_LOGS)
    expected = oracle_runs(logs, logs["n_inliers"].astype(float), ORBSLAM3_TH, runs, poses=True)
    n_predicted = 0
    for i, ref in zip(runs, expected, strict=True):
        n = int(logs["length"][i])
        est = ref.has_estimate
        n_predicted += int(ref.predicted.sum())
        for key, value in (
            ("position", ref.position),
            ("quaternion", ref.quaternion),
            ("velocity", ref.velocity),
        ):
            np.testing.assert_allclose(
                res[key][i, :n][est], value[est], rtol=0, atol=1e-9, err_msg=f"run {i} {key}"
            )
    assert n_predicted > 5_000  # the IMU prediction really was exercised


def test_float32_replay_matches_float32_oracle():
    """The default dtype: the oracle mirrors float32 arithmetic (np.float32 scalars) on the same
    float32 times, scores and thresholds, so decisions must agree exactly."""
    logs = oracle.random_logs(seed=99, n_runs=N_FLOAT32_LOGS, kind="inliers")
    assert not jax.config.jax_enable_x64
    batch = to_batch(logs, jnp.float32, with_bins=False)
    res = result_numpy(replay_jit(batch, preset("orbslam3"), inlier_features(batch)))
    accept_all = result_numpy(
        replay_jit(batch, InlierRule(Thresholds(**ACCEPT_ALL_TH)), inlier_features(batch))
    )
    assert_visual_bitwise(
        accept_all, logs["valid"], {k: np.asarray(getattr(batch, k)) for k in ("vis_p", "vis_q", "vis_v")}
    )
    logs32 = dict(logs, t=np.asarray(batch.t), imu_init_delay=np.asarray(batch.imu_init_delay),
                  fps=np.asarray(batch.fps))  # fmt: skip
    runs = range(N_FLOAT32_LOGS)
    expected = oracle_runs(logs32, logs["n_inliers"].astype(np.float32), ORBSLAM3_TH, runs, real=np.float32)
    bad = decision_mismatches(res, logs, runs, expected)
    assert not bad, "\n".join(bad[:10])


def test_float32_sve_replay_matches_float32_oracle():
    logs = oracle.random_logs(seed=5, n_runs=200, kind="sve")
    batch = to_batch(logs, jnp.float32, with_bins=True)
    rule = preset("sve-option2")
    scores = np.asarray(eqx.filter_jit(lambda r, b: r.score(batch_features(b)))(rule, batch))
    assert scores.dtype == np.float32
    res = result_numpy(replay_jit(batch, rule))
    logs32 = dict(logs, t=np.asarray(batch.t), imu_init_delay=np.asarray(batch.imu_init_delay),
                  fps=np.asarray(batch.fps))  # fmt: skip
    th32 = {k: np.float32(v) for k, v in SVE_CODE_TH.items()}
    expected = oracle_runs(logs32, scores, th32, range(200), real=np.float32)
    bad = decision_mismatches(res, logs, range(200), expected)
    assert not bad, "\n".join(bad[:10])


# ------------------------------------------------------------------------------------------------
# Hypothesis: short logs on a quarter-second clock, so that t - t_lost hits 5.0 exactly.

SCORE_VALUES = (0, 5, 9, 10, 11, 14, 15, 16, 30, 49, 50, 51, 200)
TH_VALUES = (-math.inf, 0.0, 10.0, 15.0, 16.0, 49.5, 50.0, math.inf)
F_SHORT = 64


@st.composite
def short_logs(draw):
    n = draw(st.integers(1, F_SHORT))
    steps_ms = draw(st.lists(st.sampled_from([250, 500, 1000, 1250, 2500]), min_size=n - 1, max_size=n - 1))
    scores = draw(st.lists(st.sampled_from(SCORE_VALUES), min_size=n, max_size=n))
    if draw(st.booleans()):
        imu = draw(st.lists(st.booleans(), min_size=n, max_size=n))
    else:
        k_init = draw(st.integers(0, n))
        imu = [k >= k_init for k in range(n)]
    if draw(st.booleans()):
        th = dict(ORBSLAM3_TH)
    else:
        th = {k: draw(st.sampled_from(TH_VALUES)) for k in ("imu_init", "not_init", "reloc", "recovery")}
    return dict(
        t=np.concatenate([[0], np.cumsum(steps_ms, dtype=np.int64)]) / 1000.0,  # quarter seconds: exact
        scores=np.asarray(scores, float), imu=np.asarray(imu, bool), th=th,
        fps=draw(st.sampled_from([1.0, 2.0, 3.0, 4.5, 20.0])),
        delay=draw(st.sampled_from([0.0, 0.5, 1.25, 3.0, math.inf])),
    )  # fmt: skip


def single_run_batch(t, scores, imu, fps, delay, dtype=jnp.float64, n_frames=None, poses=None):
    """A one-run LogBatch (padded to n_frames) with the given decisions' inputs."""
    n = len(t)
    F = n_frames or n

    def pad(x, fill=0.0):
        return np.concatenate([np.asarray(x, float), np.full((F - n,) + np.shape(x)[1:], fill)])

    logs = dict(
        length=np.array([n]), t=pad(t, t[-1])[None], valid=(np.arange(F) < n)[None],
        imu_init=pad(imu).astype(bool)[None], n_extracted=np.full((1, F), 1000),
        n_inliers=pad(scores)[None].astype(np.int64), n_frustum=np.full((1, F), 500),
        fps=np.array([fps]), gravity=np.array([[0.0, 0.0, -9.81]]), imu_init_delay=np.array([delay]),
    )  # fmt: skip
    rng = np.random.default_rng(n)
    logs.update(vis_p=rng.normal(size=(1, F, 3)), vis_v=rng.normal(size=(1, F, 3)),
                vis_q=oracle.random_unit_quaternions(rng, (1, F)), imu_dt=np.full((1, F), 0.05),
                imu_dp=rng.normal(scale=0.05, size=(1, F, 3)), imu_dv=rng.normal(scale=0.5, size=(1, F, 3)),
                imu_dq=oracle.random_unit_quaternions(rng, (1, F), scale=0.05))  # fmt: skip
    if poses is not None:
        logs.update(poses)
    return logs, to_batch(logs, dtype, with_bins=False)


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(case=short_logs())
def test_hypothesis_short_logs_match_oracle(case):
    # float32 on purpose: every time (quarter seconds), score and threshold here is exact in
    # float32, so the float64 oracle must agree with the default-dtype replay.
    logs, batch = single_run_batch(case["t"], case["scores"], case["imu"], case["fps"], case["delay"],
                                   dtype=jnp.float32, n_frames=F_SHORT)  # fmt: skip
    assert batch.t.dtype == jnp.float32 and np.array_equal(np.asarray(batch.t), logs["t"])
    res = result_numpy(replay_jit(batch, InlierRule(Thresholds(**case["th"])), inlier_features(batch)))
    expected = oracle_runs(logs, logs["n_inliers"].astype(float), case["th"], [0])
    bad = decision_mismatches(res, logs, [0], expected)
    assert not bad, bad


# ------------------------------------------------------------------------------------------------
# Targeted cases (float64, orbslam3 preset unless stated). Letters: O ok, R recently lost, L lost.


F_TARGETED = 160


def run_modes(scores, *, fps=20.0, dt=0.05, imu=None, delay=0.0, th=None, t=None):
    """Replay one run; returns (mode letters, accepted, predicted, segment) and checks the oracle."""
    n = len(scores)
    if t is None:  # from int64 nanoseconds, as jsve.core._batch does: k * 50 ms and k / 16 s are exact
        t = (np.arange(n, dtype=np.int64) * round(dt * 1e9)) / 1e9
    imu = np.ones(n, bool) if imu is None else np.asarray(imu, bool)
    th = ORBSLAM3_TH if th is None else th
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        logs, batch = single_run_batch(t, scores, imu, fps, delay, n_frames=F_TARGETED)  # one compilation
        res = result_numpy(replay_jit(batch, InlierRule(Thresholds(**th)), inlier_features(batch)))
    finally:
        jax.config.update("jax_enable_x64", previous)
    expected = oracle_runs(logs, logs["n_inliers"].astype(float), th, [0])
    assert not decision_mismatches(res, logs, [0], expected)
    letters = "".join("ORL"[m] for m in res["mode"][0, :n])
    return letters, res["accepted"][0, :n], res["predicted"][0, :n], res["segment"][0, :n]


def test_mode_constants_match_oracle():
    assert (MODE_OK, MODE_RECENTLY_LOST, MODE_LOST) == (oracle.OK, oracle.RECENTLY_LOST, oracle.LOST)


def test_timer_expires_strictly_after_five_seconds():
    # fps 16: frame times k / 16 are exact in binary, so t - t_lost hits 5.0 exactly at 80 frames.
    scores = [100] * 20 + [5] * 120
    letters, accepted, predicted, _ = run_modes(scores, fps=16, dt=1 / 16)
    assert letters[:20] == "O" * 20
    # Frame 20 fails (t_lost = 1.25); frames 21..100 predicted; frame 100 is t - t_lost = 5.0
    # exactly: not yet expired (strict >); frame 101 expires without a recovery attempt.
    assert letters[20:101] == "R" * 81
    assert predicted[20:101].all() and not accepted[20:101].any()
    assert letters[101:] == "L" * 39
    assert not predicted[101:].any()


def test_timer_not_restarted_in_recently_lost_and_no_recovery_on_expiry():
    # In RECENTLY_LOST, failing frames never restart the timer; the expiry frame itself is not
    # tried even though its score (200) would pass.
    scores = [100] * 20 + [5] * 81 + [200] * 5
    letters, accepted, _, segment = run_modes(scores, fps=16, dt=1 / 16)
    assert letters[20:101] == "R" * 81
    assert letters[101] == "L" and not accepted[101]
    # The frame after expiry passes the strict test: a new map (segment 1) starts there.
    assert letters[102:] == "O" * 4 and accepted[102] and segment[102] == 1 and segment[101] == 0
    # A recovery resets nothing but the mode; the next failure sets a new t_lost.
    scores = [100] * 20 + [5] * 40 + [12] + [5] * 90
    letters, *_ = run_modes(scores, fps=16, dt=1 / 16)
    assert letters[20:60] == "R" * 40 and letters[60] == "O"
    assert letters[61:142] == "R" * 81 and letters[142:] == "L" * 9  # t_lost = 61/16, expiry at 142


def test_relocalisation_window():
    # fps 20: frames 0..19 need >= 50 (reloc); frame 19 fails with 49, frame 20 passes with 49.
    letters, *_ = run_modes([100] * 19 + [49] + [100] * 5)
    assert letters[19] == "R"
    letters, *_ = run_modes([100] * 20 + [49] + [100] * 5)
    assert letters[20] == "O"
    # Fractional fps truncates like ORB-SLAM3's int mMaxFrames: 20.9 -> 20 frames.
    letters, *_ = run_modes([100] * 20 + [49] + [100] * 5, fps=20.9)
    assert letters[20] == "O"
    # In RECENTLY_LOST the window check comes before the recovery rule: 30 > 10 still fails.
    letters, *_ = run_modes([100] * 5 + [5] + [30] * 3 + [100] * 3)
    assert letters[5:9] == "RRRR" and letters[9] == "O"
    # A new map opens a new window: after the new map at frame k, frames k..k+19 need >= 50.
    scores = [100] * 25 + [0] * 5 + [60] + [49] * 3
    letters, _, _, segment = run_modes(scores, imu=[True] * 25 + [False] * 9)
    assert letters[25] == "L" and letters[30] == "O" and segment[30] == 1
    assert letters[31] == "L"  # 49 < 50 inside the new map's window, and its IMU is not usable


def test_recovery_rule():
    # RECENTLY_LOST -> OK needs score > recovery (strict): 10 stays, 11 recovers.
    letters, accepted, predicted, _ = run_modes([100] * 25 + [5, 10, 11])
    assert letters[25:] == "RRO"
    assert predicted[25:27].all() and accepted[27]
    # Tie at imu_init passes (fail only below): 15 in OK stays OK.
    letters, *_ = run_modes([100] * 25 + [15, 14])
    assert letters[25:] == "OR"
    # Recovery above imu_init: in RECENTLY_LOST the main test still applies (17 >= 15 succeeds).
    th = dict(ORBSLAM3_TH, recovery=20.0)
    letters, *_ = run_modes([100] * 25 + [5, 17], th=th)
    assert letters[25:] == "RO"


def test_reset_before_imu_initialisation():
    # No IMU: a failure resets the map (LOST, no estimate), and only the strict test restarts it.
    letters, accepted, predicted, segment = run_modes(
        [100] * 25 + [40] + [49] * 3 + [50] * 3, imu=[False] * 32
    )
    assert letters[25:] == "LLLLOOO"
    assert not (accepted[25:29] | predicted[25:29]).any()
    assert segment[28] == 0 and segment[29] == 1
    # imu_init logged from frame 0 with imu_init_delay = 1 s: the IMU is usable from t = 1.0
    # (frame 20, >=); a failure before that resets, one from then on is RECENTLY_LOST.
    letters, _, predicted, _ = run_modes([100] * 19 + [14], delay=1.0)
    assert letters[19] == "L" and not predicted.any()
    letters, _, predicted, _ = run_modes([100] * 20 + [14], delay=1.0)
    assert letters[20] == "R" and predicted[20]
    # Logged imu_init = 0 on the frame itself: not usable, whatever the delay.
    letters, *_ = run_modes([100] * 30 + [14], imu=[True] * 30 + [False], delay=0.0)
    assert letters[30] == "L"


def test_new_map_waits_for_the_imu():
    # Lost at frame 5 (t = 0.25 < delay 2 s), new map at frame 10 (t = 0.5): its IMU is usable
    # from t = 2.5, i.e. frame 50. A failure at frame 49 resets again; one at frame 50 does not.
    base = [100] * 5 + [0] * 5 + [100] * 39
    letters, _, predicted, segment = run_modes(base + [30], delay=2.0)
    assert letters[5:10] == "LLLLL" and letters[10] == "O" and segment[10] == 1
    assert letters[49] == "L" and not predicted.any()
    letters, _, predicted, segment = run_modes(base + [100, 14], delay=2.0)
    assert letters[50] == "R" and predicted[50] and segment[50] == 1


# ------------------------------------------------------------------------------------------------
# Must-shows: accept-all, reject-all, dead reckoning on EuRoC ground truth.


def assert_visual_bitwise(res, valid, vis):
    """Accept-all: every frame accepted, one segment, and the visual trajectory bit for bit (the
    blend a * visual + (1 - a) * prediction with a = 1 must not touch a single bit)."""
    assert res["accepted"][valid].all() and not res["predicted"].any()
    assert (res["segment"][valid] == 0).all() and not res["lost_any"].any()
    for key, name in (("position", "vis_p"), ("quaternion", "vis_q"), ("velocity", "vis_v")):
        assert np.array_equal(res[key][valid], vis[name][valid]), key


def test_accept_all_returns_visual_trajectory_bitwise(inlier_case):
    logs, results = inlier_case
    assert_visual_bitwise(results["accept_all"], logs["valid"], results["vis"])
    # (float32: checked in test_float32_replay_matches_float32_oracle on the same compiled replay)


def reject_all(batch):
    """Thresholds at +inf, recovery at +inf, no timer: RECENTLY_LOST from frame 0 for ever."""
    rule = InlierRule(Thresholds(**REJECT_ALL_TH))
    return result_numpy(replay_jit(batch, rule, inlier_features(batch), time_recently_lost=math.inf))


def test_reject_all_is_dead_reckoning(x64):
    logs = oracle.random_logs(seed=4, n_runs=40, kind="inliers")
    logs["imu_init"][:] = True
    logs["imu_init_delay"][:] = 0.0
    batch = to_batch(logs, jnp.float64, with_bins=False)
    res = reject_all(batch)
    valid = logs["valid"]
    assert res["predicted"][valid].all() and not res["accepted"].any()
    assert (res["mode"][valid] == MODE_RECENTLY_LOST).all()
    for i in range(40):
        n = int(logs["length"][i])
        P, V, Q = oracle.dead_reckon(logs["vis_p"][i, 0], logs["vis_v"][i, 0], logs["vis_q"][i, 0],
                                     *(logs[k][i, :n] for k in ("imu_dt", "imu_dp", "imu_dv", "imu_dq")),
                                     logs["gravity"][i])  # fmt: skip
        # 1e-9 m: rounding only (float64), over up to 400 steps of ~1 m/s random motion (~1e-12).
        np.testing.assert_allclose(res["position"][i, :n], P, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res["velocity"][i, :n], V, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res["quaternion"][i, :n], Q, rtol=0, atol=1e-9)


def _read_t_bs(path) -> np.ndarray:
    text = path.read_text()
    block = text[text.index("T_BS:") :]
    data = block[block.index("[") + 1 : block.index("]")]
    return np.array([float(x) for x in re.split(r"[,\s]+", data.strip()) if x]).reshape(4, 4)


def euroc_body_states(shared_data):
    """V1_01 ground-truth body states: positions, wxyz and finite-difference velocities (world)."""
    rows = (shared_data / "euroc/groundtruth_left_cam/V101_GT.txt").read_text().splitlines()[1:]
    stamps = np.array([int(r.split(",")[0].split(".")[0]) for r in rows], np.int64)
    values = np.array([[float(x) for x in r.split(",")[1:]] for r in rows])
    t = (stamps - stamps[0]) / 1e9
    p_wc, q_wc = values[:, :3], values[:, 3:] / np.linalg.norm(values[:, 3:], axis=1, keepdims=True)
    T_bs = _read_t_bs(shared_data / "euroc/V1_01_first95/mav0/cam0/sensor.yaml")
    u, _, vt = np.linalg.svd(T_bs[:3, :3])  # orthonormalise the 12-digit calibration
    R_bs = u @ vt
    q_bs = np.roll(Rotation.from_matrix(R_bs).as_quat(), 1)  # xyzw -> wxyz (scipy: not jsve's algebra)
    # T_BS is body-from-camera: T_wc = T_wb T_bs, so T_wb = T_wc T_bs^-1.
    q_wb = np.array([oracle.qmul(q, oracle.qconj(q_bs)) for q in q_wc])
    p_wb = p_wc - np.array([oracle.qrotate(q, T_bs[:3, 3]) for q in q_wb])
    v_wb = np.gradient(p_wb, t, axis=0)  # second-order finite differences on the 20 Hz samples
    return t, p_wb, q_wb, v_wb


def test_dead_reckoning_on_euroc_ground_truth(shared_data, x64):
    """Noise-free preintegration from consecutive ground-truth states (the prediction equations
    inverted exactly: dR = R1^T R2, dV = R1^T (v2 - v1 - g dt), dP = R1^T (p2 - p1 - v1 dt - g dt^2/2))
    makes reject-all dead reckoning reproduce the whole 143 s of V1_01 up to rounding. Bound: 1e-6 m.
    Rounding in float64 is ~1e-16 relative per step; an orientation error of k * 1e-16 rad after k
    steps feeds |dV| ~ 0.5 m/s, so velocity and position errors stay below ~1e-9 over 2,871 frames;
    any model error (a sign of g, the frame of dP, the 0.5 dt^2) is metres."""
    t, p, q, v = euroc_body_states(shared_data)
    n = len(t)
    g = np.array([0.0, 0.0, -9.81])
    dt = np.concatenate([[0.0], np.diff(t)])
    dq = np.array([[1.0, 0, 0, 0]] + [oracle.qmul(oracle.qconj(q[k]), q[k + 1]) for k in range(n - 1)])
    dv = np.zeros((n, 3))
    dp = np.zeros((n, 3))
    for k in range(n - 1):
        back = oracle.qconj(q[k])
        dv[k + 1] = oracle.qrotate(back, v[k + 1] - v[k] - g * dt[k + 1])
        dp[k + 1] = oracle.qrotate(back, p[k + 1] - p[k] - v[k] * dt[k + 1] - 0.5 * g * dt[k + 1] ** 2)
    # The visual estimate is ground truth at frame 0 and far off elsewhere: it must not be used.
    vis_p = p + 100.0
    vis_p[0] = p[0]
    poses = dict(vis_p=vis_p[None], vis_q=q[None], vis_v=v[None], imu_dt=dt[None], imu_dp=dp[None],
                 imu_dv=dv[None], imu_dq=dq[None], gravity=g[None])  # fmt: skip
    logs, batch = single_run_batch(t, np.zeros(n), np.ones(n, bool), 20.0, 0.0, poses=poses)
    res = reject_all(batch)
    assert res["predicted"][0].all()
    err_p = np.abs(res["position"][0] - p).max()
    err_v = np.abs(res["velocity"][0] - v).max()
    # q and -q are one rotation; the chain keeps the sign of the ground truth's product anyway.
    err_q = np.abs(np.abs(np.sum(res["quaternion"][0] * q, axis=1)) - 1).max()
    assert err_p < 1e-6, err_p
    assert err_v < 1e-6, err_v
    assert err_q < 1e-12, err_q
    # The data are a real trajectory (not a trivial one): it moves metres and turns.
    assert np.ptp(p, axis=0).max() > 2.0 and np.abs(dv).max() > 0.3


# ------------------------------------------------------------------------------------------------
# replay_run eager / jit / vmap, and the relaxed (SoftLogic) replay.


def _run_args(batch: LogBatch, i: int, score):
    return (score[i], batch.t[i], batch.valid[i], batch.imu_init[i], batch.vis_p[i], batch.vis_q[i],
            batch.vis_v[i], batch.imu_dt[i], batch.imu_dp[i], batch.imu_dv[i], batch.imu_dq[i],
            batch.gravity[i], batch.fps[i], batch.imu_init_delay[i])  # fmt: skip


def test_replay_run_eager_jit_vmap_agree(x64):
    """Called eagerly, under jit, and vmapped over runs, replay_run gives the same decisions
    exactly and the same poses to 1e-12 (float64; differently fused arithmetic may round
    differently, a few ulp of metre-scale values after at most 5 s of prediction)."""
    logs = oracle.random_logs(seed=11, n_runs=4, n_frames=160, min_frames=120)
    batch = to_batch(logs, jnp.float64, with_bins=False)
    score = batch.n_inliers.astype(jnp.float64)
    th = Thresholds(**ORBSLAM3_TH)

    def run(*args):
        return replay_run(*args, th)

    def check(reference, other, key, i=None):
        a, b = np.asarray(reference[key]), np.asarray(other[key] if i is None else other[key][i])
        if key in ("position", "quaternion", "velocity"):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12, err_msg=key)
        else:  # decisions, modes, segments: exact
            assert np.array_equal(a, b), key

    stacked = [jnp.stack(x) for x in zip(*[_run_args(batch, i, score) for i in range(4)], strict=True)]
    batched = jax.jit(jax.vmap(run))(*stacked)
    for i in range(4):
        jitted = jax.jit(run)(*_run_args(batch, i, score))
        assert set(jitted) == set(batched)
        for key in jitted:
            check(jitted, batched, key, i)
    # Called without jit (op by op at the top level; machine_step itself is checked op by op,
    # under jax.disable_jit, in test_rules.py).
    jitted = jax.jit(run)(*_run_args(batch, 0, score))
    eager = run(*_run_args(batch, 0, score))
    assert set(eager) == set(jitted)
    for key in jitted:
        check(jitted, eager, key)
    assert not np.asarray(jitted["accepted"]).all()  # the run is not trivially all-OK


# Half-integer thresholds: integer inlier scores are never tied, so the relaxation must converge.
OFF_TIE_TH = dict(imu_init=15.5, not_init=49.5, reloc=49.5, recovery=10.5)


def test_soft_logic_converges_to_hard_logic(x64):
    logs = oracle.random_logs(seed=12, n_runs=100, n_frames=300)
    batch = to_batch(logs, jnp.float64, with_bins=False)
    features = inlier_features(batch)
    rule = InlierRule(Thresholds(**OFF_TIE_TH))
    hard = result_numpy(replay_jit(batch, rule, features))
    valid, est = logs["valid"], hard["has_estimate"]
    flag_err, pos_err = [], []
    for temperature in (1.0, 0.1, 0.05, 0.03, 0.02, 0.01):
        soft = result_numpy(replay_jit(batch, rule, features, logic=SoftLogic(jnp.asarray(temperature))))
        keys = ("accepted", "predicted", "has_estimate")
        flag_err.append(max(np.abs(soft[k][valid] - hard[k][valid]).max() for k in keys))
        pos_err.append(np.abs(soft["position"][est] - hard["position"][est]).max())
    # The error falls with the temperature; at 0.01 inliers every |score - threshold| / T >= 50,
    # each sigmoid is within e^-50 of its limit, and flags, modes, segments and poses are the hard
    # ones to rounding (flags 1e-12; positions 1e-9 m: errors of 1e-22 in a flag, times metre-scale
    # differences between visual and predicted states, amplified by at most 5 s of prediction).
    assert flag_err[0] > 0.5 and pos_err[0] > 1.0, (flag_err, pos_err)
    assert all(b <= a + 1e-12 for a, b in zip(flag_err, flag_err[1:], strict=False)), flag_err
    assert all(b <= a + 1e-12 for a, b in zip(pos_err, pos_err[1:], strict=False)), pos_err
    assert flag_err[-1] < 1e-12 and pos_err[-1] < 1e-9, (flag_err, pos_err)
    assert np.array_equal(soft["mode"], hard["mode"])
    np.testing.assert_allclose(soft["segment"][valid], hard["segment"][valid], rtol=0, atol=1e-12)


def test_relaxed_timer_belongs_to_the_recently_lost_mass(x64):
    """After 10 s of tracking, a frame that fails with probability 0.3 leaves 30 % of the mass in
    RECENTLY_LOST with its timer started at 10 s; a good next frame must recover that mass (5 s
    have not passed). Blending t_lost with the OK mass's stale timer (0.3 * 10 + 0.7 * 0 = 3 s)
    would make the mass 'expire' (10.05 - 3 > 5) and go LOST: the relaxed replay would lose
    tracking early. machine_step carries the RECENTLY_LOST mass's own (mass-weighted) timer."""
    th = Thresholds(**ORBSLAM3_TH)
    logic = SoftLogic(jnp.asarray(1.0))
    state = initial_state()
    for k in range(200):
        state, _ = machine_step(logic, state, 100.0, k * 0.05, float(k), 1.0, th, 20.0, 0.0)
    p_fail = 0.3
    score = 15.0 + math.log((1 - p_fail) / p_fail)  # sigmoid((15 - score) / 1) = 0.3
    state, _ = machine_step(logic, state, score, 10.0, 200.0, 1.0, th, 20.0, 0.0)
    np.testing.assert_allclose(float(state.recently_lost), p_fail, rtol=1e-12)
    state, _ = machine_step(logic, state, 100.0, 10.05, 201.0, 1.0, th, 20.0, 0.0)
    assert float(state.lost) < 1e-6, float(state.lost)
    np.testing.assert_allclose(float(state.ok), 1.0, atol=1e-6)


def test_relaxed_map_start_belongs_to_the_new_map_mass(x64):
    """All mass LOST at t = 10 s (frame 200) of a run whose first map started at 0; the frame passes
    the strict test with probability 0.3, so 30 % of the mass starts a new map there. On the next
    frame that mass is inside its map's relocalisation window (needs 50) and its IMU is not usable
    yet (imu_init_delay 2 s): 30 inliers must fail it. Blending the map start with the LOST mass's
    stale start (0.3 * 10 + 0.7 * 0 = 3 s, frame 60) would make the new map look 7 s old: the window
    over, the IMU usable, and 30 inliers passing (ok = 0.3 instead of ~0). machine_step carries the
    map start of the tracking (OK + RECENTLY_LOST) mass."""
    th = Thresholds(**ORBSLAM3_TH)
    logic = SoftLogic(jnp.asarray(1.0))
    one, zero = jnp.asarray(1.0), jnp.asarray(0.0)
    state = MachineState(ok=zero, recently_lost=zero, lost=one, t_lost=zero, map_start_t=zero,
                         map_start_k=zero, segment=zero)  # fmt: skip
    fail = 1 - math.sqrt(0.3)  # less(score, 50) for both the window and not_init: pass (1 - fail)^2
    score = 50.0 - math.log(fail / (1 - fail))
    state, decision = machine_step(logic, state, score, 10.0, 200.0, 1.0, th, 20.0, 2.0)
    np.testing.assert_allclose(float(decision.new_map), 0.3, rtol=1e-12)
    state, _ = machine_step(logic, state, 30.0, 10.05, 201.0, 1.0, th, 20.0, 2.0)
    assert float(state.ok) < 1e-6, float(state.ok)


TEMPERATURE = {InlierRule: 2.0, SVERule: 0.02}  # in score units: inliers, SVE


def _soft_loss(rule, batch, features, direction):
    """A smooth scalar of the relaxed replay: accepted share plus a projection of the positions."""
    res = replay(batch, rule, features, logic=SoftLogic(jnp.asarray(TEMPERATURE[type(rule)])))
    valid = batch.valid.astype(batch.t.dtype)
    positions = jnp.sum(res.position * direction * valid[..., None])
    return (jnp.sum(res.accepted) + positions) / jnp.sum(valid)


@pytest.mark.parametrize("kind", ["inliers", "sve"])
def test_relaxed_replay_gradient_matches_finite_difference(x64, kind):
    """d loss / d theta of the relaxed replay (thresholds; for SVE also the combination's w_a, u_b,
    p, q and rho) equals a central difference with h = 1e-5. Measured on these logs, the
    difference converges to the gradient as h^2 (truncation ~ 6e-7 relative at h = 1e-5 for the
    steepest leaf, w_a, at temperature 0.02); for p at 0 the power mean switches to its p -> 0
    expansion inside |p| < 1e-6 and the float64 power formula just outside it carries ~eps / p
    relative error, ~5e-6 relative in this difference. Tolerance 2e-5 relative + 1e-9 absolute:
    a missing or wrong term of a gradient is O(1) relative. Finite everywhere, frames without
    features included (the SVE logs have N_extracted = 0 frames)."""
    logs = oracle.random_logs(
        seed=13, n_runs=6, n_frames=200, min_frames=150, kind=kind, fractional_fps=False
    )
    batch = to_batch(logs, jnp.float64, with_bins=kind == "sve")
    features = batch_features(batch) if kind == "sve" else inlier_features(batch)
    direction = jnp.asarray(np.random.default_rng(0).normal(size=(1, 1, 3)))
    rule = InlierRule(Thresholds(**OFF_TIE_TH)) if kind == "inliers" else preset("sve-option2")
    loss = eqx.filter_jit(lambda r: _soft_loss(r, batch, features, direction))
    grads = eqx.filter_jit(eqx.filter_grad(lambda r: _soft_loss(r, batch, features, direction)))(rule)
    leaves, treedef = jax.tree.flatten(rule)
    g_leaves = jax.tree.leaves(grads)
    assert len(g_leaves) == len(leaves) == (4 if kind == "inliers" else 9)
    h = 1e-5
    for j, g in enumerate(g_leaves):
        up = jax.tree.unflatten(treedef, [x + h if m == j else x for m, x in enumerate(leaves)])
        down = jax.tree.unflatten(treedef, [x - h if m == j else x for m, x in enumerate(leaves)])
        fd = (loss(up) - loss(down)) / (2 * h)
        assert np.isfinite(float(g)), j
        np.testing.assert_allclose(float(g), float(fd), rtol=2e-5, atol=1e-9, err_msg=f"leaf {j}")
    # Not vacuous: the parameters do move the loss.
    assert max(abs(float(g)) for g in g_leaves) > 1e-3
