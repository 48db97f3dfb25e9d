"""The Parquet stream (jsve.io._stream) builds, chunk by chunk, exactly the LogBatch that the per-run
path (read_parquet -> from_runs) builds: every leaf bitwise, every metadata cell."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from logfactory import make_run
from test_world import _oracle_log

from jsve.core._batch import ladder, runs_per_chunk_for
from jsve.io import _schema as schema
from jsve.io._batching import from_runs, run_meta_table
from jsve.io._errors import LogFormatError, LogVersionWarning
from jsve.io._logs import write_log
from jsve.io._parquet import ingest, read_parquet
from jsve.io._stream import HOST_BYTES_PER_FRAME, _reading_by_length, chunk_plan, iter_buckets, open_study


def _study(tmp_path, runs) -> str:
    paths = [write_log(run, tmp_path / "logs" / f"r{i:03d}.csv") for i, run in enumerate(runs)]
    out = tmp_path / "s.parquet"
    ingest(paths, out, workers=1, progress=False)
    return str(out)


def _mixed_runs():
    """Runs of four length buckets, with and without ground truth, frames without a pose or ground
    truth, several maps (ids beyond int32), a stereo sensor, a run whose poses move between world
    frames and a camera offset."""
    runs = []
    for i, n in enumerate([70, 300, 310, 64, 1000, 290, 65, 999, 301, 2]):
        map_id = None
        if i % 3 == 1:
            map_id = np.where(np.arange(n) < n // 2, 2**32 + 5, 7)
        runs.append(
            make_run(
                n,
                seed=i,
                with_gt=i != 4,
                gt_missing=0.1 * (i % 2),
                no_pose=0.05 * (i % 3),
                map_id=map_id,
                sequence=f"S{i % 4}",
                run=i,
                **({"sensor": "imu_stereo"} if i == 5 else {}),
            )  # fmt: skip
        )
    world, _ = _oracle_log()
    runs.append(world)
    return runs


def _reference(path, dtype):
    """Per run id: (its row of run_meta_table, its LogBatch leaves from from_runs, unpadded)."""
    runs = read_parquet(path)
    meta = run_meta_table(runs)
    out = {}
    for k, run in enumerate(runs):
        batch = from_runs([run], dtype=dtype).batch
        out[run.run_id] = (meta.iloc[k], batch)
    return out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("budget", [1.5e9, 2e5])
def test_streamed_chunks_equal_the_per_run_batches(tmp_path, dtype, budget, request):
    if dtype == jnp.float64:
        request.getfixturevalue("x64")
    path = _study(tmp_path, _mixed_runs())
    reference = _reference(path, dtype)
    seen = []
    # small record batches: runs span several of them
    for bucket in iter_buckets(path, dtype=dtype, host_budget=budget, batch_rows=97):
        seen += _check_chunk(bucket, reference)
    assert sorted(seen) == sorted(reference)


def _check_chunk(bucket, reference) -> list[str]:
    """Assert every run of a streamed chunk equals its per-run reference, leaf by leaf, and the padding
    is padding; the chunk's run ids."""
    batch = bucket.batch
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(batch))
    n = len(bucket.meta)
    assert (np.asarray(batch.run_index)[:n] == np.arange(n)).all()
    assert (np.asarray(batch.run_index)[n:] == -1).all() and not np.asarray(batch.valid)[n:].any()
    for i, (_, row) in enumerate(bucket.meta.iterrows()):
        ref_row, ref = reference[row["run_id"]]
        pd.testing.assert_series_equal(row.dropna(), ref_row.dropna(), check_names=False)
        length = int(row["n_frames"])
        for name in ref.__dataclass_fields__:
            mine = np.asarray(getattr(batch, name))[i]
            theirs = np.asarray(getattr(ref, name))[0]
            if name == "run_index":
                continue
            if mine.ndim >= 1 and name not in ("gravity",):
                assert not mine[length:].any() if mine.dtype == bool else True
                mine, theirs = mine[:length], theirs[:length]
            assert mine.dtype == theirs.dtype, name
            np.testing.assert_array_equal(mine, theirs, err_msg=name)
    return list(bucket.meta["run_id"])


def _with_row_groups(path, rows: int) -> str:
    """The same study rewritten with row groups of `rows` rows (cutting runs), its metadata kept."""
    out = path.replace(".parquet", f"-rg{rows}.parquet")
    table = pq.read_table(path)
    table = table.replace_schema_metadata(pq.ParquetFile(path).metadata.metadata)
    pq.write_table(table, out, row_group_size=rows)
    assert pq.ParquetFile(out).metadata.num_row_groups > 3
    return out


def test_by_length_streams_each_length_whole_from_the_row_groups_that_hold_it(tmp_path):
    """Read bucket by bucket from row groups that cut runs in two (a stretch starts inside a run,
    another ends inside one): the same runs, bitwise, every chunk of a length together, shortest first."""
    path = _with_row_groups(_study(tmp_path, _mixed_runs()), 173)
    reference = _reference(path, jnp.float32)
    study = open_study(path)
    bucket_of, frames, _ = chunk_plan(study.lengths, host_budget=2e5)
    plan = _reading_by_length(study, bucket_of)
    assert plan is not None  # the test reads bucket by bucket, not the fallback
    assert sum(len(groups) for groups in plan.values()) > pq.ParquetFile(path).metadata.num_row_groups
    seen, lengths = [], []
    for bucket in iter_buckets(path, host_budget=2e5, batch_rows=97, by_length=True):
        seen += _check_chunk(bucket, reference)
        lengths.append(bucket.batch.n_frames)
    assert sorted(seen) == sorted(reference)  # every run once
    assert lengths == sorted(lengths) and len(set(lengths)) == len(set(frames)) > 2


