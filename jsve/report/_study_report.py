"""The report of a fitting study (`jsve fit`, `jsve demo`): a headline, the figures, then the tables.

Headline             what was fitted, the recommended rule and its parameters, its held-out gain over
                     orbslam3 and sve-option2 with intervals, how often it switches, the caveats
Figures              held-out objective, per level, heat maps (presets at their own scores), SVE
Held-out comparison  fitted rules per fold kind, presets once
Fitted parameters    with identifiability flags
All runs, per rule   objective, failures, switching
Per level            compact tables, details collapsed
Method               the configuration in sentences
Fit stages           collapsed
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M
from jsve.core._rules import BASELINES, param_names, preset, rule_params
from jsve.evaluation import trust_region_warning, trusted_share
from jsve.report import _derive as derive
from jsve.report import _figures as figures
from jsve.report._document import Bullets, Details, Figure, Section, Sub, Table
from jsve.report._format import (
    cm,
    cm_ci,
    count,
    decimals_for,
    fixed,
    metres,
    number,
    percent,
    span_mm,
    words_list,
)
from jsve.report._tables import (
    OVERVIEW_TEXT,
    SUPPORT_TEXT,
    has_levels,
    level_sections,
    overview_table,
    read_json,
    read_table,
    rule_file,
    scoring_bullets,
)

DESIGN_TEXT = {"sobol": "Sobol", "grid": "grid", "random": "random", "lhs": "Latin hypercube"}
"""Search designs (jsve.fitting._designs) in words."""
GROUP_COLUMNS = ("sequence", "disturbance", "level")
"""`jsve fit`'s default run weighting (jsve.fitting._config.StudyConfig.balance_by), for a study.json that
records none."""

FAMILY_TEXT = {
    "sve": ("the SVE rule", "the weights of S_a, S_b, S_c, two exponents, rho and 4 thresholds"),
    "inliers": ("ORB-SLAM3's inlier rule", "its 4 thresholds, in inliers"),
}
"""Each family's rule and what its fit moves, in words (jsve.fitting._space)."""
PARAMETER_TEXT = {
    "w_a": "weight of S_a",
    "u_b": "share of S_b in the rest",
    "p": "exponent, outer power mean",
    "q": "exponent, inner power mean",
    "rho": "S_a's inlier-ratio scale",
    "imu_init": "fail below, IMU initialised",
    "not_init": "fail below, IMU not initialised",
    "reloc": "fail below, after relocalisation",
    "recovery": "back to OK above",
    "weight_a": "weight of S_a",
    "weight_b": "weight of S_b (derived)",
    "weight_c": "weight of S_c (derived)",
}
"""Every fitted parameter in words (jsve.core._sve.Combination, jsve.core._rules.Thresholds,
jsve.fitting._space.ParamSpace.derived); tests/test_report.py checks that it covers them all."""
FOLD_KIND_TEXT = {
    "kfold": "k-fold",
    "leave-one-sequence-out": "leave-one-sequence-out",
    "leave-one-disturbance-out": "leave-one-disturbance-out",
    "-": "(not fitted)",
}
SIMULATED_WORDS = ("simulat",)
"""A data source naming one of these is simulated (study.json's data description)."""
RARELY_SWITCHES = 0.001
"""A fitted rule that rejects less than this share of frames practically never switches: the headline
says so."""


@dataclass(frozen=True)
class StudyFolder:
    """A study folder's tables and what the report derives from them (jsve.report._derive).

    Attributes:
        out: the folder. study: study.json. fitted: fitted_<family>.json by family.
        scoring: the fit's penalty, support policy and run weighting.
        overview: rule_overview of runs.parquet; levels: level_table (None without disturbance levels).
        heldout_summary, params, heat, sve_levels: the study's tables (None where absent).
        param_table, notes: parameter_table of params; rec: the recommended fitted rule (None without a
            held-out comparison).
    """

    out: Path
    study: dict
    fitted: dict
    scoring: derive.Scoring
    overview: pd.DataFrame
    levels: pd.DataFrame | None
    heldout_summary: pd.DataFrame | None
    params: pd.DataFrame | None
    heat: pd.DataFrame | None
    sve_levels: pd.DataFrame | None
    param_table: pd.DataFrame | None
    notes: list
    rec: derive.Recommendation | None


