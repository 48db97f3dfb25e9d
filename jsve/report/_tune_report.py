"""The report of a `jsve tune` folder: the verified rule first, then the race, the replay against the
front-end, and per-level tables with failures and events.

    Headline            the tuned rule, its held-out paired differences to the baselines (95 % BCa and t
                        intervals), how often it switches, the runs spent against the seed's protocol
    Held-out check      every baseline and level; figure check.png
    The race            per round: each candidate's origin, the replay's prediction, its measured loss,
                        when it was eliminated and why, the decision
    Replay against the front-end   predicted against measured difference to the incumbent, per
                        candidate, pooled; the pick made on one half of the seeds scored on the other
    Per level           the training and held-out runs per rule and level: loss, failures, events
    Method              the study

Every number comes from the folder's files (tune.json, runs.csv, check.csv, agreement.csv, rounds/*).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from jsve.report._document import Bullets, Details, Figure, Section, Sub, Table
from jsve.report._format import cm, cm_ci, number, percent

SEED_RUNS_PER_SETTING = 100
"""The seed study's protocol: 100 runs of the front-end per setting and build (rule)..."""
SEED_SETTINGS = 31
"""... over its 31 disturbance settings (blur, downsampling and occlusion levels)."""

TUNE_TITLE = "jsve tuning report"


def read_tune(folder: Path) -> dict:
    """The tuning's files: state (tune.json), runs, check, agreement, rounds (proposal, race, decision)."""
    state = json.loads((folder / "tune.json").read_text())
    if state.get("status") != "done":
        raise ValueError(
            f"{folder}: the tuning has not finished (tune.json status {state.get('status')!r}); "
            "progress.json and runs.csv show where it is"
        )
    rounds = []
    for sub in sorted((folder / "rounds").glob("*"), key=lambda p: int(p.name)):
        rounds.append(
            {
                "proposal": json.loads((sub / "proposal.json").read_text()),
                "predictions": pd.read_csv(sub / "predictions.csv"),
                "race": _csv(sub / "race.csv"),
                "decision": _csv(sub / "decision.csv"),
            }
        )
    return {
        "state": state,
        "runs": pd.read_csv(folder / "runs.csv"),
        "check": pd.read_csv(folder / "check.csv"),
        "agreement": _csv(folder / "agreement.csv"),
        "rounds": rounds,
        "folder": folder,
    }


def _csv(path: Path) -> pd.DataFrame:
    try:
        return pd.read_csv(path)
    except pd.errors.EmptyDataError:
        return pd.DataFrame()


def apart(row: dict) -> str:
    """The check's two questions apart, in words: lost runs (failed or diverged; exact McNemar on the
    pairs where one rule alone lost track) and accuracy on the pairs neither lost; empty for a check.csv
    without them."""
    if "lost_p" not in row or not np.isfinite(row["lost_p"]):
        return ""
    interval = cm_ci(
        row["tracked_mean_diff_m"], row["tracked_bca_low_m"], row["tracked_bca_high_m"], sign=True
    )
    tracked = f"{interval} cm" if row["tracked_pairs"] else "no pair"
    return (
        f"Apart: pairs where only the rule lost track (failed or diverged) {row['rule_only_lost']}, "
        f"only the baseline {row['baseline_only_lost']} (exact McNemar p = {number(row['lost_p'], 3)}); "
        f"on the {row['tracked_pairs']} pairs neither lost, {tracked} (95 % BCa)."
    )


def _arm_rows(runs: pd.DataFrame, study: dict) -> pd.DataFrame:
    t = runs[runs.dataset.isin(study["heldout"]) & (runs.seed >= study["verify_seed_base"])].copy()
    t["arm"] = t["candidate"] + "@" + t["switch_model"]
    return t


