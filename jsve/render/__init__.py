"""jsve.render: EuRoC-format image sequences rendered along real ground-truth trajectories (`jsve render`).

A closed room around the trajectory with furniture that occludes, textured with a mosaic of real
photographs (or a procedural pattern), seen through EuRoC cam0's distorted lens with motion blur,
vignetting, gain changes and noise; optionally cars and pedestrians moving through it, with per-frame
instance masks (PNG and KITTI MOTS); IMU real or synthesised; ground truth in EuRoC's layout. The data
for running the real ORB-SLAM3 front-end (docs/render.md).
"""

from jsve.render._objects import MovingObjects as MovingObjects
from jsve.render._objects import ObjectsConfig as ObjectsConfig
from jsve.render._raster import EUROC_CAM0 as EUROC_CAM0
from jsve.render._raster import CameraRays as CameraRays
from jsve.render._raster import SensorModel as SensorModel
from jsve.render._raster import render_frame as render_frame
from jsve.render._raster import render_frame_and_instances as render_frame_and_instances
from jsve.render._scene import Scene as Scene
from jsve.render._scene import SceneConfig as SceneConfig
from jsve.render._scene import make_scene as make_scene
from jsve.render._sequence import GainModel as GainModel
from jsve.render._sequence import RenderConfig as RenderConfig
from jsve.render._sequence import RenderResult as RenderResult
from jsve.render._sequence import render_sequence as render_sequence
