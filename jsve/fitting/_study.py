"""A whole fitting study over a set of logs, written to one output folder, stage by stage.

    fit each family on all runs -> evaluate the presets and fitted rules, with the objective's terms
    and the SVE per level, in one pass -> cross-validate (k-fold; with --thorough also
    leave-one-sequence-out and leave-one-disturbance-out) -> bootstrap the fitted parameters ->
    objective over the two main thresholds -> (jsve.report._report renders it all)

Every stage writes its tables atomically (a temporary name, then a rename) as Parquet and CSV, and
records itself in `stages.json` under the study's key: a fingerprint of the configuration and one of the
data's content (data_fingerprint: sha256 over every array and metadata value the study reads). A rerun
under the same key skips finished stages, so an interrupted study resumes where it stopped; a rerun
under another key (other logs, or other log content under the same run ids; another configuration)
stops with StaleOutputError before writing anything, or with force=True deletes the study's files
(STUDY_FILES) and starts over: a folder never holds tables of two keys. `jsve fit` and `jsve demo` are
thin layers over `run_study`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import fields, replace
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from jsve._memory import peak_resident_bytes, release_memory
from jsve.core._rules import PRESETS, preset, rule_kind, rule_to_dict
from jsve.core._sve import Combination
from jsve.evaluation._aggregate import aggregate, group_weights
from jsve.evaluation._evaluate import evaluate_rules, in_run_order
from jsve.fitting._config import THOROUGH, StudyConfig
from jsve.fitting._crossval import (
    compare,
    cross_validate,
    kfold,
    leave_one_out,
    objective_results,
    parameter_bootstrap,
)
from jsve.fitting._data import FitData
from jsve.fitting._designs import grid_design
from jsve.fitting._fit import FitResult, fit, fitted_rule_name
from jsve.fitting._levels import SveLevelSums
from jsve.fitting._polish import polish_runs
from jsve.fitting._search import SearchResult
from jsve.fitting._space import ParamSpace
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


"""What `jsve fit --thorough` adds to the defaults: leave-one-sequence-out and leave-one-disturbance-out
folds, and a parameter bootstrap whose refits also choose among 1,024 settings around the fit (finer
intervals). The default takes about half the time, with the same fitted rules and k-fold held-out
objective (docs/fitting.md, "The default study and `--thorough`")."""


def fingerprint(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def data_fingerprint(data: FitData) -> str:
    """16 hex digits of sha256 over the content of what a study reads: every array of the runs' batches
    (dtype, shape and bytes, in order) and their metadata table.

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


def _describe_change(out: Path, config: dict, data: dict) -> Callable[[dict, dict], str]:
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


# ---------------------------------------------------------------------------------------------------
# Tables of the study


def _sve_combinations(fits: dict[str, FitResult]) -> dict[str, Combination]:
    """The SVE combinations of the level table: every SVE preset's, then the fitted SVE rule's."""
    combos = {name: preset(name).combination for name in PRESETS if rule_kind(preset(name)) == "sve"}
    if "sve" in fits:
        combos[fitted_rule_name("sve")] = fits["sve"].rule.combination
    return combos


