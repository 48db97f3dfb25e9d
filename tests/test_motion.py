"""jsve.sim._trajectory and jsve.sim._imu: trajectories, IMU synthesis and preintegration against what
they must show.

- its numpy rotation helpers and IMU prediction agree with jsve.core._geometry and jsve.core._replay;
- the IMU it synthesises integrates back onto the trajectory, and its dead-reckoning drift is that
  of the real EuRoC V1_01 stream against ground truth (../shared/data);
- EuRoC ground truth is read in the body frame the real IMU measures in.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jsve.core import _geometry as geometry
from jsve.sim import _imu as si
from jsve.sim import _trajectory as st


@pytest.fixture(scope="module")
def short_flight() -> st.Trajectory:
    """A procedural flight cut to its first 30 s (keeps the tests fast)."""
    flight = st.FlightProfile(duration_s=(30.0, 30.0))
    return st.procedural_trajectory("proc_test", np.random.default_rng(3), flight)


# ---- rotations and IMU -----------------------------------------------------------------------------


def test_numpy_rotations_match_jsve_geometry(x64):
    rng = np.random.default_rng(0)
    a = st.quat_normalize(rng.normal(size=(50, 4)))
    b = st.quat_normalize(rng.normal(size=(50, 4)))
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(
        st.quat_mul(a, b), geometry.quat_mul(jnp.asarray(a), jnp.asarray(b)), atol=1e-14
    )
    np.testing.assert_allclose(
        st.quat_rotate(a, v), geometry.quat_rotate(jnp.asarray(a), jnp.asarray(v)), atol=1e-13
    )
    m = st.quat_to_matrix(a)
    np.testing.assert_allclose(m, geometry.quat_to_matrix(jnp.asarray(a)), atol=1e-14)
    np.testing.assert_allclose(st.matrix_to_quat(m), geometry.matrix_to_quat(jnp.asarray(m)), atol=1e-12)
    phi = rng.normal(size=(50, 3))
    np.testing.assert_allclose(st.quat_to_matrix(st.quat_exp(phi)), st.so3_exp(phi), atol=1e-12)
    np.testing.assert_allclose(st.quat_log(st.quat_exp(0.5 * phi)), 0.5 * phi, atol=1e-12)


def test_imu_predict_is_the_replays(x64):
    from jsve.core import imu_predict

    rng = np.random.default_rng(1)
    p, v, dp, dv = (rng.normal(size=(20, 3)) for _ in range(4))
    q, dq = st.quat_normalize(rng.normal(size=(20, 4))), st.quat_normalize(rng.normal(size=(20, 4)))
    dt = rng.uniform(0.01, 0.1, 20)
    ours = si.imu_predict(p, v, q, dt, dp, dv, dq)
    theirs = imu_predict(*(jnp.asarray(x) for x in (p, v, q, dt, dp, dv, dq)), jnp.asarray(st.GRAVITY))
    for x, y in zip(ours, theirs, strict=True):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_ideal_imu_integrates_back_onto_the_trajectory(short_flight):
    # Noise-free readings of the spline, preintegrated as ORB-SLAM3 does, must reproduce the motion.
    # ORB-SLAM3's step uses the rotation at the step's start with the two readings' mean, an O(dt)
    # error: at 2000 Hz the prediction stays within 1 cm over 5 s; at 200 Hz it is ten times larger
    # (the scheme, not the synthesis).
    drift = {}
    for rate in (200.0, 2000.0):
        imu = si.synthesize_imu(short_flight, None, noise=None, rate_hz=rate)
        pre = si.preintegrate(si.frame_substeps(imu, short_flight.frame_ns), np.zeros(3), np.zeros(3))
        drift[rate] = si.dead_reckoning_drift(short_flight, pre, horizons_s=(5.0,), skip_s=1.0)[5.0]
    assert np.max(drift[2000.0]) < 0.01
    assert 5 < np.median(drift[200.0]) / np.median(drift[2000.0]) < 20


def test_preintegration_first_frame_and_dt(short_flight):
    imu = si.synthesize_imu(short_flight, np.random.default_rng(0))
    dt, dp, dv, dq = si.preintegrate(si.frame_substeps(imu, short_flight.frame_ns), np.zeros(3), np.zeros(3))
    assert dt[0] == 0 and not dp[0].any() and not dv[0].any() and tuple(dq[0]) == (1.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(dt[1:], np.diff(short_flight.frame_ns) / 1e9, atol=1e-12)


def test_spline_fit_is_the_dense_least_squares_solution():
    # The banded Cholesky solve must give the dense normal equations' solution.
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0, 20, 400))
    y = np.stack([np.sin(t), np.cos(0.3 * t)], 1) + rng.normal(0, 1e-3, (400, 2))
    h, smooth = 0.1, 1e-2
    spline = st.Spline.fit(t, y, h, smooth)
    n_seg = int(np.ceil((t[-1] - t[0]) / h - 1e-9))
    m = n_seg + 3
    x = (t - t[0]) / h
    i = np.clip(np.floor(x).astype(int), 0, n_seg - 1)
    design = np.zeros((len(t), m))
    u = x - i  # uniform cubic B-spline weights (de Boor)
    weights = np.stack([(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], 1) / 6
    for a in range(4):
        design[np.arange(len(t)), i + a] = weights[:, a]
    second = np.diff(np.eye(m), n=2, axis=0)
    dense = np.linalg.solve(design.T @ design + smooth * second.T @ second, design.T @ y)
    np.testing.assert_allclose(spline.coef, dense, atol=1e-10)


def test_gauss_markov_variance_and_correlation():
    t = np.arange(0, 4000, 0.01)
    x = si.gauss_markov(np.random.default_rng(0), t, 0.5, 2.0, dim=4)
    # 4 x 400 correlation times: the sample standard deviation is within 5 % of 0.5.
    assert np.all(np.abs(x.std(axis=0) - 0.5) < 0.025)
    lag = 200  # 2 s = one correlation time
    rho = np.mean(x[:-lag] * x[lag:]) / np.mean(x * x)
    assert abs(rho - math.exp(-1)) < 0.05


def test_procedural_flights_are_euroc_like():
    rng = np.random.default_rng(0)
    for i in range(4):
        traj = st.procedural_trajectory(f"p{i}", rng)
        t = traj.seconds(traj.frame_ns)
        speed = np.linalg.norm(traj.velocity(t), axis=1)
        assert 80 <= t[-1] <= 180
        assert 0.25 <= speed.mean() <= 1.05 and speed.max() < 3.0
        assert np.all(np.diff(traj.frame_ns) == 50_000_000)  # 20 fps
        # The accelerometer at hover reads about +g along body x (the EuRoC MAV's IMU x points up).
        f = traj.specific_force(t)
        assert np.median(f[:, 0]) > 8.0


# ---- real data -------------------------------------------------------------------------------------


def test_euroc_extrinsics_are_sensor_yaml(shared_data):
    path = shared_data / "euroc" / "V1_01_first95" / "mav0" / "cam0" / "sensor.yaml"
    np.testing.assert_array_equal(st.read_yaml_matrix(path), st.EUROC_CAM0_T_BS)


def test_euroc_ground_truth_is_in_the_imu_body_frame(shared_data):
    # The body rates of the loaded ground truth must be what the real gyro measures (same axes),
    # and the specific force what the real accelerometer measures up to a bias of EuRoC's size.
    euroc = shared_data / "euroc"
    traj = st.load_euroc_trajectory(
        "V1_01", euroc / "groundtruth_left_cam", timestamps_dir=euroc / "timestamps"
    )
    imu = si.read_imu_stream(euroc / "imu" / "V101.txt")
    t = traj.seconds(imu.t_ns)
    inside = (t > 1) & (t < traj.position.t_end - 1)
    gyro, omega = imu.gyro[inside], traj.angular_velocity(t[inside])
    bias = np.mean(gyro - omega, axis=0)
    box = np.ones(20) / 20  # 0.1 s: the rotor vibration the 20 Hz ground truth cannot see averages out
    for j in range(3):
        smooth = np.convolve(gyro[:, j], box, "valid"), np.convolve(omega[:, j], box, "valid")
        assert np.corrcoef(*smooth)[0, 1] > 0.95
    assert np.all(np.abs(bias) < 0.1)  # EuRoC V1_01: about (-0.002, 0.021, 0.076) rad/s
    accel_bias = np.mean(imu.accel[inside] - traj.specific_force(t[inside]), axis=0)
    assert np.all(np.abs(accel_bias) < 0.8)  # about (0.0, 0.55, 0.07) m/s^2; a wrong frame gives g
    # Frames: the ground-truth stamps, all of them among ORB-SLAM3's image stamps.
    stamps = np.loadtxt(euroc / "timestamps" / "V101.txt", dtype=np.int64)
    assert np.isin(traj.frame_ns, stamps).all() and len(traj.frame_ns) == 2871


def test_imu_drift_matches_the_real_stream(shared_data):
    # Same estimator, same propagation, same trajectory: the simulated stream's median drift after
    # 1, 2 and 5 s is within a factor 1.6 of the real V1_01 stream's (docs/simulator.md, "IMU").
    euroc = shared_data / "euroc"
    traj = st.load_euroc_trajectory(
        "V1_01", euroc / "groundtruth_left_cam", timestamps_dir=euroc / "timestamps"
    )
    medians = {}
    for kind, imu in (
        ("real", si.read_imu_stream(euroc / "imu" / "V101.txt")),
        ("sim", si.synthesize_imu(traj, np.random.default_rng(0))),
    ):
        bg, ba = si.frame_bias_estimate(imu, traj)
        pre = si.preintegrate(si.frame_substeps(imu, traj.frame_ns), bg, ba)
        medians[kind] = {h: np.median(e) for h, e in si.dead_reckoning_drift(traj, pre).items()}
    for horizon in (1.0, 2.0, 5.0):
        ratio = medians["sim"][horizon] / medians["real"][horizon]
        assert 1 / 1.6 < ratio < 1.6, (horizon, medians)
