"""`jsve frontend run` as a job: lockstep plans (modes, seeds, keys), the outcome of every way a run can
end, and resumption after `kill -9` at random moments with no run lost, duplicated, overlapped or
half-written. A stand-in driver (a script with the real driver's options and files) takes ORB-SLAM3's
place: what is under test is jsve's handling of runs, which does not depend on what the driver computes.
The real driver's lockstep repeats are checked by .ci/frontend-smoke."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from test_frontend_run import SETTINGS, make_build, make_dataset

from jsve.frontend._run import canonical_paths, driver_args, driver_command, outcome, plan, run_all

# Writes the log in steps (`.partial`, renamed when complete), then the driver's summary and ORB-SLAM3's
# trajectory, as jsve_orbslam3 does; every start and end goes to a ledger. Its content is a function of
# the seed alone, as a lockstep run's is. FAKE_EXIT / FAKE_SLEEP make it end as told.
FAKE_DRIVER = r"""#!{python}
import json, os, sys, time
args = sys.argv[1:]
opt = lambda k: args[args.index(k) + 1] if k in args else None
log, summary, seed = opt("--log"), opt("--summary"), opt("--seed")
ledger = os.environ["FAKE_LEDGER"]
def note(what):
    with open(ledger, "a") as f:
        f.write(f"{{what}} {{log}} {{os.getpid()}} {{time.monotonic():.6f}}\n")
note("start")
if os.environ.get("FAKE_SLEEP"):
    time.sleep(float(os.environ["FAKE_SLEEP"]))
code = int(os.environ.get("FAKE_EXIT", "0"))
key = [a for a in args if a.startswith("generator=")][0][len('generator="'):-1]
header = "# jsve-log v3 " + json.dumps({{"generator": key}})
with open(log + ".partial", "w") as f:
    f.write(header + "\n")
    for i in range(int(os.environ.get("FAKE_STEPS", "6"))):
        f.write(f"{{seed}},{{i}}\n")
        f.flush()
        time.sleep(0.05)
if code == 0:
    os.replace(log + ".partial", log)
with open(summary, "w") as f:
    mode = "lockstep" if "--lockstep" in args else "paced"
    json.dump({{"status": code, "seed": int(seed) if seed else None, "mode": mode}}, f)
