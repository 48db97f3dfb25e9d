"""jsve.fitting._estimate: the cost model's arithmetic on known sizes, its pricing, and the probe-based
estimate of a real (small) `jsve fit` against its measured wall time."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import knownanswer as ka
import numpy as np
import pytest

from jsve.fitting._config import StudyConfig
from jsve.fitting._estimate import (
    NM_MOVED_SHARE,
    Plan,
    Rates,
    StudySize,
    Work,
    backend_caveat,
    duration,
    halving_rectangles,
    plan,
    price,
    search_cost,
)
from jsve.fitting._fit import FitConfig

R, F = 64, 100  # one part of 64 runs x 100 frames


def _size(**kw) -> StudySize:
    folds = (np.arange(R) < R // 2, np.arange(R) >= R // 2)
    base = dict(
        n_runs=R,
        n_frames=R * F,
        run_counts=(R,),
        parts=((F, R),),
        chunks=((1, R, F),),
        n_devices=2,
        designs={"inliers": 1000},
        dims={"inliers": 4},
        heatmap={"inliers": True},
        presets=(("orbslam3", "I", "inliers"), ("sve-eq1", "E", "")),
        structures={"inliers": "I"},
        folds=folds,
        order=np.arange(R),
    )
    return StudySize(**{**base, **kw})


CONFIG = StudyConfig(
    families=("inliers",),
    kfold=2,
    leave_one_out=(),
    n_boot=100,
    n_local=15,
    heatmap=("imu_init", "recovery", 4),
    fit=FitConfig(n_search=1000, n_starts=2, nm_steps=10),
)


def test_search_cost_is_rounds_of_calls_times_lanes_and_frames():
    """64 runs: 128 settings a call (8192 lanes); 1000 settings are 8 calls, 4 rounds on 2 devices, each
    128 x 64 x 100 lane-frames. 16 settings: one call of 16 on one device."""
    units, keys = search_cost(_size(), 1000)
    assert units == 4 * 128 * R * F
    assert keys == {(F, R, 128, 0), (F, R, 128, 1)}
    units, keys = search_cost(_size(n_devices=1), 1000)
    assert units == 8 * 128 * R * F and keys == {(F, R, 128, 0)}
    assert search_cost(_size(), 16) == (16 * R * F, {(F, R, 16, 0)})
    # 8 of the part's 64 runs are gathered into a sub-batch of 8 (a power of 2), 5 into one of 8; 8192 / 8
    # = 1024 settings a call hold the 1000 in one call, padded to 1000 (a multiple of 8), not 1024
    assert search_cost(_size(), 1000, np.arange(8))[0] == 1000 * 8 * F
    assert search_cost(_size(), 1000, np.arange(5))[1] == {(F, 8, 1000, 0)}
    # Nelder-Mead's 38 reflections: one call of 40 settings (was 64)
    assert search_cost(_size(), 38) == (40 * R * F, {(F, R, 40, 0)})


def test_plan_counts_every_stage_of_the_study():
    """The units of each stage by hand (module docstring of jsve.fitting._estimate)."""
    work = plan(_size(), CONFIG)
    assert 0 < NM_MOVED_SHARE <= 0.25  # below: the moved points of 2 and of 4 simplexes are 1 (rounded up)
    expected = {
        # the design in 4 rounds of 128; Nelder-Mead from 2 starts in lockstep on every run (64 are
        # fewer than polish_runs): the initial simplexes (2 x 5 points, a call of 16), then 10 steps of
        # a call of 2 (reflections) and one of 1; the verdict: the search's best and 2 polishes (4)
        ("fit", "search", "inliers"): (4 * 128 + 16 + 10 * (2 + 1) + 4) * R * F,
        # the presets (two rule structures) and the fitted rule in one pass, one chunk each; it also gives
        # the cross-validation its presets' held-out rows, so that stage replays none
        ("evaluate", "evaluate", ""): 3 * R * F,
        # 2 folds x 2 starts: simplexes of 20 points (a call of 24, a multiple of 8), steps of 4 and 1
        # points; both folds' verdicts (and held-out rows) in one search of 2 x 3 candidates: a call of 8
        ("cross_validation", "search", "inliers"): (24 + 10 * (4 + 1) + 8) * R * F,
        ("parameter_bootstrap", "search", "inliers"): 16 * R * F,  # n_local + 1 settings, one call
        ("parameter_bootstrap", "flops", ""): 2 * 100 * R * (1000 + 16),
        ("heatmap", "search", "inliers"): 16 * R * F,  # 4 x 4
    }
    got = {(w.stage, w.kind, w.family): w.units for w in work.work}
    assert got == pytest.approx(expected)
    assert work.compiles["search", "inliers"] == {
        (F, R, 128, 0), (F, R, 128, 1), (F, R, 1, 0), (F, R, 2, 0), (F, R, 16, 0), (F, R, 24, 0),
        (F, R, 4, 0), (F, R, 8, 0)
    }  # fmt: skip
    assert work.compiles["evaluate", ""] == {("I", R, F), ("E", R, F)}
    assert ("nelder_mead", "inliers") not in work.compiles  # no computation of its own
    # stages done already are left out; with all of them done there is nothing to do
    fewer = plan(_size(), CONFIG, done={"evaluate", "fit_inliers"})
    assert not fewer.units("search", "inliers", stage="fit") and not fewer.units("evaluate", stage="evaluate")
    assert fewer.units("search", "inliers", stage="cross_validation") == pytest.approx(
        work.units("search", "inliers", stage="cross_validation")
    )
    every = {"fit_inliers", "evaluate", "cross_validation", "parameter_bootstrap"}
    assert plan(_size(), CONFIG, done=every | {"heatmap"}).work == ()
    # without a local design (n_local 0, the default study) the bootstrap scores the fit alone on every
    # run, never raced, and the rest is unchanged
    for screen in (0, 8):
        lean = plan(_size(), replace(CONFIG, n_local=0, bootstrap_screen_runs=screen))
        assert {(w.stage, w.kind, w.family): w.units for w in lean.work} == pytest.approx(
            {
                **expected,
                ("parameter_bootstrap", "search", "inliers"): 1 * R * F,
                ("parameter_bootstrap", "flops", ""): 2 * 100 * R * (1000 + 1),
            }
        )


def test_halving_scores_each_rung_on_its_new_runs():
    """1000 settings, 64 runs, eta 3, f0 1/9: rungs of (1000, 8), (334, 22), (112, 64) runs; each rung
    scores its settings on the runs the previous rungs did not (a prefix of the order)."""
    config = StudyConfig(
        families=("inliers",),
        kfold=2,
        leave_one_out=(),
        heatmap=(),
        fit=FitConfig(n_search=1000, search="halving", n_starts=0),
    )
    size = _size(order=np.random.default_rng(0).permutation(R))
    fit, folds = halving_rectangles(size, "inliers", 3.0, 1 / 9)
    assert [(n, len(runs)) for n, runs in fit] == [(1000, 8), (334, 14), (112, 42)]
    assert np.array_equal(np.sort(np.concatenate([r for _, r in fit])), np.arange(R))  # each run once
    # A fold's prefixes skip its held-out runs, so the folds' union reaches further into the order; with
    # the full fit's cache only those runs are new, without it every pair the folds need.
    assert all(n in (1000, 334) for n, _ in folds)
    _, uncached = halving_rectangles(size, "inliers", 3.0, 1 / 9, cached=False)
    assert sum(n * len(r) for n, r in uncached) > sum(n * len(r) for n, r in folds)
    work = plan(size, config)
    # then the verdict: the search's best on every run (no polish: n_starts 0), per fold in the folds'
    expected = sum(search_cost(size, n, runs)[0] for n, runs in fit) + search_cost(size, 1)[0]
    assert work.units("search", "inliers", stage="fit") == expected
    assert (
        work.units("search", "inliers", stage="cross_validation")
        == sum(search_cost(size, n, runs)[0] for n, runs in folds) + search_cost(size, 2)[0]
    )


def test_price_is_units_times_rates_and_the_compilations_left():
    work = Plan(
        work=(Work("fit", "search", "sve", 1e9), Work("fit", "objective", "sve", 100.0)),
        compiles={
            ("search", "sve"): frozenset({1, 2, 3}),
            ("objective", "sve"): frozenset({"sve"}),
            ("relaxed", "sve"): frozenset({"sve"}),
        },
    )
    rates = Rates(
        seconds={("search", "sve"): 2e-8, ("objective", "sve"): 0.5},
        compile={("search", "sve"): 4.0, ("objective", "sve"): 10.0, ("relaxed", "sve"): 30.0},
        compiled={("search", "sve"): frozenset({1}), ("objective", "sve"): frozenset({"sve"})},
    )
    estimate = price(work, rates)
    assert estimate.stages == {"fit": pytest.approx(20.0 + 50.0)}
    assert estimate.compile == pytest.approx(2 * 4.0 + 30.0)  # the objective was compiled by the probe
    assert estimate.total == pytest.approx(70.0 + 8.0 + 30.0)
    assert [duration(s) for s in (40, 210, 7200)] == ["40 s", "3.5 min", "2.0 h"]


def test_an_estimate_off_cpu_says_it_may_be_far_too_low():
    """The cost model was measured on CPU; on an accelerator (an H200: 3.7 min expected, not done after
    4.3 min) the line says so, and on CPU it says nothing more."""
    estimate = price(Plan(work=(Work("fit", "search", "sve", 1e9),), compiles={}), Rates(
        seconds={("search", "sve"): 2e-8}, compile={}, compiled={}
    ))  # fmt: skip
    assert backend_caveat("cpu") == "" and estimate.line().endswith("compiling")
    gpu = replace(estimate, caveat=backend_caveat("gpu"))
    assert gpu.total == estimate.total
    assert gpu.line().startswith(estimate.line() + "; on gpu it may be far too low")
    assert gpu.as_dict()["caveat"] == backend_caveat("gpu") and "H200" in gpu.line()


# One family and one call size for every search (65, 128 and 81 settings: 128 a call), so that the
# study compiles few computations: it is all compilation, about a minute without the persistent cache.
TINY_STUDY = """
families = ["inliers"]
kfold = 2
leave_one_out = []
n_boot = 50
n_local = 127
heatmap = ["imu_init", "recovery", 9]
fit = { n_search = 64, n_starts = 1, nm_steps = 10 }
"""


@pytest.mark.slow
def test_jsve_fit_states_its_expected_time_and_meets_it(tmp_path, capsys):
    """`jsve fit` states the expected wall time on stderr before the study and the actual one after, and
    records both in study.json; on a small study (all compilation: the cache is off in the tests) the
    actual time is within 3x of the expected one. The probe changes no result: a fit with
    --no-estimate (and no line about it) writes the same fitted rule."""
    from jsve.cli import main
    from jsve.io import write_log

    logs = tmp_path / "logs"
    logs.mkdir()
    for k, run in enumerate(ka.make_study("occlusion", range(6), n_frames=200)):
        write_log(run, logs / f"r{k}.csv")
    config = tmp_path / "study.toml"
    config.write_text(TINY_STUDY)
    argv = ["fit", str(logs), "--config", str(config), "--no-progress", "--no-report"]
    assert main([*argv, "-o", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err.splitlines()
    (before,) = [line for line in err if line.startswith("jsve fit: expected wall time")]
    assert "6 runs, 1,200 frames, inliers 65 settings (exhaustive), 2 folds" in before
    assert re.search(r"from a probe of \d+ s after \d+ s compiling$", before)
    (after,) = [line for line in err if line.startswith("jsve fit: took")]
    timing = json.loads((tmp_path / "a" / "study.json").read_text())["timing"]
    assert timing["actual_s"] > 0 and timing["expected_s"] > 0
    assert f"(actual / expected {timing['actual_over_expected']:.2f})" in after
    assert 1 / 3 <= timing["actual_over_expected"] <= 3, timing

    assert main([*argv, "-o", str(tmp_path / "b"), "--no-estimate"]) == 0
    assert not [line for line in capsys.readouterr().err.splitlines() if "expected" in line]
    assert "timing" not in json.loads((tmp_path / "b" / "study.json").read_text())
    fitted = [json.loads((tmp_path / d / "fitted_inliers.json").read_text()) for d in "ab"]
    assert fitted[0]["values"] == fitted[1]["values"] and fitted[0]["objective"] == fitted[1]["objective"]
    # A rerun resumes every stage: nothing to time, no probe, no line.
    assert main([*argv, "-o", str(tmp_path / "a")]) == 0
    assert "expected wall time" not in capsys.readouterr().err
    # --estimate-only: the line, then nothing written (a fresh folder stays empty); on a finished study
    # it says there is nothing left.
    assert main([*argv, "-o", str(tmp_path / "c"), "--estimate-only"]) == 0
    assert "jsve fit: expected wall time" in capsys.readouterr().err
    assert not list((tmp_path / "c").iterdir())
    assert main([*argv, "-o", str(tmp_path / "a"), "--estimate-only"]) == 0
    assert "nothing to estimate" in capsys.readouterr().err


def test_the_bootstrap_race_is_counted_rung_by_rung():
    """bootstrap_screen_runs 8 of 64 runs: rungs of 8 and 24 runs (RACE_ETA 3), each keeping
    BOOTSTRAP_KEPT_SHARE of the settings left, then the survivors on the other 40 runs."""
    from dataclasses import replace

    from jsve.fitting._crossval import RACE_ETA
    from jsve.fitting._estimate import BOOTSTRAP_KEPT_SHARE

    assert RACE_ETA == 3
    size = _size(order=np.random.default_rng(1).permutation(R))
    config = replace(CONFIG, bootstrap_screen_runs=8, n_local=99, heatmap=(), kfold=0)
    n1 = 100
    n2 = int(np.ceil(BOOTSTRAP_KEPT_SHARE * n1))
    n3 = int(np.ceil(BOOTSTRAP_KEPT_SHARE * n2))
    order = np.asarray(size.order)
    expected = (
        search_cost(size, n1, np.sort(order[:8]))[0]
        + search_cost(size, n2, np.sort(order[8:24]))[0]
        + search_cost(size, n3, np.sort(order[24:]))[0]
    )
    work = plan(size, config)
    assert work.units("search", "inliers", stage="parameter_bootstrap") == expected