def read_study(out: Path) -> StudyFolder:
    """Read a study folder's tables and derive the report's numbers.

    Raises:
        FileNotFoundError: no runs.parquet (the study has not finished its evaluation stage).
    """
    study = read_json(out / "study.json")
    cfg = study.get("config", {})
    runs = read_table(out, "runs")
    if runs is None:
        raise FileNotFoundError(
            f"{out}: no runs.parquet; the study has not finished (rerun `jsve fit` or `jsve demo` into it)"
        )
    heldout_summary, params = read_table(out, "heldout_summary"), read_table(out, "params")
    fitted = {p.stem.removeprefix("fitted_"): read_json(p) for p in sorted(out.glob("fitted_*.json"))}
    scoring = derive.Scoring(
        penalty=float(cfg.get("failure_penalty", DEFAULT_FAILURE_PENALTY_M)),
        support=str(cfg.get("support", "penalise")),
        balance_by=tuple(study.get("balance_by", GROUP_COLUMNS)),
        loss=str(cfg.get("loss", "raw" if "failure" not in cfg else "bounded")),
        failure=str(cfg.get("failure", "strict")),  # a study that records no failure setting is strict
    )
    scored = derive.scored_runs(runs, scoring)
    param_table, notes = derive.parameter_table(params, fitted) if params is not None else (None, [])
    return StudyFolder(
        out=out,
        study=study,
        fitted=fitted,
        scoring=scoring,
        overview=derive.rule_overview(scored),
        levels=derive.level_table(scored) if has_levels(runs) else None,
        heldout_summary=heldout_summary,
        params=params,
        heat=read_table(out, "heatmap"),
        sve_levels=read_table(out, "sve_levels"),
        param_table=param_table,
        notes=notes,
        rec=derive.recommend(heldout_summary, list(fitted)) if heldout_summary is not None else None,
    )


def _param_text(value, lo: float, hi: float) -> str:
    """A parameter value to 0.5 % of its search range [lo, hi] (3 decimals where the range is unknown)."""
    if value is None or not np.isfinite(value):
        return "-"
    return fixed(value, decimals_for(hi - lo))


def _held_values(fitted: dict, family: str, skip: tuple[str, str]) -> dict[str, str]:
    """The fitted values of a family's parameters other than `skip`, in the rule's parameter order."""
    rec = fitted.get(family, {})
    free = rec.get("space", {}).get("free", {})
    params = rec.get("params", {})
    out = {}
    for name in [*param_names(family), *sorted(set(params) - set(param_names(family)))]:
        if name in skip or name not in params:
            continue
        value = params[name]
        lo, hi = free.get(name, (float("nan"), float("nan")))
        out[name] = _param_text(value, lo, hi)
    return out


def _differs(name: str, family: str, fitted: dict, skip: tuple[str, str]) -> str:
    """How a preset's own parameters differ from the surface's held values, in words."""
    own = {k: float(v) for k, v in rule_params(preset(name)).items() if k not in skip}
    held = {k: float(v) for k, v in fitted.get(family, {}).get("params", {}).items() if k not in skip}
    other = [k for k in own if k in held and not np.isclose(own[k], held[k])]
    if not other:
        return "its other parameters are the fit's"
    if len(other) > 3:
        return f"{len(other)} other parameters differ from the fit's"
    return ", ".join(f"{k} {number(own[k], 3)}" for k in other)


def _heatmap_subset_note(g: pd.DataFrame) -> str:
    """A sentence where the heat map was scored on a subset of the runs (StudyConfig.heatmap_runs), so
    that nobody reads its cells as the objective the fit and the presets are scored on."""
    if "n_runs" not in g or "n_weighted" not in g:  # a study written before heatmap_runs
        return ""
    scored, weighted = int(g["n_runs"].iloc[0]), int(g["n_weighted"].iloc[0])
    if scored >= weighted:
        return ""
    return (
        f" The surface is scored on {number(scored)} of the {number(weighted)} runs (the first of the "
        "study's stratified order, `heatmap_runs`), so a cell is an estimate of the objective and can "
        "differ from the fit's and the presets' scores, which are over every run, by the subset's "
        "sampling error."
    )


