"""A parameter sweep: the objective of every setting of a design (TOML config), one batched search.

    python sweeps/threshold_sweep.py sweeps/threshold_sweep.toml

Writes OUTPUT.csv / OUTPUT.parquet (one row per setting: its parameters, weighted objective, failure
rate, coverage, the weighted shares of runs out of the logs' support and excluded) and OUTPUT.npz (the
per-run matrices, runs in the order of OUTPUT.runs.csv), each atomically (`<name>.partial`, then a
rename), so a killed sweep leaves no half-written output. Uses jsve's public names (and jsve.io's atomic
writers); the config format is in sweeps/threshold_sweep.toml.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import tomllib


def load_runs(spec: dict, seed: int):
    if "logs" in spec:
        from jsve.io import read_logs, read_parquet

        source = spec["logs"]
        return read_parquet(source) if str(source).endswith(".parquet") else read_logs(source).runs
    from jsve.sim import FlightProfile, SimConfig, simulate_study

    sim = spec.get("simulate", {})
    duration = tuple(sim.get("duration_s", (60.0, 60.0)))
    return simulate_study(
        procedural=int(sim.get("sequences", 2)),
        runs=int(sim.get("runs", 2)),
        disturbances=sim.get("disturbances", "seed"),
        seed=seed,
        config=SimConfig(flight=FlightProfile(duration_s=duration)),
        progress=True,
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="TOML file (see sweeps/threshold_sweep.toml)")
    args = parser.parse_args(argv)
    config = tomllib.loads(Path(args.config).read_text())

    from jsve.cli import use_all_cores

    use_all_cores()
    import numpy as np
    import pandas as pd

    from jsve.core import ObjectiveConfig
    from jsve.evaluation import group_weights
    from jsve.fitting import FitData, design, grid_design, search, space_from_dict
    from jsve.io import atomic_path, write_table

    seed = int(config.get("seed", 0))
    objective = dict(config.get("objective", {}))
    balance_by = objective.pop("balance_by", ["sequence", "disturbance", "level"])
    data = FitData.from_runs(load_runs(config.get("data", {}), seed), ObjectiveConfig(**objective))
    space = space_from_dict(config["space"])
    spec = config.get("design", {"kind": "sobol", "n": 1024})
    if spec["kind"] == "grid":
        unit = grid_design(spec["levels"])
    else:
        unit = design(spec["kind"], int(spec["n"]), space.dim, seed=seed)
    values = np.asarray(space.values_from_unit(unit))
    result = search(data.parts, space, values, data.config, run_counts=data.run_counts, progress=True)
    w = group_weights(data.meta, [c for c in balance_by if c in data.meta.columns])
    table = pd.DataFrame(values, columns=list(space.names))
    table["objective_m"] = result.objective(w)
    table["failure_rate"] = result.failure_rate(w)
    table["coverage"] = result.coverage_mean(w)
    table["unsupported"] = result.unsupported_rate(w)
    table["excluded"] = result.excluded_share(w)
    out = Path(config.get("output", "sweep-results/sweep"))
    write_table(table, out.with_suffix(".csv"))
    write_table(table, out.with_suffix(".parquet"))
    write_table(data.meta, out.with_suffix(".runs.csv"))
    with atomic_path(out.with_suffix(".npz")) as partial, open(partial, "wb") as f:
        np.savez_compressed(
            f,
            values=values,
            loss=result.loss,
            failed=result.failed,
            rmse=result.rmse,
            coverage=result.coverage,
            unsupported=result.unsupported,
            included=result.included,
        )
    best = table.sort_values("objective_m").iloc[0]
    print(
        json.dumps({"settings": len(table), "runs": data.n_runs, "best": best.to_dict(), "output": str(out)})
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