def test_by_length_never_hands_on_a_bucket_short_of_runs(tmp_path, monkeypatch):
    """A length read from row groups that miss some of its runs is an error naming the file and the
    row groups, not a shorter bucket."""
    import jsve.io._stream as stream

    path = _with_row_groups(_study(tmp_path, _mixed_runs()), 173)
    full = stream._reading_by_length

    def missing_one(study, bucket_of):
        plan = full(study, bucket_of)
        longest = max(plan, key=lambda g: len(plan[g]))
        return {**plan, longest: plan[longest][1:]}

    monkeypatch.setattr(stream, "_reading_by_length", missing_one)
    with pytest.raises(LogFormatError, match=r"rg173\.parquet.*row groups \[.*\] hold \d+ of the \d+ runs"):
        list(iter_buckets(path, host_budget=2e5, by_length=True))


def test_by_length_reads_the_file_once_where_buckets_share_its_row_groups(tmp_path):
    """One row group holding every bucket: reading it once per bucket is refused and the chunks come
    as they fill, the same as without by_length."""
    path = _study(tmp_path, _mixed_runs())
    study = open_study(path)
    assert pq.ParquetFile(path).metadata.num_row_groups == 1
    assert _reading_by_length(study, chunk_plan(study.lengths)[0]) is None
    ids = [list(b.meta["run_id"]) for b in iter_buckets(path, by_length=True)]
    assert ids == [list(b.meta["run_id"]) for b in iter_buckets(path)]


def test_chunks_follow_the_host_budget_not_the_study():
    lengths = np.array([3600] * 10_000)
    _, frames, sizes = chunk_plan(lengths, host_budget=1.5e9)
    assert frames == [ladder(3600)] and sizes[0] * frames[0] * HOST_BYTES_PER_FRAME <= 1.5e9
    assert sizes[0] <= runs_per_chunk_for(frames[0])
    # four buckets share the budget
    lengths = np.repeat([500, 1000, 2000, 4000], 1000)
    _, frames, sizes = chunk_plan(lengths, host_budget=1e9)
    assert len(sizes) == 4
    assert sum(s * f * HOST_BYTES_PER_FRAME for s, f in zip(sizes, frames, strict=True)) <= 1e9


def test_a_format_1_file_streams_with_the_v1_defaults(tmp_path):
    from test_ingest import _as_format_1

    path = _study(tmp_path, [make_run(400, i, sequence="MH_04") for i in range(3)])
    old = tmp_path / "old.parquet"
    _as_format_1(tmp_path / "s.parquet", old)
    with pytest.warns(LogVersionWarning):
        reference = _reference(old, jnp.float32)
    (bucket,) = iter_buckets(old)
    for i, run_id in enumerate(bucket.meta["run_id"]):
        ref = reference[run_id][1]
        for name in ("imu_ba2", "map_id", "ba2_delay"):
            np.testing.assert_array_equal(
                np.asarray(getattr(bucket.batch, name))[i], np.asarray(getattr(ref, name))[0]
            )
    assert path


def test_rows_out_of_run_order_are_refused(tmp_path):
    path = _study(tmp_path, [make_run(50, i) for i in range(3)])
    table = pq.read_table(path)
    swapped = table.take(np.r_[50:100, 0:50, 100:150])
    bad = tmp_path / "bad.parquet"
    kv = {k: v for k, v in pq.ParquetFile(path).metadata.metadata.items() if k.startswith(b"jsve.")}
    pq.write_table(swapped.replace_schema_metadata(kv), bad)
    with pytest.raises(LogFormatError, match="not grouped by run"):
        list(iter_buckets(bad))


def test_a_file_without_the_run_list_is_refused(tmp_path):
    path = _study(tmp_path, [make_run(50, 0)])
    plain = tmp_path / "plain.parquet"
    pq.write_table(pq.read_table(path).replace_schema_metadata({}), plain)
    with pytest.raises(LogFormatError, match="not a jsve Parquet file"):
        open_study(plain)
    assert schema.N_BINS == 64


def test_jsve_evaluate_of_the_parquet_file_equals_that_of_its_logs(tmp_path):
    # The streamed path (chunks in fill order, put back in file order) against the per-run path.
    from jsve.cli import main

    runs = [
        make_run(n, seed=i, run=i, sequence=f"S{i % 3}") for i, n in enumerate([300, 80, 310, 640, 75, 305])
    ]
    path = _study(tmp_path, runs)
    for source, out in ((path, "streamed"), (str(tmp_path / "logs"), "per-run")):
        argv = ["evaluate", source, "--rule", "orbslam3", "--rule", "sve-option2", "--no-progress"]
        assert main([*argv, "-o", str(tmp_path / out)]) == 0
    streamed = pd.read_csv(tmp_path / "streamed" / "runs.csv")
    per_run = pd.read_csv(tmp_path / "per-run" / "runs.csv")
    order = read_parquet(path)
    # rule by rule, each rule's runs in the file's order
    expected = [r.run_id for r in order]
    for rule in ("orbslam3", "sve-option2"):
        assert streamed.loc[streamed["rule"] == rule, "run_id"].tolist() == expected
    assert streamed["rule"].tolist() == ["orbslam3"] * len(runs) + ["sve-option2"] * len(runs)
    key = ["rule", "run_id"]
    pd.testing.assert_frame_equal(
        streamed.sort_values(key).reset_index(drop=True), per_run.sort_values(key).reset_index(drop=True)
    )
    assert pd.read_csv(tmp_path / "streamed" / "summary.csv").equals(
        pd.read_csv(tmp_path / "per-run" / "summary.csv")
    )
