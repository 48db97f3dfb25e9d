"""Identity replay (jsve check): a log's own rule replayed gives back its logged states."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from jsve.cli import main
from jsve.evaluation._identity import IDENTITY_THRESHOLD, identity_table
from jsve.io._logs import write_log
from jsve.io._schema import STATE_LOST, STATE_OK
from jsve.sim import simulate_run


@pytest.fixture(scope="module")
def simulated():
    # blur 30 loses tracking in places: resets, expiries and new maps all appear in the logged states (and
    # frames before the first map, NOT_INITIALIZED, in every log)
    return [simulate_run("proc_00", "blur", level, run=r) for level in (0, 30) for r in range(2)]


def test_simulated_logs_agree_on_every_frame(simulated):
    states = np.concatenate([r.frames["state"].to_numpy() for r in simulated])
    assert (states != STATE_OK).any(), "the fixture must exercise more than the OK state"
    table = identity_table(simulated)
    assert (table["agreement"] == 1.0).all(), table
    assert not table["flagged"].any() and (table["first_mismatch"] == -1).all()
    assert set(table["rule"]) == {"orbslam3"} and set(table["switch_model"]) == {"orbslam3"}


def corrupt(run, share, seed=0):
    """The run with `share` of its frames' states replaced by LOST where they were OK."""
    frames = run.frames.copy()
    ok = np.flatnonzero(frames["state"].to_numpy() == STATE_OK)
    hit = np.random.default_rng(seed).choice(ok, int(share * len(frames)), replace=False)
    frames.loc[hit, "state"] = STATE_LOST
    return dataclasses.replace(run, frames=frames), int(hit.min())


def test_corrupted_states_are_flagged(simulated):
    bad, first = corrupt(simulated[0], 0.02)
    slight, _ = corrupt(simulated[1], 0.002)
    table = identity_table([bad, slight])
    assert table["flagged"].tolist() == [True, False]
    assert table["agreement"][0] == pytest.approx(0.98, abs=1e-3) and table["first_mismatch"][0] == first
    assert IDENTITY_THRESHOLD <= table["agreement"][1] < 1.0


def test_a_log_without_its_rule_needs_one(simulated):
    run = simulated[0]
    anonymous = dataclasses.replace(run, meta={k: v for k, v in run.meta.items() if k != "rule"})
    with pytest.raises(ValueError, match=r"metadata has no 'rule'.*--rule"):
        identity_table([anonymous])
    assert identity_table([anonymous], rule="orbslam3")["agreement"][0] == 1.0
    unknown = dataclasses.replace(run, meta=run.meta | {"rule": "nonsense"})
    with pytest.raises(ValueError, match="'nonsense' is not a preset"):
        identity_table([unknown])


def test_cli_exit_status_follows_the_flags(simulated, tmp_path, capsys):
    good = tmp_path / "good"
    write_log(simulated[0], good / "a.csv")
    assert main(["check", str(good), "--no-progress", "-o", str(tmp_path / "t.csv")]) == 0
    assert (tmp_path / "t.csv").read_text().startswith("run_id,")
    bad = tmp_path / "bad"
    write_log(corrupt(simulated[0], 0.05)[0], bad / "a.csv")
    assert main(["check", str(bad), "--no-progress"]) == 1
    assert re.search(r"replayed states agree on 9[45]\.\d\d % of frames", capsys.readouterr().out)
