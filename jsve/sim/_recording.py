"""Sequences and their recordings: what every run and setting of a simulated sequence shares.

SequenceSpec                a procedural flight, or a EuRoC sequence from ORB-SLAM3's files
make_recording(spec, seed)  truth, IMU (synthetic or EuRoC's), preintegration and scene texture
generator_key(spec, seed)   what a simulated log is a function of (its `generator` metadata)
seed_key(*parts)            a stable seed sequence from names and numbers
"""

from __future__ import annotations

import functools
import os
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from jsve.io._resume import file_digest, fingerprint
from jsve.sim._config import FRONTEND, SimConfig
from jsve.sim._imu import frame_bias_estimate, frame_substeps, preintegrate, read_imu_stream, synthesize_imu
from jsve.sim._scene import make_scene
from jsve.sim._trajectory import (
    EUROC_CAM0_T_BS,
    EUROC_SEQUENCES,
    Trajectory,
    euroc_file_stem,
    load_euroc_trajectory,
    procedural_trajectory,
    quat_to_matrix,
)


@dataclass(frozen=True)
class SequenceSpec:
    """A sequence to simulate: a procedural flight, or a EuRoC sequence from ORB-SLAM3's files.

    Attributes:
        name: metadata `sequence` ("MH_01", "proc_03").
        euroc_gt: folder of ORB-SLAM3's left-camera ground truth (MH01_GT.txt, ...), for EuRoC.
        timestamps: folder of frame stamp lists (MH01.txt), optional. imu: folder of real imu0
            streams (V101.txt), optional (used with SimConfig.imu_source = "real").
    """

    name: str
    euroc_gt: str | None = None
    timestamps: str | None = None
    imu: str | None = None

    @property
    def procedural(self) -> bool:
        return self.euroc_gt is None


def procedural_sequences(n: int) -> list[SequenceSpec]:
    """n procedural flights named proc_00, proc_01, ..."""
    return [SequenceSpec(f"proc_{i:02d}") for i in range(n)]


def euroc_sequences(names: Sequence[str], euroc_gt: str | os.PathLike) -> list[SequenceSpec]:
    """EuRoC sequences from `euroc_gt` (ORB-SLAM3's EuRoC_left_cam folder); the sibling folders
    `timestamps/` and `imu/` are used where they exist (the layout of ../shared/data/euroc)."""
    gt = Path(euroc_gt)
    if not gt.is_dir():
        raise FileNotFoundError(f"--euroc-gt {gt}: not a folder")
    ts = gt.parent / "timestamps"
    imu = gt.parent / "imu"
    out = []
    for name in names:
        stem = euroc_file_stem(name)
        if not (gt / f"{stem}_GT.txt").is_file():
            raise FileNotFoundError(f"{gt / f'{stem}_GT.txt'}: no ground truth for sequence {name}")
        canonical = next(k for k, v in EUROC_SEQUENCES.items() if v == stem)
        out.append(
            SequenceSpec(
                canonical, str(gt), str(ts) if ts.is_dir() else None, str(imu) if imu.is_dir() else None
            )
        )
    return out


def input_files(spec: SequenceSpec, config: SimConfig = SimConfig()) -> list[Path]:
    """The files make_recording reads for `spec` under `config`: the ground truth and, where used, the
    frame stamp list and the real IMU stream; none for a procedural flight."""
    if spec.euroc_gt is None:  # procedural
        return []
    stem = euroc_file_stem(spec.name)
    files = [Path(spec.euroc_gt) / f"{stem}_GT.txt"]
    for folder, used in ((spec.timestamps, True), (spec.imu, config.imu_source == "real")):
        if used and folder is not None and (Path(folder) / f"{stem}.txt").is_file():
            files.append(Path(folder) / f"{stem}.txt")
    return files


def generator_key(spec: SequenceSpec, seed: int, config: SimConfig = SimConfig()) -> dict:
    """What a simulated log is a function of besides its sequence name, setting and run: the study
    seed, the simulator model (FRONTEND), the IMU source, a fingerprint of the whole SimConfig, and a
    digest of the content of the input files (input_files: "procedural" for a procedural flight).
    Written into every log's metadata as `generator`; write_study resumes a log only under an equal key.
    """
    files = input_files(spec, config)
    return {
        "seed": int(seed),
        "model": FRONTEND,
        "imu_source": config.imu_source,
        "config": fingerprint(asdict(config)),
        "inputs": file_digest(files) if files else "procedural",
    }


