"""Does the replay predict the re-run? Replay every recording under every rule and compare with the
rules' own runs of the real front-end (issue 11; jsve.evaluation's agreement functions hold the
statistics, docs/validation.md the method and criteria).

    python analysis/replay_vs_rerun.py [LOGDIR] [--config validation.toml] [--ground-truth SEQ=GT.csv ...]
        [--rules orbslam3,sve-option2,fit/{switch_model}/fitted_sve.json] [--fitted NAME]
        [--penalty 1.0] [--n-boot 1000] [--seed 0] [-o OUTDIR]

LOGDIR is `jsve frontend run`'s output over one or more rules and switch models
(LOGDIR/<sequence>/<disturbance>-<level>[/<rule>-<model>]/run_<k>.csv). --config is the sweep's config
(sweeps/validation.toml; `validation.toml` in the current folder is read when there is one): it names
LOGDIR, the rules, the switch models, the re-runs planned and the ground truth. A rule may name its
switch model as `{switch_model}` (the fitted rule of each model is its own file); a rule file is named
by its stem, as the front-end names its runs.

Every loss is the bounded loss of jsve.core._objective (a run's saved-trajectory ATE capped at --penalty,
the penalty for a failed run; failures by coverage), the default of every jsve table. Every finished
log is a recording; a `record` run is one of the `record-<model>` protocol, any other
rule's run one of `other-rules`. Each recording is replayed under each rule and switch model, except a
rule's own runs under that rule (those are its re-runs, scored by replaying them under their own rule:
jsve check shows that this reproduces the logged states). A run that ORB-SLAM3 crashed in (its
summary's exit code is not 0; the log stays `.partial`) is a failed re-run, counted. A setting whose
re-runs are fewer than the config's `runs` is still running: it is left out of every number and listed.
Rules are ranked on the `record` recordings only, the ones every rule is replayed on.

Writes into OUTDIR: agreement.csv (per setting, rule, switch model, recording protocol), ranking.csv
(per level: tau, regret@1 of the replay's choice and of the fitted rule, 95 % bootstrap intervals),
verdict.csv (per switch model and protocol, pooled over levels), trust.csv (agreement per bin of the
replay's changed share), deploy.csv (the fitted rule's re-runs against each preset's), cost.csv (the
runs' wall time), unmatched.csv, figures (bland_altman.png, tau_per_level.png, trust_region.png,
deploy.png) and validation.md (the tables and figures for docs/validation.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import tomllib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from jsve.evaluation import (  # noqa: E402
    CHANGED_SHARE_EDGES,
    MAX_ABS_BIAS_M,
    MIN_IN_BAND_RATIO,
    MIN_REPLAYS_PER_BIN,
    MIN_RULES_FOR_VERDICT,
    REGRET_TOLERANCE_M,
    REPLAY_TRUSTED_CHANGED_SHARE,
    SETTING,
    agreement_by_changed_share,
    agreement_summary,
    bootstrap_ranking,
    deploy_differences,
    evaluate,
    pool_draws,
    ranking_verdict,
    replay_rows,
    rerun_summary,
    trusted_changed_share,
    unmatched,
)
from jsve.io import GroundTruth, buckets, load_rules, read_logs, recorded_rule_label  # noqa: E402

KEYS = [*SETTING, "rule", "switch_model"]
LEVEL = [*SETTING, "switch_model"]
GROUP = ["switch_model", "recording"]
"""A verdict's unit: a switch model and a recording protocol."""
DEFAULT_CONFIG = Path("validation.toml")
OTHER_RULES = "other-rules"
"""The protocol of recordings made by another rule in the loop (not `record` mode)."""


# ---------------------------------------------------------------------------------------------------
# Inputs


def recording_label(meta: dict) -> str:
    """The rule and switch model a run ran under, e.g. `orbslam3-orbslam3`, `record-imu-coast`."""
    return recorded_rule_label(meta) or "orbslam3-orbslam3"


def split_label(label: str, models) -> tuple[str, str]:
    """(rule, switch model) of a `<rule>-<model>` folder name: models hold a dash (`imu-coast`)."""
    for model in sorted(models, key=len, reverse=True):
        if label.endswith(f"-{model}"):
            return label[: -len(model) - 1], model
    rule, _, model = label.rpartition("-")
    return rule, model


def summaries(logdir: Path, models) -> pd.DataFrame:
    """Every run's summary (`jsve frontend run` writes one per run): setting, rule, switch_model, run,
    exit_code, wall_seconds (s, the run as a whole) and track_seconds (s, ORB-SLAM3's tracking)."""
    rows = []
    for path in sorted(logdir.rglob("run_*.summary.json")):
        info = json.loads(path.read_text())
        # the summary's folder, not its `log` (a path relative to where the run was started)
        parts = path.parent.relative_to(logdir).parts
        disturbance, _, level = parts[1].rpartition("-")
        rule, model = split_label(parts[2] if len(parts) > 2 else "orbslam3-orbslam3", models)
        rows.append({"sequence": parts[0], "disturbance": disturbance, "level": float(level), "rule": rule,
                     "switch_model": model, "run": int(path.name.split(".")[0].removeprefix("run_")),
                     "exit_code": info.get("exit_code", 0), "wall_seconds": info.get("wall_seconds", np.nan),
                     "track_seconds": info.get("track_seconds", np.nan)})  # fmt: skip
    columns = [*KEYS, "run", "exit_code", "wall_seconds", "track_seconds"]
    return pd.DataFrame(rows, columns=columns)


