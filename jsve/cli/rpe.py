"""`jsve rpe REF EST [EST ...]`: relative pose error of many estimates against one reference (evo_rpe).

Files are read and associated as `jsve ape` reads them (jsve.io._trajectories), padded to the longest and
scored by jsve.core._pose_error.batched_rpe in float64: each estimate aligned (default: not, as evo_rpe),
the pose pairs chosen delta apart (--delta, --delta_unit f|d|r|m, --all_pairs), and the error of each pair's
relative motion (-r/--pose_relation). Statistics equal evo_rpe's to 1e-9 relative. Prints evo's title, the
alignment used and one row per estimate, or JSON; exit code 2 when a file or an option cannot be used.
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common
from jsve.cli import _pose_commands as pose

HELP = "relative pose error of many estimates against one reference (evo_rpe-like, batched)"

DEFAULT_ALIGN = "none"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "rpe",
        help=HELP,
        description=(
            "Relative pose error of each EST against REF (evo_rpe): for each pose pair (i, j) delta apart, "
            "the error of the estimate's motion from i to j against the reference's, "
            "E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j). Statistics as evo defines them (rmse, mean, median, std, "
            "min, max, sse, count of pairs), in the pose relation's unit. evo_rpe's options work: --delta, "
            "--delta_unit, --all_pairs, --delta_tol, --pairs_from_reference, -r, -a, -s, --align_origin, "
            "--n_to_align, --save_results, --plot, --save_plot."
        ),
    )
    parser.add_argument("ref", metavar="REF", help="reference (ground-truth) trajectory file")
    parser.add_argument("est", metavar="EST", nargs="+", help="estimated trajectory file(s)")
    parser.add_argument(
        "-d",
        "--delta",
        type=float,
        default=1.0,
        help="the distance of a pair, in --delta_unit (frames: a whole number). Default: 1",
    )
    parser.add_argument(
        "-u",
        "--delta-unit",
        "--delta_unit",
        dest="delta_unit",
        choices=("f", "d", "r", "m"),
        default="f",
        help="f frames, d degrees, r radians (of rotation accumulated between the poses), m metres (of "
        "path). Default: f",
    )
    parser.add_argument(
        "--all-pairs",
        "--all_pairs",
        dest="all_pairs",
        action="store_true",
        help="every pair delta apart, not only consecutive ones (for d/r: pairs whose relative rotation "
        "is delta; for m: for each pose the one whose path from it is closest to delta). Default: off",
    )
    parser.add_argument(
        "-t",
        "--delta-tol",
        "--delta_tol",
        dest="delta_tol",
        type=float,
        metavar="TOL",
        default=0.1,
        help="with --all_pairs in m/d/r: the accepted miss, a fraction of delta. Default: 0.1",
    )
    parser.add_argument(
        "--pairs-from-reference",
        "--pairs_from_reference",
        dest="pairs_from_reference",
        action="store_true",
        help="choose the pairs on the reference's path and rotations instead of the aligned estimate's. "
        "Default: off",
    )
    pose.add_alignment_options(parser, default=DEFAULT_ALIGN, evo_default=" (evo_rpe's)")
    pose.add_pose_relation_option(parser)
    common.add_trajectory_options(parser, default_format="tum")
    pose.add_output_options(parser, "RPE")
    parser.set_defaults(func=run)


@common.guarded("rpe")
def run(args: argparse.Namespace) -> int:
    import numpy as np

    from jsve.core._pose_error import DELTA_UNITS, RPE_FAILURE_CAUSES
    from jsve.core._pose_error_batch import batched_rpe, check_delta
    from jsve.core._trajectory import failure_reason
    from jsve.io._trajectories import read_pose_pairs, stack_pose_pairs

    try:
        method, n_first, alignment = pose.resolve_alignment(args, DEFAULT_ALIGN)
        check_delta(args.delta, args.delta_unit, args.delta_tol)
        pose.check_outputs(args)
        pairs = read_pose_pairs(args.ref, args.est, args.format, t_max_diff=args.t_max_diff)
    except ValueError as error:  # TrajectoryFileError is a ValueError: a file that cannot be used
        return common.fail("rpe", error)
    pose.warn_y_down("rpe", method, pairs, args.ref)

    relation, unit = args.pose_relation, args.delta_unit
    delta = int(args.delta) if unit == "f" else args.delta
    with pose.enable_x64():  # evo computes in float64; so do we, to match it
        result = batched_rpe(
            *stack_pose_pairs(pairs),
            delta=delta,
            unit=unit,
            all_pairs=args.all_pairs,
            rel_tol=args.delta_tol,
            pairs_from_reference=args.pairs_from_reference,
            relation=relation,
            align=method,
            n_first=n_first,
        )
        aligned = np.asarray(result.aligned)
        second = np.asarray(result.second)
        mask, per_pair = np.asarray(result.mask), np.asarray(result.per_pair)
        matrices = np.asarray(pose.sim3_matrices(result.transforms))
        bits = np.asarray(result.failure)
    reasons = [failure_reason(b, RPE_FAILURE_CAUSES) for b in bits]
    table = pose.stats_table(list(args.est), result.stats, result.failed, reasons)

    detail = (
        f"\nfor delta = {delta} ({DELTA_UNITS[unit]}) using "
        f"{'all pairs' if args.all_pairs else 'consecutive pairs'}"
    )
    title = pose.evo_title("RPE", relation, method, n_first, detail)
    arrays, curves, tracks = [], [], []
    for i, pair in enumerate(pairs):
        n = len(pair.ref)
        x, timed = pose.seconds_or_index(pair)
        ends = second[i][mask[i]]  # evo keeps j of each pair (i, j)
        errors = per_pair[i][mask[i]]
        est_p = aligned[i, :n, :3, 3]
        entry = {"error_array": errors}
        if timed:  # as evo_rpe: the poses [0] + the pairs' ends, their times and path lengths
            ids = np.concatenate([[0], ends])
            entry["seconds_from_start"] = x[ends]
            entry["distances_from_start"] = pose.accumulated(pair.ref[ids, :3, 3])[1:]
            entry["distances"] = pose.accumulated(est_p[ids])[1:]
        if method != "none":
            entry["alignment_transformation_sim3"] = matrices[i]
        arrays.append(entry)
        if not bool(table["failed"][i]):
            order = np.argsort(ends, kind="stable")
            curves.append((pair.name, x[ends][order], errors[order], timed))
            tracks.append((pair.name, est_p))
    return pose.finish(
        "rpe",
        args,
        title=title,
        alignment=alignment,
        relation=relation,
        table=table,
        arrays=arrays,
        curves=curves,
        tracks=tracks,
        reference=pairs[0].ref[:, :3, 3],
    )
