"""The parameter bootstrap's screen (jsve.fitting._crossval.plausible_winners): settings dropped on a
subset of the runs are ones that never win a resample of the whole study.

Oracle: the bootstrap itself, run on the full matrix of per-run losses (every setting on every run):
a setting that wins any of its resamples must survive the screen."""

from __future__ import annotations

import numpy as np
import pytest

from jsve.fitting._crossval import effective_runs, plausible_winners


def _losses(rng, n_settings: int, n_runs: int) -> np.ndarray:
    """Per-run losses of settings around a fit (last row): a run effect shared by all settings (runs
    differ far more than settings do), plus each setting's own offset from the fit (0 to 8 cm, most
    near 0: a local design around an optimum) and per-pair noise; failed runs at the 1 m penalty."""
    run = rng.gamma(2.0, 0.05, n_runs)
    offset = np.concatenate([rng.exponential(0.02, n_settings - 1), [0.0]])
    noise = rng.normal(0.0, 0.03, (n_settings, n_runs))
    noise[-1] = 0.0
    loss = np.clip(run[None] + offset[:, None] + noise, 0.0, None)
    # failures: runs that fail under every setting (the front-end lost), and a few setting-run pairs
    failed = (rng.random(n_runs) < 0.03)[None] | (rng.random((n_settings, n_runs)) < 0.005)
    return np.where(failed, 1.0, loss)


def _bootstrap_winners(loss: np.ndarray, weights: np.ndarray, n_boot: int, rng) -> np.ndarray:
    n = loss.shape[1]
    counts = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(n_boot)])
    objective = (counts * weights[None]) @ loss.T  # [n_boot, S]
    return np.unique(np.argmin(objective, axis=1))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_setting_that_wins_a_resample_survives_the_screen(seed):
    rng = np.random.default_rng(seed)
    n_settings, n_runs, m = 400, 3000, 300
    loss = _losses(rng, n_settings, n_runs)
    weights = rng.uniform(0.5, 2.0, n_runs)
    subset = np.sort(rng.choice(n_runs, m, replace=False))
    keep = plausible_winners(loss[:, subset], weights[subset], effective_runs(weights))
    winners = _bootstrap_winners(loss, weights, 500, rng)
    assert keep[winners].all(), f"dropped winners {winners[~keep[winners]]}"
    assert keep[-1]
    # and it drops some: settings several cm worse than the fit cannot win
    assert keep.mean() < 0.9


def test_the_screen_keeps_ties_and_drops_the_clearly_worse():
    fit = np.linspace(0.1, 0.5, 50)
    loss = np.stack([fit + 0.3, fit, fit + np.where(np.arange(50) % 2, 0.01, -0.01), fit])
    keep = plausible_winners(loss, np.ones(50), 5000.0)
    # 0.3 m worse on every run: dropped. Equal: kept. +-1 cm around the fit: kept. The fit: kept.
    assert keep.tolist() == [False, True, True, True]


def test_a_wider_screen_keeps_more():
    rng = np.random.default_rng(5)
    loss = _losses(rng, 300, 400)
    w = np.ones(400)
    narrow = plausible_winners(loss, w, 4000.0, z=1.0)
    wide = plausible_winners(loss, w, 4000.0, z=4.0)
    assert (narrow <= wide).all() and wide.sum() > narrow.sum()


def test_effective_runs_is_kish():
    assert effective_runs(np.ones(10)) == pytest.approx(10.0)
    assert effective_runs(np.array([1.0, 1.0, 2.0])) == pytest.approx(16 / 6)


