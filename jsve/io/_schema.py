"""Tracking log format v3: the one home of column names, dtypes, units and metadata keys.

Every reader, writer, simulator and the C++ header follow this module; docs/log-format.md describes
it for people. A log is one CSV file per run:

    # jsve-log v3 {"sequence": "MH_04", "run": 7, "fps": 20, ...}      <- line 1: magic + JSON metadata
    t_ns,state,imu_init,map_id,imu_ba2,n_extracted,...                  <- line 2: header (COLUMNS order)
    1403636580838555648,2,1,0,1,1000,...                                <- one row per frame
    # jsve-log trailer orbslam3 {"keyframes": ...}                      <- optional trailer lines (v3)
    # jsve-log end frames=3600                                          <- last line: completeness marker

Conventions: timestamps are int64 nanoseconds; poses are body-in-world T_wb with quaternions wxyz;
positions in metres (world frame), velocities in m/s (world frame); IMU preintegration is from the
previous frame to this one, expressed in the previous body frame (ORB-SLAM3's mpImuPreintegratedFrame).

Format v1 (no `map_id` / `imu_ba2`, a pose on every frame) is still read: `v1_defaults` fills the two
columns (docs/log-format.md, "Reading v1 logs: defaults"). Format v2 is v3 without the keyframe columns
and trailers, which v3 makes optional: a v2 log reads as it is.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
import pandas as pd

FORMAT_VERSION = 3
"""The version every writer writes."""

READ_VERSIONS = (1, 2, 3)
"""The versions the readers accept."""

MAGIC_PREFIX = "# jsve-log v"
"""Line 1 starts with this, the version number and a space."""

MAGICS = {v: f"{MAGIC_PREFIX}{v} " for v in READ_VERSIONS}
"""Line-1 prefix of each readable version; the rest of the line is a JSON object of metadata."""

MAGIC = MAGICS[FORMAT_VERSION]
"""Prefix of line 1 as written: `# jsve-log v3 `."""

TRAILER_PREFIX = "# jsve-log trailer "
"""Prefix of a trailer line (v3): then a key ([a-z0-9_]+), a space and one JSON value. Trailer lines
follow the rows and precede the end marker; each key at most once."""

ORBSLAM3_TRAILER = "orbslam3"
"""The trailer of jsve's ORB-SLAM3 hook: what System::SaveTrajectoryEuRoC reads at the end of the run
(jsve.io._saved_trajectory)."""

END_MARKER = "# jsve-log end frames="
"""Prefix of the last line, followed by the frame count. A log without it is incomplete."""

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
POSED_STATES = (STATE_OK, STATE_RECENTLY_LOST, STATE_OK_KLT)
"""States in which the front-end has a pose: a row in one of them must carry its vis_* values."""
STATE_NAMES = {
    -1: "SYSTEM_NOT_READY",
    0: "NO_IMAGES_YET",
    1: "NOT_INITIALIZED",
    2: "OK",
    3: "RECENTLY_LOST",
    4: "LOST",
    5: "OK_KLT",
}

VIS_POSITION = ("vis_px", "vis_py", "vis_pz")
VIS_QUATERNION = ("vis_qw", "vis_qx", "vis_qy", "vis_qz")
VIS_VELOCITY = ("vis_vx", "vis_vy", "vis_vz")
IMU_DP = ("imu_dpx", "imu_dpy", "imu_dpz")
IMU_DV = ("imu_dvx", "imu_dvy", "imu_dvz")
IMU_DQ = ("imu_dqw", "imu_dqx", "imu_dqy", "imu_dqz")
GT_POSITION = ("gt_px", "gt_py", "gt_pz")
GT_QUATERNION = ("gt_qw", "gt_qx", "gt_qy", "gt_qz")
VIS_COLUMNS = VIS_POSITION + VIS_QUATERNION + VIS_VELOCITY
"""The pose of a frame: all ten present, or (outside POSED_STATES) all ten empty / NaN."""
GT_COLUMNS = GT_POSITION + GT_QUATERNION
WORLD_QUATERNION = ("world_qw", "world_qx", "world_qy", "world_qz")
WORLD_TRANSLATION = ("world_tx", "world_ty", "world_tz")
WORLD_SCALE = "world_s"
WORLD_COLUMNS = WORLD_QUATERNION + WORLD_TRANSLATION + (WORLD_SCALE,)
"""The similarity W from the frame's map's first world frame to the world frame its vis_* pose is in:
x = world_s R(world_q) x_first + world_t for points (optional; all eight or none, on every frame; the
identity until the front-end first re-expresses its map). ORB-SLAM3 re-expresses a whole map
(Map::ApplyScaledRotation: gravity direction and scale) at IMU initialisation, inertial BA1 / BA2 and
scale refinement without a new map id, so the online poses of one map are in several world frames;
jsve.io._world re-expresses them in one."""
REL_POSITION = ("rel_px", "rel_py", "rel_pz")
REL_QUATERNION = ("rel_qw", "rel_qx", "rel_qy", "rel_qz")
REL_COLUMNS = REL_POSITION + REL_QUATERNION
KEYFRAME_INT_COLUMNS = ("events", "traj", "ref_kf")
KEYFRAME_COLUMNS = KEYFRAME_INT_COLUMNS + REL_COLUMNS
"""Format v3's optional last group (all ten or none): `events`, the front-end's events at this frame
(a bit set of EVENTS); `traj`, 1 when the frame entered the front-end's saved trajectory (ORB-SLAM3's
mlRelativeFramePoses); `ref_kf`, its reference keyframe (-1: none); rel_*, the camera's pose relative to
that keyframe's camera, T_cr (empty where ref_kf is -1)."""

