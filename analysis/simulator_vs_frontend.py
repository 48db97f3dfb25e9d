"""The simulator against the real front-end: does jsve's simulator rank the switching rules as the real,
hooked ORB-SLAM3 v1.0 does? (issue 11, deliverable 4; docs/validation.md gives the method and the verdict)

    python analysis/simulator_vs_frontend.py [--euroc-gt DIR] [--runs 5] [--frames 700] [--seed 0]
        [--n-boot 1000] [-o docs/data] [--figure docs/figures/simulator_vs_frontend.png]

The real side is what the validation study kept (docs/data/validation_agreement.csv; its raw logs are
gone): per dataset (rendered V101 and V201, frames 0:700, `jsve render --imu-noise datasheet`;
undisturbed, blur 20/30/35/40, occlusion 200/350), rule and switch model, the 5 re-runs' mean loss
(m: ATE RMSE, or the 1 m penalty for a failed run), 5/95 % quantiles, failure share and coverage.
The fitted rule's parameters were not kept, so only the presets (RULES) are compared.

The simulator's side: jsve.sim simulates the same EuRoC trajectories (V1_01, V2_01) with the datasheet
IMU at the same settings, `--runs` runs each, keeps each log's first `--frames` frames (the simulator
has no frame range: a log is cut after simulating the whole sequence; what it computes is causal, so
the kept frames are those a 700-frame run would give), and replays every simulated run under every rule
and switch model (jsve.evaluation.evaluate): each simulated run is a recording every rule is replayed
on, as the `record` runs of the validation. Two scenes (VARIANTS): the rendered one the real front-end
saw (SceneProfile.texture_scale = jsve.sim.RENDERED_TEXTURE_SCALE, fitted to the rendered frames'
keypoints per pyramid level, and the renderer's 8 ms exposure), and
the camera images' (the simulator's default, fitted to the real V1_01 photographs).

Statistics are jsve.evaluation's, as analysis/replay_vs_rerun.py uses them with the simulated runs in
the place of the replayed recordings: Kendall's tau-b and regret@1 of the simulator's pick per level
(`bootstrap_ranking`), pooled per switch model (`pool_draws`), failure agreement per level and rule
(`agreement_table`). The bootstrap resamples each rule's re-runs; only their summaries were kept, so a
setting's re-runs are rebuilt (`pseudo_reruns`) as its failed re-runs at the penalty and the others at
their mean loss: mean and failure share exact, the successful re-runs' spread left out, so the
intervals are too narrow by that spread. `chance` is the regret@1 of a pick at random (the simulator's
own when it ties every rule).

Writes into OUT: simulator_vs_frontend.csv (per level and simulator variant: tau, regret@1, the chance
regret, with 95 % intervals), simulator_vs_frontend_rules.csv (per level and rule: simulated and real
loss, failure share, coverage, failure agreement, and the simulated runs' first-map frame),
simulator_vs_frontend_pooled.csv (per variant, levels pooled (SCOPES) and switch model); and the figure.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from jsve.core import preset  # noqa: E402
from jsve.evaluation import (  # noqa: E402
    SETTING,
    Draws,
    agreement_table,
    bootstrap_ci,
    bootstrap_ranking,
    evaluate,
    pool_draws,
)
from jsve.io import buckets  # noqa: E402
from jsve.sim import (  # noqa: E402
    RENDERED_TEXTURE_SCALE,
    ImuNoise,
    SceneProfile,
    SimConfig,
    euroc_sequences,
    simulate_study,
)

REPO = Path(__file__).resolve().parents[1]
EUROC = REPO.parent / "shared" / "data" / "euroc"
REAL = REPO / "docs" / "data" / "validation_agreement.csv"
NAME = "simulator_vs_frontend"
RULES = ("orbslam3", "sve-option2", "sve-option1")
"""The presets both sides ran; the validation's fitted rule is left out (its file was not kept)."""
SEQUENCES = {"V1_01": "V101", "V2_01": "V201"}
"""Simulated EuRoC sequence -> the validation's name of its rendered dataset."""
MODELS = ("orbslam3", "imu-coast")
RENDER_EXPOSURE_S = 0.008
"""s: `jsve render`'s exposure (its default --exposure-ms 8, docs/render.md), whose motion blur the
rendered scene's camera has."""
KEYS = [*SETTING, "rule", "switch_model"]
LEVEL = [*SETTING, "switch_model"]
PENALTY_M = 1.0
"""Loss of a failed run (m), as in the validation study."""
RENDERED, CAMERA = "rendered scene", "camera-image scene"
VARIANTS = {
    RENDERED: SimConfig(
        imu=ImuNoise.datasheet(),
        scene=SceneProfile(
            texture_scale=RENDERED_TEXTURE_SCALE,
            exposure_s=RENDER_EXPOSURE_S,
        ),
    ),
    CAMERA: SimConfig(imu=ImuNoise.datasheet()),
}
"""The simulator's scenes: the rendered images the real front-end ran on, and the camera images the vision
model was fitted on (the simulator's default). Both with the datasheet IMU, as the renders."""


