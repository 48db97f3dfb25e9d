"""FitData streamed from Parquet (FitData.from_parquet) scores every rule as FitData of the parsed runs
does: the same runs, the same per-setting objectives, the same fingerprint on a second read."""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import preset
from jsve.evaluation._aggregate import group_weights
from jsve.fitting._fit import FitData, hard_objective
from jsve.fitting._space import inlier_space, sve_space
from jsve.fitting._study import data_fingerprint
from jsve.io._ingest import ingest
from jsve.io._logs import write_log

COAST = ObjectiveConfig(switch_model="imu-coast")


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fitstream")
    runs = ka.make_study("occlusion", range(7), n_frames=400) + ka.make_study(
        "counts", range(5), n_frames=700
    )
    paths = [write_log(run, tmp / "logs" / f"r{i:02d}.csv") for i, run in enumerate(runs)]
    ingest(paths, tmp / "s.parquet", workers=1, progress=False)
    return FitData.from_runs(runs, COAST), FitData.from_parquet(tmp / "s.parquet", COAST), tmp / "s.parquet"


def test_the_same_runs_with_the_same_metadata(both):
    parsed, streamed, _ = both
    assert streamed.n_runs == parsed.n_runs and streamed.n_frames == parsed.n_frames
    key = ["run_id", "sequence", "disturbance", "level", "n_frames", "t0_ns"]
    a = parsed.meta[key].sort_values("run_id").reset_index(drop=True)
    b = streamed.meta[key].sort_values("run_id").reset_index(drop=True)
    assert a.equals(b)


@pytest.mark.parametrize(
    ("space", "name"),
    [(sve_space(), "sve-option2"), (sve_space(), "sve-option1"), (inlier_space(), "orbslam3")],
    ids=["sve-option2", "sve-option1", "orbslam3"],
)
def test_objectives_equal_those_of_the_parsed_runs(both, space, name):
    parsed, streamed, _ = both
    values = space.values_of(preset(name))
    # group weights follow each FitData's own run order
    a = hard_objective(parsed, space, values, group_weights(parsed.meta))
    b = hard_objective(streamed, space, values, group_weights(streamed.meta))
    assert b == pytest.approx(a, rel=1e-6)


def test_the_fingerprint_is_that_of_the_content(both, tmp_path):
    _, streamed, path = both
    again = FitData.from_parquet(path, COAST)
    assert data_fingerprint(again) == data_fingerprint(streamed)
    assert streamed.buckets == [] and streamed.source is not None
    # whole runs again, for evaluating rules: every run once
    seen = [r for b in streamed.full_buckets() for r in b.meta["run_id"]]
    assert sorted(seen) == sorted(streamed.meta["run_id"]) and seen == list(streamed.meta["run_id"])
    assert np.isfinite(hard_objective(streamed, sve_space(), sve_space().values_of(preset("sve-option2"))))