def heatmap_table(
    data: FitData,
    space: ParamSpace,
    values,
    weights,
    x: str,
    y: str,
    n: int,
    *,
    runs: int = 0,
    seed: int = 0,
    progress: bool = False,
) -> pd.DataFrame:
    """The objective over a grid of two free parameters (the others at `values`), with failure rate.

    Arguments:
        weights: [R] run weights (None: 1).
        runs: score the grid on the first `runs` weighted runs of the study's stratified order (seeded
            by `seed`; jsve.fitting._polish.polish_runs), laid out as jsve.fitting._packing.subset_layout
            chooses: a picture of the surface whose cost stops growing with the study. 0, or no more
            weighted runs than that: on every run.
        progress: the search's bar.
    Returns:
        One row per grid point: family, x_name, y_name, x, y, objective (metres), failure_rate,
        n_runs (weighted runs scored) and n_weighted (weighted runs of the study).
    """
    if x not in space.names or y not in space.names:
        raise ValueError(f"heat map axes {x!r}, {y!r} must be free parameters of {space.names}")
    w = np.ones(data.n_runs) if weights is None else np.asarray(weights, np.float64)
    ix, iy = space.names.index(x), space.names.index(y)
    unit = grid_design([n, n])
    grid = np.repeat(np.asarray(values, np.float64)[None], len(unit), axis=0)
    grid[:, ix] = space.lo[ix] + (space.hi[ix] - space.lo[ix]) * unit[:, 0]
    grid[:, iy] = space.lo[iy] + (space.hi[iy] - space.lo[iy]) * unit[:, 1]
    subset = polish_runs(data.meta, w, runs, seed=seed)
    scorer = data.scorer if subset is None else data.scorer.on(subset, len(grid))
    scored_w = w[scorer.runs]
    res = scorer.score(space, grid, progress=progress, desc=f"heat map {space.kind}")
    return pd.DataFrame(
        {
            "family": space.kind,
            "x_name": x,
            "y_name": y,
            "x": grid[:, ix],
            "y": grid[:, iy],
            "objective": res.objective(scored_w),
            "failure_rate": res.failure_rate(scored_w),
            "n_runs": int(np.sum(scored_w > 0)),
            "n_weighted": int(np.sum(w > 0)),
        }
    )


def _fit_record(name: str, result: FitResult) -> dict:
    """fitted_<family>.json: the rule as `rule_to_dict` writes it at the top level (kind and parameter
    tables), so that the file is a rule file for `jsve evaluate --rule` and `jsve frontend run --rule`,
    then the fit's facts (rule_from_dict ignores them)."""
    return {
        **rule_to_dict(result.rule),
        "family": name,
        "space": result.space.describe(),
        "values": result.values.tolist(),
        "params": result.params(),
        "objective": result.objective,
        "failure_rate": result.failure_rate,
        "coverage": result.coverage,
        "unsupported_rate": result.unsupported_rate,
        "n_unsupported": result.n_unsupported,
        "n_excluded": result.n_excluded,
        "stages": result.stages,
    }


def _save_search(result: SearchResult, path: Path) -> None:
    # A file object, so that numpy does not append ".npz" to the temporary name.
    with atomic.atomic_path(path) as partial, open(partial, "wb") as f:
        np.savez_compressed(f, **{k.name: getattr(result, k.name) for k in fields(SearchResult)})


def _load_search(path: Path) -> SearchResult:
    with np.load(path) as z:
        return SearchResult(**{k.name: z[k.name] for k in fields(SearchResult)})


def study_folds(meta: pd.DataFrame, config: StudyConfig) -> list:
    """The cross-validation's folds of a study: config.kfold folds over runs (seeded), then one fold per
    value of each leave_one_out column (a column with fewer than 2 values is skipped)."""
    folds = []
    if config.kfold:
        folds += kfold(len(meta), min(config.kfold, len(meta)), seed=config.seed)
    for column in config.leave_one_out:
        if column in meta.columns and meta[column].astype(str).nunique() >= 2:
            folds += leave_one_out(meta, column)
        else:
            log.info("leave-one-%s-out skipped: fewer than 2 values", column)
    return folds


def finished_stages(
    out_dir: str | os.PathLike,
    config: StudyConfig,
    data: FitData,
    *,
    data_description: dict | None = None,
    force: bool = False,
) -> set[str]:
    """The stages a rerun of run_study(data, out_dir, config) skips: those recorded in stages.json under
    this study's key (configuration and data fingerprints); none for a folder without stages.json.
    Costs a data_fingerprint only where stages.json exists. data_description: as run_study's (its
    source names the data in the error below).

    Raises:
        StaleOutputError: the folder holds a study of another key (as run_study would, before it
            writes anything); with force, none is finished instead (run_study deletes them).
    """
    out = Path(out_dir)
    if not (out / "stages.json").is_file():
        return set()
    if data.config != config.objective():
        data = replace(data, config=config.objective())
    try:
        stages, _ = _open_stages(out, config, data, data_description, force=False)
    except StaleOutputError:
        if force:
            return set()
        raise
    return set(stages.done)


