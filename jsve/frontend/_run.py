"""`jsve frontend run`: the hooked ORB-SLAM3 (IMU_MONOCULAR or MONOCULAR) over EuRoC-format datasets, N
runs each.

Each run calls the driver that `jsve frontend build` made (BUILD/bin/jsve_orbslam3) and writes, under
OUT/<sequence>/<disturbance>-<level>/ (the simulator's layout):

    run_<k>.csv               the format-v3 log (jsve_log.hpp; `.partial` while running or after a failure)
    run_<k>.orbslam3.txt      ORB-SLAM3's own trajectory (SaveTrajectoryEuRoC: body poses, stamps in ns)
    run_<k>.orbslam3-euroc.txt   the same as a EuRoC CSV (int ns, p, q wxyz), for `jsve ape --format
                              euroc` against the dataset's state_groundtruth_estimate0/data.csv
    run_<k>.saved-from-log.txt   the same trajectory rebuilt from the log alone (jsve.io._saved_trajectory)
    run_<k>.summary.json      the run's outcome and where its time went (the driver's summary), its
                              events, and the ATE of both trajectories (saved_trajectory_scores);
                              written last, atomically: a run is finished exactly when it exists
    run_<k>.console.txt       ORB-SLAM3's console output
    run_<k>.keypoints.csv     with `keypoints`: every frame's keypoints (jsve.io._keypoints, format v1)

With `masks`, each dataset's mav0/cam0/masks/<image name>.png (16-bit instance maps) take the keypoints
on cars and pedestrians out of ORB-SLAM3's frames before it tracks them (docs/masks.md, "Masks in the
loop"); the log's `masks` trailer holds the counts per frame.

Modes (docs/frontend.md): `paced` feeds frames at the camera's rate, as a live camera does; `no-wait`
as fast as tracking takes them; `lockstep` as fast as possible with ORB-SLAM3's three threads taking
turns, so that a run depends only on its inputs and its seed (run k draws its RANSAC samples from
seed S + k). Paced and no-wait runs are not repeatable: N of them differ by the threads' timing.

Runs are resumable after the command is killed at any moment: a run counts as done only once its
summary is written under the run's key (driver build, hook, dataset, settings, vocabulary content,
rule, mode and seed); a run without one is cleared and run again. A complete log of another key stops
the command unless `force`. A run that ended in a crash, a timeout or a lockstep gate that never opened
is an outcome, not a gap: its summary (`outcome` not "ok") is kept and not run again unless
`retry_failed`, since re-running crashes until they succeed would bias the failure rate towards zero.
Each run holds `run_<k>.lock` while it runs (shared with its driver, which also dies with its parent),
so an attempt left running by a killed command never overlaps its retry; the lock goes once the run
is finished.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import fcntl
import functools
import json
import os
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from jsve.frontend import DEFAULT_GATE_TIMEOUT_S
from jsve.io import _scheduler
from jsve.io._resume import StaleOutputError, differences, file_digest, fingerprint

FRONTEND = "ORB-SLAM3 v1.0 + jsve hook"
"""The logs' `frontend` metadata."""

MAX_SEED = 2**32 - 2
"""The largest seed the driver takes (it seeds glibc's rand with seed + 1: srand treats 0 as 1)."""

MODES = ("paced", "no-wait", "lockstep")
"""How the driver feeds frames (module docstring)."""

RUN_FILES = (".csv", ".csv.partial", ".orbslam3.txt", ".orbslam3-euroc.txt", ".saved-from-log.txt",
             ".summary.json", ".console.txt", ".keypoints.csv", ".keypoints.csv.partial")  # fmt: skip
"""The files of one run (suffixes of run_<k>), cleared before it runs again."""


SENSORS = {"imu-monocular": "imu_monocular", "monocular": "monocular"}
"""The driver's --sensor values (ORB-SLAM3's IMU_MONOCULAR and MONOCULAR) and the logs' `sensor` metadata."""

MASK_FOLDER = Path("mav0") / "cam0" / "masks"
"""Where a dataset keeps its masks: one 16-bit instance map per image, named as the image (.png)."""


