"""`jsve ape REF EST [EST ...]`: absolute pose error of many estimates against one reference, in one call.

An evo_ape-like command that scores every estimate in a single batched JAX computation (float64, equal to
evo to 1e-9 relative): files are read with evo's file_interface and associated by timestamps with evo's
associate_trajectories (tum, euroc) or by index (kitti), padded to the longest (jsve.io._trajectories),
aligned and scored by jsve.core._pose_error.batched_ape, as Table I does. evo's option spellings work
(-a, -s, --align_origin, --n_to_align, -r/--pose_relation, --save_results, --save_plot).
Prints evo's title, the alignment used and one row per estimate (with failed and failure_reason) or
JSON; exit code 2 when a file or an option cannot be used.
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common
from jsve.cli import _pose_commands as pose

HELP = "absolute pose error of many estimates against one reference (evo_ape-like, batched)"

DEFAULT_ALIGN = "se3"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "ape",
        help=HELP,
        description=(
            "Absolute pose error of each EST against REF (evo_ape), aligned first and scored in one batched "
            "computation. Statistics as evo defines them: rmse, mean, median, std (population), min, max, "
            "sse, count, in the pose relation's unit. The output starts with evo's title and the "
            "alignment used ('aligned: SE(3) Umeyama (evo -a)'). evo's spellings work: -a, -a -s, -s, "
            "--align_origin, --n_to_align N, -r/--pose_relation, --save_results, --plot, --save_plot."
        ),
    )
    parser.add_argument("ref", metavar="REF", help="reference (ground-truth) trajectory file")
    parser.add_argument("est", metavar="EST", nargs="+", help="estimated trajectory file(s)")
    pose.add_alignment_options(
        parser, default=DEFAULT_ALIGN, evo_default=" (unlike evo_ape, which aligns only with -a)"
    )
    pose.add_pose_relation_option(parser)
    common.add_trajectory_options(parser, default_format="tum")
    pose.add_output_options(parser, "APE")
    parser.set_defaults(func=run)


@common.guarded("ape")
def run(args: argparse.Namespace) -> int:
    import numpy as np
    import pandas as pd

    from jsve.core._pose_error_batch import batched_ape
    from jsve.evaluation._aggregate import per_run_table
    from jsve.io._trajectories import read_pose_pairs, stack_pose_pairs

    try:
        method, n_first, alignment = pose.resolve_alignment(args, DEFAULT_ALIGN)
        pose.check_outputs(args)
        pairs = read_pose_pairs(args.ref, args.est, args.format, t_max_diff=args.t_max_diff)
    except ValueError as error:  # TrajectoryFileError is a ValueError: a file that cannot be used
        return common.fail("ape", error)
    pose.warn_y_down("ape", method, pairs, args.ref)

    relation = args.pose_relation
    with pose.enable_x64():  # evo computes in float64; so do we, to match it
        result = batched_ape(*stack_pose_pairs(pairs), align=method, n_first=n_first, relation=relation)
        table = per_run_table(result.errors, pd.DataFrame({"estimate": list(args.est)}))
        aligned = np.asarray(result.aligned)
        per_pose = np.asarray(result.per_pose)
        matrices = np.asarray(pose.sim3_matrices(result.transforms))
    extra = ()
    if method in ("sim3", "scale"):
        table["scale"] = np.asarray(result.transforms.scale, np.float64)
        extra = ("scale",)

    title = pose.evo_title("APE", relation, method, n_first)
    arrays, curves, tracks = [], [], []
    for i, pair in enumerate(pairs):
        n = len(pair.ref)
        x, timed = pose.seconds_or_index(pair)
        est_p = aligned[i, :n, :3, 3]
        errors = per_pose[i, :n]
        entry = {"error_array": errors}
        if timed:  # as evo_ape stores a trajectory with stamps (distances: path lengths, metres)
            entry["seconds_from_start"] = x
            entry["distances_from_start"] = pose.accumulated(pair.ref[:, :3, 3])
            entry["distances"] = pose.accumulated(est_p)
        if method != "none":
            entry["alignment_transformation_sim3"] = matrices[i]
        arrays.append(entry)
        if not bool(table["failed"][i]):
            curves.append((pair.name, x, errors, timed))
            tracks.append((pair.name, est_p))
    return pose.finish(
        "ape",
        args,
        title=title,
        alignment=alignment,
        relation=relation,
        table=table,
        arrays=arrays,
        curves=curves,
        tracks=tracks,
        reference=pairs[0].ref[:, :3, 3],
        extra=extra,
    )