def _heatmap_blocks(heat, fitted, overview, fig_dir) -> list:
    blocks: list = []
    if heat is None:
        return blocks
    scores = overview.set_index("rule")["objective"] if overview is not None else pd.Series(dtype=float)
    for family, g in heat.groupby("family", sort=True):
        family = str(family)
        x_name, y_name = str(g["x_name"].iloc[0]), str(g["y_name"].iloc[0])
        skip = (x_name, y_name)
        rec = fitted.get(family)
        fit = (rec["params"][x_name], rec["params"][y_name], rec["objective"]) if rec else None
        presets = {}
        base = BASELINES.get(family)
        if base is not None and base in scores.index:
            th = rule_params(preset(base))
            presets[base] = (
                float(th[x_name]),
                float(th[y_name]),
                float(scores[base]),
                _differs(base, family, fitted, skip),
            )
        held = _held_values(fitted, family, skip)
        path, info = figures.figure_heatmap(
            g, fig_dir / f"heatmap_{family}.png", fit=fit, presets=presets, held=held
        )
        listed = ", ".join(f"{k} {v}" for k, v in held.items())
        text = (
            f"The {family} family's objective over {x_name} x {y_name}, with its other "
            f"{count(len(held), 'parameter')} held at the fit ({listed})."
        )
        if info.flat:
            text += (
                f" The surface is flat: {cm(info.low)} cm everywhere (it varies by "
                f"{span_mm(info.high - info.low)}), so at the fit these two thresholds do not change the "
                "objective; it is drawn in one colour."
            )
        else:
            text += f" It spans {cm(info.low)} to {cm(info.high)} cm."
        text += _heatmap_subset_note(g)
        for name, (_, _, score, differs) in presets.items():
            text += (
                f" `{name}` is drawn at its thresholds with its own score, {cm(score)} cm ({differs}): the "
                "cell under it holds the fit's other parameters, not its own."
            )
        blocks += [
            Sub(f"Objective over two thresholds: {family}"),
            text,
            Figure(path, f"objective over {x_name} x {y_name} ({family})"),
        ]
    return blocks


def _heldout_table(rows: pd.DataFrame, support: str | None) -> pd.DataFrame:
    out = []
    for d in rows.to_dict("records"):
        row = {
            "rule": d["rule"],
            "fold kind": FOLD_KIND_TEXT.get(d["fold_kind"], d["fold_kind"]),
            "runs": d["n_runs"],
            "held-out objective, cm [95 % CI]": cm_ci(d["mean_loss"], d["ci_low"], d["ci_high"]),
            "failed runs": percent(d["failure_rate"]),
            "coverage": percent(d["coverage"]),
        }
        if "unsupported" in d:
            row["runs out of support"] = percent(d["unsupported"])
        for base in BASELINES.values():
            key = f"diff_vs_{base}"
            present = key in d and pd.notna(d[key])
            row[f"vs {base}, cm [CI]"] = (
                cm_ci(d[key], d[f"{key}_ci_low"], d[f"{key}_ci_high"], sign=True) if present else "-"
            )
        out.append(row)
    return pd.DataFrame(out)


def _parameter_view(table: pd.DataFrame, family: str) -> pd.DataFrame:
    rows = []
    base = BASELINES.get(family, "preset")
    for d in table[table["family"] == family].to_dict("records"):
        lo, hi = d["lo"], d["hi"]
        fmt = lambda v, lo=lo, hi=hi: _param_text(v, lo, hi)  # noqa: E731
        row = {
            "parameter": d["parameter"],
            "meaning": PARAMETER_TEXT.get(d["parameter"], ""),
            "fitted": fmt(d["value"]),
            "95 % CI": f"[{fmt(d['ci_low'])}, {fmt(d['ci_high'])}]",
            "search range": f"[{fmt(lo)}, {fmt(hi)}]" if np.isfinite(lo) else "-",
            base: fmt(d["baseline"]) if d["baseline"] is not None else "-",
        }
        if family in derive.COUNT_FAMILIES:
            row["acts as"] = d["acts_as"] or "-"
        row["flags"] = "; ".join(d["flags"]) or "-"
        rows.append(row)
    return pd.DataFrame(rows)


