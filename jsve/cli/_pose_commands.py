"""What `jsve ape` and `jsve rpe` share: evo's option spellings, the alignment line, results and plots.

Options take both spellings, jsve's (`--n-to-align`, `--save-plot`) and evo's (`--n_to_align`,
`--save_plot`), so that an evo_ape / evo_rpe command line works with `jsve` in front. The outputs:

- the table (stdout, `--json`, `-o TABLE.csv`), headed by evo's title and the alignment used;
- `--save_results FILE.zip`: evo's result file (evo.tools.file_interface.save_res_file's layout: info.json,
  stats.json, one .npy per array), written without evo, which `evo_res` reads and tabulates;
- `--plot` / `--save_plot FILE.png|svg`: the error over time and a top view of the trajectories.

Like the subcommand modules, this module imports only the standard library at top level.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import zipfile
from collections.abc import Sequence
from pathlib import Path

from jsve.cli import _common as common

ALIGNMENT_WORDS = {
    "se3": "SE(3) Umeyama (evo -a)",
    "sim3": "Sim(3) Umeyama, with scale (evo -a -s)",
    "scale": "scale only, Sim(3) Umeyama's scale (evo -s)",
    "posyaw": "yaw about the world z axis + translation, 4-DoF (rpg_trajectory_evaluation's posyaw, "
    "not in evo)",
    "origin": "first pose onto the reference's first pose (evo --align_origin)",
    "none": "none (evo without -a)",
}
"""The alignment line's words per method (jsve.core._pose_error.POSE_ALIGN_METHODS)."""

_EVO_TITLES = {
    "se3": "(with SE(3) Umeyama alignment)",
    "sim3": "(with Sim(3) Umeyama alignment)",
    "scale": "(scale corrected)",
    "posyaw": "(with posyaw alignment: yaw about the world z axis)",
    "origin": "(with origin alignment)",
    "none": "(not aligned)",
}
"""evo's title lines (evo.main_ape.ape); posyaw's is jsve's own."""

PLOT_SUFFIXES = (".png", ".svg")

STAT_NAMES = ("rmse", "mean", "median", "std", "min", "max", "sse")
"""evo's statistics, in evo's order (metrics.StatisticsType)."""

TABLE_COLUMNS = (*STAT_NAMES, "count", "failed", "failure_reason")
"""The columns printed after `estimate` (a failed run's statistics are NaN; failure_reason says why)."""


# --------------------------------------------------------------------------------------------------
# Options


def add_alignment_options(parser: argparse.ArgumentParser, *, default: str, evo_default: str) -> None:
    """--align [METHOD] (jsve's, its choices the library's methods; bare, evo's -a), evo's -a, -s /
    --correct_scale and --align_origin."""
    parser.add_argument(
        "--align",
        nargs="?",
        const="se3",
        default=None,
        choices=common.LibraryNames("jsve.core._align", "ALIGN_METHODS"),
        metavar="METHOD",
        help=f"alignment: se3 (rotation + translation, Umeyama), sim3 (with scale), posyaw (yaw about the "
        f"world z axis + translation: assumes z is up, meaningless for y-down frames such as KITTI's "
        f"camera frame, which is warned about), origin (the first pose onto the reference's), none; "
        f"--align without METHOD is evo's -a (se3). Default: {default}{evo_default}",
    )
    parser.add_argument(
        "-a",
        dest="evo_align",
        action="store_true",
        help="evo's -a/--align: SE(3) Umeyama, as --align se3. Default: off",
    )
    parser.add_argument(
        "-s",
        "--correct_scale",
        "--correct-scale",
        dest="correct_scale",
        action="store_true",
        help="evo's -s: with -a (or --align se3) Sim(3) Umeyama, as --align sim3; alone, evo's scale-only "
        "correction (Sim(3) Umeyama's scale applied to the positions, no rotation or translation). "
        "Default: off",
    )
    parser.add_argument(
        "--align_origin",
        "--align-origin",
        dest="align_origin",
        action="store_true",
        help="evo's --align_origin: map the first pose onto the reference's first pose, as --align origin. "
        "Default: off",
    )


