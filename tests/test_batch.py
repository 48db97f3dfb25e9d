"""jsve.core._batch: LogBatch padding and masks, relative times, length buckets, chunks, padding runs."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from logfactory import EUROC_T0_NS, make_run

from jsve.core._batch import (
    bucket_by_length,
    iter_chunks,
    pad_runs,
    runs_per_chunk_for,
    take_runs,
)
from jsve.core._replay import replay
from jsve.core._rules import preset
from jsve.io import _schema as schema
from jsve.io._batching import buckets, from_runs


def _runs():
    return [
        make_run(100, seed=1, sequence="MH_04", disturbance="blur", level=15),
        make_run(130, seed=2, gt_missing=0.2, fps=10),
        make_run(65, seed=3, with_gt=False, gravity=[0.0, -9.81, 0.0]),
    ]


def test_from_runs_pads_and_masks(x64):
    runs = _runs()
    bucket = from_runs(runs, dtype=jnp.float64)
    b = bucket.batch
    assert (b.n_runs, b.n_frames) == (3, 192)  # the longest run (130) rounded up to 64
    for i, run in enumerate(runs):
        n = len(run.frames)
        f = run.frames
        assert np.asarray(b.valid[i, :n]).all() and not np.asarray(b.valid[i, n:]).any()
        # the frames are the run's, bit for bit (float64 batch)
        assert np.array_equal(np.asarray(b.n_inliers[i, :n]), f["n_inliers"].to_numpy())
        assert np.array_equal(np.asarray(b.bins[i, :n]), f[list(schema.BIN_COLUMNS)].to_numpy())
        assert np.array_equal(np.asarray(b.vis_p[i, :n]), f[list(schema.VIS_POSITION)].to_numpy())
        assert np.array_equal(np.asarray(b.imu_dq[i, :n]), f[list(schema.IMU_DQ)].to_numpy())
        assert np.array_equal(np.asarray(b.imu_init[i, :n]), f["imu_init"].to_numpy() != 0)
        # padding is inert: zero counts and deltas, identity rotations
        assert not np.asarray(b.n_extracted[i, n:]).any() and not np.asarray(b.imu_dt[i, n:]).any()
        for q in (b.vis_q, b.imu_dq, b.gt_q):
            assert np.array_equal(np.asarray(q[i, n:]), np.tile([1.0, 0, 0, 0], (192 - n, 1)))
    assert np.array_equal(np.asarray(b.fps), [20.0, 10.0, 20.0])
    assert np.array_equal(np.asarray(b.gravity[2]), [0.0, -9.81, 0.0])
    assert np.array_equal(np.asarray(b.run_index), [0, 1, 2])
    assert list(bucket.meta["n_frames"]) == [100, 130, 65]
    assert bucket.meta.loc[0, "run_id"] == "MH_04/blur-15/1"
    assert bucket.meta.loc[0, "image_size"] == (752, 480)  # lists become hashable tuples


def test_ground_truth_masks(x64):
    runs = _runs()
    b = from_runs(runs, dtype=jnp.float64).batch
    gp = runs[1].frames[list(schema.GT_POSITION)].to_numpy()
    present = np.isfinite(gp).all(axis=1)
    assert 0 < present.sum() < len(present)
    assert np.array_equal(np.asarray(b.gt_valid[1, :130]), present)
    assert np.array_equal(np.asarray(b.gt_p[1, :130][present]), gp[present])
    assert not np.asarray(b.gt_p[1, :130][~present]).any()  # NaN never enters the batch
    assert np.isfinite(np.asarray(b.gt_q)).all()
    assert not np.asarray(b.gt_valid[2]).any()  # a run logged without ground truth


def test_relative_times_are_exact(x64):
    """t = (t_ns - t_ns[0]) / 1e9 with the int64 difference first: the float64 result is the
    correctly rounded quotient. Converting absolute EuRoC stamps (1.4e18 ns) to float64 first would
    not be: their spacing there is 256 ns."""
    run = make_run(500, seed=4, t0_ns=EUROC_T0_NS)
    stamps = run.frames["t_ns"].to_numpy()
    b = from_runs([run], dtype=jnp.float64).batch
    expected = np.array([int(s - stamps[0]) / 1e9 for s in stamps])  # Python ints: exact differences
    assert np.array_equal(np.asarray(b.t[0, :500]), expected)
    naive = (stamps.astype(np.float64) - float(stamps[0])) / 1e9
    assert not np.array_equal(naive, expected)  # the trap the int64 difference avoids
    # float32 batches hold the float64 value rounded once
    b32 = from_runs([run]).batch
    assert b32.t.dtype == jnp.float32
    assert np.array_equal(np.asarray(b32.t[0, :500]), expected.astype(np.float32))


def test_imu_init_delay(x64):
    run = make_run(200, seed=5)
    init = run.frames["imu_init"].to_numpy().copy()
    init[:] = 0
    init[57:] = 1
    init[120] = 0  # a later flicker does not move the first initialisation
    run.frames["imu_init"] = init
    never = make_run(80, seed=6)
    never.frames["imu_init"] = 0
    b = from_runs([run, never], dtype=jnp.float64).batch
    assert float(b.imu_init_delay[0]) == float(b.t[0, 57])
    assert math.isinf(float(b.imu_init_delay[1]))


def test_from_runs_errors():
    runs = _runs()
    with pytest.raises(ValueError, match="no runs"):
        from_runs([])
    with pytest.raises(ValueError, match=r"n_frames=100 is shorter than the longest run \(130 frames\)"):
        from_runs(runs, n_frames=100)
    empty = make_run(5, seed=7)
    empty = type(empty)(meta=empty.meta, frames=empty.frames.iloc[:0], source="empty.csv")
    with pytest.raises(ValueError, match="empty.csv"):
        from_runs([runs[0], empty])
    assert from_runs(runs, n_frames=130).batch.n_frames == 130


# ------------------------------------------------------------------------------------------------
# Buckets


def _check_buckets(lengths, groups, max_padding, pad_multiple):
    flat = np.concatenate(groups) if groups else np.array([], int)
    assert sorted(flat.tolist()) == list(range(len(lengths)))  # every run exactly once
    for g in groups:
        lens = np.asarray(lengths)[g]
        assert np.all(np.diff(lens) >= 0)  # ascending by length
        def rounded(n):
            return max(pad_multiple, math.ceil(n / pad_multiple) * pad_multiple)

        own = sum(rounded(n) for n in lens)  # each run rounded to the multiple on its own
        padded = rounded(lens.max()) * len(g)
        # The padding the grouping adds, beyond each run's own rounding, stays within the bound
        # (1e-9: float rounding of the product; counts are integers).
        assert padded - own <= max_padding * own + 1e-9


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    lengths=st.lists(st.integers(1, 5000), min_size=0, max_size=60),
    max_padding=st.sampled_from([0.0, 0.05, 0.1, 0.5]),
    pad_multiple=st.sampled_from([1, 16, 64]),
)
def test_bucket_by_length_covers_each_run_once_with_bounded_padding(lengths, max_padding, pad_multiple):
    groups = bucket_by_length(lengths, max_padding=max_padding, pad_multiple=pad_multiple)
    _check_buckets(lengths, groups, max_padding, pad_multiple)


def test_equal_lengths_share_one_bucket_whatever_the_multiple():
    # 400 frames round to 448: the rounding alone is 12 % > max_padding, yet nothing is gained by
    # splitting equal runs (the bug was one bucket per run).
    assert [len(g) for g in bucket_by_length([400] * 10, max_padding=0.1, pad_multiple=64)] == [10]


def test_bucket_by_length_groups_similar_lengths():
    rng = np.random.default_rng(8)
    lengths = np.concatenate([rng.integers(3500, 3600, 50), rng.integers(600, 640, 50), [10]])
    groups = bucket_by_length(lengths)
    _check_buckets(lengths, groups, 0.1, 64)
    assert len(groups) <= 4  # two clusters and a straggler, not one bucket per run


def test_buckets_stack_each_group(x64):
    runs = [make_run(n, seed=i) for i, n in enumerate([300, 70, 310, 65, 290])]
    out = buckets(runs, dtype=jnp.float64)
    seen = []
    for bucket in out:
        b = bucket.batch
        for i in range(b.n_runs):
            row = bucket.meta.iloc[int(b.run_index[i])]
            seen.append(row["run"])
            n = row["n_frames"]
            assert int(np.asarray(b.valid[i]).sum()) == n
            source = runs[row["run"]].frames
            assert np.array_equal(np.asarray(b.n_inliers[i, :n]), source["n_inliers"].to_numpy())
    assert sorted(seen) == list(range(5))


# ------------------------------------------------------------------------------------------------
# take_runs, pad_runs, iter_chunks


def test_take_runs():
    b = from_runs(_runs()).batch
    sub = take_runs(b, np.array([2, 0]))
    assert np.array_equal(np.asarray(sub.run_index), [2, 0])
    for a, c in zip(jax.tree.leaves(sub), jax.tree.leaves(b), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(c)[[2, 0]])


def test_pad_runs():
    b = from_runs(_runs()).batch
    assert pad_runs(b, 3) is b
    padded = pad_runs(b, 5)
    assert padded.n_runs == 5
    assert np.array_equal(np.asarray(padded.run_index), [0, 1, 2, -1, -1])
    assert not np.asarray(padded.valid[3:]).any() and not np.asarray(padded.gt_valid[3:]).any()
    for a, c in zip(jax.tree.leaves(take_runs(padded, np.arange(3))), jax.tree.leaves(b), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(c))  # the real runs are untouched
    with pytest.raises(ValueError, match="more than n_runs=2"):
        pad_runs(b, 2)
    # a padding run replays to nothing: no estimate, no decision, never lost
    res = jax.jit(replay)(padded, preset("orbslam3"))
    assert not np.asarray(res.has_estimate[3:]).any() and not np.asarray(res.lost_any[3:]).any()
    assert (np.asarray(res.mode[3:]) == -1).all()
    assert np.asarray(res.has_estimate[0, :100]).any()


def test_iter_chunks():
    runs = [make_run(64, seed=i) for i in range(7)]
    b = from_runs(runs).batch
    chunks = list(iter_chunks(b, 3))
    assert [s for s, _ in chunks] == [slice(0, 3), slice(3, 6), slice(6, 7)]
    assert all(c.n_runs == 3 for _, c in chunks)  # one compiled shape for all chunks
    last = chunks[-1][1]
    assert np.array_equal(np.asarray(last.run_index), [6, -1, -1])
    assert not np.asarray(last.valid[1:]).any()
    rebuilt = np.concatenate([np.asarray(c.n_inliers)[: s.stop - s.start] for s, c in chunks])
    assert np.array_equal(rebuilt, np.asarray(b.n_inliers))
    with pytest.raises(ValueError, match="runs_per_chunk must be >= 1"):
        list(iter_chunks(b, 0))
    assert [s for s, _ in iter_chunks(b, 10)] == [slice(0, 7)]


def test_runs_per_chunk_for():
    assert runs_per_chunk_for(3600) == int(4e9 // (600 * 3600))
    assert runs_per_chunk_for(10**9) == 1  # never zero
    assert runs_per_chunk_for(100) > runs_per_chunk_for(1000)