def _open_stages(
    out: Path, config: StudyConfig, data: FitData, data_description: dict | None, *, force: bool
) -> tuple[Stages, dict]:
    """The study folder's stage records under this study's key (configuration and data fingerprints),
    and the data's summary (fingerprint, runs, frames, source) as study.json records it."""
    summary = {
        "fingerprint": data_fingerprint(data),
        "n_runs": data.n_runs,
        "n_frames": data.n_frames,
        "source": (data_description or {}).get("source"),
    }
    config_json = json.loads(json.dumps(config.to_dict(), default=str))
    stages = Stages(
        out,
        fingerprint(config.to_dict()),
        summary["fingerprint"],
        force=force,
        describe=_describe_change(out, config_json, summary),
    )
    return stages, summary


def record_timing(out_dir: str | os.PathLike, timing: dict) -> None:
    """Add `timing` (JSON-ready: the wall time expected before the study and the one measured) to the
    study's study.json under "timing", replacing an earlier run's."""
    path = Path(out_dir) / "study.json"
    study = json.loads(path.read_text())
    study["timing"] = timing
    write_json(study, path)


def run_study(
    data: FitData,
    out_dir: str | os.PathLike,
    config: StudyConfig = StudyConfig(),  # noqa: B008
    *,  # noqa: B008
    progress: bool = True,
    data_description: dict | None = None,
    force: bool = False,
) -> dict:
    """Run every stage of a fitting study on `data` and write its tables to `out_dir`.

    Resumable: stages finished under the same key (configuration and data_fingerprint) are skipped.

    Arguments:
        data: FitData (with its buckets, for jsve.evaluation._evaluate); its objective config must be
            config's.
        data_description: JSON-ready facts about the data (source, simulator settings) for the report.
        force: the folder holds a study of another key: delete its files (STUDY_FILES) and start over,
            instead of raising StaleOutputError.
    Returns:
        The stage records (seconds and key results per stage).

    Raises:
        StaleOutputError: `out_dir` holds a study of other data or another configuration (nothing is
            written; force=True starts over).
        OutputError: `out_dir` or a table cannot be written.
    """
    out = Path(out_dir)
    if data.config != config.objective():
        data = replace(data, config=config.objective())
    release_memory()  # what came before (loading, `jsve fit`'s timing probe) holds gigabytes
    meta = data.meta
    stages, summary = _open_stages(out, config, data, data_description, force=force)
    data_fp = summary["fingerprint"]
    atomic.check_writable(out)
    by = [c for c in config.balance_by if c in meta.columns]
    weights = group_weights(meta, by)
    write_json(
        {
            "config": config.to_dict(),
            "data": data_description or {},
            "data_fingerprint": data_fp,
            "n_runs": data.n_runs,
            "n_frames": data.n_frames,
            "balance_by": by,
        },
        out / "study.json",
    )
    spaces = {f: config.space(f) for f in config.families}
    eval_kwargs = dict(
        align=config.align,
        min_coverage=config.min_coverage,
        failure=config.failure,
        switch_model=config.switch_model,
        progress=progress,
    )

    fits: dict[str, FitResult] = {}
    caches = {}  # the halving's per-run results of fits run in this process, which the folds reuse
    for family, space in spaces.items():
        json_path, search_path = out / f"fitted_{family}.json", out / f"search_{family}.npz"

        def do_fit(family=family, space=space, json_path=json_path, search_path=search_path):
            result = fit(data, space, weights, config.fit, progress=progress)
            if result.cache is not None:
                caches[family] = result.cache
            _save_search(result.search, search_path)
            write_json(_fit_record(family, result), json_path)
            return {"objective": result.objective, "values": result.values.tolist()}

        stages.run(f"fit_{family}", do_fit, [json_path, search_path])
        record = json.loads(json_path.read_text())
        fits[family] = FitResult(
            space=space,
            values=np.asarray(record["values"]),
            objective=record["objective"],
            failure_rate=record["failure_rate"],
            coverage=record["coverage"],
            stages=record["stages"],
            search=_load_search(search_path),
            unsupported_rate=record["unsupported_rate"],
            n_unsupported=record["n_unsupported"],
            n_excluded=record["n_excluded"],
        )

    has_levels = {"disturbance", "level"} <= set(meta.columns)

    def evaluate():
        # Every preset and fitted rule in one pass over the runs (one stream of a Parquet study, each
        # chunk's features computed once), with the objective's terms of every run (the cross-
        # validation's held-out rows of the presets the kernel does not search) and the SVE level
        # sums riding on the same chunks.
        rules = [(name, preset(name)) for name in PRESETS]
        rules += [(fitted_rule_name(f), r.rule) for f, r in fits.items()]
        levels = SveLevelSums(_sve_combinations(fits)) if has_levels else None
        # Length by length: the pass drops each length's executables once past it (jsve._memory)
        # without meeting that length again; the table is then put in the runs' order.
        per_run = evaluate_rules(
            data.full_buckets(by_length=True), rules, n_runs=data.n_runs, objective=data.config,
            on_chunk=None if levels is None else levels.add, **eval_kwargs,
        )  # fmt: skip
        per_run = in_run_order(per_run, data.meta_order(per_run["run_id"]))
        write_table(per_run, out, "runs")
        group = [c for c in ("disturbance", "level") if c in per_run.columns]
        write_table(
            aggregate(
                per_run,
                group + ["rule"],
                n_boot=config.n_boot,
                level=config.level,
                seed=config.seed,
                failure_penalty=config.failure_penalty,
                support=config.support,
            ),  # fmt: skip
            out,
            "summary",
        )
        if levels is not None:
            write_table(levels.table(), out, "sve_levels")

    outputs = [out / "runs.parquet", out / "summary.parquet"] + [out / "sve_levels.parquet"] * has_levels
    stages.run("evaluate", evaluate, outputs)

    def crossvalidate():
        folds = study_folds(meta, config)
        if not folds:
            return {"folds": 0}
        cv = cross_validate(
            data,
            spaces,
            folds,
            weights,
            config.fit,
            searches={f: r.search for f, r in fits.items()},
            caches=caches,
            replayed=objective_results(read_table(out, "runs"), meta, PRESETS),
            progress=progress,
        )
        write_table(cv.heldout, out, "heldout")
        write_table(cv.params, out, "cv_params")
        write_table(
            compare(cv.heldout, n_boot=config.n_boot, level=config.level, seed=config.seed),
            out,
            "heldout_summary",
        )
        return {"folds": len(folds)}

    stages.run("cross_validation", crossvalidate, [out / "heldout_summary.parquet"])

    def bootstrap():
        tables = [
            parameter_bootstrap(
                data,
                spaces[f],
                r,
                weights,
                n_local=config.n_local,
                fraction=config.local_fraction,
                n_boot=config.n_boot,
                level=config.level,
                seed=config.seed,
                screen_runs=config.bootstrap_screen_runs,
                progress=progress,
            )
            for f, r in fits.items()
        ]
        write_table(pd.concat(tables, ignore_index=True), out, "params")

    stages.run("parameter_bootstrap", bootstrap, [out / "params.parquet"])

    def heatmap():
        x, y, n = config.heatmap
        tables = [
            heatmap_table(
                data,
                spaces[f],
                r.values,
                weights,
                x,
                y,
                int(n),
                runs=config.heatmap_runs,
                seed=config.fit.seed,
                progress=progress,
            )
            for f, r in fits.items()
            if x in spaces[f].names and y in spaces[f].names
        ]
        if tables:
            write_table(pd.concat(tables, ignore_index=True), out, "heatmap")

    stages.run("heatmap", heatmap, [out / "heatmap.parquet"] if config.heatmap else [])

    return stages.done


__all__ = [
    "StudyConfig",
    "THOROUGH",
    "run_study",
    "data_fingerprint",
    "STUDY_FILES",
    "finished_stages",
    "record_timing",
    "study_folds",
    "heatmap_table",
    "write_table",
    "read_table",
]