@dataclasses.dataclass(frozen=True)
class Dataset:
    """An EuRoC-format dataset and what its manifest says it is."""

    path: Path
    sequence: str
    disturbance: str
    level: float


def describe_dataset(path: Path) -> Dataset:
    """Sequence, disturbance and level of a dataset from its manifest: `jsve disturb`'s
    (jsve_manifest.json) names the disturbance and its source; `jsve render`'s (jsve_render.json) an
    undisturbed sequence. Without either, the folder's name and no disturbance.

    Raises:
        ValueError naming the folder when it holds no mav0/cam0/data.csv.
    """
    path = Path(path)
    if not (path / "mav0" / "cam0" / "data.csv").is_file():
        raise ValueError(f"{path}: not a EuRoC-format dataset (no mav0/cam0/data.csv)")
    disturbed = path / "jsve_manifest.json"
    if disturbed.is_file():
        m = json.loads(disturbed.read_text())
        source = describe_dataset(Path(m["source"])) if Path(m["source"]).is_dir() else None
        sequence = source.sequence if source else str(m.get("dataset", path.name))
        return Dataset(path, sequence, str(m["disturbance"]), float(m["level"]))
    rendered = path / "jsve_render.json"
    if rendered.is_file():
        m = json.loads(rendered.read_text())
        sequence = m.get("sequence") or Path(str(m.get("trajectory", path.name))).stem.removesuffix("_GT")
        return Dataset(path, str(sequence), "none", 0.0)
    return Dataset(path, path.name, "none", 0.0)


def mask_files(dataset: Path) -> list[Path]:
    """The mask of every image of a dataset, in the order of mav0/cam0/data.csv: MASK_FOLDER/<the image's
    name, extension .png>, as the driver's --masks reads them.

    Raises:
        ValueError naming the first missing mask and how many are missing: a frame without its mask
        would go unmasked.
    """
    folder = dataset / MASK_FOLDER
    names = []
    for line in (dataset / "mav0" / "cam0" / "data.csv").read_text().splitlines():
        fields = line.split(",")
        if line.strip() and not line.startswith("#") and len(fields) >= 2:
            names.append(Path(fields[1].strip()).stem + ".png")
    present = {p.name for p in folder.iterdir()} if folder.is_dir() else set()
    missing = [name for name in names if name not in present]
    if missing:
        raise ValueError(
            f"{folder / missing[0]}: no mask ({len(missing)} of the {len(names)} images have none); "
            "--masks needs one 16-bit instance map per image"
        )
    return [folder / name for name in names]


