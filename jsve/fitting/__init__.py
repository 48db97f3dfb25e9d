"""jsve.fitting: fitting rule weights and thresholds to minimise position error.

The parameter space (bounds, transforms, presets as points), space-filling designs, the fused search
kernel (replay + alignment statistics in one scan over many settings), the scorer every optimiser
asks for per-run results (Scorer; ReplayScorer replays logs with the kernel), Nelder-Mead fits (jsve's
own lockstep driver) and relaxed BFGS fits (optimistix), cross-validation with bootstrap CIs, and the
resumable study behind `jsve fit`.
"""

from jsve.fitting._config import THOROUGH as THOROUGH
from jsve.fitting._config import StudyConfig as StudyConfig
from jsve.fitting._crossval import compare as compare
from jsve.fitting._crossval import cross_validate as cross_validate
from jsve.fitting._crossval import kfold as kfold
from jsve.fitting._crossval import leave_one_out as leave_one_out
from jsve.fitting._data import FitData as FitData
from jsve.fitting._designs import design as design
from jsve.fitting._designs import grid_design as grid_design
from jsve.fitting._designs import sobol as sobol
from jsve.fitting._distributed import ShardedSearch as ShardedSearch
from jsve.fitting._fit import FitConfig as FitConfig
from jsve.fitting._fit import FitResult as FitResult
from jsve.fitting._fit import fit as fit
from jsve.fitting._fit import fit_search as fit_search
from jsve.fitting._fit import fitted_rule_name as fitted_rule_name
from jsve.fitting._fit import judge as judge
from jsve.fitting._fit import polish as polish
from jsve.fitting._fit import polish_fits as polish_fits
from jsve.fitting._fit import resolve_search as resolve_search
from jsve.fitting._fit import search_all as search_all
from jsve.fitting._halving import RunLossCache as RunLossCache
from jsve.fitting._halving import halving_search as halving_search
from jsve.fitting._halving import halving_searches as halving_searches
from jsve.fitting._halving import rung_sizes as rung_sizes
from jsve.fitting._halving import stratified_order as stratified_order
from jsve.fitting._optimise import nelder_mead as nelder_mead
from jsve.fitting._optimise import relaxed_fit as relaxed_fit
from jsve.fitting._packing import LAYOUT_CLASSES as LAYOUT_CLASSES
from jsve.fitting._packing import cheapest_layout as cheapest_layout
from jsve.fitting._packing import layout_shapes as layout_shapes
from jsve.fitting._packing import pack_runs as pack_runs
from jsve.fitting._packing import scan_cost as scan_cost
from jsve.fitting._packing import subset_parts as subset_parts
from jsve.fitting._polish import polish_runs as polish_runs
from jsve.fitting._scorer import ReplayScorer as ReplayScorer
from jsve.fitting._scorer import Scorer as Scorer
from jsve.fitting._search import lanes_per_call as lanes_per_call
from jsve.fitting._search import search as search
from jsve.fitting._search import use_all_cores as use_all_cores
from jsve.fitting._simplex import lockstep_nelder_mead as lockstep_nelder_mead
from jsve.fitting._space import ParamSpace as ParamSpace
from jsve.fitting._space import inlier_space as inlier_space
from jsve.fitting._space import space_from_dict as space_from_dict
from jsve.fitting._space import sve_space as sve_space
from jsve.fitting._study import run_study as run_study
from jsve.fitting._study import study_folds as study_folds