@dataclass(frozen=True)
class Recording:
    """What a sequence gives every run and setting: truth, IMU, preintegration and scene.

    Attributes (F frames):
        spec: the sequence. trajectory: the smooth true trajectory. frame_ns: [F] int64.
        t: [F] s since the first frame. p, q, v: [F, 3|4|3] true body pose and velocity (world).
        omega: [F, 3] true body rates, rad/s. r_wc: [F, 3, 3] camera-to-world rotation.
        camera_p: [F, 3] camera centre, m (world): the parallax of monocular initialisation.
        preint_zero, preint_est: (dt, dp, dv, dq) with zero biases (before IMU initialisation) and
            with the estimator's biases (after). scene: the texture process. travelled: [F] m.
        imu_source: where the IMU came from.
    """

    spec: SequenceSpec
    trajectory: Trajectory
    frame_ns: np.ndarray
    t: np.ndarray
    p: np.ndarray
    q: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    r_wc: np.ndarray
    camera_p: np.ndarray
    preint_zero: tuple
    preint_est: tuple
    scene: object
    travelled: np.ndarray
    imu_source: str

    @property
    def n_frames(self) -> int:
        return len(self.frame_ns)


def seed_key(*parts) -> list[int]:
    """A stable integer seed sequence from strings and numbers (crc32; Python's hash() is salted)."""
    out = []
    for part in parts:
        if isinstance(part, str):
            out.append(zlib.crc32(part.encode()))
        elif isinstance(part, float):
            out.append(zlib.crc32(repr(part).encode()))
        else:
            out.append(int(part))
    return out


def make_recording(spec: SequenceSpec, seed: int = 0, config: SimConfig = SimConfig()) -> Recording:
    """Build a sequence's recording (deterministic in seed and name)."""
    rng = np.random.default_rng(seed_key(seed, "recording", spec.name))
    if spec.procedural:
        trajectory = procedural_trajectory(spec.name, rng, config.flight)
    else:
        trajectory = load_euroc_trajectory(spec.name, spec.euroc_gt, timestamps_dir=spec.timestamps)
    imu_rng = np.random.default_rng(seed_key(seed, "imu", spec.name))
    imu = None
    if config.imu_source == "real" and spec.imu is not None:
        path = Path(spec.imu) / f"{euroc_file_stem(spec.name)}.txt"
        if path.is_file():
            imu = read_imu_stream(path)
    if imu is None:
        imu = synthesize_imu(trajectory, imu_rng, config.imu)
    steps = frame_substeps(imu, trajectory.frame_ns)
    bg, ba = frame_bias_estimate(imu, trajectory, window_s=config.bias_window_s)
    t = trajectory.seconds(trajectory.frame_ns)
    p, q = trajectory.pose(t)
    v = trajectory.velocity(t)
    omega = trajectory.angular_velocity(t)
    r_wb = quat_to_matrix(q)
    r_wc = r_wb @ EUROC_CAM0_T_BS[:3, :3]
    scene = make_scene(np.random.default_rng(seed_key(seed, "scene", spec.name)), t, omega, config.scene)
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    return Recording(
        spec=spec,
        trajectory=trajectory,
        frame_ns=trajectory.frame_ns,
        t=t,
        p=p,
        q=q,
        v=v,
        omega=omega,
        r_wc=r_wc,
        camera_p=p + r_wb @ EUROC_CAM0_T_BS[:3, 3],
        preint_zero=preintegrate(steps, np.zeros(3), np.zeros(3)),
        preint_est=preintegrate(steps, bg, ba),
        scene=scene,
        travelled=travelled,
        imu_source=imu.source,
    )


@functools.lru_cache(maxsize=4)
def _cached_recording(spec: SequenceSpec, seed: int, config: SimConfig) -> Recording:
    return make_recording(spec, seed, config)


__all__ = [
    "SequenceSpec",
    "procedural_sequences",
    "euroc_sequences",
    "input_files",
    "generator_key",
    "Recording",
    "seed_key",
    "make_recording",
]
