"""Importers for the SVE authors' own outputs: per-frame metric time series, without poses.

Runs of the original SVE implementations cannot be replayed (they hold no poses), but their metric
time series feed jsve's metric analysis and plots. Two formats (docs/frontend.md, section 5):

    SceneVisibilityEstimation.txt   Haggart & Aitken: no header, `t SVE a b c` per line, t in seconds
    the seed's CSV                  Rugg-Gunn & Aitken: header `Time,SVE,SVE_a,SVE_b,SVE_c`, Time in ns

Both read into the same DataFrame: `t_ns` (int64 nanoseconds), `sve`, `s_a`, `s_b`, `s_c` (float64),
one row per frame, with `attrs["source"]` (the path) and `attrs["format"]`. For jsve.core._sve, stack the
components: `np.stack([df.s_a, df.s_b, df.s_c], axis=-1)`.

Validation is strict; every error is a jsve.io._logs.LogFormatError naming the file, the 1-based line and
the field as the format names it, e.g. `run7/SceneVisibilityEstimation.txt:12: field 'SVE' = 'nan':
not a finite number`.
"""

from __future__ import annotations

import math
import os
import re
from decimal import ROUND_HALF_EVEN, Decimal

import numpy as np
import pandas as pd

from jsve.io import _text as text
from jsve.io._errors import LogFormatError, shorten

SVE_COLUMNS = ("t_ns", "sve", "s_a", "s_b", "s_c")
"""Columns of every imported series, in order."""

HAGGART_FIELDS = ("t", "SVE", "a", "b", "c")
"""Fields of a SceneVisibilityEstimation.txt line, as Haggart's scripts name them."""

SEED_HEADER = ("Time", "SVE", "SVE_a", "SVE_b", "SVE_c")
"""Header of the seed's CSV."""

FORMAT_HAGGART = "haggart_txt"
FORMAT_SEED = "seed_csv"

_INTEGER_NS = re.compile(r"[+-]?[0-9]+(?:\.0*)?")
"""Integer nanoseconds; a fractional part of zeros ('1403636579763555584.000') is accepted."""
_NS_PER_S = Decimal(10) ** 9


def read_haggart_sve(path: str | os.PathLike) -> pd.DataFrame:
    """Read a SceneVisibilityEstimation.txt written by Haggart & Aitken's ORB-SLAM SVE.

    Each line is `t SVE a b c`, separated by whitespace (CRLF line endings and a UTF-8 byte-order
    mark are tolerated), t in seconds. Seconds become int64
    nanoseconds in exact decimal arithmetic (rounded half-even below 1 ns), never through a float.
    Values are not range-checked: Haggart's S_b and S_c are unclamped.

    Arguments:
        path: the file.

    Returns:
        DataFrame with columns SVE_COLUMNS (t_ns int64, the rest float64); attrs["format"] is
        "haggart_txt".

    Raises:
        LogFormatError: naming file, line and field (t, SVE, a, b, c): a line without exactly five
            fields, a value that is not a finite decimal number, stamps not strictly increasing,
            an empty line before the end, or a file without rows.
    """
    source = os.fspath(path)
    rows = []
    for lineno, line in _lines(source):
        fields = line.split()
        _check_count(fields, HAGGART_FIELDS, source, lineno, "separated by whitespace")
        t_ns = _seconds_to_ns(fields[0], source, lineno)
        values = [
            _finite(f, name, source, lineno) for f, name in zip(fields[1:], HAGGART_FIELDS[1:], strict=True)
        ]
        rows.append((lineno, t_ns, values))
    return _frame(rows, source, FORMAT_HAGGART, HAGGART_FIELDS[0])


def read_seed_sve_csv(path: str | os.PathLike) -> pd.DataFrame:
    """Read the seed's SVE CSV (Rugg-Gunn & Aitken's ORB-SLAM3 SVE): `Time,SVE,SVE_a,SVE_b,SVE_c`.

    Time is integer nanoseconds (EuRoC's clock); a fractional part of zeros is accepted, exponent
    notation is not (`1.4036e+18` has already lost its nanoseconds). Spaces around fields, CRLF line
    endings and a UTF-8 byte-order mark are tolerated.

    Arguments:
        path: the file.

    Returns:
        DataFrame with columns SVE_COLUMNS (t_ns int64, the rest float64); attrs["format"] is
        "seed_csv".

    Raises:
        LogFormatError: naming file, line and field (Time, SVE, SVE_a, SVE_b, SVE_c): a wrong header,
            a row without exactly five fields, a Time that is not integer nanoseconds, a value that is
            not a finite decimal number, stamps not strictly increasing, an empty line before the
            end, or a file without rows.
    """
    source = os.fspath(path)
    lines = _lines(source)
    header = next(lines, None)
    if header is None:
        raise LogFormatError(source, None, "empty file: no header and no rows")
    lineno, line = header
    names = tuple(f.strip() for f in line.split(","))
    if names != SEED_HEADER:
        raise LogFormatError(
            source, lineno, f"the header must be '{','.join(SEED_HEADER)}', found '{shorten(line)}'"
        )
    rows = []
    for lineno, line in lines:
        fields = [f.strip() for f in line.split(",")]
        _check_count(fields, SEED_HEADER, source, lineno, "separated by commas")
        t_ns = _integer_ns(fields[0], source, lineno)
        values = [
            _finite(f, name, source, lineno) for f, name in zip(fields[1:], SEED_HEADER[1:], strict=True)
        ]
        rows.append((lineno, t_ns, values))
    return _frame(rows, source, FORMAT_SEED, SEED_HEADER[0])


