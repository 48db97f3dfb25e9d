"""What a round races: candidates proposed from the round's logs (the incumbent's own, or the record
rule's), and the replay's predictions.

    propose        the replay's fit within the trust region, the family's presets, perturbations
    predictions    each candidate's replayed loss on each of those logs (per run)

The replay fit searches a Sobol design of the family's space (jsve.fitting's ReplayScorer over the
round's logs) and checks its best settings against the trust region, the share of the logged
decisions a candidate may change before the replay stops predicting the front-end
(jsve.evaluation.trusted_share of the switch model): the best one inside it is proposed, ties (to
0.1 mm) going to the one that changes fewest decisions. Settings
between the best one and the incumbent (when it is of the family) come closer to the region.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import BASELINES, rule_kind
from jsve.fitting._data import FitData
from jsve.fitting._designs import sobol
from jsve.fitting._space import ParamSpace, family_space
from jsve.tuning._frontend import Candidate

FAMILY_PRESETS = {"sve": ("sve-option1", "sve-option2"), "inliers": ("orbslam3",)}
"""The presets each family races (the seed's SVE builds as the authors built them; ORB-SLAM3's)."""

SHRINK = (0.5, 0.25, 0.1)
"""Steps from the incumbent towards the replay's best setting, tried when that one leaves the region."""


@dataclass(frozen=True)
class Proposal:
    """A round's candidates and what the replay said of them.

    Attributes:
        candidates: the incumbent first, then the proposals (no name twice).
        predictions: per (candidate, incumbent's log): predicted loss, failure, changed share.
        trust_share: the switch model's trust region (share of changed decisions).
        note: how the replay fit went (e.g. no setting inside the region).
    """

    candidates: list[Candidate]
    predictions: pd.DataFrame
    trust_share: float
    note: str


def replay_table(logs: Sequence, candidates: Sequence[Candidate], config: ObjectiveConfig) -> pd.DataFrame:
    """Every candidate replayed on every log (jsve.evaluation.evaluate_rules): one row per (candidate,
    log) with predicted_loss_m (the bounded loss of jsve.evaluation.run_loss), predicted_failed and
    changed_fraction (share of frames whose state the replay changes)."""
    from jsve.evaluation import evaluate_rules, run_loss
    from jsve.io._batching import buckets

    table = evaluate_rules(
        buckets(list(logs)),
        [(c.name, c.rule) for c in candidates],
        switch_model=config.switch_model,
        min_coverage=config.min_coverage,
        progress=False,
    )
    table["predicted_loss_m"] = run_loss(table, config.failure_penalty, config.loss)
    table["predicted_failed"] = table["failed"].astype(bool) | (table["unsupported_fraction"] > 0)
    return table.rename(columns={"rule": "candidate"})


def _perturbed(space: ParamSpace, centre: np.ndarray, n: int, scale: float, rng) -> list[np.ndarray]:
    u = np.asarray(space.unit_from_values(centre), np.float64)
    return [
        np.asarray(space.values_from_unit(np.clip(u + rng.normal(0, scale, u.shape), 0, 1)), np.float64)
        for _ in range(n)
    ]


def _rounded(space: ParamSpace, values: np.ndarray) -> np.ndarray:
    """Values at 4 significant digits (readable rule files; the replay cannot tell them apart)."""
    v = np.asarray(values, np.float64)
    with np.errstate(divide="ignore"):
        digits = 3 - np.floor(np.log10(np.where(v == 0, 1, np.abs(v))))
    out = np.array([round(float(x), int(k)) for x, k in zip(v, digits, strict=True)])
    return np.clip(out, space.lo, space.hi)


def propose(
    logs: Sequence,
    incumbent: Candidate,
    family: str,
    config: ObjectiveConfig,
    *,
    round: int,
    design: int,
    shortlist: int,
    perturbations: int,
    perturbation_scale: float,
    seed: int,
) -> Proposal:
    """The candidates of a round from its logs (RunLogs with ground truth): the incumbent's, or those of
    the record rule (which support every rule).

    Raises:
        ValueError when there are no logs to replay.
    """
    from jsve.evaluation import trusted_share

    if not logs:
        raise ValueError("propose: the incumbent has no finished logs to replay")
    space = family_space(family)
    share = trusted_share(config.switch_model)
    in_family = rule_kind(incumbent.rule) == family
    centre = space.values_of(incumbent.rule) if in_family else space.values_of(_preset(BASELINES[family]))
    rng = np.random.default_rng([seed, round])
    data = FitData.from_runs(list(logs), config)
    values = np.asarray(space.values_from_unit(sobol(design, space.dim, seed=seed + round)), np.float64)
    values = np.vstack([values, *_perturbed(space, centre, design // 8, perturbation_scale, rng)])
    mean = data.scorer.score(space, values).loss.mean(axis=1)
    best = values[np.argsort(mean, kind="stable")[:shortlist]]
    tried = [_rounded(space, v) for v in best]
    if in_family:
        tried += [_rounded(space, centre + t * (best[0] - centre)) for t in SHRINK]
    shortlisted = _unique([Candidate.of(space.rule(v), "replay-fit", round) for v in tried], incumbent)
    presets = [Candidate.preset(n, "preset", round) for n in FAMILY_PRESETS[family]]
    perturbed = [
        Candidate.of(space.rule(_rounded(space, v)), "perturbation", round)
        for v in _perturbed(space, centre, perturbations, perturbation_scale, rng)
    ]
    everyone = _unique([incumbent, *shortlisted, *presets, *perturbed], None)
    table = replay_table(logs, everyone, config)
    summary = table.groupby("candidate", sort=False).agg(
        loss=("predicted_loss_m", "mean"), changed=("changed_fraction", "mean")
    )
    inside = summary.loc[[c.name for c in shortlisted if summary.loc[c.name, "changed"] <= share]]
    picked: list[Candidate] = []
    if len(inside):
        # the lowest predicted loss (to 0.1 mm, below what a run resolves), then the fewest changed decisions
        order = inside.assign(key=inside["loss"].round(4)).sort_values(["key", "changed"], kind="stable")
        name = str(order.index[0])
        picked = [c for c in shortlisted if c.name == name]
        note = (
            f"replay fit: {name}, predicted {inside.loc[name, 'loss'] * 100:.2f} cm against the "
            f"incumbent's {summary.loc[incumbent.name, 'loss'] * 100:.2f} cm, changing "
            f"{inside.loc[name, 'changed']:.2%} of the decisions (trust region {share:.2%})"
        )
    else:
        least = summary.loc[[c.name for c in shortlisted], "changed"].min()
        note = (
            f"replay fit: none of the {len(shortlisted)} best settings changes at most {share:.2%} of the "
            f"decisions (the least changes {least:.2%}); "
            "no replay-fit candidate this round"
        )
    candidates = _unique([incumbent, *picked, *presets, *perturbed], None)
    names = {c.name for c in candidates}
    table = table[table.candidate.isin(names)].reset_index(drop=True)
    return Proposal(candidates, table, share, note)


def _preset(name: str):
    from jsve.core._rules import preset

    return preset(name)


def _unique(candidates: Sequence[Candidate], exclude: Candidate | None) -> list[Candidate]:
    seen = {exclude.name} if exclude is not None else set()
    out = []
    for c in candidates:
        if c.name not in seen:
            seen.add(c.name)
            out.append(c)
    return out


__all__ = ["FAMILY_PRESETS", "Proposal", "propose", "replay_table"]
