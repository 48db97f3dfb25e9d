"""jsve.evaluation: rules over logs at scale. Chunked replay + APE per run, tables, aggregation, CIs."""

from jsve.evaluation._aggregate import aggregate as aggregate
from jsve.evaluation._aggregate import bootstrap_ci as bootstrap_ci
from jsve.evaluation._aggregate import failure_counts as failure_counts
from jsve.evaluation._aggregate import group_weights as group_weights
from jsve.evaluation._aggregate import per_run_table as per_run_table
from jsve.evaluation._aggregate import run_loss as run_loss
from jsve.evaluation._agreement import SETTING as SETTING
from jsve.evaluation._agreement import agreement_table as agreement_table
from jsve.evaluation._agreement import kendall_tau as kendall_tau
from jsve.evaluation._agreement import ranking_table as ranking_table
from jsve.evaluation._agreement import rerun_summary as rerun_summary
from jsve.evaluation._agreement import unmatched as unmatched
from jsve.evaluation._evaluate import Evaluation as Evaluation
from jsve.evaluation._evaluate import evaluate as evaluate
from jsve.evaluation._evaluate import evaluate_batch as evaluate_batch
from jsve.evaluation._identity import identity_table as identity_table
from jsve.evaluation._record import EVALUATION_RECORD as EVALUATION_RECORD
from jsve.evaluation._record import EvaluationRecord as EvaluationRecord
from jsve.evaluation._record import RuleRecord as RuleRecord
from jsve.evaluation._record import read_evaluation_record as read_evaluation_record
from jsve.evaluation._record import rule_records as rule_records
from jsve.evaluation._record import write_evaluation_record as write_evaluation_record
