"""FitData streamed from Parquet (FitData.from_parquet) scores every rule as FitData of the parsed runs
does: the same runs, the same per-setting objectives, the same fingerprint on a second read."""

from __future__ import annotations

import knownanswer as ka
import numpy as np
import pytest

from jsve.core._objective import ObjectiveConfig
from jsve.core._rules import preset
from jsve.evaluation._aggregate import group_weights
from jsve.fitting._data import FitData
from jsve.fitting._optimise import hard_objective
from jsve.fitting._space import inlier_space, sve_space
from jsve.fitting._stages import data_fingerprint
from jsve.io._logs import write_log
from jsve.io._parquet import ingest

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
    from jsve.fitting._levels import sve_level_table

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


def test_one_evaluation_pass_gives_the_presets_objective_and_the_level_table():
    """`jsve fit` evaluates every rule in one pass that also scores each run as the objective does
    (evaluate_rules(objective=...)) and sums the SVE level table (on_chunk): the presets' per-run
    results taken from that table equal those replayed (or searched) on their own, and the level table
    equals the one of a pass of its own."""
    from jsve.evaluation._evaluate import evaluate_rules
    from jsve.fitting._crossval import objective_results, preset_results
    from jsve.fitting._levels import SveLevelSums, sve_level_table

    runs = ka.make_study("occlusion", range(6), n_frames=300)
    runs[1], runs[4] = ka.lose_map(runs[1], 100, 160), ka.lose_map(runs[4], 220)  # failures to compare
    streamed = FitData.from_runs(runs, COAST)
    names = ["sve-eq1", "sve-option1", "orbslam3", "sve-option2"]
    combos = {"eq1": preset("sve-eq1").combination, "option2": preset("sve-option2").combination}
    levels = SveLevelSums(combos)
    table = evaluate_rules(
        streamed.full_buckets(), [(n, preset(n)) for n in names], n_runs=streamed.n_runs,
        switch_model=COAST.switch_model, objective=COAST, on_chunk=levels.add, progress=False,
    )  # fmt: skip
    from_table = objective_results(table, streamed.meta, names)
    alone = preset_results(streamed, names)
    assert list(from_table) == names
    failures = 0
    for name in names:
        a, b = from_table[name], alone[name]
        assert a.loss.shape == b.loss.shape == (1, streamed.n_runs)
        np.testing.assert_array_equal(a.failed, b.failed)
        np.testing.assert_array_equal(a.included, b.included)
        np.testing.assert_array_equal(a.unsupported, b.unsupported)
        np.testing.assert_allclose(a.loss, b.loss, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(a.coverage, b.coverage, rtol=1e-6)
        np.testing.assert_array_equal(np.isnan(a.rmse), a.failed)  # no number for a failure
        failures += int(a.failed.sum())
    assert 0 < failures < len(names) * streamed.n_runs  # both outcomes are compared
    pd_testing = pytest.importorskip("pandas.testing")
    pd_testing.assert_frame_equal(levels.table(), sve_level_table(streamed, combos), rtol=1e-6, atol=1e-9)

    # a rule scored on only some of the runs is an error, never a shorter row; a table without the
    # objective's columns gives nothing (the presets are then replayed)
    partial = table[~((table["rule"] == "sve-eq1") & (table["run_id"] == table["run_id"].iloc[0]))]
    with pytest.raises(ValueError, match=r"'sve-eq1' on \d+ runs and lacks 1 of the study's"):
        objective_results(partial, streamed.meta, names)
    assert objective_results(table.drop(columns=["objective_loss"]), streamed.meta, names) == {}


def test_a_pass_length_by_length_is_put_back_in_the_runs_order(tmp_path):
    """`jsve fit` evaluates length by length (full_buckets(by_length=True)); in_run_order with
    meta_order gives the table of the pass in `meta`'s order, row for row, held or streamed."""
    import pyarrow.parquet as pq
    from pandas.testing import assert_frame_equal

    from jsve.evaluation import evaluate_rules, in_run_order

    long_first = ka.make_study("counts", range(8), n_frames=700) + ka.make_study(
        "occlusion", range(4), n_frames=400
    )  # as they fill, the 700-frame chunk (8 runs: ladder_chunk_size) comes first
    paths = [write_log(run, tmp_path / "logs" / f"r{i:02d}.csv") for i, run in enumerate(long_first)]
    ingest(paths, tmp_path / "s.parquet", workers=1, progress=False)
    table = pq.read_table(tmp_path / "s.parquet")
    table = table.replace_schema_metadata(pq.ParquetFile(tmp_path / "s.parquet").metadata.metadata)
    pq.write_table(table, tmp_path / "rg.parquet", row_group_size=500)  # row groups cut the runs
    rules = [("orbslam3", preset("orbslam3")), ("sve-option2", preset("sve-option2"))]
    held = FitData.from_runs(long_first, COAST)  # bucket_by_length: held buckets come by length anyway
    for data in (held, FitData.from_parquet(tmp_path / "rg.parquet", COAST)):
        options = dict(n_runs=data.n_runs, switch_model=COAST.switch_model, objective=COAST, progress=False)
        plain = evaluate_rules(data.full_buckets(), rules, **options)
        lengthwise = evaluate_rules(data.full_buckets(by_length=True), rules, **options)
        if data is not held:
            assert list(lengthwise["run_id"]) != list(plain["run_id"])  # the pass came in another order
        assert list(plain["run_id"]) == list(data.meta["run_id"]) * 2
        assert_frame_equal(in_run_order(lengthwise, data.meta_order(lengthwise["run_id"])), plain)


def test_the_objective_of_another_replay_is_refused(both):
    """The objective's terms come from the evaluation's replay: an objective under another switch model
    (or time_recently_lost) would describe a replay that did not happen."""
    from jsve.evaluation._evaluate import evaluate_rules

    _, streamed, _ = both
    with pytest.raises(ValueError, match=r"the objective replays under switch_model='imu-coast'"):
        evaluate_rules(
            streamed.full_buckets(), [("orbslam3", preset("orbslam3"))], switch_model="orbslam3",
            objective=COAST, progress=False,
        )  # fmt: skip
