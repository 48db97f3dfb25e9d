"""Parsed logs (RunLog) -> LogBatch: stacking runs into padded arrays, with host-side metadata.

The LogBatch pytree and its pure array helpers live in jsve.core; this module is the I/O edge that
fills it from parsed runs (pandas frames) and keeps per-run metadata in a DataFrame.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import pandas as pd

from jsve.core._batch import LADDER_RATIO, LogBatch, bucket_by_ladder, ladder, padded_length
from jsve.core._machine import MODE_LOST, MODE_OK, MODE_RECENTLY_LOST
from jsve.io import _schema as schema
from jsve.io._saved_trajectory import SAVED_COLUMN, in_saved_frame
from jsve.io._schema import RunLog


@dataclass(frozen=True)
class Bucket:
    """A LogBatch with its host-side metadata: `meta.iloc[i]` describes run `batch.run_index == i`."""

    batch: LogBatch
    meta: pd.DataFrame


def recorded_mode(state):
    """The replay's mode (jsve.core._machine MODE_*) of a logged eTrackingState, elementwise (numpy or
    jax arrays): OK and OK_KLT -> OK, RECENTLY_LOST -> RECENTLY_LOST, anything else -> LOST (no map)."""
    ok = (state == schema.STATE_OK) | (state == schema.STATE_OK_KLT)
    recently_lost = state == schema.STATE_RECENTLY_LOST
    return (MODE_OK * ok + MODE_RECENTLY_LOST * recently_lost + MODE_LOST * (~ok & ~recently_lost)).astype(
        "int8"
    )


RECORDED_KEYS = {"rule": "recorded_rule", "switch_model": "recorded_switch_model"}
"""Metadata keys renamed in the run table, where `rule` and `switch_model` name what is replayed."""


def run_meta_table(runs: Sequence[RunLog]) -> pd.DataFrame:
    """One row per run: run_id, source, n_frames, t0_ns and every metadata key (missing -> NA)."""
    return meta_table(
        (r.run_id, r.source, len(r.frames), int(r.frames["t_ns"].iloc[0]) if len(r.frames) else 0, r.meta)
        for r in runs
    )


def meta_columns(metas: Iterable[dict]) -> list[str]:
    """The columns `meta_table` gives runs with these metadata dicts, in its order, without building it."""
    columns = dict.fromkeys(("run_id", "source", "n_frames", "t0_ns"))
    for meta in metas:
        columns.update(dict.fromkeys(RECORDED_KEYS.get(key, key) for key in meta))
    return list(columns)


def meta_table(records: Iterable[tuple[str, str, int, int, dict]]) -> pd.DataFrame:
    """`run_meta_table` of (run_id, source, n_frames, t0_ns, meta) records, as the Parquet stream
    (jsve.io._stream) has them without parsed runs."""
    rows = []
    for run_id, source, n_frames, t0_ns, meta in records:
        row = {"run_id": run_id, "source": source, "n_frames": n_frames, "t0_ns": t0_ns}
        for key, value in meta.items():
            # The rule the recorded run ran is not the rule a table row replays: it keeps its own name.
            key = RECORDED_KEYS.get(key, key)
            row[key] = json.dumps(value, sort_keys=True) if isinstance(value, dict) else json_cell(value)
        rows.append(row)
    table = pd.DataFrame(rows)
    for key in ("disturbance",):
        if key in table:
            table[key] = table[key].fillna("none")
    return table


def json_cell(value):
    """Metadata values as table cells: lists become tuples (hashable, groupable)."""
    return tuple(value) if isinstance(value, list) else value


def map_ranks(map_id: np.ndarray) -> np.ndarray:
    """A run's Atlas map ids as dense ranks of its sorted distinct ids (int32: 0, 1, 2, ...).

    The format allows any id >= 0 that int64 holds (Map::GetId is an unsigned long), which int32 would
    wrap (2**32 + 5 onto 5: two maps taken for one). The replay only compares ids (a map starts where the
    id changes, a reset stays in its map: jsve.core._replay.frame_data), and ranks compare as the ids
    do; ids 0, 1, 2 ... stay as they are.
    """
    _, ranks = np.unique(np.asarray(map_id, np.int64), return_inverse=True)
    return ranks.reshape(np.shape(map_id)).astype(np.int32)


def from_runs(
    runs: Sequence[RunLog], *, n_frames: int | None = None, dtype=jnp.float32, pad_multiple: int = 64
) -> Bucket:
    """Stack runs into one padded LogBatch.

    Arguments:
        runs: parsed logs (validated by jsve.io._logs); poses of v3 logs with ORB-SLAM3's trailer are
            those of its saved trajectory, of others with world_* columns re-expressed in one world
            frame per recorded segment (jsve.io._saved_trajectory.in_saved_frame).
        n_frames: padded length; default: the longest run rounded up to `pad_multiple`.
        dtype: float dtype of the arrays (float64 needs jax_enable_x64).
    Returns:
        Bucket(batch, meta) with meta from `run_meta_table`.
    """
    if not runs:
        raise ValueError("from_runs: no runs given")
    lengths = [len(r.frames) for r in runs]
    if min(lengths) < 1:
        empty = [r.source for r in runs if len(r.frames) == 0]
        raise ValueError(f"from_runs: runs without frames: {empty[:5]}")
    F = n_frames if n_frames is not None else padded_length(max(lengths), pad_multiple)
    if F < max(lengths):
        raise ValueError(f"from_runs: n_frames={F} is shorter than the longest run ({max(lengths)} frames)")
    R = len(runs)
    fdt = np.dtype(jnp.dtype(dtype).name)

    def alloc(shape, dt, fill=0):
        return np.full((R, F) + shape, fill, dtype=dt)

    t, valid = alloc((), fdt), alloc((), bool, False)
    state, imu_init, imu_ba2 = alloc((), np.int8), alloc((), bool, False), alloc((), bool, False)
    map_id, has_pose, in_saved = alloc((), np.int32), alloc((), bool, False), alloc((), bool, False)
    n_ext, n_inl, n_fru = alloc((), np.int32), alloc((), np.int32), alloc((), np.int32)
    bins = alloc((schema.N_BINS,), np.uint16)
    vis_p, vis_v, imu_dp, imu_dv, gt_p = (alloc((3,), fdt) for _ in range(5))
    vis_q, imu_dq, gt_q = (alloc((4,), fdt) for _ in range(3))
    for q in (vis_q, imu_dq, gt_q):
        q[..., 0] = 1.0
    imu_dt, gt_valid = alloc((), fdt), alloc((), bool, False)
    fps = np.zeros(R, fdt)
    gravity = np.zeros((R, 3), fdt)
    delay, ba2_delay = np.zeros(R, fdt), np.zeros(R, fdt)
    n_features, stereo = np.zeros(R, fdt), np.zeros(R, bool)
    for i, run in enumerate(runs):
        # The saved trajectory's frame (v3), or one world frame per recorded map segment.
        f = in_saved_frame(run).frames
        n = len(f)
        stamps = f["t_ns"].to_numpy(np.int64)
        t[i, :n] = (stamps - stamps[0]) / 1e9  # int64 difference first: exact, then to seconds
        valid[i, :n] = True
        state[i, :n] = f["state"].to_numpy()
        init = f["imu_init"].to_numpy() != 0
        ba2 = f["imu_ba2"].to_numpy() != 0
        posed = np.isfinite(f[list(schema.VIS_POSITION)].to_numpy()).all(axis=1)  # NaN: no pose (v2)
        imu_init[i, :n], imu_ba2[i, :n], has_pose[i, :n] = init, ba2, posed
        in_saved[i, :n] = f[SAVED_COLUMN].to_numpy() != 0
        map_id[i, :n] = map_ranks(f["map_id"].to_numpy())
        # Delays from the recorded run's first map (its first posed frame), as a new map needs them.
        t_first = t[i, int(np.argmax(posed))] if posed.any() else 0.0
        delay[i] = t[i, int(np.argmax(init))] - t_first if init.any() else np.inf
        ba2_delay[i] = t[i, int(np.argmax(ba2))] - t_first if ba2.any() else np.inf
        n_ext[i, :n] = f["n_extracted"].to_numpy()
        n_inl[i, :n] = f["n_inliers"].to_numpy()
        n_fru[i, :n] = f["n_frustum"].to_numpy()
        bins[i, :n] = f[list(schema.BIN_COLUMNS)].to_numpy()
        vis_p[i, :n][posed] = f[list(schema.VIS_POSITION)].to_numpy()[posed]
        vis_q[i, :n][posed] = f[list(schema.VIS_QUATERNION)].to_numpy()[posed]
        vis_v[i, :n][posed] = f[list(schema.VIS_VELOCITY)].to_numpy()[posed]
        imu_dt[i, :n] = f["imu_dt"].to_numpy()
        imu_dp[i, :n] = f[list(schema.IMU_DP)].to_numpy()
        imu_dv[i, :n] = f[list(schema.IMU_DV)].to_numpy()
        imu_dq[i, :n] = f[list(schema.IMU_DQ)].to_numpy()
        if run.has_ground_truth:
            gp = f[list(schema.GT_POSITION)].to_numpy()
            gq = f[list(schema.GT_QUATERNION)].to_numpy()
            ok = np.isfinite(gp).all(1) & np.isfinite(gq).all(1)
            gt_p[i, :n][ok] = gp[ok]
            gt_q[i, :n][ok] = gq[ok]
            gt_valid[i, :n] = ok
        fps[i] = float(run.meta["fps"])
        gravity[i] = run.meta.get("gravity", schema.DEFAULT_GRAVITY)
        n_features[i] = run.meta.get("n_features", schema.DEFAULT_N_FEATURES)
        stereo[i] = run.meta.get("sensor", "imu_monocular") in schema.STEREO_SENSORS
    batch = LogBatch(
        t=jnp.asarray(t),
        valid=jnp.asarray(valid),
        state=jnp.asarray(state),
        imu_init=jnp.asarray(imu_init),
        imu_ba2=jnp.asarray(imu_ba2),
        map_id=jnp.asarray(map_id),
        has_pose=jnp.asarray(has_pose),
        in_saved=jnp.asarray(in_saved),
        n_extracted=jnp.asarray(n_ext),
        n_inliers=jnp.asarray(n_inl),
        n_frustum=jnp.asarray(n_fru),
        bins=jnp.asarray(bins),
        vis_p=jnp.asarray(vis_p),
        vis_q=jnp.asarray(vis_q),
        vis_v=jnp.asarray(vis_v),
        imu_dt=jnp.asarray(imu_dt),
        imu_dp=jnp.asarray(imu_dp),
        imu_dv=jnp.asarray(imu_dv),
        imu_dq=jnp.asarray(imu_dq),
        gt_p=jnp.asarray(gt_p),
        gt_q=jnp.asarray(gt_q),
        gt_valid=jnp.asarray(gt_valid),
        fps=jnp.asarray(fps),
        gravity=jnp.asarray(gravity),
        imu_init_delay=jnp.asarray(delay),
        ba2_delay=jnp.asarray(ba2_delay),
        n_features=jnp.asarray(n_features),
        stereo=jnp.asarray(stereo),
        run_index=jnp.arange(R, dtype=jnp.int32),
    )
    return Bucket(batch=batch, meta=run_meta_table(runs).reset_index(drop=True))


def buckets(runs: Sequence[RunLog], *, ratio: float = LADDER_RATIO, dtype=jnp.float32) -> list[Bucket]:
    """Split runs into length buckets, one per rung of the padded-length ladder (`bucket_by_ladder`),
    and stack each into a Bucket padded to its rung: a study has a handful of frame counts, and every
    compiled evaluation is reused by all the buckets, and the studies, that share its rung."""
    groups = bucket_by_ladder([len(r.frames) for r in runs], ratio=ratio)
    return [
        from_runs([runs[i] for i in g], n_frames=ladder(len(runs[g[-1]].frames), ratio=ratio), dtype=dtype)
        for g in groups
    ]