def crashed_runs(runs_summary: pd.DataFrame) -> pd.DataFrame:
    """Re-runs ORB-SLAM3 crashed in: failed, no error, no coverage."""
    crashed = runs_summary[runs_summary["exit_code"] != 0]
    return crashed[KEYS].assign(rmse=np.nan, failed=True, coverage=0.0, recording="crashed")


def rule_names(args, config: dict, runs) -> list[str]:
    """The rules to replay, templates kept (`fit/{switch_model}/fitted_sve.json`)."""
    if args.rules:
        return args.rules.split(",")
    if "rules" in config:
        return list(config["rules"])
    return sorted({r.meta.get("rule_name", "orbslam3") for r in runs} - {"record"})


def rules_for(names: list[str], model: str) -> tuple[list, list[str]]:
    """(name, Rule) pairs of `names` under `model`, and the rule files that do not exist yet."""
    found, missing = [], []
    for name in (n.format(switch_model=model) for n in names):
        try:
            found += load_rules([name])
        except ValueError:
            missing.append(name)
    return found, missing


def fitted_name(names: list[str], given: str | None) -> str | None:
    """The fitted rule: --fitted, else the stem of the first rule given as a file."""
    if given:
        return given
    files = [Path(n).stem for n in names if n.endswith(".json")]
    return files[0] if files else None


# ---------------------------------------------------------------------------------------------------
# Replays and re-runs


def replay_all(runs, names: list[str], models: list[str]) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """Every recording replayed under every rule and switch model (a rule's own runs under it are its
    re-runs instead): (replayed, reruns, rule files not there yet). `recording` names the protocol."""
    labels = {r.source: recording_label(r.meta) for r in runs}
    bucketed = buckets(runs)
    replayed, reruns, missing = [], [], []
    for model in models:
        rules, absent = rules_for(names, model)
        missing += absent
        for name, rule in rules:
            table = evaluate(bucketed, rule, rule_name=name, switch_model=model, progress=False)
            label = table["source"].map(labels)
            own = label == f"{name}-{model}"
            reruns.append(table[own].assign(recording="own"))
            kind = label.where(label.str.startswith("record-"), OTHER_RULES)
            replayed.append(table[~own].assign(recording=kind))
    return pd.concat(replayed, ignore_index=True), pd.concat(reruns, ignore_index=True), missing


def incomplete(reruns: pd.DataFrame, planned: int | None) -> pd.DataFrame:
    """(setting, rule, switch model) whose re-runs are fewer than planned: still running."""
    counts = reruns.groupby(KEYS).size().rename("reruns").reset_index()
    if planned is None:
        return counts.iloc[:0]
    return counts[counts["reruns"] < planned]


def drop_keys(table: pd.DataFrame, keys: pd.DataFrame) -> pd.DataFrame:
    """`table` without the rows whose KEYS are in `keys`."""
    marked = table.merge(keys[KEYS].drop_duplicates(), on=KEYS, how="left", indicator=True)
    return table[(marked["_merge"] == "left_only").to_numpy()]


# ---------------------------------------------------------------------------------------------------
# Tables


