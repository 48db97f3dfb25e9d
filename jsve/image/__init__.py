"""jsve.image: the image side. Disturbances (OpenCV), disturbed EuRoC datasets, ORB extraction as
ORB-SLAM3 does it, and per-frame measurement of counts, bins and SVE metrics on real frames."""

from jsve.image._datasets import DatasetError as DatasetError
from jsve.image._datasets import disturb_datasets as disturb_datasets
from jsve.image._datasets import format_level as format_level
from jsve.image._disturb import DISTURBANCES as DISTURBANCES
from jsve.image._disturb import disturb_image as disturb_image
from jsve.image._disturb import scale_intrinsics as scale_intrinsics
from jsve.image._measure import Camera as Camera
from jsve.image._measure import FrameCounts as FrameCounts
from jsve.image._measure import measure_datasets as measure_datasets
from jsve.image._measure import measure_frames as measure_frames
from jsve.image._measure import read_image as read_image
from jsve.image._measure import read_sequence as read_sequence
from jsve.image._measure import visibility_table as visibility_table
from jsve.image._orb import OrbSettings as OrbSettings
from jsve.image._orb import extract_orb as extract_orb
