"""jsve.fitting._study: the study's configuration and its tables (whole studies: tests/test_report.py).

Oracles: jsve.fitting._space for the families' spaces, and the per-frame features averaged by hand
(numpy over the valid frames of each disturbance and level) for the SVE-per-level table.
"""

from __future__ import annotations

import re

import jax.numpy as jnp
import knownanswer as ka
import numpy as np
import pytest

from jsve.core._rules import preset
from jsve.core._sve import FrameFeatures, s_a_from_ratio
from jsve.fitting._config import StudyConfig
from jsve.fitting._data import FitData
from jsve.fitting._levels import sve_level_table
from jsve.fitting._search import search
from jsve.fitting._space import inlier_space, space_from_dict, sve_space
from jsve.fitting._study import heatmap_table


def test_config_spaces_are_the_families_spaces():
    config = StudyConfig()
    assert config.space("sve") == sve_space() and config.space("inliers") == inlier_space()
    narrowed = StudyConfig(spaces={"sve": {"fixed": {"rho": 0.25}, "free": {"imu_init": [0.0, 0.3]}}})
    want = space_from_dict({"kind": "sve", "fixed": {"rho": 0.25}, "free": {"imu_init": [0.0, 0.3]}})
    assert narrowed.space("sve") == want and want.dim == sve_space().dim - 1
    assert narrowed.space("inliers") == inlier_space()
    with pytest.raises(ValueError, match="space kind must be 'sve' or 'inliers', got 'linear'"):
        config.space("linear")


def test_config_round_trip_and_unknown_keys():
    config = StudyConfig(kfold=3, heatmap=("imu_init", "not_init", 5))
    assert StudyConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown study settings"):
        StudyConfig.from_dict({"kfolds": 3})
    with pytest.raises(ValueError, match=r"unknown \[fit\] settings"):
        StudyConfig.from_dict({"fit": {"steps": 3}})


def test_support_policy_keys_the_study_and_reaches_the_objective():
    """`support` is a study setting: it reaches the objective, it keys the study (a study resumed under
    the other policy stops, or starts over with --force: tests/test_report.py), `jsve fit --support`
    sets it, and a wrong value is refused when the study is configured."""
    from jsve.cli import build_parser
    from jsve.fitting._stages import fingerprint

    default, exclude = StudyConfig(), StudyConfig(support="exclude")
    assert default.objective().support == "penalise" and exclude.objective().support == "exclude"
    assert StudyConfig.from_dict(exclude.to_dict()) == exclude
    assert fingerprint(default.to_dict()) != fingerprint(exclude.to_dict())
    assert StudyConfig.from_toml(None, support="exclude") == exclude
    assert StudyConfig.from_toml(None, support=None) == default
    args = build_parser().parse_args(["fit", "logs", "-o", "out", "--support", "exclude"])
    assert args.support == "exclude"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "logs", "-o", "out", "--support", "drop"])
    with pytest.raises(ValueError, match="support must be one of"):
        StudyConfig.from_dict({"support": "drop"})


def test_search_method_from_the_config_file_and_the_command_line(tmp_path):
    """[fit] search / eta / initial_fraction in the TOML config, `jsve fit --search --eta
    --initial-fraction` over them; the study's key changes with them; wrong values are refused when the
    study is configured (argparse for the method's name)."""
    from jsve.cli import build_parser
    from jsve.fitting._fit import FitConfig
    from jsve.fitting._stages import fingerprint

    toml = tmp_path / "fit.toml"
    toml.write_text('[fit]\nsearch = "exhaustive"\neta = 2.0\n')
    from_file = StudyConfig.from_toml(str(toml))
    assert (from_file.fit.search, from_file.fit.eta) == ("exhaustive", 2.0)
    both = StudyConfig.from_toml(str(toml), search="halving", initial_fraction=0.25, eta=None)
    assert (both.fit.search, both.fit.eta, both.fit.initial_fraction) == ("halving", 2.0, 0.25)
    assert StudyConfig.from_dict(both.to_dict()) == both
    assert fingerprint(both.to_dict()) != fingerprint(from_file.to_dict())
    assert StudyConfig.from_toml(None).fit == FitConfig()
    argv = ["fit", "logs", "-o", "out", "--search", "exhaustive", "--eta", "4", "--initial-fraction", "0.5"]
    args = build_parser().parse_args(argv)
    assert (args.search, args.eta, args.initial_fraction) == ("exhaustive", 4.0, 0.5)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "logs", "-o", "out", "--search", "random"])
    with pytest.raises(ValueError, match="initial_fraction"):
        StudyConfig.from_toml(None, search="halving", initial_fraction=2.0)
    with pytest.raises(ValueError, match="eta > 1"):
        StudyConfig.from_toml(None, search="halving", eta=1.0)


