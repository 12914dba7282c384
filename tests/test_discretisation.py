"""`check_discretisation`: a fit of a `Model.from_ode` model refitted with finer steps."""

import functools
import warnings

import numpy as np
import pytest

import oneshot_jax as oj

A, DT, T, NOISE = 12.0, 0.1, 400, 0.01


def lag(x, u, p):
    return p["a"] * (p["g"] * u - x)


def _record(t):
    """The lag's exact samples (the ODE's solution, u held over each interval) at times t,
    with noise."""
    rng = np.random.default_rng(0)
    u = np.sign(np.sin(0.3 * np.arange(t.size)))[:, None] + 0.3 * rng.standard_normal((t.size, 1))
    x = np.zeros(t.size)
    for k in range(t.size - 1):
        decay = np.exp(-A * (t[k + 1] - t[k]))
        x[k + 1] = decay * x[k] + (1 - decay) * u[k, 0]
    return u, x[:, None] + NOISE * rng.standard_normal((t.size, 1))


U, Z = _record(DT * np.arange(T))
THETA0 = {"a": 10.0, "g": 1.0}


@functools.cache
def _fit(substeps):
    """The lag (gain g held at its truth) fitted with `substeps` RK4 steps a sample."""
    model = oj.Model.from_ode(lag, DT, substeps=substeps)
    return oj.fit(model, THETA0, np.zeros(1), U, Z, fixed=["g"])


def test_a_fit_biased_by_its_step_is_refitted_with_finer_steps_and_warns():
    """One RK4 step a sample at |lambda| h = 1.29 (inside the accurate range: no stability
    warning) puts a at 12.89 from the ODE's own samples (a = 12); the check's refit is the
    fit of the model with two substeps, its refit at one step stays at the converged
    estimate, the move is measured in that refit's standard error, and the held gain
    stays held (no move to measure)."""
    coarse = _fit(1)
    assert coarse.success
    assert not oj.check_stability(coarse.model, coarse.theta, coarse.x0, U).inaccurate
    with pytest.warns(RuntimeWarning, match=r"a moves by 2\d\.\d standard errors"):
        check = oj.check_discretisation(coarse, U, Z)
    fine = _fit(2)
    assert check.depends and check.name == "a" and check.factor == 2
    assert check.refit.success
    np.testing.assert_allclose(check.refit.theta["a"], fine.theta["a"], rtol=1e-9)
    assert check.refit.theta["g"] == 1.0 and np.isnan(check.shift["g"])
    np.testing.assert_allclose(check.coarse.theta["a"], coarse.theta["a"], rtol=1e-9)
    expected = (fine.theta["a"] - check.coarse.theta["a"]) / check.coarse.std["a"]
    np.testing.assert_allclose(check.shift["a"], expected, rtol=1e-6)
    assert expected < -20 and check.largest == pytest.approx(-expected)
    assert "depend on the integrator's step" in str(check)


