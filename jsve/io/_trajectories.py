"""Trajectory files (EuRoC, TUM, KITTI): read with evo's file_interface, estimates paired with a reference.

    read_trajectory(path, fmt)                 one file -> evo trajectory
    associate(ref, est, ...)                   the poses of both at the same frames: by timestamps
                                               (evo's associate_trajectories; tum, euroc) or by index (kitti)
    read_pose_pairs(ref_path, est_paths, fmt)  a reference and its estimates -> PosePairs
    stack_pose_pairs(pairs)                    PosePairs -> padded arrays, for jsve.core._pose_error

Ground truth for tracking logs (jsve.io._groundtruth) reads its files through `evo_reader` too. Errors are
`TrajectoryFileError`s naming the file; evo itself is imported only when a file is read (~0.4 s).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from jsve.io import _schema as schema
from jsve.io._errors import TrajectoryFileError

TRAJECTORY_FORMATS: tuple[str, ...] = ("euroc", "tum", "kitti")
"""Trajectory file formats: "euroc" (CSV, int ns stamps, p, q wxyz), "tum" (s stamps, p, q xyzw), "kitti"
(3x4 poses, no stamps)."""

_FIELDS = {
    "tum": ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"),
    "euroc": ("timestamp", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"),
    "kitti": ("r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz"),
}
"""The fields of a line that jsve reads, per format (EuRoC's further fields are not read)."""

ROTATION_TOLERANCE = 1e-3
"""Largest accepted | |q| - 1 | of a file's quaternion, and largest entry of |R R^T - I| of a KITTI
rotation. evo normalises a non-unit quaternion and turns a zero one into the identity without a word
(with `--align origin` a zero first quaternion moved every error); files written with 6 decimals are
within 1e-5 of unit."""

_EVO_READERS = {
    "euroc": "read_euroc_csv_trajectory",
    "tum": "read_tum_trajectory_file",
    "kitti": "read_kitti_poses_file",
}


def evo_reader(fmt: str) -> Callable:
    """evo's reader of a format in TRAJECTORY_FORMATS: path -> PoseTrajectory3D (PosePath3D for kitti)."""
    if fmt not in TRAJECTORY_FORMATS:
        raise ValueError(f"fmt must be one of {TRAJECTORY_FORMATS}, got {fmt!r}")
    from evo.tools import file_interface

    return getattr(file_interface, _EVO_READERS[fmt])


@dataclass(frozen=True)
class PosePair:
    """One estimate and its reference, associated pose by pose.

    Attributes:
        name: a label (the estimate's file name).
        ref: [T, 4, 4] reference poses T_wb (rotation, translation in metres), reference world frame.
        est: [T, 4, 4] estimated poses of the same frames, estimate world frame.
        t: [T] seconds since the first reference pose, or None (poses are then plotted by index).
    """

    name: str
    ref: np.ndarray
    est: np.ndarray
    t: np.ndarray | None = None

    def __post_init__(self):
        ref, est = np.asarray(self.ref, np.float64), np.asarray(self.est, np.float64)
        if ref.ndim != 3 or ref.shape[1:] != (4, 4) or est.shape != ref.shape:
            raise ValueError(
                f"{self.name}: ref and est must both have shape (T, 4, 4), got {ref.shape} and {est.shape}"
            )
        if len(ref) == 0:
            raise ValueError(f"{self.name}: no poses")
        if self.t is not None and np.shape(self.t) != (len(ref),):
            raise ValueError(f"{self.name}: t must have shape ({len(ref)},), got {np.shape(self.t)}")
        object.__setattr__(self, "ref", ref)
        object.__setattr__(self, "est", est)


def read_trajectory(path: str | os.PathLike, fmt: str):
    """Read one trajectory file with evo.

    Arguments:
        path: the file.
        fmt: one of TRAJECTORY_FORMATS.

    Returns:
        evo's PoseTrajectory3D (tum, euroc; stamps in seconds) or PosePath3D (kitti), at least one pose.

    Raises:
        TrajectoryFileError: the file cannot be read as `fmt`, or holds no poses.
    """
    reader = evo_reader(fmt)
    try:
        traj = reader(path)
    except Exception as error:  # evo raises FileInterfaceException, OSError, ValueError, ... per format
        raise TrajectoryFileError(f"cannot read {os.fspath(path)} as {fmt}: {error}") from error
    if traj.num_poses == 0:
        raise TrajectoryFileError(f"{os.fspath(path)} holds no poses")
    check_poses(traj, path, fmt)
    return traj


def check_poses(traj, path: str | os.PathLike, fmt: str) -> None:
    """Refuse what evo reads without a word: a stamp or pose value that is NaN, infinite or beyond
    float32's range (schema.FLOAT_MAX: jsve computes logs in float32, where it would be inf), a
    quaternion that is not unit (zero ones included) or a KITTI rotation that is not a rotation
    (ROTATION_TOLERANCE).

    Arguments:
        traj: what evo read from `path` (rows in file order).
        path: the file, for the message; fmt: its format (TRAJECTORY_FORMATS).

    Raises:
        TrajectoryFileError: `path:line: column 'name' = 'value': reason`, the first bad line.
    """
    n = traj.num_poses
    if fmt == "kitti":
        rows = np.stack(traj.poses_se3)[:, :3, :].reshape(n, 12)  # r11 r12 r13 tx r21 ... tz, as written
    else:
        stamps = np.asarray(traj.timestamps, np.float64).reshape(n, 1)
        q = np.asarray(traj.orientations_quat_wxyz, np.float64)
        q_as_written = q[:, [1, 2, 3, 0]] if fmt == "tum" else q  # tum writes xyzw
        rows = np.concatenate([stamps, np.asarray(traj.positions_xyz, np.float64), q_as_written], axis=1)
    names = _FIELDS[fmt]
    with np.errstate(invalid="ignore"):
        bad_value = ~np.isfinite(rows) | (np.abs(rows) > schema.FLOAT_MAX)
    if fmt == "kitti":
        r = rows[:, [0, 1, 2, 4, 5, 6, 8, 9, 10]].reshape(n, 3, 3)
        with np.errstate(invalid="ignore", over="ignore"):
            off = np.abs(r @ np.swapaxes(r, 1, 2) - np.eye(3)).max(axis=(1, 2))
            bad_rotation = ~(off <= ROTATION_TOLERANCE) | ~(np.linalg.det(r) > 0)
        group, what = (0, 1, 2, 4, 5, 6, 8, 9, 10), "not a rotation: |R R^T - I| = {:.3g} or det R <= 0"
        size = off
    else:
        with np.errstate(invalid="ignore", over="ignore"):
            size = np.linalg.norm(q, axis=1)
            bad_rotation = ~(np.abs(size - 1.0) <= ROTATION_TOLERANCE)
        group, what = (4, 5, 6, 7), "not a unit quaternion: |q| = {:.6g}"
    bad = bad_value.any(axis=1) | bad_rotation
    if not bad.any():
        return
    k = int(np.argmax(bad))
    line, fields = _data_line(path, k, "," if fmt == "euroc" else " ")
    if bad_value[k].any():
        c = int(np.argmax(bad_value[k]))
        text = fields[c] if c < len(fields) else repr(float(rows[k, c]))
        reason = (
            "NaN or inf is not allowed"
            if not np.isfinite(rows[k, c])
            else f"beyond float32's range (|x| <= {schema.FLOAT_MAX:.8g}), the range jsve computes in"
        )
        raise TrajectoryFileError.at(path, line, reason, names[c], text)
    shown = " ".join(fields[c] for c in group if c < len(fields))
    reason = what.format(float(size[k])) + f" (tolerance {ROTATION_TOLERANCE:g})"
    raise TrajectoryFileError.at(
        path, line, reason, f"{names[group[0]]}..{names[group[-1]]}", shown, "columns"
    )


def _data_line(path: str | os.PathLike, k: int, delimiter: str) -> tuple[int | None, list[str]]:
    """(1-based line number, fields) of the k-th row evo's csv_read_matrix reads from `path`: the lines
    that do not start with '#', after a UTF-8 byte-order mark."""
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        row = -1
        for number, text in enumerate(f, start=1):
            if text.startswith("#"):
                continue
            row += 1
            if row == k:
                return number, text.rstrip("\r\n").split(delimiter)
    return None, []


def associate(ref, est, ref_path: str, est_path: str, fmt: str, t_max_diff: float = 0.01):
    """The poses of `ref` and `est` at the same frames, in the same order.

    Arguments:
        ref, est: evo trajectories as `read_trajectory` returns them; ref_path, est_path name them in
            messages.
        fmt: kitti files are associated by index; tum and euroc by timestamps (evo's
            associate_trajectories).
        t_max_diff: largest time difference of an associated pair, seconds (tum, euroc).

    Returns:
        (reference, estimate) with one pose per associated frame.

    Raises:
        TrajectoryFileError: kitti files of different lengths, or no pose pair within t_max_diff.
    """
    if fmt == "kitti":
        if ref.num_poses != est.num_poses:
            raise TrajectoryFileError(
                f"{est_path} has {est.num_poses} poses but {ref_path} has {ref.num_poses} "
                "(kitti files are associated by index and must have the same length)"
            )
        return ref, est
    from evo.core import sync

    try:
        return sync.associate_trajectories(ref, est, max_diff=t_max_diff)
    except sync.SyncException as error:
        raise TrajectoryFileError(f"cannot associate {est_path} with {ref_path}: {error}") from error


def read_kitti_times(path: str | os.PathLike, n_poses: int) -> np.ndarray:
    """A KITTI times file (seconds, one line per pose), as seconds since its first line.

    Raises:
        TrajectoryFileError: the file cannot be read, or it does not hold `n_poses` times.
    """
    try:
        times = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except (OSError, ValueError) as error:
        raise TrajectoryFileError(
            f"cannot read {os.fspath(path)} as KITTI times (seconds, one per line): {error}"
        ) from error
    finite = np.isfinite(times)
    if not finite.all():
        k = int(np.argmax(~finite))
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            # np.loadtxt skips blank lines and '#' comments.
            lines = [(i, t.strip()) for i, t in enumerate(f, start=1) if t.strip() and not t.startswith("#")]
        line, text = lines[k] if k < len(lines) else (None, repr(float(times[k])))
        raise TrajectoryFileError.at(path, line, "NaN or inf is not allowed (seconds)", "time", text)
    if times.shape != (n_poses,):
        raise TrajectoryFileError(
            f"{os.fspath(path)} has {times.size} times but the reference has {n_poses} poses"
        )
    return times - times[0]


def read_pose_pairs(
    ref_path: str | os.PathLike[str],
    est_paths: Sequence[str | os.PathLike[str]],
    fmt: str = "tum",
    *,
    t_max_diff: float = 0.01,
    kitti_times: str | os.PathLike | None = None,
) -> list[PosePair]:
    """Read a reference and its estimates and associate each estimate with the reference.

    Files are read in order (the reference, the times file, then each estimate), so the error raised is
    the first problem in that order.

    Arguments:
        ref_path: the reference (ground-truth) trajectory.
        est_paths: the estimates; each PosePair is named by its path as given.
        fmt: one of TRAJECTORY_FORMATS, the format of every file.
        t_max_diff: largest time difference of an associated pair, seconds (tum, euroc).
        kitti_times: kitti only: the reference's times file (seconds), for PosePair.t.

    Returns:
        One PosePair per estimate, in order. t is seconds since the reference's first pose for tum and
        euroc; for kitti the times file's, or None without one.

    Raises:
        TrajectoryFileError: a file that cannot be read or associated.
        ValueError: kitti_times with a format other than kitti.
    """
    if kitti_times is not None and fmt != "kitti":
        raise ValueError(f"kitti_times applies to fmt='kitti' (tum and euroc carry stamps), got fmt={fmt!r}")
    ref_path = os.fspath(ref_path)
    ref = read_trajectory(ref_path, fmt)
    times = read_kitti_times(kitti_times, ref.num_poses) if kitti_times is not None else None
    pairs = []
    for est_path in est_paths:
        path = os.fspath(est_path)
        ref_i, est_i = associate(ref, read_trajectory(path, fmt), ref_path, path, fmt, t_max_diff)
        if fmt == "kitti":
            t = times
        else:
            t = np.asarray(ref_i.timestamps, np.float64) - float(ref.timestamps[0])
        pairs.append(PosePair(path, np.stack(ref_i.poses_se3), np.stack(est_i.poses_se3), t))
    return pairs


def stack_pose_pairs(pairs: Sequence[PosePair]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs as padded arrays, for one batched computation (jsve.core._pose_error.batched_pose_error).

    Arguments:
        pairs: at least one.

    Returns:
        (est [R, T, 4, 4], ref [R, T, 4, 4], valid [R, T] bool), T the longest pair; padding poses are the
        identity and not valid.
    """
    if not pairs:
        raise ValueError("stack_pose_pairs needs at least one pair")
    n_runs, n_frames = len(pairs), max(len(p.est) for p in pairs)
    eye = np.broadcast_to(np.eye(4), (n_runs, n_frames, 4, 4))
    est, ref = eye.copy(), eye.copy()
    valid = np.zeros((n_runs, n_frames), bool)
    for i, pair in enumerate(pairs):
        est[i, : len(pair.est)], ref[i, : len(pair.ref)] = pair.est, pair.ref
        valid[i, : len(pair.est)] = True
    return est, ref, valid
