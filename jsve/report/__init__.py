"""jsve.report: the threshold report (Markdown + self-contained HTML) from a fit's tables."""

from jsve.report._report import write_report as write_report