def headline(data: dict) -> Section:
    from jsve.tuning._race import RESOLUTION_M, check_verdict

    state, study = data["state"], data["state"]["study"]
    tuned = state["tuned"]
    rule = json.loads((data["folder"] / "rules" / f"{tuned}.json").read_text())
    params = ", ".join(
        f"{k} {number(v)}" for part in ("combination", "thresholds") for k, v in rule.get(part, {}).items()
    )
    how = (
        "the incumbent after the race: it beat the rule before it on the training runs"
        if state["tuned_is_incumbent"]
        else f"the best challenger: no candidate beat `{study['incumbent']}` on the training runs, so the "
        "check measures how far the best one is from the baselines"
    )
    items = [
        f"Tuned **{tuned}** ({study['family']} family, switch model `{study['switch_model']}`): {how}; "
        f"stopped: {state['stopped']}.",
        f"Parameters: {params}.",
    ]
    check = data["check"]
    for row in check[check.scope == "all held-out"].to_dict("records"):
        half = (row["bca_high_m"] - row["bca_low_m"]) / 2
        items.append(
            f"vs `{row['baseline']}` on {row['pairs']} held-out runs: "
            f"{cm_ci(row['mean_diff_m'], row['bca_low_m'], row['bca_high_m'], sign=True)} cm "
            f"(95 % BCa; t {cm(row['t_low_m'], sign=True)} to {cm(row['t_high_m'], sign=True)} cm; "
            f"half-width {cm(half)} cm), Wilcoxon p = {number(row['wilcoxon_p'], 3)}: "
            f"**{check_verdict(row)}**; better on {row['better']}, worse on {row['worse']}; "
            f"failed runs {row['rule_failed']} against "
            f"{row['baseline_failed']}; at this spread a half-width of {cm(RESOLUTION_M)} cm takes about "
            f"{row['pairs_for_resolution']} pairs. {apart(row)}"
        )
    arms = _arm_rows(data["runs"], study)
    if len(arms):
        sw = arms.groupby("arm").agg(switches=("switches", "mean"), share=("recently_lost_share", "mean"))
        items.append(
            "Switching on the held-out runs (OK to RECENTLY_LOST per run; share of tracked frames in "
            "RECENTLY_LOST): "
            + "; ".join(f"`{a}` {r.switches:.1f}, {percent(r.share)}" for a, r in sw.iterrows())
            + "."
        )
    items.append(cost_line(data))
    return Section("Headline", [Bullets(tuple(items))])


def cost_line(data: dict) -> str:
    """Runs spent, against the seed's protocol and a full grid of the same candidates, and their time."""
    runs, study = data["runs"], data["state"]["study"]
    raced = {c["name"] for r in data["rounds"] for c in r["proposal"]["candidates"]}
    seeds = len(data["rounds"]) * study["seeds_per_round"]
    check_runs = (1 + len(study["baselines"])) * len(study["heldout"]) * study["verify_seeds"]
    grid = len(raced) * len(study["train"]) * seeds + check_runs
    rules = len(raced) + len(study["baselines"])
    datasets = len(study["train"]) + len(study["heldout"])
    wall, cpu = runs["wall_s"].dropna(), runs["cpu_s"].dropna()
    return (
        f"Runs spent: {len(runs)} (budget {study['budget']}). A full grid of the same {len(raced)} "
        f"candidates on every training run, with the same check: {grid}. The seed's protocol, "
        f"{SEED_RUNS_PER_SETTING} runs per setting and build: {SEED_RUNS_PER_SETTING * datasets * rules:,} "
        f"for these {datasets} datasets and {rules} rules ({SEED_RUNS_PER_SETTING * SEED_SETTINGS:,} per "
        f"build over its {SEED_SETTINGS} settings). Front-end time: {wall.sum() / 3600:.2f} h of run "
        f"wall time, {wall.mean():.1f} s a run"
        + (f" ({cpu.mean():.1f} s CPU)." if len(cpu) else " (no CPU time recorded).")
    )