# ---------------------------------------------------------------------------------------------------
# The real re-runs


def real_reruns(path: Path = REAL, rules=RULES) -> pd.DataFrame:
    """The validation's re-run summaries of `rules` (m, shares): one row per setting, rule and switch model.
    The re-run columns do not depend on the recording protocol: one protocol's rows are taken."""
    table = pd.read_csv(path)
    table = table[table["rule"].isin(rules) & (table["recording"] == table["recording"].iloc[0])]
    columns = ["reruns", "rerun_loss", "rerun_q05", "rerun_q95", "rerun_failed", "rerun_coverage"]
    return table[[*KEYS, *columns]].reset_index(drop=True)


def pseudo_reruns(real: pd.DataFrame, penalty: float = PENALTY_M) -> pd.DataFrame:
    """Per-run rows that keep each setting's re-run mean loss and failure share (`real_reruns`): its
    round(n x failed share) failed re-runs (rmse NaN, charged `penalty` m) and the rest at the mean loss
    of the successful ones, (n mean - k penalty) / (n - k) m; coverage the recorded mean everywhere."""
    rows = []
    for _, r in real.iterrows():
        n = int(r["reruns"])
        k = int(round(n * r["rerun_failed"]))
        ok_loss = (n * r["rerun_loss"] - k * penalty) / (n - k) if n > k else np.nan
        key = {c: r[c] for c in KEYS}
        rows += [{**key, "rmse": np.nan, "failed": True, "coverage": r["rerun_coverage"]}] * k
        rows += [{**key, "rmse": ok_loss, "failed": False, "coverage": r["rerun_coverage"]}] * (n - k)
    return pd.DataFrame(rows, columns=[*KEYS, "rmse", "failed", "coverage"])


def settings_spec(real: pd.DataFrame) -> str:
    """The settings of `real` as jsve.sim reads them: `none,blur=20,30,occlusion=200`."""
    parts = []
    for name, part in real.groupby("disturbance", sort=True):
        levels = sorted(part["level"].unique())
        parts.append("none" if name == "none" else f"{name}=" + ",".join(f"{lv:g}" for lv in levels))
    return ",".join(parts)


# ---------------------------------------------------------------------------------------------------
# The simulator's runs


def simulate(euroc_gt: Path, spec: str, runs: int, frames: int, seed: int, config: SimConfig) -> list:
    """Simulated RunLogs of SEQUENCES at the settings `spec` under `config`, each cut to its first
    `frames` frames."""
    specs = euroc_sequences(list(SEQUENCES), euroc_gt)
    logs = simulate_study(specs, disturbances=spec, runs=runs, seed=seed, config=config)
    return [dataclasses.replace(r, frames=r.frames.iloc[:frames].reset_index(drop=True)) for r in logs]


def first_maps(logs: list) -> pd.DataFrame:
    """Per setting (SETTING, the validation's names): the simulated runs' mean first-map frame (their first
    posed frame; runs that never start one left out: NaN when none did) and the share that started one."""
    rows = []
    for run in logs:
        posed = run.frames["vis_px"].notna().to_numpy()
        first = np.argmax(posed) if posed.any() else np.nan
        rows.append({"sequence": SEQUENCES[run.meta["sequence"]], "disturbance": run.meta["disturbance"],
                     "level": float(run.meta["level"]), "sim_first_map": first,
                     "sim_started": bool(posed.any())})  # fmt: skip
    return pd.DataFrame(rows).groupby(list(SETTING), as_index=False)[["sim_first_map", "sim_started"]].mean()


