"""jsve.io._importers: the SVE authors' SceneVisibilityEstimation.txt and the seed's CSV."""

from __future__ import annotations

import numpy as np
import pytest

from jsve.io._importers import (
    FORMAT_HAGGART,
    FORMAT_SEED,
    SVE_COLUMNS,
    read_haggart_sve,
    read_seed_sve_csv,
    read_sve_output,
)
from jsve.io._logs import LogFormatError


def _write(tmp_path, name: str, content: str | bytes):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8"))
    return path


def _bits(values) -> list[int]:
    return np.asarray(values, dtype=np.float64).view(np.uint64).tolist()


# --------------------------------------------------------------------------------------------------
# SceneVisibilityEstimation.txt (Haggart)


HAGGART = (
    "1403636579.763555584 0.873 0.95 0.81 0.79\n"  # single spaces, as Haggart's writer
    "1403636579.8135555845  0.1\t-0.2 1.25 1e-3\r\n"  # tabs, repeated spaces, CRLF, 10 decimals
    "1403636579.8635555855 .5 5. +0.30000000000000004 0\n"
    "1403636580 1 1 1 1"  # integer seconds, no final newline
)


def test_haggart_reads_exact_stamps_and_values(tmp_path):
    path = _write(tmp_path, "SceneVisibilityEstimation.txt", HAGGART)
    df = read_haggart_sve(path)
    assert list(df.columns) == list(SVE_COLUMNS)
    assert df["t_ns"].dtype == np.int64 and all(df[c].dtype == np.float64 for c in SVE_COLUMNS[1:])
    assert df.attrs == {"source": str(path), "format": FORMAT_HAGGART}
    # Decimal seconds -> ns exactly; a half nanosecond rounds to even (...584.5 -> 584, ...585.5 -> 586).
    assert df["t_ns"].tolist() == [
        1403636579763555584,
        1403636579813555584,
        1403636579863555586,
        1403636580000000000,
    ]
    assert _bits(df["sve"]) == _bits([0.873, 0.1, 0.5, 1.0])
    assert _bits(df["s_a"]) == _bits([0.95, -0.2, 5.0, 1.0])
    assert _bits(df["s_b"]) == _bits([0.81, 1.25, 0.30000000000000004, 1.0])  # unclamped, as Haggart's
    assert _bits(df["s_c"]) == _bits([0.79, 1e-3, 0.0, 1.0])


def test_haggart_small_stamps_are_seconds(tmp_path):
    """Stamps as Haggart's bag files give them (a 100000 s offset); jsve keeps them as written."""
    df = read_haggart_sve(_write(tmp_path, "S.txt", "100000.05 0.5 0.5 0.5 0.5\n100000.1 0.5 0.5 0.5 0.5\n"))
    assert df["t_ns"].tolist() == [100_000_050_000_000, 100_000_100_000_000]


OK = "1 0.5 0.5 0.5 0.5\n"  # a valid first line (t = 1 s)
FIELDS_H = "(t SVE a b c, separated by whitespace)"
FIELDS_S = "(Time SVE SVE_a SVE_b SVE_c, separated by commas)"
INCREASING = "(stamps must be strictly increasing)"
EMPTY = "empty line (one line per frame, none blank)"

