"""jsve.io._batching: LogBatch from runs (padding, masks, relative times, IMU start) and buckets of runs."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from logfactory import EUROC_T0_NS, make_run

from jsve.io import _schema as schema
from jsve.io import buckets, from_runs


def test_from_runs_pads_and_masks(x64, mixed_runs):
    runs = mixed_runs
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


def test_ground_truth_masks(x64, mixed_runs):
    runs = mixed_runs
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


def test_from_runs_errors(mixed_runs):
    runs = mixed_runs
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


@pytest.mark.parametrize("base", [5, 1 << 40])
def test_map_ids_beyond_int32_stay_apart(base):
    """Two maps whose ids differ by 2**32 are two maps in the batch (int32 would wrap one onto the
    other), and the replay sees the same map starts and resets as with ids 0 and 1: a new map where
    the id changes, a reset where a map's id comes back."""
    from jsve.core._replay import frame_data
    from jsve.io._batching import map_ranks

    n = 90
    small = np.repeat([0, 1, 0], [30, 30, 30])  # map 0, map 1, back to map 0
    big = np.where(small == 0, base, base + (1 << 32))
    runs = [make_run(n, seed=7, map_id=ids) for ids in (small, big)]
    assert runs[1].frames["map_id"].iloc[30] - runs[1].frames["map_id"].iloc[0] == 1 << 32
    batch = from_runs(runs, dtype=jnp.float32).batch
    assert np.array_equal(np.asarray(batch.map_id[1, :n]), small)  # dense ranks of the sorted ids
    data = frame_data(batch)
    for name in ("rec_start", "rec_loss", "rec_reloc"):
        a, b = (np.asarray(getattr(data, name)[i, :n]) for i in (0, 1))
        assert np.array_equal(a, b), name
    assert np.isfinite(runs[1].frames["vis_px"].to_numpy()).all()  # a pose on every frame
    assert list(np.flatnonzero(np.asarray(data.rec_start[1, :n]))) == [0, 30, 60]
    assert np.array_equal(map_ranks(np.array([7, 3, 7, 1 << 40, 3])), [1, 0, 1, 2, 0])