def _refit_text(params: pd.DataFrame | None) -> str:
    """What a bootstrap resample's refit chose from, in words: with a local design (params' `local`,
    the fit included, above 1) the best of the search and of the design; without one (the default
    study) the best of the search's settings and the fit, a coarse interval."""
    local = int(params["local"].max()) if params is not None and "local" in params else 0
    if local == 1:
        return (
            "each resample's best of the search's settings, under halving its last rung's survivors, "
            "and the fit; no local design, so an interval is only as fine as those settings are dense: "
            "`jsve fit --thorough` adds 1,024 settings around the fit"
        )
    return "the best setting of the search and a dense local design under each resample's weights"


def _method_bullets(study: dict, scoring: derive.Scoring) -> list[str]:
    cfg = study.get("config", {})
    fit = cfg.get("fit", {})
    items = scoring_bullets(
        scoring,
        align=str(cfg.get("align", "se3")),
        min_coverage=cfg.get("min_coverage", 0.0) or 0.0,
        switch_model=cfg.get("switch_model"),
        support=scoring.support if cfg.get("support") else None,  # a study from before the setting: none
    )
    if fit:
        design = DESIGN_TEXT.get(fit.get("design"), fit.get("design", ""))
        search = f"{number(fit.get('n_search'))} {design} settings per family plus the presets"
        polish = f"{count(int(fit.get('n_starts', 1)), 'Nelder-Mead polish')} of {fit.get('nm_steps')} steps"
        if fit.get("relaxed"):
            polish += f", then relaxed BFGS ({fit.get('bfgs_steps')} steps)"
        items.append(f"Search: {search}, then {polish}.")
    kinds = []
    if cfg.get("kfold"):
        kinds.append(f"{cfg['kfold']}-fold")
    kinds += [f"leave-one-{c}-out" for c in cfg.get("leave_one_out", [])]
    if kinds:
        items.append(
            f"Cross-validation: {words_list(kinds)}; each run is held out once per kind and the fitted "
            "rules are refitted without it (a leave-one-out kind needs two values of its column)."
        )
    if cfg.get("n_boot"):
        level = cfg.get("level", 0.95)
        items.append(
            f"Intervals: {100 * level:g} % percentile bootstrap over runs, {number(cfg['n_boot'])} "
            "resamples; differences are paired (the same resampled runs for both rules; negative: better)."
        )
    data = study.get("data") or {}
    if data:
        facts = [f"{k}: {_fact(v)}" for k, v in data.items() if k != "source"]
        items.append(
            f"Data: {data.get('source', 'not described')}"
            + (f"; {'; '.join(facts)}" if facts else "")
            + f"; {number(study.get('n_runs'))} runs, {number(study.get('n_frames'))} frames."
        )
    return items


def _fact(value) -> str:
    if isinstance(value, list):
        if len(set(value)) == 1:
            return number(value[0])
        return " to ".join(number(v) for v in value)
    return number(value)