EVENTS = {
    "reset": 1 << 0,  # Tracking::ResetActiveMap: the active map was cleared
    "reset_all": 1 << 1,  # Tracking::Reset: every map was cleared
    "new_map": 1 << 2,  # Tracking::CreateMapInAtlas (after LOST)
    "merge": 1 << 3,  # LoopClosing::MergeLocal / MergeLocal2
    "loop": 1 << 4,  # LoopClosing::CorrectLoop
    "imu_init": 1 << 5,  # a map's IMU initialised (Map::SetImuInitialized, first time)
    "ba1": 1 << 6,  # a map's inertial BA1 (Map::SetIniertialBA1, first time)
    "ba2": 1 << 7,  # a map's inertial BA2 (Map::SetIniertialBA2, first time)
}
"""The bits of the `events` column (jsve_log.hpp's jsve::Event); each is set on the first frame logged
after it happened."""

EVENT_MASK = sum(EVENTS.values())

COUNT_COLUMNS = ("n_extracted", "n_inliers", "n_frustum")
MAP_COLUMNS = ("map_id", "imu_ba2")
"""The recorded run's map and its inertial stage, new in v2 (right after imu_init)."""

INT_COLUMNS = ("t_ns", "state", "imu_init") + MAP_COLUMNS + COUNT_COLUMNS + BIN_COLUMNS
FLOAT_COLUMNS = VIS_COLUMNS + ("imu_dt",) + IMU_DP + IMU_DV + IMU_DQ

REQUIRED_COLUMNS = INT_COLUMNS + FLOAT_COLUMNS
"""Columns every v2 log has, in this order."""

OPTIONAL_GROUPS = (GT_COLUMNS, WORLD_COLUMNS, KEYFRAME_COLUMNS)
"""Optional column groups, each all or none, in file order after the required columns."""

COLUMNS = REQUIRED_COLUMNS + GT_COLUMNS
"""Column order when ground truth is logged; gt_* are optional (all seven or none), and so are the
world_* columns after them (`column_order`)."""


def column_order(version: int, gt: bool, world: bool, keyframes: bool = False) -> tuple[str, ...]:
    """The columns of format `version` with (or without) the gt_*, world_* and (v3) keyframe groups,
    in file order."""
    return (
        required_columns(version)
        + (GT_COLUMNS if gt else ())
        + (WORLD_COLUMNS if world else ())
        + (KEYFRAME_COLUMNS if keyframes else ())
    )


V1_REQUIRED_COLUMNS = tuple(c for c in REQUIRED_COLUMNS if c not in MAP_COLUMNS)
"""Columns every v1 log has, in this order (v2 without map_id and imu_ba2)."""


def required_columns(version: int) -> tuple[str, ...]:
    """The required columns of format `version` (1 or 2), in file order."""
    return V1_REQUIRED_COLUMNS if version == 1 else REQUIRED_COLUMNS


V1_BA2_DELAY_S = 15.0
"""s of map age after which a v1 log's frames count as past inertial BA2: ORB-SLAM3 v1.0
LocalMapping::Run starts VIBA 2 once the map's inertial time `mTinit` exceeds 15 s
(src/LocalMapping.cc, `if (mTinit>15.0f)`, ~l.218)."""

V1_DEFAULTS_TEXT = f"map_id = 0, imu_ba2 = imu_init & (t - t_first >= {V1_BA2_DELAY_S:g} s)"
"""The v1 defaults in words, for warnings and messages."""


