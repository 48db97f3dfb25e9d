"""jsve.io._scheduler: where the front-end sweeps' tasks run, and `--scheduler` on the commands.

The oracle of a cluster run is the process pool's run of the same command: a Dask cluster with two
worker processes, reached through its scheduler's address on loopback, must write the same files, byte
for byte. The commands run in subprocesses (a fresh client, as a user's shell starts it) under a
timeout, and the cluster is closed whatever happens.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from jsve.io import _scheduler

COMMAND_TIMEOUT_S = 300
"""A command that has not finished by then has hung (each takes seconds to tens of seconds on 2 cores)."""


# --------------------------------------------------------------------------------------------------
# The value of --scheduler


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (None, "local"),
        ("local", "local"),
        ("processes", "processes"),
        ("tcp://10.0.0.5:8786", "tcp://10.0.0.5:8786"),
        ("tls://head.cluster:8786", "tls://head.cluster:8786"),
        ("head-node.cluster:8786", "tcp://head-node.cluster:8786"),
    ],
)
def test_check_scheduler_names_the_schedulers(value, expected):
    assert _scheduler.check_scheduler(value) == expected


def test_a_scheduler_file_is_its_absolute_path_and_must_exist(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(_scheduler.SchedulerError, match="no such scheduler file"):
        _scheduler.check_scheduler("scheduler.json")
    (tmp_path / "scheduler.json").write_text("{}")
    assert _scheduler.check_scheduler("scheduler.json") == str(tmp_path / "scheduler.json")


@pytest.mark.parametrize("value", ["", "dask", "8786", "tcp:/host:8786", "host:port"])
def test_anything_else_is_refused_with_the_choices(value):
    with pytest.raises(
        _scheduler.SchedulerError, match="expected local, processes, a Dask scheduler address"
    ):
        _scheduler.check_scheduler(value)


def test_one_worker_or_one_task_runs_here_unless_a_cluster_is_named():
    assert _scheduler.in_process(1, "local", 10) and _scheduler.in_process(1, "processes", 10)
    assert _scheduler.in_process(4, None, 1) and _scheduler.in_process(4, "local", 0)
    assert not _scheduler.in_process(2, "local", 2) and not _scheduler.in_process(2, "processes", 2)
    assert not _scheduler.in_process(1, "tcp://127.0.0.1:8786", 1)  # the cluster was asked for


# --------------------------------------------------------------------------------------------------
# Executors


def _count(calls: list, tag: str) -> None:
    calls.append(tag)


def test_a_dask_task_runs_its_initializer_once_per_worker_and_again_for_another():
    """_call is what a Dask worker runs: the sweep's initializer before its first task (a process pool
    runs it when a worker starts), and again when the previous task was another sweep's."""
    calls: list = []
    _scheduler._initialised.clear()
    try:
        assert _scheduler._call(_count, (calls, "a"), abs, -1) == 1
        assert _scheduler._call(_count, (calls, "a"), abs, -2) == 2
        assert calls == ["a"]
        _scheduler._call(_count, (calls, "b"), abs, -3)
        _scheduler._call(_count, (calls, "a"), abs, -4)
        assert calls == ["a", "b", "a"]
        _scheduler._call(None, (), abs, -5)  # no initializer: nothing run
        assert calls == ["a", "b", "a"]
    finally:
        _scheduler._initialised.clear()


@pytest.mark.parametrize("scheduler", ["processes", "local"])
def test_executor_runs_tasks_in_other_processes_after_the_initializer(scheduler, tmp_path):
    """Both local schedulers run tasks in worker processes that ran the initializer first (here: moved
    into tmp_path); the embedded LocalCluster leaves this process's environment as it found it (its
    nannies set variables in the process that runs them)."""
    before, here = dict(os.environ), os.getcwd()
    with _scheduler.executor(2, scheduler, initializer=os.chdir, initargs=(str(tmp_path),)) as pool:
        folders = [pool.submit(os.getcwd) for _ in range(4)]
        pids = [pool.submit(os.getpid) for _ in range(4)]
        assert [f.result(timeout=120) for f in folders] == [str(tmp_path)] * 4
        assert os.getpid() not in {f.result(timeout=120) for f in pids}
    assert dict(os.environ) == before and os.getcwd() == here


def test_leaving_on_an_error_cancels_the_tasks_not_started():
    with pytest.raises(ZeroDivisionError):
        with _scheduler.executor(1, "processes") as pool:
            first = pool.submit(divmod, 1, 0)
            rest = [pool.submit(sum, range(10**7)) for _ in range(20)]
            first.result(timeout=120)
    assert any(f.cancelled() for f in rest)


class _FakeClient:
    """What _check_workers asks of a distributed.Client: client.run(function, *args) on every worker."""

    def __init__(self, answers: dict):
        self.answers = answers

    def run(self, function, *args):
        return self.answers