def _headline(s: StudyFolder) -> list:
    study, scoring, fitted, rec = s.study, s.scoring, s.fitted, s.rec
    heldout_summary, overview, param_table = s.heldout_summary, s.overview, s.param_table
    cfg = study.get("config", {})
    blocks: list = []
    families = [f for f in cfg.get("families", list(fitted)) if f in fitted] or list(fitted)
    what = []
    for f in families:
        name, moves = FAMILY_TEXT.get(f, (f"the {f} rule", "its parameters"))
        free = list(fitted[f].get("space", {}).get("free", {}))
        if free and f in FAMILY_TEXT and len(free) < len(param_names(f)):
            moves = ", ".join(n for n in param_names(f) if n in free)  # a reduced space: what moved
        what.append(f"{name} ({count(len(free), 'free parameter')}: {moves})" if free else name)
    source = (study.get("data") or {}).get("source", "not described")
    blocks.append(
        f"**What was fitted.** {_capital(words_list(what))}. Each fit minimises the objective, the mean "
        f"per-run ATE RMSE of the trajectory the front-end saves"
        f"{f', capped at {metres(scoring.penalty)},' if scoring.loss == 'bounded' else ''} "
        f"with a failed run charged {metres(scoring.penalty)}, over "
        f"{number(study.get('n_runs'))} runs ({number(study.get('n_frames'))} frames; data: {source})."
    )
    if rec is None or heldout_summary is None:
        blocks.append("No held-out comparison in this folder: nothing is recommended.")
        return blocks
    rows = heldout_summary[heldout_summary["rule"] == rec.rule]
    blocks.append(
        f"**Recommended: `{rec.rule}`** ({rec.reason}). Its rule file `{rule_file(rec.rule)}` works "
        f"as it is: `jsve evaluate LOGS --rule {rule_file(rec.rule)}`."
    )
    if param_table is not None and not param_table.empty:
        blocks.append(Table(_parameter_view(param_table, rec.family)))
    # the held-out gain
    first = rows.iloc[0]
    sentences = []
    for base in BASELINES.values():
        key = f"diff_vs_{base}"
        if key not in first or not pd.notna(first[key]):
            continue
        d, lo, hi = first[key], first[f"{key}_ci_low"], first[f"{key}_ci_high"]
        word = derive.verdict(lo, hi)
        if word == "better":
            sentences.append(f"better than `{base}` by {cm(-d)} cm (95 % CI {cm(-hi)} to {cm(-lo)})")
        elif word == "worse":
            sentences.append(f"worse than `{base}` by {cm(d)} cm (95 % CI {cm(lo)} to {cm(hi)})")
        else:
            sentences.append(
                f"not clearly different from `{base}` ({cm(d, sign=True)} cm, 95 % CI {cm(lo, sign=True)} to "
                f"{cm(hi, sign=True)}: it contains 0)"
            )
    kind = FOLD_KIND_TEXT.get(first["fold_kind"], first["fold_kind"])
    blocks.append(
        f"**Held-out gain.** On held-out runs ({kind}) it scores "
        f"{cm_ci(first['mean_loss'], first['ci_low'], first['ci_high'])} cm"
        + (f": {words_list(sentences)}." if sentences else ".")
        + " Intervals: paired bootstrap over runs. Every fold kind (differences: negative is better):"
    )
    blocks.append(Table(_heldout_table(rows, scoring.support).drop(columns=["rule"])))
    # how often it switches
    if overview is not None and {"rejected", "reached_lost"} <= set(overview.columns):
        o = overview.set_index("rule")
        parts = [
            f"`{b}` {percent(o.loc[b, 'rejected'])} and {percent(o.loc[b, 'reached_lost'])}"
            for b in BASELINES.values()
            if b in o.index
        ]
        mine = o.loc[rec.rule]
        blocks.append(
            f"**How often it switches.** Fitted on all runs and replayed on them, `{rec.rule}` rejects "
            f"{percent(mine['rejected'])} of frames and {percent(mine['reached_lost'])} of runs reach LOST"
            + (f" ({'; '.join(parts)})." if parts else ".")
        )
    caveats = _caveats(s, rec, heldout_summary)
    return [*blocks, "**Caveats.**", Bullets(tuple(caveats))]


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


def trust_sentence(rule: str, changed: float, switch_model: str = "orbslam3") -> str:
    """Whether `rule`'s replays stay where replays under `switch_model` agreed with re-runs of the real
    front-end (jsve.evaluation.trusted_share): the warning `jsve fit` prints, or that it stays."""
    warning = trust_region_warning(rule, changed, switch_model=switch_model)
    if warning is not None:
        return warning + "."
    return (
        f"`{rule}` changes {percent(changed)} of the recordings' decisions, within the "
        f"{percent(trusted_share(switch_model))} up to which replays under switch model `{switch_model}` "
        "agreed with re-runs of the real ORB-SLAM3 (docs/validation.md)."
    )


