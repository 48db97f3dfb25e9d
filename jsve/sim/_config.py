"""The simulator's configuration: everything its logs depend on besides sequence, setting, run and seed.

SimConfig       the vision model, the tracking model, scene, IMU noise, flight profile, IMU source
TrackingParams  the run-level tracking model (map inliers, frustum, pose error, IMU initialisation)
FRONTEND        the model's version, written into every simulated log
"""

from __future__ import annotations

from dataclasses import dataclass

from jsve.sim._imu import ImuNoise
from jsve.sim._scene import SceneProfile
from jsve.sim._trajectory import FlightProfile
from jsve.sim._vision import N_FEATURES, VisionParams

FRONTEND = "jsve simulator 2"
"""Value of the `frontend` metadata key of simulated logs (the model version)."""


@dataclass(frozen=True)
class TrackingParams:
    """Run-level tracking model: map inliers, frustum counts, visual pose error, IMU initialisation.

    Attributes:
        map_fraction: share of frame-to-frame matchable keypoints that carry a local-map point.
        run_sigma, run_tau: log spread and correlation time (s) of a run's map quality (ORB-SLAM3's
            runs differ through threading and RANSAC).
        frustum_window_s: s; n_frustum counts the local map's points in view, built from the
            keypoints of about the last second (ORB-SLAM3's covisible keyframes).
        frustum_ratio: local-map points in view per keypoint of that window (1: the real-frame
            stand-in's ratio).
        depth_spread: coefficient of variation of the scene depth about its median (breaks the
            translation-rotation ambiguity of a narrow view).
        prior_position, prior_rotation: m, rad: the motion-model prior of the pose optimisation.
        drift_per_sqrt_m, yaw_drift_per_sqrt_m: m, rad per sqrt(m travelled): the map's slow drift
            (visual-inertial: position and yaw unobservable).
        jitter_to_drift: share of each frame's error that stays in the map.
        outlier_rate, outlier_inliers: a gross jump happens on a frame with probability
            outlier_rate exp(-inliers / outlier_inliers).
        outlier_position, outlier_rotation: m, rad: standard deviation of a jump per axis.
        recovery_s: s, time for strong tracking (many inliers) to pull an excursion back; weak
            tracking holds it (recovery slows as inliers / (inliers + recovery_inliers) falls).
        velocity_tau: s, smoothing of the visual velocity (the visual-inertial window).
        imu_init_s: (min, max) s after the first map's first frame at which ORB-SLAM3 initialises the
            IMU (LocalMapping: the first inertial initialisation after 2 s of map).
        init_match_share: level-0 keypoints that monocular initialisation's windowed search matches
            between its reference and a frame up to 0.5 s later, per keypoint matched frame to frame.
        init_max_age_s: s, ORB-SLAM3 drops an IMU_MONOCULAR initialisation reference older than this.
        init_parallax_deg: degrees of parallax a two-view reconstruction needs.
        map_lifetime_s: s a scene point must stay in view to become a map point (keyframes, then
            triangulation): under an occluder the points that emerge from behind it within this
            time of image motion have none yet.
    """

    map_fraction: float = 0.46
    run_sigma: float = 0.1
    run_tau: float = 5.0
    frustum_window_s: float = 1.0
    frustum_ratio: float = 1.0
    depth_spread: float = 0.3
    prior_position: float = 0.3
    prior_rotation: float = 0.1
    drift_per_sqrt_m: float = 0.006
    yaw_drift_per_sqrt_m: float = 0.001
    jitter_to_drift: float = 0.1
    outlier_rate: float = 0.5
    outlier_inliers: float = 8.0
    outlier_position: float = 0.25
    outlier_rotation: float = 0.05
    recovery_s: float = 0.2
    recovery_inliers: float = 30.0
    velocity_tau: float = 0.25
    imu_init_s: tuple[float, float] = (2.0, 3.5)
    init_match_share: float = 0.79
    init_max_age_s: float = 1.0
    init_parallax_deg: float = 1.0
    map_lifetime_s: float = 1.25


@dataclass(frozen=True)
class SimConfig:
    """Everything the simulator's output depends on besides sequence, setting, run and seed."""

    vision: VisionParams = VisionParams()
    tracking: TrackingParams = TrackingParams()
    scene: SceneProfile = SceneProfile()
    imu: ImuNoise = ImuNoise()
    flight: FlightProfile = FlightProfile()
    imu_source: str = "synthetic"  # "synthetic" or "real" (EuRoC imu0 stream where available)
    bias_window_s: float = 10.0
    n_features: int = N_FEATURES


__all__ = ["FRONTEND", "TrackingParams", "SimConfig"]