def test_a_screened_bootstrap_gives_the_unscreened_intervals():
    """On logs whose best inlier threshold is K (tests/knownanswer.py), the screened parameter
    bootstrap scores fewer local settings on every run and picks the same setting in every resample:
    with one screen (60 of the 160 runs) and with a race of two (20, then 60 runs), whose second rung
    drops settings the first kept."""
    import knownanswer as ka

    from jsve.core._objective import ObjectiveConfig
    from jsve.fitting._crossval import parameter_bootstrap
    from jsve.fitting._data import FitData
    from jsve.fitting._fit import FitConfig, fit
    from jsve.fitting._space import inlier_space

    data = FitData.from_runs(
        ka.make_study("counts", range(160), n_frames=300, k_min=40), ObjectiveConfig(switch_model="imu-coast")
    )
    space = inlier_space()
    result = fit(data, space, config=FitConfig(n_search=64, n_starts=0), progress=False)
    kwargs = dict(n_local=127, fraction=0.3, n_boot=300, seed=3, progress=False)
    full = parameter_bootstrap(data, space, result, **kwargs)
    screened = parameter_bootstrap(data, space, result, screen_runs=60, **kwargs)
    raced = parameter_bootstrap(data, space, result, screen_runs=20, **kwargs)
    assert set(full["local"]) == set(full["local_scored"]) == {128} and set(full["race"]) == {"128"}
    assert screened["local_scored"].iloc[0] < 128
    first, second, last = (int(k) for k in raced["race"].iloc[0].split(">"))
    assert first == 128 and 128 > second > last == raced["local_scored"].iloc[0]
    for column in ("value", "ci_low", "ci_high", "boot_std"):
        np.testing.assert_allclose(screened[column], full[column], err_msg=column)
        np.testing.assert_allclose(raced[column], full[column], err_msg=column)
    # the objective is flat for the recovery threshold in (K - 1, K]: the resamples' refits spread over
    # that plateau and never leave it
    row = full.set_index("parameter").loc["recovery"]
    assert 39.0 < row["ci_low"] < row["ci_high"] <= 40.0 + 1e-6, row
    # without a local design (n_local 0, the default study) a refit chooses between the search's
    # settings and the fit: no race (one setting to score, the fit, on every run), and every interval
    # lies within those candidates' values
    bare = parameter_bootstrap(data, space, result, **{**kwargs, "n_local": 0}, screen_runs=20)
    assert set(bare["local"]) == set(bare["local_scored"]) == {1} and set(bare["race"]) == {"1"}
    unscreened = parameter_bootstrap(data, space, result, **{**kwargs, "n_local": 0})
    for column in ("ci_low", "ci_high", "boot_std"):  # skipping the race changes nothing
        np.testing.assert_array_equal(bare[column], unscreened[column], err_msg=column)
    candidates = np.concatenate([result.search.values, result.values[None]])
    for j, name in enumerate(space.names):
        row = bare.set_index("parameter").loc[name]
        lo, hi = candidates[:, j].min(), candidates[:, j].max()
        assert lo - 1e-9 <= row["ci_low"] <= row["ci_high"] <= hi + 1e-9, (name, row)


def test_a_tie_is_broken_at_random_whatever_the_order():
    """resample_winners: without ties the argmin; among settings that tie (a plateau of the hard
    objective) each is drawn about equally often, never a setting that does not tie, and the draw
    depends on the settings' values, not on their order or on the other settings scored."""
    from jsve.fitting._crossval import resample_winners

    rng = np.random.default_rng(0)
    values = rng.random((6, 3))
    objective = rng.random((4000, 6)) + 1.0
    np.testing.assert_array_equal(resample_winners(objective, values), np.argmin(objective, axis=1))
    objective[:, [1, 3, 4]] = 0.5  # three settings on one plateau, best in every resample
    objective[:, 3] += 1e-14  # rounding of equal per-run losses summed in another order
    picks = resample_winners(objective, values)
    assert set(picks) == {1, 3, 4}
    shares = np.bincount(picks, minlength=6)[[1, 3, 4]] / len(picks)
    np.testing.assert_allclose(shares, 1 / 3, atol=0.03)  # binomial sd 0.0075 at 4000 draws
    order = rng.permutation(6)
    permuted = resample_winners(objective[:, order], values[order])
    np.testing.assert_array_equal(order[permuted], picks)
    extra = np.concatenate([objective, objective[:, :1] + 1.0], axis=1)  # a dominated setting added
    np.testing.assert_array_equal(resample_winners(extra, np.concatenate([values, values[:1] + 1])), picks)
