"""The text-format helpers of jsve's files: numbers, metadata JSON, and the magic-line CSV layout.

Tracking logs (jsve.io._logs) and keypoint side files (jsve.io._keypoints) share one layout:

    <MAGIC>{"sequence": "MH_04", ...}      line 1: a magic prefix, then the metadata as one JSON object
    t_ns,...                               line 2: the CSV header
    1403636579763555584,...                one row per record
    <END_MARKER>3600                       last line: the end marker and the number of rows

This module is the one home of what that layout needs (cutting a file into its sections, reading the
end marker's count, writing the head and tail, strict JSON metadata, Arrow's typed CSV for the rows) and
of the number grammar and formatting that every text reader of jsve uses (the importers of the SVE
authors' files too). The messages of each format stay in its own module; the rules live here.
"""

from __future__ import annotations

import codecs
import dataclasses
import gzip
import json
import re
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from jsve.io._errors import LogFormatError, LogIncompleteError

# --------------------------------------------------------------------------------------------------
# Numbers

DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
"""A plain decimal number: ASCII digits, an optional point and exponent; no nan/inf, no underscores,
no hex (all of which Python's float() accepts)."""

INT64_TEXT = re.compile(r"-?[0-9]+")
"""An integer as Arrow's int64 CSV parser reads it (no '+', no fraction)."""

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
"""The int64 range (nanosecond stamps, counts)."""

NON_FINITE_WORDS = ("nan", "inf", "infinity")
"""Words (any case, optionally signed) that parse as a float but are not a finite number."""


def is_non_finite_word(text: str) -> bool:
    """Whether `text` spells NaN or an infinity ('nan', '-inf', 'Infinity', ...)."""
    return text.lower().lstrip("+-") in NON_FINITE_WORDS


def in_int64(value: int) -> bool:
    """Whether a Python int fits an int64."""
    return INT64_MIN <= value <= INT64_MAX


def format_value(x) -> str:
    """A value as a file holds it: integers exactly, floats in the shortest form that reads back to
    the same double (Python's repr)."""
    if isinstance(x, (np.integer, int)):
        return str(int(x))
    return repr(float(x))


# --------------------------------------------------------------------------------------------------
# Metadata JSON


