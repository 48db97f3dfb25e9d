"""IMU prediction: ORB-SLAM3's PredictStateIMU, the pose a frame gets from the previous state and the
preintegrated IMU measurements of the interval.

The one home of IMU prediction in jsve. The replay (jsve.core._replay) calls `imu_predict` on rows, the
fused search kernel (jsve.fitting._kernel) calls `imu_predict_columns` on the coordinate columns it keeps
its state in, and the simulator (jsve.sim._imu) calls `imu_predict` with `xp=numpy` in float64. The row
form is the column form stacked, so all three perform the same floating-point operations in the same order.
"""

from __future__ import annotations

from types import ModuleType

import jax.numpy as jnp
from jaxtyping import Float

from jsve.core._geometry import AnyArray, columns, quat_mul_columns, quat_rotate_columns


def imu_predict_columns(p, v, q, dt, dp, dv, dq, gravity) -> tuple[tuple, tuple, tuple]:
    """`imu_predict` on coordinate columns: p, v, dp, dv, gravity are (x, y, z) tuples of arrays, q and dq
    (w, x, y, z) tuples, dt an array; all broadcast against each other. Returns (p2, v2, q2) as tuples."""
    # ORB-SLAM3 v1.0 Tracking::PredictStateIMU (previous-frame branch): R2 = R1 dR,
    # v2 = v1 + g dt + R1 dV, p2 = p1 + v1 dt + 0.5 g dt^2 + R1 dP
    rp, rv = quat_rotate_columns(q, dp), quat_rotate_columns(q, dv)
    p2 = tuple(p[i] + v[i] * dt + 0.5 * gravity[i] * dt * dt + rp[i] for i in range(3))
    v2 = tuple(v[i] + gravity[i] * dt + rv[i] for i in range(3))
    return p2, v2, quat_mul_columns(q, dq)


def imu_predict(
    p: Float[AnyArray, "... 3"],
    v: Float[AnyArray, "... 3"],
    q: Float[AnyArray, "... 4"],
    dt: Float[AnyArray, ...],
    dp: Float[AnyArray, "... 3"],
    dv: Float[AnyArray, "... 3"],
    dq: Float[AnyArray, "... 4"],
    gravity: Float[AnyArray, "... 3"],
    *,
    xp: ModuleType = jnp,
) -> tuple[Float[AnyArray, "... 3"], Float[AnyArray, "... 3"], Float[AnyArray, "... 4"]]:
    """One step of ORB-SLAM3's PredictStateIMU from the previous body state.

    R2 = R1 dR;  v2 = v1 + g dt + R1 dV;  p2 = p1 + v1 dt + 0.5 g dt^2 + R1 dP.

    Arguments:
        p, v, q: previous position (m), velocity (m/s) and orientation (wxyz, body to world); world frame.
        dt: length of the interval, s.
        dp, dv, dq: preintegrated position (m), velocity (m/s) and rotation (wxyz) over the interval,
            in the previous body frame.
        gravity: m/s^2, world frame.
        xp: the array namespace (jax.numpy, or numpy for float64 host code; see jsve.core._geometry).
    Returns:
        (p2 m, v2 m/s, q2 wxyz) at the end of the interval, world frame.
    """
    p2, v2, q2 = imu_predict_columns(
        columns(p), columns(v), columns(q), dt, columns(dp), columns(dv), columns(dq), columns(gravity)
    )
    return xp.stack(p2, axis=-1), xp.stack(v2, axis=-1), xp.stack(q2, axis=-1)
