"""A whole fitting study over a set of logs, written to one output folder: a list of stages.

    fit_<family>          each family fitted on all runs (`fit_stage`)
    evaluate              the presets and fitted rules, the objective's terms and the SVE per level
    cross_validation      k-fold (with --thorough also leave-one-sequence/disturbance-out)
    parameter_bootstrap   the fitted parameters' intervals
    heatmap               the objective over the two main thresholds

Each stage is a top-level function of a `Study` (the data, the resolved configuration, the run
weights, the spaces and the fits so far) that writes its tables; `stages(study)` lists them in order
with their outputs, and `run_study` runs them through the resumable runner of jsve.fitting._stages
(a finished stage under the same key is skipped). jsve.report._report renders the folder; `jsve fit`
and `jsve demo` are thin layers over `run_study`.
"""

from __future__ import annotations

import functools
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import pandas as pd

from jsve._memory import release_memory
from jsve.core._rules import PRESETS, preset, rule_kind, rule_to_dict
from jsve.core._sve import Combination
from jsve.evaluation._aggregate import aggregate, group_weights
from jsve.evaluation._evaluate import evaluate_rules, in_run_order
from jsve.fitting._config import StudyConfig
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
from jsve.fitting._stages import (
    Stages,
    data_fingerprint,
    describe_change,
    fingerprint,
    read_table,
    write_json,
    write_table,
)
from jsve.io import _atomic as atomic
from jsve.io._resume import StaleOutputError

log = logging.getLogger(__name__)


@dataclass
class Study:
    """What the stages of one study read and share.

    Attributes:
        data: the logs (FitData, its objective the configuration's).
        out: the study's folder.
        config: the study's configuration, its "auto" settings resolved for these data
            (StudyConfig.resolved).
        weights: [R] run weights (groups of config.balance_by count equally).
        spaces: family -> ParamSpace.
        progress: show progress bars.
        fits: family -> FitResult, as the fit stages wrote them (read back from their files).
        caches: family -> the halving's per-run results of a fit run in this process, which the folds
            of the cross-validation reuse.
    """

    data: FitData
    out: Path
    config: StudyConfig
    weights: np.ndarray
    spaces: dict[str, ParamSpace]
    progress: bool = True
    fits: dict[str, FitResult] = field(default_factory=dict)
    caches: dict = field(default_factory=dict)

    @property
    def has_levels(self) -> bool:
        return {"disturbance", "level"} <= set(self.data.meta.columns)


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


# ---------------------------------------------------------------------------------------------------
# The stages


def fit_files(study: Study, family: str) -> list[Path]:
    """fitted_<family>.json (the rule file and the fit's facts) and search_<family>.npz (its search)."""
    return [study.out / f"fitted_{family}.json", study.out / f"search_{family}.npz"]


def fit_stage(study: Study, family: str) -> dict:
    """Fit `family` on every run and write its files."""
    json_path, search_path = fit_files(study, family)
    result = fit(study.data, study.spaces[family], study.weights, study.config.fit, progress=study.progress)
    if result.cache is not None:
        study.caches[family] = result.cache
    _save_search(result.search, search_path)
    write_json(_fit_record(family, result), json_path)
    return {"objective": result.objective, "values": result.values.tolist()}


