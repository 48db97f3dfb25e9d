"""jsve.tuning: rules tuned in the real front-end's loop, the replay proposing and paired runs deciding.

`tune(study, out)` records the incumbent (ORB-SLAM3's own rule first), proposes candidates from its
logs (the replay's fit within the trust region, the family's presets, perturbations), races them seed
by seed on paired runs with Holm-corrected Wilcoxon tests, repeats from a winner, and verifies the
result on held-out sequences with fresh seeds. `FrontendScorer` is jsve.fitting's Scorer over rules
run in the loop (ORB-SLAM3, or the simulator to rehearse).
"""

from jsve.tuning._frontend import Candidate as Candidate
from jsve.tuning._frontend import FrontendScorer as FrontendScorer
from jsve.tuning._frontend import Instance as Instance
from jsve.tuning._frontend import OrbSlam3Frontend as OrbSlam3Frontend
from jsve.tuning._frontend import SimulatedFrontend as SimulatedFrontend
from jsve.tuning._frontend import run_row as run_row
from jsve.tuning._race import better_than as better_than
from jsve.tuning._race import eliminate as eliminate
from jsve.tuning._race import holm as holm
from jsve.tuning._race import paired_difference as paired_difference
from jsve.tuning._study import TuneStudy as TuneStudy
from jsve.tuning._tune import tune as tune
