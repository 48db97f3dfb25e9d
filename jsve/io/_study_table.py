"""The consolidated Parquet study (`jsve ingest`): its layout, encodings, and one run's rows in it.

    PARQUET_SCHEMA                 one row per frame: run_id, frame, the v2 columns, gt_*, world_*
    PARQUET_WRITE_OPTIONS          the encodings every writer of a study uses (pyarrow.parquet keywords)
    run_rows(columns, n_frames)    one run's rows in the layout, without run_id
    row_group(run_ids, rows)       several runs' rows with their dictionary-encoded run_id

Both of a log's routes to the file go through `run_rows`: the Arrow table a log parses to (jsve ingest's
route, no pandas) and a RunLog's frames (v1 logs with their defaults, runs given ground truth).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from jsve.io import _schema as schema

RUN_ID_FIELD = pa.field("run_id", pa.dictionary(pa.int32(), pa.string()), nullable=False)

_RUN_FIELDS = (
    [pa.field("frame", pa.int32(), False)]
    + [pa.field(c, pa.int64(), nullable=False) for c in schema.INT_COLUMNS]
    + [pa.field(c, pa.float64(), nullable=False) for c in schema.FLOAT_COLUMNS]
    + [pa.field(c, pa.float64(), nullable=True) for c in schema.GT_COLUMNS]
    + [pa.field(c, pa.float64(), nullable=True) for c in schema.WORLD_COLUMNS]
    + [pa.field("in_saved", pa.int8(), nullable=True)]
)
_RUN_SCHEMA = pa.schema(_RUN_FIELDS)

PARQUET_SCHEMA = pa.schema([RUN_ID_FIELD, *_RUN_FIELDS])
"""Layout of the consolidated Parquet file: one row per frame, runs contiguous in sorted path order.
vis_* are NaN on frames without a pose; gt_* are null for runs without ground truth, NaN for frames
without it in runs that have it; world_* are null for runs whose logs have none (files written
before the world_* columns existed lack them: their runs have none)."""

_FLOAT_NAMES = schema.FLOAT_COLUMNS + schema.GT_COLUMNS + schema.WORLD_COLUMNS

PARQUET_WRITE_OPTIONS: dict = {
    "compression": "lz4",
    "use_dictionary": ["run_id", "frame", *(c for c in schema.INT_COLUMNS if c != "t_ns")],
    "column_encoding": {"t_ns": "DELTA_BINARY_PACKED", **dict.fromkeys(_FLOAT_NAMES, "BYTE_STREAM_SPLIT")},
}
"""Encodings of a study file. Small integers (counts, bins, states, frame numbers) dictionary-encoded;
stamps delta-encoded (unique, evenly spaced); floats split by byte (BYTE_STREAM_SPLIT) rather than
dictionary-encoded: a pose rarely repeats, and a dictionary over floats triples the decoding time of a
row group. LZ4 (LZ4_RAW): with these encodings the file is about as small as with zstd and
dictionaries everywhere, and is written and decoded several times faster (docs/performance.md,
"`jsve ingest`")."""


def _as_arrow(values, field: pa.Field) -> pa.ChunkedArray:
    """A column as Arrow: an Arrow column as it is, a NumPy one converted to the field's type."""
    if isinstance(values, pa.ChunkedArray):
        return values
    if isinstance(values, pa.Array):
        return pa.chunked_array([values])
    return pa.chunked_array([pa.array(np.asarray(values), field.type)])


def run_rows(columns: Mapping[str, pa.ChunkedArray | pa.Array | np.ndarray], n_frames: int) -> pa.Table:
    """One run's frames in the study layout (PARQUET_SCHEMA without run_id).

    Arguments:
        columns: name -> values [n_frames] for every schema.REQUIRED_COLUMNS name, and the gt_* and
            world_* groups where the run has them: Arrow columns as a log parses (null where a field is
            empty) or NumPy columns of a RunLog's frames (NaN where a value is absent).
        n_frames: frames of the run.

    A vis_* or gt_* null becomes NaN; a group the run lacks is null on every frame.
    """
    arrays = [pa.chunked_array([pa.array(np.arange(n_frames, dtype=np.int32))])]
    for field in _RUN_FIELDS[1:]:
        values = columns.get(field.name)
        if values is None:
            if not field.nullable:
                raise KeyError(f"run_rows: column {field.name!r} is missing")
            arrays.append(pa.chunked_array([pa.nulls(n_frames, field.type)]))
            continue
        column = _as_arrow(values, field)
        if column.null_count:
            column = pc.fill_null(column, math.nan)
        arrays.append(column)
    return pa.Table.from_arrays(arrays, schema=_RUN_SCHEMA)


def row_group(run_ids: Sequence[str], rows: Sequence[pa.Table]) -> pa.Table:
    """Runs' rows (from `run_rows`) in one table of PARQUET_SCHEMA, each run's frames under its id."""
    lengths = [t.num_rows for t in rows]
    indices = np.repeat(np.arange(len(rows), dtype=np.int32), lengths)
    run_id = pa.DictionaryArray.from_arrays(pa.array(indices), pa.array(list(run_ids), pa.string()))
    return pa.concat_tables(rows).add_column(0, RUN_ID_FIELD, pa.chunked_array([run_id]))