def test_workers_with_another_jsve_are_refused():
    from importlib.metadata import version

    ours = version("jsve")
    _scheduler._check_workers(_FakeClient({"tcp://a:1": ours, "tcp://b:1": ours}), "here")
    with pytest.raises(
        _scheduler.SchedulerError, match=r"here: workers run another jsve \(tcp://b:1: 0\.0\.1"
    ):
        _scheduler._check_workers(_FakeClient({"tcp://a:1": ours, "tcp://b:1": "0.0.1"}), "here")


def test_an_unreachable_scheduler_is_one_error_and_nothing_is_written(tmp_path, monkeypatch):
    from jsve.sim import _config as sim_config
    from jsve.sim import _study as sim_study
    from jsve.sim import _trajectory as st

    monkeypatch.setattr(_scheduler, "CONNECT_TIMEOUT_S", 1.0)
    short = sim_config.SimConfig(flight=st.FlightProfile(duration_s=(25.0, 25.0)))
    with pytest.raises(_scheduler.SchedulerError, match="tcp://127.0.0.1:9: cannot connect"):
        sim_study.write_study(tmp_path / "s", procedural=1, disturbances="blur:0", runs=1, config=short,
                              progress=False, scheduler="127.0.0.1:9")  # fmt: skip
    assert not list(tmp_path.rglob("*.csv"))


@pytest.mark.parametrize("command", ["simulate", "disturb", "render", "frontend run"])
def test_a_wrong_scheduler_value_is_one_line_and_exit_2(command, tmp_path, capsys):
    import jsve.cli

    argv = {
        "simulate": ["simulate", "-o", str(tmp_path / "out"), "--procedural", "1", "--runs", "1"],
        "disturb": ["disturb", str(tmp_path), "-o", str(tmp_path / "out")],
        "render": ["render", "--trajectory", "gt.txt", "--timestamps", "ts.txt", "-o", str(tmp_path / "out")],
        "frontend run": [
            "frontend",
            "run",
            str(tmp_path),
            str(tmp_path),
            "--vocabulary",
            __file__,
            "--settings",
            __file__,
            "-o",
            str(tmp_path / "out"),
        ],  # fmt: skip
    }[command]
    (tmp_path / "build.json").write_text("{}")
    assert jsve.cli.main([*argv, "--scheduler", "nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"jsve {command}: --scheduler 'nowhere': expected local, processes, a Dask scheduler "
                   "address (tcp://host:8786) or a scheduler file (scheduler.json)"]  # fmt: skip
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------
# A sweep on a cluster equals the process pool's


@pytest.fixture(scope="module")
def cluster():
    """A Dask cluster of two single-threaded worker processes, as `dask scheduler` + `dask worker`
    would make one (Dask's default worker environment), reached on loopback; closed at the end."""
    distributed = pytest.importorskip("distributed")
    local = distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=":0",
        scheduler_kwargs={"dashboard": False},
        silence_logs=logging.ERROR,
    )
    try:
        yield local
    finally:
        local.close(timeout=30)


def _jsve(*argv: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "jsve.cli", *argv, "--no-progress"],
        capture_output=True,
        text=True,
        timeout=COMMAND_TIMEOUT_S,
    )
    assert done.returncode == 0, done.stderr


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _tasks_run(cluster) -> dict[str, int]:
    """Tasks the cluster has finished, by prefix: how often one entered the state "memory" (the scheduler
    runs in this process and counts every state a task enters)."""
    prefixes = cluster.scheduler.task_prefixes
    return {name: prefix.state_counts["memory"] for name, prefix in prefixes.items()}


@pytest.mark.slow
def test_simulate_on_a_cluster_writes_what_the_process_pool_writes(cluster, tmp_path):
    address = cluster.scheduler_address
    assert address.startswith("tcp://127.0.0.1:")
    sweep = ["--procedural", "2", "--duration", "30", "--disturbances", "blur=0", "--runs", "1"]
    sweep += ["--workers", "2"]
    _jsve("simulate", "-o", str(tmp_path / "pool"), *sweep, "--scheduler", "processes")
    _jsve("simulate", "-o", str(tmp_path / "cluster"), *sweep, "--scheduler", address)
    assert _tasks_run(cluster).get("jsve_run_job") == 2  # one task per sequence, on the cluster
    pool, on_cluster = _files(tmp_path / "pool"), _files(tmp_path / "cluster")
    assert sorted(pool) == ["proc_00/blur-0/run_000.csv", "proc_01/blur-0/run_000.csv"]
    assert on_cluster == pool
    # Resumable as on the pool: a second run through the cluster finds every log complete.
    _jsve("simulate", "-o", str(tmp_path / "cluster"), *sweep, "--scheduler", address)
    assert _tasks_run(cluster).get("jsve_run_job") == 2 and _files(tmp_path / "cluster") == pool