def resolve_alignment(args: argparse.Namespace, default: str) -> tuple[str, int | None, str]:
    """The alignment asked for, in evo's spelling or jsve's.

    Returns:
        (method of jsve.core._pose_error.POSE_ALIGN_METHODS, n_first (None: all poses), the alignment line
        without its 'aligned: ' prefix).

    Raises:
        ValueError: options that contradict each other (evo refuses -a with --align_origin too) or that jsve
            cannot combine; --n-to-align 0 or below -1.
    """
    chosen = args.align
    if args.evo_align:
        if chosen not in (None, "se3", "sim3"):
            raise ValueError(f"-a (evo's SE(3) alignment) contradicts --align {chosen}")
        chosen = chosen or "se3"
    if args.align_origin:
        if chosen not in (None, "origin"):
            raise ValueError(
                f"--align_origin cannot be combined with {'-a' if args.evo_align else '--align ' + chosen} "
                "(evo refuses align and align_origin together)"
            )
        if args.correct_scale:
            raise ValueError(
                "-s with --align_origin (evo: scale correction, then the origin alignment) is not supported; "
                "use -a -s (sim3) or --align_origin alone"
            )
        chosen = "origin"
    if args.correct_scale:
        if chosen is None:
            chosen = "scale"  # evo: correct_scale without align corrects the scale only
        elif chosen in ("se3", "sim3"):
            chosen = "sim3"
        else:
            raise ValueError(f"-s/--correct_scale applies to Umeyama alignment (se3), not --align {chosen}")
    method = chosen or default
    n_first = common.n_first(args.n_to_align)
    words = ALIGNMENT_WORDS[method]
    if n_first is not None and method not in ("origin", "none"):
        words += f", on the first {n_first} poses (evo --n_to_align {n_first})"
    return method, n_first, words


def add_pose_relation_option(parser: argparse.ArgumentParser) -> None:
    """-r / --pose-relation / --pose_relation: jsve.core._pose_error.POSE_RELATIONS (evo's trans_part
    accepted for translation)."""

    def relation(text: str) -> str:
        return "translation" if text == "trans_part" else text

    parser.add_argument(
        "-r",
        "--pose-relation",
        "--pose_relation",
        dest="pose_relation",
        type=relation,
        choices=common.LibraryNames("jsve.core._pose_error", "POSE_RELATIONS"),
        metavar="RELATION",
        default="translation",
        help="the error of a pose (evo's --pose_relation): translation (metres; evo's trans_part, also "
        "accepted), angle_deg / angle_rad (the angle of the error rotation, degrees / radians), full "
        "(||E - I||, unit-less). Default: translation",
    )


