"""Dead-reckoning drift of the simulated IMU against the real EuRoC IMU, over 1, 2 and 5 s.

For each EuRoC sequence with a real imu0 stream in ../shared/data/euroc/imu (V1_01, MH_04), the
same procedure is applied to four streams over the same smooth ground-truth trajectory
(jsve.sim.load_euroc_trajectory):

    real         the recorded ADIS16448 stream
    simulated    jsve.sim.synthesize_imu with the default ImuNoise (datasheet noise and
                 random-walk biases plus the in-flight Gauss-Markov errors), three seeds
    datasheet    the same without the in-flight errors (ImuNoise.datasheet())
    ideal        no noise, no bias: what ORB-SLAM3's first-order preintegration at 200 Hz leaves

Each stream is preintegrated per frame as the simulator logs it (ORB-SLAM3's midpoint steps,
corrected with the biases of a 10 s trailing-window estimator: jsve.sim.frame_bias_estimate),
and from every second after the first 10 s the true state is propagated with the preintegration
alone (ORB-SLAM3's PredictStateIMU, the replay's IMU prediction) and compared with the ground-truth
position after 1, 2 and 5 s. Prints median, RMS and 90th percentile of the position error (m).

    python analysis/imu_drift.py [--euroc ../shared/data/euroc] [--markdown]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.sim import (
    ImuNoise,
    dead_reckoning_drift,
    frame_bias_estimate,
    frame_substeps,
    load_euroc_trajectory,
    preintegrate,
    read_imu_stream,
    synthesize_imu,
)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_EUROC = REPO.parent / "shared" / "data" / "euroc"
HORIZONS = (1.0, 2.0, 5.0)
SEQUENCES = {"V1_01": "V101", "MH_04": "MH04"}


def drift_table(euroc: Path, sequences=SEQUENCES, seeds=(0, 1, 2)) -> pd.DataFrame:
    rows = []
    for name, stem in sequences.items():
        imu_path = euroc / "imu" / f"{stem}.txt"
        if not imu_path.is_file():
            continue
        trajectory = load_euroc_trajectory(
            name, euroc / "groundtruth_left_cam", timestamps_dir=euroc / "timestamps"
        )
        streams = [("real", read_imu_stream(imu_path))]
        streams += [("simulated", synthesize_imu(trajectory, np.random.default_rng(s))) for s in seeds]
        streams += [
            ("datasheet", synthesize_imu(trajectory, np.random.default_rng(s), ImuNoise.datasheet()))
            for s in seeds
        ]
        streams += [("ideal", synthesize_imu(trajectory, None, noise=None))]
        errors: dict[str, dict[float, list]] = {}
        for kind, imu in streams:
            bg, ba = frame_bias_estimate(imu, trajectory)
            pre = preintegrate(frame_substeps(imu, trajectory.frame_ns), bg, ba)
            for horizon, e in dead_reckoning_drift(trajectory, pre, horizons_s=HORIZONS).items():
                errors.setdefault(kind, {}).setdefault(horizon, []).append(e)
        for kind, by_horizon in errors.items():
            for horizon, parts in by_horizon.items():
                e = np.concatenate(parts)
                rows.append(
                    {
                        "sequence": name,
                        "stream": kind,
                        "horizon_s": horizon,
                        "starts": len(e),
                        "median_m": float(np.median(e)),
                        "rms_m": float(np.sqrt(np.mean(e**2))),
                        "p90_m": float(np.percentile(e, 90)),
                    }
                )
    return pd.DataFrame(rows)


def flight_table(euroc: Path, n_procedural: int = 11, seed: int = 0) -> pd.DataFrame:
    """Duration, speed, acceleration and angular rate of the EuRoC ground truth (as the simulator
    loads it) beside the procedural flights (jsve.sim.make_recording's proc_00 ... under `seed`)."""
    from jsve.sim import EUROC_SEQUENCES, make_recording, procedural_sequences

    rows = []

    def describe(kind, name, traj):
        t = traj.seconds(traj.frame_ns)
        speed = np.linalg.norm(traj.velocity(t), axis=1)
        accel = np.linalg.norm(traj.acceleration(t), axis=1)
        rate = np.linalg.norm(traj.angular_velocity(t), axis=1)
        rows.append(
            {
                "kind": kind,
                "sequence": name,
                "duration_s": t[-1],
                "speed_mean": speed.mean(),
                "speed_p95": np.percentile(speed, 95),
                "accel_p95": np.percentile(accel, 95),
                "rate_mean": rate.mean(),
                "rate_p95": np.percentile(rate, 95),
            }
        )

    gt = euroc / "groundtruth_left_cam"
    for name in EUROC_SEQUENCES:
        if (gt / f"{EUROC_SEQUENCES[name]}_GT.txt").is_file():
            describe("EuRoC", name, load_euroc_trajectory(name, gt, timestamps_dir=euroc / "timestamps"))
    for spec in procedural_sequences(n_procedural):
        describe("procedural", spec.name, make_recording(spec, seed).trajectory)
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--euroc", type=Path, default=DEFAULT_EUROC, help="the shared EuRoC data folder")
    parser.add_argument("--markdown", action="store_true")
    parser.add_argument(
        "--flights",
        action="store_true",
        help="instead: motion statistics of EuRoC and of the procedural flights",
    )
    args = parser.parse_args(argv)
    if args.flights:
        table = flight_table(args.euroc)
        summary = table.drop(columns="sequence").groupby("kind").agg(["min", "median", "max"])
        with pd.option_context("display.width", 200):
            print(summary.round(2).T.to_string())
        return 0
    table = drift_table(args.euroc)
    if table.empty:
        print(f"no real IMU streams under {args.euroc / 'imu'}")
        return 1
    wide = table.pivot_table(index=["sequence", "stream"], columns="horizon_s", values=["median_m", "rms_m"])
    order = {"real": 0, "simulated": 1, "datasheet": 2, "ideal": 3}
    wide = wide.sort_index(key=lambda idx: idx.map(order) if idx.name == "stream" else idx)
    if args.markdown:
        print("| sequence | stream | median 1 s | median 2 s | median 5 s | RMS 1 s | RMS 2 s | RMS 5 s |")
        print("|---|---|---:|---:|---:|---:|---:|---:|")
        for (seq, kind), r in wide.iterrows():
            med = [r[("median_m", h)] for h in HORIZONS]
            rms = [r[("rms_m", h)] for h in HORIZONS]
            print(f"| {seq} | {kind} | " + " | ".join(f"{v:.3f}" for v in med + rms) + " |")
    else:
        with pd.option_context("display.width", 160):
            print(wide.round(3).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