def check_section(data: dict, fig_dir: Path) -> Section:
    from jsve.report._tune_figures import figure_check
    from jsve.tuning._race import check_verdict

    check = data["check"].copy()
    table = pd.DataFrame(
        {
            "scope": check["scope"],
            "baseline": check["baseline"],
            "pairs": check["pairs"],
            "difference, cm (BCa 95 %)": [
                cm_ci(r.mean_diff_m, r.bca_low_m, r.bca_high_m, sign=True) for r in check.itertuples()
            ],
            "t 95 %, cm": [
                f"{cm(r.t_low_m, sign=True)} to {cm(r.t_high_m, sign=True)}" for r in check.itertuples()
            ],
            "median, cm": [cm(x, sign=True) for x in check["median_diff_m"]],
            "Wilcoxon p": [number(x, 3) for x in check["wilcoxon_p"]],
            "better / worse": [f"{r.better} / {r.worse}" for r in check.itertuples()],
            "failed (rule / baseline)": [
                f"{r.rule_failed} / {r.baseline_failed}" for r in check.itertuples()
            ],
            **(
                {
                    "lost track alone (rule / baseline), p": [
                        f"{r.rule_only_lost} / {r.baseline_only_lost}, {number(r.lost_p, 3)}"
                        for r in check.itertuples()
                    ],
                    "neither lost: pairs, cm (BCa)": [
                        f"{r.tracked_pairs}, "
                        + cm_ci(r.tracked_mean_diff_m, r.tracked_bca_low_m, r.tracked_bca_high_m, sign=True)
                        for r in check.itertuples()
                    ],
                }
                if "lost_p" in check
                else {}
            ),
            "verdict": [check_verdict(r) for r in check.to_dict("records")],
        }
    )
    blocks = [
        f"The tuned rule `{check['rule'].iloc[0] if len(check) else ''}` against each baseline on the "
        "held-out datasets with fresh seeds, paired by (dataset, seed), on the bounded loss (difference "
        "rule - baseline; "
        "negative: the tuned rule is better). A failed run costs the penalty, so a few failures can "
        "carry the mean: lost runs (failed, or diverged past the loss's cap) are also tested apart (pairs "
        "where one rule alone lost track, and the exact McNemar p over them), and the difference is also "
        "given over the pairs neither rule lost.",
        Table(table),
    ]
    if len(check):
        blocks.append(Figure(figure_check(check, fig_dir / "check.png"), "held-out paired differences"))
    return Section("Held-out check", blocks)


def race_section(data: dict) -> Section:
    blocks = []
    runs = data["runs"]
    model = data["state"]["study"]["switch_model"]
    for k, r in enumerate(data["rounds"]):
        proposal, race, decision = r["proposal"], r["race"], r["decision"]
        incumbent = proposal["candidates"][0]["name"]
        summary = data["state"]["rounds"][k]
        seeds = summary["seeds"]
        pred = (
            r["predictions"]
            .groupby("candidate")
            .agg(pred=("predicted_loss_m", "mean"), changed=("changed_fraction", "mean"))
        )
        mine = runs[
            (runs.switch_model == model)
            & runs.seed.isin(seeds)
            & runs.dataset.isin(data["state"]["study"]["train"])
        ]
        measured = mine.groupby("candidate").agg(
            loss=("loss_m", "mean"), runs=("loss_m", "size"), failed=("failed", "sum")
        )
        rows = []
        for c in proposal["candidates"]:
            name = c["name"]
            out = race[race.candidate == name].query("eliminated") if len(race) else pd.DataFrame()
            dec = decision[decision.candidate == name] if len(decision) else pd.DataFrame()
            fate = (
                f"out after seed {int(out.iloc[0].after_seed)} (worse than {out.iloc[0].best}, "
                f"Holm p {number(out.iloc[0].p_holm, 3)})"
                if len(out)
                else "incumbent"
                if name == incumbent
                else f"survived; beats the incumbent: {'yes' if dec.iloc[0].beats else 'no'} "
                f"(Holm p {number(dec.iloc[0].p_holm, 3)})"
                if len(dec)
                else "survived"
            )
            m = measured.loc[name] if name in measured.index else None
            rows.append(
                {
                    "candidate": name,
                    "origin": c["origin"],
                    "replay: predicted, cm": cm(pred.loc[name, "pred"]) if name in pred.index else "",
                    "changed decisions": percent(pred.loc[name, "changed"]) if name in pred.index else "",
                    "measured, cm": cm(m["loss"]) if m is not None else "",
                    "runs": int(m["runs"]) if m is not None else 0,
                    "failed": int(m["failed"]) if m is not None else 0,
                    "fate": fate,
                }
            )
        blocks += [
            Sub(f"Round {k}: incumbent {incumbent}, seeds {seeds[0]}-{seeds[-1]}"),
            proposal["note"] + ".",
            Table(pd.DataFrame(rows)),
            f"Decision: {summary['winner'] or 'no candidate beat the incumbent'}"
            + (f" (race stopped: {summary['stopped']})" if summary.get("stopped") else "")
            + ".",
        ]
    return Section("The race", blocks)