HAGGART_ERRORS = [
    # (content, line, message after "path:line: ")
    (OK + "2 0.5 0.5 0.5\n", 2, f"field 'c': missing: the line has 4 of 5 fields {FIELDS_H}"),
    (
        OK + "2 0.5 0.5 0.5 0.5 x\n",
        2,
        f"field 'c' = 'x': too many fields: the line has 6, expected 5 {FIELDS_H}",
    ),
    (OK + OK.replace("1", "2") + "3 nan 0.5 0.5 0.5\n", 3, "field 'SVE' = 'nan': not a finite number"),
    (OK + "2 0.5 -inf 0.5 0.5\n", 2, "field 'a' = '-inf': not a finite number"),
    ("1 0.5 0.5 0.5x 0.5\n", 1, "field 'b' = '0.5x': not a number"),
    (OK + "1_000 0.5 0.5 0.5 0.5\n", 2, "field 't' = '1_000': not a number"),
    ("1 0.5 0.5 1e999 0.5\n", 1, "field 'b' = '1e999': not a finite number (overflows a double)"),
    (OK + "2 0.5 0.5 0.5 0x1p-2\n", 2, "field 'c' = '0x1p-2': not a number"),
    (
        OK + "2 1 1 1 1\n2.0 1 1 1 1\n",
        3,
        f"field 't' = '2000000000 ns': the same stamp as line 2 {INCREASING}",
    ),
    (
        OK + "3 1 1 1 1\n4 1 1 1 1\n2 1 1 1 1\n",
        4,
        f"field 't' = '2000000000 ns': earlier than line 3 {INCREASING}",
    ),
    (OK + "2 1 1 1 1\n\n3 1 1 1 1\n", 3, EMPTY),
    (OK + "2 1 1 1 1\n\n", 3, EMPTY),
    (OK + " \t \n", 2, EMPTY),
    (OK.encode() + b"2 0.5 0.5 \xff 0.5\n", 2, "not UTF-8 text (invalid start byte)"),
    ("1e10 0.5 0.5 0.5 0.5\n", 1, "field 't' = '1e10': out of the int64 nanosecond range"),
]


@pytest.mark.parametrize(("content", "line", "message"), HAGGART_ERRORS)
def test_haggart_errors_name_file_line_and_field(tmp_path, content, line, message):
    path = _write(tmp_path, "SceneVisibilityEstimation.txt", content)
    with pytest.raises(LogFormatError) as info:
        read_haggart_sve(path)
    assert str(info.value) == f"{path}:{line}: {message}"
    assert info.value.line == line and info.value.path == str(path)


def test_haggart_empty_file(tmp_path):
    path = _write(tmp_path, "S.txt", "")
    with pytest.raises(LogFormatError) as info:
        read_haggart_sve(path)
    assert str(info.value) == f"{path}: no rows: the file holds no frames"


# --------------------------------------------------------------------------------------------------
# The seed's CSV


SEED = (
    "\ufeffTime,SVE,SVE_a,SVE_b,SVE_c\r\n"  # byte-order mark and CRLF, as Windows tools write
    "9007199254740992,0.5,0.25,0.75,1\r\n"
    "9007199254740993, 0.1 ,0.2,0.3,0.4\r\n"  # 2^53 + 1: integer nanoseconds never pass through a float
    "9007199254740994.000,1e-300,-0.0,0.30000000000000004,5e-324\r\n"
)


def test_seed_csv_reads_exact_integers_and_values(tmp_path):
    path = _write(tmp_path, "sve.csv", SEED)
    df = read_seed_sve_csv(path)
    assert list(df.columns) == list(SVE_COLUMNS)
    assert df.attrs == {"source": str(path), "format": FORMAT_SEED}
    assert df["t_ns"].dtype == np.int64
    assert df["t_ns"].tolist() == [2**53, 2**53 + 1, 2**53 + 2]
    assert _bits(df["sve"]) == _bits([0.5, 0.1, 1e-300])
    assert _bits(df["s_a"]) == _bits([0.25, 0.2, -0.0])  # the sign of zero survives
    assert _bits(df["s_b"]) == _bits([0.75, 0.3, 0.30000000000000004])
    assert _bits(df["s_c"]) == _bits([1.0, 0.4, 5e-324])


def test_seed_csv_euroc_stamps(tmp_path):
    path = _write(
        tmp_path,
        "sve.csv",
        "Time,SVE,SVE_a,SVE_b,SVE_c\n1403636579763555584,1,1,1,1\n1403636579813555456,0,0,0,0\n",
    )
    assert read_seed_sve_csv(path)["t_ns"].tolist() == [1403636579763555584, 1403636579813555456]


HEADER = "Time,SVE,SVE_a,SVE_b,SVE_c\n"
BAD_HEADER = "the header must be 'Time,SVE,SVE_a,SVE_b,SVE_c', found"
INTEGER_NS = "must be integer nanoseconds (a fraction or exponent notation loses nanoseconds)"

