"""Atomic file output: write under `<name>.partial`, rename into place only when complete.

The one home of jsve's "never leave a half-written output" rule: a crash leaves at most a
`.partial` file, which readers report as incomplete and re-runs redo.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import pandas as pd

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


def write_table(table: pd.DataFrame, path: str | os.PathLike, **csv_options) -> Path:
    """Write a table as Parquet (`.parquet`) or CSV (any other suffix) atomically, without the index."""
    with atomic_path(path) as partial:
        if Path(path).suffix == ".parquet":
            table.to_parquet(partial, index=False)
        else:
            table.to_csv(partial, index=False, **csv_options)
    return Path(path)
