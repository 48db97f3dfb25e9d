"""The report of a folder: a fitting study (`jsve fit`, `jsve demo`) or an evaluation (`jsve evaluate -o`).

`write_report(out_dir)` reads the folder's tables and writes

    report.md      Markdown (figures linked from figures/)
    report.html    the same page with the figures embedded (base64 PNG): one file to share
    report.json    the report's title, so that `jsve report DIR` renders the same page again
    figures/       heldout.png, levels.png, heatmap_<family>.png, sve_levels_<disturbance>.png

A study's report (jsve.report._study_report) opens with a headline (what was fitted, the recommended rule,
its held-out gain over the baselines with intervals, how often it switches, the caveats), then the
figures, then the tables, the long ones collapsed; an evaluation's (jsve.report._evaluation_report) has
the same shape without the fit. Lengths are in centimetres, shares in percent; every number comes from one
of the folder's tables through jsve.report._derive.

Rendering is deterministic: the same tables give byte-identical files (matplotlib's Agg backend, no
timestamps, fixed ordering). Every file is written through jsve.io's atomic writers (`<name>.partial`,
then a rename), so a killed render leaves no half-written report under its final name.
"""

from __future__ import annotations

import os
from pathlib import Path

from jsve.core._rules import BASELINES
from jsve.evaluation import trust_region_warning
from jsve.fitting._fit import fitted_rule_name
from jsve.io import _atomic as atomic
from jsve.report import _derive as derive
from jsve.report._document import Details, Figure, Section, render
from jsve.report._evaluation_report import evaluation_sections
from jsve.report._format import cm_ci, percent
from jsve.report._study_report import FOLD_KIND_TEXT, read_study, study_sections
from jsve.report._tables import read_json, rule_file
from jsve.report._tune_report import TUNE_TITLE, tune_sections

STUDY_TITLE = "jsve threshold report"
EVALUATION_TITLE = "jsve evaluation report"


def _title(source: Path, out: Path, title: str | None, default: str) -> str:
    """The title given (then kept in out/report.json), else the one the output folder keeps, else the one
    the source folder keeps, else the default. The source folder is only read."""
    kept = read_json(out / "report.json").get("title") or read_json(source / "report.json").get("title")
    if title is None:
        return str(kept or default)
    if read_json(out / "report.json").get("title") != title:
        atomic.write_json(out / "report.json", {"title": title})
    return title


def _figure_paths(blocks) -> list[Path]:
    paths = []
    for block in blocks:
        if isinstance(block, (Section, Details)):
            paths += _figure_paths(block.blocks)
        elif isinstance(block, Figure):
            paths.append(block.path)
    return paths


def write_report(
    out_dir: str | os.PathLike, *, title: str | None = None, output: str | os.PathLike | None = None
) -> dict[str, Path]:
    """Render report.md, report.html and the figures of a study folder (`jsve fit`, `jsve demo`) or of an
    evaluation folder (`jsve evaluate -o`).

    Arguments:
        out_dir: the folder whose tables are read.
        title: the page title; it is kept in report.json, and None takes the kept one (else
            "jsve threshold report" / "jsve evaluation report"), so a re-render keeps the title.
        output: the folder the report (report.md, report.html, report.json, figures/) is written to;
            None: out_dir itself. Figures are linked relative to it, so the page is the same bytes
            wherever it is written.
    Returns:
        Paths of what was written, by name: "markdown", "html", and "figure <file name>" per figure.
    Raises:
        FileNotFoundError: the folder holds neither a study nor an evaluation.
    """
    source = Path(out_dir)
    out = source if output is None else atomic.make_dir(output)
    fig_dir = out / "figures"
    if (source / "study.json").is_file():
        title = _title(source, out, title, STUDY_TITLE)
        sections = study_sections(read_study(source), fig_dir)
    elif (source / "tune.json").is_file():
        title = _title(source, out, title, TUNE_TITLE)
        sections = tune_sections(source, fig_dir)
    elif (source / "runs.parquet").is_file():
        title = _title(source, out, title, EVALUATION_TITLE)
        sections = evaluation_sections(source, fig_dir)
    else:
        raise FileNotFoundError(
            f"{source}: no study.json (from `jsve fit` or `jsve demo`) and no runs.parquet (from "
            "`jsve evaluate -o`): nothing to report"
        )
    md, page = render(title, sections, out)
    written = {"markdown": out / "report.md", "html": out / "report.html"}
    atomic.write_text(written["markdown"], md)
    atomic.write_text(written["html"], page)
    for path in _figure_paths(sections):
        written[f"figure {path.name}"] = path
    return written


