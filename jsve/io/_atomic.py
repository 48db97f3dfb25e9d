"""Atomic file output: write under `<name>.partial`, rename into place only when complete.

The one home of jsve's "never leave a half-written output" rule, and of writing result tables: a crash
leaves at most a `.partial` file, which readers report as incomplete and re-runs redo.

    atomic_path(path)             a context: the temporary name to write, renamed on success
    all_or_nothing()              a context: every output written inside appears together, or none does
    make_dir(path)                an output folder, or OutputError
    output_error, is_write_error  an OSError of writing as OutputError; whether it is one
    check_writable(folder)        fail early (OutputError) when a folder cannot take outputs
    write_bytes / write_text      bytes or UTF-8 text
    write_json(path, obj)         indented, sorted keys, numpy values as numbers
    write_table(table, path)      a DataFrame as Parquet (`.parquet`) or CSV (any other suffix)

An output that cannot be written (read-only folder, full disk, a path whose parent is a file, a target
that is a folder) raises `OutputError`, an OSError whose message is `cannot write PATH: REASON` and
names the final path, never the temporary one; `jsve` prints it as one line and exits with status 2.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.io._text import json_default

PARTIAL_SUFFIX = ".partial"

# errno values that only a write produces: an OSError with one of them inside atomic_path is the
# output's, whatever file it names.
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


class OutputError(OSError):
    """An output that cannot be written: `filename` is the final path, `strerror` the reason."""

    def __str__(self) -> str:
        return f"cannot write {self.filename}: {self.strerror}"


def _reason(error: OSError, path: Path) -> str:
    if isinstance(error, FileExistsError) or (
        path.exists() and not path.is_dir() and error.errno == errno.EEXIST
    ):
        return "exists and is not a folder"
    if error.strerror:
        return error.strerror
    if error.errno:
        return os.strerror(error.errno)
    return str(error) or type(error).__name__


def output_error(error: OSError, path: str | os.PathLike) -> OutputError:
    """`error`, raised while writing `path`, as an OutputError naming `path`."""
    if isinstance(error, OutputError):
        return error
    path = Path(path)
    return OutputError(error.errno, _reason(error, path), os.fspath(path))


def make_dir(path: str | os.PathLike) -> Path:
    """Create the folder `path` (and its parents) unless it exists.

    Raises:
        OutputError: it cannot be created, or exists and is not a folder.
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise output_error(error, path) from error
    return path


def check_writable(folder: str | os.PathLike) -> Path:
    """Create `folder` if needed and create and remove a file in it, so that a long job fails before
    it starts rather than at its first output.

    Raises:
        OutputError: the folder cannot be created or written (read-only, not a folder, no space).
    """
    folder = make_dir(folder)
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".jsve-probe-"):
            pass
    except OSError as error:
        raise output_error(error, folder) from error
    return folder


def _commit(partial: Path, path: Path) -> None:
    """The rename that makes an output appear (one place, so that tests can make it fail)."""
    os.replace(partial, path)


# The outputs of the innermost all_or_nothing() block: (partial, final) pairs waiting for their rename.
_group: contextvars.ContextVar[list[tuple[Path, Path]] | None] = contextvars.ContextVar(
    "jsve_atomic_group", default=None
)


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Every output written through this module inside the block is renamed into place when the block
    ends without an error; on an error every one of them is removed, so a command leaves all its
    outputs or none (files it replaces keep their old contents).

    Raises:
        OutputError: a rename at the end failed (the outputs renamed before it stay).
    """
    pending: list[tuple[Path, Path]] = []
    token = _group.set(pending)
    try:
        yield
    except BaseException:
        for partial, _ in pending:
            with contextlib.suppress(OSError):
                partial.unlink(missing_ok=True)
        raise
    finally:
        _group.reset(token)
    for partial, path in pending:
        try:
            _commit(partial, path)
        except OSError as error:
            for rest, _ in pending:
                with contextlib.suppress(OSError):
                    rest.unlink(missing_ok=True)
            raise output_error(error, path) from error


def is_write_error(error: OSError, *outputs: str | os.PathLike) -> bool:
    """Whether an OSError raised while writing `outputs` (files or folders) is theirs, not a read of an
    input: an OutputError, an errno only writes produce (full disk, quota, read-only file system), no
    file name, or a file name at or under one of `outputs`."""
    if isinstance(error, OutputError) or error.errno in _WRITE_ERRNOS or error.filename is None:
        return True
    name = Path(os.fspath(error.filename))
    return any(name == Path(p) or Path(p) in name.parents for p in outputs)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield the temporary path to write; on success rename it to `path` (at the end of an enclosing
    all_or_nothing block, if any), on error remove it.

    Raises:
        OutputError: the folder cannot be created, or the write or the rename failed (read-only folder,
            full disk, `path` a folder, a parent a file); other errors of the block pass unchanged.
    """
    path = Path(path)
    make_dir(path.parent)
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    group = _group.get()
    try:
        yield partial
        if path.is_dir():  # os.replace would say "Is a directory" of the temporary name on some systems
            raise IsADirectoryError(errno.EISDIR, "is a folder", os.fspath(path))
        if group is None:
            _commit(partial, path)
        else:
            group.append((partial, path))
    except OSError as error:
        with contextlib.suppress(OSError):
            partial.unlink(missing_ok=True)
        if is_write_error(error, partial, path):
            raise output_error(error, path) from error
        raise
    except BaseException:
        with contextlib.suppress(OSError):
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

    In CSV a cell holding a list, tuple or array (list-valued metadata such as `image_size`, a tuple in
    jsve.io._batching.run_meta_table) is written as a JSON list, `[752, 480]`, not as Python's repr;
    read_table reads it back as a tuple.

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
            _json_lists(table).to_csv(partial, index=False, **csv_options)
    return Path(path)


def _is_list(value) -> bool:
    return isinstance(value, (list, tuple, np.ndarray))


def _json_lists(table: pd.DataFrame) -> pd.DataFrame:
    """The table with every list-like cell as JSON text (a copy where there is one)."""
    lists = [
        name for name in table.columns if table[name].dtype == object and table[name].map(_is_list).any()
    ]
    if not lists:
        return table
    table = table.copy()
    for name in lists:
        table[name] = [json.dumps(v, default=json_default) if _is_list(v) else v for v in table[name]]
    return table


def read_table(path: str | os.PathLike) -> pd.DataFrame:
    """A table write_table wrote: Parquet as it is; CSV with its JSON-list cells as tuples again.

    Raises:
        OSError: the file cannot be read.
    """
    if Path(path).suffix == ".parquet":
        return pd.read_parquet(path)
    table = pd.read_csv(path)
    for name in table.columns:
        column = table[name]
        if column.dtype == object or pd.api.types.is_string_dtype(column):
            cells = [_from_json_list(v) for v in column]
            if any(isinstance(v, tuple) for v in cells):
                table[name] = pd.Series(cells, index=table.index, dtype=object)
    return table


def _from_json_list(value):
    """A cell's JSON list as a tuple; any other value as it is."""
    if isinstance(value, str) and value.startswith("[") and value.endswith("]"):
        try:
            parsed = json.loads(value)
        except ValueError:
            return value
        if isinstance(parsed, list):
            return tuple(parsed)
    return value
