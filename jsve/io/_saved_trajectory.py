"""ORB-SLAM3's own saved trajectory, rebuilt from a format-v3 log (its `orbslam3` trailer).

What a SLAM researcher scores is the trajectory ORB-SLAM3 writes at the end of a run,
System::SaveTrajectoryEuRoC (ORB-SLAM3 v1.0, src/System.cc l.662-777), not the online poses: it keeps
the map with the most keyframes (the first such map in id order), and poses every entry of the
tracker's trajectory lists (one per frame that ended in OK or RECENTLY_LOST, Tracking.cc l.2300-2318)
that is not marked lost as

    T_wb = (T_bc  T_cr  T_rw)^-1,   T_rw = T_cp,1 ... T_cp,n  T_cw(K)  T_w b0

where r is the entry's reference keyframe, a bad (culled) keyframe is replaced by its parent with its
T_cp (the keyframe's pose relative to its parent when it was culled) until a good one K is reached,
T_cw(K) is K's final, bundle-adjusted and loop-corrected pose, and b0 is the body of the saved map's
lowest-id keyframe. Entries whose keyframe K is not in the saved map (another map, or a reset map's,
whose keyframes belong to none) are left out. The hook's trailer holds exactly those inputs at the end
of the run (jsve_orbslam3_hook.hpp, write_trailer), so the rebuild equals the saved file up to the
float32 arithmetic ORB-SLAM3 composes in and the 9 decimals it prints.

Poses are [qw, qx, qy, qz, tx, ty, tz] (the form of the metadata `camera_in_body`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jsve.core._geometry import quat_conj, quat_mul, quat_normalize, quat_rotate
from jsve.io import _schema as schema
from jsve.io._errors import LogFormatError
from jsve.io._schema import RunLog


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a o b of rigid transforms [..., 7] ([qw, qx, qy, qz, tx, ty, tz]), float64."""
    q = quat_mul(a[..., :4], b[..., :4], xp=np)
    t = a[..., 4:] + quat_rotate(a[..., :4], b[..., 4:], xp=np)
    return np.concatenate([q, t], axis=-1)


def invert(a: np.ndarray) -> np.ndarray:
    """a^-1 of rigid transforms [..., 7]."""
    qi = quat_conj(a[..., :4], xp=np)
    return np.concatenate([qi, -quat_rotate(qi, a[..., 4:], xp=np)], axis=-1)


IDENTITY = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True)
class SavedTrajectory:
    """The trajectory ORB-SLAM3 saves, rebuilt from a log.

    Attributes:
        rows: [N] the log rows (frames) of its poses, increasing.
        t_ns: [N] their stamps, ns.
        pose: [N, 7] body poses T_b0 b, in the saved file's frame (the saved map's first keyframe's body).
        world_pose: [N, 7] the same poses in the saved map's world frame (T_w b = T_w b0 T_b0 b: gravity
            along -z once the map's IMU is initialised).
        saved_map: the saved map's id. n_frames: the log's frames.
    """

    rows: np.ndarray
    t_ns: np.ndarray
    pose: np.ndarray
    world_pose: np.ndarray
    saved_map: int
    n_frames: int

    @property
    def coverage(self) -> float:
        """Share of the log's frames that have a saved pose."""
        return len(self.rows) / self.n_frames if self.n_frames else 0.0


class _Keyframes:
    """The trailer's keyframe table, indexed by id."""

    def __init__(self, table: dict, source: str):
        ids = np.asarray(table["id"], np.int64)
        self.ids = ids
        self.index = {int(k): i for i, k in enumerate(ids)}
        self.map_id = np.asarray(table["map_id"], np.int64)
        self.bad = np.asarray(table["bad"], bool)
        self.parent = np.asarray(table["parent"], np.int64)
        self.t_cw = _poses(table["t_cw"])
        self.t_cp = _poses(table["t_cp"])
        self.source = source

    def resolve(self, kf: int) -> tuple[int, np.ndarray] | None:
        """(good keyframe K, T_cp chain) for keyframe `kf`: SaveTrajectoryEuRoC's walk up the spanning
        tree from a bad keyframe; None where the walk leaves the table (no parent)."""
        chain = IDENTITY
        seen = 0
        while True:
            i = self.index.get(int(kf))
            if i is None:
                return None
            if not self.bad[i]:
                return i, chain
            chain = compose(chain, self.t_cp[i])
            kf = self.parent[i]
            seen += 1
            if kf < 0 or seen > len(self.index):
                return None


