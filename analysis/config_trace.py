"""How far a study's configuration travels: the files a `jsve demo` visits with its StudyConfig or
FitConfig in hand, in order (issue 34's trace of the rule's parameters from the command to the kernel).

    python analysis/config_trace.py [--tree CHECKOUT] [--json OUT.json]

Runs a small `jsve demo` (one flight, one run per setting, a small search; seconds of fitting) under
`sys.setprofile`, and records every call of a function in jsve whose arguments (or `self`) include a
StudyConfig or a FitConfig. Consecutive calls in one file make one *stay*; printed are the stays, the
distinct files, the *returns* (stays in a file the trace has already left), the *climbs* (a stay in a
layer above the previous stay's, analysis/architecture.py's LAYERS order) and the stays per file.
--tree runs it on another checkout (e.g. a `git worktree` of an older commit) with the same counting.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

CONFIG_TYPES = ("StudyConfig", "FitConfig")

DEMO_CONFIG = """
families = ["sve", "inliers"]
kfold = 2
n_boot = 100
heatmap = ["imu_init", "recovery", 3]
[fit]
n_search = 32
n_starts = 1
nm_steps = 4
[demo]
sequences = 1
runs = 1
duration_s = [10.0, 10.0]
"""


def _layer_rank(module: str) -> int:
    """The position of a module's layer in LAYERS, lowest first (the entry points last)."""
    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here))
    try:
        import architecture
    finally:
        sys.path.pop(0)
    order = list(architecture.LAYERS)
    layer = architecture.layer_of(module)
    return order.index(layer) if layer in order else len(order)


def _traced_files(tree: Path, out: Path) -> list[str]:
    """The files (relative to the checkout) of every jsve call that holds the configuration, in order."""
    calls: list[str] = []
    package = str(tree / "jsve")

    def profile(frame, event, arg):
        if event != "call" or not frame.f_code.co_filename.startswith(package):
            return
        code = frame.f_code
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        if any(type(frame.f_locals.get(n)).__name__ in CONFIG_TYPES for n in names):
            calls.append(os.path.relpath(code.co_filename, tree))

    config = out / "demo.toml"
    config.write_text(DEMO_CONFIG)
    from jsve.cli import main

    sys.setprofile(profile)
    try:
        argv = ["demo", "-o", str(out / "demo"), "--config", str(config), "--no-progress", "--workers", "1"]
        code = main(argv)
    finally:
        sys.setprofile(None)
    if code != 0:
        raise SystemExit(f"jsve demo exited {code}")
    return calls


def summary(files: list[str]) -> dict:
    """Stays, distinct files, returns, climbs and stays per file of a trace of files."""
    stays = [f for i, f in enumerate(files) if i == 0 or files[i - 1] != f]
    seen: set[str] = set()
    returns = 0
    for i, f in enumerate(stays):
        returns += f in seen and i > 0
        seen.add(f)
    module = [f.removesuffix(".py").replace(os.sep, ".").removesuffix(".__init__") for f in stays]
    ranks = [_layer_rank(m) for m in module]
    climbs = sum(b > a for a, b in zip(ranks, ranks[1:], strict=False))
    return {
        "calls": len(files),
        "stays": len(stays),
        "files": len(seen),
        "returns": returns,
        "climbs": climbs,
        "stays_per_file": dict(Counter(stays).most_common()),
        "path": stays,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tree", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--json", type=Path)
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    tree = args.tree.resolve()
    if not args.inner:
        # A fresh interpreter with the checkout first on the path, so --tree's jsve is the one traced.
        env = {**os.environ, "PYTHONPATH": str(tree)}
        cmd = [sys.executable, __file__, "--inner", "--tree", str(tree)]
        cmd += ["--json", str(args.json)] if args.json else []
        return subprocess.run(cmd, env=env, cwd=tree, check=False).returncode
    with tempfile.TemporaryDirectory() as tmp:
        result = summary(_traced_files(tree, Path(tmp)))
    git = ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"]
    commit = subprocess.run(git, capture_output=True, text=True, check=False)
    result["commit"] = commit.stdout.strip()
    shown = {k: v for k, v in result.items() if k != "path"}
    print(json.dumps(shown, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