def scaled_settings(settings: str, width: int, height: int) -> str | None:
    """ORB-SLAM3's settings text for images of `width` x `height` (a downsampled dataset): pinhole
    intrinsics and sizes scaled; None when the settings already describe that size."""
    import cv2

    fs = cv2.FileStorage(settings, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    w0, h0 = int(fs.getNode("Camera.width").real()), int(fs.getNode("Camera.height").real())
    if (w0, h0) == (width, height):
        return None
    sx, sy = width / w0, height / h0
    scale = {"Camera1.fx": sx, "Camera1.cx": sx, "Camera.width": sx, "Camera.newWidth": sx,
             "Camera1.fy": sy, "Camera1.cy": sy, "Camera.height": sy, "Camera.newHeight": sy}  # fmt: skip
    lines = []
    for line in settings.splitlines():
        key = line.split(":", 1)[0].strip()
        if key in scale and ":" in line:
            value = float(line.split(":", 1)[1].split("#", 1)[0])
            new = value * scale[key]
            text = str(round(new)) if key.startswith("Camera.") else repr(new)
            line = f"{key}: {text}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def camera_in_body(settings: str) -> list[float] | None:
    """T_bc, the camera pose in the body (IMU) frame, from ORB-SLAM3 settings text (`IMU.T_b_c1`, a 4 x 4
    matrix) as the log's metadata `camera_in_body`: [qw, qx, qy, qz, tx, ty, tz] (m); None without it."""
    import cv2
    import numpy as np

    from jsve.core._geometry import matrix_to_quat, quat_normalize

    fs = cv2.FileStorage(settings, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    node = fs.getNode("IMU.T_b_c1")
    if node.empty():
        return None
    t_bc = np.asarray(node.mat(), np.float64)
    q = quat_normalize(matrix_to_quat(t_bc[:3, :3], xp=np), xp=np)
    return [float(x) for x in q] + [float(x) for x in t_bc[:3, 3]]


def orb_features(settings: str) -> int:
    """ORBextractor.nFeatures of ORB-SLAM3 settings text (the log's `n_features`; 1000 when absent)."""
    import cv2

    fs = cv2.FileStorage(
        settings, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
    )  # alive while its node is read
    node = fs.getNode("ORBextractor.nFeatures")
    return 1000 if node.empty() else int(node.real())


def image_size(dataset: Path) -> tuple[int, int]:
    """(width, height) of the dataset's first image."""
    import cv2

    first = sorted((dataset / "mav0" / "cam0" / "data").iterdir())[0]
    im = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise ValueError(f"{first}: not an image")
    return im.shape[1], im.shape[0]


RECORD_THRESHOLDS = {"imu_init": 1.0, "not_init": 1.0, "reloc": 1.0, "recovery": 0.0}
"""The `record` rule: ORB-SLAM3's test failing only a frame without a single inlier match and recovering
on the first frame with one (docs/frontend.md section 6): its logs support every stricter rule."""


def record_rule():
    """The permissive recording rule (RECORD_THRESHOLDS) as a jsve Rule."""
    from jsve.core._rules import InlierRule, Thresholds

    return InlierRule(Thresholds(**RECORD_THRESHOLDS))


def driver_rule(name: str, rule, switch_model: str, n_features: int = 1000) -> tuple[list[str], str]:
    """The driver's arguments for running `rule` in the loop, and the log's `rule` metadata.

    `name` "orbslam3" under "orbslam3" runs ORB-SLAM3's own test untouched (no arguments); any other
    rule (the inlier family, or the SVE family with any of its inputs), or "imu-coast", replaces it
    through the hook. Returns (arguments, metadata `rule`: the preset name "orbslam3", else
    rule_to_dict's object as JSON text, which jsve check reads back).
    """
    from jsve.core._rules import rule_kind, rule_to_dict

    spec = rule_to_dict(rule)
    meta = name if name == "orbslam3" else json.dumps(spec, sort_keys=True)
    if name == "orbslam3" and switch_model == "orbslam3":
        return [], meta
    t = spec["thresholds"]
    numbers = [float(t[k]) for k in ("imu_init", "not_init", "reloc", "recovery")]
    if rule_kind(rule) == "inliers":
        args = ["--rule-inliers", ",".join(map(repr, numbers))]
    else:
        c = spec["combination"]
        numbers = [float(c[k]) for k in ("w_a", "u_b", "p", "q", "rho")] + numbers
        inputs = c.get("inputs", "jsve")
        args = ["--rule-sve", ",".join([inputs, *map(repr, numbers)]), "--n-features", str(n_features)]
    return args + (["--coast"] if switch_model == "imu-coast" else []), meta


@dataclasses.dataclass(frozen=True)
class RunJob:
    dataset: Dataset
    run: int
    log: Path
    settings: Path
    meta: dict
    rule_args: tuple[str, ...] = ()
    mode: str = "paced"
    seed: int | None = None  # the driver's --seed; None: ORB-SLAM3's own (0)
    sensor: str = "imu-monocular"  # one of SENSORS
    masks: bool = False  # the dataset's masks in the loop
    keypoints: bool = False  # write run_<k>.keypoints.csv


def driver_args(job: RunJob, gate_timeout_s: float = DEFAULT_GATE_TIMEOUT_S) -> list[str]:
    """The driver's options for the job's mode, seed, sensor, masks and keypoints (none for a default: a
    run's command, and with it its heap, holds only the options it uses)."""
    args = {
        "paced": [],
        "no-wait": ["--no-wait"],
        "lockstep": ["--lockstep", "--gate-timeout", repr(gate_timeout_s)],
    }
    return (
        args[job.mode]
        + ([] if job.seed is None else ["--seed", str(job.seed)])
        + ([] if job.sensor == "imu-monocular" else ["--sensor", job.sensor])
        + (["--masks"] if job.masks else [])
        + (["--keypoints"] if job.keypoints else [])
    )


def driver_command(
    driver: Path, vocabulary: Path, job: RunJob, gate_timeout_s: float = DEFAULT_GATE_TIMEOUT_S
) -> list[str]:
    """The driver's command line for `job`: its files beside the log (run_<k>.orbslam3.txt,
    run_<k>.summary.json), metadata, rule, mode and seed."""
    stem = job.log.with_suffix("")
    return [
        str(driver), "--vocabulary", str(vocabulary), "--settings", str(job.settings),
        "--sequence", str(job.dataset.path), "--log", str(job.log), "--overwrite",
        "--trajectory", f"{stem}.orbslam3.txt", "--summary", str(stem.with_suffix(".summary.json")),
        *_meta_args(job.meta), *job.rule_args, *driver_args(job, gate_timeout_s),
    ]  # fmt: skip


def outcome(exit_code: int, timed_out: bool = False) -> str:
    """What a driver's exit status says of its run: ok, failed (the run or its log), bad_input,
    gate_timeout (lockstep), timeout (stopped by `timeout_s`), or the signal that ended it
    (SIGKILL: e.g. the kernel's out-of-memory killer; SIGSEGV, SIGABRT: a crash)."""
    if timed_out:
        return "timeout"
    if exit_code < 0:
        try:
            return signal.Signals(-exit_code).name
        except ValueError:
            return f"signal {-exit_code}"
    return {0: "ok", 1: "failed", 2: "bad_input", 3: "gate_timeout"}.get(exit_code, f"exit {exit_code}")


def _meta_args(meta: dict) -> list[str]:
    args = []
    for key, value in meta.items():
        # a string in double quotes stays a string in the driver, which takes the text between them
        # as it is (no JSON escapes); lists as JSON; numbers as numbers
        if isinstance(value, str):
            text = f'"{value}"'
        else:
            text = json.dumps(value, separators=(",", ":")) if isinstance(value, list) else repr(value)
        args += ["--meta", f"{key}={text}"]
    return args


def run_one(
    driver: Path,
    vocabulary: Path,
    job: RunJob,
    timeout_s: float | None = None,
    wait: bool = True,
    gate_timeout_s: float = DEFAULT_GATE_TIMEOUT_S,
) -> dict:
    """One run of the driver; returns its summary (plus `outcome`, `exit_code`, `wall_seconds`, `log`).

    The run holds run_<k>.lock, which its driver inherits: an earlier attempt still running (its
    command killed) is waited for, never overlapped, and a run another command finished meanwhile is
    not run again. The run's old files are cleared first, and the summary is written last, atomically.
    `wait` False turns a paced job into a no-wait one (the mode's default is the job's).
    """
    stem = job.log.with_suffix("")
    summary_path = stem.with_suffix(".summary.json")
    mode = "no-wait" if (job.mode == "paced" and not wait) else job.mode
    cmd = driver_command(driver, vocabulary, dataclasses.replace(job, mode=mode), gate_timeout_s)
    lock_path = Path(f"{stem}.lock")
    lock = os.open(lock_path, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        finished = finished_summary(job.log, job.meta["generator"])
        if finished is not None and finished.get("exit_code") == 0:
            return finished  # finished while this run waited for the lock (another command's attempt)
        for suffix in RUN_FILES:
            Path(f"{stem}{suffix}").unlink(missing_ok=True)
        start = time.monotonic()
        timed_out = False
        with open(f"{stem}.console.txt", "w") as out, canonical_paths(cmd) as (cwd, canonical):
            proc = subprocess.Popen(
                canonical, stdout=out, stderr=subprocess.STDOUT, pass_fds=(lock,), cwd=cwd
            )
            try:
                code = proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                code, timed_out = proc.wait(), True
        summary = _driver_summary(summary_path)
        summary.update(outcome=outcome(code, timed_out), exit_code=code,
                       wall_seconds=round(time.monotonic() - start, 2), log=str(job.log),
                       generator=job.meta["generator"])  # fmt: skip
        trajectory = Path(f"{stem}.orbslam3.txt")
        if code == 0 and trajectory.is_file():
            write_euroc_trajectory(trajectory, Path(f"{stem}.orbslam3-euroc.txt"))
        summary.update(saved_trajectory_scores(job.log, job.dataset.path))
        _write_atomically(summary_path, json.dumps(summary, indent=2) + "\n")
        lock_path.unlink(missing_ok=True)  # still held: a waiter on it finds the run finished
    finally:
        os.close(lock)
    return summary


PATH_OPTIONS = {"--vocabulary": "v", "--settings": "s", "--sequence": "d"}
"""The driver's input paths and their names in `canonical_paths`' folder; the outputs go under "o"."""


@contextlib.contextmanager
def canonical_paths(cmd: list[str]) -> Iterator[tuple[str, list[str]]]:
    """The driver's command with every path of the same length wherever the files are: a fresh folder of
    fixed-length name holds links v, s, d (vocabulary, settings, dataset) and o (the output folder), and
    the driver runs there. A lockstep run's heap, by whose addresses ORB-SLAM3 orders keyframes and map
    points, then does not depend on where its inputs and outputs are (docs/frontend.md)."""
    out_options = ("--log", "--trajectory", "--summary", "--branch-log", "--branch-summary")  # one folder
    with tempfile.TemporaryDirectory(prefix="jsve-run-") as tmp:
        folder = Path(tmp)
        canonical = [str(Path(cmd[0]).absolute()), *cmd[1:]]  # the driver runs in the folder
        for i, arg in enumerate(cmd[:-1]):
            if arg in PATH_OPTIONS:
                name = PATH_OPTIONS[arg] + Path(cmd[i + 1]).suffix  # OpenCV reads settings by their suffix
                (folder / name).symlink_to(Path(cmd[i + 1]).absolute())
                canonical[i + 1] = name
            elif arg in out_options:
                out = folder / "o"
                if not out.exists():
                    out.symlink_to(Path(cmd[i + 1]).parent.absolute())
                canonical[i + 1] = str(Path("o") / Path(cmd[i + 1]).name)
        yield tmp, canonical


def _driver_summary(path: Path) -> dict:
    """The driver's summary; {} when it wrote none or was stopped while writing it."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def _write_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as stream:
        stream.write(text)
        stream.flush()
        os.fsync(stream.fileno())
    tmp.replace(path)


def saved_trajectory_scores(log: Path, dataset: Path) -> dict:
    """What a run's summary says of its saved trajectory: ORB-SLAM3's own file and the one jsve rebuilds
    from the log (written beside it as `run_<k>.saved-from-log.txt`, EuRoC CSV), each scored against the
    dataset's ground truth as `jsve ape --align se3` does, their difference (a mismatch is a defect of
    the hook or the rebuild), the share of frames saved and the run's events.

    Returns:
        {} where the log is incomplete; `saved_trajectory_error` where the log or a trajectory cannot be
        read; else `events` and, as far as they exist, `saved_coverage`, `ate_saved_file_m`,
        `ate_from_log_m`, `ate_difference_m` (None where a part is missing).
    """
    from jsve.io._errors import LogFormatError, TrajectoryFileError
    from jsve.io._logs import read_log

    if not log.is_file():
        return {}
    try:
        return _scores(read_log(log), log, dataset)
    except (LogFormatError, TrajectoryFileError) as error:  # an outcome of the run, recorded, never a crash
        # named by the log's file name: a summary reads the same wherever the run's folder is
        return {"saved_trajectory_error": str(error).replace(f"{log.parent}{os.sep}", "")}


def _scores(run, log: Path, dataset: Path) -> dict:
    from jsve.io._saved_trajectory import euroc_ate, event_counts, saved_trajectory, write_euroc

    # A monocular run has no metric scale: its trajectories are scored after a similarity (sim3).
    align = "sim3" if run.meta.get("sensor") == SENSORS["monocular"] else "se3"
    out: dict = {"events": event_counts(run), "ate_align": align}
    if not run.has_keyframes or run.trailers is None:
        return out
    saved = saved_trajectory(run)
    gt = dataset / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    file = Path(f"{log.with_suffix('')}.orbslam3-euroc.txt")
    rebuilt = Path(f"{log.with_suffix('')}.saved-from-log.txt")
    out.update(saved_coverage=None if saved is None else round(saved.coverage, 6), ate_saved_file_m=None,
               ate_from_log_m=None, ate_difference_m=None)  # fmt: skip
    if saved is None or len(saved.rows) == 0 or not gt.is_file():
        return out
    write_euroc(saved.t_ns, saved.pose, rebuilt)
    out["ate_from_log_m"] = euroc_ate(gt, rebuilt, align)[0]
    if file.is_file():
        out["ate_saved_file_m"] = euroc_ate(gt, file, align)[0]
        out["ate_difference_m"] = abs(out["ate_saved_file_m"] - out["ate_from_log_m"])
    return out


def write_euroc_trajectory(orbslam3: Path, out: Path) -> None:
    """ORB-SLAM3's SaveTrajectoryEuRoC file (`t x y z qx qy qz qw`, t = 1e9 x the double stamp, printed
    with 6 decimals) as a EuRoC CSV (`t_ns,x,y,z,qw,qx,qy,qz`). The stamp went through a double, so it
    is the frame's to within ~130 ns; association tolerates far more."""
    rows = ["#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []"]
    for n, line in enumerate(orbslam3.read_text().splitlines(), 1):
        fields = line.split()
        if len(fields) != 8:
            raise ValueError(f"{orbslam3}:{n}: {len(fields)} fields, expected 8 (t x y z qx qy qz qw)")
        t, x, y, z, qx, qy, qz, qw = fields
        rows.append(",".join([str(round(float(t))), x, y, z, qw, qx, qy, qz]))
    out.write_text("\n".join(rows) + "\n")


def _recorded_generator(log: Path) -> str | None:
    """The `generator` key in a log's line-1 metadata (`# jsve-log v3 {...}`), None when it has none
    or line 1 is not a jsve log's."""
    from jsve.io import schema

    with open(log, encoding="utf-8-sig") as stream:
        line = stream.readline()
    magic = next((m for m in schema.MAGICS.values() if line.startswith(m)), None)
    if magic is None:
        return None
    try:
        return json.loads(line[len(magic) :]).get("generator")
    except json.JSONDecodeError:
        return None


def finished_summary(log: Path, key: str) -> dict | None:
    """The summary of a finished run at `log` under `key`, or None when the run is still to do.

    A run is finished once run_one has written its summary (last, atomically; the driver's own
    summary, in the same file until then, has no `exit_code`) and it names `key`; a successful one
    also has its complete log. Summaries written before they carried the key
    are matched by the generator in the log's (or the partial log's) first line.
    """
    summary = _driver_summary(log.with_suffix(".summary.json"))
    if "exit_code" not in summary:
        return None  # none, or only the driver's own (run_one had not yet added the outcome)
    partial = log.with_name(log.name + ".partial")
    header = log if log.is_file() else partial
    recorded = summary.get("generator") or (_recorded_generator(header) if header.is_file() else None)
    if recorded != key:
        return None
    if summary.get("exit_code", 0) == 0 and not log.is_file():
        return None  # a summary without its log: not a finished run
    return summary


def plan(
    build: Path,
    datasets: Sequence[Path],
    *,
    runs: int,
    out: Path,
    vocabulary: Path,
    settings: Path,
    rule: tuple[str, object] | None = None,
    switch_model: str = "orbslam3",
    force: bool = False,
    retry_failed: bool = False,
    mode: str = "paced",
    seed: int | None = None,
    sensor: str = "imu-monocular",
    masks: bool = False,
    keypoints: bool = False,
) -> tuple[list[RunJob], list[Path]]:
    """The runs still to do and the runs already done under the same key (`finished_summary`): complete
    logs, and the logs of attempts that ended in a crash, a timeout or a closed gate (their `.csv`
    path, which does not exist), which are outcomes and run again only with `retry_failed`.

    `mode`: one of MODES. `seed`: run k draws from seed + k (lockstep's default: 0, so that run k has
    seed k); None outside lockstep keeps ORB-SLAM3's own seed for every run.

    `rule`: (name, jsve Rule) run in the loop (default: ORB-SLAM3's own); `switch_model` "orbslam3" or
    "imu-coast" (a failed frame keeps the pose TrackLocalMap started from). Logs go under
    OUT/<sequence>/<disturbance>-<level>/, in a <rule>-<switch model> subfolder unless the rule is
    ORB-SLAM3's own under "orbslam3".

    `sensor`: one of SENSORS; "monocular" runs ORB-SLAM3's own rule only (jsve's rules replace the
    IMU_MONOCULAR test). `masks`: every dataset's MASK_FOLDER in the loop (`mask_files`). `keypoints`:
    each run writes its keypoint side file. The three are part of a run's key: masked and unmasked
    runs, or the two sensors, go to separate output folders.

    Raises:
        StaleOutputError when a complete log was made from other inputs (unless `force`).
        ValueError when two datasets would write the same logs (same sequence, disturbance and level
        in their manifests): their runs would overwrite each other; a sensor that is not in SENSORS, a
        rule other than ORB-SLAM3's own in a monocular run, a dataset without its masks.
    """
    from jsve.core._machine import check_switch_model
    from jsve.core._rules import preset

    check_switch_model(switch_model)
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    if mode == "lockstep" and seed is None:
        seed = 0
    if seed is not None and not 0 <= seed <= MAX_SEED - max(runs - 1, 0):
        raise ValueError(f"seed {seed}: runs 0..{runs - 1} need seeds in [0, {MAX_SEED}]")
    if sensor not in SENSORS:
        raise ValueError(f"sensor {sensor!r}: expected one of {', '.join(SENSORS)}")
    name, rule_obj = rule if rule is not None else ("orbslam3", preset("orbslam3"))
    if sensor == "monocular" and (name != "orbslam3" or switch_model != "orbslam3"):
        raise ValueError(
            f"rule {name!r} under {switch_model!r}: a monocular run tracks with ORB-SLAM3's own rule only "
            "(jsve's rules and replay model the IMU_MONOCULAR success test)"
        )
    settings_text = settings.read_text()
    n_features = orb_features(settings_text)
    rule_args, rule_meta = driver_rule(name, rule_obj, switch_model, n_features)
    stock = not rule_args
    base_key = {
        "hook": json.loads((build / "build.json").read_text())["hook_sha256"][:16],
        "vocabulary": file_digest([vocabulary]),
        "settings": file_digest([settings]),
        "rule": rule_meta,
        "switch_model": switch_model,
    }
    if mode == "lockstep" or seed is not None:  # paced runs of ORB-SLAM3's own seed keep their keys
        base_key.update(mode=mode, seed=seed)
    for key, value, default in (("sensor", sensor, "imu-monocular"), ("keypoints", keypoints, False)):
        if value != default:  # a default run's key does not name options it does not use
            base_key[key] = value
    # the vis_* poses of a monocular run are the camera's own: no body frame to move them as
    t_bc = camera_in_body(settings_text) if sensor == "imu-monocular" else None
    todo, done = [], []
    folders: dict[Path, Path] = {}
    for path in datasets:
        ds = describe_dataset(path)
        folder = out / ds.sequence / f"{ds.disturbance}-{ds.level:g}"
        if folders.get(folder) == ds.path.resolve():
            continue  # named twice: one dataset, planned once
        if folder in folders:
            raise ValueError(
                f"{folders[folder]} and {ds.path}: both are {ds.sequence}, {ds.disturbance} {ds.level:g} by "
                f"their manifests, so their runs would write the same logs under {folder}; run them into "
                "separate output folders"
            )
        folders[folder] = ds.path.resolve()
        if not stock:
            folder = folder / f"{name}-{switch_model}"
        folder.mkdir(parents=True, exist_ok=True)
        width, height = image_size(ds.path)
        own = scaled_settings(settings_text, width, height)
        run_settings = settings
        if own is not None:
            run_settings = folder / "orbslam3_settings.yaml"
            run_settings.write_text(own)
        data_key = file_digest(sorted((ds.path / "mav0").rglob("*.csv")))
        key_parts = {**base_key, "data": data_key, "dataset": str(ds.path.resolve())}
        if masks:
            key_parts["masks"] = file_digest(mask_files(ds.path))
        key = fingerprint(key_parts)
        for k in range(runs):
            log = folder / f"run_{k:03d}.csv"
            if log.is_file() and (recorded := _recorded_generator(log)) != key and not force:
                raise StaleOutputError(
                    folder, differences({"generator": recorded}, {"generator": key}) + f" in {log.name}"
                )
            finished = finished_summary(log, key)
            if finished is not None and (finished.get("exit_code", 0) == 0 or not retry_failed):
                done.append(log)
                continue
            meta = {
                "sequence": ds.sequence, "run": k, "fps": 20.0, "sensor": SENSORS[sensor],
                "n_features": n_features, "image_size": [width, height], "grid": [8, 8], "frontend": FRONTEND,
                "disturbance": ds.disturbance, "level": ds.level, "rule": rule_meta,
                "switch_model": switch_model, "rule_name": name, "generator": key,
            }  # fmt: skip
            if seed is not None:
                meta.update(mode=mode, seed=seed + k)
            if t_bc is not None:
                meta["camera_in_body"] = t_bc
            todo.append(RunJob(ds, k, log, run_settings, meta, tuple(rule_args), mode,
                               None if seed is None else seed + k, sensor, masks, keypoints))  # fmt: skip
    return todo, done


def run_all(
    build: Path,
    jobs: Sequence[RunJob],
    vocabulary: Path,
    *,
    workers: int = 1,
    timeout_s: float | None = None,
    wait: bool = True,
    progress: bool = True,
    scheduler: str | None = None,
    gate_timeout_s: float = DEFAULT_GATE_TIMEOUT_S,
) -> list[dict]:
    """Run `jobs` with `workers` drivers at once (each ORB-SLAM3 runs three threads); summaries in order.

    `scheduler` (jsve.io._scheduler): "local" (the default) and "processes" start the drivers from
    threads of this process (each driver is its own process, so a LocalCluster would add only idle
    Python processes); a Dask scheduler's address runs each driver on a worker of that cluster, which
    must see BUILD, the vocabulary, the datasets and the output folder under the same absolute paths.
    """
    from tqdm.auto import tqdm

    scheduler = _scheduler.check_scheduler(scheduler)
    driver = build / "bin" / "jsve_orbslam3"
    if not driver.is_file():
        raise FileNotFoundError(f"{driver}: no driver; run `jsve frontend build -o {build}` first")
    tasks = list(jobs)
    if _scheduler.is_cluster(scheduler):  # a worker does not share this process's working folder
        driver, vocabulary = driver.absolute(), vocabulary.absolute()
        tasks = [
            dataclasses.replace(
                job,
                dataset=dataclasses.replace(job.dataset, path=job.dataset.path.absolute()),
                log=job.log.absolute(),
                settings=job.settings.absolute(),
            )
            for job in jobs
        ]
    results: list[dict] = [{} for _ in jobs]
    with _scheduler.executor(max(1, workers), scheduler, threads=True) as pool:
        run = functools.partial(
            run_one, driver, vocabulary, timeout_s=timeout_s, wait=wait, gate_timeout_s=gate_timeout_s
        )
        futures = {pool.submit(run, job): i for i, job in enumerate(tasks)}
        with tqdm(total=len(jobs), desc="frontend runs", unit="run", disable=not progress) as bar:
            for future in concurrent.futures.as_completed(futures):
                i = futures[future]
                results[i] = {**future.result(), "log": str(jobs[i].log)}
                bar.update()
    return results
