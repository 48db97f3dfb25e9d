"""One world frame per recorded map: undo the front-end's re-expressions of its map.

ORB-SLAM3 re-expresses a whole map in a new world frame (Map::ApplyScaledRotation: gravity direction
and scale) at IMU initialisation, at inertial BA1 / BA2 and at scale refinement, keeping the map's id.
The online pose of a frame (what a live system outputs, and what the hook logs) is in the world frame
of that moment, so the logged trajectory of one map jumps by metres at each re-expression while every
piece of it is right. A log that carries the world_* columns (jsve.io._schema.WORLD_COLUMNS: the
similarity W_k from the map's first world frame to frame k's) is re-expressed here in the world frame of
the last posed frame of each recorded segment (a run of posed frames in one map, as
jsve.core._replay.frame_data starts them), the frame the map ends in:

    S_k = W_L o W_k^-1:   s = s_L / s_k,   R = R_L R_k^T,   t = t_L - s R t_k      (x_L = s R x_k + t)

ApplyScaledRotation moves the camera centres by the similarity (KeyFrame poses are camera poses), while
the logged pose is the body's, T_wb = T_wc T_cb with the body offset unscaled. So a pose is moved as its
camera: with T_bc = (q_bc, t_bc) from the metadata `camera_in_body` (the identity without it),

    R_b' = R R_b,   p_b' = s R p_b + t + (s - 1) R R_b t_bc,   v' = s R v

(velocities scale with the map, ApplyScaledRotation's bScaledVel, as every re-expression of
LocalMapping passes it). Loop closures and merges correct a map non-rigidly and are not undone: they
are part of the trajectory a live system produces.
"""

from __future__ import annotations

import numpy as np

from jsve.core._geometry import quat_conj, quat_mul, quat_rotate
from jsve.io import _schema as schema
from jsve.io._schema import RunLog


def segment_last_frame(
    posed: np.ndarray, map_id: np.ndarray, run_start: np.ndarray | None = None
) -> np.ndarray:
    """For every frame, the index of the last posed frame of its recorded segment; -1 where not posed.

    A segment is a run of posed frames in one map: it starts at a posed frame after a frame without a
    pose, or where the map id changes (a reset keeps the id but leaves frames without a pose between).

    Arguments:
        posed: [F] bool, the frame has a pose.
        map_id: [F] int, the recorded map of each frame.
        run_start: [F] bool, the frame starts a run, where frames of several runs lie end to end (a
            segment never crosses a run); None: one run.
    """
    posed = np.asarray(posed, bool)
    map_id = np.asarray(map_id)
    n = len(posed)
    prev_posed = np.concatenate([[False], posed[:-1]])
    prev_map = np.concatenate([map_id[:1], map_id[:-1]])
    start = posed & (~prev_posed | (map_id != prev_map))
    if run_start is not None:
        start |= posed & np.asarray(run_start, bool)
    segment = np.cumsum(start) - 1
    last = np.full(n, -1, np.int64)
    if not posed.any():
        return last
    idx = np.flatnonzero(posed)
    # The last posed index of each segment: posed frames are sorted, so the maximum per segment.
    ends = np.zeros(segment[idx].max() + 1, np.int64)
    np.maximum.at(ends, segment[idx], idx)
    last[idx] = ends[segment[idx]]
    return last


def to_last_world_frame(
    p: np.ndarray,
    q: np.ndarray,
    v: np.ndarray,
    world_q: np.ndarray,
    world_t: np.ndarray,
    world_s: np.ndarray,
    last: np.ndarray,
    camera_in_body: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body poses and velocities moved from each frame's world frame to that of frame `last[k]`.

    Arguments:
        p, q, v: [F, 3], [F, 4] (wxyz), [F, 3]: body position (m), orientation, velocity (m/s), each in
            its frame's world frame.
        world_q, world_t, world_s: [F, 4], [F, 3], [F]: the similarity W_k of each frame's world frame.
        last: [F] the frame whose world frame each one goes to (segment_last_frame); -1 leaves it as is.
        camera_in_body: [7] T_bc as [qw, qx, qy, qz, tx, ty, tz], or [F, 7] one per frame (frames of
            several runs end to end); None: the camera is the body.

    Returns:
        (p', q', v') in the target world frames, float64.
    """
    p, q, v = (np.asarray(x, np.float64) for x in (p, q, v))
    world_q, world_t, world_s = (np.asarray(x, np.float64) for x in (world_q, world_t, world_s))
    target = np.where(last >= 0, last, np.arange(len(last)))
    s = world_s[target] / world_s
    r = quat_mul(world_q[target], quat_conj(world_q, xp=np), xp=np)  # R_L R_k^T
    t = world_t[target] - s[:, None] * quat_rotate(r, world_t, xp=np)
    t_bc = np.zeros(3) if camera_in_body is None else np.asarray(camera_in_body, np.float64)[..., 4:]
    q2 = quat_mul(r, q, xp=np)
    lever = (s - 1.0)[:, None] * quat_rotate(q2, np.broadcast_to(t_bc, p.shape), xp=np)
    p2 = s[:, None] * quat_rotate(r, p, xp=np) + t + lever
    v2 = s[:, None] * quat_rotate(r, v, xp=np)
    return p2, q2, v2


def in_one_world_frame(run: RunLog) -> RunLog:
    """The run with every pose of a recorded segment in the world frame its map ends in (see the module
    docstring); the world_* columns are dropped. A run without them is returned as it is."""
    if not run.has_world_frame:
        return run
    f = run.frames
    posed = np.isfinite(f[list(schema.VIS_POSITION)].to_numpy()).all(axis=1)
    last = segment_last_frame(posed, f["map_id"].to_numpy())
    t_bc = run.meta.get("camera_in_body")
    p2, q2, v2 = to_last_world_frame(
        f[list(schema.VIS_POSITION)].to_numpy(),
        f[list(schema.VIS_QUATERNION)].to_numpy(),
        f[list(schema.VIS_VELOCITY)].to_numpy(),
        f[list(schema.WORLD_QUATERNION)].to_numpy(),
        f[list(schema.WORLD_TRANSLATION)].to_numpy(),
        f[schema.WORLD_SCALE].to_numpy(),
        last,
        None if t_bc is None else np.asarray(t_bc),
    )
    out = f.drop(columns=list(schema.WORLD_COLUMNS))
    for names, values in ((schema.VIS_POSITION, p2), (schema.VIS_QUATERNION, q2), (schema.VIS_VELOCITY, v2)):
        # Frames without a pose keep NaN (the products above are NaN there too).
        out[list(names)] = np.where(posed[:, None], values, np.nan)
    return RunLog(meta=run.meta, frames=out, source=run.source)