def trust_tables(rows: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Agreement per changed-share bin for every (switch model, protocol), and per group the share up to
    which the replay agrees (trusted_changed) with the agreement of the replays beyond it (beyond_replays,
    beyond_in_band_ratio, beyond_bias in m): what is known past the region, bins pooled."""
    bins, shares = [], []
    for key, part in rows.groupby(GROUP, sort=True):
        table = agreement_by_changed_share(part, cluster=KEYS)  # replays of a setting share its re-runs
        named = dict(zip(GROUP, key, strict=True))
        bins.append(pd.concat([pd.DataFrame([named] * len(table)), table], axis=1))
        trusted = trusted_changed_share(table)
        beyond = part[part["changed_fraction"] > trusted] if np.isfinite(trusted) else part.iloc[:0]
        ratio = beyond["inside"].mean() / beyond["expected_in_band"].mean() if len(beyond) else np.nan
        shares.append({**named, "trusted_changed": trusted, "beyond_replays": len(beyond),
                       "beyond_in_band_ratio": ratio, "beyond_bias": beyond["d"].mean()})  # fmt: skip
    columns = [*GROUP, "trusted_changed", "beyond_replays", "beyond_in_band_ratio", "beyond_bias"]
    return pd.concat(bins, ignore_index=True), pd.DataFrame(shares, columns=columns)


def verdict_table(ranking, rows: pd.DataFrame, trusted: pd.DataFrame, level: float) -> pd.DataFrame:
    """Per switch model and recording protocol: the replays' agreement and trusted changed share, and,
    where rules were ranked, the pooled tau and regret@1 with intervals and the verdict
    (jsve.evaluation.ranking_verdict's criteria)."""
    pooled = pool_draws(ranking, GROUP, level)
    most = ranking.table.groupby(GROUP)["rules"].max().rename("max_rules").reset_index()
    table = agreement_summary(rows, GROUP).merge(trusted, on=GROUP, how="left")
    table = table.merge(pooled.merge(most, on=GROUP), on=GROUP, how="left")
    judged = [
        ranking_verdict(row) if row["recording"].startswith("record-") else ("-", NO_RANKING)
        for _, row in table.iterrows()
    ]
    table["verdict"] = [v for v, _ in judged]
    table["reason"] = [r for _, r in judged]
    return table


NO_RANKING = "agreement only: each rule is replayed on the other rules' runs, so rules are not ranked on them"


def deploy_tables(reruns, fitted, presets, n_boot, seed, level) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The fitted rule's re-runs against each preset's: per level, and pooled over levels per model."""
    if fitted is None:
        return pd.DataFrame(), pd.DataFrame()
    draws = deploy_differences(reruns, fitted, presets, LEVEL, n_boot=n_boot, seed=seed)
    return draws.with_ci(level), pool_draws(draws, ["switch_model", "baseline"], level)


def cost_table(runs_summary: pd.DataFrame) -> pd.DataFrame:
    """Per rule and switch model: runs, crashed runs, mean and total wall time (s, h) of the front-end."""
    g = runs_summary.groupby(["rule", "switch_model"])
    table = g.agg(
        runs=("run", "size"),
        crashed=("exit_code", lambda x: int((x != 0).sum())),
        wall_s_per_run=("wall_seconds", "mean"),
        track_s_per_run=("track_seconds", "mean"),
        wall_h=("wall_seconds", lambda x: x.sum() / 3600),
    )
    return table.reset_index()


# ---------------------------------------------------------------------------------------------------
# Figures


def level_name(row) -> str:
    """`V101 blur 20` for a setting's row."""
    return f"{row['sequence']} {row['disturbance']} {row['level']:g}"


def level_order(table: pd.DataFrame) -> list[str]:
    """The settings of `table` by sequence, then undisturbed first and each disturbance mild to harsh."""
    levels = table[list(SETTING)].drop_duplicates()
    levels = levels.assign(plain=levels["disturbance"] != "none").sort_values(
        ["sequence", "plain", "disturbance", "level"]
    )
    return [level_name(r) for _, r in levels.iterrows()]


def colours(names) -> dict:
    """One colour of matplotlib's tab10 cycle per name, in order."""
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {n: cycle[i % len(cycle)] for i, n in enumerate(names)}


def metres_axis(ax, linthresh: float, ticks: tuple[float, ...]) -> None:
    """A symlog y axis in metres with plain tick labels at +-`ticks` and 0: linear within `linthresh`."""
    ax.set_yscale("symlog", linthresh=linthresh, linscale=1.0)
    limits = ax.get_ylim()  # set_yticks widens the view to every tick: keep the data's
    values = sorted({0.0, *ticks, *(-t for t in ticks)})
    ax.set_yticks(values, [f"{t:g}" for t in values])
    ax.set_ylim(limits)
    ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())


def figure_bland_altman(rows: pd.DataFrame, path: Path) -> None:
    """Replayed minus mean re-run loss against their mean, one panel per switch model, coloured by
    recording protocol, with each protocol's bias and limits of agreement."""
    models = sorted(rows["switch_model"].unique())
    kinds = colours(sorted(rows["recording"].unique()))
    fig, axes = plt.subplots(1, len(models), figsize=(max(8.0, 6.5 * len(models)), 5.6), squeeze=False,
                             sharey=True)  # fmt: skip
    for ax, model in zip(axes[0], models, strict=True):
        part = rows[rows["switch_model"] == model]
        for kind, colour in kinds.items():
            k = part[part["recording"] == kind]
            if k.empty:
                continue
            bias, sd = k["d"].mean(), k["d"].std(ddof=1)
            low, high = 100 * (bias - 1.96 * sd), 100 * (bias + 1.96 * sd)
            label = f"{kind}: {len(k)} replays, bias {100 * bias:+.1f} cm, LoA {low:+.0f} to {high:+.0f} cm"
            ax.scatter((k["loss"] + k["rerun_loss"]) / 2, k["d"], s=14, alpha=0.55, color=colour, label=label)
            ax.axhline(bias, color=colour, lw=1.2)
            for limit in (bias - 1.96 * sd, bias + 1.96 * sd):
                ax.axhline(limit, color=colour, lw=0.9, ls="--")
        failed = part[part["failed"] & (part["rerun_failed"] == 1)]
        if len(failed):  # replay and every re-run failed: one point hides them all
            text = f"{len(failed)} replays: replay and\nevery re-run failed"
            ax.annotate(text, (1.0, 0.0), xytext=(-125, 6), textcoords="offset points", fontsize=8,
                        arrowprops={"arrowstyle": "->", "lw": 0.7})  # fmt: skip
        ax.axhline(0, color="black", lw=0.6)
        ax.set_xscale("log")
        metres_axis(ax, 0.01, (0.01, 0.1, 1, 10))
        ax.set_title(f"switch model {model}", fontsize=10)
        ax.set_xlabel("mean of the replayed and the mean re-run loss (m)")
        ax.grid(alpha=0.3, lw=0.4)
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    axes[0][0].set_ylabel("replayed - mean re-run loss (m)")
    fig.suptitle("Bland-Altman: replays against re-runs\n(solid: bias; dashed: 95 % limits of agreement)",
                 fontsize=11)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def figure_tau(ranking: pd.DataFrame, verdicts: pd.DataFrame, path: Path) -> None:
    """Kendall's tau per level with its 95 % interval, one panel per recording protocol, one series per
    switch model (an x where tau is undefined: replays or re-runs tie); the pooled tau and its interval
    as a line and band."""
    kinds = sorted(ranking["recording"].unique())
    models = colours(sorted(ranking["switch_model"].unique()))
    names = level_order(ranking)
    fig, axes = plt.subplots(len(kinds), 1, figsize=(max(8.0, 0.6 * len(names) + 2), 3.0 * len(kinds) + 1.2),
                             squeeze=False, sharex=True)  # fmt: skip
    for ax, kind in zip(axes[:, 0], kinds, strict=True):
        for k, (model, colour) in enumerate(models.items()):
            part = ranking[(ranking["recording"] == kind) & (ranking["switch_model"] == model)]
            x = np.array([names.index(level_name(r)) for _, r in part.iterrows()], dtype=float)
            x += 0.18 * (k - (len(models) - 1) / 2)
            tau = part["tau"].to_numpy()
            err = np.abs(part[["tau_low", "tau_high"]].to_numpy().T - tau)
            ax.errorbar(
                x, tau, yerr=err, fmt="o", ms=4, capsize=2, color=colour, label=f"switch model {model}"
            )
            undefined = ~np.isfinite(tau)
            ax.plot(x[undefined], np.zeros(undefined.sum()), "x", color=colour, ms=6)
            pooled = verdicts[(verdicts["recording"] == kind) & (verdicts["switch_model"] == model)]
            if len(pooled) and np.isfinite(pooled["tau"].iloc[0]):
                p = pooled.iloc[0]
                ax.axhline(p["tau"], color=colour, lw=1, ls="--")
                ax.axhspan(p["tau_low"], p["tau_high"], color=colour, alpha=0.12, lw=0)
        ax.axhline(0, color="black", lw=0.6)
        ax.set_ylim(-1.1, 1.1)
        ax.set_xlim(-0.5, len(names) - 0.5)
        ax.set_ylabel("Kendall tau")
        ax.set_title(f"{kind} recordings replayed under every rule", fontsize=10)
        ax.grid(alpha=0.3, lw=0.4)
        ax.legend(fontsize=8, loc="lower left")
    axes[-1, 0].set_xticks(range(len(names)), names, rotation=40, ha="right", fontsize=8)
    fig.suptitle("Rule ranking: replay against re-runs, per level (95 % bootstrap intervals)\n"
                 "x: tau undefined (replays or re-runs tie); dashed line and band: pooled over levels",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def figure_trust(bins: pd.DataFrame, trusted: pd.DataFrame, path: Path) -> None:
    """In-band share (as a ratio to what another re-run reaches), bias with 1.96 standard errors, and the
    number of replays per changed-share bin, one series per switch model and protocol; bins with too few
    replays drawn hollow."""
    groups = colours([tuple(k) for k in bins[GROUP].drop_duplicates().itertuples(index=False)])
    edges = list(CHANGED_SHARE_EDGES)
    names = [f"{100 * lo:g}-{100 * hi:g}" for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    fig, (top, middle, bottom) = plt.subplots(3, 1, figsize=(9, 8.4), sharex=True,
                                              gridspec_kw={"height_ratios": [3, 3, 1.6]})  # fmt: skip
    for k, (key, colour) in enumerate(groups.items()):
        part = bins[(bins[GROUP[0]] == key[0]) & (bins[GROUP[1]] == key[1])].reset_index(drop=True)
        x = np.arange(len(part)) + 0.1 * (k - (len(groups) - 1) / 2)
        few = (part["evidence"] == "too few").to_numpy()
        share = trusted[(trusted[GROUP[0]] == key[0]) & (trusted[GROUP[1]] == key[1])]["trusted_changed"]
        label = f"{key[1]} recordings, switch model {key[0]}"
        if len(share) and np.isfinite(share.iloc[0]):
            label += f": agrees up to {100 * share.iloc[0]:g} %"
        top.plot(x[~few], part["in_band_ratio"][~few], "o", color=colour, ms=6, label=label)
        top.plot(x[few], part["in_band_ratio"][few], "o", color=colour, mfc="none", ms=5)
        err = 1.96 * part["bias_se"].fillna(0).to_numpy()
        for mask, face in ((~few, colour), (few, "none")):
            middle.errorbar(x[mask], part["bias"][mask], yerr=err[mask], fmt="o", color=colour, mfc=face,
                            ms=5, capsize=2, lw=0.8)  # fmt: skip
        bottom.bar(x, part["replays"], width=0.1, color=colour)
    top.axhline(MIN_IN_BAND_RATIO, color="black", ls="--", lw=0.8)
    top.axhline(1.0, color="grey", ls=":", lw=0.8)
    top.set_ylabel("in-band share /\nanother re-run's")
    top.legend(fontsize=8, loc="upper right")
    for sign in (-1, 1):
        middle.axhline(sign * MAX_ABS_BIAS_M, color="black", ls="--", lw=0.8)
    middle.axhline(0, color="grey", lw=0.6)
    metres_axis(middle, 0.1, (0.05, 0.1, 1, 10))
    middle.set_ylabel("bias +- 1.96 se (m):\nreplayed - re-run loss")
    bottom.set_yscale("log")
    bottom.axhline(MIN_REPLAYS_PER_BIN, color="black", ls="--", lw=0.8)
    bottom.set_ylabel("replays")
    bottom.set_xticks(range(len(names)), names, rotation=30, ha="right")
    bottom.set_xlabel("share of the recording's decisions the replay changes (%, bin)")
    for ax in (top, middle, bottom):
        ax.grid(alpha=0.3, lw=0.4)
    fig.suptitle(f"Where the replay agrees with the re-runs (dashed: the criteria; hollow: fewer than "
                 f"{MIN_REPLAYS_PER_BIN} replays, no evidence)", fontsize=10)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def figure_deploy(per_level: pd.DataFrame, pooled: pd.DataFrame, fitted: str, path: Path) -> None:
    """The fitted rule's mean re-run loss minus each preset's, per level with its interval, one panel per
    switch model; the pooled difference last."""
    models = sorted(per_level["switch_model"].unique())
    bases = colours(sorted(per_level["baseline"].unique()))
    fig, axes = plt.subplots(1, len(models), figsize=(max(8.5, 7 * len(models)), 5.2), squeeze=False,
                             sharey=True)  # fmt: skip
    for ax, model in zip(axes[0], models, strict=True):
        part = per_level[per_level["switch_model"] == model]
        names = [*level_order(part), "pooled"]
        for k, (base, colour) in enumerate(bases.items()):
            b = part[part["baseline"] == base]
            p = pooled[(pooled["switch_model"] == model) & (pooled["baseline"] == base)]
            d = [*b["diff"], *p["diff"]]
            lo, hi = [*b["diff_low"], *p["diff_low"]], [*b["diff_high"], *p["diff_high"]]
            x = [names.index(level_name(r)) for _, r in b.iterrows()] + [len(names) - 1] * len(p)
            x = np.array(x) + 0.15 * (k - (len(bases) - 1) / 2)
            err = np.abs(np.array([lo, hi]) - np.array(d))
            ax.errorbar(x, d, yerr=err, fmt="o", ms=4, capsize=2, color=colour, label=f"{fitted} - {base}")
        ax.axhline(0, color="black", lw=0.6)
        ax.axvline(len(names) - 1.5, color="grey", lw=0.6)
        metres_axis(ax, 0.01, (0.01, 0.1, 1, 10))
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right", fontsize=8)
        ax.set_title(f"switch model {model}", fontsize=10)
        ax.grid(alpha=0.3, lw=0.4)
        ax.legend(fontsize=8, loc="upper left")
    axes[0][0].set_ylabel("difference of mean re-run loss (m)\nbelow 0: the fitted rule is better")
    title = "Deploy loop: the fitted rule run in the front-end against the presets\n"
    fig.suptitle(title + "(95 % bootstrap intervals over re-runs; pooled: mean over levels)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------------
# Markdown


def markdown_table(table: pd.DataFrame) -> str:
    """A pipe table of `table`'s cells as they are (format them first)."""
    head = "| " + " | ".join(map(str, table.columns)) + " |"
    rule = "|" + "|".join("---" for _ in table.columns) + "|"
    body = ["| " + " | ".join(map(str, row)) + " |" for row in table.itertuples(index=False)]
    return "\n".join([head, rule, *body])


def ci(x, low, high, scale=1.0, digits=2) -> str:
    """`x [low, high]` scaled (100: m to cm), `-` for an undefined value."""
    if not np.isfinite(x):
        return "-"
    if not (np.isfinite(low) and np.isfinite(high)):
        return f"{scale * x:.{digits}f}"
    return f"{scale * x:.{digits}f} [{scale * low:.{digits}f}, {scale * high:.{digits}f}]"


def count(n: int, noun: str) -> str:
    """`1 setting`, `3 settings`."""
    return f"{n} {noun}" + ("" if n == 1 else "s")


def percent(share: float) -> str:
    """`0.1 %` for 0.001, `-` for an undefined share."""
    return f"{100 * share:g} %" if share >= 0 else "-"


def ci_of(row, name: str, scale=1.0, digits=2) -> str:
    """`ci` of a row's statistic `name` and its `<name>_low`, `<name>_high`."""
    return ci(row[name], row[f"{name}_low"], row[f"{name}_high"], scale, digits)


def verdict_markdown(verdicts: pd.DataFrame) -> pd.DataFrame:
    """The verdict table as the docs show it (losses in cm)."""
    rows = []
    for _, v in verdicts.iterrows():
        rows.append({
            "switch model": v["switch_model"], "recordings": v["recording"],
            "levels (rules)": f"{v['units_tau']:.0f} ({v['max_rules']:.0f})" if v["verdict"] != "-" else "-",
            "tau": ci_of(v, "tau"),
            "fitted regret@1, cm": ci_of(v, "fitted_regret", 100, 1),
            "replay's pick regret@1, cm": ci_of(v, "regret_at_1", 100, 1),
            "in band (another re-run)": f"{v['in_band']:.2f} ({v['expected_in_band']:.2f})",
            "bias, cm [LoA]": ci(v["bias"], v["loa_low"], v["loa_high"], 100, 1),
            "failure agreement": f"{v['failure_agreement']:.2f}",
            "coverage bias, pp": f"{100 * v['coverage_bias']:+.1f}",
            "agrees up to changed share": percent(v["trusted_changed"]),
            "verdict": v["verdict"],
        })  # fmt: skip
    return pd.DataFrame(rows)


def trust_markdown(trusted: pd.DataFrame) -> pd.DataFrame:
    """The trust region per switch model and protocol, and what the replays beyond it showed."""
    rows = []
    for _, t in trusted.iterrows():
        rows.append({"switch model": t["switch_model"], "recordings": t["recording"],
                     "agrees up to changed share": percent(t["trusted_changed"]),
                     "replays beyond": t["beyond_replays"],
                     "their in-band share / another re-run's": f"{t['beyond_in_band_ratio']:.2f}",
                     "their bias, cm": f"{100 * t['beyond_bias']:+.1f}"})  # fmt: skip
    return pd.DataFrame(rows)


def deploy_sentence(pooled) -> str:
    """Does fitting on replays improve the real system? One pooled row in words."""
    d = ci_of(pooled, "diff", 100, 1)
    where = f"under `{pooled['switch_model']}`, over {count(pooled['units_diff'], 'level')}"
    if pooled["diff_high"] < 0:
        return f"{where}: the fitted rule beats `{pooled['baseline']}` in the front-end: {d} cm"
    if pooled["diff_low"] > 0:
        return f"{where}: the fitted rule is worse than `{pooled['baseline']}` in the front-end: {d} cm"
    return f"{where}: no clear difference from `{pooled['baseline']}` ({d} cm; the interval holds 0)"


def deploy_markdown(per_level: pd.DataFrame, pooled: pd.DataFrame) -> pd.DataFrame:
    """The deploy loop's table: per level and pooled, fitted - preset mean re-run loss in cm."""
    rows = []
    for _, r in per_level.iterrows():
        rows.append({"switch model": r["switch_model"], "level": level_name(r), "vs": r["baseline"],
                     "runs": f"{r['fitted_runs']} / {r['baseline_runs']}",
                     "fitted, cm": f"{100 * r['fitted_loss']:.1f}",
                     "preset, cm": f"{100 * r['baseline_loss']:.1f}",
                     "difference, cm": ci_of(r, "diff", 100, 1)})  # fmt: skip
    for _, p in pooled.iterrows():
        rows.append({"switch model": p["switch_model"], "level": f"pooled ({p['units_diff']} levels)",
                     "vs": p["baseline"], "runs": "", "fitted, cm": "", "preset, cm": "",
                     "difference, cm": ci_of(p, "diff", 100, 1)})  # fmt: skip
    return pd.DataFrame(rows)


def write_markdown(out: Path, parts: dict) -> None:
    """OUTDIR/validation.md: the verdicts, tables, figures and cost, to paste into docs/validation.md."""
    v, cost = parts["verdicts"], parts["cost"]
    lines = [
        "## Results",
        "",
        f"Replays of {parts['recordings']} recordings against {parts['reruns']} re-runs "
        f"({count(parts['incomplete'], 'setting')} still running and {parts['unmatched']} without re-runs "
        "left out: unmatched.csv); 95 % percentile bootstrap intervals over re-runs and recordings within "
        f"each setting ({parts['n_boot']} draws, seed {parts['seed']}).",
        "",
        "### Verdicts",
        "",
    ]
    lines += [f"- `{r['switch_model']}`, `{r['recording']}` recordings: **{r['verdict']}**: {r['reason']}."
              for _, r in v.iterrows()]  # fmt: skip
    lines += ["", markdown_table(verdict_markdown(v)), "", "![Rule ranking per level](tau_per_level.png)", ""]
    lines += ["![Bland-Altman](bland_altman.png)", "", "### Trust region", ""]
    lines += [
        f"Replays agree in a changed-share bin when they land in the re-runs' 5-95 % band at least "
        f"{MIN_IN_BAND_RATIO:g} times as often as another re-run would and their bias is within "
        f"{100 * MAX_ABS_BIAS_M:g} cm or not significantly beyond it (|bias| - 1.96 se); bins of fewer than "
        f"{MIN_REPLAYS_PER_BIN} replays are no evidence. The replay is trusted up to the last agreeing bin "
        "before the first disagreeing one. jsve.evaluation.REPLAY_TRUSTED_CHANGED_SHARE holds, per switch "
        "model: "
        + ", ".join(f"`{m}` {100 * v:g} %" for m, v in REPLAY_TRUSTED_CHANGED_SHARE.items())
        + " (recordings in `record` mode under that model).",
        "",
        markdown_table(trust_markdown(parts["trusted"])),
        "",
        "![Agreement against changed share](trust_region.png)",
        "",
    ]
    if len(parts["deploy"]):
        lines += ["### Deploy loop", ""]
        lines += [f"- {deploy_sentence(p)}" for _, p in parts["deploy_pooled"].iterrows()]
        lines += ["", markdown_table(deploy_markdown(parts["deploy"], parts["deploy_pooled"]))]
        lines += ["", "![Deploy loop](deploy.png)", ""]
    else:
        lines += ["### Deploy loop", "", "No re-runs of the fitted rule yet.", ""]
    hours = cost["wall_h"].sum()
    lines += ["### Cost", "",
              f"{int(cost['runs'].sum())} front-end runs, {hours:.1f} h of run wall time in all (2 at a time "
              f"on the 2-core machine); this analysis took {parts['seconds']:.0f} s.", ""]  # fmt: skip
    shown = cost.round({"wall_s_per_run": 1, "track_s_per_run": 1, "wall_h": 2})
    lines += [markdown_table(shown), ""]
    (out / "validation.md").write_text("\n".join(lines))


# ---------------------------------------------------------------------------------------------------


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", metavar="LOGDIR", type=Path, nargs="?", help="default: --config's output")
    parser.add_argument(
        "--config", type=Path, help=f"the sweep's config (default: {DEFAULT_CONFIG} if present)"
    )
    parser.add_argument(
        "--ground-truth",
        action="append",
        metavar="SEQUENCE=FILE",
        help="EuRoC ground truth of a sequence (repeatable; default: --config's)",
    )
    parser.add_argument("--rules", help="comma-separated presets or rule files, {switch_model} replaced "
                        "(default: --config's, else the rules run)")  # fmt: skip
    parser.add_argument("--fitted", help="the fitted rule's name (default: the first rule file's stem)")
    parser.add_argument("--penalty", type=float, default=1.0, help="loss of a failed run, m (default 1)")
    parser.add_argument("--n-boot", type=int, default=1000, help="bootstrap draws (default 1000)")
    parser.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    parser.add_argument("-o", "--output", type=Path, default=Path("replay_vs_rerun"), help="output folder")
    return parser.parse_args(argv)


@dataclass(frozen=True)
class Inputs:
    """What the analysis reads: the replays and re-runs (per-run tables), the runs' summaries, what is
    left out (unmatched, settings still running, rule files not there yet), the rules and the fitted one."""

    replayed: pd.DataFrame
    reruns: pd.DataFrame
    runs_summary: pd.DataFrame
    missing: pd.DataFrame
    running: pd.DataFrame
    missing_files: list[str]
    names: list[str]
    fitted: str | None


def collect(args) -> Inputs:
    """Read the logs and the summaries, replay every recording under every rule and switch model."""
    config_path = args.config or (DEFAULT_CONFIG if DEFAULT_CONFIG.is_file() else None)
    config = tomllib.loads(config_path.read_text()) if config_path else {}
    logdir = args.logs or Path(config.get("output", "validation-logs"))
    truth = args.ground_truth or [
        f"{k}={v}" for k, v in config.get("fit", {}).get("ground_truth", {}).items()
    ]
    if not truth:
        sys.exit("replay_vs_rerun: --ground-truth SEQ=FILE (or a --config with [fit] ground_truth) is needed")
    gt = {k: GroundTruth(v, fmt="euroc") for k, v in (s.split("=", 1) for s in truth)}
    runs = read_logs(logdir, ground_truth=gt, on_error="quarantine", progress=False).runs
    names = rule_names(args, config, runs)
    models = config.get("switch_models") or sorted({r.meta.get("switch_model", "orbslam3") for r in runs})
    fitted = fitted_name(names, args.fitted)
    print(f"rules {names} under {models} (from {config_path or 'the runs'}); fitted rule: {fitted}")

    replayed, reruns, missing_files = replay_all(runs, names, models)
    runs_summary = summaries(logdir, models)
    crashed = crashed_runs(runs_summary)
    reruns = pd.concat([reruns, crashed[crashed["rule"].isin(replayed["rule"])]], ignore_index=True)
    planned = config.get("runs")
    running = incomplete(reruns, planned)
    reruns = drop_keys(reruns, running)
    replayed = drop_keys(replayed, running)  # a setting still running is no evidence either way
    still = running.assign(side=[f"{n} of {planned} re-runs (running)" for n in running["reruns"]])
    missing = pd.concat([unmatched(replayed, reruns, KEYS), still.drop(columns="reruns")], ignore_index=True)
    return Inputs(replayed, reruns, runs_summary, missing, running, missing_files, names, fitted)


def analyse(inputs: Inputs, args) -> dict[str, pd.DataFrame]:
    """Every table of the study (the CSV files), with the replay rows, the ranking's draws and the pooled
    deploy loop the figures need."""
    replayed, reruns, fitted = inputs.replayed, inputs.reruns, inputs.fitted
    rows = replay_rows(replayed, reruns, KEYS, args.penalty)
    agreement = agreement_summary(rows, [*KEYS, "recording"]).merge(
        rerun_summary(reruns, KEYS, args.penalty), on=KEYS, how="left"
    )
    # rules are ranked on the recordings every rule is replayed on: the `record` runs (an other-rules
    # recording is never replayed under its own rule, so each rule's replays would be other runs)
    recorded = replayed[replayed["recording"].str.startswith("record-")]
    ranking = bootstrap_ranking(recorded, reruns, LEVEL, split_by=["recording"], fitted=fitted,
                                n_boot=args.n_boot, seed=args.seed, penalty=args.penalty)  # fmt: skip
    bins, trusted = trust_tables(rows)
    presets = [n for n in inputs.names if not n.endswith(".json") and n != fitted]
    deploy, deploy_pooled = deploy_tables(reruns, fitted, presets, args.n_boot, args.seed, 0.95)
    return {
        "agreement": agreement,
        "ranking": ranking.with_ci(0.95),
        "verdict": verdict_table(ranking, rows, trusted, 0.95),
        "trust": bins,
        "trusted": trusted,
        "deploy": deploy,
        "deploy_pooled": deploy_pooled,
        "cost": cost_table(inputs.runs_summary),
        "unmatched": inputs.missing,
        "rows": rows,
    }


CSV = ("agreement", "ranking", "verdict", "trust", "deploy", "cost", "unmatched")
"""The tables written as OUTDIR/<name>.csv (deploy.csv holds the pooled rows too, sequence `pooled`)."""


def write_outputs(out: Path, t: dict, inputs: Inputs, args, seconds: float) -> None:
    """The CSV files, the figures and validation.md into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    for name in CSV:
        table = t[name]
        if name == "deploy":
            table = pd.concat([table, t["deploy_pooled"].assign(sequence="pooled")], ignore_index=True)
        table.to_csv(out / f"{name}.csv", index=False)
    if len(t["rows"]):
        figure_bland_altman(t["rows"], out / "bland_altman.png")
        figure_tau(t["ranking"], t["verdict"], out / "tau_per_level.png")
        figure_trust(t["trust"], t["trusted"], out / "trust_region.png")
    if len(t["deploy"]):
        figure_deploy(t["deploy"], t["deploy_pooled"], inputs.fitted, out / "deploy.png")
    parts = {"verdicts": t["verdict"], "cost": t["cost"], "deploy": t["deploy"], "trusted": t["trusted"],
             "deploy_pooled": t["deploy_pooled"], "recordings": inputs.replayed["source"].nunique(),
             "reruns": len(inputs.reruns), "incomplete": len(inputs.running),
             "unmatched": int((inputs.missing["side"] == "no re-runs").sum()),
             "n_boot": args.n_boot, "seed": args.seed, "seconds": seconds}  # fmt: skip
    write_markdown(out, parts)


def main(argv=None) -> int:
    started = time.perf_counter()
    args = parse(argv)
    inputs = collect(args)
    tables = analyse(inputs, args)
    write_outputs(args.output, tables, inputs, args, time.perf_counter() - started)
    report(tables, inputs.missing_files)
    return 0


def report(tables: dict, missing_files: list[str]) -> None:
    """Print the ranking, the verdicts and what was left out."""
    verdicts = tables["verdict"]
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(tables["ranking"].round(3).to_string(index=False))
        for _, v in verdicts.iterrows():
            print(f"{v['switch_model']}, {v['recording']} recordings: {v['verdict']}: {v['reason']}")
        if len(tables["unmatched"]):
            counts = tables["unmatched"].groupby(["rule", "switch_model", "side"]).size()
            print(f"left out (unmatched.csv), settings per rule:\n{counts.to_string()}")
        for name in missing_files:
            print(f"rule file {name} does not exist yet: not replayed")
    print(
        f"criteria: {REGRET_TOLERANCE_M=} m, {MIN_RULES_FOR_VERDICT=}; trust region: {MIN_IN_BAND_RATIO=}, "
        f"{MAX_ABS_BIAS_M=} m"
    )


if __name__ == "__main__":
    sys.exit(main())
