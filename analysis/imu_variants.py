"""Copies of a rendered EuRoC sequence that differ only in their IMU stream: which IMU agrees with the images?

ORB-SLAM3 (IMU_MONOCULAR) on the full rendered V1_01 with the real V1_01 IMU stream scores 15-16 cm ATE
(SE3) with its scale 7 % short, where the literature reports a few centimetres on the real sequence. The
images are rendered along the ground truth, while the real stream measured the real flight; whatever the
ground truth gets wrong (mostly attitude, docs/simulator.md "Drift against the real stream") becomes a
disagreement between the images and the IMU that the real footage never had. This script isolates it:
each variant keeps the rendered images and ground truth (symbolic links) and replaces mav0/imu0:

    real-debiased    the real stream minus EuRoC's own bias estimate for V1_01 (a constant bias is not it)
    in-flight        jsve.sim.synthesize_imu with the default ImuNoise (datasheet noise and bias walk plus
                     the correlated errors fitted to the real stream's drift against the ground truth)
    datasheet-zero   the datasheet noise and bias walk only, starting from zero bias: consistent with the
                     images up to the sensor's own noise

Each variant's manifest names the sequence `<SEQ>-imu-<variant>` so that `jsve frontend run` can run them
into one log folder. Then score ORB-SLAM3's own trajectory against the dataset's ground truth:

    python analysis/imu_variants.py rendered/V1_01 --ground-truth ../shared/data/euroc/groundtruth_left_cam \\
        --timestamps ../shared/data/euroc/timestamps -o variants
    jsve frontend run BUILD variants/* --vocabulary voc.txt --settings EuRoC.yaml --runs 2 -o logs
    jsve ape rendered/V1_01/mav0/state_groundtruth_estimate0/data.csv \\
        logs/V101-imu-*/none-0/run_*.orbslam3-euroc.txt --format euroc --align se3

`jsve render --imu-noise datasheet` renders the datasheet stream directly (with a random initial bias).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np

from jsve.sim import ImuNoise, load_euroc_trajectory, read_imu_stream, synthesize_imu

EUROC_V101_BIAS = np.array([-0.002229, 0.020700, 0.076350, -0.012492, 0.547666, 0.069073])
"""EuRoC's own estimate of V1_01's IMU biases (state_groundtruth_estimate0, first row): gyro in rad/s,
then accelerometer in m/s^2."""
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)


def write_imu(path: Path, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
    """A EuRoC imu0 CSV (stamps as int64 ns, values to 17 significant digits)."""
    values = np.concatenate([gyro, accel], axis=1)
    rows = [f"{int(t)}," + ",".join(f"{v:.17g}" for v in row) for t, row in zip(t_ns, values, strict=True)]
    path.write_text("\n".join([IMU_HEADER, *rows]) + "\n")


def make_variant(rendered: Path, out: Path, name: str, t_ns, gyro, accel) -> Path:
    """`out/<name>`: the rendered images and ground truth linked, imu0 replaced, the manifest renamed."""
    manifest = json.loads((rendered / "jsve_render.json").read_text())
    folder = out / name
    if folder.exists():
        shutil.rmtree(folder)
    (folder / "mav0" / "imu0").mkdir(parents=True)
    for part in ("cam0", "state_groundtruth_estimate0"):
        os.symlink((rendered / "mav0" / part).resolve(), folder / "mav0" / part)
    shutil.copy(rendered / "mav0" / "imu0" / "sensor.yaml", folder / "mav0" / "imu0" / "sensor.yaml")
    write_imu(folder / "mav0" / "imu0" / "data.csv", t_ns, gyro, accel)
    sequence = manifest.get("sequence") or Path(manifest["trajectory"]).stem.removesuffix("_GT")
    manifest |= {"sequence": f"{sequence}-imu-{name}", "imu": f"analysis/imu_variants.py {name}"}
    (folder / "jsve_render.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rendered", type=Path, help="a `jsve render` dataset rendered with the real V1_01 --imu")
    ap.add_argument("--ground-truth", type=Path, required=True, help="folder of ORB-SLAM3's <SEQ>_GT.txt")
    ap.add_argument("--timestamps", type=Path, required=True, help="folder of ORB-SLAM3's <SEQ>.txt stamps")
    ap.add_argument("--sequence", default="V1_01", help="EuRoC sequence the dataset was rendered along")
    ap.add_argument("--seed", type=int, default=1, help="seed of the synthesised streams")
    ap.add_argument("-o", "--output", type=Path, required=True, help="folder to write the variants into")
    args = ap.parse_args()

    args.output.mkdir(parents=True, exist_ok=True)
    real = read_imu_stream(args.rendered / "mav0" / "imu0" / "data.csv")
    written = [make_variant(args.rendered, args.output, "real-debiased", real.t_ns,
                            real.gyro - EUROC_V101_BIAS[:3], real.accel - EUROC_V101_BIAS[3:])]  # fmt: skip
    trajectory = load_euroc_trajectory(args.sequence, args.ground_truth, timestamps_dir=args.timestamps)
    zero_bias = dataclasses.replace(ImuNoise.datasheet(), gyro_bias0=0.0, accel_bias0=0.0)
    for name, noise in (("in-flight", ImuNoise()), ("datasheet-zero", zero_bias)):
        imu = synthesize_imu(trajectory, np.random.default_rng(args.seed), noise)
        written.append(make_variant(args.rendered, args.output, name, imu.t_ns, imu.gyro, imu.accel))
    for folder in written:
        print(folder)


if __name__ == "__main__":
    main()
