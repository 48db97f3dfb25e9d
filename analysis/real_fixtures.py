"""Copy chosen real logs of `jsve frontend run` into a test-fixture folder, compressed: each log, its
ORB-SLAM3 saved trajectory (EuRoC CSV) where ORB-SLAM3 saved one, and its sequence's ground truth at the
log's frame stamps (a few kB instead of the dataset's 200 Hz file).

    python analysis/real_fixtures.py LOGDIR OUT NAME=RELATIVE_LOG[:DATASET] ...

NAME is the fixture's name (files NAME.csv.gz, NAME.orbslam3-euroc.txt.gz, NAME.groundtruth.csv.gz);
RELATIVE_LOG a log under LOGDIR without `.csv`; DATASET the EuRoC dataset folder whose
mav0/state_groundtruth_estimate0/data.csv is the ground truth.
"""

from __future__ import annotations

import gzip
import shutil
import sys
from pathlib import Path

import numpy as np

import jsve


def _gzip(src: Path, dst: Path) -> None:
    with open(src, "rb") as a, gzip.GzipFile(dst, "wb", compresslevel=9, mtime=0) as b:
        shutil.copyfileobj(a, b)


def ground_truth_at_frames(gt: Path, log: Path) -> str:
    """The ground truth's header and, for each of the log's frame stamps, the rows at and before it (the
    pair around a stamp between rows: what association and interpolation read), stamp, position and
    orientation only (the first 8 columns of EuRoC's file)."""
    lines = [line for line in gt.read_text().splitlines() if line]
    stamps = np.array([int(line.split(",", 1)[0]) for line in lines[1:]], np.int64)
    frames = jsve.read_log(log).frames["t_ns"].to_numpy(np.int64)
    after = np.searchsorted(stamps, frames)
    keep = np.unique(np.clip(np.concatenate([after - 1, after]), 0, len(stamps) - 1))
    rows = [lines[1 + k] for k in keep]
    return "\n".join(",".join(line.split(",")[:8]) for line in [lines[0], *rows]) + "\n"


def main(argv: list[str]) -> int:
    logdir, out, specs = Path(argv[0]), Path(argv[1]), argv[2:]
    out.mkdir(parents=True, exist_ok=True)
    for spec in specs:
        name, rest = spec.split("=", 1)
        relative, dataset = rest.split(":", 1)
        stem = logdir / relative
        _gzip(stem.with_suffix(".csv"), out / f"{name}.csv.gz")
        saved = Path(f"{stem}.orbslam3-euroc.txt")
        if saved.is_file():
            _gzip(saved, out / f"{name}.orbslam3-euroc.txt.gz")
        gt = Path(dataset) / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        text = ground_truth_at_frames(gt, stem.with_suffix(".csv"))
        with gzip.GzipFile(out / f"{name}.groundtruth.csv.gz", "wb", compresslevel=9, mtime=0) as f:
            f.write(text.encode())
        print(f"{name}: {stem}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
