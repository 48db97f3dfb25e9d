"""jsve.sim: the stand-in front-end. Trajectories, IMU synthesis, a vision model, format-v1 logs.

Physically motivated, not defined through the SVE formulas (docs/simulator.md): EuRoC or procedural
trajectories, EuRoC-grade IMU noise preintegrated per frame, a visibility process degraded by each
disturbance as measured on real frames, and ORB-SLAM3's own state machine deciding each frame.
"""

from jsve.sim._config import SimConfig as SimConfig
from jsve.sim._driving import DrivingConfig as DrivingConfig
from jsve.sim._driving import simulate_sequence as simulate_sequence
from jsve.sim._imu import ImuNoise as ImuNoise
from jsve.sim._imu import dead_reckoning_drift as dead_reckoning_drift
from jsve.sim._imu import frame_bias_estimate as frame_bias_estimate
from jsve.sim._imu import frame_substeps as frame_substeps
from jsve.sim._imu import preintegrate as preintegrate
from jsve.sim._imu import read_imu_stream as read_imu_stream
from jsve.sim._imu import synthesize_imu as synthesize_imu
from jsve.sim._recording import euroc_sequences as euroc_sequences
from jsve.sim._recording import make_recording as make_recording
from jsve.sim._recording import procedural_sequences as procedural_sequences
from jsve.sim._scene import RENDERED_TEXTURE_SCALE as RENDERED_TEXTURE_SCALE
from jsve.sim._scene import Scene as Scene
from jsve.sim._scene import SceneProfile as SceneProfile
from jsve.sim._scene import make_scene as make_scene
from jsve.sim._simulate import settings as settings
from jsve.sim._simulate import simulate_run as simulate_run
from jsve.sim._simulate import simulate_study as simulate_study
from jsve.sim._study import write_study as write_study
from jsve.sim._trajectory import EUROC_SEQUENCES as EUROC_SEQUENCES
from jsve.sim._trajectory import FlightProfile as FlightProfile
from jsve.sim._trajectory import load_euroc_trajectory as load_euroc_trajectory
from jsve.sim._vision import VisionParams as VisionParams
from jsve.sim._vision import degradation as degradation
from jsve.sim._vision import extract as extract
from jsve.sim._vision import level_budgets as level_budgets
