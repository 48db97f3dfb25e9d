"""jsve: scene-visibility-based switching for visual-inertial SLAM, in JAX.

This file re-exports the public API; a user learns the whole surface from it.

    logs -> LogBatch -> SVE features -> rule + ORB-SLAM3 state machine -> replay -> trajectory error
"""

from . import batch as batch
from . import schema as schema
from .aggregate import aggregate as aggregate
from .aggregate import bootstrap_ci as bootstrap_ci
from .aggregate import per_run_table as per_run_table
from .batch import Bucket as Bucket
from .batch import LogBatch as LogBatch
from .batch import bucket_by_length as bucket_by_length
from .batch import buckets as buckets
from .batch import from_runs as from_runs
from .batch import iter_chunks as iter_chunks
from .evaluate import Evaluation as Evaluation
from .evaluate import evaluate as evaluate
from .evaluate import evaluate_batch as evaluate_batch
from .groundtruth import GroundTruth as GroundTruth
from .groundtruth import associate_ground_truth as associate_ground_truth
from .importers import read_haggart_sve as read_haggart_sve
from .importers import read_seed_sve_csv as read_seed_sve_csv
from .importers import read_sve_output as read_sve_output
from .ingest import ReadResult as ReadResult
from .ingest import ingest as ingest
from .ingest import read_logs as read_logs
from .ingest import read_parquet as read_parquet
from .ingest import write_quarantine_report as write_quarantine_report
from .keypoints import KeypointLog as KeypointLog
from .keypoints import read_keypoints as read_keypoints
from .keypoints import write_keypoints as write_keypoints
from .logs import LogFormatError as LogFormatError
from .logs import LogIncompleteError as LogIncompleteError
from .logs import read_log as read_log
from .logs import validate_run as validate_run
from .logs import write_log as write_log
from .masks import MotsMasks as MotsMasks
from .masks import PngMasks as PngMasks
from .masks import apply_masks as apply_masks
from .masks import dynamic_keypoints as dynamic_keypoints
from .masks import masked_log as masked_log
from .replay import ReplayResult as ReplayResult
from .replay import batch_features as batch_features
from .replay import imu_predict as imu_predict
from .replay import replay as replay
from .rules import PRESETS as PRESETS
from .rules import HardLogic as HardLogic
from .rules import InlierRule as InlierRule
from .rules import SoftLogic as SoftLogic
from .rules import SVERule as SVERule
from .rules import Thresholds as Thresholds
from .rules import machine_step as machine_step
from .rules import preset as preset
from .rules import rule_from_dict as rule_from_dict
from .rules import rule_to_dict as rule_to_dict
from .schema import RunLog as RunLog
from .sve import Combination as Combination
from .sve import FrameFeatures as FrameFeatures
from .sve import frame_features as frame_features
from .sve import power_mean as power_mean
from .sve import s_a as s_a
from .sve import s_a_original as s_a_original
from .sve import s_b as s_b
from .sve import s_c as s_c
from .sve import sve_table as sve_table
from .tablei import table_one as table_one
from .trajectory import ErrorStats as ErrorStats
from .trajectory import RunError as RunError
from .trajectory import Transform as Transform
from .trajectory import align as align
from .trajectory import ape_statistics as ape_statistics
from .trajectory import batched_run_error as batched_run_error
from .trajectory import run_error as run_error

__version__ = "0.1.0"
