"""Parameters with an exactly zero gradient at the start: the stop reason `zero_gradient`.

Two tanks with a coupling k12 * g between them. Started with k12 = g = 0, neither has any
effect on the outputs (each multiplies the other), so no solver moves them: the fit says
so, naming them, and does not report success. An ordinary start, and a start where one
of them has a zero gradient only at the start (g, while k12 = 0 moves first), do not
warn; nor does a parameter that acts nowhere on the data (d), whose gradient is zero
everywhere: the covariance reports it as not identifiable.
"""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

T = 60
TRUTH = {"a": 0.5, "k12": 1.0, "g": 0.8, "d": 0.0}


def step(x, u, theta):
    # d multiplies an overflow the levels never reach: it acts nowhere on these data (not
    # identifiable, which the covariance reports), not only at the start.
    flow = theta["k12"] * theta["g"] * (x[0] - x[1]) + theta["d"] * jnp.maximum(x[0] - 100, 0)
    dx = jnp.stack([-theta["a"] * x[0] + u[0] - flow, -theta["a"] * x[1] + flow])
    return x + 0.1 * dx


MODEL = oj.Model(step)


@pytest.fixture(scope="module")
def data():
    u = np.random.default_rng(0).normal(size=(T, 1))
    x0 = np.zeros(2)
    _, z = oj.simulate(MODEL, TRUTH, x0, u)
    return x0, u, np.asarray(z)


def _fit(data, theta0, **kw):
    x0, u, z = data
    return oj.fit(MODEL, theta0, x0, u, z, estimate_x0=False, **kw)


def test_a_coupling_started_at_zero_is_reported(data, tmp_path):
    theta0 = {"a": 0.3, "k12": 0.0, "g": 0.0, "d": 0.1}
    with pytest.warns(RuntimeWarning, match=r"theta\['g'\], theta\['k12'\] never moved") as rec:
        r = _fit(data, theta0)
    (message,) = [str(w.message) for w in rec if "never moved" in str(w.message)]
    assert "theta['a']" not in message and "theta['d']" not in message
    assert "coupling" in message and "Start them away" in message and "fix them" in message
    assert r.status == "zero_gradient" and not r.success
    assert r.theta["k12"] == 0.0 and r.theta["g"] == 0.0  # returned as they started
    assert r.theta["a"] != 0.3  # the other parameter was estimated
    assert r.stop_info["zero_gradient"] == ["theta['g']", "theta['k12']"]
    assert r.stop_info["solver_stop"] in (
        "converged",
        "statistically_converged",
        "stalled",
        "no_progress",
    )
    report = str(r)
    assert "status: zero_gradient (theta['g'], theta['k12'] never moved" in report
    assert "theta['g'], theta['k12']" in r.message and "Start them away" in r.message
    # The stop survives saving.
    r.save(tmp_path / "r.npz")
    assert oj.load_result(tmp_path / "r.npz").status == "zero_gradient"


@pytest.mark.parametrize(
    "theta0",
    [
        {"a": 0.3, "k12": 0.5, "g": 0.5, "d": 0.1},  # an ordinary start
        {"a": 0.3, "k12": 0.0, "g": 0.5, "d": 0.1},  # g's gradient is zero only at the start
    ],
)
def test_no_report_for_ordinary_fits(data, theta0):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.warns(UserWarning, match=r"rank-deficient.*\['d'"):
            r = _fit(data, theta0)
    assert r.success and r.status != "zero_gradient" and "zero_gradient" not in r.stop_info
    np.testing.assert_allclose(r.theta["a"], TRUTH["a"], rtol=1e-8)
    np.testing.assert_allclose(r.theta["k12"] * r.theta["g"], 0.8, rtol=1e-8)