def replay(logs: list, rules=RULES, models=MODELS) -> pd.DataFrame:
    """Every simulated run replayed under every rule and switch model (evaluate's per-run rows), with the
    validation's sequence names and float levels."""
    grouped = buckets(logs)
    tables = [
        evaluate(grouped, preset(rule), rule_name=rule, switch_model=model, progress=False)
        for model in models
        for rule in rules
    ]
    table = pd.concat(tables, ignore_index=True)
    return table.assign(sequence=table["sequence"].map(SEQUENCES), level=table["level"].astype(float))


# ---------------------------------------------------------------------------------------------------
# Comparison


@dataclasses.dataclass(frozen=True)
class Comparison:
    """The simulator's rule ranking and failures against the real re-runs' (`compare`).

    Attributes:
        levels: per level (LEVEL): rules, the simulator's pick (`replay_best`, ties joined by '='), the
            re-runs' best (`rerun_best`), tau, regret_at_1 and chance_regret (m) with 95 % intervals, and
            real_rules_differ (the rules' mean re-run losses are not all equal).
        rules: per level and rule: sim_runs, sim_loss (m), sim_failed, sim_coverage, sim_tracked (share of
            frames tracked), failure_agreement (the chance that a random re-run fails exactly when a
            simulated run does), and the real re-runs' real_runs, real_loss, real_q05, real_q95 (m),
            real_failed, real_coverage; real_rules_differ as in `levels`.
        ranking, chance: the bootstrap draws of the simulator's ranking and of a pick at random.
    """

    levels: pd.DataFrame
    rules: pd.DataFrame
    ranking: Draws
    chance: Draws


def compare(sim: pd.DataFrame, real: pd.DataFrame, n_boot: int = 1000, seed: int = 0) -> Comparison:
    """Compare simulated runs (evaluate's rows with KEYS, run_id, rmse, failed, coverage and
    accepted_fraction) with the real re-runs (`real_reruns`), level by level."""
    pseudo = pseudo_reruns(real)
    ranking = bootstrap_ranking(sim, pseudo, LEVEL, recording="run_id", n_boot=n_boot, seed=seed)
    chance = bootstrap_ranking(_tied(sim), pseudo, LEVEL, recording="run_id", n_boot=n_boot, seed=seed)
    levels = ranking.with_ci().drop(columns=["fitted_regret", "fitted_regret_low", "fitted_regret_high"])
    levels = levels.merge(_renamed(chance.with_ci()[[*LEVEL, *REGRET]]), on=LEVEL)
    agreement = agreement_table(sim, pseudo, KEYS)
    kept = {"replays": "sim_runs", "replay_loss": "sim_loss", "replay_failed": "sim_failed",
            "replay_coverage": "sim_coverage", "failure_agreement": "failure_agreement"}  # fmt: skip
    rules = agreement[[*KEYS, *kept]].rename(columns=kept)
    tracked = sim.groupby(KEYS)["accepted_fraction"].mean().rename("sim_tracked").reset_index()
    real_named = real.rename(columns=lambda c: "real_runs" if c == "reruns" else c.replace("rerun_", "real_"))
    rules = rules.merge(tracked, on=KEYS).merge(real_named, on=KEYS)
    # Where every rule's re-runs have one loss (all failed: blur 30 on), any pick has regret 0.
    differ = rules.groupby(LEVEL)["real_loss"].agg(lambda x: x.max() > x.min()).rename("real_rules_differ")
    flag = lambda t: t.merge(differ.reset_index(), on=LEVEL, how="left")  # noqa: E731 (keeps t's order)
    ranking, chance = (Draws(flag(d.table), d.boot) for d in (ranking, chance))
    return Comparison(flag(levels), flag(rules), ranking, chance)


REGRET = ["regret_at_1", "regret_at_1_low", "regret_at_1_high"]


def _renamed(table: pd.DataFrame) -> pd.DataFrame:
    """regret_at_1* -> chance_regret* (the regret of a pick at random)."""
    return table.rename(columns=lambda c: c.replace("regret_at_1", "chance_regret"))


def _tied(sim: pd.DataFrame) -> pd.DataFrame:
    """`sim` with every run's loss 0 m: a ranking that ties every rule, whose pick is one at random."""
    return sim.assign(rmse=0.0, failed=False, unsupported_fraction=0.0)


SCOPES = {"all": False, "real rules differ": True}
"""Levels a pooled row is over: all, or those where the rules' mean re-run losses differ (at the others
every real run failed, so any pick has regret 0 and tau is undefined)."""