def _keyframe_poses(kfs: _Keyframes, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For reference keyframe ids `refs` [N]: (found [N] bool, the map of the good keyframe each
    resolves to [N] (-1 where not found), T_rw [N, 7] = its T_cp chain o its final T_cw). Each distinct
    keyframe is resolved once."""
    unique, inverse = np.unique(np.asarray(refs, np.int64), return_inverse=True)
    found = np.zeros(len(unique), bool)
    maps = np.full(len(unique), -1, np.int64)
    t_rw = np.tile(IDENTITY, (len(unique), 1))
    for u, kf in enumerate(unique):
        resolved = kfs.resolve(kf) if kf >= 0 else None
        if resolved is not None:
            i, chain = resolved
            found[u], maps[u], t_rw[u] = True, kfs.map_id[i], compose(chain, kfs.t_cw[i])
    inverse = inverse.reshape(-1)
    return found[inverse], maps[inverse], t_rw[inverse]


def _body_in_world(t_bc: np.ndarray, t_cr: np.ndarray, t_rw: np.ndarray) -> np.ndarray:
    """T_wb = (T_bc T_cr T_rw)^-1 of frames [N, 7] (SaveTrajectoryEuRoC's composition)."""
    return invert(compose(compose(np.broadcast_to(t_bc, t_cr.shape), t_cr), t_rw))


def _poses(values) -> np.ndarray:
    p = np.asarray(values, np.float64).reshape(-1, 7)
    return np.concatenate([quat_normalize(p[:, :4], xp=np), p[:, 4:]], axis=1)


def saved_map_id(maps: dict) -> int | None:
    """The map SaveTrajectoryEuRoC saves: the first, in id order, with the most keyframes (None: no
    map has a keyframe, where ORB-SLAM3 saves nothing)."""
    order = np.argsort(np.asarray(maps["id"], np.int64), kind="stable")
    best, best_n = None, 0
    for i in order:
        if maps["keyframes"][i] > best_n:
            best, best_n = int(maps["id"][i]), int(maps["keyframes"][i])
    return best


def _trailer(run: RunLog) -> dict:
    trailer = (run.trailers or {}).get(schema.ORBSLAM3_TRAILER)
    if trailer is None:
        raise LogFormatError(
            run.source,
            None,
            f"no '{schema.ORBSLAM3_TRAILER}' trailer: ORB-SLAM3's saved trajectory can be rebuilt only from "
            "a format-v3 log of jsve's hook (a run that ended normally)",
        )
    check_trailer(trailer, run.source)
    return trailer


TRAILER_FIELDS = {
    "maps": ("id", "keyframes"),
    "keyframes": ("id", "map_id", "bad", "parent", "t_cw", "t_cp"),
    "trajectory": ("row", "ref_kf", "lost", "t_cr"),
}
"""The `orbslam3` trailer's tables and their columns (docs/log-format.md, "Format v3"); with `t_bc`."""


def check_trailer(trailer, source: str) -> None:
    """Raise LogFormatError naming the log and the field where the `orbslam3` trailer lacks a table or a
    column, has columns of different lengths, or a pose that is not 7 numbers."""

    def fail(reason):
        raise LogFormatError(source, None, f"trailer '{schema.ORBSLAM3_TRAILER}': {reason}")

    if not isinstance(trailer, dict):
        fail("not a JSON object")
    if np.shape(trailer.get("t_bc")) != (7,):
        fail("'t_bc' must be 7 numbers [qw, qx, qy, qz, tx, ty, tz]")
    for table, columns in TRAILER_FIELDS.items():
        part = trailer.get(table)
        if not isinstance(part, dict) or any(c not in part for c in columns):
            fail(f"'{table}' must be an object with {', '.join(columns)}")
        lengths = {c: len(part[c]) for c in columns}
        if len(set(lengths.values())) > 1:
            fail(f"'{table}' columns differ in length: {lengths}")
        for c in ("t_cw", "t_cp", "t_cr"):
            if c in part and len(part[c]) and np.shape(part[c])[1:] != (7,):
                fail(f"'{table}.{c}' must hold poses of 7 numbers")


def saved_trajectory(run: RunLog) -> SavedTrajectory | None:
    """SaveTrajectoryEuRoC's trajectory of a v3 log (module docstring); None where ORB-SLAM3 saves none
    (no map holds a keyframe).

    Raises:
        LogFormatError: the log has no `orbslam3` trailer, or its trajectory rows do not match its frames.
    """
    trailer = _trailer(run)
    saved = saved_map_id(trailer["maps"])
    n = len(run.frames)
    if saved is None:
        return None
    kfs = _Keyframes(trailer["keyframes"], run.source)
    traj = trailer["trajectory"]
    rows = np.asarray(traj["row"], np.int64)
    if np.any(rows >= n) or np.any(np.diff(rows[rows >= 0]) <= 0):
        raise LogFormatError(
            run.source, None, "the trailer's trajectory rows are not increasing frames of the log"
        )
    t_bc = _poses([trailer["t_bc"]])[0]
    map_kfs = np.flatnonzero((kfs.map_id == saved) & ~kfs.bad)
    first = map_kfs[np.argmin(kfs.ids[map_kfs])]  # the saved map's lowest-id keyframe
    # T_w b0 = T_wc T_cb of that keyframe (KeyFrame::GetImuPose).
    t_wb0 = compose(invert(kfs.t_cw[first]), invert(t_bc))
    t_cr = _poses(traj["t_cr"])
    refs = np.asarray(traj["ref_kf"], np.int64)
    found, maps, t_rw = _keyframe_poses(kfs, refs)
    keep = ~np.asarray(traj["lost"], bool) & (rows >= 0) & found & (maps == saved)
    # T_rw T_w b0: the keyframe's pose relative to the saved map's first body (the file's frame).
    pose = _body_in_world(t_bc, t_cr[keep], compose(t_rw[keep], np.broadcast_to(t_wb0, t_rw[keep].shape)))
    rows_kept = rows[keep]
    return SavedTrajectory(
        rows=rows_kept,
        t_ns=run.frames["t_ns"].to_numpy()[rows_kept],
        pose=pose,
        world_pose=compose(np.broadcast_to(t_wb0, pose.shape), pose),
        saved_map=saved,
        n_frames=n,
    )


def event_counts(run: RunLog) -> dict[str, int]:
    """Per-run counts of the front-end's events (schema.EVENTS) of a v3 log: frames whose `events` has
    each bit; all zero for a log without the keyframe columns."""
    if not run.has_keyframes:
        return {name: 0 for name in schema.EVENTS}
    events = run.frames["events"].to_numpy()
    return {name: int(np.count_nonzero(events & bit)) for name, bit in schema.EVENTS.items()}


def write_euroc(t_ns: np.ndarray, pose: np.ndarray, path) -> None:
    """Poses [N, 7] at stamps t_ns as a EuRoC CSV (`t_ns,p_x,p_y,p_z,q_w,q_x,q_y,q_z`), evo-readable;
    numbers in the shortest text that reads back to the same double."""
    lines = ["#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []"]
    for t, p in zip(t_ns, pose, strict=True):
        lines.append(",".join([str(int(t))] + [repr(float(x)) for x in (*p[4:], *p[:4])]))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def euroc_ate(reference, estimate, align: str = "se3") -> tuple[float, int]:
    """(ATE RMSE in metres, associated poses) of a EuRoC trajectory file against a EuRoC ground truth,
    as `jsve ape REF EST --format euroc --align ALIGN` computes it (evo's association, float64)."""
    import jax

    from jsve.core._pose_error_batch import batched_ape
    from jsve.io._trajectories import read_pose_pairs, stack_pose_pairs

    pair = read_pose_pairs(reference, [estimate], "euroc")
    est, ref, valid = stack_pose_pairs(pair)
    with jax.enable_x64(True):  # this thread only: `jsve frontend run` scores runs from several threads
        result = batched_ape(est, ref, valid, align=align)
        return float(np.asarray(result.errors.stats.rmse)[0]), int(valid.sum())


RECORDED_EVENTS = ("reset", "new_map", "merge", "loop")
"""The recorded run's events that `in_saved_frame` adds to a v3 run's metadata as `recorded_<event>`
counts (frames with the event)."""

SAVED_COLUMN = "in_saved"
"""The per-frame flag `in_saved_frame` adds: the frame's pose belongs to the saved trajectory when a
rule tracks the frame (jsve.core._batch.LogBatch.in_saved)."""


def largest_map_frames(
    posed: np.ndarray, map_id: np.ndarray, run_start: np.ndarray | None = None
) -> np.ndarray:
    """SaveTrajectoryEuRoC's choice of map where a log has no keyframe table (v1, v2, simulated): per run,
    the frames of the recorded map with the most posed frames since its last reset (posed frames stand
    in for keyframes; a reset detaches the earlier frames' keyframes from the map). Ties go to the map
    that comes first.

    Arguments:
        posed: [F] bool. map_id: [F] int. run_start: [F] bool, the frame starts a run, where several
            runs lie end to end (None: one run).
    Returns:
        [F] bool.
    """
    posed = np.asarray(posed, bool)
    map_id = np.asarray(map_id, np.int64)
    n = len(posed)
    run = np.zeros(n, np.int64) if run_start is None else np.cumsum(np.asarray(run_start, bool)) - 1
    prev_posed = np.concatenate([[False], posed[:-1]])
    prev_map = np.concatenate([map_id[:1], map_id[:-1]])
    prev_run = np.concatenate([[-1], run[:-1]])
    start = posed & (~prev_posed | (map_id != prev_map) | (run != prev_run))
    segment = np.cumsum(start) - 1  # recorded segments, numbered over all runs
    out = np.zeros(n, bool)
    if not posed.any():
        return out
    idx = np.flatnonzero(posed)
    seg, m, r = segment[idx], map_id[idx], run[idx]
    # The last segment of each (run, map): earlier ones were reset away.
    key = np.stack([r, m], axis=1)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    last = np.full(inverse.max() + 1, -1)
    np.maximum.at(last, inverse, seg)
    alive = seg == last[inverse]
    counts = np.bincount(seg[alive], minlength=segment.max() + 1)
    # Per run, the segment with most frames (first on ties: segments are numbered in time order).
    best = {}
    for s in np.unique(seg[alive]):
        run_of = int(r[np.argmax(seg == s)])
        if run_of not in best or counts[s] > counts[best[run_of]]:
            best[run_of] = s
    chosen = np.array([best.get(int(x), -2) for x in r])
    out[idx] = seg == chosen
    return out


def in_saved_frame(run: RunLog) -> RunLog:
    """The run as ORB-SLAM3's saved trajectory sees it (docs/state-machine.md, "Scoring a run"), with a
    `in_saved` column (0/1) and without the world_* and keyframe columns.

    A v3 log with the `orbslam3` trailer: vis_p and vis_q of each posed frame become its pose in the
    saved map's world frame (the saved trajectory's pose, exactly, for the frames ORB-SLAM3 saved; for
    another posed frame, its logged T_cr on its reference keyframe's final pose), vis_v rotated with
    them; in_saved marks the frames whose keyframe resolves into the saved map and whose entry (if any)
    was not marked lost. Any other log: poses in one world frame per recorded segment
    (jsve.io._world.in_one_world_frame) and in_saved from `largest_map_frames`.
    """
    from jsve.io._world import in_one_world_frame

    if SAVED_COLUMN in run.frames.columns:  # converted already (a study read back from Parquet)
        return run
    trailer = (run.trailers or {}).get(schema.ORBSLAM3_TRAILER)
    if trailer is not None:
        check_trailer(trailer, run.source)
    drop = [c for c in schema.KEYFRAME_COLUMNS if c in run.frames.columns]
    if trailer is None or not run.has_keyframes:
        out = in_one_world_frame(run)
        f = out.frames.drop(columns=drop)
        posed = np.isfinite(f[list(schema.VIS_POSITION)].to_numpy()).all(axis=1)
        f[SAVED_COLUMN] = largest_map_frames(posed, f["map_id"].to_numpy()).astype(np.int64)
        return RunLog(meta=out.meta, frames=f, source=out.source, trailers=out.trailers)
    f = run.frames
    n = len(f)
    saved = saved_map_id(trailer["maps"])
    kfs = _Keyframes(trailer["keyframes"], run.source)
    t_bc = _poses([trailer["t_bc"]])[0]
    ref = f["ref_kf"].to_numpy().copy()
    t_cr = np.concatenate(
        [f[list(schema.REL_QUATERNION)].to_numpy(), f[list(schema.REL_POSITION)].to_numpy()], 1
    )
    lost = np.zeros(n, bool)
    traj = trailer["trajectory"]
    rows = np.asarray(traj["row"], np.int64)
    entry = rows >= 0
    # The trailer's entries are the final ones (UpdateFrameIMU rescales them after the frame was logged).
    ref[rows[entry]] = np.asarray(traj["ref_kf"], np.int64)[entry]
    t_cr[rows[entry]] = _poses(traj["t_cr"])[entry]
    lost[rows[entry]] = np.asarray(traj["lost"], bool)[entry]
    posed = np.isfinite(f[list(schema.VIS_POSITION)].to_numpy()).all(axis=1)
    p = f[list(schema.VIS_POSITION)].to_numpy().copy()
    q = f[list(schema.VIS_QUATERNION)].to_numpy().copy()
    v = f[list(schema.VIS_VELOCITY)].to_numpy().copy()
    in_saved = np.zeros(n, bool)
    k = np.flatnonzero(posed & (ref >= 0))
    found, maps, t_rw = _keyframe_poses(kfs, ref[k])
    k, maps = k[found], maps[found]
    t_wb = _body_in_world(t_bc, t_cr[k], t_rw[found])
    correction = quat_mul(t_wb[:, :4], quat_conj(q[k], xp=np), xp=np)  # online -> saved rotation
    v[k] = quat_rotate(correction, v[k], xp=np)
    q[k], p[k] = t_wb[:, :4], t_wb[:, 4:]
    in_saved[k] = (maps == saved) & ~lost[k] if saved is not None else False
    out = f.drop(columns=drop + [c for c in schema.WORLD_COLUMNS if c in f.columns])
    out[list(schema.VIS_POSITION)] = np.where(posed[:, None], p, np.nan)
    out[list(schema.VIS_QUATERNION)] = np.where(posed[:, None], q, np.nan)
    out[list(schema.VIS_VELOCITY)] = np.where(posed[:, None], v, np.nan)
    out[SAVED_COLUMN] = in_saved.astype(np.int64)
    # The recorded run's events, per run (metadata: they reach every per-run table as columns).
    meta = {**run.meta, **{f"recorded_{k}": v for k, v in event_counts(run).items() if k in RECORDED_EVENTS}}
    return RunLog(meta=meta, frames=out, source=run.source, trailers=run.trailers)
