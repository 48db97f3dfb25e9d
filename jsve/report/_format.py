"""Numbers and words of the report: lengths in cm, shares in %, parameters to a sensible digit, never
scientific notation; disturbance levels with their units; Markdown and HTML tables.

One home for every number the report prints, so that a table, a sentence and a figure label show the same
digits.
"""

from __future__ import annotations

import html
import math
import re

import numpy as np
import pandas as pd

LENGTH_UNIT = "cm"
"""Every length of the report (ATE, objective, differences) is printed in centimetres, 1 decimal: the
ATE of a run that keeps tracking is centimetres (ORB-SLAM3 on EuRoC), so 1 mm is the last digit that
carries information."""

DISTURBANCE_AXES = {
    "blur": ("blur kernel n", "n x n px"),
    "downsample": ("downsampling scale factor s", "image scaled by s"),
    "occlusion": ("occluder side n", "n x n px square"),
    "noise": ("sensor noise sigma", "DN"),
    "low_light": ("light fraction k", "irradiance times k"),
    "motion_blur": ("motion-blur streak length", "px"),
    "haze": ("haze optical depth tau", "t = exp(-tau)"),
    "lens_dirt": ("lens dirt mean opacity", "0-1"),
}
"""Name and unit of each disturbance's level (jsve.image._disturb.DISTURBANCES gives the same units; the
report layer may not import the image layer, so tests/test_report.py checks that both name the same
disturbances)."""

SEVERITY_FALLS_WITH_LEVEL = frozenset({"downsample", "low_light"})
"""Disturbances that grow harsher as their level falls (s = 1 and k = 1 leave the image as it is):
figures draw their level axis decreasing, so that every panel reads mild to harsh from left to right."""


def level_axis(disturbance: str) -> str:
    """Axis label of a disturbance's level, with its unit: "blur kernel n (n x n px)"."""
    name, unit = DISTURBANCE_AXES.get(disturbance, (f"{disturbance} level", ""))
    return f"{name} ({unit})" if unit else name


def number(x, digits: int = 4) -> str:
    """A plain number: integers as integers with thousands separated ("1,024"), floats to `digits`
    significant digits in positional notation (never 1e-05); '-' for None and NaN, yes/no for booleans,
    other values as text."""
    if x is None or (isinstance(x, (float, np.floating)) and not np.isfinite(x)):
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if x == int(x) and abs(x) < 1e15:
            return f"{int(x):,}"
        return np.format_float_positional(x, precision=digits, unique=False, fractional=False, trim="-")
    return str(x)


def cm(metres, *, sign: bool = False) -> str:
    """A length in metres as centimetres, 1 decimal ("3.9"); `sign`: differences with + or -; a value
    that rounds to zero is "0.0" (never "-0.0")."""
    if metres is None or not np.isfinite(metres):
        return "-"
    value = round(100.0 * float(metres), 1)
    if value == 0:
        return "0.0"
    return f"{value:+.1f}" if sign else f"{value:.1f}"


def cm_ci(mean, low, high, *, sign: bool = False) -> str:
    """ "3.9 [3.3, 4.6]" (centimetres); "-" without a mean, the bare mean without an interval."""
    if mean is None or not np.isfinite(mean):
        return "-"
    if low is None or high is None or not (np.isfinite(low) and np.isfinite(high)):
        return cm(mean, sign=sign)
    return f"{cm(mean, sign=sign)} [{cm(low, sign=sign)}, {cm(high, sign=sign)}]"


def percent(share) -> str:
    """A share in [0, 1] as a percentage: 1 decimal, 2 below 0.1 %, "< 0.01 %" below that, "0 %" and
    "100 %" exactly."""
    if share is None or not np.isfinite(share):
        return "-"
    p = 100.0 * float(share)
    if p == 0:
        return "0 %"
    if p == 100:
        return "100 %"
    if p < 0.01:
        return "< 0.01 %"
    if p < 0.1:
        return f"{p:.2f} %"
    return f"{p:.1f} %"


