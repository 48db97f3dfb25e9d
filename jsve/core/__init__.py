"""jsve.core: the pure-JAX heart of jsve, arrays in and arrays out.

SVE metrics and their combinations, the switching rules and ORB-SLAM3's state machine, the replay
over frames, trajectory alignment and APE statistics, the objective, and the LogBatch pytree they
all consume. Nothing here reads files or imports pandas, OpenCV, the simulator or the fitting code
(tests/test_layers.py enforces it).
"""

from jsve.core._align import ALIGN_METHODS as ALIGN_METHODS
from jsve.core._align import Transform as Transform
from jsve.core._batch import LogBatch as LogBatch
from jsve.core._batch import bucket_by_length as bucket_by_length
from jsve.core._batch import iter_chunks as iter_chunks
from jsve.core._batch import pad_runs as pad_runs
from jsve.core._batch import take_runs as take_runs
from jsve.core._geometry import matrix_to_quat as matrix_to_quat
from jsve.core._geometry import quat_conj as quat_conj
from jsve.core._geometry import quat_exp as quat_exp
from jsve.core._geometry import quat_log as quat_log
from jsve.core._geometry import quat_mul as quat_mul
from jsve.core._geometry import quat_normalize as quat_normalize
from jsve.core._geometry import quat_rotate as quat_rotate
from jsve.core._geometry import quat_to_matrix as quat_to_matrix
from jsve.core._geometry import rotation_angle as rotation_angle
from jsve.core._geometry import so3_exp as so3_exp
from jsve.core._imu import imu_predict as imu_predict
from jsve.core._levels import LEVELS as LEVELS
from jsve.core._levels import SEED_DISTURBANCES as SEED_DISTURBANCES
from jsve.core._machine import HardLogic as HardLogic
from jsve.core._machine import SoftLogic as SoftLogic
from jsve.core._machine import machine_step as machine_step
from jsve.core._objective import ObjectiveConfig as ObjectiveConfig
from jsve.core._objective import objective as objective
from jsve.core._objective import run_losses as run_losses
from jsve.core._pose_error import DELTA_UNITS as DELTA_UNITS
from jsve.core._pose_error import POSE_RELATIONS as POSE_RELATIONS
from jsve.core._pose_error import align_poses as align_poses
from jsve.core._pose_error import error_statistics as error_statistics
from jsve.core._pose_error import pose_errors as pose_errors
from jsve.core._pose_error import relative_pose_errors as relative_pose_errors
from jsve.core._pose_error import rpe_angle_pairs as rpe_angle_pairs
from jsve.core._pose_error import rpe_pairs as rpe_pairs
from jsve.core._pose_error_batch import batched_ape as batched_ape
from jsve.core._pose_error_batch import batched_rpe as batched_rpe
from jsve.core._replay import ReplayResult as ReplayResult
from jsve.core._replay import batch_features as batch_features
from jsve.core._replay import replay as replay
from jsve.core._rules import PRESETS as PRESETS
from jsve.core._rules import InlierRule as InlierRule
from jsve.core._rules import SVERule as SVERule
from jsve.core._rules import Thresholds as Thresholds
from jsve.core._rules import preset as preset
from jsve.core._rules import rule_from_dict as rule_from_dict
from jsve.core._rules import rule_to_dict as rule_to_dict
from jsve.core._sve import Combination as Combination
from jsve.core._sve import FrameFeatures as FrameFeatures
from jsve.core._sve import frame_features as frame_features
from jsve.core._sve import power_mean as power_mean
from jsve.core._sve import s_a as s_a
from jsve.core._sve import s_a_original as s_a_original
from jsve.core._sve import s_b as s_b
from jsve.core._sve import s_c as s_c
from jsve.core._sve import sve_table as sve_table
from jsve.core._trajectory import FAILURE_CAUSES as FAILURE_CAUSES
from jsve.core._trajectory import ErrorStats as ErrorStats
from jsve.core._trajectory import RunError as RunError
from jsve.core._trajectory import align as align
from jsve.core._trajectory import ape_statistics as ape_statistics
from jsve.core._trajectory import batched_run_error as batched_run_error
from jsve.core._trajectory import failure_reason as failure_reason
from jsve.core._trajectory import run_error as run_error