def read_fit(study: Study, family: str) -> None:
    """`study.fits[family]`: the fit as its files hold it (the same whether it ran now or before a
    resume)."""
    json_path, search_path = fit_files(study, family)
    record = json.loads(json_path.read_text())
    study.fits[family] = FitResult(
        space=study.spaces[family],
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


def evaluate_stage(study: Study) -> None:
    """Every preset and fitted rule in one pass over the runs (one stream of a Parquet study, each
    chunk's features computed once), with the objective's terms of every run (the cross-validation's
    held-out rows of the presets the kernel does not search) and the SVE level sums riding on the same
    chunks: runs, summary and sve_levels."""
    data, config = study.data, study.config
    rules = [(name, preset(name)) for name in PRESETS]
    rules += [(fitted_rule_name(f), r.rule) for f, r in study.fits.items()]
    levels = SveLevelSums(_sve_combinations(study.fits)) if study.has_levels else None
    # Length by length: the pass drops each length's executables once past it (jsve._memory) without
    # meeting that length again; the table is then put in the runs' order.
    # One road for the objective's settings: the evaluation replays and scores as data.config says.
    objective = data.config
    per_run = evaluate_rules(
        data.full_buckets(by_length=True), rules, n_runs=data.n_runs, objective=objective,
        on_chunk=None if levels is None else levels.add, align=objective.align,
        min_coverage=objective.min_coverage, failure=objective.failure,
        switch_model=objective.switch_model, progress=study.progress,
    )  # fmt: skip
    per_run = in_run_order(per_run, data.meta_order(per_run["run_id"]))
    write_table(per_run, study.out, "runs")
    group = [c for c in ("disturbance", "level") if c in per_run.columns]
    summary = aggregate(
        per_run, group + ["rule"], n_boot=config.n_boot, level=config.level, seed=config.seed,
        failure_penalty=objective.failure_penalty, support=objective.support,
    )  # fmt: skip
    write_table(summary, study.out, "summary")
    if levels is not None:
        write_table(levels.table(), study.out, "sve_levels")


def cross_validation_stage(study: Study) -> dict:
    """Every family refitted on each fold's training runs and scored, with the presets, on its held-out
    runs: heldout, cv_params and heldout_summary."""
    config = study.config
    folds = study_folds(study.data.meta, config)
    if not folds:
        return {"folds": 0}
    cv = cross_validate(
        study.data, study.spaces, folds, study.weights, config.fit,
        searches={f: r.search for f, r in study.fits.items()}, caches=study.caches,
        replayed=objective_results(read_table(study.out, "runs"), study.data.meta, PRESETS),
        progress=study.progress,
    )  # fmt: skip
    write_table(cv.heldout, study.out, "heldout")
    write_table(cv.params, study.out, "cv_params")
    summary = compare(cv.heldout, n_boot=config.n_boot, level=config.level, seed=config.seed)
    write_table(summary, study.out, "heldout_summary")
    return {"folds": len(folds)}


def bootstrap_stage(study: Study) -> None:
    """The fitted parameters' bootstrap intervals, every family: params."""
    config = study.config
    tables = [
        parameter_bootstrap(
            study.data,
            study.spaces[f],
            r,
            study.weights,
            n_local=config.n_local,
            fraction=config.local_fraction,
            n_boot=config.n_boot,
            level=config.level,
            seed=config.seed,
            screen_runs=config.bootstrap_screen_runs,
            progress=study.progress,
        )  # fmt: skip
        for f, r in study.fits.items()
    ]
    write_table(pd.concat(tables, ignore_index=True), study.out, "params")


def heatmap_stage(study: Study) -> None:
    """The objective over config.heatmap's two thresholds for every family that has both: heatmap (none
    without config.heatmap)."""
    if not study.config.heatmap:
        return
    x, y, n = study.config.heatmap
    tables = [
        heatmap_table(
            study.data,
            study.spaces[f],
            r.values,
            study.weights,
            x,
            y,
            int(n),
            runs=study.config.heatmap_runs,
            seed=study.config.fit.seed,
            progress=study.progress,
        )  # fmt: skip
        for f, r in study.fits.items()
        if x in study.spaces[f].names and y in study.spaces[f].names
    ]
    if tables:
        write_table(pd.concat(tables, ignore_index=True), study.out, "heatmap")


@dataclass(frozen=True)
class Stage:
    """One stage of the list: its name in stages.json, what runs it, and the files that show it done.

    Attributes:
        after: what follows it every time, run or skipped (the fits read back into `Study.fits`).
    """

    name: str
    run: Callable[[], dict | None]
    outputs: list[Path]
    after: Callable[[], None] | None = None


def stages(study: Study) -> list[Stage]:
    """The study's stages in the order they run."""
    out = study.out
    fits = [
        Stage(
            f"fit_{family}",
            functools.partial(fit_stage, study, family),
            fit_files(study, family),
            after=functools.partial(read_fit, study, family),
        )
        for family in study.spaces
    ]
    evaluated = [out / "runs.parquet", out / "summary.parquet"]
    evaluated += [out / "sve_levels.parquet"] if study.has_levels else []
    heatmap = [out / "heatmap.parquet"] if study.config.heatmap else []
    return fits + [
        Stage("evaluate", functools.partial(evaluate_stage, study), evaluated),
        Stage(
            "cross_validation",
            functools.partial(cross_validation_stage, study),
            [out / "heldout_summary.parquet"],
        ),
        Stage("parameter_bootstrap", functools.partial(bootstrap_stage, study), [out / "params.parquet"]),
        Stage("heatmap", functools.partial(heatmap_stage, study), heatmap),
    ]


# ---------------------------------------------------------------------------------------------------
# The runner


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
        describe=describe_change(out, config_json, summary),
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
    *,
    progress: bool = True,
    data_description: dict | None = None,
    force: bool = False,
) -> dict:
    """Run every stage of a fitting study on `data` and write its tables to `out_dir`.

    Resumable: stages finished under the same key (configuration and data_fingerprint) are skipped.

    Arguments:
        data: FitData (with its buckets, for jsve.evaluation._evaluate); its objective config must be
            config's.
        config: the study as asked for; its key is this configuration, and its "auto" settings are
            resolved once, here, for these data (StudyConfig.resolved).
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
    record, summary = _open_stages(out, config, data, data_description, force=force)
    atomic.check_writable(out)
    by = [c for c in config.balance_by if c in data.meta.columns]
    study_record = {
        "config": config.to_dict(),
        "data": data_description or {},
        "data_fingerprint": summary["fingerprint"],
        "n_runs": data.n_runs,
        "n_frames": data.n_frames,
        "balance_by": by,
    }
    write_json(study_record, out / "study.json")
    resolved = config.resolved(data.n_runs)
    spaces = {f: resolved.space(f) for f in resolved.families}
    study = Study(data, out, resolved, group_weights(data.meta, by), spaces, progress)
    for stage in stages(study):
        record.run(stage.name, stage.run, stage.outputs)
        if stage.after is not None:
            stage.after()
    return record.done


__all__ = [
    "Study",
    "Stage",
    "stages",
    "run_study",
    "finished_stages",
    "record_timing",
    "study_folds",
    "heatmap_table",
]
