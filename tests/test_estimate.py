"""jsve.fitting._estimate and jsve.fitting._counting: the search's cost on known sizes, the study's
stages counted against a scorer that computes nothing (each stage's work by hand), the pricing, and the
probe-based estimate of a real (small) `jsve fit` against its measured wall time."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import jax
import knownanswer as ka
import numpy as np
import pandas as pd
import pytest

from jsve.core._rules import PRESETS, preset
from jsve.fitting._config import StudyConfig
from jsve.fitting._counting import flat_results, plan
from jsve.fitting._estimate import (
    BFGS_COMPILE,
    Plan,
    Rates,
    StudySize,
    Work,
    backend_caveat,
    duration,
    price,
    search_cost,
)
from jsve.fitting._fit import FitConfig

R, F = 64, 100  # one part of 64 runs x 100 frames


def _size(**kw) -> StudySize:
    base = dict(
        n_runs=R,
        n_frames=R * F,
        run_counts=(R,),
        parts=((F, R),),
        chunks=((1, R, F),),
        n_devices=2,
        designs={"inliers": 1001},
        meta=pd.DataFrame({"run_id": [f"r{k}" for k in range(R)]}),
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
    """The units of each stage by hand: the study's stages against the counting scorer's flat
    objective, on which Nelder-Mead takes every (tying) reflection and no second point."""
    work = plan(_size(), CONFIG)
    n_rules = len(PRESETS) + 1  # the presets and the fitted rule
    expected = {
        # the design (1000 Sobol points and the family's preset) in 4 rounds of 128; Nelder-Mead from 2
        # starts in lockstep on every run (64 are fewer than polish_runs): the initial simplexes (2 x 5
        # points, a call of 16), then 9 more of its 10 steps of 2 reflections; the verdict of the
        # search's best and the 2 polishes (3 settings, a call of 4)
        ("fit", "search", "inliers"): (4 * 128 + 16 + 9 * 2 + 4) * R * F,
        # the presets and the fitted rule in one pass, one chunk each; it also gives the cross-validation
        # its presets' held-out rows, so that stage replays none
        ("evaluate", "evaluate", ""): n_rules * R * F,
        # the folds reuse the full fit's search (exhaustive); 2 folds x 2 starts: simplexes of 20 points
        # (a call of 24), 9 steps of 4; both folds' verdicts in one search of their distinct candidates
        # (on a flat objective the folds' coincide: 3, a call of 4)
        ("cross_validation", "search", "inliers"): (24 + 9 * 4 + 4) * R * F,
        ("parameter_bootstrap", "search", "inliers"): 16 * R * F,  # n_local + 1 settings, one call
        ("parameter_bootstrap", "flops", ""): 2 * 100 * R * (1001 + 16),
        ("heatmap", "search", "inliers"): 16 * R * F,  # 4 x 4
    }
    got = {(w.stage, w.kind, w.family): w.units for w in work.work}
    assert got == pytest.approx(expected)
    assert work.nelder_mead_steps == (10, 10)
    assert work.compiles["search", "inliers"] == {
        (F, R, 128, 0), (F, R, 128, 1), (F, R, 2, 0), (F, R, 4, 0), (F, R, 16, 0), (F, R, 24, 0)
    }  # fmt: skip
    # one evaluate computation per rule structure: the fitted inlier rule shares orbslam3's
    structures = {str(jax.tree_util.tree_structure(preset(name))) for name in PRESETS}
    assert work.compiles["evaluate", ""] == {(s, R, F) for s in structures}
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
                ("parameter_bootstrap", "flops", ""): 2 * 100 * R * (1001 + 1),
            }
        )


def test_halving_scores_each_rung_on_its_new_runs():
    """1001 settings, 64 runs, eta 3, f0 1/9: rungs of (1001, 8), (334, 22), (112, 64) runs; each rung
    scores its settings on the runs the previous rungs did not (8, 14, 42 of the single part: sub-batches
    of 8, 16 and the part). A fold halves on the full fit's cache: only its prefixes' runs the fit's
    rungs did not reach are new; a resumed study (the fit done, its cache gone) scores every pair."""
    config = StudyConfig(
        families=("inliers",),
        kfold=2,
        leave_one_out=(),
        heatmap=(),
        n_local=0,
        fit=FitConfig(n_search=1000, search="halving", n_starts=0),
    )
    size = _size()
    work = plan(size, config)
    runs = lambda n: np.arange(n)  # noqa: E731 (one part: the cost depends on how many runs alone)
    rungs = sum(search_cost(size, n, runs(k))[0] for n, k in ((1001, 8), (334, 14), (112, 42)))
    verdict = search_cost(size, 1)[0]  # the search's best (no polish: n_starts 0) on every run
    assert work.units("search", "inliers", stage="fit") == rungs + verdict
    cached = work.units("search", "inliers", stage="cross_validation")
    resumed = plan(size, config, done={"fit_inliers"}).units("search", "inliers", stage="cross_validation")
    # the folds' verdict (their 2 bests) at least; without the cache the folds' rungs again, at least
    # the 1001 settings on the first rung's 8 runs (each weighted in one of the 2 folds)
    assert search_cost(size, 1)[0] <= cached < resumed
    assert resumed >= cached + search_cost(size, 1001, runs(8))[0]


def test_the_flat_objective_answers_in_the_requested_shape():
    values = np.ones((3, 2))
    res = flat_results(values, 5)
    assert res.loss.shape == res.included.shape == (3, 5) and not res.failed.any()
    assert np.allclose(res.objective(np.ones(5)), res.loss[0, 0]) and res.coverage.min() == 1.0


def test_price_is_units_times_rates_and_the_compilations_left():
    work = Plan(
        work=(Work("fit", "search", "sve", 1e9), Work("fit", "relaxed", "sve", 100.0)),
        compiles={
            ("search", "sve"): frozenset({1, 2, 3}),
            ("relaxed", "sve"): frozenset({"sve"}),
            ("bfgs", "sve"): frozenset({"sve"}),
        },
    )
    rates = Rates(
        seconds={("search", "sve"): 2e-8, ("relaxed", "sve"): 0.5},
        compile={("search", "sve"): 4.0, ("relaxed", "sve"): 10.0},
        compiled={("search", "sve"): frozenset({1}), ("relaxed", "sve"): frozenset({"sve"})},
    )
    estimate = price(work, rates)
    assert estimate.stages == {"fit": pytest.approx(20.0 + 50.0)}
    # the relaxed objective was compiled by the probe; the BFGS costs BFGS_COMPILE times its compile
    assert estimate.compile == pytest.approx(2 * 4.0 + BFGS_COMPILE * 10.0)
    assert estimate.total == pytest.approx(70.0 + 8.0 + BFGS_COMPILE * 10.0)
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
    """bootstrap_screen_runs 8 of 64 runs: rungs of 8 and 24 runs (RACE_ETA 3); on a flat objective
    every setting could win a resample, so the race keeps all 100 (its most work): 8, then 16 new runs,
    then the other 40."""
    from jsve.fitting._crossval import RACE_ETA

    assert RACE_ETA == 3
    config = replace(CONFIG, bootstrap_screen_runs=8, n_local=99, heatmap=(), kfold=0)
    expected = sum(search_cost(_size(), 100, np.arange(k))[0] for k in (8, 16, 40))
    work = plan(_size(), config)
    assert work.units("search", "inliers", stage="parameter_bootstrap") == expected
