"""World frames: the log's world_* columns (ORB-SLAM3 re-expressing a map) read, checked and undone.

The oracle re-expresses camera poses the way ORB-SLAM3's Map::ApplyScaledRotation does (4 x 4 matrices,
scipy rotations; src/Map.cc: Twc.translation() *= s, Tyc = Tyw Twc) and derives the logged body pose
as ORB-SLAM3's Frame::GetImuPosition does (T_wb = T_wc T_cb, the camera-body offset unscaled), so
jsve.io._world's closed form is checked against the procedure it inverts, not against itself.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from logfactory import make_run, set_field
from scipy.spatial.transform import Rotation

from jsve.io import _schema as schema
from jsve.io import from_runs, read_log, read_parquet, write_log
from jsve.io._errors import LogFormatError
from jsve.io._parquet import ingest
from jsve.io._schema import RunLog
from jsve.io._world import in_one_world_frame, segment_last_frame, to_last_world_frame


def _wxyz(rot: Rotation) -> np.ndarray:
    return np.roll(rot.as_quat(), 1, axis=-1)


def _rot(q_wxyz) -> Rotation:
    return Rotation.from_quat(np.roll(np.asarray(q_wxyz), -1, axis=-1))


def _matrix(rot: Rotation, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot.as_matrix(), t
    return m


def _apply_scaled_rotation(t_wc: np.ndarray, t_yw: np.ndarray, s: float) -> np.ndarray:
    """ORB-SLAM3's Map::ApplyScaledRotation on one camera pose T_wc (4 x 4)."""
    scaled = t_wc.copy()
    scaled[:3, 3] *= s
    return t_yw @ scaled


def _oracle_run(n=120, changes=((40, 0.5), (80, 1.3)), seed=3):
    """(logged body poses, world similarities per frame, body poses in the last world frame, T_bc).

    A camera trajectory in the map's first world frame; at frame k of each (k, s) of `changes` the map
    is re-expressed by a random rotation and translation and scale s. Frame j's logged pose is its
    camera pose re-expressed by every change at or before j, turned into a body pose.
    """
    rng = np.random.default_rng(seed)
    rot_c = Rotation.from_rotvec(rng.normal(scale=0.6, size=(n, 3)))
    p_c = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    t_bc = _matrix(Rotation.from_rotvec([0.1, -0.2, 1.5]), [-0.02, -0.065, 0.01])
    t_cb = np.linalg.inv(t_bc)
    cams = [_matrix(rot_c[i], p_c[i]) for i in range(n)]
    sims = [(np.eye(4), 1.0)]
    for _, s in changes:
        t_yw = _matrix(Rotation.from_rotvec(rng.normal(size=3)), rng.normal(size=3))
        sims.append((t_yw, s))
    logged, world, final = [], [], []
    for j in range(n):
        applied = [0] + [i + 1 for i, (k, _) in enumerate(changes) if k <= j]
        cam = cams[j]
        w = np.eye(4)  # the accumulated similarity as a 4 x 4 with the scale in the rotation block
        for i in applied[1:]:
            t_yw, s = sims[i]
            cam = _apply_scaled_rotation(cam, t_yw, s)
            sim = t_yw.copy()
            sim[:3, :3] *= s
            w = sim @ w
        logged.append(cam @ t_cb)
        world.append(w)
        cam_final = cams[j]
        for t_yw, s in sims[1:]:
            cam_final = _apply_scaled_rotation(cam_final, t_yw, s)
        final.append(cam_final @ t_cb)
    return np.array(logged), np.array(world), np.array(final), t_bc


def _split_similarity(w: np.ndarray):
    s = np.cbrt(np.linalg.det(w[:, :3, :3]))
    return _wxyz(Rotation.from_matrix(w[:, :3, :3] / s[:, None, None])), w[:, :3, 3], s


