"""Benchmark: one rule setting over growing numbers of runs (replay + SE3 alignment + APE statistics).

    python benchmarks/bench_evaluate.py                       # 10 .. 10,000 runs x 3,600 frames
    python benchmarks/bench_evaluate.py --sizes 100,1000 --evo-runs 5

Prints, per size: wall time of the compiled evaluation (data already in memory; compile time shown
apart), frames per second, peak resident memory of the process, and the ratio against evo's APE loop
(PoseTrajectory3D + associate_trajectories + align + APE per run, timed on --evo-runs runs of the same
data and extrapolated linearly). Runs are synthetic but physically consistent (smooth flight, visual
estimate = truth + noise with dropouts, IMU preintegration exact from the truth), generated chunk by
chunk so that 36 M frames never sit in memory at once; generation time is not counted.
"""

from __future__ import annotations

import argparse
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

import jsve
from jsve.core import pad_runs, quat_conj, quat_exp, quat_mul, quat_rotate

G = np.array([0.0, 0.0, -9.81])
BA2_S = 15.0
"""Inertial BA2 done 15 s after the first frame (one map, every frame posed, monocular-inertial): as
jsve.io reads a v1 log (LocalMapping starts VIBA 2 once the map's inertial time exceeds 15 s)."""


def _rotate_inv(q, v):
    """R(q)^T v, in float64 numpy (jsve.core's quaternion algebra with xp=numpy)."""
    return quat_rotate(quat_conj(q, xp=np), v, xp=np)


