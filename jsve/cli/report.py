"""`jsve report DIR`: render the report (Markdown, self-contained HTML, figures) of a study or an evaluation.

The folder is what `jsve fit` or `jsve demo` wrote (a fitting study), or what `jsve evaluate -o` wrote (an
evaluation: every rule on every run, nothing fitted); every number of the report comes from its tables.
"""

from __future__ import annotations

from jsve.cli import _common as common

HELP = "render the report of a `jsve fit` / `jsve demo` / `jsve evaluate -o` folder"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report",
        help=HELP,
        description="Write report.md, report.html (figures embedded) and figures/*.png into DIR (or -o OUT) "
        "from DIR's tables: a study's report (headline, figures, held-out comparison, fitted parameters) for "
        "a `jsve fit` or `jsve demo` folder, an evaluation's report for a `jsve evaluate -o` folder. "
        "Deterministic: the same tables give the same files.",
    )
    p.add_argument("folder", metavar="DIR", help="a study folder or a `jsve evaluate -o` folder")
    common.add_output_option(
        p,
        metavar="OUT",
        help="folder to write report.md, report.html, report.json and figures/ to; DIR is only read "
        "(default: DIR itself)",
    )
    p.add_argument(
        "--title",
        default=None,
        help="the page title, kept in the output folder's report.json for later renders (default: the "
        "title kept there, else DIR's, else 'jsve threshold report' or 'jsve evaluation report')",
    )
    p.set_defaults(func=run)


@common.guarded("report")
def run(args) -> int:
    from jsve.report._report import write_report

    try:
        written = write_report(args.folder, title=args.title, output=args.output)
    except (FileNotFoundError, ValueError) as err:
        return common.fail("report", err)
    figures = common.plural(len(written) - 2, "figure")
    print(f"jsve report: {written['html']} ({figures}; Markdown: {written['markdown']})")
    return 0