def pooled(c: Comparison, n_boot: int = 1000, seed: int = 0) -> pd.DataFrame:
    """Per scope (SCOPES) and switch model: tau and regret@1 of the simulator's pick and of a pick at
    random (the mean over the levels where each is defined, with the 95 % interval of that mean:
    `pool_draws`), and the failure agreement's mean over levels and rules with a 95 % bootstrap interval
    over those units."""
    out = []
    for scope, only_differ in SCOPES.items():
        keep = c.ranking.table["real_rules_differ"].to_numpy() | (not only_differ)
        own = pool_draws(_subset(c.ranking, keep), ["switch_model"])
        own = own[[k for k in own.columns if "fitted" not in k]]
        rand = pool_draws(_subset(c.chance, keep), ["switch_model"])[["switch_model", *REGRET]]
        table = own.merge(_renamed(rand), on="switch_model").assign(levels=scope)
        rules = c.rules[c.rules["real_rules_differ"] | (not only_differ)]
        for model, fa in rules.groupby("switch_model")["failure_agreement"]:
            low, high = bootstrap_ci(fa.to_numpy(), n_boot=n_boot, seed=seed)
            at = table["switch_model"] == model
            table.loc[at, ["failure_agreement", "failure_agreement_low", "failure_agreement_high"]] = [
                fa.mean(),
                low,
                high,
            ]
        out.append(table)
    return pd.concat(out, ignore_index=True)


def _subset(draws: Draws, keep: np.ndarray) -> Draws:
    """The units (rows) of `draws` where `keep` holds, with their bootstrap draws."""
    return Draws(draws.table[keep].reset_index(drop=True), {k: v[keep] for k, v in draws.boot.items()})


# ---------------------------------------------------------------------------------------------------
# Figure and output


def dataset_order(table: pd.DataFrame) -> list[tuple]:
    """(sequence, disturbance, level) of `table`: by sequence, undisturbed first, then mild to harsh."""
    levels = table[list(SETTING)].drop_duplicates()
    levels = levels.assign(plain=levels["disturbance"] != "none").sort_values(
        ["sequence", "plain", "disturbance", "level"]
    )
    return [tuple(r) for r in levels[list(SETTING)].itertuples(index=False)]