def v1_defaults(t_ns: np.ndarray, imu_init: np.ndarray) -> dict[str, np.ndarray]:
    """map_id and imu_ba2 for frames that do not say (v1 logs, sources without Atlas maps).

    One map for the whole run (map_id 0), and inertial BA2 done from V1_BA2_DELAY_S after the first
    frame on frames whose IMU is initialised.

    Arguments:
        t_ns: [F] int64 stamps, ns, strictly increasing.
        imu_init: [F] 0/1.

    Returns:
        {"map_id": [F] int64 zeros, "imu_ba2": [F] int64 0/1}.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    map_id = np.zeros(len(t), np.int64)
    if len(t) == 0:
        return {"map_id": map_id, "imu_ba2": map_id.copy()}
    # The threshold in Python ints: t_first + 15 s may not fit in int64 (stamps near 2^63).
    threshold = int(t[0]) + round(V1_BA2_DELAY_S * 1e9)
    aged = t >= threshold if threshold <= np.iinfo(np.int64).max else np.zeros(len(t), bool)
    imu_ba2 = ((np.asarray(imu_init) != 0) & aged).astype(np.int64)
    return {"map_id": map_id, "imu_ba2": imu_ba2}


QUATERNION_GROUPS = {
    "vis_q": VIS_QUATERNION,
    "imu_dq": IMU_DQ,
    "gt_q": GT_QUATERNION,
    "world_q": WORLD_QUATERNION,
    "rel_q": REL_QUATERNION,
}

UNIT_QUATERNION_TOLERANCE = 1e-6
"""Largest accepted | |q| - 1 | for a logged quaternion (doubles written with 17 digits are far tighter)."""

FLOAT_MAX = float(np.finfo(np.float32).max)
"""Largest magnitude of a value in a float column (3.4028234663852886e38): jsve computes in float32
(LogBatch), where a larger value becomes inf; no metre, second or m/s of a real run comes near it."""

COUNT_MAX = int(np.iinfo(np.int32).max)
"""Largest count (n_extracted, n_inliers, n_frustum): ORB-SLAM3 counts in `int`, LogBatch in int32."""

BIN_MAX = int(np.iinfo(np.uint16).max)
"""Largest count of one SVE bin (65535): LogBatch holds bins as uint16. It also bounds the sum of the
64 bins far inside int64."""

UNITS = {
    "t_ns": "ns (int64, sensor clock)",
    "state": "ORB-SLAM3 eTrackingState (-1..5)",
    "imu_init": "0/1, Atlas::isImuInitialized() for the active map",
    "map_id": "ORB-SLAM3 Map::GetId() of the Atlas map the frame was tracked in (int >= 0)",
    "imu_ba2": "0/1, Map::GetIniertialBA2() of that map (1 requires imu_init = 1)",
    "n_extracted": "keypoints extracted (Frame::N)",
    "n_inliers": "map-point inliers after TrackLocalMap (mnMatchesInliers)",
    "n_frustum": "local-map points in frustum (nToMatch in SearchLocalPoints)",
    "bin_k": "keypoints in SVE bin k (count)",
    "vis_p*": "m, world frame (T_wb translation); empty / NaN on a frame without a pose",
    "vis_q*": "unit quaternion wxyz, body-to-world rotation",
    "vis_v*": "m/s, world frame",
    "imu_dt": "s, preintegration interval (0 on the first frame)",
    "imu_dp*": "m, preintegrated position delta in previous body frame",
    "imu_dv*": "m/s, preintegrated velocity delta in previous body frame",
    "imu_dq*": "unit quaternion wxyz, preintegrated rotation delta",
    "gt_p*": "m, ground-truth body position, world frame",
    "gt_q*": "unit quaternion wxyz, ground-truth body-to-world rotation",
    "world_q*": "unit quaternion wxyz, rotation of the similarity from the map's first world frame",
    "world_t*": "m (this frame's world), translation of that similarity",
    "world_s": "scale of that similarity (> 0, dimensionless)",
    "events": "bit set of EVENTS at this frame",
    "traj": "0/1, the frame entered the front-end's saved trajectory",
    "ref_kf": "reference keyframe id (-1: none)",
    "rel_p*": "m, camera position relative to the reference keyframe's camera (T_cr translation)",
    "rel_q*": "unit quaternion wxyz, T_cr rotation",
}

REQUIRED_METADATA = {"sequence": str, "run": int, "fps": (int, float)}
"""Metadata keys every log has, with accepted Python types."""

OPTIONAL_METADATA = {
    "disturbance": str,  # "none", "blur", "downsample", "occlusion", ...
    "level": (int, float),  # disturbance level in its own unit (kernel px, scale, square px)
    "sensor": str,  # "imu_monocular", "imu_stereo", ...
    "n_features": int,  # ORB nFeatures of the front-end (S_a original variant)
    "image_size": list,  # [width, height] in pixels
    "grid": list,  # SVE bins [cols, rows], always [8, 8]
    "gravity": list,  # world gravity vector, m/s^2; default [0, 0, -9.81]
    "frontend": str,  # free text: "ORB-SLAM3 v1.0 + jsve logger", "jsve simulator 0.1"
    "seed": int,  # simulator seed
    "rule": (str, dict),  # the rule the front-end ran: a preset name, or jsve.core._rules.rule_to_dict's form
    "switch_model": str,  # what the front-end does with a rejected frame's pose: "orbslam3", "imu-coast", ...
    "rule_name": str,  # a short name of that rule for run ids and folders ("record", "sve-option2", "fitted")
    "camera_in_body": list,  # T_bc, the camera pose in the body (IMU) frame: [qw, qx, qy, qz, tx, ty, tz] (m)
}

DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
"""World gravity (m/s^2) when the metadata has no `gravity`: z up, as in EuRoC's world frame."""

