"""The study's resumable runner and its files: stages recorded under the study's key, atomic tables.

    Stages(out, config_fp, data_fp)     stages.json: which stages finished under which key
    stages.run(name, fn, outputs)       run a stage unless finished under this key with its outputs
    fingerprint, data_fingerprint       the key: the configuration's and the data's content
    write_table, read_table, write_json every output written under a temporary name and renamed

A rerun under the same key skips finished stages, so an interrupted study resumes where it stopped; a
rerun under another key (other logs, or other log content under the same run ids; another configuration)
stops with StaleOutputError before writing anything, or with force=True deletes the study's files
(STUDY_FILES) and starts over: a folder never holds tables of two keys.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from jsve._memory import peak_resident_bytes, release_memory
from jsve.io import _atomic as atomic
from jsve.io._resume import StaleOutputError, differences

log = logging.getLogger(__name__)

TABLES = (
    "runs",
    "summary",
    "heldout",
    "cv_params",
    "heldout_summary",
    "params",
    "heatmap",
    "sve_levels",
)
"""The study's tables, each written as `<name>.parquet` and `<name>.csv`."""

STUDY_FILES = (
    "study.json",
    "stages.json",
    "fitted_*.json",
    "search_*.npz",
    *(f"{name}.{suffix}" for name in TABLES for suffix in ("parquet", "csv")),
    "report.md",
    "report.html",
    "report.json",
    "figures/*.png",
    "runs_presets.parquet",  # the presets' own table, which older versions of the study write
    "runs_presets.csv",
)
"""Glob patterns of every file a study and its report write in their folder: what force=True deletes
(and only that: the folder may hold other files)."""


def fingerprint(obj) -> str:
    """16 hex digits of sha256 over `obj`'s JSON (keys sorted; other types by str): the study's key.
    Jobs key their outputs with jsve.io._resume.fingerprint, whose JSON is compact; the two are kept
    apart so that every study folder written so far keeps its key."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def data_fingerprint(data) -> str:
    """16 hex digits of sha256 over the content of what a study reads (a FitData): every array of the
    runs' batches (dtype, shape and bytes, in order) and their metadata table.

    The study's results are a function of these and of its configuration alone, so equal fingerprints
    mean equal results, and any change of a log's values, runs or metadata changes it (run ids and frame
    counts, or the input files' sizes and modification times, would not be enough: other logs can have
    the same). It costs one pass over the arrays (sha256 at about 1 GB/s), small next to any stage.
    """
    if data.content_digest is not None:  # streamed: its chunks were hashed as they went by
        total = hashlib.sha256(data.content_digest.encode())
        total.update(data.meta.to_csv(index=False).encode())
        return total.hexdigest()[:16]
    total = hashlib.sha256()
    batches = [b.batch for b in data.buckets] if data.buckets else [b for b, _, _ in data.iter_slim()]
    for batch in batches:
        for leaf in jax.tree_util.tree_leaves(batch):
            array = np.ascontiguousarray(np.asarray(leaf))
            total.update(f"{array.dtype.str}{array.shape}".encode())
            total.update(array.reshape(-1).view(np.uint8).data)  # the bytes, without a copy
    total.update(data.meta.to_csv(index=False).encode())
    return total.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------------
# Atomic outputs


def write_table(table: pd.DataFrame, out: Path, name: str) -> None:
    """`name`.parquet and `name`.csv, each written under a temporary name and renamed."""
    for suffix in (".parquet", ".csv"):
        atomic.write_table(table, Path(out) / f"{name}{suffix}")


def read_table(out: Path, name: str) -> pd.DataFrame:
    return pd.read_parquet(Path(out) / f"{name}.parquet")


def write_json(obj, path: Path) -> None:
    atomic.write_json(path, obj)


def study_files(out: Path) -> list[Path]:
    """The files of STUDY_FILES in `out`."""
    return sorted({p for pattern in STUDY_FILES for p in Path(out).glob(pattern) if p.is_file()})


class Stages:
    """stages.json: which stages finished under which key (configuration and data fingerprints).

    Raises:
        StaleOutputError: the folder's stages ran under another key (and force is False); with force,
            the study's files are deleted and every stage runs again.
    """

    def __init__(self, out: Path, config_fp: str, data_fp: str, *, force: bool = False, describe=None):
        self.path = out / "stages.json"
        self.key = {"config": config_fp, "data": data_fp}
        self.done = {}
        if not self.path.is_file():
            return
        record = json.loads(self.path.read_text())
        if record.get("key") == self.key:
            self.done = record.get("done", {})
            return
        old = record.get("key") or {}
        what = describe(old, self.key) if describe else differences(old, self.key)
        if not force:
            raise StaleOutputError(out, what)
        log.info("%s: a study of another key (%s); its files are deleted (force)", out, what)
        files = study_files(out)
        for path in files:
            try:
                path.unlink()
            except OSError as error:
                raise atomic.output_error(error, path) from error
        for folder in {p.parent for p in files} - {out}:
            if not any(folder.iterdir()):
                folder.rmdir()  # the report's figures/

    def run(self, name: str, fn: Callable[[], dict | None], outputs: Sequence[Path]) -> dict:
        if name in self.done and all(p.exists() for p in outputs):
            log.info("stage %s: done already, skipped", name)
            return self.done[name]
        started = time.perf_counter()
        info = fn() or {}
        info["seconds"] = time.perf_counter() - started
        # the process's peak so far (the stage's own where memory grew in it), then what it left behind
        peak = peak_resident_bytes()
        if peak is not None:
            info["peak_rss_gb"] = round(peak / 1e9, 2)
        release_memory()
        self.done[name] = info
        write_json({"key": self.key, "done": self.done}, self.path)
        return info


def describe_change(out: Path, config: dict, data: dict) -> Callable[[dict, dict], str]:
    """What differs between the study in `out` (its stages.json key `old` and its study.json) and this
    one (key `new`, JSON-ready `config`, `data` summary), in words: `data: ...; configuration: ...`."""

    def describe(old: dict, new: dict) -> str:
        try:
            study = json.loads((out / "study.json").read_text())
        except (OSError, ValueError):
            study = {}
        parts = []
        if old.get("data") != new["data"]:
            before = {
                "fingerprint": old.get("data"),
                "n_runs": study.get("n_runs"),
                "n_frames": study.get("n_frames"),
                "source": (study.get("data") or {}).get("source"),
            }
            parts.append(f"data: {differences(before, data)}")
        if old.get("config") != new["config"]:
            shown = differences(study["config"], config) if "config" in study else "another"
            parts.append(f"configuration: {shown or 'another'}")
        return "; ".join(parts) or f"key {old} != {new}"

    return describe


__all__ = [
    "TABLES",
    "STUDY_FILES",
    "Stages",
    "describe_change",
    "fingerprint",
    "data_fingerprint",
    "write_table",
    "read_table",
    "write_json",
    "study_files",
]
