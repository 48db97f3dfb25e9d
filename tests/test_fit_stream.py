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


def _by_run(meta, result):
    """A [1, R] SearchResult's losses and failures keyed by run id (FitData orders runs by bucket)."""
    ids = enumerate(meta["run_id"])
    return {rid: (float(result.loss[0, i]), bool(result.failed[0, i])) for i, rid in ids}


def test_streamed_data_holds_only_the_search_layout_and_streams_the_rest_again(both):
    """from_parquet keeps no slim batches (about the search layout's size again: 1.7 GB at 3,410 logs);
    what needs them (replaying presets outside the search's spaces, the SVE level table, the relaxed
    fit) streams the same parts again, with the same values as the parsed runs' held ones."""
    from jsve.fitting._crossval import preset_results
    from jsve.fitting._study import sve_level_table

    parsed, streamed, path = both
    assert streamed.batches == [] and streamed.features == [] and parsed.batches
    again = list(streamed.iter_slim())
    assert [n for _, _, n in again] == streamed.run_counts
    assert [b.t.shape for b, _, _ in again] == [(p.n_runs, p.n_frames) for p in streamed.parts]
    assert streamed.batches == []  # iterating holds nothing

    names = ["sve-eq1", "sve-option1", "orbslam3"]  # the first two are replayed, not searched
    a, b = preset_results(parsed, names), preset_results(streamed, names)
    assert list(b) == names
    for name in names:
        left, right = _by_run(parsed.meta, a[name]), _by_run(streamed.meta, b[name])
        assert left.keys() == right.keys()
        for rid, (loss, failed) in left.items():
            assert right[rid][1] == failed and right[rid][0] == pytest.approx(loss, rel=1e-5, abs=1e-7)

    combos = {"option1": preset("sve-option1").combination}
    pd_testing = pytest.importorskip("pandas.testing")
    pd_testing.assert_frame_equal(
        sve_level_table(streamed, combos), sve_level_table(parsed, combos), rtol=1e-6, atol=1e-9
    )

    held = FitData.from_parquet(path, COAST, keep_slim=True)
    batches, features = held.slim()
    assert batches is held.batches and len(batches) == len(held.parts)
    fresh = FitData.from_parquet(path, COAST)
    assert len(fresh.slim()[0]) == len(fresh.parts) and fresh.batches  # streamed once, then held
