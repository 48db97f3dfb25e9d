"""lockstep_nelder_mead: optimistix's Nelder-Mead step for step (with its bookkeeping), the textbook method
without it (scipy's minimum), many runs moved together as each alone, and the stall test."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
import scipy.optimize

from jsve.fitting._simplex import lockstep_nelder_mead

TARGET = jnp.array([0.3, -0.2, 0.1])


def smooth(z):
    return jnp.sum((z - TARGET) ** 2) + 0.1 * jnp.sum((z - TARGET) ** 4)


def plateau(z):
    """Piecewise constant, as the fit's hard objective is: steps of 0.01."""
    return jnp.floor(100 * jnp.sum((z - TARGET) ** 2)) / 100


def rosenbrock(z):
    return jnp.sum(100 * (z[1:] - z[:-1] ** 2) ** 2 + (1 - z[:-1]) ** 2)


def scored(fn):
    """The objective lockstep_nelder_mead calls: a batch of points (owners unused)."""
    return lambda points, owners: np.asarray(jax.vmap(fn)(jnp.asarray(points)))


def lockstep(fn, z0, **kw):
    kw = {"adelta": 0.5, "rtol": 1e-4, "atol": 1e-4, "window": 0, **kw}
    return lockstep_nelder_mead(scored(fn), np.atleast_2d(np.asarray(z0, np.float32)), **kw)


def kink(z):
    """Not smooth, and without plateaus (no ties between vertices)."""
    return jnp.sum(jnp.abs(z - TARGET) * jnp.array([1.0, 2.0, 3.0]))


@pytest.mark.parametrize("fn", [smooth, kink])
@pytest.mark.parametrize("max_steps", [1, 2, 3, 5, 10, 30, 200])
def test_with_optimistix_bookkeeping_it_is_optimistix_nelder_mead(fn, max_steps):
    """optimistix.NelderMead on y as a tuple of scalars (the one form for which its initial simplex is
    z0 + adelta e_i) against the lockstep driver keeping its stale best and worst vertices: the same
    steps and the same iterate, on objectives without ties (between equal values the two pick another
    worst vertex: jsve.fitting._simplex). Tolerance: float32 rounding of the same operations, compiled
    by XLA on one side and run by numpy on the other (1e-7 measured after 200 steps)."""
    solver = optx.NelderMead(rtol=1e-4, atol=1e-4, rdelta=0.0, adelta=0.5)
    y0 = tuple(jnp.zeros(()) for _ in range(3))
    ref = optx.minimise(lambda y, args: fn(jnp.stack(y)), solver, y0, max_steps=max_steps, throw=False)
    ours = lockstep(fn, np.zeros(3), max_steps=max_steps, previous_simplex_vertices=True)
    assert int(ours.steps[0]) == int(ref.stats["num_steps"])
    np.testing.assert_allclose(ours.z[0], np.stack(ref.value), rtol=1e-5, atol=1e-6)


def test_it_finds_the_minimum_where_optimistix_stops_short():
    """Without optimistix's defects the simplex reaches the bowl's minimum; optimistix on a vector y
    (its initial simplex degenerate) ends in the plane z_1 = z_2 through the start."""
    ours = lockstep(smooth, np.zeros(3), rtol=1e-6, atol=1e-6, max_steps=500)
    assert float(smooth(jnp.asarray(ours.z[0]))) < 1e-8
    np.testing.assert_allclose(ours.z[0], TARGET, atol=1e-3)
    assert ours.value[0] == pytest.approx(float(smooth(jnp.asarray(ours.z[0]))), rel=1e-6)
    solver = optx.NelderMead(rtol=1e-6, atol=1e-6, rdelta=0.0, adelta=0.5)
    theirs = optx.minimise(lambda y, args: smooth(y), solver, jnp.zeros(3), max_steps=500, throw=False)
    assert float(theirs.value[1]) == pytest.approx(float(theirs.value[2]), abs=1e-6)
    assert float(smooth(theirs.value)) > 1e-3


def test_rosenbrock_reaches_scipys_minimum():
    """scipy's Nelder-Mead (another implementation, other constants) as the oracle of where the method
    ends on Rosenbrock's curved valley from the classic start: (1, 1). The valley takes over a hundred
    steps that the stall test (windows of 10 improving by more than 1e-12) must not cut short; it stops
    the run only at float32's resolution of the valley floor."""
    z0 = np.array([-1.2, 1.0])
    ref = scipy.optimize.minimize(lambda z: float(rosenbrock(jnp.asarray(z))), z0, method="Nelder-Mead",
                                  options={"xatol": 1e-8, "fatol": 1e-10, "maxiter": 5000})  # fmt: skip
    ours = lockstep(rosenbrock, z0, rtol=1e-7, atol=1e-7, window=10, ftol=1e-12, max_steps=3000)
    assert ours.steps[0] > 100
    np.testing.assert_allclose(ref.x, [1.0, 1.0], atol=1e-4)
    np.testing.assert_allclose(ours.z[0], ref.x, atol=2e-3)  # float32 iterates: the valley floor's width


