"""Ground truth for tracking logs: read a trajectory file, associate its poses with a run's frames.

EuRoC, TUM and KITTI files are read with evo's file_interface (through jsve.io._trajectories); their
stamps are parsed from the text as exact int64 nanoseconds. A frame takes the pose at its t_ns,
interpolated (linear in position, slerp in rotation) between samples less than `max_gap_ns` apart; frames
left without ground truth get NaN in all seven gt_* columns (docs/log-format.md, "Ground truth").

    load_ground_truth(file, fmt)         stamps, positions, quaternions of a file (cached per file version)
    associate_ground_truth(run, file)    gt_* columns of a run from a file
    GroundTruth(file, ...)               a file and its association settings (read_log, read_logs, ingest)
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from functools import lru_cache

import numpy as np
import pandas as pd

from jsve.io import _schema as schema
from jsve.io._errors import shorten
from jsve.io._schema import RunLog
from jsve.io._trajectories import TRAJECTORY_FORMATS, check_poses, evo_reader

# The log reader's logger: users configure one name for the warnings of reading logs, and the worker
# processes of jsve.io._ingest forward what is logged there.
logger = logging.getLogger(__name__)

GT_FORMATS = TRAJECTORY_FORMATS
"""Ground-truth file formats accepted by `associate_ground_truth`: the trajectory formats."""

DEFAULT_MAX_GAP_NS = 200_000_000
"""Default largest gap (ns) between two ground-truth samples that a frame may be interpolated across.

0.2 s covers EuRoC's 200 Hz state estimate and ORB-SLAM3's 20 Hz left-camera files (50 ms) and KITTI's
10 Hz poses (~104 ms), and leaves frames in genuine ground-truth dropouts without ground truth."""


@dataclass(frozen=True)
class GroundTruth:
    """A ground-truth trajectory file and how to associate it with logs (see `associate_ground_truth`).

    Attributes:
        path: the file.
        fmt: "euroc" (CSV, int ns stamps, p, q wxyz), "tum" (s stamps, p, q xyzw) or "kitti" (3x4 poses).
        kitti_times: KITTI times file (s, one per pose); None associates KITTI poses by frame index.
        max_gap_ns: frames are only given ground truth between samples less than this apart (ns).
        interpolate: linear in position and slerp in rotation; False takes the nearer sample.
    """

    path: str
    fmt: str = "euroc"
    kitti_times: str | None = None
    max_gap_ns: int = DEFAULT_MAX_GAP_NS
    interpolate: bool = True

    def __post_init__(self):
        object.__setattr__(self, "path", os.fspath(self.path))
        if self.kitti_times is not None:
            object.__setattr__(self, "kitti_times", os.fspath(self.kitti_times))
        _check_gt_args(self.fmt, self.kitti_times, self.max_gap_ns)


GroundTruthSpec = GroundTruth | str | os.PathLike | Mapping[str, GroundTruth | str | os.PathLike]
"""What `read_log` / `read_logs` / `ingest` accept as `ground_truth`: one GroundTruth (or a path, read
as EuRoC) for every log, or a mapping from metadata `sequence` to one."""


def _check_gt_args(fmt, kitti_times, max_gap_ns) -> None:
    if fmt not in GT_FORMATS:
        raise ValueError(f"fmt must be one of {GT_FORMATS}, got {fmt!r}")
    if kitti_times is not None and fmt != "kitti":
        raise ValueError(f"kitti_times is only used with fmt='kitti', got fmt={fmt!r}")
    if not max_gap_ns > 0:
        raise ValueError(f"max_gap_ns must be positive (nanoseconds), got {max_gap_ns!r}")


@dataclass(frozen=True)
class _Trajectory:
    stamps: np.ndarray | None  # int64 ns, strictly increasing; None for KITTI without times
    p: np.ndarray  # [n, 3] metres
    q: np.ndarray  # [n, 4] unit wxyz


def _decimal_ns(text: str, exponent: int) -> int:
    """Exact integer nanoseconds of a decimal string in units of 10^-exponent... i.e. value * 10^exponent."""
    d = Decimal(text)
    if not d.is_finite():
        raise InvalidOperation
    return int(d.scaleb(exponent).to_integral_value(rounding=ROUND_HALF_EVEN))


def _read_stamps_ns(path: str, delimiter: str | None, exponent: int) -> np.ndarray:
    """First field of every non-comment line as int64 ns (parsed from the text: evo's float seconds
    lose ~200 ns at 1.4e9 s). Comment and skipping rules follow evo's csv_read_matrix."""
    stamps = []
    with open(path, encoding="utf-8-sig") as f:
        try:
            for lineno, line in enumerate(f, start=1):
                if line.startswith("#") or not line.strip():
                    continue
                text = line.strip().split(delimiter)[0]
                try:
                    stamps.append(_decimal_ns(text, exponent))
                except (InvalidOperation, ValueError):
                    reason = f"timestamp '{shorten(text)}' is not a number"
                    raise ValueError(f"{path}:{lineno}: {reason}") from None
        except UnicodeDecodeError as e:
            raise ValueError(f"{path}: not a readable times file: {_not_text(e)}") from None
    return np.asarray(stamps, dtype=np.int64)