def test_a_fit_whose_step_is_fine_enough_passes_in_silence():
    """Four substeps (|lambda| h = 0.3): the refit with eight moves a by 0.05 standard
    errors; nothing warns. Its refit stopped after one step is no all-clear."""
    fit4 = _fit(4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check = oj.check_discretisation(fit4, U, Z)
    assert not check.depends and check.largest < 0.1 and check.refit.success
    assert "do not depend on the step" in str(check)
    with pytest.warns(RuntimeWarning, match="inconclusive"):
        stopped = oj.check_discretisation(fit4, U, Z, solver=oj.LevenbergMarquardt(max_steps=1))
    assert not stopped.depends and not stopped.refit.success
    assert "inconclusive" in str(stopped)


def test_a_time_stamped_model_is_refitted_with_each_intervals_steps_split():
    """A model of time-stamped records with `max_step` 0.25 over intervals of 0.05 to
    0.15: one step an interval, and as many with `max_step` halved (0.125); the refit
    takes two steps on every interval, the model of two substeps without `max_step`."""
    rng = np.random.default_rng(1)
    t = np.cumsum(np.r_[0.0, rng.uniform(0.05, 0.15, T - 1)])
    u, z = _record(t)
    timed = oj.Model.from_ode(lag, None, max_step=0.25, substeps=2)
    result = oj.fit(timed, THETA0, np.zeros(1), u, z, t=t, fixed=["g"])
    with pytest.warns(RuntimeWarning, match="depend on the integrator's step"):
        check = oj.check_discretisation(result, u, z, t=t)
    finer = oj.Model.from_ode(lag, None, substeps=2)
    direct = oj.fit(finer, THETA0, np.zeros(1), u, z, t=t, fixed=["g"])
    np.testing.assert_allclose(check.refit.theta["a"], direct.theta["a"], rtol=1e-9)
    assert check.depends and check.coarse.success


def test_an_unfinished_fit_is_measured_against_its_own_refit():
    """A fit stopped after two steps (at a = 11.1 where the optimum is at 12.05), with
    a step fine enough (four substeps): the move to the finer refit is measured from the
    refit at the fit's own step, which goes on to the optimum, so the rest of the
    optimisation is not blamed on the step; the held x0 stays held in both refits."""
    model = oj.Model.from_ode(lag, DT, substeps=4)
    solver = oj.LevenbergMarquardt(max_steps=2)
    start = {"a": 5.0, "g": 1.0}
    stopped = oj.fit(model, start, np.zeros(1), U, Z, fixed=["g"], estimate_x0=False, solver=solver)
    assert not stopped.success
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check = oj.check_discretisation(stopped, U, Z)
    assert check.coarse.success and not check.depends and check.largest < 0.1
    optimum = oj.fit(model, start, np.zeros(1), U, Z, fixed=["g"], estimate_x0=False)
    np.testing.assert_allclose(check.coarse.theta["a"], optimum.theta["a"], rtol=1e-8)
    assert abs(stopped.theta["a"] - optimum.theta["a"]) > 10 * optimum.std["a"]
    assert check.refit.x0 == 0.0 and check.coarse.x0 == 0.0


def test_check_discretisation_refuses_what_it_cannot_check():
    coarse = _fit(1)
    with pytest.raises(TypeError, match="`result` must be a FitResult"):
        oj.check_discretisation(coarse.theta, U, Z)
    with pytest.raises(ValueError, match="integer >= 2"):
        oj.check_discretisation(coarse, U, Z, factor=1)
    with pytest.raises(TypeError, match="integer >= 2"):
        oj.check_discretisation(coarse, U, Z, factor=2.5)
    with pytest.raises(ValueError, match="`margin` must be a non-negative number"):
        oj.check_discretisation(coarse, U, Z, margin=-1.0)
    with pytest.raises(TypeError, match="`margin` must be a non-negative number"):
        oj.check_discretisation(coarse, U, Z, margin=True)
    with pytest.raises(ValueError, match="`multistart` is not a keyword"):
        oj.check_discretisation(coarse, U, Z, multistart=True)
    with pytest.raises(TypeError, match="unexpected keyword arguments \\['substep'\\]"):
        oj.check_discretisation(coarse, U, Z, substep=2)
    with pytest.raises(ValueError, match="the record the result was fitted on"):
        oj.check_discretisation(coarse, U[::-1], Z[::-1])
    with pytest.raises(ValueError, match=r"same records and samples.*u \(100, 1\), z \(400, 1\)"):
        oj.check_discretisation(coarse, U[:100], Z)
    windowed = oj.fit(_fit(4).model, THETA0, np.zeros((8, 1)), U, Z, window=50, fixed=["g"])
    with pytest.raises(ValueError, match="pass `window=`"):
        oj.check_discretisation(windowed, U, Z)
    discrete = oj.Model(lambda x, u, p: 0.3 * x + p["b"] * u, lambda x, u, p: x)
    result = oj.fit(discrete, {"b": 0.5}, np.zeros(1), U[:50], Z[:50])
    with pytest.raises(ValueError, match="`Model.from_ode` model"):
        oj.check_discretisation(result, U[:50], Z[:50])


def test_fixed_entries_of_a_theta_that_is_no_dict_are_named_as_not_carried():
    """A theta of one array with an entry held: `fixed` cannot be said per key, so the
    check warns that the refits free it, and holds it where `fixed` is passed again."""
    model = oj.Model.from_ode(lambda x, u, p: p[0] * (p[1] * u - x), DT, substeps=4)
    result = oj.fit(model, np.array([10.0, 1.0]), np.zeros(1), U, Z, fixed=np.array([False, True]))
    with pytest.warns(UserWarning, match="cannot carry the result's fixed entries to its refits"):
        freed = oj.check_discretisation(result, U, Z)
    assert freed.refit.theta[1] != 1.0 and np.isfinite(freed.shift[1])
    held = oj.check_discretisation(result, U, Z, fixed=np.array([False, True]))
    assert held.refit.theta[1] == 1.0 and np.isnan(held.shift[1]) and not held.depends
