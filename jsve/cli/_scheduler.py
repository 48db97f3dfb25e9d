"""--scheduler, the option of the commands whose tasks can run on a Dask cluster (docs/scaling.md).

The value is checked by jsve.io._scheduler.check_scheduler when the command runs (a wrong one is one
line and exit 2): building the parser imports nothing of the library.
"""

from __future__ import annotations

import argparse

DEFAULT = "local"  # jsve.io._scheduler.DEFAULT_SCHEDULER (not imported: jsve.io loads pandas)


def add_scheduler_option(
    parser: argparse.ArgumentParser,
    shared: str,
    local: str = "an embedded Dask cluster of --workers processes (with --workers 1: this process alone)",
    processes: str = "a process pool of --workers processes, without Dask",
) -> None:
    """--scheduler local|processes|ADDRESS.

    Arguments:
        shared: what a cluster's workers must see under the same absolute paths.
        local, processes: what "local" (the default) and "processes" mean for this command.
    """
    parser.add_argument(
        "--scheduler",
        default=DEFAULT,
        metavar="local|processes|ADDRESS",
        help=f"where the tasks run: local, {local}; processes, {processes}; or a running "
        "Dask cluster: its scheduler's address (tcp://host:8786) or scheduler file (scheduler.json), "
        f"whose workers must have the same jsve and see {shared} under the same absolute paths "
        "(docs/scaling.md), --workers then unused (the cluster has its own)",
    )