def figure(rules: pd.DataFrame, path: Path) -> None:
    """Mean loss, failure share and coverage per dataset and rule: the real re-runs (filled) beside the
    simulator's rendered scene (hollow) and its camera-image scene (+), one column per switch model."""
    names = dataset_order(rules)
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    rows = (("loss", "mean run loss (m; a failed run costs 1 m)"), ("failed", "share of failed runs"),
            ("coverage", "coverage (share of frames with an estimate)"))  # fmt: skip
    fig, axes = plt.subplots(len(rows), len(MODELS), figsize=(14, 10.5), sharex=True, squeeze=False)
    for col, model in enumerate(MODELS):
        for k, rule in enumerate(RULES):
            mine = rules[(rules["switch_model"] == model) & (rules["rule"] == rule)]
            real = mine[mine["simulator"] == RENDERED]
            camera = real[list(SETTING)].merge(
                mine[mine["simulator"] == CAMERA], on=list(SETTING), how="left"
            )
            x = np.array([names.index(tuple(v)) for v in real[list(SETTING)].itertuples(index=False)], float)
            x += 0.27 * (k - 1)
            for row, (what, _) in enumerate(rows):
                ax = axes[row, col]
                ax.plot(x - 0.08, real[f"real_{what}"], "o", color=cycle[k], ms=6,
                        label=f"{rule}: real ORB-SLAM3 re-runs")  # fmt: skip
                ax.plot(x, real[f"sim_{what}"], "s", color=cycle[k], mfc="none", ms=6,
                        label=f"{rule}: simulator, rendered scene")  # fmt: skip
                ax.plot(x + 0.08, camera[f"sim_{what}"], "+", color=cycle[k], ms=6,
                        label=f"{rule}: simulator, camera-image scene")  # fmt: skip
        axes[0, col].set_yscale("log")
        axes[0, col].set_title(f"switch model {model}", fontsize=10)
        for row in (1, 2):
            axes[row, col].set_ylim(-0.05, 1.08)
        for ax in axes[:, col]:
            ax.axvline(len(names) / 2 - 0.5, color="grey", lw=0.8)
            ax.grid(alpha=0.3, lw=0.4)
    for row, (_, label) in enumerate(rows):
        axes[row, 0].set_ylabel(label, fontsize=9)
    for ax in axes[-1]:
        ax.set_xticks(range(len(names)), [f"{s} {d} {lv:g}" for s, d, lv in names], rotation=45, ha="right",
                      fontsize=8)  # fmt: skip
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle("The simulator against the real front-end: rendered V1_01 / V2_01, first 35 s, "
                 "5 runs per rule and dataset", fontsize=11)  # fmt: skip
    fig.tight_layout(rect=(0, 0.09, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def interval(row: pd.Series, name: str, scale: float = 1.0, digits: int = 2) -> str:
    """`value [low, high]` of statistic `name` and its interval in `row`, times `scale`."""
    low, value, high = (scale * row[f"{name}{end}"] for end in ("_low", "", "_high"))
    return f"{value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def markdown(pool: pd.DataFrame) -> str:
    """The pooled table (per simulator variant, scope and switch model) in Markdown (docs/validation.md)."""
    lines = [
        "| simulator | levels (with tau) | switch model | tau | regret@1 of the simulator's pick, cm "
        "| regret@1 of a pick at random, cm | failure agreement |",
        "|---|---|---|---|---|---|---|",
    ]
    for _, p in pool.iterrows():
        scope = f"{p['levels']}: {p['units_regret_at_1']} ({p['units_tau']})"
        cells = [p["simulator"], scope, p["switch_model"], interval(p, "tau"),
                 interval(p, "regret_at_1", 100, 1), interval(p, "chance_regret", 100, 1),
                 interval(p, "failure_agreement")]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    gt = EUROC / "groundtruth_left_cam"
    parser.add_argument("--euroc-gt", type=Path, default=gt, help="ORB-SLAM3's EuRoC_left_cam ground truth")
    parser.add_argument("--real", type=Path, default=REAL, help="the validation's agreement.csv")
    parser.add_argument("--runs", type=int, default=5, help="simulated runs per dataset (default 5)")
    parser.add_argument("--frames", type=int, default=700, help="frames kept per log (default 700: 35 s)")
    parser.add_argument("--seed", type=int, default=0, help="simulator and bootstrap seed (default 0)")
    parser.add_argument("--n-boot", type=int, default=1000, help="bootstrap draws (default 1000)")
    parser.add_argument(
        "-o", "--output", type=Path, default=REPO / "docs" / "data", help="folder of the CSVs"
    )
    parser.add_argument("--figure", type=Path, default=REPO / "docs" / "figures" / f"{NAME}.png")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    wall, cpu = time.perf_counter(), time.process_time()
    args = parse(argv)
    real = real_reruns(args.real)
    levels, rules, pools, replays = [], [], [], 0
    for name, config in VARIANTS.items():
        logs = simulate(args.euroc_gt, settings_spec(real), args.runs, args.frames, args.seed, config)
        table = replay(logs)
        replays += len(table)
        c = compare(table, real, args.n_boot, args.seed)
        levels.append(c.levels.assign(simulator=name))
        rules.append(c.rules.merge(first_maps(logs), on=list(SETTING), how="left").assign(simulator=name))
        pools.append(pooled(c, args.n_boot, args.seed).assign(simulator=name))
    out = {"": pd.concat(levels), "_rules": pd.concat(rules), "_pooled": pd.concat(pools)}
    args.output.mkdir(parents=True, exist_ok=True)
    for suffix, table in out.items():
        first = ["simulator"]
        table = table[[*first, *(c for c in table.columns if c not in first)]]
        table.to_csv(args.output / f"{NAME}{suffix}.csv", index=False, float_format="%.6g")
    figure(out["_rules"], args.figure)
    with pd.option_context("display.width", 220, "display.max_columns", 40, "display.max_rows", 200):
        shown = ["simulator", *LEVEL, "replay_best", "rerun_best", "tau", "regret_at_1", "chance_regret"]
        print(out[""][shown].round(3).to_string(index=False))
        starts = ["simulator", *SETTING, "sim_first_map", "sim_started"]
        print(out["_rules"][starts].drop_duplicates().round(2).to_string(index=False))
    print(markdown(out["_pooled"]))
    datasets = len(real[list(SETTING)].drop_duplicates())
    print(f"CPU cost: {time.perf_counter() - wall:.1f} s wall, {time.process_time() - cpu:.1f} s CPU "
          f"({len(VARIANTS)} scenes x {args.runs} runs x {datasets} datasets; "
          f"{replays} replays under {len(RULES)} rules x {len(MODELS)} switch models)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