def test_runs_in_lockstep_equal_each_run_alone():
    """Five starts on two objectives at once (the owner picks each point's objective) end exactly where
    each ends alone, after as many steps: lockstep only batches the calls."""
    starts = np.array([[0, 0, 0], [1, -1, 0.5], [-0.5, 0.2, 0.9], [2, 2, -2], [0.3, -0.2, 0.1]], np.float32)
    owner_fn = [smooth, plateau, smooth, plateau, plateau]

    def objective(points, owners):
        return np.array([float(owner_fn[o](jnp.asarray(p))) for p, o in zip(points, owners, strict=True)])

    finished = []
    kw = {"adelta": 0.5, "rtol": 1e-4, "atol": 1e-4, "window": 25, "ftol": 1e-4, "max_steps": 200}
    together = lockstep_nelder_mead(objective, starts, on_finish=finished.append, **kw)
    assert sorted(finished) == list(range(5))
    for i, z0 in enumerate(starts):
        alone = lockstep_nelder_mead(scored(owner_fn[i]), z0[None], **kw)
        np.testing.assert_array_equal(together.z[i], alone.z[0])
        assert together.steps[i] == alone.steps[0] and together.stalled[i] == alone.stalled[0]
    assert len(set(together.steps.tolist())) > 1  # the runs ended at different steps


def test_on_a_plateau_the_simplex_travels():
    """All vertices equal: the oldest is reflected each step, so the simplex rolls across the plateau,
    each step to a new point, instead of reflecting its newest vertex back and forth between two points
    (optimistix's first-index rule)."""
    seen = []

    def flat(points, owners):
        seen.extend(map(tuple, np.round(points, 5)))
        return np.zeros(len(points))

    start = np.zeros((1, 3), np.float32)
    ours = lockstep_nelder_mead(flat, start, adelta=0.5, rtol=1e-4, atol=1e-4, window=0, max_steps=40)
    assert ours.steps[0] == 40
    assert len(set(seen)) == len(seen) == 4 + 39  # the initial simplex, then one new point a step
    assert np.abs(np.asarray(seen)).max() > 2.0  # it travelled, by several simplex sizes


def test_a_plateau_stops_at_a_checkpoint():
    plain = lockstep(plateau, np.zeros(3), max_steps=200)
    assert plain.steps[0] == 200  # the convergence test never holds on a plateau
    ours = lockstep(plateau, np.zeros(3), window=25, ftol=1e-4, max_steps=200)
    assert ours.stalled[0] and ours.steps[0] < 200 and (ours.steps[0] - 1) % 25 == 0
    assert float(plateau(jnp.asarray(ours.z[0]))) <= float(plateau(jnp.asarray(plain.z[0])))


def test_a_first_window_without_progress_stops_the_run():
    """From the minimum of a plateau no move improves: the run stops after the initial simplex and one
    window, judged against the initial simplex's best (not after two windows)."""
    ours = lockstep(plateau, np.asarray(TARGET), adelta=0.01, window=10, ftol=1e-4)
    assert ours.stalled[0] and ours.steps[0] == 11


def test_a_coarse_tolerance_stops_earlier_than_a_fine_one():
    def run(ftol):
        ours = lockstep(smooth, np.zeros(3), rtol=1e-10, atol=1e-10, window=10, ftol=ftol, max_steps=400)
        return int(ours.steps[0]), float(ours.value[0])

    (coarse, f_coarse), (fine, f_fine) = run(1e-2), run(1e-9)
    assert coarse < fine
    assert f_fine <= f_coarse


@pytest.mark.parametrize(("field", "bad"), [("nm_window", -1), ("nm_window", 2.5), ("nm_ftol", -1e-3)])
def test_a_wrong_stall_test_is_refused(field, bad):
    from jsve.fitting import FitConfig

    with pytest.raises(ValueError, match=field):
        FitConfig(**{field: bad})


def test_the_fit_records_the_steps_of_a_stalled_polish():
    """A fit with the stall test stops its Nelder-Mead runs at a checkpoint, never later than without it,
    and reaches an objective no worse than its search's best."""
    from jsve.fitting import FitConfig, FitData, fit, sve_space
    from jsve.sim import FlightProfile, SimConfig, simulate_study

    flights = SimConfig(flight=FlightProfile(duration_s=(40.0, 40.0)))  # 800 frames a run
    runs = simulate_study(procedural=1, disturbances="blur=0,30,50", runs=2, config=flights)
    data = FitData.from_runs(runs)
    steps = 30  # the stall test's checkpoints 11 and 21 come before the limit
    config = dict(n_search=32, n_starts=1, nm_steps=steps, polish_runs=0)
    stalled = fit(data, sve_space(), config=FitConfig(nm_window=10, **config), progress=False)
    full = fit(data, sve_space(), config=FitConfig(nm_window=0, **config), progress=False)
    (a,) = [s for s in stalled.stages if s["stage"].startswith("nelder_mead")]
    (b,) = [s for s in full.stages if s["stage"].startswith("nelder_mead")]
    assert (a["steps"] - 1) % 10 == 0 or a["steps"] == steps
    assert a["steps"] <= b["steps"]
    assert stalled.objective <= stalled.stages[0]["objective"] + 1e-9