def summary_lines(out_dir: str | os.PathLike, *, report: bool = True) -> list[str]:
    """A study's headline in a few plain lines for a terminal (`jsve demo` and `jsve fit` end with them):
    the recommended rule and its file, its held-out objective and differences to the baselines with
    intervals (the first fold kind), how often it switches, and where the report is.

    Arguments:
        out_dir: the study folder. report: whether its report has been written (else the last line says
            how to write it).
    Raises:
        FileNotFoundError: the folder holds no finished study.
    """
    s = read_study(Path(out_dir))
    html = Path(out_dir) / "report.html"
    where = f"report: {html}" if report else f"report: not written (`jsve report {out_dir}` writes it)"
    if s.rec is None or s.heldout_summary is None:
        return [f"no held-out comparison in {out_dir}: nothing recommended", where]
    first = s.heldout_summary[s.heldout_summary["rule"] == s.rec.rule].iloc[0]
    objective = cm_ci(first["mean_loss"], first["ci_low"], first["ci_high"])
    lines = [
        f"recommended: {s.rec.rule} (rule file {s.out / rule_file(s.rec.rule)}, for `jsve evaluate --rule`)",
        f"held-out objective ({FOLD_KIND_TEXT.get(first['fold_kind'], first['fold_kind'])}): {objective} cm",
    ]
    for base in BASELINES.values():
        key = f"diff_vs_{base}"
        if key in first and first[key] == first[key]:
            low, high = first[f"{key}_ci_low"], first[f"{key}_ci_high"]
            lines.append(
                f"  vs {base}: {cm_ci(first[key], low, high, sign=True)} cm ({derive.verdict(low, high)})"
            )
    o = s.overview.set_index("rule")
    if {"rejected", "reached_lost"} <= set(o.columns) and s.rec.rule in o.index:
        lines.append(
            f"switches: {percent(o.loc[s.rec.rule, 'rejected'])} of frames rejected, "
            f"{percent(o.loc[s.rec.rule, 'reached_lost'])} of runs reach LOST (all runs)"
        )
    lines.append(where)
    return lines


def trust_warnings(out_dir: str | os.PathLike, threshold: float | None = None) -> list[str]:
    """One line per fitted rule of a study whose replays change more of the recordings' decisions than
    replays under the study's switch model were validated for (jsve.evaluation.trust_region_warning;
    `jsve fit` prints them).

    Arguments:
        out_dir: the study folder. threshold: the changed share trusted (default
            jsve.evaluation.trusted_share of the study's switch model).
    Raises:
        FileNotFoundError: the folder holds no finished study.
    """
    s = read_study(Path(out_dir))
    o = s.overview
    if "changed" not in o:
        return []
    model = s.study.get("config", {}).get("switch_model", "orbslam3")
    fitted = [fitted_rule_name(f) for f in BASELINES]
    lines = [
        trust_region_warning(r, c, switch_model=model, threshold=threshold)
        for r, c in zip(o["rule"], o["changed"], strict=True)
        if r in fitted
    ]
    return [line for line in lines if line is not None]


__all__ = ["write_report", "summary_lines", "trust_warnings", "STUDY_TITLE", "EVALUATION_TITLE"]
