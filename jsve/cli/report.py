"""`jsve report OUT`: render the threshold report (Markdown, self-contained HTML, figures) of a study folder.

The folder is what `jsve fit` or `jsve demo` wrote; every number of the report comes from its tables.
"""

from __future__ import annotations

from jsve.cli import _common as common

HELP = "render the threshold report of a `jsve fit` / `jsve demo` folder"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help=HELP,
        description="Write OUT/report.md, OUT/report.html (figures embedded) and OUT/figures/*.png from the "
        "study's tables. Deterministic: the same tables give the same files.",
    )
    p.add_argument("output", metavar="OUT", help="study folder")
    p.add_argument("--title", default="jsve threshold report")
    p.set_defaults(func=run)


@common.guarded("report")
def run(args) -> int:
    from jsve.report._report import write_report

    try:
        written = write_report(args.output, title=args.title)
    except (FileNotFoundError, ValueError) as err:
        return common.fail("report", err)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0
