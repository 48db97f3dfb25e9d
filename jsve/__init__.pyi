# The public API of jsve, in one place. `jsve/__init__.py` loads these names lazily from this file
# (lazy_loader, SPEC 1), so `import jsve` and `jsve --help` do not pay for JAX, pandas or OpenCV until
# a name is used; type checkers and readers see the whole surface here.
#
# Layers, lowest first (tests/test_layers.py enforces that nothing imports a higher layer):
#   core        pure JAX: SVE metrics, rules + ORB-SLAM3 state machine, replay, alignment + APE/RPE, objective
#   io          the file edge: logs (format v1), ground truth, Parquet, importers, keypoint side files
#   evaluation  rules over logs at scale: chunked replay + APE per run, tables, aggregation
#   image       disturbances, disturbed datasets, ORB extraction, measurement on real frames
#   masks       dynamic-object masks (Algorithm 1) and Table I
#   sim         the stand-in front-end (trajectories, IMU, vision model, logs)
#   fitting     parameter spaces, designs, the search kernel, optimisers, cross-validation, studies
#   tuning      rules tuned in the real front-end's loop (`jsve tune`): proposals, races, the check
#   report      the threshold report
#   cli, frontend   the `jsve` command; the C++ log writer header

from . import cli as cli
from . import core as core
from . import evaluation as evaluation
from . import fitting as fitting
from . import frontend as frontend
from . import image as image
from . import io as io
from . import masks as masks
from . import report as report
from . import sim as sim
from . import tuning as tuning
from ._demo import run_demo as run_demo
from ._version import __version__ as __version__
from .core import FAILURE_CAUSES as FAILURE_CAUSES
from .core import PRESETS as PRESETS
from .core import Combination as Combination
from .core import ErrorStats as ErrorStats
from .core import FrameFeatures as FrameFeatures
from .core import HardLogic as HardLogic
from .core import InlierRule as InlierRule
from .core import LogBatch as LogBatch
from .core import ObjectiveConfig as ObjectiveConfig
from .core import ReplayResult as ReplayResult
from .core import RunError as RunError
from .core import SoftLogic as SoftLogic
from .core import SVERule as SVERule
from .core import Thresholds as Thresholds
from .core import Transform as Transform
from .core import align as align
from .core import ape_statistics as ape_statistics
from .core import batch_features as batch_features
from .core import batched_run_error as batched_run_error
from .core import error_statistics as error_statistics
from .core import failure_reason as failure_reason
from .core import frame_features as frame_features
from .core import imu_predict as imu_predict
from .core import machine_step as machine_step
from .core import objective as objective
from .core import pose_errors as pose_errors
from .core import power_mean as power_mean
from .core import preset as preset
from .core import relative_pose_errors as relative_pose_errors
from .core import replay as replay
from .core import rpe_pairs as rpe_pairs
from .core import rule_from_dict as rule_from_dict
from .core import rule_to_dict as rule_to_dict
from .core import run_error as run_error
from .core import run_losses as run_losses
from .core import s_a as s_a
from .core import s_a_original as s_a_original
from .core import s_b as s_b
from .core import s_c as s_c
from .core import sve_table as sve_table
from .evaluation import Evaluation as Evaluation
from .evaluation import aggregate as aggregate
from .evaluation import bootstrap_ci as bootstrap_ci
from .evaluation import evaluate as evaluate
from .evaluation import evaluate_batch as evaluate_batch
from .evaluation import evaluate_rules as evaluate_rules
from .evaluation import failure_counts as failure_counts
from .evaluation import per_run_table as per_run_table
from .fitting import FitConfig as FitConfig
from .fitting import FitData as FitData
from .fitting import FitResult as FitResult
from .fitting import ParamSpace as ParamSpace
from .fitting import compare as compare
from .fitting import cross_validate as cross_validate
from .fitting import fit as fit
from .fitting import inlier_space as inlier_space
from .fitting import kfold as kfold
from .fitting import leave_one_out as leave_one_out
from .fitting import nelder_mead as nelder_mead
from .fitting import relaxed_fit as relaxed_fit
from .fitting import search as search
from .fitting import sve_space as sve_space
from .io import Bucket as Bucket
from .io import GroundTruth as GroundTruth
from .io import KeypointLog as KeypointLog
from .io import LogFormatError as LogFormatError
from .io import LogIncompleteError as LogIncompleteError
from .io import ParquetStudy as ParquetStudy
from .io import ReadResult as ReadResult
from .io import RunLog as RunLog
from .io import SavedTrajectory as SavedTrajectory
from .io import associate_ground_truth as associate_ground_truth
from .io import buckets as buckets
from .io import event_counts as event_counts
from .io import from_runs as from_runs
from .io import in_saved_frame as in_saved_frame
from .io import ingest as ingest
from .io import iter_buckets as iter_buckets
from .io import open_study as open_study
from .io import read_haggart_sve as read_haggart_sve
from .io import read_keypoints as read_keypoints
from .io import read_log as read_log
from .io import read_logs as read_logs
from .io import read_parquet as read_parquet
from .io import read_seed_sve_csv as read_seed_sve_csv
from .io import read_sve_output as read_sve_output
from .io import saved_trajectory as saved_trajectory
from .io import validate_run as validate_run
from .io import write_euroc as write_euroc
from .io import write_keypoints as write_keypoints
from .io import write_log as write_log
from .io import write_quarantine_report as write_quarantine_report
from .masks import MotsMasks as MotsMasks
from .masks import PngMasks as PngMasks
from .masks import apply_masks as apply_masks
from .masks import dynamic_keypoints as dynamic_keypoints
from .masks import masked_log as masked_log
from .masks import table_one as table_one
from .report import write_report as write_report
from .sim import SimConfig as SimConfig
from .sim import simulate_run as simulate_run
from .sim import simulate_study as simulate_study
from .sim import write_study as write_study
