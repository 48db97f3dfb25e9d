"""jsve.io._text: the number grammar and formatting, strict metadata JSON, and the magic-line layout."""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jsve.io import _text as text
from jsve.io._errors import LogFormatError

# --------------------------------------------------------------------------------------------------
# Numbers


@pytest.mark.parametrize("field", ["0", "-3", "+2.5", ".5", "5.", "1e3", "-1.25E-07", "007"])
def test_decimal_accepts_plain_numbers(field):
    assert text.DECIMAL.fullmatch(field) and math.isfinite(float(field))


@pytest.mark.parametrize("field", ["nan", "inf", "1_000", "0x10", "1e", "", " 1", "١٢", "--1", "1.2.3"])
def test_decimal_rejects_what_float_would_take_or_nothing_is(field):
    # Python's float() reads several of these ('nan', '1_000', the Arabic-Indic digits); a file must not.
    assert not text.DECIMAL.fullmatch(field)


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_every_finite_double_formats_to_a_decimal_that_reads_back(x):
    written = text.format_value(x)
    assert text.DECIMAL.fullmatch(written) and float(written) == x


def test_format_value_keeps_integers_exact():
    assert text.format_value(np.int64(2**62 + 1)) == str(2**62 + 1)
    assert text.format_value(np.float64(0.1)) == "0.1"


def test_non_finite_words_and_int64_range():
    assert all(text.is_non_finite_word(w) for w in ("nan", "NaN", "-inf", "+Infinity"))
    assert not text.is_non_finite_word("1e999")  # overflows, but is a number in the grammar
    assert text.in_int64(2**63 - 1) and not text.in_int64(2**63)
    assert text.in_int64(-(2**63)) and not text.in_int64(-(2**63) - 1)
    assert text.INT64_TEXT.fullmatch("-12") and not text.INT64_TEXT.fullmatch("+12")


# --------------------------------------------------------------------------------------------------
# Metadata JSON


def test_load_meta_rejects_non_finite_constants():
    assert text.load_meta('{"fps": 20.0}', "a.csv") == {"fps": 20.0}
    for bad in ('{"level": NaN}', '{"level": Infinity}', '{"a": 1'):
        with pytest.raises(LogFormatError, match=r"^a\.csv:1: metadata is not valid JSON"):
            text.load_meta(bad, "a.csv")


def test_canonical_meta_is_what_the_file_reads_back():
    meta = {"image_size": (752, 480), "fps": np.float32(20.0), "run": np.int64(3), "g": np.zeros(3)}
    assert text.canonical_meta(meta, "<memory>") == {
        "image_size": [752, 480],
        "fps": 20.0,
        "run": 3,
        "g": [0.0, 0.0, 0.0],
    }
    with pytest.raises(LogFormatError, match="metadata cannot be written as JSON"):
        text.canonical_meta({"level": float("nan")}, "<memory>")
    with pytest.raises(LogFormatError, match="of type object is not JSON serialisable"):
        text.canonical_meta({"x": object()}, "<memory>")


def test_json_types_do_not_take_booleans_for_numbers():
    assert text.is_type(3, int) and not text.is_type(True, int) and text.is_type(True, (bool, int))
    assert text.type_name((int, float)) == "an integer or a number"


# --------------------------------------------------------------------------------------------------
# The magic-line layout


def test_head_rows_tail_cut_back_into_their_sections():
    meta = {"sequence": "MH_04", "run": 7}
    table = pa.table({"t_ns": pa.array([5, 9], pa.int64()), "x": [0.1, -2.5]})
    data = text.head("# fmt v1 ", meta, ["t_ns", "x"]) + text.write_rows(table) + text.tail("# end n=", 2)
    assert data == b'# fmt v1 {"sequence": "MH_04", "run": 7}\nt_ns,x\n5,0.1\n9,-2.5\n# end n=2\n'
    parts = text.cut(data)
    assert parts.first == b'# fmt v1 {"sequence": "MH_04", "run": 7}'
    assert parts.header == b"t_ns,x" and parts.rows == b"5,0.1\n9,-2.5\n"
    assert parts.last == "# end n=2" and parts.n_lines == 5
    assert text.end_count(parts.last, "# end n=") == "2"
    back = text.read_rows(parts.rows, ["t_ns", "x"], {"t_ns"})
    assert back.equals(table)
    assert text.raw_line(parts.rows, 1) == b"9,-2.5" and text.raw_field(b"9,-2.5", 1) == "-2.5"
    assert text.raw_field(b"9,-2.5", 5) == ""


def test_cut_finds_what_an_unfinished_file_lacks():
    one_line = text.cut(b'# fmt v1 {"a": 1}')
    assert one_line.last is None and one_line.header is None and one_line.n_lines == 1
    no_header = text.cut(b'# fmt v1 {"a": 1}\r\n# end n=0\r\n\n')
    assert no_header.header is None and no_header.last == "# end n=0" and no_header.n_lines == 2
    died = text.cut(b"# m\nt_ns,x\n5,0.1\n9,-2")
    assert died.last == "9,-2" and text.end_count(died.last, "# end n=") is None
    assert text.is_count("12") and not text.is_count("-1") and not text.is_count("1.0")


def test_write_rows_of_no_rows_is_empty():
    assert text.write_rows(pa.table({"a": pa.array([], pa.int64())})) == b""


def test_read_rows_keeps_int64_exact_and_refuses_fractions():
    big = 2**62 + 1  # not representable as a double
    table = text.read_rows(f"{big},1.5\n".encode(), ["t_ns", "x"], {"t_ns"})
    assert table.column("t_ns").to_pylist() == [big]
    with pytest.raises(pa.ArrowInvalid):
        text.read_rows(b"1.5,1.5\n", ["t_ns", "x"], {"t_ns"})