def test_the_default_study_is_k_fold_only_and_thorough_adds_the_rest(tmp_path):
    """The default study cross-validates by k-fold and its parameter bootstrap has no local design;
    `jsve fit --thorough` (jsve.fitting.THOROUGH) adds leave-one-sequence/disturbance-out folds and a
    local design of 1,024 settings;
    a --config file's keys win over --thorough, command-line flags over both; the study's key changes
    with it; a count that is not one is refused."""
    from jsve.cli import build_parser
    from jsve.fitting._config import THOROUGH
    from jsve.fitting._stages import fingerprint
    from jsve.fitting._study import study_folds

    default = StudyConfig()
    assert default.leave_one_out == () and default.n_local == 0
    runs = ka.make_study("occlusion", range(6), n_frames=50)
    folds = study_folds(FitData.from_runs(runs).meta, default)
    assert {f.kind for f in folds} == {"kfold"} and len(folds) == default.kfold
    thorough = StudyConfig.from_toml(None, thorough=True)
    assert thorough.leave_one_out == THOROUGH["leave_one_out"] == ("sequence", "disturbance")
    assert thorough.n_local == THOROUGH["n_local"] == 1024
    assert thorough == StudyConfig(**THOROUGH) and StudyConfig.from_toml(None) == default
    assert fingerprint(thorough.to_dict()) != fingerprint(default.to_dict())
    toml = tmp_path / "fit.toml"
    toml.write_text("n_local = 64\n")
    assert StudyConfig.from_toml(str(toml), thorough=True) == StudyConfig(**{**THOROUGH, "n_local": 64})
    assert StudyConfig.from_toml(str(toml), thorough=True, seed=3).seed == 3
    assert build_parser().parse_args(["fit", "logs", "-o", "out", "--thorough"]).thorough
    assert not build_parser().parse_args(["fit", "logs", "-o", "out"]).thorough
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match=r"n_local must be a count >= 0 \(0: none\)"):
            StudyConfig(n_local=bad)


def test_a_wrong_setting_names_where_it_came_from(tmp_path):
    """A wrong value in the --config file names the file (and [fit] for that table); one from a
    command-line flag over a good file names the command line, not the file."""

    toml = tmp_path / "fit.toml"
    toml.write_text("n_local = -1\n")
    with pytest.raises(ValueError, match=rf"^{re.escape(str(toml))}: StudyConfig.n_local must be a count"):
        StudyConfig.from_toml(str(toml))
    toml.write_text('[fit]\nsearch = "halving"\neta = 1.0\n')
    with pytest.raises(ValueError, match=rf"^{re.escape(str(toml))}: \[fit\] halving needs eta > 1"):
        StudyConfig.from_toml(str(toml))
    toml.write_text('[fit]\nsearch = "halving"\n')
    with pytest.raises(ValueError, match=r"^the command line: \[fit\] halving needs eta > 1"):
        StudyConfig.from_toml(str(toml), eta=1.0)


@pytest.fixture(scope="module")
def data():
    return FitData.from_runs(ka.make_study("occlusion", range(6), n_frames=200))


