"""StallingNelderMead: optimistix's simplex step for step without the stall test, and a stop once the best
value stops improving with it."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jsve.fitting._simplex import StallingNelderMead

TARGET = jnp.array([0.3, -0.2, 0.1])


def smooth(z, args):
    return jnp.sum((z - TARGET) ** 2) + 0.1 * jnp.sum((z - TARGET) ** 4)


def plateau(z, args):
    """Piecewise constant, as the fit's hard objective is: steps of 0.01."""
    return jnp.floor(100 * jnp.sum((z - TARGET) ** 2)) / 100


def minimise(fn, solver, z0=None, max_steps=200):
    z0 = jnp.zeros(3) if z0 is None else z0
    return optx.minimise(fn, solver, z0, max_steps=max_steps, throw=False)


@pytest.mark.parametrize("fn", [smooth, plateau])
def test_without_the_stall_test_it_is_optimistix_nelder_mead(fn):
    plain = minimise(fn, optx.NelderMead(rtol=1e-4, atol=1e-4, rdelta=0.0, adelta=0.5))
    ours = minimise(fn, StallingNelderMead(rtol=1e-4, atol=1e-4, adelta=0.5, window=0))
    np.testing.assert_array_equal(np.asarray(ours.value), np.asarray(plain.value))
    assert int(ours.stats["num_steps"]) == int(plain.stats["num_steps"])
    assert not bool(ours.stats["stalled"])


def test_a_plateau_stops_at_a_checkpoint_with_the_same_value():
    plain = minimise(plateau, optx.NelderMead(rtol=1e-4, atol=1e-4, rdelta=0.0, adelta=0.5))
    assert int(plain.stats["num_steps"]) == 200  # optimistix's own test never holds on a plateau
    ours = minimise(plateau, StallingNelderMead(rtol=1e-4, atol=1e-4, adelta=0.5, window=25, ftol=1e-4))
    steps = int(ours.stats["num_steps"])
    assert bool(ours.stats["stalled"])
    assert steps < 200 and (steps - 1) % 25 == 0  # the initial simplex (step 1), then whole windows
    assert float(plateau(ours.value, None)) <= float(plateau(plain.value, None))


def test_a_first_window_without_progress_stops_the_run():
    """From the minimum of a plateau no move improves: the run stops after the initial simplex and one
    window, judged against the initial simplex's best (not after two windows)."""
    solver = StallingNelderMead(rtol=1e-4, atol=1e-4, adelta=0.01, window=10, ftol=1e-4)
    sol = minimise(plateau, solver, TARGET)
    assert bool(sol.stats["stalled"]) and int(sol.stats["num_steps"]) == 11


def test_a_run_that_keeps_improving_is_not_stopped():
    # Rosenbrock's curved valley takes hundreds of steps, each window of 10 improving by far more than
    # 1e-12 until the simplex reaches the minimum (1, 1) to float32's precision.
    def rosenbrock(z, args):
        return jnp.sum(100 * (z[1:] - z[:-1] ** 2) ** 2 + (1 - z[:-1]) ** 2)

    solver = StallingNelderMead(rtol=1e-8, atol=1e-8, adelta=0.5, window=10, ftol=1e-12)
    plain = optx.NelderMead(rtol=1e-8, atol=1e-8, rdelta=0.0, adelta=0.5)
    z0 = jnp.array([-1.0, 1.5])
    ours, ref = minimise(rosenbrock, solver, z0, 2000), minimise(rosenbrock, plain, z0, 2000)
    assert int(ours.stats["num_steps"]) > 100
    np.testing.assert_allclose(np.asarray(ours.value), [1.0, 1.0], atol=1e-3)
    np.testing.assert_allclose(np.asarray(ours.value), np.asarray(ref.value), atol=1e-3)


def test_a_coarse_tolerance_stops_earlier_than_a_fine_one():
    def steps(ftol):
        sol = minimise(smooth, StallingNelderMead(rtol=1e-10, atol=1e-10, adelta=0.5, window=10, ftol=ftol))
        return int(sol.stats["num_steps"]), float(smooth(sol.value, None))

    (coarse, f_coarse), (fine, f_fine) = steps(1e-2), steps(1e-9)
    assert coarse < fine
    assert f_fine <= f_coarse


def test_under_jit_and_vmap_it_equals_a_loop():
    solver = StallingNelderMead(rtol=1e-4, atol=1e-4, adelta=0.5, window=25, ftol=1e-4)
    starts = jnp.array([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5], [-0.5, 0.2, 0.9]])

    def solve(z0):
        sol = optx.minimise(plateau, solver, z0, max_steps=200, throw=False)
        return sol.value, sol.stats["num_steps"]

    values, steps = jax.jit(jax.vmap(solve))(starts)
    for i, z0 in enumerate(starts):
        value, n = solve(z0)
        np.testing.assert_allclose(np.asarray(values[i]), np.asarray(value), rtol=1e-6, atol=1e-7)
        assert int(steps[i]) == int(n)


@pytest.mark.parametrize(("field", "bad"), [("nm_window", -1), ("nm_window", 2.5), ("nm_ftol", -1e-3)])
def test_a_wrong_stall_test_is_refused(field, bad):
    from jsve.fitting import FitConfig

    with pytest.raises(ValueError, match=field):
        FitConfig(**{field: bad})


def test_the_fit_records_the_steps_of_a_stalled_polish():
    """A fit with the stall test stops its Nelder-Mead runs at a multiple of the window, never later than
    without it, and reaches an objective no worse than its search's best."""
    from jsve.fitting import FitConfig, FitData, fit, sve_space
    from jsve.sim import simulate_study

    data = FitData.from_runs(simulate_study(procedural=1, disturbances="blur=0,30,50", runs=2))
    config = dict(n_search=32, n_starts=1, nm_steps=60, polish_runs=0)
    stalled = fit(data, sve_space(), config=FitConfig(nm_window=10, **config), progress=False)
    full = fit(data, sve_space(), config=FitConfig(nm_window=0, **config), progress=False)
    (a,) = [s for s in stalled.stages if s["stage"].startswith("nelder_mead")]
    (b,) = [s for s in full.stages if s["stage"].startswith("nelder_mead")]
    assert (a["steps"] - 1) % 10 == 0 or a["steps"] == 60
    assert a["steps"] <= b["steps"] == 60
    assert stalled.objective <= stalled.stages[0]["objective"] + 1e-9