def add_output_options(parser: argparse.ArgumentParser, metric: str) -> None:
    """--json, -o/--output TABLE.csv, --save_results FILE.zip, --plot, --save_plot FILE, --plot_mode."""
    parser.add_argument(
        "--json", action="store_true", help="print JSON (a list of objects) instead of a table. Default: off"
    )
    parser.add_argument(
        "-o",
        "--output",
        metavar="TABLE.csv",
        help="also write the per-estimate table as CSV. Default: none",
    )
    parser.add_argument(
        "--save-results",
        "--save_results",
        dest="save_results",
        metavar="FILE.zip",
        help="write evo's result file (evo_res reads it: `evo_res FILE.zip ...`); with several estimates "
        "one per estimate, FILE_<estimate name>.zip. An estimate that failed gets none. Default: none",
    )
    parser.add_argument(
        "--plot",
        action="store_true",
        help=f"show the {metric} over time and the trajectories' top view in a window (evo's --plot; "
        "needs a display, else says so and goes on). Default: off",
    )
    parser.add_argument(
        "--save-plot",
        "--save_plot",
        dest="save_plot",
        metavar="FILE",
        help=f"write that figure to FILE, PNG or SVG after its suffix ({', '.join(PLOT_SUFFIXES)}). "
        "Default: none",
    )
    parser.add_argument(
        "--plot-mode",
        "--plot_mode",
        dest="plot_mode",
        choices=("auto", "xy", "xz", "yz"),
        default="auto",
        help="the top view's axes (evo's --plot_mode): auto picks the two along which the reference "
        "spreads most (xz for KITTI's camera frame, xy for EuRoC). Default: auto",
    )


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse an output the command could not write, before any work.

    Raises:
        ValueError: --save_plot without a .png or .svg suffix.
    """
    if args.save_plot and Path(args.save_plot).suffix.lower() not in PLOT_SUFFIXES:
        raise ValueError(
            f"--save_plot {args.save_plot}: the suffix must be one of {', '.join(PLOT_SUFFIXES)}"
        )


# --------------------------------------------------------------------------------------------------
# Titles and tables


def evo_title(metric: str, relation: str, method: str, n_first: int | None, detail: str = "") -> str:
    """evo's result title, e.g. 'APE w.r.t. translation part (m)\\n(with SE(3) Umeyama alignment)'
    (evo_res warns when the titles of the files it compares differ)."""
    from jsve.core._pose_error import POSE_RELATIONS

    name, unit = POSE_RELATIONS[relation]
    title = f"{metric} w.r.t. {name} ({unit}){detail}\n{_EVO_TITLES[method]}"
    if n_first is not None and method in ("se3", "sim3", "scale", "posyaw"):
        title += f" (aligned poses: {n_first})"
    return title


def stats_table(names: Sequence[str], stats, failed, reasons: Sequence[str]):
    """The per-estimate table (pandas): estimate, rmse..sse (NaN where nothing was scored), count,
    failed, failure_reason."""
    import numpy as np
    import pandas as pd

    table = pd.DataFrame({"estimate": list(names)})
    count = np.atleast_1d(np.asarray(stats.count)).astype(np.int64)
    for name in STAT_NAMES:
        table[name] = np.where(
            count == 0, np.nan, np.atleast_1d(np.asarray(getattr(stats, name), np.float64))
        )
    table["count"] = count
    table["failed"] = np.atleast_1d(np.asarray(failed)).astype(bool)
    table["failure_reason"] = np.array(list(reasons), dtype=object)
    return table


def report(table, args: argparse.Namespace, title: str, alignment: str, relation: str, extra=()) -> None:
    """Print evo's title (on one line), the alignment line and the table; or JSON: one object per
    estimate with `pose_relation`, `unit` and `alignment` beside its columns."""
    from jsve.core._pose_error import POSE_RELATIONS

    shown = table[["estimate", *TABLE_COLUMNS[:-2], *extra, *TABLE_COLUMNS[-2:]]]
    if args.json:
        unit = POSE_RELATIONS[relation][1]
        records = [
            {
                **{k: _plain(v) for k, v in r.items()},
                "pose_relation": relation,
                "unit": unit,
                "alignment": alignment,
            }
            for r in shown.to_dict(orient="records")
        ]
        print(json.dumps(records, indent=2))
    else:
        print(title.replace("\n", " "))
        print(f"aligned: {alignment}")
        print(shown.to_string(index=False, float_format=lambda v: f"{v:.6f}"))


def _plain(value):
    """A JSON-ready Python scalar (NaN becomes null)."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and value != value:
        return None
    return value


def warn_y_down(command: str, method: str, pairs, ref_path: str) -> None:
    """posyaw on a trajectory that moves in a plane normal to y (jsve.core._align.y_is_vertical): one
    warning line per file on stderr."""
    if method != "posyaw":
        return
    import jax.numpy as jnp

    from jsve.core._align import y_is_vertical

    def y_down(poses) -> bool:
        p = jnp.asarray(poses[:, :3, 3])
        return bool(y_is_vertical(p, jnp.ones(len(p), bool)))

    named = [(ref_path, pairs[0].ref)] + [(pair.name, pair.est) for pair in pairs]
    for name, poses in named:
        if y_down(poses):
            print(
                f"jsve {command}: warning: {name} moves in a plane normal to y (y-down, as KITTI's camera "
                "frame): posyaw's yaw about the world z axis is not a heading there, its alignment is "
                "meaningless; use --align se3",
                file=sys.stderr,
            )


# --------------------------------------------------------------------------------------------------
# evo's result file


def result_paths(path: str, names: Sequence[str]) -> list[Path]:
    """Where each estimate's result file goes: `path` for one estimate, else `<stem>_<name><suffix>`
    beside it (`<stem>_<k>_<name><suffix>` when two estimates share a name)."""
    target = Path(path)
    if len(names) == 1:
        return [target]
    stems = [Path(n).stem for n in names]
    unique = len(set(stems)) == len(stems)
    return [
        target.with_name(
            f"{target.stem}_{s}{target.suffix}" if unique else f"{target.stem}_{k}_{s}{target.suffix}"
        )
        for k, s in enumerate(stems)
    ]


