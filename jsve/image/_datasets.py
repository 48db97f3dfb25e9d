"""Disturbed copies of EuRoC-format datasets, written atomically and resumably (an I/O edge of jsve).

`disturb_datasets` writes one dataset per (source, disturbance, level) under
`OUT/<source name>/<disturbance>-<level>[_<param>=<value>...]`, every camera frame passed through
jsve.image._disturb's registered image function. Each is built in a sibling folder ending in `.partial` and
renamed when complete, with a manifest (`jsve_manifest.json`) written last; a re-run skips finished
datasets made under the same key (generator_key: the source's path and content, disturbance, level,
parameters and seed; recorded in the manifest), stops with StaleOutputError at a dataset of another key
(or, with force, deletes and rewrites it), and discards stale `.partial` folders.

Also the EuRoC reading helpers jsve.image._measure shares (`camera_dirs`, `read_frame_list`,
`read_yaml_list`) and the process pool of both (`run_parallel`).
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import json
import logging
import os
import re
import shutil
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from jsve.image._disturb import (
    DISTURBANCES,
    _check_parameters,
    disturb_image,
    disturbance_parameters,
    scale_intrinsics,
)
from jsve.io import _atomic as atomic
from jsve.io import _scheduler
from jsve.io._resume import StaleOutputError, differences, stop_if_stale

# The name users configure for the disturbance tools' messages (jsve disturb).
logger = logging.getLogger(__name__)

MANIFEST_NAME = "jsve_manifest.json"
"""File name of the manifest inside every written dataset; its presence marks the dataset finished."""

PARTIAL_SUFFIX = ".partial"
"""Suffix of the folder a dataset is built in before it is renamed into place."""

MANIFEST_VERSION = 1

IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


class DatasetError(Exception):
    """A dataset folder that cannot be read or written; the message names the path."""


@dataclass(frozen=True)
class Job:
    """One dataset to write: `source` disturbed by `name` at `level` into `target`.

    `source_hash` is content_hash(source)'s digest, computed once per source by disturb_datasets (None:
    computed when needed)."""

    source: Path
    target: Path
    name: str
    level: float
    parameters: tuple[tuple[str, object], ...]
    seed: int
    source_hash: str | None = None


@dataclass(frozen=True)
class JobResult:
    """What happened to one job: status "written", "skipped" (finished before) or "redone" (stale partial)."""

    target: Path
    status: str
    manifest: dict


def format_level(level: float) -> str:
    """Level as it appears in folder names: 15 -> "15", 0.9 -> "0.9", 0.05 -> "0.05"."""
    return f"{float(level):g}"


def dataset_dir_name(name: str, level: float, parameters: Mapping[str, object] | None = None) -> str:
    """`<name>-<level>`, with `_<param>=<value>` appended for every parameter not at its default."""
    defaults = disturbance_parameters(name)
    parts = [f"{name}-{format_level(level)}"]
    for key, value in sorted(_check_parameters(name, parameters).items()):
        if value != defaults[key]:
            parts.append(f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}")
    return "_".join(parts)


def _mav0(dataset: Path) -> Path:
    dataset = Path(dataset)
    if (dataset / "mav0").is_dir():
        return dataset / "mav0"
    raise DatasetError(f"{dataset}: not a EuRoC dataset folder (no mav0/ inside)")


def camera_dirs(dataset: Path) -> list[Path]:
    """The camera folders mav0/cam*/ of a EuRoC dataset that hold data/ and data.csv, sorted."""
    mav0 = _mav0(dataset)
    cams = sorted(p for p in mav0.glob("cam*") if (p / "data").is_dir() and (p / "data.csv").is_file())
    if not cams:
        raise DatasetError(f"{mav0}: no camera folder with data/ and data.csv")
    return cams


def read_frame_list(cam_dir: Path) -> list[tuple[int, str]]:
    """(t_ns, file name) per frame from a EuRoC camera's data.csv, in file order."""
    path = Path(cam_dir) / "data.csv"
    frames = []
    with open(path, encoding="utf-8") as stream:
        for lineno, line in enumerate(stream, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = [f.strip() for f in line.split(",")]
            try:
                frames.append((int(fields[0]), fields[1]))
            except (ValueError, IndexError) as error:
                raise DatasetError(f"{path}:{lineno}: expected `t_ns,filename`, got {line!r}") from error
    return frames


_FLOW_LIST = r"^(?P<key>{key})\s*:\s*\[(?P<values>[^\]]*)\](?P<rest>.*)$"


def read_yaml_list(text: str, key: str) -> list[float] | None:
    """The numbers of a one-line flow list `key: [a, b, ...]` in an EuRoC sensor.yaml, or None."""
    match = re.search(_FLOW_LIST.format(key=re.escape(key)), text, flags=re.MULTILINE)
    if match is None:
        return None
    return [float(v) for v in match.group("values").split(",") if v.strip()]


def rescale_sensor_yaml(text: str, target_size: tuple[int, int]) -> str:
    """sensor.yaml text with `resolution` set to target_size and `intrinsics` scaled to match.

    Everything else (comments, extrinsics, distortion) is kept byte for byte.
    """
    resolution = read_yaml_list(text, "resolution")
    intrinsics = read_yaml_list(text, "intrinsics")
    if resolution is None or intrinsics is None or len(resolution) != 2 or len(intrinsics) != 4:
        raise DatasetError("sensor.yaml: need `resolution: [w, h]` and `intrinsics: [fu, fv, cu, cv]`")
    source_size = (int(resolution[0]), int(resolution[1]))
    scaled = scale_intrinsics(intrinsics, source_size, target_size)

    def replace(key: str, values: str, text: str) -> str:
        pattern = _FLOW_LIST.format(key=re.escape(key))
        return re.sub(
            pattern,
            lambda m: f"{m.group('key')}: [{values}]{m.group('rest')}",
            text,
            count=1,
            flags=re.MULTILINE,
        )

    text = replace("resolution", f"{target_size[0]}, {target_size[1]}", text)
    return replace("intrinsics", ", ".join(f"{v:.9g}" for v in scaled), text)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def content_hash(folder: Path, exclude: Iterable[str] = (MANIFEST_NAME,)) -> tuple[str, int]:
    """sha256 over every file's relative path and bytes, in sorted path order; and the file count."""
    folder = Path(folder)
    exclude = set(exclude)
    files = sorted(
        p for p in folder.rglob("*") if p.is_file() and p.relative_to(folder).as_posix() not in exclude
    )
    total = hashlib.sha256()
    for path in files:
        total.update(path.relative_to(folder).as_posix().encode())
        total.update(b"\0")
        digest = hashlib.sha256()
        with open(path, "rb") as stream:
            for chunk in iter(lambda: stream.read(1 << 20), b""):
                digest.update(chunk)
        total.update(digest.digest())
    return "sha256:" + total.hexdigest(), len(files)


def read_manifest(dataset: Path) -> dict | None:
    """The manifest of a written dataset, or None when it has none."""
    path = Path(dataset) / MANIFEST_NAME
    if not path.is_file():
        return None
    with open(path, encoding="utf-8") as stream:
        return json.load(stream)


def generator_key(job: Job) -> dict:
    """What a disturbed dataset is a function of: the source (resolved path and content hash: every
    file's bytes, so an edited or replaced image counts), the disturbance, its level and its parameters
    with the seed. The manifest records each; a finished dataset is kept only under an equal key."""
    source = Path(job.source)
    key = {
        "source": str(source.resolve()),
        "source_hash": job.source_hash or content_hash(source)[0],
        "disturbance": job.name,
        "level": job.level,
        "parameters": {**disturbance_parameters(job.name), **dict(job.parameters), "seed": job.seed},
    }
    return json.loads(json.dumps(key))  # as the manifest reads back (tuples as lists)


def _stale(job: Job, manifest: dict) -> str | None:
    """What differs between a finished dataset's manifest and the job's key, or None."""
    key = generator_key(job)
    recorded = {k: manifest[k] for k in key if k in manifest}
    return None if recorded == key else differences(recorded, key)


def _jsve_version() -> str:
    try:
        from importlib.metadata import version

        return version("jsve")
    except Exception:  # not installed (running from a checkout)
        from jsve._version import __version__

        return __version__


def _write_dataset(job: Job, partial: Path) -> dict:
    source = Path(job.source)
    parameters = dict(job.parameters)
    partial.mkdir(parents=True)
    cams = camera_dirs(source)
    cam_names = {cam.relative_to(source).as_posix() for cam in cams}
    # Everything outside the camera folders (IMU, ground truth, body.yaml, licence) is linked untouched.
    for path in sorted(source.rglob("*")):
        rel = path.relative_to(source)
        if any(rel.as_posix() == c or rel.as_posix().startswith(c + "/") for c in cam_names):
            continue
        if path.is_dir():
            (partial / rel).mkdir(parents=True, exist_ok=True)
        elif path.is_file():
            (partial / rel).parent.mkdir(parents=True, exist_ok=True)
            _link_or_copy(path, partial / rel)
    n_frames = {}
    for cam_index, cam in enumerate(cams):
        rel_cam = cam.relative_to(source)
        out_cam = partial / rel_cam
        (out_cam / "data").mkdir(parents=True, exist_ok=True)
        for path in sorted(cam.rglob("*")):
            rel = path.relative_to(cam)
            if rel.parts[0] == "data" or rel.as_posix() == "sensor.yaml":
                continue
            if path.is_dir():
                (out_cam / rel).mkdir(parents=True, exist_ok=True)
            elif path.is_file():
                (out_cam / rel).parent.mkdir(parents=True, exist_ok=True)
                _link_or_copy(path, out_cam / rel)
        frames = read_frame_list(cam)
        sizes = set()
        for t_ns, filename in frames:
            image = cv2.imread(str(cam / "data" / filename), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise DatasetError(f"{cam / 'data' / filename}: cannot read image listed in data.csv")
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            if image.dtype != np.uint8:
                raise DatasetError(f"{cam / 'data' / filename}: expected an 8-bit image, got {image.dtype}")
            out = disturb_image(
                image,
                job.name,
                job.level,
                parameters,
                seed=(job.seed, cam_index),
                frame_seed=(job.seed, cam_index, t_ns),
            )
            sizes.add((image.shape[1], image.shape[0], out.shape[1], out.shape[0]))
            if not cv2.imwrite(str(out_cam / "data" / filename), out):
                # OpenCV says no more than False (a full disk, a read-only folder)
                raise atomic.OutputError(
                    None, "OpenCV could not write the image", str(out_cam / "data" / filename)
                )
        # Images not listed in data.csv are not part of the sequence and are not written.
        sensor = cam / "sensor.yaml"
        if sensor.is_file():
            resized = {(w1, h1) for w0, h0, w1, h1 in sizes if (w0, h0) != (w1, h1)}
            if resized:
                if len(resized) > 1:
                    raise DatasetError(f"{cam}: frames of different sizes after {job.name}")
                text = rescale_sensor_yaml(sensor.read_text(encoding="utf-8"), resized.pop())
                (out_cam / "sensor.yaml").write_text(text, encoding="utf-8")
            else:
                shutil.copy2(sensor, out_cam / "sensor.yaml")
        n_frames[rel_cam.as_posix()] = len(frames)
    digest, file_count = content_hash(partial)
    manifest = {
        "jsve_manifest": MANIFEST_VERSION,
        **generator_key(job),
        "dataset": source.name,
        "unit": DISTURBANCES[job.name].unit,
        "jsve_version": _jsve_version(),
        "frames": n_frames,
        "file_count": file_count,
        "content_hash": digest,
    }
    with open(partial / MANIFEST_NAME, "w", encoding="utf-8") as stream:
        json.dump(manifest, stream, indent=2)
    return manifest


def disturb_dataset(job: Job, *, force: bool = False) -> JobResult:
    """Write one disturbed dataset, atomically and resumably.

    A finished dataset (target folder with a manifest) made under the job's key (generator_key) is
    skipped; one made under another key raises StaleOutputError, or with force=True is deleted and
    written again (status "redone"). Otherwise the dataset is built in `<target>.partial/` (a stale one
    from a crashed run is discarded first), its manifest written last, and the folder renamed to
    `target`. A target folder without a manifest is not jsve's and raises.

    Raises:
        StaleOutputError: a finished dataset of another key (and force is False).
        OutputError: the dataset cannot be written (nothing is left of it).
        DatasetError: the source cannot be read, or the target is not jsve's.
    """
    target = Path(job.target)
    manifest = read_manifest(target)
    status = "written"
    if manifest is not None:
        what = _stale(job, manifest)
        if what is None:
            return JobResult(target, "skipped", manifest)
        if not force:
            raise StaleOutputError(target.parent.parent, f"{target.parent.name}/{target.name}: {what}")
        logger.info("discarding %s, written under another key (%s)", target, what)
        shutil.rmtree(target)
        status = "redone"
    elif target.exists():
        raise DatasetError(
            f"{target}: exists but has no {MANIFEST_NAME}; not overwriting a folder jsve did not write"
        )
    partial = target.with_name(target.name + PARTIAL_SUFFIX)
    if partial.exists():
        logger.info("discarding stale %s", partial)
        shutil.rmtree(partial)
        status = "redone"
    try:
        manifest = _write_dataset(job, partial)
        os.replace(partial, target)
    except OSError as error:
        shutil.rmtree(partial, ignore_errors=True)
        if atomic.is_write_error(error, partial, target):
            raise atomic.output_error(error, target) from error
        raise
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return JobResult(target, status, manifest)


def make_jobs(
    sources: Sequence[Path | str],
    out_dir: Path | str,
    disturbances: Sequence[str] | None = None,
    levels: Mapping[str, Sequence[float]] | None = None,
    parameters: Mapping[str, Mapping[str, object]] | None = None,
    seed: int = 0,
) -> list[Job]:
    """One Job per (source, disturbance, level): targets `out_dir/<source name>/<dataset_dir_name>`.

    Arguments:
        sources: EuRoC dataset folders (each holding mav0/).
        out_dir: root of the written datasets.
        disturbances: names from DISTURBANCES (default: all).
        levels: per-disturbance level lists overriding the registry's grid.
        parameters: per-disturbance keyword parameters, e.g. {"downsample": {"mode": "calibration"}}.
        seed: base seed of every random disturbance.
    """
    names = list(disturbances) if disturbances is not None else list(DISTURBANCES)
    levels = dict(levels or {})
    parameters = dict(parameters or {})
    for name in list(levels) + list(parameters):
        if name not in names:
            raise ValueError(
                f"levels/parameters given for {name!r}, which is not among the disturbances {names}"
            )
    jobs = []
    for source in sources:
        source = Path(source)
        camera_dirs(source)  # fail early on a folder that is not a dataset
        for name in names:
            params = _check_parameters(name, parameters.get(name))
            for level in levels.get(name, DISTURBANCES[name].levels):
                target = Path(out_dir) / source.name / dataset_dir_name(name, level, params)
                jobs.append(Job(source, target, name, level, tuple(sorted(params.items())), int(seed)))
    return jobs


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one process per core; OpenCV's own threads would oversubscribe


def run_parallel(
    function: Callable, items: Sequence, workers: int, progress: bool, desc: str, scheduler: str | None = None
) -> list:
    """function(item) for every item, in order, run where `scheduler` says (jsve.io._scheduler: "local",
    the default, an embedded Dask LocalCluster of `workers` processes; "processes", a process pool of
    the spawn start method, no fork of a process that may hold JAX or OpenCV threads; or a Dask
    scheduler's address), in this process when workers <= 1; a tqdm progress bar counts finished items.
    """
    from tqdm.auto import tqdm

    results: list = [None] * len(items)
    with tqdm(total=len(items), desc=desc, disable=not progress, unit="job") as bar:
        if _scheduler.in_process(workers, scheduler, len(items)):
            for index, item in enumerate(items):
                results[index] = function(item)
                bar.update()
            return results
        with _scheduler.executor(min(workers, len(items)), scheduler, initializer=_init_worker) as pool:
            futures = {pool.submit(function, item): index for index, item in enumerate(items)}
            for future in concurrent.futures.as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    return results


def disturb_datasets(
    sources: Sequence[Path | str],
    out_dir: Path | str,
    disturbances: Sequence[str] | None = None,
    levels: Mapping[str, Sequence[float]] | None = None,
    parameters: Mapping[str, Mapping[str, object]] | None = None,
    *,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
    force: bool = False,
    scheduler: str | None = None,
) -> list[JobResult]:
    """Write every (source, disturbance, level) dataset, in parallel, skipping finished ones.

    See make_jobs for the arguments; `workers` processes write datasets side by side, where `scheduler`
    says (run_parallel; a Dask cluster's workers must see the sources and out_dir under the same
    absolute paths), and a tqdm bar counts finished datasets. A finished dataset is kept only when
    made under the job's key (see
    disturb_dataset; each source's content is hashed once per call); any made under another raises
    StaleOutputError before anything is written, unless force=True (then they are written again).

    Returns:
        One JobResult per job, in job order.

    Raises:
        StaleOutputError, OutputError, DatasetError: as disturb_dataset.
        SchedulerError: `scheduler` names no scheduler, or its workers run another jsve.
    """
    scheduler = _scheduler.check_scheduler(scheduler)  # a wrong value fails before any work
    jobs = make_jobs(sources, out_dir, disturbances, levels, parameters, seed)
    hashes = {source: content_hash(source)[0] for source in {job.source for job in jobs}}
    jobs = [replace(job, source_hash=hashes[job.source]) for job in jobs]
    # Every finished dataset is checked before any is written: a folder never mixes two keys.
    stale = [(job, what) for job in jobs if (m := read_manifest(job.target)) and (what := _stale(job, m))]
    if not force:
        stop_if_stale(
            out_dir, [(job.target, what) for job, what in stale], "datasets written under another key"
        )
    atomic.check_writable(out_dir)
    for job in jobs:
        atomic.make_dir(job.target.parent)
    # Absolute paths: a cluster's worker does not share this process's working folder.
    absolute = [
        replace(
            job, source=Path(_scheduler.absolute(job.source)), target=Path(_scheduler.absolute(job.target))
        )
        for job in jobs
    ]
    results = run_parallel(
        functools.partial(disturb_dataset, force=force), absolute, workers, progress, "disturb", scheduler
    )
    return [replace(result, target=job.target) for job, result in zip(jobs, results, strict=True)]
