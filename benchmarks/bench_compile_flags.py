"""XLA CPU compile time of a fixed set of jsve programs under sets of XLA_FLAGS, against the first set.

    python benchmarks/bench_compile_flags.py            # the suite's first three flags, then all six
    python benchmarks/bench_compile_flags.py --repeats 5 --flags "" --flags "--xla_cpu_ftz=true"

Each measurement is a fresh process (XLA reads XLA_FLAGS once, when its backend starts) that compiles the
same programs: the search kernel on four simulated runs (jsve.sim) for both rule families, both switch
models and two numbers of settings; batched_rpe and batched_ape for three relations; and 40 eager
operations of distinct shapes (float64). It reports jax.monitoring's backend_compile seconds and the
process's wall time, one line per set and repeat (sets interleaved, so that a machine that slows down
for a while slows every set alike), then each set's median and its ratio to the first set's median.
The test suite's flags are tests/conftest.py's SUITE_XLA_FLAGS.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

SUITE = (
    "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
    "--xla_cpu_multi_thread_eigen=false"
)
DEFAULT_SETS = (
    SUITE,
    SUITE
    + " --xla_cpu_parallel_codegen_split_count=1 --xla_cpu_copy_insertion_use_region_analysis=false"
    + " --xla_cpu_enable_concurrency_optimized_scheduler=false",
)


def compile_programs() -> dict:
    """Compile the benchmark's programs in this process: backend_compile seconds, programs, wall s."""
    import time

    import jax
    import jax.monitoring as monitoring
    import jax.numpy as jnp
    import numpy as np

    totals = {"compile_s": 0.0, "programs": 0}

    def on_duration(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            totals["compile_s"] += duration
            totals["programs"] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    from jsve.core._objective import ObjectiveConfig
    from jsve.core._pose_error_batch import batched_ape, batched_rpe
    from jsve.core._replay import batch_features
    from jsve.fitting._designs import sobol
    from jsve.fitting._kernel import prepare, search_chunk
    from jsve.fitting._space import inlier_space, sve_space
    from jsve.io._batching import from_runs
    from jsve.sim._config import SimConfig
    from jsve.sim._simulate import simulate_run
    from jsve.sim._trajectory import FlightProfile

    start = time.perf_counter()
    config = SimConfig(flight=FlightProfile(duration_s=(15.0, 15.0)))
    runs = [simulate_run("proc_00", "occlusion", 300.0, run=k, config=config) for k in range(4)]
    batch = from_runs(runs, dtype=jnp.float32).batch
    sb = prepare(batch, batch_features(batch))
    for switch_model in ("orbslam3", "imu-coast"):
        for space in (sve_space(), inlier_space()):
            for n in (8, 24):
                values = jnp.asarray(space.values_from_unit(sobol(n, space.dim, seed=4)), jnp.float32)
                result = search_chunk(sb, space.rule(values), ObjectiveConfig(switch_model=switch_model))
                jax.block_until_ready(result.loss)
    rng = np.random.default_rng(0)

    def poses(n: int) -> np.ndarray:
        p = np.tile(np.eye(4), (2, n, 1, 1))
        p[..., :3, 3] = np.cumsum(rng.normal(size=(2, n, 3)), axis=1)
        return p

    est, ref, valid = poses(200), poses(200), np.ones((2, 200), bool)
    for relation in ("translation", "angle_deg", "full"):
        for delta, unit in ((1, "f"), (3.0, "m")):
            rpe = batched_rpe(est, ref, valid, delta=delta, unit=unit, relation=relation, align="se3")
            jax.block_until_ready(jax.tree.leaves(rpe))
        jax.block_until_ready(jax.tree.leaves(batched_ape(est, ref, valid, relation=relation, align="sim3")))
    x = jnp.linspace(0.0, 1.0, 1000)
    for k in range(40):  # eager operations, one small program per shape
        x = jnp.sin(x[: 1000 - k]) * 2.0 + jnp.cumsum(x[: 1000 - k])
    jax.block_until_ready(x)
    return {**totals, "wall_s": time.perf_counter() - start}


def measure(flags: str) -> dict:
    """compile_programs() in a fresh process under XLA_FLAGS=flags (float64, no compilation cache)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(XLA_FLAGS=flags, JAX_ENABLE_X64="1")
    code = "import json, bench_compile_flags as b; print(json.dumps(b.compile_programs()))"
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True,
        cwd=os.path.dirname(os.path.abspath(__file__)),
    )  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"XLA_FLAGS={flags!r}: the measuring process failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--flags", action="append", help="a set of XLA_FLAGS (repeat; the first is the baseline)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="fresh processes per set (default 3)")
    args = parser.parse_args(argv)
    sets = args.flags or list(DEFAULT_SETS)
    seen: dict[int, list[dict]] = {i: [] for i in range(len(sets))}
    for rep in range(args.repeats):
        for i, flags in enumerate(sets):
            r = measure(flags)
            seen[i].append(r)
            print(f"repeat {rep + 1} set {i}: compile {r['compile_s']:.2f} s ({r['programs']} programs), "
                  f"wall {r['wall_s']:.2f} s", flush=True)  # fmt: skip
    base = statistics.median(r["compile_s"] for r in seen[0])
    for i, flags in enumerate(sets):
        median = statistics.median(r["compile_s"] for r in seen[i])
        wall = statistics.median(r["wall_s"] for r in seen[i])
        print(f"set {i}: median compile {median:.2f} s (x{median / base:.2f} of set 0), wall {wall:.2f} s: "
              f"XLA_FLAGS={flags!r}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
