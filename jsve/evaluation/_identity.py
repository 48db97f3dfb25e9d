"""Identity replay: does jsve's machine reproduce the states a front-end logged under its own rule?

A log names the rule its front-end ran (metadata `rule`: a preset name, or a rule object, see
jsve.core._rules.rule_to_dict, also as JSON text) and the switch model (`switch_model`). Replaying that
rule over the log must give back the logged `state` on (almost) every frame; a hook that logs the wrong
counts, states or flags shows up here first. This is how a real front-end's hook is validated
(docs/frontend.md).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from jsve.core._machine import SWITCH_MODELS
from jsve.core._replay import as_logged_mode, replay
from jsve.core._rules import PRESETS, Rule, preset, rule_from_dict
from jsve.io._batching import from_runs, recorded_mode
from jsve.io._schema import RunLog

IDENTITY_THRESHOLD = 0.99
"""Share of frames whose replayed state must equal the logged one; a log below it is flagged."""


def recorded_rule(run: RunLog, default: str | None = None) -> tuple[str, Rule]:
    """(name, Rule) of the rule the run's front-end ran: its metadata `rule`, else `default`.

    Raises:
        ValueError naming the log when neither says which rule, or the rule is unknown.
    """
    spec = run.meta.get("rule", default)
    if spec is None:
        raise ValueError(
            f"{run.source}: metadata has no 'rule' (the rule its front-end ran); give one with --rule"
        )
    if isinstance(spec, str) and spec.lstrip().startswith("{"):
        # a rule object written as JSON text (jsve_log.hpp writes metadata strings, not objects)
        try:
            spec = json.loads(spec)
        except json.JSONDecodeError as err:
            raise ValueError(f"{run.source}: metadata 'rule' is not valid JSON: {err.msg}") from None
    if isinstance(spec, dict):
        return json.dumps(spec, sort_keys=True), rule_from_dict(spec, source=run.source)
    if spec not in PRESETS:
        raise ValueError(f"{run.source}: metadata 'rule' = {spec!r} is not a preset ({', '.join(PRESETS)})")
    return spec, preset(spec)


def recorded_switch_model(run: RunLog, default: str = "orbslam3") -> str:
    """The switch model the run's front-end ran (metadata `switch_model`), else `default`."""
    model = run.meta.get("switch_model", default)
    if model not in SWITCH_MODELS:
        raise ValueError(
            f"{run.source}: metadata 'switch_model' = {model!r}: identity replay needs one of "
            f"{', '.join(SWITCH_MODELS)}"
        )
    return model


def recorded_groups(
    runs: Sequence[RunLog], rule: str | None = None
) -> tuple[dict[tuple[str, str], list[int]], dict[str, Rule]]:
    """The runs grouped by the rule and switch model their front-end ran: ({(rule name, switch model):
    run indices}, {rule name: rule}); `rule` is the preset of logs that name none."""
    groups: dict[tuple[str, str], list[int]] = {}
    rules: dict[str, Rule] = {}
    for i, run in enumerate(runs):
        name, r = recorded_rule(run, rule)
        rules[name] = r
        groups.setdefault((name, recorded_switch_model(run)), []).append(i)
    return groups, rules


def identity_table(runs: Sequence[RunLog], *, rule: str | None = None, dtype=jnp.float32) -> pd.DataFrame:
    """One row per log: the share of frames whose replayed state equals the logged one.

    Arguments:
        runs: parsed logs. rule: the preset to assume where a log's metadata names none.
    Returns:
        Columns run_id, source, rule, switch_model, n_frames, agreement (share in [0, 1]),
        first_mismatch (frame index, -1 if none), flagged (agreement < IDENTITY_THRESHOLD).
    """
    groups, rules = recorded_groups(runs, rule)
    rows: list[dict] = [{}] * len(runs)
    replay_jit = jax.jit(replay, static_argnames=("switch_model",))
    for (name, model), index in groups.items():
        bucket = from_runs([runs[i] for i in index], dtype=dtype)
        result = replay_jit(bucket.batch, rules[name], switch_model=model)
        valid = np.asarray(bucket.batch.valid)
        same = (np.asarray(as_logged_mode(result)) == recorded_mode(np.asarray(bucket.batch.state))) & valid
        for j, i in enumerate(index):
            n = int(valid[j].sum())
            agreement = float(same[j].sum()) / max(n, 1)
            miss = np.flatnonzero(valid[j] & ~same[j])
            rows[i] = dict(
                run_id=runs[i].run_id,
                source=runs[i].source,
                rule=name,
                switch_model=model,
                n_frames=n,
                agreement=agreement,
                first_mismatch=int(miss[0]) if miss.size else -1,
                flagged=agreement < IDENTITY_THRESHOLD,
            )
    return pd.DataFrame(rows)


def own_rule_table(
    runs: Sequence[RunLog],
    *,
    rule: str | None = None,
    dtype=jnp.float64,
    progress: bool = False,
    **scoring,
) -> pd.DataFrame:
    """Every run scored under the rule and switch model its own front-end ran (its identity replay):
    on a format-v3 log of ORB-SLAM3, the ATE of the trajectory ORB-SLAM3 saved, as `jsve ape` of its
    saved file gives it (docs/state-machine.md, "Scoring a run").

    Arguments:
        runs: parsed logs with ground truth. rule: the preset to assume where a log names none.
        dtype: float64 by default (evo's precision). scoring: jsve.evaluation.evaluate's keywords
            (align, min_coverage, failure).
    Returns:
        evaluate's per-run table, rows in the order of `runs`.
    """
    from jsve.evaluation._evaluate import evaluate

    groups, rules = recorded_groups(runs, rule)
    parts, order = [], []
    for (name, model), index in groups.items():
        bucket = from_runs([runs[i] for i in index], dtype=dtype)
        parts.append(evaluate([bucket], rules[name], rule_name=name, switch_model=model, progress=progress,
                              **scoring))  # fmt: skip
        order += index
    table = pd.concat(parts, ignore_index=True)
    return table.iloc[np.argsort(order, kind="stable")].reset_index(drop=True)