SEED_ERRORS = [
    ("time,SVE,SVE_a,SVE_b,SVE_c\n1,1,1,1,1\n", 1, f"{BAD_HEADER} 'time,SVE,SVE_a,SVE_b,SVE_c'"),
    ("Time,SVE,SVE_a,SVE_b,SVE_c,\n1,1,1,1,1\n", 1, f"{BAD_HEADER} 'Time,SVE,SVE_a,SVE_b,SVE_c,'"),
    (HEADER + "1,1,1,1,1\n1.4036e+18,1,1,1,1\n", 3, f"field 'Time' = '1.4036e+18': {INTEGER_NS}"),
    (HEADER + "12.5,1,1,1,1\n", 2, f"field 'Time' = '12.5': {INTEGER_NS}"),
    (HEADER + "abc,1,1,1,1\n", 2, "field 'Time' = 'abc': not a number"),
    (HEADER + "1,1,1,1,1\n2,1,1,inf,1\n", 3, "field 'SVE_b' = 'inf': not a finite number"),
    (
        HEADER + "1,1,1,1,1\n2,1,1,1,1\n3,1,1,1\n",
        4,
        f"field 'SVE_c': missing: the line has 4 of 5 fields {FIELDS_S}",
    ),
    (
        HEADER + "1,1,1,1,1,9\n",
        2,
        f"field 'SVE_c' = '9': too many fields: the line has 6, expected 5 {FIELDS_S}",
    ),
    (HEADER + "1,1,,1,1\n", 2, "field 'SVE_a' = '': not a number"),
    (
        HEADER + "5,1,1,1,1\n6,1,1,1,1\n4,1,1,1,1\n",
        4,
        f"field 'Time' = '4 ns': earlier than line 3 {INCREASING}",
    ),
    (
        HEADER + "5,1,1,1,1\n5.00,1,1,1,1\n",
        3,
        f"field 'Time' = '5 ns': the same stamp as line 2 {INCREASING}",
    ),
    (HEADER + "1,1,1,1,1\n\n2,1,1,1,1\n", 3, EMPTY),
    (
        HEADER + "9223372036854775808,1,1,1,1\n",
        2,
        "field 'Time' = '9223372036854775808': out of the int64 nanosecond range",
    ),
]


@pytest.mark.parametrize(("content", "line", "message"), SEED_ERRORS)
def test_seed_csv_errors_name_file_line_and_field(tmp_path, content, line, message):
    path = _write(tmp_path, "sve.csv", content)
    with pytest.raises(LogFormatError) as info:
        read_seed_sve_csv(path)
    assert str(info.value) == f"{path}:{line}: {message}"
    assert info.value.line == line


@pytest.mark.parametrize(
    ("content", "message"),
    [("", "empty file: no header and no rows"), (HEADER, "no rows: the file holds no frames")],
)
def test_seed_csv_without_rows(tmp_path, content, message):
    path = _write(tmp_path, "sve.csv", content)
    with pytest.raises(LogFormatError) as info:
        read_seed_sve_csv(path)
    assert str(info.value) == f"{path}: {message}"


# --------------------------------------------------------------------------------------------------
# Dispatch


def test_read_sve_output_picks_the_format(tmp_path):
    seed = _write(tmp_path, "a.csv", SEED)
    haggart = _write(tmp_path, "SceneVisibilityEstimation.txt", HAGGART)
    assert read_sve_output(seed).attrs["format"] == FORMAT_SEED
    assert read_sve_output(haggart).attrs["format"] == FORMAT_HAGGART
    a, b = read_sve_output(seed), read_seed_sve_csv(seed)
    assert a.equals(b)
    # A seed file with a broken header is not mistaken for Haggart's format: it fails as the seed's.
    broken = _write(tmp_path, "b.csv", "Time;SVE;SVE_a;SVE_b;SVE_c\n1;1;1;1;1\n")
    with pytest.raises(LogFormatError, match=r"b\.csv:1: the header must be"):
        read_sve_output(broken)
