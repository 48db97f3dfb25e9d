"""`jsve ape REF EST [EST ...]`: absolute pose error of many estimates against one reference, in one call.

An evo_ape-like command that scores every estimate in a single batched JAX computation (float64, equal to
evo to 1e-6): files are read with evo's file_interface, associated by timestamps with evo's
associate_trajectories (tum, euroc) or by index (kitti), padded to the longest, aligned and scored by
`jsve.core._trajectory.batched_run_error`.
Prints one row per estimate (APE translation part, metres) or JSON; exit code 2 when a file cannot be used.
"""

from __future__ import annotations

import argparse
import json
import sys

ALIGN_CHOICES = ("se3", "sim3", "posyaw", "origin", "none")  # jsve.core._trajectory.ALIGN_METHODS, kept import-free
FORMATS = ("tum", "euroc", "kitti")
TABLE_COLUMNS = ("rmse", "mean", "median", "std", "min", "max", "sse", "count")


class InputError(Exception):
    """A file that cannot be read or matched; the message names the file."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "ape",
        help="absolute pose error of many estimates against one reference (evo_ape-like, batched)",
        description=(
            "Absolute pose error (translation part, metres) of each EST against REF, aligned with --align "
            "and scored in one batched computation. Statistics as evo defines them: rmse, mean, median, std "
            "(population), min, max, sse, count."
        ),
    )
    parser.add_argument("ref", metavar="REF", help="reference (ground-truth) trajectory file")
    parser.add_argument("est", metavar="EST", nargs="+", help="estimated trajectory file(s)")
    parser.add_argument(
        "--align",
        choices=ALIGN_CHOICES,
        default="se3",
        help="alignment: se3, sim3 (with scale), posyaw (yaw + translation), origin (first pose), none "
        "(default: se3)",
    )
    parser.add_argument("--format", choices=FORMATS, default="tum", help="file format (default: tum)")
    parser.add_argument(
        "--n-to-align",
        type=int,
        default=-1,
        metavar="N",
        help="align on the first N associated poses only (default -1: all)",
    )
    parser.add_argument(
        "--t-max-diff",
        type=float,
        default=0.01,
        metavar="S",
        help="largest time difference in seconds for associating poses (tum, euroc; default 0.01)",
    )
    parser.add_argument(
        "--json", action="store_true", help="print JSON (a list of objects) instead of a table"
    )
    parser.add_argument(
        "-o", "--output", metavar="TABLE.csv", help="also write the per-estimate table as CSV"
    )
    parser.set_defaults(func=run)


def _read(path: str, fmt: str):
    from evo.tools import file_interface

    readers = {
        "tum": file_interface.read_tum_trajectory_file,
        "euroc": file_interface.read_euroc_csv_trajectory,
        "kitti": file_interface.read_kitti_poses_file,
    }
    try:
        traj = readers[fmt](path)
    except Exception as error:  # evo raises FileInterfaceException, OSError, ValueError, ... per format
        raise InputError(f"cannot read {path} as {fmt}: {error}") from error
    if traj.num_poses == 0:
        raise InputError(f"{path} holds no poses")
    return traj


def _associate(ref, est, ref_path: str, est_path: str, fmt: str, t_max_diff: float):
    """(reference, estimate) with one pose per associated frame, in the same order."""
    if fmt == "kitti":
        if ref.num_poses != est.num_poses:
            raise InputError(
                f"{est_path} has {est.num_poses} poses but {ref_path} has {ref.num_poses} "
                "(kitti files are associated by index and must have the same length)"
            )
        return ref, est
    from evo.core import sync

    try:
        return sync.associate_trajectories(ref, est, max_diff=t_max_diff)
    except sync.SyncException as error:
        raise InputError(f"cannot associate {est_path} with {ref_path}: {error}") from error


def _score(pairs, align: str, n_first: int | None):
    """Stack the associated pairs (padded to the longest) and score them in one batched call."""
    import jax.numpy as jnp
    import numpy as np

    from jsve.core._trajectory import batched_run_error

    n_runs, n_frames = len(pairs), max(est.num_poses for _, est in pairs)
    est_p = np.zeros((n_runs, n_frames, 3))
    ref_p = np.zeros((n_runs, n_frames, 3))
    est_q = np.zeros((n_runs, n_frames, 4))
    ref_q = np.zeros((n_runs, n_frames, 4))
    est_q[..., 0] = ref_q[..., 0] = 1.0
    valid = np.zeros((n_runs, n_frames), bool)
    for i, (ref, est) in enumerate(pairs):
        n = est.num_poses
        est_p[i, :n], est_q[i, :n] = est.positions_xyz, est.orientations_quat_wxyz
        ref_p[i, :n], ref_q[i, :n] = ref.positions_xyz, ref.orientations_quat_wxyz
        valid[i, :n] = True
    valid_j = jnp.asarray(valid)
    return batched_run_error(
        jnp.asarray(est_p),
        jnp.asarray(est_q),
        valid_j,
        jnp.zeros((n_runs, n_frames), jnp.int32),
        jnp.asarray(ref_p),
        jnp.asarray(ref_q),
        valid_j,
        valid_j,
        align=align,
        n_first=n_first,
    )


def run(args: argparse.Namespace) -> int:
    import jax
    import pandas as pd

    from jsve.evaluation._aggregate import per_run_table

    if args.n_to_align == 0 or args.n_to_align < -1:
        print(
            f"jsve ape: --n-to-align must be a positive number or -1 (all), got {args.n_to_align}",
            file=sys.stderr,
        )
        return 2
    n_first = None if args.n_to_align == -1 else args.n_to_align
    try:
        ref = _read(args.ref, args.format)
        pairs = [
            _associate(ref, _read(path, args.format), args.ref, path, args.format, args.t_max_diff)
            for path in args.est
        ]
    except InputError as error:
        print(f"jsve ape: {error}", file=sys.stderr)
        return 2

    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)  # evo computes in float64; so do we, to match it to 1e-6
    try:
        errors = _score(pairs, args.align, n_first)
        table = per_run_table(errors, pd.DataFrame({"estimate": list(args.est)}))
    finally:
        jax.config.update("jax_enable_x64", previous)

    if args.output:
        table.to_csv(args.output, index=False)
    if args.json:
        records = table[["estimate", *TABLE_COLUMNS, "failed"]].to_dict(orient="records")
        print(json.dumps([{k: _plain(v) for k, v in r.items()} for r in records], indent=2))
    else:
        shown = table[["estimate", *TABLE_COLUMNS, "failed"]]
        print(shown.to_string(index=False, float_format=lambda v: f"{v:.6f}"))
    return 0


def _plain(value):
    """A JSON-ready Python scalar (NaN becomes null)."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and value != value:
        return None
    return value