def test_poses_return_to_the_world_frame_the_map_ends_in():
    logged, world, final, t_bc = _oracle_run()
    q_w, t_w, s_w = _split_similarity(world)
    n = len(logged)
    v = np.random.default_rng(0).normal(size=(n, 3))
    p2, q2, v2 = to_last_world_frame(
        logged[:, :3, 3], _wxyz(Rotation.from_matrix(logged[:, :3, :3])), v, q_w, t_w, s_w,
        np.full(n, n - 1), np.concatenate([_wxyz(Rotation.from_matrix(t_bc[:3, :3])), t_bc[:3, 3]]),
    )  # fmt: skip
    np.testing.assert_allclose(p2, final[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(_rot(q2).as_matrix(), final[:, :3, :3], atol=1e-12)
    # velocities: the map's scale and rotation since each frame (ApplyScaledRotation, bScaledVel)
    rel = world[-1] @ np.linalg.inv(world)
    np.testing.assert_allclose(v2, np.einsum("fij,fj->fi", rel[:, :3, :3], v), atol=1e-12)


def test_without_the_body_offset_the_lever_arm_matters():
    """Moving the body pose as if it were the camera is off by (s - 1) R R_b t_bc: T_bc is needed."""
    logged, world, final, _ = _oracle_run()
    q_w, t_w, s_w = _split_similarity(world)
    n = len(logged)
    p2, _, _ = to_last_world_frame(
        logged[:, :3, 3], _wxyz(Rotation.from_matrix(logged[:, :3, :3])), np.zeros((n, 3)), q_w, t_w, s_w,
        np.full(n, n - 1),
    )  # fmt: skip
    assert np.abs(p2 - final[:, :3, 3]).max() > 1e-3


def test_segments_end_at_a_gap_or_a_new_map():
    posed = np.array([0, 1, 1, 1, 0, 1, 1, 1, 1, 0], bool)
    map_id = np.array([0, 0, 0, 0, 0, 0, 0, 3, 3, 3])
    np.testing.assert_array_equal(segment_last_frame(posed, map_id), [-1, 3, 3, 3, -1, 6, 6, 8, 8, -1])
    assert (segment_last_frame(np.zeros(4, bool), np.zeros(4, int)) == -1).all()


def _with_world(run: RunLog, world: np.ndarray, t_bc=None) -> RunLog:
    f = run.frames.copy()
    q, t, s = _split_similarity(world)
    for names, values in ((schema.WORLD_QUATERNION, q), (schema.WORLD_TRANSLATION, t)):
        f[list(names)] = values
    f[schema.WORLD_SCALE] = s
    meta = dict(run.meta)
    if t_bc is not None:
        meta["camera_in_body"] = [float(x) for x in _wxyz(Rotation.from_matrix(t_bc[:3, :3]))] + [
            float(x) for x in t_bc[:3, 3]
        ]
    return RunLog(meta=meta, frames=f, source=run.source)


def _oracle_log(tmp_path=None):
    logged, world, final, t_bc = _oracle_run()
    run = make_run(len(logged), seed=5)
    f = run.frames.copy()
    f[list(schema.VIS_POSITION)] = logged[:, :3, 3]
    f[list(schema.VIS_QUATERNION)] = _wxyz(Rotation.from_matrix(logged[:, :3, :3]))
    run = _with_world(RunLog(meta=run.meta, frames=f, source="oracle"), world, t_bc)
    return run, final


def test_a_log_with_world_columns_round_trips_and_batches_in_one_frame(tmp_path):
    run, final = _oracle_log()
    path = write_log(run, tmp_path / "w.csv")
    back = read_log(path)
    assert back.has_world_frame
    assert list(back.frames.columns[-8:]) == list(schema.WORLD_COLUMNS)
    pd.testing.assert_frame_equal(back.frames, run.frames, check_exact=True)
    one = in_one_world_frame(back)
    assert not one.has_world_frame
    np.testing.assert_allclose(one.frames[list(schema.VIS_POSITION)].to_numpy(), final[:, :3, 3], atol=1e-12)
    # the replay's input (float32: positions of a few metres to ~1e-6 m)
    batch = from_runs([back]).batch
    np.testing.assert_allclose(np.asarray(batch.vis_p[0, : len(final)]), final[:, :3, 3], atol=1e-5)
    # through Parquet, beside a run without world columns
    plain = make_run(50, seed=9)
    plain = RunLog(meta={**plain.meta, "run": 1}, frames=plain.frames, source="plain")
    ingest([path, write_log(plain, tmp_path / "p.csv")], tmp_path / "s.parquet", progress=False)
    runs = {r.source: r for r in read_parquet(tmp_path / "s.parquet")}
    pd.testing.assert_frame_equal(runs[str(path)].frames, run.frames, check_exact=True)
    assert not runs[str(tmp_path / "p.csv")].has_world_frame


def test_bad_world_values_name_line_and_column(tmp_path):
    run, _ = _oracle_log()
    path = write_log(run, tmp_path / "w.csv")
    set_field(path, line=9, column="world_s", text="0")
    with pytest.raises(LogFormatError, match=r"w.csv:9: column 'world_s' = '0': must be > 0"):
        read_log(path)
    path = write_log(run, tmp_path / "w2.csv")
    set_field(path, line=5, column="world_qx", text="0.5")
    with pytest.raises(
        LogFormatError, match=r"w2.csv:5: columns 'world_qw..world_qz'.*not a unit quaternion"
    ):
        read_log(path)


def test_partial_world_columns_are_refused(tmp_path):
    run, _ = _oracle_log()
    f = run.frames.drop(columns=["world_s"])
    with pytest.raises(LogFormatError, match="world-frame columns partially present.*lacks 'world_s'"):
        write_log(RunLog(meta=run.meta, frames=f), tmp_path / "x.csv")


def test_camera_in_body_must_be_a_pose(tmp_path):
    run, _ = _oracle_log()
    bad = RunLog(meta={**run.meta, "camera_in_body": [1, 0, 0, 0, 0, 0]}, frames=run.frames)
    with pytest.raises(LogFormatError, match="camera_in_body"):
        write_log(bad, tmp_path / "x.csv")
