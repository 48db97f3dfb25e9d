"""jsve.io: the file edge. Tracking logs (format v1), ground truth, trajectory files, Parquet, importers,
side files.

Every reader raises `LogFormatError` naming file, line, column and value; every writer writes to a
temporary name and renames, so no half-written output is ever left under the final name; scripts write
their own outputs through the same writers (`atomic_path`, `write_text`, `write_json`, `write_table`, ...).
"""

from jsve.io import _schema as schema  # noqa: F401  (jsve.io.schema: the v1 names)
from jsve.io._atomic import PARTIAL_SUFFIX as PARTIAL_SUFFIX
from jsve.io._atomic import atomic_path as atomic_path
from jsve.io._atomic import write_bytes as write_bytes
from jsve.io._atomic import write_json as write_json
from jsve.io._atomic import write_table as write_table
from jsve.io._atomic import write_text as write_text
from jsve.io._batching import Bucket as Bucket
from jsve.io._batching import buckets as buckets
from jsve.io._batching import from_runs as from_runs
from jsve.io._errors import LogFormatError as LogFormatError
from jsve.io._errors import LogIncompleteError as LogIncompleteError
from jsve.io._errors import TrajectoryFileError as TrajectoryFileError
from jsve.io._groundtruth import DEFAULT_MAX_GAP_NS as DEFAULT_MAX_GAP_NS
from jsve.io._groundtruth import GT_FORMATS as GT_FORMATS
from jsve.io._groundtruth import GroundTruth as GroundTruth
from jsve.io._groundtruth import associate_ground_truth as associate_ground_truth
from jsve.io._importers import read_haggart_sve as read_haggart_sve
from jsve.io._importers import read_seed_sve_csv as read_seed_sve_csv
from jsve.io._importers import read_sve_output as read_sve_output
from jsve.io._ingest import ReadResult as ReadResult
from jsve.io._ingest import read_logs as read_logs
from jsve.io._ingest import write_quarantine_report as write_quarantine_report
from jsve.io._keypoints import KeypointLog as KeypointLog
from jsve.io._keypoints import keypoints_path as keypoints_path
from jsve.io._keypoints import read_keypoints as read_keypoints
from jsve.io._keypoints import write_keypoints as write_keypoints
from jsve.io._logs import read_log as read_log
from jsve.io._logs import validate_run as validate_run
from jsve.io._logs import write_log as write_log
from jsve.io._parquet import ingest as ingest
from jsve.io._parquet import load_runs as load_runs
from jsve.io._parquet import read_parquet as read_parquet
from jsve.io._rule_files import load_rules as load_rules
from jsve.io._saved_trajectory import SavedTrajectory as SavedTrajectory
from jsve.io._saved_trajectory import euroc_ate as euroc_ate
from jsve.io._saved_trajectory import event_counts as event_counts
from jsve.io._saved_trajectory import in_saved_frame as in_saved_frame
from jsve.io._saved_trajectory import saved_trajectory as saved_trajectory
from jsve.io._saved_trajectory import write_euroc as write_euroc
from jsve.io._schema import RunLog as RunLog
from jsve.io._schema import recorded_rule_label as recorded_rule_label
from jsve.io._stream import ParquetStudy as ParquetStudy
from jsve.io._stream import iter_buckets as iter_buckets
from jsve.io._stream import open_study as open_study
from jsve.io._study_table import PARQUET_WRITE_OPTIONS as PARQUET_WRITE_OPTIONS
from jsve.io._trajectories import TRAJECTORY_FORMATS as TRAJECTORY_FORMATS
from jsve.io._trajectories import PosePair as PosePair
from jsve.io._trajectories import read_pose_pairs as read_pose_pairs
from jsve.io._trajectories import read_trajectory as read_trajectory
from jsve.io._trajectories import stack_pose_pairs as stack_pose_pairs
