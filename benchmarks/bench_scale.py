"""Benchmark: cost growth of ingest, evaluate and fit with the study's size (issue 14, item 3).

    python benchmarks/bench_scale.py STUDY_DIR STUDY.parquet --sizes 100,1000,3410,10000 --work W \\
        [--fit-sizes 100,1000] [--estimate-sizes 3410,10000] [--before-tree OLD] [--json W/scale.json]

For each size N: the first N logs of STUDY_DIR (sorted paths, as `jsve ingest` orders them) ingested
to Parquet (`jsve ingest`), and that file (with --skip-ingest: the first N runs of STUDY.parquet, a
subset with its run list cut to match) evaluated under one rule (`jsve evaluate SUBSET --rule
orbslam3`); at --fit-sizes the default `jsve fit SUBSET` (every stage; its stages.json gives each
stage's time), at --estimate-sizes `jsve fit SUBSET --estimate-only` (the expected wall time: a timing
probe and the cost model). Each command runs in a fresh process under /usr/bin/time (wall, peak RSS),
the 1-minute load average beside every figure: timings move with the machine's load, and a shared
2-core machine is never quiet. `evaluate` runs twice, the second with JAX's compilation cache filled by
the first; --before-tree times an older checkout's `jsve evaluate` (PYTHONPATH) on the same subsets.
Prints one table (sizes x stages) and writes --json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq

from jsve.io import PARQUET_WRITE_OPTIONS

RUNS_KEY, FORMAT_KEY = b"jsve.runs", b"jsve.format"


def timed(cmd: list[str], env: dict[str, str] | None = None) -> dict:
    """Wall seconds, peak RSS (GB) and the load average before and after `cmd` (under /usr/bin/time);
    "stderr": the command's own lines (those before /usr/bin/time's report)."""
    before = os.getloadavg()[0]
    proc = subprocess.run(["/usr/bin/time", "-v", *cmd], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(cmd)}\n{proc.stderr[-3000:]}")
    h, m, s = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", proc.stderr).groups()
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    own = proc.stderr.split("\tCommand being timed:")[0]
    return {"wall_s": int(h or 0) * 3600 + int(m) * 60 + float(s), "peak_rss_gb": rss / 1e6,
            "load": [round(before, 1), round(os.getloadavg()[0], 1)], "stderr": own[-2000:]}  # fmt: skip


def subset_parquet(source: Path, n_runs: int, out: Path) -> int:
    """The first `n_runs` runs of a jsve Parquet file, with the run list cut to them; frames written."""
    pf = pq.ParquetFile(source)
    kv = dict(pf.metadata.metadata)
    entries = json.loads(kv[RUNS_KEY])[:n_runs]
    n_frames = sum(e["n_frames"] for e in entries)
    kv[RUNS_KEY] = json.dumps(entries).encode()
    with pq.ParquetWriter(out, pf.schema_arrow.remove_metadata(), **PARQUET_WRITE_OPTIONS) as writer:
        left = n_frames
        for rb in pf.iter_batches(batch_size=262_144):
            if left <= 0:
                break
            writer.write_batch(rb.slice(0, min(left, rb.num_rows)))
            left -= rb.num_rows
        writer.add_key_value_metadata({k: v for k, v in kv.items() if k.startswith(b"jsve.")})
    return n_frames


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", type=Path, help="folder of logs (`jsve simulate -o`)")
    p.add_argument("parquet", type=Path, help="the same logs ingested (`jsve ingest`)")
    p.add_argument("--sizes", default="100,1000,3410", help="numbers of logs (default: 100,1000,3410)")
    p.add_argument("--fit-sizes", default="", help="sizes (of --sizes) at which to run the default jsve fit")
    p.add_argument("--estimate-sizes", default="", help="sizes at which to run jsve fit --estimate-only")
    p.add_argument("--work", type=Path, required=True, help="folder for subsets and outputs")
    p.add_argument("--before-tree", type=Path, help="an older checkout whose `jsve evaluate` to time too")
    p.add_argument("--skip-ingest", action="store_true", help="time evaluate only")
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    logs = sorted(str(f) for f in args.study.rglob("*.csv"))  # as `jsve ingest` orders a folder
    figures: dict[str, dict] = {}
    for n in (int(x) for x in args.sizes.split(",")):
        row: dict = {"logs": n}
        if not args.skip_ingest:
            text_mb = sum(os.path.getsize(f) for f in logs[:n]) / 1e6
            folder = args.work / f"logs-{n}"  # the first n logs, linked
            for k, log in enumerate(logs[:n]):
                link = folder / f"{k:06d}.csv"
                if not link.exists():
                    link.parent.mkdir(parents=True, exist_ok=True)
                    link.symlink_to(Path(log).resolve())
            out = args.work / f"ingest-{n}.parquet"
            row["ingest"] = timed(["jsve", "ingest", str(folder), "-o", str(out), "--no-progress", "--yes"])
            row["ingest"]["mb_per_s"] = text_mb / row["ingest"]["wall_s"]
        if args.skip_ingest:
            subset = args.work / f"study-{n}.parquet"
            row["frames"] = subset_parquet(args.parquet, n, subset)
        else:
            subset = out  # the first n logs, as ingested
            row["frames"] = pq.ParquetFile(subset).metadata.num_rows
        cmd = ["jsve", "evaluate", str(subset), "--rule", "orbslam3", "--no-progress"]
        row["evaluate_first"] = timed([*cmd, "-o", str(args.work / f"eval-{n}")])
        row["evaluate"] = timed([*cmd, "-o", str(args.work / f"eval-{n}")])
        if args.before_tree:
            env = dict(os.environ, PYTHONPATH=str(args.before_tree.resolve()))
            row["evaluate_before"] = timed([*cmd, "-o", str(args.work / f"eval-before-{n}")], env)
        if str(n) in args.estimate_sizes.split(","):
            est = args.work / f"estimate-{n}"
            row["fit_estimate"] = timed(
                ["jsve", "fit", str(subset), "-o", str(est), "--estimate-only", "--no-progress"]
            )
            line = re.search(r"expected wall time .*", row["fit_estimate"]["stderr"])
            row["fit_estimate"]["expected"] = line.group(0) if line else None
        if str(n) in args.fit_sizes.split(","):
            fit_dir = args.work / f"fit-{n}"
            shutil.rmtree(fit_dir, ignore_errors=True)  # a fresh fit, not a resumed one
            row["fit"] = timed(["jsve", "fit", str(subset), "-o", str(fit_dir), "--no-progress"])
            stages = json.loads((fit_dir / "stages.json").read_text())["done"]
            row["fit"]["stages_s"] = {k: round(v["seconds"], 1) for k, v in stages.items()}
        figures[str(n)] = row
        print(json.dumps(row), flush=True)
    print(f"\n{'logs':>6} {'frames':>10} {'stage':<16} {'wall s':>8} {'peak GB':>8} {'load':>10}")
    for row in figures.values():
        for stage in ("ingest", "evaluate_first", "evaluate", "evaluate_before", "fit_estimate", "fit"):
            if stage in row:
                f = row[stage]
                extra = f"  {f['mb_per_s']:.0f} MB/s" if "mb_per_s" in f else ""
                extra += f"  {f['expected']}" if f.get("expected") else ""
                print(f"{row['logs']:>6} {row['frames']:>10} {stage:<16} {f['wall_s']:>8.1f} "
                      f"{f['peak_rss_gb']:>8.2f} {f['load'][0]:>4}-{f['load'][1]:<4}{extra}")  # fmt: skip
    if args.json:
        for row in figures.values():  # the commands' own output stays on the screen only
            for f in row.values():
                if isinstance(f, dict):
                    f.pop("stderr", None)
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
