"""jsve.fitting: fitting rule weights and thresholds to minimise position error.

- Where: `ParamSpace` (bounds, transforms, presets as points), `sve_space`, `inlier_space`,
  `space_from_dict`; designs over it (`design`, `grid_design`).
- Scoring: `FitData` (logs packed for the kernel), `search` (the fused kernel: replay and alignment
  statistics of many settings in one scan), and the seam every optimiser scores through, `Scorer`,
  whose replay implementation is `ReplayScorer` (jsve.tuning's FrontendScorer runs the front-end).
- Optimisers: `fit` with `FitConfig` -> `FitResult` (search or successive halving, then Nelder-Mead and
  optionally annealed BFGS), `nelder_mead`, `relaxed_fit` (optimistix BFGS on the relaxed objective).
- Validation: `kfold`, `leave_one_out`, `cross_validate`, `compare` (bootstrap CIs).
- The study behind `jsve fit`: `StudyConfig`, `run_study` (resumable).

Layouts, packing, devices, the compilation cache and Dask sharding are internal.
"""

from jsve.fitting._config import StudyConfig as StudyConfig
from jsve.fitting._crossval import compare as compare
from jsve.fitting._crossval import cross_validate as cross_validate
from jsve.fitting._crossval import kfold as kfold
from jsve.fitting._crossval import leave_one_out as leave_one_out
from jsve.fitting._data import FitData as FitData
from jsve.fitting._designs import design as design
from jsve.fitting._designs import grid_design as grid_design
from jsve.fitting._fit import FitConfig as FitConfig
from jsve.fitting._fit import FitResult as FitResult
from jsve.fitting._fit import fit as fit
from jsve.fitting._optimise import nelder_mead as nelder_mead
from jsve.fitting._optimise import relaxed_fit as relaxed_fit
from jsve.fitting._scorer import ReplayScorer as ReplayScorer
from jsve.fitting._scorer import Scorer as Scorer
from jsve.fitting._search import search as search
from jsve.fitting._space import ParamSpace as ParamSpace
from jsve.fitting._space import inlier_space as inlier_space
from jsve.fitting._space import space_from_dict as space_from_dict
from jsve.fitting._space import sve_space as sve_space
from jsve.fitting._study import run_study as run_study
