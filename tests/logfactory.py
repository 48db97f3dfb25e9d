"""Synthetic, valid format-v2 runs for tests, and text-level edits to make broken log files.

    from logfactory import make_run, set_field
    run = make_run(300, seed=1, sequence="MH_04", disturbance="blur", level=15)
    write_log(run, tmp_path / "r1.csv")
    set_field(tmp_path / "r1.csv", line=12, column="imu_dt", text="-0.05")   # now invalid at line 12

`make_run` draws every value at random (deterministically from `seed`) within the v2 rules: strictly
increasing int64 stamps with jitter, ORB-SLAM3 states, one map (map_id 0) with imu_ba2 by
schema.v1_defaults unless asked otherwise, counts with n_inliers <= n_extracted and the binned
keypoints <= n_extracted, unit quaternions (wxyz), optionally frames without a pose (NaN vis_*, only
outside states 2, 3, 5), IMU preintegration from the previous frame with frame 0 at imu_dt = 0 and
identity, and optional ground truth. `v1_text` turns a written v2 log into the v1 file it would have
been. It is not a physical simulation
(the simulator is jsve.sim._simulate): positions, velocities and preintegration are not consistent with
each other. Floats use all 17 significant digits, so round trips are a real test of exactness.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.io import _schema as schema
from jsve.io._schema import RunLog

EUROC_T0_NS = 1_403_715_274_312_143_104
"""A realistic EuRoC stamp (V1_01's first ground-truth sample), ns: float64 cannot hold it exactly."""

DEFAULT_META = {
    "sequence": "SYN",
    "disturbance": "none",
    "level": 0,
    "sensor": "imu_monocular",
    "n_features": 1000,
    "image_size": [752, 480],
    "grid": [8, 8],
    "fps": 20,
    "gravity": [0.0, 0.0, -9.81],
    "frontend": "tests/logfactory.py",
}


def _unit_quaternions(rng: np.random.Generator, n: int, spread: float | None = None) -> np.ndarray:
    """n unit wxyz quaternions: uniform on SO(3), or within ~`spread` rad of the identity."""
    if spread is None:
        q = rng.normal(size=(n, 4))
    else:
        q = np.concatenate([np.ones((n, 1)), rng.normal(scale=spread / 2, size=(n, 3))], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def make_run(
    n_frames: int = 200,
    seed: int = 0,
    *,
    with_gt: bool = True,
    gt_missing: float = 0.0,
    t0_ns: int = EUROC_T0_NS,
    period_ns: int | None = None,
    awkward_floats: bool = False,
    no_pose: float = 0.0,
    map_id: np.ndarray | None = None,
    source: str = "<memory>",
    **meta,
) -> RunLog:
    """A random, valid format-v2 run.

    Arguments:
        n_frames: frames (>= 1).
        seed: seeds every random draw; also the default metadata `run`.
        with_gt: add the seven gt_* columns.
        gt_missing: fraction of frames (drawn at random) with no ground truth (all seven gt_* NaN).
        t0_ns: stamp of frame 0, ns.
        period_ns: mean frame spacing, ns (default 1e9 / fps); each step is jittered by up to +-10 %.
        awkward_floats: put -0.0, the smallest subnormal, the largest float32 (schema.FLOAT_MAX, the
            largest value a log may hold) and 0.1 into vis_v* of frames 1-4
            (needs n_frames >= 5): values that a careless writer would not round-trip.
        no_pose: fraction of frames (drawn at random among those not in states 2, 3, 5, and never
            frames 1-4 with awkward_floats) without a pose: all ten vis_* NaN.
        map_id: [n_frames] int map ids (default 0 on every frame).
        source: RunLog.source.
        **meta: metadata entries, overriding DEFAULT_META and `run` (e.g. sequence="MH_04", level=15).

    Returns:
        RunLog with frames in v2 column order, int64 / float64.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    rng = np.random.default_rng(seed)
    meta = {**DEFAULT_META, "run": seed, **meta}
    if period_ns is None:
        period_ns = int(round(1e9 / meta["fps"]))
    n = n_frames

    step = period_ns + rng.integers(-period_ns // 10, period_ns // 10 + 1, size=n - 1)
    t_ns = t0_ns + np.concatenate([[0], np.cumsum(step)]).astype(np.int64)

    state = rng.choice(np.array([1, 2, 2, 2, 2, 3, 4, 5]), size=n).astype(np.int64)
    imu_init = (np.arange(n) >= rng.integers(0, n)).astype(np.int64)
    n_features = int(meta.get("n_features", 1000))
    n_extracted = rng.integers(0, n_features + 1, size=n)
    n_binned = rng.binomial(n_extracted, 0.95)
    bins = np.stack([rng.multinomial(k, rng.dirichlet(np.ones(schema.N_BINS))) for k in n_binned])
    n_inliers = rng.integers(0, n_extracted + 1)
    n_frustum = rng.integers(0, 2 * n_features + 1, size=n)

    cols: dict[str, np.ndarray] = {
        "t_ns": t_ns,
        "state": state,
        "imu_init": imu_init,
        **schema.v1_defaults(t_ns, imu_init),
        "n_extracted": n_extracted.astype(np.int64),
        "n_inliers": n_inliers.astype(np.int64),
        "n_frustum": n_frustum.astype(np.int64),
    }
    for k, c in enumerate(schema.BIN_COLUMNS):
        cols[c] = bins[:, k].astype(np.int64)

    def put(names, values):
        for k, c in enumerate(names):
            cols[c] = np.ascontiguousarray(values[:, k], dtype=np.float64)

    put(schema.VIS_POSITION, np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0))
    put(schema.VIS_QUATERNION, _unit_quaternions(rng, n))
    put(schema.VIS_VELOCITY, rng.normal(size=(n, 3)))
    dt = np.concatenate([[0.0], np.diff(t_ns).astype(np.float64) * 1e-9])
    cols["imu_dt"] = dt
    dp = rng.normal(scale=0.05, size=(n, 3))
    dv = rng.normal(scale=0.5, size=(n, 3))
    dq = _unit_quaternions(rng, n, spread=0.05)
    dp[0], dv[0], dq[0] = 0.0, 0.0, (1.0, 0.0, 0.0, 0.0)  # first frame: nothing preintegrated
    put(schema.IMU_DP, dp)
    put(schema.IMU_DV, dv)
    put(schema.IMU_DQ, dq)
    if awkward_floats:
        if n < 5:
            raise ValueError("awkward_floats needs n_frames >= 5")
        cols["vis_vx"][1:5] = [-0.0, 5e-324, schema.FLOAT_MAX, 0.1]
    if map_id is not None:
        cols["map_id"] = np.asarray(map_id, dtype=np.int64)
    if no_pose:
        posed = np.isin(state, schema.POSED_STATES)
        if awkward_floats:
            posed[1:5] = True
        lacking = ~posed & (rng.random(n) < no_pose)
        for c in schema.VIS_COLUMNS:
            cols[c][lacking] = np.nan
    if with_gt:
        gp = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
        gq = _unit_quaternions(rng, n)
        missing = rng.random(n) < gt_missing
        gp[missing] = np.nan
        gq[missing] = np.nan
        put(schema.GT_POSITION, gp)
        put(schema.GT_QUATERNION, gq)
    order = schema.COLUMNS if with_gt else schema.REQUIRED_COLUMNS
    return RunLog(meta=meta, frames=pd.DataFrame(cols, columns=list(order)), source=source)


# ---------------------------------------------------------------------------------------------------
# Text-level edits of a written log (1-based line numbers, as in LogFormatError messages).


def v1_text(path: str | os.PathLike) -> None:
    """Rewrite a v2 log in place as the v1 file it would have been: v1 magic, no map_id / imu_ba2.

    The log must have a pose on every frame (v1 has no empty vis_* fields)."""
    lines = read_lines(path)
    drop = [lines[1].split(",").index(c) for c in schema.MAP_COLUMNS]
    lines[0] = schema.MAGICS[1] + lines[0][len(schema.MAGIC) :]
    for i in range(1, len(lines) - 1):
        fields = lines[i].split(",")
        lines[i] = ",".join(f for k, f in enumerate(fields) if k not in drop)
    write_lines(path, lines)


def read_lines(path: str | os.PathLike) -> list[str]:
    """The lines of a file, without line ends."""
    return Path(path).read_text().split("\n")[:-1]


def write_lines(path: str | os.PathLike, lines: list[str], *, final_newline: bool = True) -> None:
    Path(path).write_text("\n".join(lines) + ("\n" if final_newline else ""))


def edit_line(path: str | os.PathLike, line: int, text: str | None) -> None:
    """Replace line `line` with `text`, or delete it when text is None."""
    lines = read_lines(path)
    if text is None:
        del lines[line - 1]
    else:
        lines[line - 1] = text
    write_lines(path, lines)


def set_field(path: str | os.PathLike, line: int, column: str, text: str) -> None:
    """Set one field of a data row (line >= 3) to `text`, found by the header's column name."""
    lines = read_lines(path)
    k = lines[1].split(",").index(column)
    fields = lines[line - 1].split(",")
    fields[k] = text
    lines[line - 1] = ",".join(fields)
    write_lines(path, lines)


def get_field(path: str | os.PathLike, line: int, column: str) -> str:
    """The text of one field of a data row."""
    lines = read_lines(path)
    return lines[line - 1].split(",")[lines[1].split(",").index(column)]


def same_bits(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Same columns, dtypes and bit patterns (so NaN == NaN and -0.0 != 0.0): an exact round trip."""
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return False
    return all(
        a[c].dtype == b[c].dtype
        and np.array_equal(a[c].to_numpy().view(np.int64), b[c].to_numpy().view(np.int64))
        for c in a.columns
    )
