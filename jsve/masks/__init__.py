"""jsve.masks: dynamic-object masks (Masked ORB-SLAM3). Algorithm 1 on logged keypoints, KITTI MOTS
and PNG masks, masked counts and bins, and Table I (APE statistics of masked vs original runs)."""

from jsve.masks._masks import MotsMasks as MotsMasks
from jsve.masks._masks import PngMasks as PngMasks
from jsve.masks._masks import apply_masks as apply_masks
from jsve.masks._masks import dynamic_keypoints as dynamic_keypoints
from jsve.masks._masks import masked_log as masked_log
from jsve.masks._masks import sve_bin_index as sve_bin_index
from jsve.masks._table_one import PosePair as PosePair
from jsve.masks._table_one import table_one as table_one
from jsve.masks._table_one import to_markdown as to_markdown