def result_bytes(info: dict, stats: dict, arrays: dict) -> bytes:
    """A zip archive laid out as evo.tools.file_interface.save_res_file writes one: info.json, stats.json
    and one NAME.npy (numpy's format) per array; evo.tools.file_interface.load_res_file reads it."""
    import numpy as np

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("info.json", json.dumps(info))
        archive.writestr("stats.json", json.dumps({k: float(v) for k, v in stats.items()}))
        for name, array in arrays.items():
            npy = io.BytesIO()
            np.save(npy, np.asarray(array))
            archive.writestr(f"{name}.npy", npy.getvalue())
    return buffer.getvalue()


def accumulated(points) -> object:
    """The path length from the first point to each, metres (evo's PosePath3D.distances)."""
    import numpy as np

    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def write_results(
    command: str,
    path: str,
    names: Sequence[str],
    ref_path: str,
    title: str,
    metric: str,
    relation: str,
    table,
    arrays: Sequence[dict],
) -> None:
    """Each estimate's evo result file (`result_paths`); a failed estimate gets none, said on stderr."""
    from jsve.core._pose_error import POSE_RELATIONS
    from jsve.io import _atomic as atomic

    unit = POSE_RELATIONS[relation][1]
    for target, name, row, extra in zip(
        result_paths(path, names), names, table.itertuples(), arrays, strict=True
    ):
        if row.failed:
            print(f"jsve {command}: no result file for {name}: {row.failure_reason}", file=sys.stderr)
            continue
        info = {"title": title, "ref_name": ref_path, "est_name": name, "label": f"{metric} ({unit})"}
        stats = {s: getattr(row, s) for s in STAT_NAMES}
        atomic.write_bytes(target, result_bytes(info, stats, extra))


# --------------------------------------------------------------------------------------------------
# Plots


def finish(
    command: str,
    args: argparse.Namespace,
    *,
    title: str,
    alignment: str,
    relation: str,
    table,
    arrays,
    curves,
    tracks,
    reference,
    extra=(),
) -> int:
    """What `jsve ape` and `jsve rpe` end with: the table (-o), the result files and the figure, all or
    none of them, then the report on the screen. Returns the exit status (0)."""
    from jsve.core._pose_error import POSE_RELATIONS
    from jsve.io import _atomic as atomic

    metric = command.upper()
    with atomic.all_or_nothing():  # the table, the result files and the figure, or none of them
        if args.output:
            atomic.write_text(args.output, table.to_csv(index=False))  # CSV whatever the suffix
        if args.save_results:
            write_results(
                command, args.save_results, list(args.est), args.ref, title, metric, relation, table, arrays
            )
        plot(
            command,
            args,
            title=title,
            alignment=alignment,
            ylabel=f"{metric} ({POSE_RELATIONS[relation][1]})",
            curves=curves,
            trajectories=tracks,
            reference=reference,
            table=table,
        )
    report(table, args, title, alignment, relation, extra)
    return 0


def _top_view_axes(mode: str, ref_points) -> tuple[int, int]:
    import numpy as np

    if mode != "auto":
        return "xyz".index(mode[0]), "xyz".index(mode[1])
    spread = np.ptp(ref_points, axis=0)
    a, b = sorted(np.argsort(spread)[-2:].tolist())
    return a, b


