"""`jsve tune STUDY.toml -o DIR`: tune a rule in the real front-end's loop (docs/tuning.md).

Records the incumbent (ORB-SLAM3's own rule first), proposes candidates from its logs by replay, races
them on paired runs, repeats from a winner and verifies the result on held-out sequences with fresh
seeds. Resumable: run the same command again after a stop; finished runs are never repeated.
"""

from __future__ import annotations

import sys

from jsve.cli import _common as common
from jsve.cli._scheduler import add_scheduler_option

HELP = "tune a rule in the front-end's loop: the replay proposes, paired runs decide, held-out runs verify"


def register(sub) -> None:
    p = sub.add_parser("tune", help=HELP, description=HELP + ". " + __doc__.split("\n\n")[1])
    p.add_argument("study", metavar="STUDY.toml", help="the study's [tune] table (docs/tuning.md)")
    common.add_output_option(p, metavar="DIR", required=True, help="the tuning's folder")
    p.add_argument(
        "--pool",
        metavar="DIR",
        help="where every front-end run is kept, shared by tunings that use the same runs "
        "(default: DIR/runs)",
    )
    p.add_argument(
        "--root",
        metavar="DIR",
        help="the folder the study's datasets and vocabulary are read from (default: the study's `root`, "
        "else the study file's folder)",
    )
    p.add_argument("--workers", type=int, metavar="N", help="runs at once (default: the study's, else 2)")
    p.add_argument("--budget", type=int, metavar="N", help="front-end runs in all (default: the study's)")
    p.add_argument(
        "--verify-seeds",
        type=int,
        metavar="N",
        help="seeds of the held-out check, the budget moved by the runs that adds: a finished tuning "
        "resumed with more runs its new check seeds alone (default: the study's)",
    )
    add_scheduler_option(
        p,
        shared="BUILD, the vocabulary, the datasets, DIR and the pool",
        local="the drivers started from threads of this process (each driver is its own process)",
        processes="the same",
    )
    common.add_force_option(p)
    common.add_progress_option(p)
    p.set_defaults(func=run)


@common.guarded("tune")
def run(args) -> int:
    from jsve._jax_cache import enable_compilation_cache
    from jsve.tuning import TuneStudy, tune

    enable_compilation_cache()  # the proposals' replays and fits: a resumed tuning compiles nothing again
    scheduler = None if args.scheduler == "local" else args.scheduler
    try:
        study = TuneStudy.from_toml(
            args.study, root=args.root, workers=args.workers, budget=args.budget, scheduler=scheduler
        )
        if args.verify_seeds is not None:
            study = study.with_check_seeds(args.verify_seeds)
        state = tune(study, args.output, pool=args.pool, force=args.force, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as err:
        return common.fail("tune", err)
    role = "the new incumbent" if state["tuned_is_incumbent"] else "best challenger; the incumbent stayed"
    print(f"jsve tune: {state['tuned']} ({role}), {state['runs_used']} runs; stopped: {state['stopped']}")
    for row in state["check"]:
        if row["scope"] == "all held-out":
            cm = {k: 100 * row[k] for k in ("mean_diff_m", "bca_low_m", "bca_high_m")}
            tracked = {k: 100 * row[f"tracked_{k}"] for k in ("mean_diff_m", "bca_low_m", "bca_high_m")}
            print(
                f"  vs {row['baseline']}: {cm['mean_diff_m']:+.2f} cm [{cm['bca_low_m']:+.2f}, "
                f"{cm['bca_high_m']:+.2f}] (95 % BCa, {row['pairs']} held-out pairs, Wilcoxon p = "
                f"{row['wilcoxon_p']:.3g}); lost alone {row['rule_only_lost']} / {row['baseline_only_lost']} "
                f"(McNemar p = {row['lost_p']:.3g}); on the {row['tracked_pairs']} pairs neither lost "
                f"{tracked['mean_diff_m']:+.2f} cm [{tracked['bca_low_m']:+.2f}, "
                f"{tracked['bca_high_m']:+.2f}]"
            )
    print(f"  report: jsve report {args.output}", file=sys.stderr)
    return 0