def _not_text(error: UnicodeDecodeError) -> str:
    return f"not UTF-8 text (a byte {error.object[error.start]:#04x})"


def _unit_quaternions(q: np.ndarray) -> np.ndarray:
    # check_poses has refused norms off by more than ROTATION_TOLERANCE; files store ~10 digits, and
    # normalising moves their values by < 1e-9.
    return q / np.linalg.norm(q, axis=1)[:, None]


def _file_key(path: str | None):
    if path is None:
        return None
    st = os.stat(path)
    return (os.path.abspath(path), st.st_mtime_ns, st.st_size)


def load_ground_truth(
    gt_path: str | os.PathLike, fmt: str = "euroc", *, kitti_times: str | os.PathLike | None = None
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """Read a ground-truth trajectory: poses through evo's file_interface, stamps as exact int64 ns.

    Arguments:
        gt_path: EuRoC CSV (state_groundtruth_estimate0/data.csv or ORB-SLAM3's *_GT.txt; stamps in ns,
            a trailing '.000...' accepted), TUM (stamps in s) or KITTI poses (no stamps).
        fmt: "euroc", "tum" or "kitti".
        kitti_times: KITTI times file (seconds, one line per pose).

    Returns:
        (stamps int64 ns [n] or None for KITTI without times, positions [n, 3] in metres,
        quaternions [n, 4] wxyz normalised). Arrays are read-only and cached per file version.
    """
    _check_gt_args(fmt, kitti_times, 1)
    gt_path = os.fspath(gt_path)
    kitti_times = None if kitti_times is None else os.fspath(kitti_times)
    traj = _load_cached(gt_path, fmt, kitti_times, _file_key(gt_path), _file_key(kitti_times))
    return traj.stamps, traj.p, traj.q


@lru_cache(maxsize=32)
def _load_cached(gt_path, fmt, kitti_times, _key, _times_key) -> _Trajectory:
    from evo.tools import file_interface  # 0.4 s import; only when ground truth is used

    try:
        evo_traj = evo_reader(fmt)(gt_path)
    except file_interface.FileInterfaceException as e:
        raise ValueError(f"{gt_path}: not a readable {fmt} ground-truth file: {e}") from None
    except UnicodeDecodeError as e:  # evo's message names no file
        raise ValueError(f"{gt_path}: not a readable {fmt} ground-truth file: {_not_text(e)}") from None
    # NaN, inf, values float32 cannot hold, zero or non-unit quaternions, KITTI rotations that are not
    # rotations: refused with line and column (TrajectoryFileError, a ValueError).
    check_poses(evo_traj, gt_path, fmt)
    if fmt == "euroc":
        stamps = _read_stamps_ns(gt_path, ",", 0)
    elif fmt == "tum":
        stamps = _read_stamps_ns(gt_path, None, 9)
    else:
        stamps = None if kitti_times is None else _read_stamps_ns(kitti_times, None, 9)
    p = np.array(evo_traj.positions_xyz, dtype=np.float64)
    q = _unit_quaternions(np.array(evo_traj.orientations_quat_wxyz, dtype=np.float64))
    if stamps is not None:
        source = kitti_times if fmt == "kitti" else gt_path
        if len(stamps) != len(p):
            raise ValueError(f"{source}: {len(stamps)} timestamps for {len(p)} poses in {gt_path}")
        step = np.diff(stamps)
        if (step <= 0).any():
            k = int(np.argmax(step <= 0)) + 1
            raise ValueError(f"{source}: timestamps not strictly increasing at pose {k} ({stamps[k]} ns)")
    for a in (p, q) + (() if stamps is None else (stamps,)):
        a.setflags(write=False)
    return _Trajectory(stamps, p, q)


def _slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit wxyz quaternions, row-wise, along the shorter arc."""
    sign = np.where(np.sum(q0 * q1, axis=1) < 0.0, -1.0, 1.0)
    q1 = q1 * sign[:, None]
    # Angle between the 4-vectors via atan2: accurate near 0, unlike arccos of the dot product.
    omega = 2.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=1), np.linalg.norm(q1 + q0, axis=1))
    sin_omega = np.sin(omega)
    small = sin_omega < 1e-9
    safe = np.where(small, 1.0, sin_omega)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * omega) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * omega) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _associate_by_time(stamps, p_gt, q_gt, t, max_gap_ns: int, interpolate: bool):
    """Ground truth at frame times t (int64 ns); NaN where t is outside the span or in a gap."""
    n, m = len(t), len(stamps)
    p = np.full((n, 3), np.nan)
    q = np.full((n, 4), np.nan)
    j = np.searchsorted(stamps, t, side="left")  # stamps[j-1] < t <= stamps[j]
    jc = np.minimum(j, m - 1)
    exact = (j < m) & (stamps[jc] == t)
    p[exact] = p_gt[jc[exact]]
    q[exact] = q_gt[jc[exact]]
    lo, hi = np.clip(j - 1, 0, m - 1), jc
    gap = stamps[hi] - stamps[lo]
    between = ~exact & (j > 0) & (j < m) & (gap < max_gap_ns)
    if between.any():
        lo, hi = lo[between], hi[between]
        # Differences of int64 stamps are exact in float64 (< 2^53 ns).
        alpha = (t[between] - stamps[lo]).astype(np.float64) / (stamps[hi] - stamps[lo]).astype(np.float64)
        if interpolate:
            p[between] = p_gt[lo] + alpha[:, None] * (p_gt[hi] - p_gt[lo])
            q[between] = _slerp(q_gt[lo], q_gt[hi], alpha)
        else:
            nearest = np.where(alpha <= 0.5, lo, hi)
            p[between] = p_gt[nearest]
            q[between] = q_gt[nearest]
    return p, q


def associate_ground_truth(
    run: RunLog,
    gt_path: str | os.PathLike,
    fmt: str = "euroc",
    *,
    kitti_times: str | os.PathLike | None = None,
    max_gap_ns: int = DEFAULT_MAX_GAP_NS,
    interpolate: bool = True,
) -> RunLog:
    """Fill the gt_* columns of a run from a ground-truth trajectory file.

    EuRoC and TUM files, and KITTI with a times file, are associated by time: a frame whose t_ns equals
    a ground-truth stamp takes that pose; a frame between two samples less than `max_gap_ns` apart
    takes the interpolated pose (linear in position, slerp in rotation), or the nearer sample when
    `interpolate` is False. Stamps are compared as exact int64 ns (the frames' clock must be the
    ground truth's: EuRoC ns, KITTI seconds from the times file). KITTI without times is associated by
    frame index: frame i takes pose i.

    Frames left without ground truth (outside the file's span, in a gap, or past the last KITTI pose)
    get NaN in all seven gt_* columns; their count is stored in meta['gt_missing_frames'] (and the
    file in meta['gt_source']) and logged as a warning. Existing gt_* columns are replaced.

    Arguments:
        run: the run (not modified).
        gt_path: ground-truth file; poses read with evo.tools.file_interface.
        fmt: "euroc", "tum" or "kitti".
        kitti_times: KITTI times file (s), or None to associate by index.
        max_gap_ns: largest ground-truth sample spacing to interpolate across, ns.
        interpolate: interpolate between samples (True) or take the nearer one (False).

    Returns:
        A new RunLog with gt_px, gt_py, gt_pz (metres, ground-truth world frame) and gt_qw..gt_qz
        (unit quaternion wxyz, body to world), as the file defines body and world.
    """
    _check_gt_args(fmt, kitti_times, max_gap_ns)
    stamps, p_gt, q_gt = load_ground_truth(gt_path, fmt, kitti_times=kitti_times)
    t = run.frames["t_ns"].to_numpy(dtype=np.int64)
    if stamps is None:
        n, k = len(t), min(len(t), len(p_gt))
        p = np.full((n, 3), np.nan)
        q = np.full((n, 4), np.nan)
        p[:k], q[:k] = p_gt[:k], q_gt[:k]
    else:
        p, q = _associate_by_time(stamps, p_gt, q_gt, t, int(max_gap_ns), interpolate)
    missing = int(np.isnan(p[:, 0]).sum())
    base = run.frames.drop(columns=list(schema.GT_COLUMNS), errors="ignore")
    gt = pd.DataFrame(np.concatenate([p, q], axis=1), columns=list(schema.GT_COLUMNS), index=base.index)
    frames = pd.concat([base, gt], axis=1)
    meta = {**run.meta, "gt_missing_frames": missing, "gt_source": os.fspath(gt_path)}
    out = RunLog(meta=meta, frames=frames, source=run.source, trailers=run.trailers)
    if missing:
        how = (
            "by frame index" if stamps is None else f"outside its span or in gaps >= {max_gap_ns / 1e6:g} ms"
        )
        logger.warning(
            "%s (%s): %d of %d frames have no ground truth in %s (%s); their gt_* are NaN "
            "(meta['gt_missing_frames'])",
            out.run_id,
            run.source,
            missing,
            len(t),
            os.fspath(gt_path),
            how,
        )
    return out


def apply_ground_truth(run: RunLog, spec: GroundTruthSpec) -> RunLog:
    if isinstance(spec, Mapping):
        sequence = run.meta["sequence"]
        if sequence not in spec:
            logger.warning(
                "%s (%s): no ground truth given for sequence '%s'; the run has none",
                run.run_id,
                run.source,
                sequence,
            )
            return run
        spec = spec[sequence]
    if not isinstance(spec, GroundTruth):
        spec = GroundTruth(spec)
    if run.has_ground_truth and not run.frames[list(schema.GT_COLUMNS)].isna().all(axis=None):
        logger.warning(
            "%s (%s): the log carries its own ground truth; kept it and did not use %s",
            run.run_id,
            run.source,
            spec.path,
        )
        return run
    return associate_ground_truth(
        run,
        spec.path,
        spec.fmt,
        kitti_times=spec.kitti_times,
        max_gap_ns=spec.max_gap_ns,
        interpolate=spec.interpolate,
    )