def _caveats(s: StudyFolder, rec: derive.Recommendation, heldout_summary: pd.DataFrame) -> list[str]:
    study, scoring, overview, param_table = s.study, s.scoring, s.overview, s.param_table
    cfg = study.get("config", {})
    source = str((study.get("data") or {}).get("source", ""))
    items = []
    if any(w in source.lower() for w in SIMULATED_WORDS):
        items.append(
            f"Simulated data, from the {source}: its vision model decides every number here. They "
            "carry over to the real ORB-SLAM3 only as far as the simulator's calibration holds "
            "(docs/simulator.md, docs/frontend.md)."
        )
    model = cfg.get("switch_model", "orbslam3")
    if model == "orbslam3":
        items.append(
            "Switch model `orbslam3`: a rejected frame keeps its logged pose, so a rule changes the error "
            "only through LOST, resets and coverage. The fit can learn to avoid LOST, not to reject bad "
            "poses."
        )
    elif model == "imu-coast":
        items.append(
            "Switch model `imu-coast`: a frame in RECENTLY_LOST takes the IMU prediction, so rejecting a "
            "frame helps only where the IMU beats the logged visual pose."
        )
    if overview is not None and "changed" in overview and rec.rule in set(overview["rule"]):
        changed = float(overview.set_index("rule").loc[rec.rule, "changed"])
        items.append(trust_sentence(rec.rule, changed, model))
    if overview is not None and "rejected" in overview:
        o = overview.set_index("rule")
        if rec.rule in o.index and o.loc[rec.rule, "rejected"] < RARELY_SWITCHES:
            items.append(
                f"`{rec.rule}` practically never switches ({percent(o.loc[rec.rule, 'rejected'])} of frames "
                "rejected): it wins by never reaching LOST."
            )
    first = heldout_summary[heldout_summary["fold_kind"] == heldout_summary["fold_kind"].iloc[0]]
    first = first.set_index("rule")
    for base in BASELINES.values():
        if base in first.index and first.loc[base, "failure_rate"] > 0:
            share = first.loc[base, "failure_rate"]
            total, part = cm(first.loc[base, "mean_loss"]), cm(share * scoring.penalty)
            items.append(
                f"The failure penalty drives the comparison: of `{base}`'s {total} cm, {part} cm is the "
                f"penalty of its failed runs ({percent(share)} of runs at {metres(scoring.penalty)} each); "
                "another penalty moves every gain."
            )
            break
    if "unsupported" in heldout_summary:
        share = float(heldout_summary[heldout_summary["rule"] == rec.rule]["unsupported"].max())
        if share > 0:
            items.append(
                f"Support: up to {percent(share)} of `{rec.rule}`'s held-out runs leave the logs' support "
                f"(policy `{scoring.support}`: {SUPPORT_TEXT.get(scoring.support, '')}); what those runs "
                "would have done is unknown."
            )
        else:
            items.append(
                f"Support: none of `{rec.rule}`'s held-out runs leaves the logs' support, so every score is "
                "backed by recorded poses."
            )
    if param_table is not None and not param_table.empty:
        mine = param_table[(param_table["family"] == rec.family) & param_table["flags"].map(bool)]
        if len(mine):
            kinds = sorted({f.split(":")[0] for flags in mine["flags"] for f in flags})
            items.append(
                f"{count(len(mine), 'parameter')} of `{rec.rule}` flagged ({', '.join(kinds)}): see Fitted "
                "parameters. A flat or wide optimum means other values score the same."
            )
    return items


