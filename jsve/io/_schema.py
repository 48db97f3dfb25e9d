"""Tracking log format v1: the one home of column names, dtypes, units and metadata keys.

Every reader, writer, simulator and the C++ header follow this module; docs/log-format.md describes
it for people. A log is one CSV file per run:

    # jsve-log v1 {"sequence": "MH_04", "run": 7, "fps": 20, ...}      <- line 1: magic + JSON metadata
    t_ns,state,imu_init,n_extracted,...                                 <- line 2: header (COLUMNS order)
    1403636580838555648,2,1,1000,...                                    <- one row per frame
    # jsve-log end frames=3600                                          <- last line: completeness marker

Conventions: timestamps are int64 nanoseconds; poses are body-in-world T_wb with quaternions wxyz;
positions in metres (world frame), velocities in m/s (world frame); IMU preintegration is from the
previous frame to this one, expressed in the previous body frame (ORB-SLAM3's mpImuPreintegratedFrame).
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

MAGIC = "# jsve-log v1 "
"""Prefix of line 1; the rest of the line is a JSON object of metadata."""

END_MARKER = "# jsve-log end frames="
"""Prefix of the last line, followed by the frame count. A log without it is incomplete."""

FORMAT_VERSION = 1

N_BINS = 64
"""SVE bins per frame: ORB-SLAM3's 64 x 48 keypoint grid binned 8 x 8 (bin x = col // 8, y = row // 6)."""

BIN_COLUMNS = tuple(f"bin_{k}" for k in range(N_BINS))
"""Extracted keypoints per SVE bin, row-major (k = 8 * bin_y + bin_x)."""

# ORB-SLAM3 v1.0 Tracking::eTrackingState values, as logged in the `state` column.
STATE_SYSTEM_NOT_READY = -1
STATE_NO_IMAGES_YET = 0
STATE_NOT_INITIALIZED = 1
STATE_OK = 2
STATE_RECENTLY_LOST = 3
STATE_LOST = 4
STATE_OK_KLT = 5
VALID_STATES = (-1, 0, 1, 2, 3, 4, 5)

VIS_POSITION = ("vis_px", "vis_py", "vis_pz")
VIS_QUATERNION = ("vis_qw", "vis_qx", "vis_qy", "vis_qz")
VIS_VELOCITY = ("vis_vx", "vis_vy", "vis_vz")
IMU_DP = ("imu_dpx", "imu_dpy", "imu_dpz")
IMU_DV = ("imu_dvx", "imu_dvy", "imu_dvz")
IMU_DQ = ("imu_dqw", "imu_dqx", "imu_dqy", "imu_dqz")
GT_POSITION = ("gt_px", "gt_py", "gt_pz")
GT_QUATERNION = ("gt_qw", "gt_qx", "gt_qy", "gt_qz")
GT_COLUMNS = GT_POSITION + GT_QUATERNION
COUNT_COLUMNS = ("n_extracted", "n_inliers", "n_frustum")

INT_COLUMNS = ("t_ns", "state", "imu_init") + COUNT_COLUMNS + BIN_COLUMNS
FLOAT_COLUMNS = VIS_POSITION + VIS_QUATERNION + VIS_VELOCITY + ("imu_dt",) + IMU_DP + IMU_DV + IMU_DQ

REQUIRED_COLUMNS = INT_COLUMNS + FLOAT_COLUMNS
"""Columns every v1 log has, in this order."""

COLUMNS = REQUIRED_COLUMNS + GT_COLUMNS
"""Full column order when ground truth is logged; gt_* are optional (all seven or none)."""

QUATERNION_GROUPS = {"vis_q": VIS_QUATERNION, "imu_dq": IMU_DQ, "gt_q": GT_QUATERNION}

UNIT_QUATERNION_TOLERANCE = 1e-6
"""Largest accepted | |q| - 1 | for a logged quaternion (doubles written with 17 digits are far tighter)."""

UNITS = {
    "t_ns": "ns (int64, sensor clock)",
    "state": "ORB-SLAM3 eTrackingState (-1..5)",
    "imu_init": "0/1, Atlas::isImuInitialized() for the active map",
    "n_extracted": "keypoints extracted (Frame::N)",
    "n_inliers": "map-point inliers after TrackLocalMap (mnMatchesInliers)",
    "n_frustum": "local-map points in frustum (nToMatch in SearchLocalPoints)",
    "bin_k": "keypoints in SVE bin k (count)",
    "vis_p*": "m, world frame (T_wb translation)",
    "vis_q*": "unit quaternion wxyz, body-to-world rotation",
    "vis_v*": "m/s, world frame",
    "imu_dt": "s, preintegration interval (0 on the first frame)",
    "imu_dp*": "m, preintegrated position delta in previous body frame",
    "imu_dv*": "m/s, preintegrated velocity delta in previous body frame",
    "imu_dq*": "unit quaternion wxyz, preintegrated rotation delta",
    "gt_p*": "m, ground-truth body position, world frame",
    "gt_q*": "unit quaternion wxyz, ground-truth body-to-world rotation",
}

REQUIRED_METADATA = {"sequence": str, "run": int, "fps": (int, float)}
"""Metadata keys every log has, with accepted Python types."""

OPTIONAL_METADATA = {
    "disturbance": str,  # "none", "blur", "downsample", "occlusion", ...
    "level": (int, float),  # disturbance level in its own unit (kernel px, scale, square px)
    "sensor": str,  # "imu_monocular", "imu_stereo", ...
    "n_features": int,  # ORB nFeatures of the front-end (S_a original variant)
    "image_size": list,  # [width, height] in pixels
    "grid": list,  # SVE bins [cols, rows], always [8, 8] in v1
    "gravity": list,  # world gravity vector, m/s^2; default [0, 0, -9.81]
    "frontend": str,  # free text: "ORB-SLAM3 v1.0 + jsve logger", "jsve simulator 0.1"
    "seed": int,  # simulator seed
}

DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
"""World gravity (m/s^2) when the metadata has no `gravity`: z up, as in EuRoC's world frame."""


@dataclass(frozen=True)
class RunLog:
    """One run's tracking log in memory, as read from (or about to be written to) a v1 file.

    Attributes:
        meta: the metadata object of line 1 (REQUIRED_METADATA keys at least).
        frames: one row per frame, columns in REQUIRED_COLUMNS (+ GT_COLUMNS) order; integer
            columns int64, float columns float64, gt_* NaN where no ground truth is associated.
        source: where it came from (a path, or a name for in-memory logs), used in every message.
    """

    meta: dict
    frames: pd.DataFrame
    source: str = "<memory>"

    @property
    def run_id(self) -> str:
        """`sequence/disturbance-level/run`, unique within a study."""
        m = self.meta
        return f"{m['sequence']}/{m.get('disturbance', 'none')}-{m.get('level', 0)}/{m['run']}"

    @property
    def has_ground_truth(self) -> bool:
        return all(c in self.frames.columns for c in GT_COLUMNS)
