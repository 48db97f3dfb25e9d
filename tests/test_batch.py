"""jsve.core._batch: length buckets, taking and padding runs, chunks of a LogBatch."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from logfactory import make_run

from jsve.core import bucket_by_length, iter_chunks, pad_runs, preset, replay, take_runs
from jsve.core._batch import (
    DEVICE_BUDGET_BYTES,
    LADDER_RATIO,
    bucket_by_ladder,
    ladder,
    ladder_chunk_size,
    runs_per_chunk_for,
)
from jsve.io import from_runs

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


# ------------------------------------------------------------------------------------------------
# take_runs, pad_runs, iter_chunks


def test_take_runs(mixed_runs):
    b = from_runs(mixed_runs).batch
    sub = take_runs(b, np.array([2, 0]))
    assert np.array_equal(np.asarray(sub.run_index), [2, 0])
    for a, c in zip(jax.tree.leaves(sub), jax.tree.leaves(b), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(c)[[2, 0]])


def test_pad_runs(mixed_runs):
    b = from_runs(mixed_runs).batch
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
    # while the real runs are replayed (their random counts reset before BA2 again and again, which
    # erases their estimates: docs/state-machine.md; so the mode, not the estimate, shows it)
    assert (np.asarray(res.mode[0, :100]) >= 0).all() and (np.asarray(res.mode[0, :100]) == 0).any()


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
    assert runs_per_chunk_for(3600) == int(DEVICE_BUDGET_BYTES // (600 * 3600))
    assert runs_per_chunk_for(3600, bytes_budget=4e9) == int(4e9 // (600 * 3600))
    assert runs_per_chunk_for(10**9) == 1  # never zero
    assert runs_per_chunk_for(100) > runs_per_chunk_for(1000)


# ------------------------------------------------------------------------------------------------
# The padded-length ladder: few compiled shapes whatever the study's exact lengths


@settings(max_examples=300, deadline=None, derandomize=True)
@given(n=st.integers(1, 200_000), multiple=st.sampled_from([1, 8, 64]))
def test_ladder_rung_covers_n_with_bounded_padding(n, multiple):
    rung = ladder(n, multiple=multiple)
    assert rung >= n and rung % multiple == 0
    # at most one ratio step above n, plus the rounding to the multiple
    assert rung <= max(multiple, math.ceil(n * LADDER_RATIO / multiple) * multiple + multiple)
    assert ladder(rung, multiple=multiple) == rung  # a rung is its own rung: lengths never creep up


def test_ladder_is_monotone_and_has_few_rungs():
    rungs = [ladder(n) for n in range(1, 20_001)]
    assert all(a <= b for a, b in zip(rungs[:-1], rungs[1:], strict=True))
    # runs of 1,000 to 4,000 frames (EuRoC's sequences at 20 fps) compile at most 9 frame counts
    assert len({ladder(n) for n in range(1000, 4001)}) <= 9
    with pytest.raises(ValueError, match="n must be >= 1"):
        ladder(0)
    with pytest.raises(ValueError, match="ratio must be > 1"):
        ladder(10, ratio=1.0)


@settings(max_examples=100, deadline=None, derandomize=True)
@given(lengths=st.lists(st.integers(1, 5000), min_size=0, max_size=60))
def test_bucket_by_ladder_groups_runs_by_rung(lengths):
    groups = bucket_by_ladder(lengths)
    flat = np.concatenate(groups) if groups else np.array([], int)
    assert sorted(flat.tolist()) == list(range(len(lengths)))  # every run exactly once
    rungs = [{ladder(lengths[i]) for i in g} for g in groups]
    assert all(len(r) == 1 for r in rungs)  # one padded length per group
    assert [r.pop() for r in rungs] == sorted(
        {ladder(n) for n in lengths}
    )  # one group per rung, shortest first


@settings(max_examples=200, deadline=None, derandomize=True)
@given(n_runs=st.integers(1, 5000), cap=st.integers(1, 600))
def test_ladder_chunk_size_needs_the_fewest_chunks(n_runs, cap):
    size = ladder_chunk_size(n_runs, cap)
    assert 1 <= size <= cap
    assert math.ceil(n_runs / size) == math.ceil(n_runs / cap)  # no more compiled calls than the cap needs


def test_ladder_chunk_sizes_are_shared_between_buckets():
    # buckets of 90 to 120 runs under a cap of 512 share a handful of chunk shapes, not 31
    assert len({ladder_chunk_size(n, 512) for n in range(90, 121)}) <= 2


def test_pad_runs_in_numpy_equals_jax_and_stays_on_the_host(mixed_runs):
    batch = from_runs(mixed_runs).batch
    on_host = jax.tree.map(np.asarray, batch)
    padded_host, padded_jax = pad_runs(on_host, 5), pad_runs(batch, 5)
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(padded_host))
    for a, b in zip(jax.tree.leaves(padded_host), jax.tree.leaves(padded_jax), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    assert padded_host.run_index.tolist() == [0, 1, 2, -1, -1]
    assert not padded_host.valid[3:].any() and not padded_host.gt_valid[3:].any()
