"""A least-squares step that linearises at its trial point (few Jacobian columns: the
loss is the linearisation's C, an accepted full step keeps it) takes the iterates of the
step that simulates the trial and linearises where it ends (`TRIAL_COLUMNS = 0`).

The cases have rejected steps (LM from a far start), shortened steps (Gauss-Newton's
backtracking) and steps at an active bound (the projected-gradient fallback), where
keeping the trial's linearisation would be wrong: the two ways would then part."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.internal import Params, least_squares_module

DT, T = 0.05, 200


def rhs(x, u, th):
    return jnp.array([x[1], -th["k"] * jnp.sin(x[0]) - th["c"] * x[1] + th["b"] * u[0]])


def data():
    model = oj.Model.from_ode(rhs, DT, observe=lambda x, u, th: x[:1])
    t = np.arange(T) * DT
    u = (np.sin(0.7 * t) + 0.5 * np.sin(2.3 * t))[:, None]
    truth = {"k": 9.0, "c": 0.4, "b": 2.0}
    z = np.asarray(oj.simulate(model, truth, np.array([0.3, 0.0]), u)[1])
    z = z + 0.01 * np.random.default_rng(0).standard_normal(z.shape)
    return model, u, z


CASES = {
    "lm_far_start": dict(solver=oj.LevenbergMarquardt(), theta0={"k": 3.0, "c": 2.0, "b": 0.5}),
    "gn_far_start": dict(solver=oj.GaussNewton(), theta0={"k": 5.0, "c": 1.5, "b": 1.0}),
    "lm_active_bound": dict(
        solver=oj.LevenbergMarquardt(),
        theta0={"k": 6.0, "c": 1.0, "b": 1.0},
        constraints=oj.constraints.box(upper={"c": 0.2}),
    ),
    "gn_active_bound": dict(
        solver=oj.GaussNewton(),
        theta0={"k": 6.0, "c": 1.0, "b": 1.0},
        constraints=oj.constraints.box(upper={"c": 0.2}),
    ),
}


@pytest.mark.default_optimisation  # (two programs, equal to the bit: conftest.py)
@pytest.mark.parametrize("case", sorted(CASES))
def test_trial_linearisation_takes_the_same_iterates(case, monkeypatch):
    model, u, z = data()
    kw = dict(CASES[case])
    theta0 = kw.pop("theta0")
    x0 = np.array([0.3, 0.0])
    fast = oj.fit(model, theta0, x0, u, z, **kw)
    monkeypatch.setattr(least_squares_module, "TRIAL_COLUMNS", 0)
    jax.clear_caches()  # (the compiled solve of these shapes is traced anew)
    plain = oj.fit(model, theta0, x0, u, z, **kw)
    jax.clear_caches()
    assert fast.num_steps == plain.num_steps and fast.stop_reason == plain.stop_reason
    np.testing.assert_allclose(fast.history.loss, plain.history.loss, rtol=1e-10)
    for k in theta0:
        np.testing.assert_allclose(fast.history.theta[k], plain.history.theta[k], rtol=1e-9)
        np.testing.assert_allclose(fast.theta[k], plain.theta[k], rtol=1e-10)
    np.testing.assert_allclose(fast.std["k"], plain.std["k"], rtol=1e-8)
    assert fast.success
    if "bound" in case:
        assert float(fast.theta["c"]) == 0.2  # the bound is active at the solution
    if case == "lm_far_start":
        # Its rejected steps are each followed by the projected-gradient step, which ends
        # elsewhere than the step's trial point (the second linearisation of a step): the
        # iterate moves at every row.
        k = fast.history.theta["k"][:-1]  # (the last row repeats the final iterate)
        assert np.all(np.diff(k) != 0)


def test_the_trial_is_linearised_for_few_columns_only():
    solver = oj.LevenbergMarquardt()
    limit = least_squares_module.TRIAL_COLUMNS

    def params(p, m):
        return Params(jnp.zeros(p), jnp.zeros((4, m)))

    # (a problem's shapes: 4 records of 50 samples, one output, two states)
    problem = types.SimpleNamespace(
        z=np.zeros((4, 50, 1)), x0_base=np.zeros((4, 2)), dtype=np.dtype(np.float64)
    )
    assert solver._linearises_trials(problem, params(limit - 2, 2))
    assert not solver._linearises_trials(problem, params(limit - 1, 2))
    cg = oj.LevenbergMarquardt(linear_solver="cg")
    assert not cg._linearises_trials(problem, params(3, 2))
