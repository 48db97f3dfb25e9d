"""`jsve demo`: simulate a study, evaluate the presets, fit, cross-validate and write the report.

    pip install -e . && jsve demo            # writes ./jsve-demo/report.html in a few minutes

Needs nothing outside the package (procedural EuRoC-like flights); resumable (rerun to finish). A folder
holding a demo of another configuration stops the command (one line, exit 2) unless --force.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import tomllib

from jsve.cli import _common as common

HELP = "simulate a study, fit the rules, cross-validate and write the threshold report"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help=HELP,
        description="Simulate EuRoC-like flights under the seed paper's 31 disturbance settings, evaluate "
        "the presets, fit SVE and ORB-SLAM3 thresholds, cross-validate, and write DIR/report.html.",
    )
    p.add_argument(
        "-o", "--output", default="jsve-demo", metavar="DIR", help="output folder (default: %(default)s)"
    )
    p.add_argument(
        "--config",
        metavar="TOML",
        help="demo and study settings: top-level and [fit] keys for the study, [demo] for the simulation "
        "(default: the built-in settings, which sweeps/demo.toml spells out)",
    )
    p.add_argument(
        "--flights",
        type=int,
        metavar="N",
        help="procedural EuRoC-like flights to simulate (default: --config's [demo] sequences, else 3)",
    )
    # The earlier spelling, hidden: elsewhere --sequences names sequences (simulate --sequences MH_01,V1_01),
    # here it counted flights; old commands keep working.
    p.add_argument("--sequences", type=int, dest="flights", help=argparse.SUPPRESS)
    p.add_argument(
        "--runs", type=int, metavar="N", help="runs per flight and setting (default: --config's, else 2)"
    )
    p.add_argument("--seed", type=int, metavar="N", help="simulator seed (default: --config's, else 0)")
    p.add_argument("--workers", type=int, metavar="N", help="simulator processes (default: all cores)")
    common.add_switch_model_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars (default: shown)")
    p.add_argument(
        "--json",
        action="store_true",
        help="end with one JSON line of the seconds each part took, for scripts (default: the summary only)",
    )
    common.add_force_option(p)
    p.set_defaults(func=run)


@common.guarded("demo")
def run(args) -> int:
    from jsve._jax_cache import enable_compilation_cache
    from jsve.cli._common import use_all_cores

    use_all_cores()  # one XLA CPU device per core: the batched search runs on all of them
    enable_compilation_cache()  # a second run compiles nothing
    from dataclasses import replace

    from jsve._demo import DemoConfig, run_demo

    try:
        config = DemoConfig()
        if args.config:
            try:
                config = DemoConfig.from_dict(
                    tomllib.loads(Path(args.config).read_text()), source=args.config
                )
            except (OSError, tomllib.TOMLDecodeError) as err:
                raise ValueError(f"{args.config}: {err}") from None
        changes = {
            k: v
            for k, v in (("sequences", args.flights), ("runs", args.runs), ("seed", args.seed))
            if v is not None
        }
        config = replace(config, **changes)
        if args.switch_model is not None:
            config = replace(config, study=replace(config.study, switch_model=args.switch_model))
    except (ValueError, TypeError) as err:
        return common.fail("demo", err)
    timings = run_demo(
        args.output, config, progress=not args.no_progress, workers=args.workers, force=args.force
    )
    common.print_study_summary(f"jsve demo: done in {timings['total']:.0f} s", args.output)
    if args.json:
        print(
            json.dumps(
                {k: round(v, 1) if isinstance(v, float) else v for k, v in timings.items() if k != "stages"}
            )
        )
    return 0