def _dataset(root: Path, n_frames: int = 2) -> Path:
    """A small EuRoC-format dataset: textured cam0 frames and an IMU file to be linked."""
    rng = np.random.default_rng(3)
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for i in range(n_frames):
        t = 1403715273262142976 + i * 50_000_000
        image = cv2.GaussianBlur(rng.uniform(0, 255, (480, 752)).astype(np.float32), (0, 0), 1.5)
        cv2.imwrite(str(cam / "data" / f"{t}.png"), np.clip(image, 0, 255).astype(np.uint8))
        lines.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    (root / "mav0" / "imu0").mkdir()
    (root / "mav0" / "imu0" / "data.csv").write_text(
        "#t,wx,wy,wz,ax,ay,az\n1403715273262142976,0,0,0,0,0,9.81\n"
    )
    return root


@pytest.mark.slow
def test_disturb_on_a_cluster_writes_what_the_process_pool_writes(cluster, tmp_path):
    source = _dataset(tmp_path / "SEQ")
    sweep = [str(source), "--disturbances", "noise=5,haze=1", "--workers", "2"]
    _jsve("disturb", *sweep, "-o", str(tmp_path / "pool"), "--scheduler", "processes")
    before = _tasks_run(cluster).get("jsve_disturb_dataset", 0)
    _jsve("disturb", *sweep, "-o", str(tmp_path / "cluster"), "--scheduler", cluster.scheduler_address)
    assert _tasks_run(cluster).get("jsve_disturb_dataset", 0) - before == 2
    pool = _files(tmp_path / "pool")
    frames = [f"mav0/cam0/data/{t}.png" for t in (1403715273262142976, 1403715273312142976)]
    files = ["jsve_manifest.json", "mav0/cam0/data.csv", *frames, "mav0/imu0/data.csv"]
    assert sorted(pool) == [f"SEQ/{d}/{f}" for d in ("haze-1", "noise-5") for f in files]
    assert _files(tmp_path / "cluster") == pool


FAKE_DRIVER = """#!/bin/sh
# A stand-in for jsve_orbslam3: reads the dataset it is given, writes a log, a trajectory and a summary.
while [ $# -gt 0 ]; do
  case "$1" in
    --sequence) sequence=$2; shift ;;
    --log) log=$2; shift ;;
    --trajectory) trajectory=$2; shift ;;
    --summary) summary=$2; shift ;;
  esac
  shift
done
frames=$(($(wc -l < "$sequence/mav0/cam0/data.csv") - 1)) || exit 3
echo "# jsve-log v2 {}" > "$log"
echo "1403715273.262143 0.5 0 0 0 0 0 1" > "$trajectory"
echo "{\\"frames\\": $frames}" > "$summary"
echo "ran $(basename "$log")"
"""

SETTINGS = "%YAML:1.0\nCamera.width: 752\nCamera.height: 480\nCamera.fps: 20\n"


def _without_timing(files: dict[str, bytes]) -> dict[str, bytes]:
    """The files with each summary's wall time and log path (absolute on a cluster) left out."""
    import json

    out = {}
    for name, data in files.items():
        if name.endswith(".summary.json"):
            summary = json.loads(data)
            summary.pop("wall_seconds")
            assert Path(summary.pop("log")).name == Path(name).name.replace(".summary.json", ".csv")
            data = json.dumps(summary, sort_keys=True).encode()
        out[name] = data
    return out


@pytest.mark.slow
def test_frontend_run_on_a_cluster_writes_what_local_threads_write(cluster, tmp_path, monkeypatch):
    """`jsve frontend run` through the cluster's address, with a stand-in driver and every path relative
    to a working folder the workers do not share: the same files as the local run, the same summaries."""
    from jsve.frontend._run import plan, run_all

    monkeypatch.chdir(tmp_path)  # the cluster's workers started elsewhere
    build = Path("build")
    (build / "bin").mkdir(parents=True)
    (build / "build.json").write_text('{"hook_sha256": "' + "ab" * 32 + '"}')
    driver = build / "bin" / "jsve_orbslam3"
    driver.write_text(FAKE_DRIVER)
    driver.chmod(0o755)
    _dataset(Path("SEQ"), n_frames=2)
    Path("voc.txt").write_text("10 6 0 0")
    Path("settings.yaml").write_text(SETTINGS)
    results = {}
    for name, scheduler in (("local", "local"), ("cluster", cluster.scheduler_address)):
        todo, _ = plan(build, [Path("SEQ")], runs=3, out=Path(name), vocabulary=Path("voc.txt"),
                       settings=Path("settings.yaml"))  # fmt: skip
        results[name] = run_all(build, todo, Path("voc.txt"), workers=2, progress=False, scheduler=scheduler)
        assert [r["exit_code"] for r in results[name]] == [0, 0, 0]
        assert [r["log"] for r in results[name]] == [str(job.log) for job in todo]  # as planned: relative
    assert _tasks_run(cluster).get("jsve_run_one") == 3
    local, on_cluster = _files(Path("local")), _files(Path("cluster"))
    assert len(local) == 3 * 5 and _without_timing(on_cluster) == _without_timing(local)
