"""Throughput of the batched search (jsve.fitting.search) in frame-settings per second.

    python benchmarks/bench_search.py                      # all cores (one XLA CPU device per core)
    python benchmarks/bench_search.py --devices 1          # one device
    python benchmarks/bench_search.py --settings 4096 --output bench_search.json
    python benchmarks/bench_search.py --lanes 8192,131072   # settings x runs per kernel call, each timed

Simulates a study (procedural flights x the seed's settings, jsve.sim.simulate_study), prepares it once, and
times `jsve.fitting.search` on Sobol designs of both rule families (inlier thresholds; SVE combination and
thresholds). A frame-setting is one frame replayed under one setting, alignment statistics included.
Reports wall-clock and per-CPU-second rates (the machine may be shared), after one warm-up call per
shape (compilation is timed separately). For reference it also times the generic path,
jsve.core.run_losses (replay + trajectory alignment per run), vmapped over settings.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--devices", type=int, default=os.cpu_count(), help="XLA CPU devices (default: cores)"
    )
    parser.add_argument("--sequences", type=int, default=2)
    parser.add_argument("--runs", type=int, default=1, help="runs per sequence and setting")
    parser.add_argument("--duration", type=float, default=60.0, help="flight length, s")
    parser.add_argument("--settings", type=int, default=2048, help="settings per family")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--lanes",
        help="comma-separated settings x runs per kernel call to time in turn (JSVE_LANES_PER_CALL; "
        "default: jsve's own for the platform)",
    )
    parser.add_argument("--output", help="write the results as JSON here")
    args = parser.parse_args(argv)
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}"
    ).strip()

    import jax
    import numpy as np

    from jsve.fitting import FitData, design, inlier_space, sve_space
    from jsve.fitting._search import lanes_per_call
    from jsve.sim import FlightProfile, SimConfig, simulate_study

    t0 = time.perf_counter()
    runs = simulate_study(
        procedural=args.sequences,
        runs=args.runs,
        disturbances="seed",
        seed=0,
        config=SimConfig(flight=FlightProfile(duration_s=(args.duration, args.duration))),
    )
    data = FitData.from_runs(runs)
    frames = data.n_frames
    print(
        f"{len(runs)} runs, {frames} frames (simulated and prepared in {time.perf_counter() - t0:.1f} s); "
        f"{len(jax.local_devices())} XLA {jax.default_backend()} device(s), {os.cpu_count()} cores",
        flush=True,
    )
    results = {
        "runs": len(runs),
        "frames": frames,
        "devices": len(jax.local_devices()),
        "backend": jax.default_backend(),
        "cores": os.cpu_count(),
        "families": {},
    }
    lanes = [int(n) for n in args.lanes.split(",")] if args.lanes else [None]
    for space in (inlier_space(), sve_space()):
        values = np.asarray(space.values_from_unit(design("sobol", args.settings, space.dim, seed=1)))
        for n_lanes in lanes:
            if n_lanes is not None:
                os.environ["JSVE_LANES_PER_CALL"] = str(n_lanes)
            row = time_search(data, space, values, args.repeats)
            row["lanes"] = lanes_per_call()
            results["families"].setdefault(space.kind, []).append(row)
            print(
                f"{space.kind:8s} {args.settings} settings x {frames} frames, {row['lanes']} lanes a call: "
                f"{row['wall_s']:.2f} s wall, {row['cpu_s']:.2f} s CPU -> {row['per_s']:.3g} "
                f"frame-settings/s ({row['per_cpu_s']:.3g} per CPU-second); first call "
                f"{row['first_call_s']:.1f} s",
                flush=True,
            )
        generic = time_generic(data, space, values)
        results["families"][space.kind][-1]["generic_per_s"] = generic
        print(f"{space.kind:8s} generic replay + alignment path: {generic:.3g} frame-settings/s", flush=True)
    if args.output:
        with open(args.output, "w") as f:
            json.dump(results, f, indent=2)
    return 0


def time_search(data, space, values, repeats: int) -> dict:
    """Wall and CPU seconds of `search` over every run, best of `repeats` after a first (compiling) call."""
    from jsve.fitting import search

    def once() -> None:
        search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=False)

    t = time.perf_counter()
    once()
    first = time.perf_counter() - t
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        once()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    wall, cpu = min(walls), min(cpus)
    work = len(values) * data.n_frames
    return {
        "settings": len(values),
        "frame_settings": work,
        "first_call_s": first,
        "wall_s": wall,
        "cpu_s": cpu,
        "per_s": work / wall,
        "per_cpu_s": work / cpu,
    }


def time_generic(data, space, values, few: int = 16) -> float:
    """Frame-settings per second of the generic path (replay + alignment per run, jsve.core.run_losses)
    vmapped over a few settings on the first part."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jsve.core import run_losses

    rules = space.rule(jnp.asarray(values[:few], jnp.float32))
    fn = jax.jit(jax.vmap(lambda r, b=data.batches[0], f=data.features[0]: run_losses(b, r, f).loss))
    jax.block_until_ready(fn(rules))
    t = time.perf_counter()
    jax.block_until_ready(fn(rules))
    return few * float(np.sum(np.asarray(data.batches[0].valid))) / (time.perf_counter() - t)


if __name__ == "__main__":
    sys.exit(main())
