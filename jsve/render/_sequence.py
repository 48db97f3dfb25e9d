"""Rendered EuRoC-format sequences along real ground-truth trajectories (`jsve render`).

    render_sequence(trajectory, timestamps, out, ...)   write DIR/mav0/{cam0,imu0,state_groundtruth_estimate0}

The dataset a EuRoC driver of ORB-SLAM3 (mono_inertial_euroc) reads: cam0 PNGs named by their stamp with
data.csv and sensor.yaml (EuRoC cam0's intrinsics, radial-tangential distortion and T_BS), imu0 at 200 Hz
(the real stream when given, else synthesised from the trajectory with jsve.sim's ADIS16448 model) and
the body ground truth in EuRoC's layout. The trajectory is ORB-SLAM3's EuRoC left-camera ground truth
(evaluation/Ground_truth/EuRoC_left_cam/<SEQ>_GT.txt), loaded by jsve.sim.load_euroc_trajectory: those
files store the conjugate of the camera rotation (docs/render.md verifies it against the real gyro), and
the body pose is T_wb = T_wc inv(T_BS); frames, IMU and ground truth all follow the same smooth spline
through those poses, so the images, the IMU and the ground truth agree.

Deterministic under the seed: the room and texture from (seed, 0), the IMU from (seed, 1), the gain curve
from (seed, 2), each frame's noise from (seed, 3, t_ns), so a frame does not depend on which worker drew
it or on --frames. Resumable: the dataset is built in `OUT.partial/` (each PNG written under a temporary
name and renamed), with the configuration's key in `OUT.partial/jsve_render_key.json`; a re-run with the
same key keeps the frames already there; the manifest `jsve_render.json` is written last and the folder
renamed to OUT, which a re-run then skips (or refuses, when made under another key).
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import dataclasses
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jsve.io import _scheduler, write_bytes, write_json, write_text
from jsve.io._resume import StaleOutputError, differences, file_digest
from jsve.render._objects import ObjectsConfig
from jsve.render._raster import (
    EUROC_CAM0,
    CameraRays,
    SensorModel,
    render_frame_and_instances,
    vignetting_map,
)
from jsve.render._scene import (
    Scene,
    SceneConfig,
    image_files,
    layout,
    load_texture_images,
    make_scene,
    with_objects,
)
from jsve.sim import ImuNoise, load_euroc_trajectory, read_imu_stream, synthesize_imu
from jsve.sim._trajectory import EUROC_CAM0_T_BS, GRAVITY, Trajectory, quat_to_matrix

logger = logging.getLogger(__name__)

MASKS_FOLDER = "masks"
"""mav0/cam0/masks/<t_ns>.png: per frame, the KITTI MOTS object id each pixel sees (16-bit, 0 static)."""

INSTANCES_NAME = "instances.txt"
"""mav0/cam0/instances.txt: the masks as KITTI MOTS instances_txt (frame = index in cam0/data.csv)."""

MANIFEST_NAME = "jsve_render.json"
"""Written last into a finished dataset; its presence marks it complete."""

KEY_NAME = "jsve_render_key.json"
"""The configuration key of a dataset being built (inside OUT.partial/)."""

FORMAT_VERSION = 1
"""Bumped when the same configuration would render different images."""

TEXTURE_IMAGES = 400
"""At most this many photographs of --texture (spread evenly over the sorted files) make the mosaic."""


@dataclass(frozen=True)
class GainModel:
    """Auto-exposure gain per frame: a log-normal Ornstein-Uhlenbeck wander plus sudden steps.

    Attributes:
        sigma: stationary standard deviation of the log gain. tau_s: its correlation time, s.
        steps_per_min: mean rate of sudden steps (an auto-exposure re-adjusting). step: their size range in
            log gain (either sign). low, high: the gain's clip range.
    """

    sigma: float = 0.12
    tau_s: float = 3.0
    steps_per_min: float = 4.0
    step: tuple[float, float] = (0.08, 0.2)
    low: float = 0.6
    high: float = 1.5


@dataclass(frozen=True)
class RenderConfig:
    """Everything a rendered sequence is a function of, besides its input files."""

    seed: int = 0
    scene: SceneConfig = SceneConfig()
    sensor: SensorModel = SensorModel()
    gain: GainModel = GainModel()
    imu_noise: ImuNoise = ImuNoise()
    png_compression: int = 1
    objects: ObjectsConfig = ObjectsConfig()


@dataclass(frozen=True)
class RenderResult:
    """What render_sequence did: the dataset folder, frames rendered now and before, seconds, the manifest."""

    out: Path
    status: str  # "written", "resumed" or "complete" (already there)
    rendered: int
    kept: int
    seconds: float
    manifest: dict


# --------------------------------------------------------------------------------------------------
# Inputs


def sequence_stem(trajectory: str | os.PathLike) -> str:
    """'V101' from '.../V101_GT.txt' (ORB-SLAM3's EuRoC_left_cam file names)."""
    name = Path(trajectory).name
    if not name.endswith("_GT.txt"):
        raise ValueError(
            f"{trajectory}: expected one of ORB-SLAM3's EuRoC left-camera ground-truth files, named "
            "<SEQ>_GT.txt (MH01_GT.txt ... V203_GT.txt)"
        )
    return name[: -len("_GT.txt")]


def load_trajectory(path: str | os.PathLike) -> Trajectory:
    """The body trajectory of an ORB-SLAM3 EuRoC left-camera ground-truth file (jsve.sim)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such trajectory file")
    return load_euroc_trajectory(sequence_stem(path), path.parent)


def read_stamps(path: str | os.PathLike) -> np.ndarray:
    """Frame stamps, ns: one per line (ORB-SLAM3's EuRoC_TimeStamps) or the first field of a EuRoC
    data.csv; '#' lines skipped."""
    stamps = []
    with open(path) as stream:
        for line_no, line in enumerate(stream, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                stamps.append(int(line.split(",")[0].split(".")[0]))
            except ValueError:
                raise ValueError(f"{path}:{line_no}: expected a stamp in ns, got {line!r}") from None
    out = np.array(stamps, np.int64)
    if len(out) == 0 or np.any(np.diff(out) <= 0):
        raise ValueError(f"{path}: frame stamps must be increasing (and there must be some)")
    return out


def frame_range(spec: str | None, n: int) -> slice:
    """'A:B' (Python slice bounds, either may be empty) -> slice over n frames."""
    if not spec:
        return slice(0, n)
    try:
        start, stop = (int(v) if v else None for v in spec.split(":"))
    except ValueError:
        raise ValueError(f"--frames must be A:B (e.g. 0:600), got {spec!r}") from None
    return slice(*slice(start, stop).indices(n)[:2])


def camera_poses(trajectory: Trajectory, t_ns: np.ndarray, offsets_s: np.ndarray):
    """Camera (cam0) poses (r_wc [..., 3, 3], p_wc [..., 3]) at t_ns + offsets (s), world frame, m."""
    t = trajectory.seconds(np.asarray(t_ns, np.int64))[..., None] + offsets_s
    p_wb, q_wb = trajectory.pose(t.ravel())
    r_wb = np.asarray(quat_to_matrix(q_wb))
    r_wc = r_wb @ EUROC_CAM0_T_BS[:3, :3]
    p_wc = p_wb + r_wb @ EUROC_CAM0_T_BS[:3, 3]
    return r_wc.reshape(*t.shape, 3, 3), p_wc.reshape(*t.shape, 3)


def subframe_offsets(
    trajectory: Trajectory, t_ns: int, sensor: SensorModel, depth_m: float = 1.5
) -> np.ndarray:
    """Sub-exposure instants (s from the stamp) spaced so the image moves about sensor.subframe_px between
    them: 1 for a still camera, an odd number up to sensor.max_subframes (rounded up to odd).

    The image motion over the exposure is bounded by the rotation angle times the focal length plus the
    translation over a near depth (depth_m) times it.
    """
    half = sensor.exposure_s / 2
    r, p = camera_poses(trajectory, np.array(t_ns), np.array([-half, half]))
    cos_angle = (np.trace(r[0].T @ r[1]) - 1) / 2
    angle = math.acos(float(np.clip(cos_angle, -1.0, 1.0)))
    blur_px = EUROC_CAM0.fx * (angle + float(np.linalg.norm(p[1] - p[0])) / depth_m)
    n = int(np.clip(math.ceil(blur_px / sensor.subframe_px) + 1, 1, sensor.max_subframes))
    n += 1 - n % 2  # odd: the middle one is at the stamp, where the visible surfaces are cast
    return np.zeros(1) if n == 1 else np.linspace(-half, half, n)


def gain_curve(t_ns: np.ndarray, model: GainModel, rng: np.random.Generator) -> np.ndarray:
    """Gain of every frame (module GainModel), from a seeded generator."""
    t = (np.asarray(t_ns, np.int64) - t_ns[0]) / 1e9
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / model.tau_s)
    noise = rng.standard_normal(len(t))
    jumps = rng.random(len(t)) < model.steps_per_min / 60.0 * dt
    sizes = rng.uniform(*model.step, len(t)) * rng.choice([-1.0, 1.0], len(t))
    log_gain = np.empty(len(t))
    x = rng.normal(0.0, model.sigma)
    for k in range(len(t)):  # a scalar recurrence over a few thousand frames, once per sequence
        x = a[k] * x + model.sigma * math.sqrt(1 - a[k] ** 2) * noise[k] + (sizes[k] if jumps[k] else 0.0)
        log_gain[k] = x
    return np.clip(np.exp(log_gain), model.low, model.high)


# --------------------------------------------------------------------------------------------------
# Workers


@dataclass(frozen=True)
class _Setup:
    """What a worker needs to build its own copy of the scene (cheaper than shipping the atlas)."""

    trajectory: str
    texture: str | None
    config: RenderConfig


_STATE: dict = {}


def _scene_of(setup: _Setup, trajectory: Trajectory) -> Scene:
    textures = load_texture_images(setup.texture, TEXTURE_IMAGES) if setup.texture else None
    r, p = camera_poses(trajectory, trajectory.frame_ns, np.zeros(1))
    rng = np.random.default_rng([setup.config.seed, 0])
    source = f"mosaic of {len(textures)} images from {setup.texture}" if textures else ""
    return make_scene(p[:, 0], rng, textures, setup.config.scene, texture_source=source,
                      objects=setup.config.objects, objects_rng=_objects_rng(setup.config))  # fmt: skip


def _objects_rng(config: RenderConfig) -> np.random.Generator:
    """The generator that places and textures the dynamic objects: (seed, 4)."""
    return np.random.default_rng([config.seed, 4])


def _scene_facts(setup: _Setup, trajectory: Trajectory) -> dict:
    """The manifest's facts about the scene, without building its texture (the workers built theirs):
    make_scene draws the layout first from the same generator."""
    r, p = camera_poses(trajectory, trajectory.frame_ns, np.zeros(1))
    lo, hi = layout(p[:, 0], np.random.default_rng([setup.config.seed, 0]), setup.config.scene)
    if setup.texture:
        n_images = min(len(image_files(setup.texture)), TEXTURE_IMAGES)
        source = f"mosaic of {n_images} images from {setup.texture}"
    else:
        source = "procedural (no --texture given)"
    facts = {
        "texture": source,
        "room_lo_m": lo[0].round(3).tolist(),
        "room_hi_m": hi[0].round(3).tolist(),
        "furniture_boxes": len(lo) - 1,
    }
    if setup.config.objects.count:
        placed = with_objects(p[:, 0], lo, hi, _objects_rng(setup.config), setup.config.objects)[2]
        facts["objects"] = placed.describe()
    return facts


_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3  # glibc's malloc.h


def _keep_freed_memory() -> None:
    """glibc: serve a frame's many short-lived arrays (1-3 MB each) from the heap and keep what is freed.

    By default glibc maps each such array afresh and unmaps it when freed, and every page of it faults in
    again on first touch: about a quarter of a frame's time (measured, docs/render.md). A no-op elsewhere.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)  # glibc's largest; the texture atlas is still mapped
        libc.mallopt(_M_TRIM_THRESHOLD, 256 << 20)
        libc.mallopt(_M_TOP_PAD, 32 << 20)
    except (OSError, AttributeError):  # another C library
        pass


def _init_worker(setup: _Setup) -> None:
    cv2.setNumThreads(1)  # one process per core; OpenCV's own threads would oversubscribe
    _keep_freed_memory()
    trajectory = load_trajectory(setup.trajectory)
    rays = CameraRays.of(EUROC_CAM0)
    _STATE.update(
        setup=setup,
        trajectory=trajectory,
        scene=_scene_of(setup, trajectory),
        rays=rays,
        vignette=vignetting_map(EUROC_CAM0, setup.config.sensor.vignetting),
    )


def _png_params(compression: int) -> list[int]:
    """cv2.imencode's PNG options: the 'sub' filter and Huffman coding only take a quarter of the default's
    time on noisy frames and give smaller files (203 against 221 kB at level 1, measured)."""
    return [cv2.IMWRITE_PNG_COMPRESSION, compression, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB,
            cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]  # fmt: skip


def _render_chunk(jobs: Sequence[tuple[int, float, str]]) -> int:
    """Render and write frames (t_ns, gain, path); returns how many."""
    setup: _Setup = _STATE["setup"]
    config = setup.config
    trajectory: Trajectory = _STATE["trajectory"]
    for t_ns, gain, path in jobs:
        offsets = subframe_offsets(trajectory, t_ns, config.sensor)
        r_wc, p_wc = camera_poses(trajectory, np.array(t_ns), offsets)
        rng = np.random.default_rng([config.seed, 3, t_ns])
        scene = _STATE["scene"].at(float(trajectory.seconds(np.array(t_ns))))
        image, instances = render_frame_and_instances(scene, _STATE["rays"], (r_wc, p_wc), gain, rng,
                                                      config.sensor, _STATE["vignette"])  # fmt: skip
        if scene.objects:  # the mask first: the image marks the frame done
            _write_png(mask_path(path), instances, config.png_compression)
        _write_png(path, image, config.png_compression)
    return len(jobs)


def _write_png(path: str | os.PathLike, image: np.ndarray, compression: int) -> None:
    ok, png = cv2.imencode(".png", image, _png_params(compression))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    write_bytes(path, png.tobytes())


def mask_path(image: str | os.PathLike) -> Path:
    """DATASET/mav0/cam0/masks/<t_ns>.png, the instance map of DATASET/mav0/cam0/data/<t_ns>.png."""
    image = Path(image)
    return image.parent.parent / MASKS_FOLDER / image.name


# --------------------------------------------------------------------------------------------------
# Text files


def _matrix_yaml(m: np.ndarray) -> str:
    rows = [", ".join(repr(float(v)) for v in row) for row in m]
    return "  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def cam0_sensor_yaml(rate_hz: float = 20.0) -> str:
    """mav0/cam0/sensor.yaml in EuRoC's layout, with EuRoC cam0's calibration."""
    c = EUROC_CAM0
    return (
        "%YAML:1.0\n"
        "# Rendered by jsve render: EuRoC cam0's calibration (ORB-SLAM3 v1.0 EuRoC.yaml, Camera1.*).\n"
        "sensor_type: camera\ncomment: jsve render, EuRoC cam0 model\n\n"
        "# Sensor extrinsics wrt. the body-frame.\nT_BS:\n" + _matrix_yaml(EUROC_CAM0_T_BS) + "\n"
        f"rate_hz: {rate_hz:g}\nresolution: [{c.width}, {c.height}]\ncamera_model: pinhole\n"
        f"intrinsics: [{c.fx!r}, {c.fy!r}, {c.cx!r}, {c.cy!r}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(repr(float(v)) for v in c.distortion)}]\n"
    )


def imu0_sensor_yaml(noise: ImuNoise, synthetic: bool) -> str:
    """mav0/imu0/sensor.yaml in EuRoC's layout (ADIS16448 datasheet noise)."""
    source = "synthesised by jsve render (jsve.sim ADIS16448 model)" if synthetic else "the real EuRoC stream"
    return (
        "%YAML:1.0\nsensor_type: imu\n"
        f"comment: {source}\n\n"
        "# Sensor extrinsics wrt. the body-frame.\nT_BS:\n" + _matrix_yaml(np.eye(4)) + "rate_hz: 200\n\n"
        f"gyroscope_noise_density: {noise.gyro_density!r}     # [ rad / s / sqrt(Hz) ]\n"
        f"gyroscope_random_walk: {noise.gyro_walk!r}       # [ rad / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_noise_density: {noise.accel_density!r}  # [ m / s^2 / sqrt(Hz) ]\n"
        f"accelerometer_random_walk: {noise.accel_walk!r}    # [ m / s^3 / sqrt(Hz) ]\n"
    )


def _csv(header: str, t_ns: np.ndarray, values: np.ndarray) -> str:
    lines = [header]
    lines += [f"{int(t)}," + ",".join(f"{v:.17g}" for v in row) for t, row in zip(t_ns, values, strict=True)]
    return "\n".join(lines) + "\n"


IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


def _write_side_files(
    partial: Path, trajectory: Trajectory, frames: np.ndarray, imu_path: str | None, config: RenderConfig
) -> dict:
    """cam0/data.csv and sensor.yaml, imu0, state_groundtruth_estimate0; returns facts for the manifest."""
    mav0 = partial / "mav0"
    write_text(mav0 / "cam0" / "data.csv",
               "#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in frames))  # fmt: skip
    rate = 1e9 / float(np.median(np.diff(frames))) if len(frames) > 1 else 20.0
    write_text(mav0 / "cam0" / "sensor.yaml", cam0_sensor_yaml(round(rate, 3)))
    if imu_path:
        imu = read_imu_stream(imu_path)
        if imu.t_ns[0] > frames[0] or imu.t_ns[-1] < frames[-1]:
            raise ValueError(f"{imu_path}: the IMU stream does not cover the frames")
    else:
        imu = synthesize_imu(
            trajectory, np.random.default_rng([config.seed, 1]), config.imu_noise, gravity=GRAVITY
        )
    write_text(
        mav0 / "imu0" / "data.csv", _csv(IMU_HEADER, imu.t_ns, np.concatenate([imu.gyro, imu.accel], 1))
    )
    write_text(mav0 / "imu0" / "sensor.yaml", imu0_sensor_yaml(config.imu_noise, synthetic=not imu_path))
    # Body ground truth at the IMU stamps inside the trajectory's span.
    inside = (imu.t_ns >= trajectory.frame_ns[0]) & (imu.t_ns <= trajectory.frame_ns[-1])
    t_ns = imu.t_ns[inside]
    t = trajectory.seconds(t_ns)
    p, q = trajectory.pose(t)
    v = trajectory.velocity(t)
    if imu.bias_gyro is not None and imu.bias_accel is not None:
        bias = np.concatenate([imu.bias_gyro[inside], imu.bias_accel[inside]], 1)
    else:
        bias = np.zeros((len(t_ns), 6))  # the real stream's biases are not known here
    gt = np.concatenate([p, q, v, bias], 1)
    write_text(mav0 / "state_groundtruth_estimate0" / "data.csv", _csv(GT_HEADER, t_ns, gt))
    return {"imu": imu.source, "imu_samples": len(imu.t_ns), "ground_truth_rows": len(t_ns)}


def write_instances(cam0: Path, frames: np.ndarray) -> dict:
    """cam0/instances.txt, the masks of cam0/masks/ as KITTI MOTS instances_txt (frame: the index in
    cam0/data.csv; COCO RLE by pycocotools); returns how much of the image the objects cover.

    Returns:
        {"instances_txt", "mask_share_mean", "mask_share_p95", "mask_share_max" (share of the image's
        pixels on an object, over all frames), "frames_with_objects" (share of frames)}.
    """
    from pycocotools import mask as mask_util

    lines, share = [], np.zeros(len(frames))
    for k, t in enumerate(frames):
        path = cam0 / MASKS_FOLDER / f"{t}.png"
        instances = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if instances is None:
            raise FileNotFoundError(f"{path}: the frame's mask is missing or unreadable")
        share[k] = np.count_nonzero(instances) / instances.size
        for obj_id in np.unique(instances[instances > 0]):
            rle = mask_util.encode(np.asfortranarray(instances == obj_id, dtype=np.uint8))
            h, w = rle["size"]
            lines.append(f"{k} {obj_id} {obj_id // 1000} {h} {w} {rle['counts'].decode('ascii')}\n")
    write_text(cam0 / INSTANCES_NAME, "".join(lines))
    return {
        "instances_txt": f"mav0/cam0/{INSTANCES_NAME}",
        "mask_share_mean": round(float(share.mean()), 4),
        "mask_share_p95": round(float(np.percentile(share, 95)), 4),
        "mask_share_max": round(float(share.max()), 4),
        "frames_with_objects": round(float(np.mean(share > 0)), 4),
    }


# --------------------------------------------------------------------------------------------------
# The sequence


def _key(trajectory: str, timestamps: str, imu: str | None, texture: str | None, frames: np.ndarray,
         config: RenderConfig) -> dict:  # fmt: skip
    texture_files = image_files(texture) if texture else []
    return {
        "format": FORMAT_VERSION,
        "trajectory": file_digest([trajectory]),
        "timestamps": file_digest([timestamps]),
        "imu": file_digest([imu]) if imu else None,
        "texture": file_digest(texture_files) if texture_files else None,
        "frames": [int(frames[0]), int(frames[-1]), len(frames)],
        "config": _config_key(config),
    }


def _config_key(config: RenderConfig) -> dict:
    """The configuration as JSON; a scene without objects keeps the key it had before objects existed, so
    datasets rendered then stay complete."""
    key = json.loads(json.dumps(dataclasses.asdict(config)))
    if not config.objects.count:
        del key["objects"]
    return key


def _frames(traj: Trajectory, trajectory: str, timestamps: str | os.PathLike, frames: str | None):
    """(stamps inside the trajectory's span, those --frames selects), ns."""
    stamps = read_stamps(timestamps)
    inside = stamps[(stamps >= traj.frame_ns[0]) & (stamps <= traj.frame_ns[-1])]
    if len(inside) == 0:
        raise ValueError(f"{timestamps}: no frame stamp inside the trajectory's span ({trajectory})")
    selected = inside[frame_range(frames, len(inside))]
    if len(selected) == 0:
        raise ValueError(f"--frames {frames} selects no frame of {len(inside)}")
    return inside, selected


PNG_BYTES_PER_PIXEL = 0.6
"""Bytes of a rendered frame's PNG per pixel (png_compression 1; the sensor noise leaves little to
compress): measured 0.57 (207 kB of EuRoC's 752 x 480) with the procedural texture, for sequence_size."""

SIDE_BYTES_PER_SECOND = 200 * 495
"""Bytes of imu0/data.csv and state_groundtruth_estimate0/data.csv per second of the trajectory: 200 Hz
rows of about 144 and 351 bytes (measured on V1_01), for sequence_size."""


def sequence_size(
    trajectory: str | os.PathLike, timestamps: str | os.PathLike, frames: str | None = None
) -> tuple[int, float, float]:
    """What render_sequence would write, before it renders: (frames, estimated bytes of their PNGs
    (PNG_BYTES_PER_PIXEL), of the IMU and ground-truth files over the trajectory's whole span
    (SIDE_BYTES_PER_SECOND)). Arguments as render_sequence; raises as it does."""
    trajectory = os.fspath(trajectory)
    traj = load_trajectory(trajectory)
    _, selected = _frames(traj, trajectory, timestamps, frames)
    images = len(selected) * EUROC_CAM0.width * EUROC_CAM0.height * PNG_BYTES_PER_PIXEL
    span_s = (int(traj.frame_ns[-1]) - int(traj.frame_ns[0])) / 1e9
    return len(selected), float(images), span_s * SIDE_BYTES_PER_SECOND


def render_sequence(
    trajectory: str | os.PathLike,
    timestamps: str | os.PathLike,
    out: str | os.PathLike,
    *,
    imu: str | os.PathLike | None = None,
    texture: str | os.PathLike | None = None,
    config: RenderConfig = RenderConfig(),
    frames: str | None = None,
    workers: int = 2,
    progress: bool = True,
    force: bool = False,
    chunk: int = 8,
    scheduler: str | None = None,
) -> RenderResult:
    """Render a EuRoC-format sequence along a ground-truth trajectory (module docstring).

    Arguments:
        trajectory: ORB-SLAM3's EuRoC left-camera ground truth, <SEQ>_GT.txt.
        timestamps: frame stamps (ns, one per line); those outside the trajectory's span are dropped.
        out: the dataset folder to write (OUT/mav0/...).
        imu: a real EuRoC imu0 CSV to copy (it must cover the frames); None synthesises one.
        texture: a folder of photographs for the mosaic texture; None: a procedural texture.
        frames: 'A:B', a slice of the frames kept after dropping those outside the trajectory.
        workers: processes rendering frames, where `scheduler` says (jsve.io._scheduler: "local", the
            default, an embedded Dask LocalCluster; "processes", a process pool; or a Dask scheduler's
            address, whose workers must see the inputs and OUT under the same absolute paths); one
            worker renders in this process. force: replace an OUT made under another configuration.
    Returns:
        RenderResult. Raises StaleOutputError when OUT holds another configuration's dataset (and not force).
    """
    start_time = time.perf_counter()
    scheduler = _scheduler.check_scheduler(scheduler)  # a wrong value fails before any work
    trajectory, timestamps = os.fspath(trajectory), os.fspath(timestamps)
    imu_path = os.fspath(imu) if imu else None
    texture_dir = os.fspath(texture) if texture else None
    out = Path(out)
    traj = load_trajectory(trajectory)
    inside, selected = _frames(traj, trajectory, timestamps, frames)
    key = _key(trajectory, timestamps, imu_path, texture_dir, selected, config)

    manifest_path = out / MANIFEST_NAME
    if manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text())
        if manifest.get("key") == key:
            return RenderResult(out, "complete", 0, len(selected), time.perf_counter() - start_time, manifest)
        if not force:
            raise StaleOutputError(out, differences(manifest.get("key", {}), key))
    elif out.exists() and any(out.iterdir()) and not force:
        raise StaleOutputError(out, "a non-empty folder without a jsve render manifest")

    setup = _Setup(trajectory, texture_dir, config)
    scene_facts = _scene_facts(setup, traj)  # places the objects: one that finds no path fails here
    partial = out.with_name(out.name + ".partial")
    key_path = partial / KEY_NAME
    if partial.exists() and not (key_path.is_file() and json.loads(key_path.read_text()) == key):
        logger.info("discarding %s (another configuration)", partial)
        shutil.rmtree(partial)
    status = "resumed" if partial.exists() else "written"
    (partial / "mav0" / "cam0" / "data").mkdir(parents=True, exist_ok=True)
    if config.objects.count:
        (partial / "mav0" / "cam0" / MASKS_FOLDER).mkdir(exist_ok=True)
    write_json(key_path, key)

    gains = gain_curve(inside, config.gain, np.random.default_rng([config.seed, 2]))
    gain_of = dict(zip(inside.tolist(), gains.tolist(), strict=True))  # the curve of the whole sequence
    data = partial / "mav0" / "cam0" / "data"
    todo = [
        (int(t), gain_of[int(t)], str(data / f"{t}.png"))
        for t in selected
        if not (
            (data / f"{t}.png").is_file()
            and (not config.objects.count or mask_path(data / f"{t}.png").is_file())
        )
    ]
    kept = len(selected) - len(todo)
    render_start = time.perf_counter()
    _run(setup, todo, workers, progress, chunk, scheduler)
    render_s = time.perf_counter() - render_start

    facts = _write_side_files(partial, traj, selected, imu_path, config)
    if config.objects.count:
        facts["masks"] = write_instances(partial / "mav0" / "cam0", selected)
    manifest = {
        "key": key,
        "trajectory": trajectory,
        "timestamps": timestamps,
        "frames": len(selected),
        "first_ns": int(selected[0]),
        "last_ns": int(selected[-1]),
        **scene_facts,
        "rendered_now": len(todo),
        "render_seconds": round(render_s, 2),
        "frames_per_second": round(len(todo) / render_s, 2) if todo and render_s > 0 else None,
        "workers": workers,
        **facts,
    }
    write_json(partial / MANIFEST_NAME, manifest)
    key_path.unlink()
    if out.exists():
        shutil.rmtree(out)
    os.replace(partial, out)
    return RenderResult(out, status, len(todo), kept, time.perf_counter() - start_time, manifest)


def _run(setup: _Setup, todo: list, workers: int, progress: bool, chunk: int, scheduler: str) -> None:
    from tqdm.auto import tqdm

    chunks = [todo[i : i + chunk] for i in range(0, len(todo), chunk)]
    with tqdm(total=len(todo), desc="render", unit="frame", disable=not progress) as bar:
        if _scheduler.in_process(workers, scheduler, len(chunks)):
            if _STATE.get("setup") != setup:
                _init_worker(setup)
            for c in chunks:
                bar.update(_render_chunk(c))
            return
        # Absolute paths: a cluster's worker does not share this process's working folder.
        absolute = _scheduler.absolute
        texture = absolute(setup.texture) if setup.texture else None
        setup = dataclasses.replace(setup, trajectory=absolute(setup.trajectory), texture=texture)
        chunks = [[(t_ns, gain, absolute(path)) for t_ns, gain, path in c] for c in chunks]
        with _scheduler.executor(
            min(workers, len(chunks)), scheduler, initializer=_init_worker, initargs=(setup,)
        ) as pool:
            futures = [pool.submit(_render_chunk, c) for c in chunks]
            for future in concurrent.futures.as_completed(futures):
                bar.update(future.result())
