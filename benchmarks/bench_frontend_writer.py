"""Per-frame cost of jsve_log.hpp, the C++ writer of log format v2.

Compiles tests/cpp/bench_writer.cpp with the system compiler at -O2, writes N realistic frames
(ORB-SLAM3 on EuRoC magnitudes) to a real file in a temporary directory, REPEATS times, and
prints the median and minimum microseconds per frame (validation + formatting + buffered write,
open and close amortised), and the cost of binning ORB-SLAM3's 64 x 48 keypoint grid into the
64 SVE bins with jsve::fill_bins_from_grid. Both float formatters are measured: std::to_chars
(default) and the snprintf "%.17g" fallback (-DJSVE_LOG_USE_SNPRINTF).

    python benchmarks/bench_frontend_writer.py                 # 20000 frames x 5 repeats
    python benchmarks/bench_frontend_writer.py --frames 100000 --repeats 7 --json out.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jsve.frontend

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO / "tests" / "cpp" / "bench_writer.cpp"


def build(compiler: str, out: Path, defines: list[str]) -> None:
    cmd = [
        compiler,
        "-std=c++17",
        "-O2",
        *defines,
        f"-I{jsve.frontend.get_include()}",
        str(SOURCE),
        "-o",
        str(out),
    ]
    subprocess.run(cmd, check=True)


def run(binary: Path, log: Path, frames: int, repeats: int) -> dict:
    done = subprocess.run(
        [str(binary), str(log), str(frames), str(repeats)], check=True, capture_output=True, text=True
    )
    return json.loads(done.stdout)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20000, help="frames per repeat (default 20000)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (default 5)")
    parser.add_argument(
        "--compiler", default=shutil.which("g++") or shutil.which("clang++"), help="C++ compiler"
    )
    parser.add_argument("--json", type=Path, help="also write the results to this JSON file")
    args = parser.parse_args(argv)
    if not args.compiler:
        parser.error("no C++ compiler found (g++ or clang++); pass --compiler")
    version = subprocess.run(
        [args.compiler, "--version"], capture_output=True, text=True
    ).stdout.splitlines()[0]
    results = {"compiler": version, "flags": "-std=c++17 -O2", "variants": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name, defines in (("to_chars", []), ("snprintf", ["-DJSVE_LOG_USE_SNPRINTF"])):
            binary = Path(tmp) / f"bench_{name}"
            build(args.compiler, binary, defines)
            results["variants"][name] = run(binary, Path(tmp) / "bench.csv", args.frames, args.repeats)
    for name, r in results["variants"].items():
        print(
            f"{name:9s} {r['median_us_per_frame']:.2f} us/frame median, {r['min_us_per_frame']:.2f} min "
            f"({r['frames']} frames x {r['repeats']}, {r['bytes_per_frame']:.0f} bytes/frame, {version})"
        )
    bins = results["variants"]["to_chars"]["bins_us_per_frame"]
    print(f"binning   {bins:.2f} us/frame (fill_bins_from_grid over a 64 x 48 grid of 1000 keypoints)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