def json_default(obj):
    """json.dumps fallback for numpy scalars and arrays (metadata, study records)."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"metadata value {obj!r} of type {type(obj).__name__} is not JSON serialisable")


def _reject_constant(name: str):
    raise ValueError(f"{name} is not valid JSON (metadata values must be finite)")


class _RepeatedKey(ValueError):
    def __init__(self, key: str, first, second):
        super().__init__(key)
        self.key, self.first, self.second = key, first, second


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    # JSON allows a repeated key and Python's json keeps the last value: a repeated `run` would change
    # the run id without a word.
    seen: dict = {}
    for key, value in pairs:
        if key in seen:
            raise _RepeatedKey(key, seen[key], value)
        seen[key] = value
    return seen


def load_meta(text: str, source: str, line: int | None = 1):
    """Parse metadata JSON strictly: NaN and Infinity (which Python's json accepts) are errors, and so
    is a key that appears twice in one object (at any depth).

    Raises:
        LogFormatError: `source:line: metadata is not valid JSON: ...`, or `source:line: metadata key
            'run': appears twice ...`.
    """
    try:
        return json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except _RepeatedKey as e:
        shown = f"{json.dumps(e.first, default=repr)}, then {json.dumps(e.second, default=repr)}"
        raise LogFormatError(
            source,
            line,
            f"appears twice in one object of the metadata ({shown}); each key may appear once",
            column=e.key,
            what="metadata key",
        ) from None
    except ValueError as e:
        raise LogFormatError(source, line, f"metadata is not valid JSON: {e}") from None


def canonical_meta(meta, source: str) -> dict:
    """In-memory metadata as it reads back from its file: tuples become lists, numpy scalars Python numbers.

    Raises:
        LogFormatError: a value JSON cannot hold (NaN, inf, an arbitrary object).
    """
    try:
        text = json.dumps(meta, default=json_default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise LogFormatError(source, None, f"metadata cannot be written as JSON: {e}") from None
    return json.loads(text)


def is_type(value, types) -> bool:
    """isinstance for JSON values, where true/false are not numbers unless bool is among `types`."""
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in types:
        return False
    return isinstance(value, types)


def type_name(types) -> str:
    """`types` in words, for messages: (int, float) -> 'an integer or a number'."""
    types = types if isinstance(types, tuple) else (types,)
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", dict: "an object"}
    return " or ".join(names.get(t) or t.__name__ for t in types)


# --------------------------------------------------------------------------------------------------
# The bytes of a file

GZIP_MAGIC = b"\x1f\x8b"
"""The first two bytes of a gzip stream (RFC 1952)."""

UTF8_BOM = codecs.BOM_UTF8


def file_bytes(data: bytes, source: str) -> bytes:
    """The text of a file as its parsers read it: a gzip stream (recognised by its magic bytes, whatever
    the file's name) decompressed, and a UTF-8 byte-order mark before line 1 dropped.

    Raises:
        LogIncompleteError: a gzip stream that ends early (its writer, or a copy, stopped mid-file).
        LogFormatError: bytes that are not a valid gzip stream.
    """
    if data.startswith(GZIP_MAGIC):
        try:
            data = gzip.decompress(data)
        except EOFError:
            raise LogIncompleteError(
                source, None, "the file is incomplete: its gzip stream ends early (the file was cut short)"
            ) from None
        except (OSError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
            raise LogFormatError(source, None, f"not a readable gzip file: {e}") from None
    return data.removeprefix(UTF8_BOM)


# --------------------------------------------------------------------------------------------------
# The magic-line layout


_WHITESPACE = b" \t\n\r\x0b\x0c"  # what bytes.rstrip() strips


@dataclass(frozen=True)
class Sections:
    """A magic-line file cut into its parts; nothing is validated but where the lines are.

    Attributes:
        first: line 1 without its line ending (bytes).
        last: the last non-blank line, decoded (undecodable bytes replaced), without '\\r'; None when
            the file has a single line.
        header: line 2 without its line ending, or None when line 2 is the last line.
        data: the file. rows_start, rows_end: where the rows are in it (`rows`).
        body_end: the end of the last non-blank line (for n_lines).
    """

    first: bytes
    last: str | None
    header: bytes | None
    data: bytes
    rows_start: int
    rows_end: int
    body_end: int

    @property
    def rows(self) -> bytes:
        """The bytes between the header and the last line, each row ending in '\\n' (a copy: where
        that costs, `rows_view` and data.find(x, rows_start, rows_end) do not copy)."""
        return self.data[self.rows_start : self.rows_end]

    @property
    def rows_view(self) -> memoryview:
        """`rows` without copying them."""
        return memoryview(self.data)[self.rows_start : self.rows_end]

    def rows_hold(self, needle: bytes) -> bool:
        """Whether `needle` occurs in the rows (no copy)."""
        return self.data.find(needle, self.rows_start, self.rows_end) >= 0

    @property
    def n_lines(self) -> int:
        """The 1-based number of the last non-blank line: a scan of the whole file, so computed only
        where a message needs it."""
        return self.data.count(b"\n", 0, self.body_end) + 1


def cut(data: bytes) -> Sections:
    """Find line 1, the header, the rows and the last non-blank line of a non-empty file."""
    nl1 = data.find(b"\n")
    first = data if nl1 < 0 else data[:nl1]
    body_end = len(data)
    while body_end and data[body_end - 1] in _WHITESPACE:  # data.rstrip() without copying the file
        body_end -= 1
    last_nl = data.rfind(b"\n", 0, body_end)
    if last_nl < 0:
        return Sections(first, None, None, data, 0, 0, body_end)
    last = data[last_nl + 1 : body_end].decode("utf-8", errors="replace").rstrip("\r")
    if last_nl == nl1:
        return Sections(first, last, None, data, 0, 0, body_end)
    nl2 = data.find(b"\n", nl1 + 1)
    return Sections(first, last, data[nl1 + 1 : nl2].rstrip(b"\r"), data, nl2 + 1, last_nl + 1, body_end)


def split_trailers(parts: Sections, prefix: str) -> tuple[Sections, list[tuple[int, str]]]:
    """The rows without the trailer lines that end them (lines starting with `prefix`, right before the
    last line), and those lines as (1-based line number, text) in file order."""
    data, end, start = parts.data, parts.rows_end, parts.rows_start
    key = prefix.encode("utf-8")
    found: list[bytes] = []
    while end > start:
        begin = data.rfind(b"\n", start, end - 1) + 1
        begin = max(begin, start)
        if not data.startswith(key, begin):
            break
        found.append(data[begin:end].rstrip(b"\r\n"))
        end = begin
    if not found:
        return parts, []
    first_line = data.count(b"\n", 0, end) + 1
    lines = [(first_line + k, raw.decode("utf-8", errors="replace")) for k, raw in enumerate(reversed(found))]
    return dataclasses.replace(parts, rows_end=end), lines


def end_count(last: str | None, end_marker: str) -> str | None:
    """The text after the end marker on the last line, stripped; None when the last line is no end marker
    (its writer stopped before the end)."""
    if last is None or not last.startswith(end_marker):
        return None
    return last[len(end_marker) :].strip()


def is_count(text: str) -> bool:
    """Whether an end marker's count is a non-negative integer written in ASCII digits."""
    return re.fullmatch(r"[0-9]+", text) is not None


def head(magic: str, meta: dict, columns: Sequence[str]) -> bytes:
    """Line 1 (magic and metadata JSON) and line 2 (the header) of a file, UTF-8."""
    return (magic + json.dumps(meta, allow_nan=False) + "\n" + ",".join(columns) + "\n").encode("utf-8")


def tail(end_marker: str, count: int) -> bytes:
    """The last line: the end marker and the number of rows."""
    return f"{end_marker}{count}\n".encode("ascii")


def write_rows(table: pa.Table) -> bytes:
    """The rows of a table as CSV without header or quotes: integers exact, floats shortest round-trip
    (Arrow's formatting), nulls as empty fields."""
    if table.num_rows == 0:
        return b""
    sink = pa.BufferOutputStream()
    pacsv.write_csv(table, sink, pacsv.WriteOptions(include_header=False, quoting_style="none"))
    return sink.getvalue().to_pybytes()


def read_rows(
    rows: bytes | memoryview,
    columns: Sequence[str],
    int_columns: frozenset[str] | set[str],
    *,
    threads: bool = False,
) -> pa.Table:
    """Parse the rows with one explicit type per column: int64 for `int_columns` (never through a float),
    float64 (correctly rounded) for the others; an empty field is null; a quote is an ordinary character.

    Arguments:
        threads: parse 1 MB blocks on Arrow's thread pool (many logs' rows at once); otherwise the rows
            are one block on this thread, each column then one chunk, which NumPy and Parquet take
            without copying.

    Raises:
        pyarrow.ArrowInvalid: a row that does not parse; the caller locates it for its message.
    """
    types = {c: (pa.int64() if c in int_columns else pa.float64()) for c in columns}
    block_size = 1 << 20 if threads else max(len(rows) + 1, 1 << 20)
    return pacsv.read_csv(
        pa.py_buffer(rows),
        read_options=pacsv.ReadOptions(
            column_names=list(columns), use_threads=threads, block_size=block_size
        ),
        # Fields are never quoted (docs/log-format.md): a quote is part of a value, which then does not
        # convert; quoting would also let one row span lines and shift every line number after it.
        parse_options=pacsv.ParseOptions(ignore_empty_lines=False, quote_char=False),
        convert_options=pacsv.ConvertOptions(
            column_types=types,
            null_values=[""],
            strings_can_be_null=False,
            quoted_strings_can_be_null=False,
        ),
    )


def raw_line(rows: bytes, row: int) -> bytes:
    """Row `row` (0-based) of the rows, as written, without its line ending."""
    start = 0
    for _ in range(row):
        start = rows.index(b"\n", start) + 1
    end = rows.find(b"\n", start)
    return rows[start : end if end >= 0 else len(rows)].rstrip(b"\r")


def raw_field(raw: bytes, k: int) -> str:
    """Field `k` (0-based) of a raw CSV row, as written; '' when the row is shorter."""
    fields = raw.rstrip(b"\r").split(b",")
    return fields[k].decode("utf-8", errors="replace") if k < len(fields) else ""