def test_sve_level_table_is_the_mean_of_the_valid_frames(data):
    """Per (disturbance, level, combination): frames, and the mean and std of the score and of every
    metric (S_a at the combination's rho, then each further FrameFeatures field) over the valid frames
    of those runs, as numpy computes them from the features (float64 sums of float32 values: 1e-6
    relative for means, 1e-4 for the std's one-pass variance)."""
    combos = {name: preset(name).combination for name in ("sve-eq1", "sve-option2")}
    table = sve_level_table(data, combos)
    metrics = [k for k in FrameFeatures.__dataclass_fields__ if k not in ("n_inliers", "inlier_ratio")]
    assert {"s_b", "s_c"} <= set(metrics)
    assert list(table.columns) == ["disturbance", "level", "combination", "frames"] + [
        f"{k}_{s}" for k in ("sve", "s_a", *metrics) for s in ("mean", "std")
    ]
    frames = []
    for feats, batch, n in zip(data.features, data.batches, data.run_counts, strict=True):
        valid = np.asarray(batch.valid[:n])
        for r in range(n):
            keys = ("inlier_ratio", *metrics)
            frames.append({k: np.asarray(getattr(feats, k)[r], np.float64)[valid[r]] for k in keys})
    levels = data.meta["level"].to_numpy()
    for name, combo in combos.items():
        for level in np.unique(levels):
            runs = [frames[i] for i in np.flatnonzero(levels == level)]
            cat = {k: np.concatenate([f[k] for f in runs]) for k in runs[0]}
            leaves = cat | {"n_inliers": 0 * cat["s_b"]}
            features = FrameFeatures(**{k: jnp.asarray(x) for k, x in leaves.items()})  # JAX leaves
            want = {
                "sve": np.asarray(combo.score(features), np.float64),
                "s_a": np.asarray(s_a_from_ratio(cat["inlier_ratio"], combo.rho), np.float64),
                **{k: cat[k] for k in metrics},
            }
            row = table[(table["combination"] == name) & (table["level"] == level)].iloc[0]
            assert row["frames"] == len(cat["s_b"])
            for k, x in want.items():
                np.testing.assert_allclose(row[f"{k}_mean"], x.mean(), rtol=1e-6, err_msg=k)
                np.testing.assert_allclose(row[f"{k}_std"], x.std(), rtol=1e-4, atol=1e-7, err_msg=k)


def test_heatmap_table_is_the_search_over_a_grid(data):
    """Every cell is the search's objective at that pair of thresholds, the other values held (to
    float32 rounding of the kernel)."""
    space = inlier_space()
    values = space.values_of(preset("orbslam3"))
    weights = np.ones(data.n_runs)
    table = heatmap_table(data, space, values, weights, "imu_init", "recovery", 3)
    assert len(table) == 9 and set(table["x_name"]) == {"imu_init"} and set(table["y_name"]) == {"recovery"}
    cell = table.iloc[4]
    point = np.array(values)
    point[space.names.index("imu_init")], point[space.names.index("recovery")] = cell["x"], cell["y"]
    res = search(data.parts, space, point[None], data.config, run_counts=data.run_counts, progress=False)
    # float32 kernel: XLA contracts multiply-adds differently for another number of settings (lanes)
    assert cell["objective"] == pytest.approx(float(res.objective(weights)[0]), rel=1e-5)
    with pytest.raises(ValueError, match="heat map axes"):
        heatmap_table(data, space, values, weights, "imu_init", "rho", 3)
    assert set(table["n_runs"]) == set(table["n_weighted"]) == {data.n_runs}


def test_a_heatmap_on_a_subset_is_the_objective_of_those_runs(data):
    """heatmap_runs: every cell is the objective over the subset's runs alone (the full search with the
    other runs' weights set to 0), and the table says how many runs it scored of how many."""
    from jsve.fitting._polish import polish_runs

    space = inlier_space()
    values = space.values_of(preset("orbslam3"))
    weights = np.linspace(0.5, 2.0, data.n_runs)
    m = data.n_runs // 2
    table = heatmap_table(data, space, values, weights, "imu_init", "recovery", 3, runs=m, seed=4)
    assert set(table["n_runs"]) == {m} and set(table["n_weighted"]) == {data.n_runs}
    subset = polish_runs(data.meta, weights, m, seed=4)
    only = np.zeros(data.n_runs)
    only[subset] = weights[subset]
    grid = np.repeat(np.asarray(values, np.float64)[None], len(table), axis=0)
    grid[:, space.names.index("imu_init")] = table["x"]
    grid[:, space.names.index("recovery")] = table["y"]
    res = search(data.parts, space, grid, data.config, run_counts=data.run_counts, progress=False)
    np.testing.assert_allclose(table["objective"], res.objective(only), rtol=1e-5)
    assert np.abs(res.objective(only) - res.objective(weights)).max() > 1e-3  # the subset matters here
    np.testing.assert_allclose(table["failure_rate"], res.failure_rate(only), rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="heatmap_runs"):
        StudyConfig(heatmap_runs=-1)