def synthetic_chunk(n_runs: int, n_frames: int, seed: int, fps: float = 20.0) -> jsve.LogBatch:
    """Physically consistent synthetic runs as a float32 LogBatch (see module docstring)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / fps
    t = np.arange(n_frames) * dt
    # Smooth flight: sums of random sinusoids per axis (m), yaw rotating slowly.
    freq = rng.uniform(0.02, 0.2, (n_runs, 1, 3, 3))
    amp = rng.uniform(0.5, 3.0, (n_runs, 1, 3, 3))
    phase = rng.uniform(0, 2 * np.pi, (n_runs, 1, 3, 3))
    arg = 2 * np.pi * freq * t[None, :, None, None] + phase
    p = np.sum(amp * np.sin(arg), axis=-1)
    v = np.sum(amp * 2 * np.pi * freq * np.cos(arg), axis=-1)
    yaw = 0.1 * np.sin(0.05 * t)[None, :] + rng.uniform(-np.pi, np.pi, (n_runs, 1))
    q = quat_exp(np.stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw], -1), xp=np)
    # Exact preintegration from consecutive true states (inverse of PredictStateIMU).
    dq = np.zeros_like(q)
    dq[..., 0] = 1.0
    dq[:, 1:] = quat_mul(quat_conj(q[:, :-1], xp=np), q[:, 1:], xp=np)
    dv = np.zeros_like(p)
    dp = np.zeros_like(p)
    dv[:, 1:] = _rotate_inv(q[:, :-1], v[:, 1:] - v[:, :-1] - G * dt)
    dp[:, 1:] = _rotate_inv(q[:, :-1], p[:, 1:] - p[:, :-1] - v[:, :-1] * dt - 0.5 * G * dt * dt)
    imu_dt = np.full((n_runs, n_frames), dt)
    imu_dt[:, 0] = 0.0
    # Visibility: texture with dropouts; visual error grows when inliers are few.
    texture = np.clip(rng.normal(0.7, 0.25, (n_runs, n_frames)), 0, 1)
    n_inl = (texture * 300).astype(np.int32)
    noise = 0.02 + 0.5 * (n_inl < 30)[..., None]
    vis_p = p + rng.normal(size=p.shape) * noise
    f32 = np.float32
    return jsve.LogBatch(
        t=jnp.asarray(np.broadcast_to(t, (n_runs, n_frames)), f32), valid=jnp.ones((n_runs, n_frames), bool),
        state=jnp.full((n_runs, n_frames), 2, jnp.int8), imu_init=jnp.asarray(t[None] > 3.0).repeat(n_runs, 0),
        imu_ba2=jnp.asarray(t[None] >= BA2_S).repeat(n_runs, 0), map_id=jnp.zeros((n_runs, n_frames), jnp.int32),
        has_pose=jnp.ones((n_runs, n_frames), bool), in_saved=jnp.ones((n_runs, n_frames), bool),
        n_extracted=jnp.full((n_runs, n_frames), 1000, jnp.int32), n_inliers=jnp.asarray(n_inl),
        n_frustum=jnp.asarray(n_inl + 60), bins=jnp.full((n_runs, n_frames, 64), 15, jnp.uint16),
        vis_p=jnp.asarray(vis_p, f32), vis_q=jnp.asarray(q, f32), vis_v=jnp.asarray(v, f32),
        imu_dt=jnp.asarray(imu_dt, f32), imu_dp=jnp.asarray(dp, f32), imu_dv=jnp.asarray(dv, f32),
        imu_dq=jnp.asarray(dq, f32), gt_p=jnp.asarray(p, f32), gt_q=jnp.asarray(q, f32),
        gt_valid=jnp.ones((n_runs, n_frames), bool), fps=jnp.full((n_runs,), fps, f32),
        gravity=jnp.asarray(np.broadcast_to(G, (n_runs, 3)), f32), imu_init_delay=jnp.full((n_runs,), 3.0, f32),
        ba2_delay=jnp.full((n_runs,), BA2_S, f32), n_features=jnp.full((n_runs,), 1000.0, f32),
        stereo=jnp.zeros((n_runs,), bool), run_index=jnp.arange(n_runs, dtype=jnp.int32),
    )  # fmt: skip


def time_jsve(n_runs: int, n_frames: int, chunk: int, rule) -> tuple[float, float]:
    """(seconds of compiled evaluation over all chunks, first-call compile+run seconds)."""
    total = 0.0
    compile_s = 0.0
    for i, start in enumerate(range(0, n_runs, chunk)):
        size = min(chunk, n_runs - start)
        batch = pad_runs(synthetic_chunk(size, n_frames, seed=start), chunk)
        features = jax.block_until_ready(jsve.batch_features(batch))
        if i == 0:
            t0 = time.perf_counter()
            jax.block_until_ready(jsve.evaluate_batch(batch, rule, features))
            compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        out = jsve.evaluate_batch(batch, rule, features)
        jax.block_until_ready(out)
        total += time.perf_counter() - t0
    return total, compile_s


def time_evo(n_runs: int, n_frames: int) -> float:
    """Seconds per run of evo's APE pipeline on runs of the same synthetic data."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    batch = synthetic_chunk(n_runs, n_frames, seed=123)
    stamps = np.asarray(batch.t, np.float64)
    per_run = []
    for r in range(n_runs):
        t0 = time.perf_counter()
        ref = PoseTrajectory3D(np.asarray(batch.gt_p[r], float), np.asarray(batch.gt_q[r], float), stamps[r])
        est = PoseTrajectory3D(
            np.asarray(batch.vis_p[r], float), np.asarray(batch.vis_q[r], float), stamps[r]
        )
        ref, est = sync.associate_trajectories(ref, est)
        est.align(ref, correct_scale=False)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        ape.get_all_statistics()
        per_run.append(time.perf_counter() - t0)
    return float(np.median(per_run))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="10,100,1000,10000", help="numbers of runs")
    parser.add_argument("--frames", type=int, default=3600)
    parser.add_argument("--chunk", type=int, default=1000, help="runs per compiled call")
    parser.add_argument("--evo-runs", type=int, default=10)
    parser.add_argument("--rule", default="sve-option2")
    args = parser.parse_args()
    rule = jsve.preset(args.rule)
    evo_s = time_evo(args.evo_runs, args.frames)
    print(f"device: {jax.devices()[0]}  jax {jax.__version__}  rule {args.rule}  frames/run {args.frames}")
    print(f"evo APE loop: {evo_s * 1e3:.1f} ms per {args.frames}-pose run (median of {args.evo_runs})")
    print(f"{'runs':>7} {'frames':>12} {'jsve s':>9} {'Mframes/s':>10} {'compile s':>10} {'peak RSS GB':>12} "
          f"{'evo s (est)':>12} {'speed-up':>9}")  # fmt: skip
    for n_runs in (int(s) for s in args.sizes.split(",")):
        chunk = min(args.chunk, n_runs)
        seconds, compile_s = time_jsve(n_runs, args.frames, chunk, rule)
        frames = n_runs * args.frames
        peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        evo_total = evo_s * n_runs
        print(f"{n_runs:>7} {frames:>12,} {seconds:>9.3f} {frames / seconds / 1e6:>10.2f} {compile_s:>10.2f} "
              f"{peak_gb:>12.2f} {evo_total:>12.1f} {evo_total / seconds:>9.0f}x", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
