"""Atomic file output: write under `<name>.partial`, rename into place only when complete.

The one home of jsve's "never leave a half-written output" rule, and of writing result tables: a crash
leaves at most a `.partial` file, which readers report as incomplete and re-runs redo.

    atomic_path(path)             a context: the temporary name to write, renamed on success
    write_bytes / write_text      bytes or UTF-8 text
    write_json(path, obj)         indented, sorted keys, numpy values as numbers
    write_table(table, path)      a DataFrame as Parquet (`.parquet`) or CSV (any other suffix)
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import pandas as pd

from jsve.io._text import json_default

PARTIAL_SUFFIX = ".partial"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield the temporary path to write; on success rename it to `path`, on error remove it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        yield partial
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def write_bytes(path: str | os.PathLike, *parts: bytes) -> Path:
    """Write the concatenation of `parts` to `path` atomically."""
    with atomic_path(path) as partial, open(partial, "wb") as f:
        for part in parts:
            f.write(part)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 text to `path` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj) -> Path:
    """Write `obj` as JSON (2-space indent, sorted keys, a final newline; numpy scalars and arrays as
    numbers and lists) to `path` atomically."""
    return write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=json_default) + "\n")


def write_table(table: pd.DataFrame, path: str | os.PathLike, **csv_options) -> Path:
    """Write a table as Parquet (`.parquet`) or CSV (any other suffix) atomically, without the index.

    Arguments:
        table: the rows; its index is not written.
        path: destination; parent folders are created.
        csv_options: passed to DataFrame.to_csv (e.g. float_format="%.9g"); CSV only.

    Returns:
        The path written.
    """
    with atomic_path(path) as partial:
        if Path(path).suffix == ".parquet":
            table.to_parquet(partial, index=False)
        else:
            table.to_csv(partial, index=False, **csv_options)
    return Path(path)