def study_sections(s: StudyFolder, fig_dir: Path) -> list[Section]:
    """The study's report as sections; the figures are written to `fig_dir`."""
    study, scoring, fitted, overview = s.study, s.scoring, s.fitted, s.overview
    heldout_summary, param_table, notes = s.heldout_summary, s.param_table, s.notes
    sections = [Section("Headline", _headline(s))]
    figure_blocks: list = []
    rows = derive.heldout_rows(heldout_summary) if heldout_summary is not None else None
    if rows is not None:
        figure_blocks += [
            Sub("Held-out objective per rule"),
            "Each fitted rule per fold kind, each preset once (presets are not fitted: every fold kind "
            "scores them alike). Bars: the mean over held-out runs; whiskers: 95 % bootstrap intervals.",
            Figure(figures.figure_heldout(rows, fig_dir / "heldout.png"), "held-out objective per rule"),
        ]
    level_figure, level_section = level_sections(s.levels, fig_dir)
    figure_blocks += level_figure
    figure_blocks += _heatmap_blocks(s.heat, fitted, overview, fig_dir)
    if s.sve_levels is not None:
        for dist in sorted(s.sve_levels["disturbance"].astype(str).unique()):
            if dist == "none":
                continue
            path = figures.figure_sve_levels(s.sve_levels, dist, fig_dir / f"sve_levels_{dist}.png")
            figure_blocks += [Sub(f"SVE per {dist} level"), Figure(path, f"SVE per {dist} level")]
    if figure_blocks:
        sections.append(Section("Figures", figure_blocks))
    if rows is not None:
        text = (
            "Each run is held out once per fold kind; fitted rules are refitted without it. 95 % bootstrap "
            "intervals over runs; differences are paired (negative: the rule beats the baseline)."
        )
        if scoring.support == "exclude":
            text += (
                " Support policy exclude: every rule is scored on the held-out runs all rules support "
                "(runs); runs out of support is each rule's share of all held-out runs."
            )
        sections.append(Section("Held-out comparison", [text, Table(_heldout_table(rows, scoring.support))]))
    if param_table is not None and not param_table.empty:
        blocks: list = [
            "Fitted on all runs; 95 % intervals from refits on bootstrap resamples of the runs ("
            + _refit_text(s.params)
            + "). Flags: not "
            f"identified (the interval spans at least {100 * derive.NOT_IDENTIFIED_SPAN:.0f} % of the search "
            f"range), at a bound (within {100 * derive.AT_BOUND_SHARE:.0f} % of the range from a bound), "
            "outside its interval (the fit is not inside its own bootstrap interval), implausible (an inlier "
            f"threshold below {derive.MIN_PLAUSIBLE_INLIERS}). Inlier counts are integers, so a threshold "
            "acts as the whole number in 'acts as'."
        ]
        for family in dict.fromkeys(param_table["family"]):
            name, moves = FAMILY_TEXT.get(family, (family, "its parameters"))
            blocks += [Sub(f"{family}: {name}, {moves}"), Table(_parameter_view(param_table, family))]
        if notes:
            blocks.append("Shown once (the same numbers): " + "; ".join(notes) + ".")
        sections.append(Section("Fitted parameters", blocks))
    sections.append(
        Section(
            "All runs, per rule",
            [
                "Every rule replayed on all runs (the fitted rules as fitted on all of them, so their rows "
                "are in-sample). " + OVERVIEW_TEXT,
                Table(overview_table(overview)),
            ],
        )
    )
    if level_section is not None:
        sections.append(level_section)
    sections.append(Section("Method", [Bullets(tuple(_method_bullets(study, scoring)))]))
    stage_blocks = []
    for family, record in fitted.items():
        stages = pd.DataFrame(
            [
                {
                    "stage": s["stage"],
                    "objective, cm": cm(s["objective"]),
                    "seconds": fixed(s.get("seconds", float("nan")), 1)
                    + (f" (all {s['simplexes']} simplexes)" if s.get("simplexes", 1) > 1 else ""),
                }
                for s in record.get("stages", [])
            ]
        )
        text = (
            f"`fitted_{family}.json`: objective {cm(record.get('objective'))} cm, failed runs "
            f"{percent(record.get('failure_rate'))}, coverage {percent(record.get('coverage'))}."
        )
        if "n_unsupported" in record:
            text += (
                f" The rule's replay leaves the logs' support on {count(record['n_unsupported'], 'run')} "
                f"(weighted share {percent(record['unsupported_rate'])}); "
                f"{count(record['n_excluded'], 'run')} excluded from the objective."
            )
        stage_blocks += [Sub(f"{family}"), text, Table(stages)]
    if stage_blocks:
        sections.append(
            Section(
                "Fit stages", [Details("the objective after each stage of each fit", tuple(stage_blocks))]
            )
        )
    return sections