def decimals_for(span: float) -> int:
    """Decimals that resolve 0.5 % of a parameter's search range, at least 1 (0.6 -> 3, 8 -> 2,
    200 -> 1); 3 where the range is unknown."""
    if not (np.isfinite(span) and span > 0):
        return 3
    return max(1, math.ceil(-math.log10(0.005 * span)))


def span_mm(metres: float) -> str:
    """A small length difference in millimetres: "0.06 mm", "less than 0.01 mm"."""
    mm = 1000.0 * abs(float(metres))
    return "less than 0.01 mm" if mm < 0.01 else f"{mm:.2f} mm"


def metres(x) -> str:
    """A configured length in metres as set ("1 m", "0.5 m")."""
    return f"{number(float(x), 3)} m"


def fixed(x, decimals: int) -> str:
    """x with a fixed number of decimals; '-' for None/NaN; never "-0.000"."""
    if x is None or not np.isfinite(x):
        return "-"
    text = f"{float(x):.{decimals}f}"
    return text[1:] if re.fullmatch(r"-0\.?0*", text) else text


def count(n: int, noun: str) -> str:
    """ "1 run", "186 runs"."""
    return f"{n:,} {noun}" + ("" if n == 1 else "s")


def words_list(items) -> str:
    """ "a", "a and b", "a, b and c"."""
    items = [str(i) for i in items]
    if len(items) <= 1:
        return "".join(items)
    return ", ".join(items[:-1]) + " and " + items[-1]


# ---------------------------------------------------------------------------------------------------
# Tables

_NUMERIC = re.compile(r"^\[?([-+<]\s?)?\d|^-( \(n = 0\))?$")
"""Text that reads as a number: it starts with a digit (after a sign or '<'), or is '-'."""


def _is_numeric_column(values) -> bool:
    """A column is right-aligned when every cell is a number, or text that starts as one ("3.9 [3.3,
    4.6]", "2.2 (0 %)", "< 0.01 %"), or '-'."""
    for v in values:
        if isinstance(v, str):
            if not _NUMERIC.match(v.strip()):
                return False
        elif not isinstance(v, (int, float, np.integer, np.floating, bool, np.bool_)) and v is not None:
            return False
    return True


def alignments(table: pd.DataFrame) -> list[str]:
    """'r' for columns of numbers, 'l' for columns of words, in column order."""
    return ["r" if _is_numeric_column(table[c].tolist()) else "l" for c in table.columns]


def markdown_table(table: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table: words left-aligned, numbers right-aligned; float cells to 4
    significant digits without scientific notation (columns the report formats itself are text)."""
    align = alignments(table)
    head = "| " + " | ".join(map(str, table.columns)) + " |"
    rule = "|" + "|".join("---:" if a == "r" else ":---" for a in align) + "|"
    rows = ["| " + " | ".join(number(v) for v in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join([head, rule, *rows])


SHORT_TEXT = 28
"""Word cells up to this many characters (rule names, fold kinds) stay on one line in HTML."""


def _cell_class(text: str, align: str) -> str:
    if align == "r":
        return "n"
    return "w" if len(text) <= SHORT_TEXT else "t"


def html_table(table: pd.DataFrame) -> str:
    """The same table in HTML: class "n" on number cells (right-aligned, one line), "w" on short words
    (left-aligned, one line), "t" on longer text (left-aligned, wrapped)."""
    align = alignments(table)
    head = "".join(
        f'<th class="{"n" if a == "r" else "w"}">{html.escape(str(c))}</th>'
        for c, a in zip(table.columns, align, strict=True)
    )
    body = "".join(
        "<tr>"
        + "".join(
            f'<td class="{_cell_class(text, a)}">{html.escape(text)}</td>'
            for text, a in zip(map(number, row), align, strict=True)
        )
        + "</tr>"
        for row in table.itertuples(index=False)
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def inline_html(text: str) -> str:
    """The report's inline Markdown (`code` and **bold**) as HTML, everything else escaped."""
    out = html.escape(text, quote=False)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", out)
