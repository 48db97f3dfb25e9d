"""Micro-benchmark: batched JAX trajectory error (alignment + APE statistics) against evo's per-run loop.

    python benchmarks/bench_ape.py                                  # N = 10, 100, 1000 runs x 3,600 poses
    python benchmarks/bench_ape.py --sizes 10,100 --evo-runs 20 --align sim3

JAX: `jsve.batched_run_error` (jit-compiled, vmapped over runs; one segment per run, full ground truth), in
float32 and float64, timed after compilation (compile time printed apart; median of --repeats calls).
evo: for each of --evo-runs runs, PoseTrajectory3D for estimate and reference, `align` (Umeyama; with scale
for sim3), `metrics.APE(translation_part)` and all statistics; the time per run is extrapolated linearly.
Prints milliseconds per run and evo's time per run over JAX's. Runs are synthetic: a smooth reference
flight and an estimate that is a noisy similarity transform of it (generation time is not counted).
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)  # float64 is benchmarked too; float32 inputs stay float32

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from evo.core import metrics  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

import jsve  # noqa: E402


def synthetic_runs(n_runs: int, n_frames: int, seed: int = 0):
    """Reference positions/quaternions and a noisy similarity-transformed estimate per run (float64 numpy)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / 20.0  # 20 fps
    freq = rng.uniform(0.01, 0.1, (n_runs, 1, 3))
    amp = rng.uniform(1.0, 10.0, (n_runs, 1, 3))
    phase = rng.uniform(0, 2 * np.pi, (n_runs, 1, 3))
    ref_p = amp * np.sin(2 * np.pi * freq * t[None, :, None] + phase)
    yaw = 0.05 * t[None, :] + rng.uniform(0, 2 * np.pi, (n_runs, 1))
    ref_q = np.stack([np.cos(yaw / 2), np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2)], axis=-1)
    angle = rng.uniform(0, 2 * np.pi, n_runs)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.zeros((n_runs, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    scale = rng.uniform(0.5, 2.0, (n_runs, 1, 1))
    est_p = scale * np.einsum("rij,rtj->rti", rot, ref_p) + rng.normal(size=(n_runs, 1, 3))
    est_p += rng.normal(scale=0.1, size=est_p.shape)
    rot_q = np.stack([np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)], axis=-1)[:, None, :]
    # est_q = rot_q * ref_q (both yaw-only, so the product is the yaw sum)
    w1, z1 = rot_q[..., 0], rot_q[..., 3]
    w2, z2 = ref_q[..., 0], ref_q[..., 3]
    est_q = np.stack([w1 * w2 - z1 * z2, 0 * w2, 0 * w2, w1 * z2 + z1 * w2], axis=-1)
    return est_p, est_q, ref_p, ref_q


def batched_args(est_p, est_q, ref_p, ref_q, dtype) -> tuple:
    """Positional arguments of batched_run_error: one segment per run, every frame estimated and valid."""
    n_runs, n_frames = est_p.shape[:2]
    ones = jnp.ones((n_runs, n_frames), bool)
    segment = jnp.zeros((n_runs, n_frames), jnp.int32)
    est_p, est_q, ref_p, ref_q = (jnp.asarray(x, dtype) for x in (est_p, est_q, ref_p, ref_q))
    return est_p, est_q, ones, segment, ref_p, ref_q, ones, ones


def time_jax(est_p, est_q, ref_p, ref_q, dtype, align: str, repeats: int) -> tuple[float, float]:
    """(compile seconds, median seconds per batched call) of batched_run_error on device-resident arrays."""
    args = batched_args(est_p, est_q, ref_p, ref_q, dtype)
    start = time.perf_counter()
    out = jax.block_until_ready(jsve.batched_run_error(*args, align=align))
    compile_s = time.perf_counter() - start
    if out.stats.rmse.dtype != dtype:
        raise RuntimeError(f"expected {dtype} statistics, got {out.stats.rmse.dtype}")
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(jsve.batched_run_error(*args, align=align))
        times.append(time.perf_counter() - start)
    return compile_s, float(np.median(times))


def time_evo(est_p, est_q, ref_p, ref_q, align: str) -> tuple[float, np.ndarray]:
    """(seconds per run, rmse per run) of evo's loop: trajectories, Umeyama alignment, APE statistics."""
    stamps = np.arange(est_p.shape[1]) / 20.0
    rmse = []
    start = time.perf_counter()
    for i in range(len(est_p)):
        ref = PoseTrajectory3D(positions_xyz=ref_p[i], orientations_quat_wxyz=ref_q[i], timestamps=stamps)
        est = PoseTrajectory3D(positions_xyz=est_p[i], orientations_quat_wxyz=est_q[i], timestamps=stamps)
        est.align(ref, correct_scale=align == "sim3")
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        rmse.append(ape.get_all_statistics()["rmse"])
    return (time.perf_counter() - start) / len(est_p), np.array(rmse)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="10,100,1000", help="numbers of runs for JAX (comma-separated)")
    parser.add_argument("--frames", type=int, default=3600, help="poses per run")
    parser.add_argument("--evo-runs", type=int, default=30, help="runs timed with evo (extrapolated per run)")
    parser.add_argument("--align", choices=("se3", "sim3"), default="se3")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per size (median reported)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]

    platform = jax.devices()[0].platform
    load = os.getloadavg()[0]
    print(f"jax {jax.__version__} on {platform}, {os.cpu_count()} CPUs, load average {load:.1f}; "
          f"{args.frames} poses per run, align={args.align}")  # fmt: skip
    evo_data = synthetic_runs(args.evo_runs, args.frames, seed=1)
    evo_per_run, evo_rmse = time_evo(*evo_data, args.align)
    jsve_rmse = jsve.batched_run_error(*batched_args(*evo_data, jnp.float64), align=args.align).stats.rmse
    max_diff = float(np.max(np.abs(np.asarray(jsve_rmse) - evo_rmse)))
    print(f"evo: {evo_per_run * 1e3:.2f} ms per run ({args.evo_runs} runs timed); "
          f"float64 rmse max |jsve - evo| = {max_diff:.1e} m")  # fmt: skip
    header = ("runs", "dtype", "compile s", "call ms", "ms/run", "Mframes/s", "evo/jax")
    print("".join(f"{h:>11}" for h in header))
    for n_runs in sizes:
        data = synthetic_runs(n_runs, args.frames, seed=2)
        for dtype in (jnp.float32, jnp.float64):
            compile_s, call_s = time_jax(*data, dtype=dtype, align=args.align, repeats=args.repeats)
            per_run = call_s / n_runs
            row = (f"{n_runs}", jnp.dtype(dtype).name, f"{compile_s:.2f}", f"{call_s * 1e3:.1f}",
                   f"{per_run * 1e3:.3f}", f"{n_runs * args.frames / call_s / 1e6:.1f}",
                   f"{evo_per_run / per_run:.0f}")  # fmt: skip
            print("".join(f"{c:>11}" for c in row))


if __name__ == "__main__":
    main()