def read_sve_output(path: str | os.PathLike) -> pd.DataFrame:
    """Read either format, chosen by the first line: a `Time,...` header is the seed's CSV, anything
    else a SceneVisibilityEstimation.txt. See `read_seed_sve_csv` and `read_haggart_sve`."""
    with open(path, "rb") as f:
        start = f.read(64)
    if start.removeprefix(b"\xef\xbb\xbf").lstrip(b" \t").startswith(b"Time"):
        return read_seed_sve_csv(path)
    return read_haggart_sve(path)


# --------------------------------------------------------------------------------------------------


def _lines(source: str):
    """(1-based line number, text without the line ending) of every line; an empty line other than the
    end of the file is an error, and a UTF-8 byte-order mark at the start is dropped."""
    with open(source, "rb") as f:
        data = f.read()
    raw_lines = data.split(b"\n")
    if raw_lines and raw_lines[-1] == b"":
        raw_lines.pop()  # the newline that ends the last line
    for i, raw in enumerate(raw_lines):
        lineno = i + 1
        try:
            line = raw.decode("utf-8-sig" if i == 0 else "utf-8").rstrip("\r")
        except UnicodeDecodeError as e:
            raise LogFormatError(source, lineno, f"not UTF-8 text ({e.reason})") from None
        if not line.strip():
            raise LogFormatError(source, lineno, "empty line (one line per frame, none blank)")
        yield lineno, line


def _check_count(fields: list[str], names: tuple[str, ...], source: str, lineno: int, how: str) -> None:
    n, want = len(fields), len(names)
    if n < want:
        raise LogFormatError(
            source,
            lineno,
            f"missing: the line has {n} of {want} fields ({' '.join(names)}, {how})",
            column=names[n],
            what="field",
        )
    if n > want:
        raise LogFormatError(
            source,
            lineno,
            f"too many fields: the line has {n}, expected {want} ({' '.join(names)}, {how})",
            column=names[-1],
            value=fields[want],
            what="field",
        )


def _finite(field: str, name: str, source: str, lineno: int) -> float:
    if text.DECIMAL.fullmatch(field):
        value = float(field)
        if math.isfinite(value):
            return value
        raise LogFormatError(
            source, lineno, "not a finite number (overflows a double)", column=name, value=field, what="field"
        )
    reason = "not a finite number" if text.is_non_finite_word(field) else "not a number"
    raise LogFormatError(source, lineno, reason, column=name, value=field, what="field")


def _seconds_to_ns(field: str, source: str, lineno: int) -> int:
    if not text.DECIMAL.fullmatch(field):
        _finite(field, HAGGART_FIELDS[0], source, lineno)  # raises with the right reason
    ns = int((Decimal(field) * _NS_PER_S).to_integral_value(rounding=ROUND_HALF_EVEN))
    return _in_int64(ns, field, HAGGART_FIELDS[0], source, lineno)


def _integer_ns(field: str, source: str, lineno: int) -> int:
    name = SEED_HEADER[0]
    if not _INTEGER_NS.fullmatch(field):
        if text.DECIMAL.fullmatch(field):
            raise LogFormatError(
                source,
                lineno,
                "must be integer nanoseconds (a fraction or exponent notation loses nanoseconds)",
                column=name,
                value=field,
                what="field",
            )
        _finite(field, name, source, lineno)  # raises: not a (finite) number
    return _in_int64(int(Decimal(field)), field, name, source, lineno)


def _in_int64(ns: int, field: str, name: str, source: str, lineno: int) -> int:
    if not text.in_int64(ns):
        raise LogFormatError(
            source, lineno, "out of the int64 nanosecond range", column=name, value=field, what="field"
        )
    return ns


def _frame(rows: list, source: str, fmt: str, time_name: str) -> pd.DataFrame:
    if not rows:
        raise LogFormatError(source, None, "no rows: the file holds no frames")
    lines = [r[0] for r in rows]
    t_ns = np.array([r[1] for r in rows], dtype=np.int64)
    bad = np.diff(t_ns) <= 0
    if bad.any():
        k = int(np.argmax(bad)) + 1
        same = t_ns[k] == t_ns[k - 1]
        reason = (
            f"{'the same stamp as' if same else 'earlier than'} line {lines[k - 1]} "
            "(stamps must be strictly increasing)"
        )
        shown = str(int(t_ns[k]))
        raise LogFormatError(source, lines[k], reason, column=time_name, value=f"{shown} ns", what="field")
    values = np.array([r[2] for r in rows], dtype=np.float64)
    frame = pd.DataFrame(
        {"t_ns": t_ns, "sve": values[:, 0], "s_a": values[:, 1], "s_b": values[:, 2], "s_c": values[:, 3]},
        columns=list(SVE_COLUMNS),
    )
    frame.attrs["source"] = source
    frame.attrs["format"] = fmt
    return frame
