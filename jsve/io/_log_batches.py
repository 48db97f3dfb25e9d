"""Many logs parsed as one: `jsve ingest`'s reading (docs/log-format.md, "Reading many logs").

    parse_logs(items)                 per (source, bytes): (meta, version, rows) | LogFormatError
    iter_parsed(paths, ...)           (path, that) in path order, batches of ~16 MB on threads

Each log's rows are parsed by Arrow's CSV reader as one block (Arrow is fastest on 1-2 MB blocks, a
log's size); the values of all logs that share a header are then validated in one pass over their
columns joined, where one log alone would spend ~4 ms in NumPy calls on small arrays. Batches of logs
are parsed on several threads at once: Arrow and NumPy release the GIL. The result is what reading
each log alone gives (jsve.io._logs.read_log_table), bit for bit, errors included: a log is read
alone, with its own line numbers in any message, whenever the batch cannot vouch for it: the lines
around its rows fail; Arrow refuses its rows or they are not as many as its end marker says; its
bytes hold a '\\r' or an 'x' (a Windows line ending, a bare carriage return, a hexadecimal number);
or any log of its group breaks a value rule.
"""

from __future__ import annotations

import itertools
import os
from collections import defaultdict, deque
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyarrow as pa

from jsve.io import _schema as schema
from jsve.io import _text as text
from jsve.io._errors import LogFormatError
from jsve.io._logs import log_layout, parse_table, read_log_bytes, rows_are_valid, unreadable

Parsed = tuple[dict, int, pa.Table]

_INT_COLUMNS = frozenset(schema.INT_COLUMNS + schema.KEYFRAME_INT_COLUMNS)
_ALONE_BYTES = (b"\r", b"x", b"X")  # a log holding one is read alone (module docstring)
_BATCH_BYTES = 16 << 20  # logs validated together: ~9 EuRoC logs (8-64 MB batches are about as fast)


def _alone(source: str, data: bytes) -> Parsed | LogFormatError:
    try:
        return parse_table(data, source)
    except LogFormatError as e:
        return e


def parse_logs(items: Sequence[tuple[str, bytes]]) -> list[Parsed | LogFormatError]:
    """Parse and validate many logs: for each (source, file bytes), what `read_log_table` returns for
    it, or the LogFormatError it raises.

    Arguments:
        items: (name used in messages, the whole file) per log.
    """
    out: list[Parsed | LogFormatError | None] = [None] * len(items)
    groups: dict[tuple, list[tuple[int, dict, pa.Table]]] = defaultdict(list)
    for k, (source, data) in enumerate(items):
        try:
            layout = log_layout(data, source)
        except LogFormatError as e:
            out[k] = e
            continue
        table = None
        # A log with trailers is read alone: parse_table attaches them to its table.
        if layout.trailers is None and not any(layout.parts.rows_hold(b) for b in _ALONE_BYTES):
            table = _rows(layout.parts.rows_view, layout.columns)
        if table is None or table.num_rows != layout.count:
            out[k] = _alone(source, data)
            continue
        groups[(layout.version, tuple(layout.columns))].append((k, layout.meta, table))
    for (version, columns), members in groups.items():
        tables = [table for _, _, table in members]
        starts = np.cumsum([0] + [t.num_rows for t in tables[:-1]])
        if rows_are_valid(pa.concat_tables(tables), columns, version, starts):
            for k, meta, table in members:
                out[k] = (meta, version, table)
        else:  # some log of the group is broken: each alone says which, and where
            for k, _, _ in members:
                out[k] = _alone(*items[k])
    return out  # type: ignore[return-value]  (every entry is set above)


def _rows(rows: memoryview, columns: list[str]) -> pa.Table | None:
    """A log's rows parsed (one block, one chunk per column), or None when Arrow refuses them."""
    try:
        return text.read_rows(rows, columns, _INT_COLUMNS)
    except pa.ArrowInvalid:
        return None


def _read(paths: Sequence[str]) -> list[tuple[str, bytes | LogFormatError]]:
    out: list[tuple[str, bytes | LogFormatError]] = []
    for p in paths:
        try:
            out.append((p, read_log_bytes(p)))
        except LogFormatError as e:
            out.append((p, e))
        except OSError as e:
            out.append((p, unreadable(p, e)))
    return out


def _batches(paths: Sequence[str], batch_bytes: int) -> list[list[str]]:
    """Consecutive runs of paths of about batch_bytes each (file sizes; at least one path each)."""
    batches: list[list[str]] = [[]]
    size = 0
    for p in paths:
        try:
            n = os.path.getsize(p)
        except OSError:
            n = 0  # reported when it is read
        if batches[-1] and size + n > batch_bytes:
            batches.append([])
            size = 0
        batches[-1].append(p)
        size += n
    return [b for b in batches if b]


def _read_and_parse(paths: Sequence[str]) -> list[tuple[str, Parsed | LogFormatError]]:
    files = _read(paths)
    readable = [(p, data) for p, data in files if isinstance(data, bytes)]
    parsed = iter(parse_logs(readable))
    return [(p, data if isinstance(data, LogFormatError) else next(parsed)) for p, data in files]


def iter_parsed(
    paths: Sequence[str], *, threads: int = 2, stop_on_error: bool = False, on_batch=None
) -> Iterator[tuple[str, Parsed | LogFormatError]]:
    """(path, its `parse_logs` result) for every path, in order.

    Batches are read and parsed on `threads` threads at once, each batch on one (its columns then one
    chunk each, which validation and Parquet take without copying); Arrow's parsing and NumPy's checks
    run without the GIL.

    Arguments:
        threads: batches in flight (1: one at a time, on one thread besides this one).
        stop_on_error: end after the first error.
        on_batch: called with the number of logs after each batch (a progress bar's update).
    """
    batches = iter(_batches(paths, _BATCH_BYTES))
    with ThreadPoolExecutor(max(1, threads)) as pool:
        ahead = deque(pool.submit(_read_and_parse, b) for b in itertools.islice(batches, max(1, threads)))
        while ahead:
            results = ahead.popleft().result()
            nxt = next(batches, None)
            if nxt is not None:
                ahead.append(pool.submit(_read_and_parse, nxt))
            for p, result in results:
                yield p, result
                if stop_on_error and isinstance(result, LogFormatError):
                    for future in ahead:
                        future.cancel()
                    return
            if on_batch is not None:
                on_batch(len(results))