DEFAULT_N_FEATURES = 1000
"""ORB nFeatures when the metadata has no `n_features` (ORB-SLAM3 EuRoC settings, ORBextractor.nFeatures)."""

STEREO_SENSORS = ("imu_stereo", "imu_rgbd")
"""`sensor` values whose success test ignores the IMU state (Tracking.cc l.3047-3053: < 15 inliers fails)."""


def recorded_rule_label(meta: dict) -> str | None:
    """`rule-switch_model` of a run whose front-end ran another rule than ORB-SLAM3's own, else None.

    The rule is named by the metadata `rule_name` when the front-end wrote one (`jsve frontend run`
    does), else by "rule-" and the first 8 hex digits of the SHA-1 of `rule` as JSON text."""
    rule = meta.get("rule")
    model = meta.get("switch_model", "orbslam3")
    if rule is None or (rule == "orbslam3" and model == "orbslam3"):
        return None
    name = meta.get("rule_name")
    if not name:
        text = rule if isinstance(rule, str) else json.dumps(rule, sort_keys=True)
        name = "rule-" + hashlib.sha1(text.encode("utf-8")).hexdigest()[:8]
    return f"{name}-{model}"


def run_id(meta: dict) -> str:
    """`sequence/disturbance-level/run` of a log's metadata, unique within a study; a run whose front-end
    ran another rule than ORB-SLAM3's own (metadata `rule`, `switch_model`) has its rule in it as well,
    `sequence/disturbance-level/rule-switch_model/run`, so that several rules' runs of one setting can be
    read together."""
    setting = f"{meta['sequence']}/{meta.get('disturbance', 'none')}-{meta.get('level', 0)}"
    label = recorded_rule_label(meta)
    return f"{setting}/{label}/{meta['run']}" if label else f"{setting}/{meta['run']}"


@dataclass(frozen=True)
class RunLog:
    """One run's tracking log in memory, as read from (or about to be written to) a v2 file.

    Attributes:
        meta: the metadata object of line 1 (REQUIRED_METADATA keys at least).
        frames: one row per frame, columns in REQUIRED_COLUMNS (+ GT_COLUMNS) (+ WORLD_COLUMNS) order; integer
            columns int64, float columns float64, vis_* NaN on frames without a pose, gt_* NaN
            where no ground truth is associated. Runs read from v1 files carry v1_defaults.
        source: where it came from (a path, or a name for in-memory logs), used in every message.
        trailers: the trailer lines of a v3 file, key -> parsed JSON (None: none).
    """

    meta: dict
    frames: pd.DataFrame
    source: str = "<memory>"
    trailers: dict | None = None

    @property
    def run_id(self) -> str:
        """run_id(meta)."""
        return run_id(self.meta)

    @property
    def has_ground_truth(self) -> bool:
        return all(c in self.frames.columns for c in GT_COLUMNS)

    @property
    def has_keyframes(self) -> bool:
        """The frames carry the v3 keyframe columns (KEYFRAME_COLUMNS)."""
        return all(c in self.frames.columns for c in KEYFRAME_COLUMNS)

    @property
    def has_world_frame(self) -> bool:
        """The frames carry world_* (the similarity of each pose's world frame, see WORLD_COLUMNS)."""
        return all(c in self.frames.columns for c in WORLD_COLUMNS)