note("end")
sys.exit(code)
"""


def make_fake_build(root: Path) -> Path:
    build = make_build(root)
    driver = build / "bin" / "jsve_orbslam3"
    driver.parent.mkdir()
    driver.write_text(FAKE_DRIVER.format(python=sys.executable))
    driver.chmod(0o755)
    return build


@pytest.fixture
def job_inputs(tmp_path):
    ds = make_dataset(tmp_path / "ds", manifest={"trajectory": "V101_GT.txt"})
    (voc := tmp_path / "voc.txt").write_text("10 6 0 0")
    (settings := tmp_path / "s.yaml").write_text(SETTINGS)
    return make_fake_build(tmp_path / "build"), ds, voc, settings


def test_lockstep_run_k_draws_from_seed_k_and_its_mode_and_seed_are_in_the_key(job_inputs, tmp_path):
    build, ds, voc, settings = job_inputs
    kw = dict(runs=3, vocabulary=voc, settings=settings)
    todo, _ = plan(build, [ds], out=tmp_path / "a", mode="lockstep", **kw)
    assert [j.seed for j in todo] == [0, 1, 2] and [j.meta["seed"] for j in todo] == [0, 1, 2]
    assert driver_args(todo[2], 30.0) == ["--lockstep", "--gate-timeout", "30.0", "--seed", "2"]
    shifted, _ = plan(build, [ds], out=tmp_path / "b", mode="lockstep", seed=10, **kw)
    assert [j.seed for j in shifted] == [10, 11, 12]
    paced, _ = plan(build, [ds], out=tmp_path / "c", **kw)
    assert [j.seed for j in paced] == [None] * 3 and "seed" not in paced[0].meta
    assert driver_args(paced[0]) == []
    keys = {jobs[0].meta["generator"] for jobs in (todo, shifted, paced)}
    assert len(keys) == 3
    with pytest.raises(ValueError, match="mode 'fast'"):
        plan(build, [ds], out=tmp_path / "d", mode="fast", **kw)


def test_outcomes_name_what_ended_a_run():
    assert [outcome(c) for c in (0, 1, 2, 3)] == ["ok", "failed", "bad_input", "gate_timeout"]
    assert outcome(-signal.SIGKILL) == "SIGKILL" and outcome(-signal.SIGSEGV) == "SIGSEGV"
    assert outcome(-9, timed_out=True) == "timeout"


@pytest.mark.parametrize(
    "env, expected",
    [({"FAKE_EXIT": "3"}, "gate_timeout"), ({"FAKE_EXIT": "1"}, "failed"), ({"FAKE_SLEEP": "30"}, "timeout")],
)
def test_a_closed_gate_a_failure_and_a_timeout_end_as_kept_outcomes(
    job_inputs, tmp_path, monkeypatch, env, expected
):
    build, ds, voc, settings = job_inputs
    monkeypatch.setenv("FAKE_LEDGER", str(tmp_path / "ledger"))
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    kw = dict(runs=1, out=tmp_path / "logs", vocabulary=voc, settings=settings, mode="lockstep")
    todo, _ = plan(build, [ds], **kw)
    started = time.monotonic()
    [summary] = run_all(build, todo, voc, timeout_s=2.0, progress=False)
    assert time.monotonic() - started < 10  # a hung driver is stopped at its timeout
    assert summary["outcome"] == expected and summary["exit_code"] != 0
    todo, done = plan(build, [ds], **kw)
    assert todo == [] and done == [tmp_path / "logs" / "V101" / "none-0" / "run_000.csv"]
    todo, _ = plan(build, [ds], retry_failed=True, **kw)
    assert len(todo) == 1


def _attempts(ledger: Path) -> dict[str, list[tuple[float, float]]]:
    """Per log: the (start, end) times of its attempts; end is inf for one that never ended."""
    starts: dict[tuple[str, str], float] = {}
    ends: dict[tuple[str, str], float] = {}
    for line in ledger.read_text().splitlines():
        what, log, pid, t = line.split()
        (starts if what == "start" else ends)[(log, pid)] = float(t)
    out: dict[str, list[tuple[float, float]]] = {}
    for (log, pid), t0 in starts.items():
        out.setdefault(log, []).append((t0, ends.get((log, pid), float("inf"))))
    return out


def test_kill_9_at_random_moments_loses_duplicates_and_half_writes_no_run(job_inputs, tmp_path):
    build, ds, voc, settings = job_inputs
    out, ledger = tmp_path / "logs", tmp_path / "ledger"
    env = {**os.environ, "FAKE_LEDGER": str(ledger), "FAKE_STEPS": "20"}
    cli = "import sys; from jsve.cli import main; sys.exit(main())"
    cmd = [sys.executable, "-c", cli, "frontend", "run", str(build), str(ds), "--vocabulary", str(voc),
           "--settings", str(settings), "--runs", "5", "--workers", "2", "--lockstep", "-o", str(out),
           "--no-progress"]  # fmt: skip
    rng = random.Random(7)
    kills = 0
    for _ in range(5):
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=rng.uniform(1.0, 3.0))
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            kills += 1
    assert kills >= 3
    final = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert final.returncode == 0, final.stderr
    folder = out / "V101" / "none-0"
    for k in range(5):
        log = folder / f"run_{k:03d}.csv"
        summary = json.loads(log.with_suffix(".summary.json").read_text())
        assert summary["outcome"] == "ok" and summary["seed"] == k
        lines = log.read_text().splitlines()
        assert lines[1:] == [f"{k},{i}" for i in range(20)]  # whole, and written once
    assert (
        not list(folder.glob("*.partial"))
        and not list(folder.glob("*.tmp"))
        and not list(folder.glob("*.lock"))
    )
    # An attempt orphaned by a kill never overlaps the attempt that replaces it.
    for log, attempts in _attempts(ledger).items():
        attempts.sort()
        for (_, end), (start, _) in zip(attempts, attempts[1:], strict=False):
            assert end <= start, f"{log}: attempts overlap"
    # The finished command found every run done: nothing ran twice after it finished.
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "5 runs done already" in again.stderr and "0 to run" in again.stderr


def test_a_run_sees_the_same_paths_wherever_its_inputs_and_outputs_are(job_inputs, tmp_path):
    # A lockstep run's heap (by whose addresses ORB-SLAM3 orders keyframes and points) depends on the
    # lengths of the strings the driver holds: every path reaches it with one length.
    build, ds, voc, settings = job_inputs
    seen = []
    for out in (tmp_path / "o", tmp_path / "a" / "much" / "longer" / "output" / "folder"):
        [job], _ = plan(build, [ds], runs=1, out=out, vocabulary=voc, settings=settings, mode="lockstep")
        cmd = driver_command(build / "bin" / "jsve_orbslam3", voc, job)
        with canonical_paths(cmd) as (cwd, canonical):
            assert len(Path(cwd).name) == len(Path(tempfile.mkdtemp(prefix="jsve-run-")).name)
            for name in ("v.txt", "s.yaml", "d", "o"):
                assert (Path(cwd) / name).resolve().exists()
            assert (Path(cwd) / "o").resolve() == job.log.parent.resolve()
            seen.append(canonical[1:])  # all but the driver itself
        assert not Path(cwd).exists()
    assert seen[0] == seen[1]
    assert "o/run_000.csv" in seen[0] and "d" in seen[0] and "v.txt" in seen[0]


def test_two_commands_on_one_folder_run_each_run_once(job_inputs, tmp_path, monkeypatch):
    # The second command planned the runs while the first was running them: it waits for each run's
    # lock and finds it finished.
    import threading

    build, ds, voc, settings = job_inputs
    ledger = tmp_path / "ledger"
    monkeypatch.setenv("FAKE_LEDGER", str(ledger))
    todo, _ = plan(
        build, [ds], runs=3, out=tmp_path / "logs", vocabulary=voc, settings=settings, mode="lockstep"
    )
    results: list[list[dict]] = []
    threads = [threading.Thread(target=lambda: results.append(run_all(build, todo, voc, progress=False)))
               for _ in range(2)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    starts = [line.split()[1] for line in ledger.read_text().splitlines() if line.startswith("start")]
    assert sorted(starts) == sorted(str(Path("o") / job.log.name) for job in todo)  # once each
    assert [r["outcome"] for r in results[0]] == [r["outcome"] for r in results[1]] == ["ok"] * 3