def plot(
    command: str,
    args: argparse.Namespace,
    *,
    title: str,
    alignment: str,
    ylabel: str,
    curves: Sequence[tuple[str, object, object, bool]],
    trajectories: Sequence[tuple[str, object]],
    reference,
    table,
) -> None:
    """The figure of --plot / --save_plot: left the error of each estimate over time (x in seconds, or
    the pose index where the files have no stamps), with rmse, mean and median for a single estimate;
    right the top view of the reference and the aligned estimates.

    Arguments:
        curves: (name, x, errors, timed) per estimate that did not fail.
        trajectories: (name, positions [T, 3]) of the aligned estimates.
        reference: [T, 3] reference positions (metres).
        table: the per-estimate table (its rmse, mean, median).
    """
    if not (args.plot or args.save_plot):
        return
    size = (11.0, 4.5)
    if args.plot:
        import matplotlib.pyplot as plt

        fig = plt.figure(figsize=size, layout="constrained")
    else:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        fig = Figure(figsize=size, layout="constrained")
        FigureCanvasAgg(fig)  # no pyplot, no GUI backend
    left, right = fig.subplots(1, 2, width_ratios=(1.4, 1.0))
    for name, x, errors, _ in curves:
        left.plot(x, errors, lw=0.8, label=Path(name).name if len(curves) > 1 else None)
    if len(curves) == 1:
        row = table.iloc[0]
        for stat, style in (("rmse", "-"), ("mean", "--"), ("median", ":")):
            left.axhline(row[stat], color="k", ls=style, lw=1.0, label=f"{stat} {row[stat]:.4g}")
    timed = all(t for *_, t in curves)
    left.set_xlabel("time (s)" if timed else "pose index")
    left.set_ylabel(ylabel)
    left.grid(alpha=0.3)
    if curves:
        left.legend(loc="upper left", fontsize="small")
    a, b = _top_view_axes(args.plot_mode, reference)
    right.plot(reference[:, a], reference[:, b], color="0.4", ls="--", lw=1.0, label="reference")
    for name, points in trajectories:
        right.plot(points[:, a], points[:, b], lw=0.9, label=Path(name).name)
    right.set_xlabel(f"{'xyz'[a]} (m)")
    right.set_ylabel(f"{'xyz'[b]} (m)")
    right.set_aspect("equal", adjustable="datalim")
    right.grid(alpha=0.3)
    right.legend(loc="best", fontsize="small")
    fig.suptitle(f"{title.splitlines()[0]}; aligned: {alignment}", fontsize="medium")
    if args.save_plot:
        import matplotlib

        from jsve.io import _atomic as atomic

        fmt = Path(args.save_plot).suffix.lower().lstrip(".")
        # Without a date and with a fixed salt for its ids, the same input gives the same SVG.
        with matplotlib.rc_context({"svg.hashsalt": "jsve"}), atomic.atomic_path(args.save_plot) as partial:
            fig.savefig(partial, format=fmt, dpi=150, metadata={"Date": None} if fmt == "svg" else None)
    if args.plot:
        import matplotlib
        import matplotlib.pyplot as plt

        if _interactive(matplotlib.get_backend()):
            plt.show()
        else:
            print(
                f"jsve {command}: --plot needs a display (matplotlib's backend is "
                f"{matplotlib.get_backend()}); --save_plot FILE.png writes the figure",
                file=sys.stderr,
            )
        plt.close(fig)


def _interactive(backend: str) -> bool:
    """Whether a matplotlib backend opens windows."""
    try:
        from matplotlib.backends import BackendFilter, backend_registry

        return backend.lower() in backend_registry.list_builtin(BackendFilter.INTERACTIVE)
    except ImportError:  # matplotlib < 3.9
        from matplotlib import rcsetup

        return backend in getattr(rcsetup, "interactive_bk", ())


def seconds_or_index(pair) -> tuple[object, bool]:
    """A pair's x axis: seconds since its first associated pose, or the pose index without stamps."""
    import numpy as np

    if pair.t is None:
        return np.arange(len(pair.ref), dtype=np.float64), False
    t = np.asarray(pair.t, np.float64)
    return t - t[0], True


def sim3_matrices(transforms):
    """[R, 4, 4] Sim(3) matrices [[s R, t], [0, 1]] of batched transforms (evo's lie.sim3), on the host."""
    import numpy as np

    rotation = np.asarray(transforms.rotation, np.float64)
    matrices = np.zeros((len(rotation), 4, 4))
    matrices[:, :3, :3] = np.asarray(transforms.scale, np.float64)[:, None, None] * rotation
    matrices[:, :3, 3] = np.asarray(transforms.translation, np.float64)
    matrices[:, 3, 3] = 1.0
    return matrices


def enable_x64():
    """A context in which JAX computes in float64 (evo's precision), restored afterwards."""
    import contextlib

    import jax

    @contextlib.contextmanager
    def on():
        previous = jax.config.jax_enable_x64
        jax.config.update("jax_enable_x64", True)
        try:
            yield
        finally:
            jax.config.update("jax_enable_x64", previous)

    return on()