def agreement_section(data: dict, fig_dir: Path) -> Section:
    from jsve.report._tune_figures import figure_agreement

    a = data["agreement"]
    if a.empty:
        return Section("Replay against the front-end", ["No raced candidate has both a prediction and runs."])
    alike = a["predicted_diff_m"].nunique() < 2 or a["measured_diff_m"].nunique() < 2
    rho = stats.spearmanr(a["predicted_diff_m"], a["measured_diff_m"]) if len(a) >= 3 and not alike else None
    bias = (a["predicted_diff_m"] - a["measured_diff_m"]).mean()
    picks = []
    for rnd, g in a.groupby("round"):
        pick = g.sort_values("predicted_diff_even_m", kind="stable").iloc[0]
        picks.append(
            f"round {rnd}: the replay's pick on the even seeds, {pick.candidate}, predicted "
            f"{cm(pick.predicted_diff_even_m, sign=True)} cm, measured on the odd seeds "
            f"{cm(pick.measured_diff_odd_m, sign=True)} cm"
        )
    items = [
        f"Each raced candidate's difference to the incumbent, predicted by replaying the incumbent's logs "
        "and measured on the same (dataset, seed) in the loop: mean bias (predicted - measured) "
        f"{cm(bias, sign=True)} cm"
        + (
            f", Spearman {rho.statistic:.2f} (p {number(rho.pvalue, 3)}) over {len(a)} candidates"
            if rho
            else ""
        )
        + ("; no rank correlation: one side gives every candidate the same difference" if alike else ""),
        *picks,
    ]
    table = pd.DataFrame(
        {
            "round": a["round"],
            "candidate": a["candidate"],
            "origin": a["origin"],
            "pairs": a["pairs"],
            "predicted, cm": a["predicted_diff_m"].map(lambda x: cm(x, sign=True)),
            "measured, cm": a["measured_diff_m"].map(lambda x: cm(x, sign=True)),
            "predicted on even seeds, cm": a["predicted_diff_even_m"].map(lambda x: cm(x, sign=True)),
            "measured on odd seeds, cm": a["measured_diff_odd_m"].map(lambda x: cm(x, sign=True)),
        }
    )
    return Section(
        "Replay against the front-end",
        [
            Bullets(tuple(items)),
            Table(table),
            Figure(figure_agreement(a, fig_dir / "agreement.png"), "replay against the front-end"),
        ],
    )


def level_tables(data: dict) -> Section:
    runs = data["runs"].copy()
    study = data["state"]["study"]
    runs["part"] = np.where(runs.dataset.isin(study["heldout"]), "held-out", "training")
    runs["rule"] = runs["candidate"] + "@" + runs["switch_model"]
    g = (
        runs.groupby(["part", "disturbance", "level", "rule"])
        .agg(
            runs=("loss_m", "size"),
            loss=("loss_m", "mean"),
            failed=("failed", "sum"),
            resets=("resets", "sum"),
            new_maps=("new_maps", "sum"),
            loops=("loops", "sum"),
            switches=("switches", "mean"),
        )
        .reset_index()
    )
    g["loss"] = g["loss"].map(cm)
    g = g.rename(columns={"loss": "loss, cm"})
    g["level"] = g["level"].map(lambda x: f"{x:g}")
    g["switches"] = g["switches"].map(lambda x: f"{x:.1f}")
    return Section(
        "Per level",
        [
            "Every rule's runs per disturbance level (loss: mean bounded loss; events: counted in the logs).",
            Details("the table", (Table(g),)),
        ],
    )


def method_section(data: dict) -> Section:
    study = data["state"]["study"]
    keep = {k: v for k, v in study.items() if k not in ("train", "heldout")}
    items = [f"{k}: {v}" for k, v in keep.items()]
    items += [f"train: {', '.join(study['train'])}", f"held out: {', '.join(study['heldout'])}"]
    return Section(
        "Method",
        [
            "A run's loss is the ATE of the trajectory ORB-SLAM3 saves (SE(3)-aligned), capped at the "
            "failure penalty; a run that did not finish, saved no trajectory or covers less than "
            "min_coverage of its frames costs the penalty. Races pair runs by (dataset, seed) and test "
            "with one-sided Wilcoxon signed-rank tests, "
            "Holm-corrected over the candidates tested at once; the check uses fresh seeds on held-out "
            "sequences.",
            Bullets(tuple(items)),
        ],
    )


def tune_sections(folder: Path, fig_dir: Path) -> list[Section]:
    data = read_tune(folder)
    return [
        headline(data),
        check_section(data, fig_dir),
        race_section(data),
        agreement_section(data, fig_dir),
        level_tables(data),
        method_section(data),
    ]


__all__ = ["TUNE_TITLE", "read_tune", "tune_sections"]
