"""Parameters with an exactly zero gradient at the start: the stop reason `zero_gradient`.

Two tanks with a coupling k12 * g between them. Started with k12 = g = 0, neither has any
effect on the outputs (each multiplies the other), so no solver moves them: the fit says
so, naming them, and does not report success. An ordinary start, and a start where one
of them has a zero gradient only at the start (g, while k12 = 0 moves first), do not
warn; nor does a parameter that acts nowhere on the data (d), whose gradient is zero
everywhere: the covariance reports it as not identifiable.
"""

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax import internal

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


@functools.cache  # one model function per sign: the fits of a test share their compile
def _relu_model(sign):
    def rhs(x, u, p):
        return jnp.stack([-p["a"] * x[0] + jax.nn.relu(sign * p["k"]) * u[0]])

    return oj.Model.from_ode(rhs, 0.05)


def _relu_data(sign):
    k = np.arange(200)
    u = (np.sin(0.3 * k) + 0.5 * np.sin(1.1 * k))[:, None]
    _, z = oj.simulate(_relu_model(sign), {"a": 1.0, "k": sign * 0.5}, np.zeros(1), u)
    return u, np.asarray(z) + 1e-3 * np.random.default_rng(0).standard_normal(np.shape(z))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_parameter_that_acts_on_one_side_of_its_start_is_reported(sign):
    """relu(-k) u started at k = 0 acts only below the start: the check moved k upwards
    only, and the fit reported statistically_converged (success) at a loss 3800 times that
    of a refit from k = -0.1. Moved both ways, it is zero_gradient as relu(+k) is; within
    a box that allows only the side where it does not act, it is not flagged."""
    u, z = _relu_data(sign)
    with pytest.warns(RuntimeWarning, match=r"theta\['k'\] never moved"):
        r = oj.fit(_relu_model(sign), {"a": 0.5, "k": 0.0}, np.zeros(1), u, z)
    assert r.status == "zero_gradient" and not r.success
    away = oj.fit(_relu_model(sign), {**r.theta, "k": sign * 0.1}, r.x0, u, z)
    assert away.success and float(away.loss) < 1e-3 * float(r.loss)
    box = oj.constraints.box(**({"upper": {"k": 0.0}} if sign > 0 else {"lower": {"k": 0.0}}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        held = oj.fit(_relu_model(sign), {"a": 0.5, "k": 0.0}, np.zeros(1), u, z, constraints=box)
    assert held.status != "zero_gradient"


def test_each_start_of_a_multistart_that_stays_at_a_zero_gradient_is_reported():
    """A multistart listed a start left at k1 = k2 = 0 (a product with a zero gradient
    there) as statistically_converged, a success, where a fit from it alone says
    zero_gradient; with every start there, the status line said zero_gradient and the
    starts' line 'statistically_converged 2'."""

    def rhs(x, u, p):
        return jnp.stack([-p["a"] * x[0] + p["k1"] * p["k2"] * u[0]])

    model = oj.Model.from_ode(rhs, 0.05)
    k = np.arange(200)
    u = (np.sin(0.3 * k) + 0.5 * np.sin(1.1 * k))[:, None]
    _, z = oj.simulate(model, {"a": 1.0, "k1": 1.0, "k2": 2.0}, np.zeros(1), u)
    z = np.asarray(z) + 1e-3 * np.random.default_rng(0).standard_normal(np.shape(z))
    theta0 = {"a": 0.5, "k1": 0.0, "k2": 0.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        both = oj.fit(
            model, theta0, np.zeros(1), u, z, multistart={"k1": [0.0, 1.0], "k2": [0.0, 1.0]}
        )
        stuck = oj.fit(model, theta0, np.zeros(1), u, z, multistart={"a": [0.5, 2.0]})
    assert both.success and both.starts.stop_reason[0] == "zero_gradient"
    assert both.starts.stop_reason[1] != "zero_gradient"
    assert stuck.status == "zero_gradient"
    assert stuck.starts.stop_reason == ("zero_gradient", "zero_gradient")
    assert "stops: zero_gradient 2" in str(stuck)


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "lbfgs"])
@pytest.mark.parametrize("constrained", [False, True])
def test_outputs_independent_of_every_variable_are_stationary(solver, constrained):
    """Every Jacobian column exactly zero (an `observe` that ignores x and theta): the
    first-order measure is 0 (not 0 / 0 = NaN, which no test passed: "stalled")."""
    u = np.random.default_rng(0).standard_normal((40, 1))
    model = oj.Model(lambda x, u, th: 0.9 * x + th["k"] * u, lambda x, u, th: 2.0 * u)
    constraints = oj.constraints.positive() if constrained else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(
            model,
            {"k": 0.3},
            np.zeros(1),
            u,
            2.0 * u + 0.01,
            solver=solver,
            constraints=constraints,
        )
    assert r.stop_info["first_order"] == 0.0
    assert r.success


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "lbfgs"])
def test_outputs_piecewise_constant_in_every_variable_are_no_success(solver):
    """A quantised sensor (`observe` rounds to 0.01): every gradient is exactly zero
    everywhere, yet the outputs change with theta and x0 (in steps). The fit cannot move
    from its start, far from the truth (a loss of 0 there), and must not call that a
    success, unlike outputs that depend on nothing (above), whose loss is the same
    everywhere."""
    dt = 0.1

    def step(x, u, th):
        return jnp.stack([x[0] + dt * x[1], x[1] + dt * (u[0] - th["c"] * x[1] - th["k"] * x[0])])

    model = oj.Model(step, lambda x, u, th: jnp.round(100 * x[:1]) / 100)
    u = np.random.default_rng(0).standard_normal((200, 1))
    x0 = np.array([1.0, 0.0])
    _, z = oj.simulate(model, {"c": 0.4, "k": 2.0}, x0, u)
    with pytest.warns(RuntimeWarning, match="piecewise-constant outputs"):
        r = oj.fit(model, {"c": 0.6, "k": 1.5}, x0, u, np.asarray(z), solver=solver)
    assert not r.success and r.status == "zero_gradient"
    assert r.stop_info["no_effect"] and r.stop_info["solver_stop"] == "converged"
    assert r.stop_info["zero_gradient"] == ["theta['c']", "theta['k']"]
    assert r.loss > 0.01
    assert oj.loss(model, {"c": 0.4, "k": 2.0}, x0, u, np.asarray(z)) == 0.0


def test_a_start_on_a_flat_piece_of_the_model_is_named():
    """A saturation level started above every input (clip(u, -s, s) from s = 50, the
    inputs within +-4): s's column is zero at the start and a little away, the fit left it
    there and said `converged` at a loss hundreds of times the optimum's, with nothing
    but "not identifiable" about s. It acts at s = 0.5 (the start times 0.01): the success
    names it in `stop_info["without_effect"]` and warns where it acts; a refit from there
    reaches the optimum. (A parameter that acts nowhere tried, `d` of
    `test_no_report_for_ordinary_fits`, is not named.)"""

    def step(x, u, th):
        return jnp.array([0.8 * x[0] + th["b"] * jnp.clip(u[0], -th["s"], th["s"])])

    model = oj.Model(step)
    rng = np.random.default_rng(8)
    u = np.clip(2.0 * rng.standard_normal((200, 1)), -4.0, 4.0)
    truth = {"b": 1.0, "s": 1.5}
    _, z = oj.simulate(model, truth, np.zeros(1), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    with pytest.warns(RuntimeWarning, match=r"theta\['s'\] \(acts at 0\.5\) never moved"):
        r = oj.fit(model, {"b": 0.5, "s": 50.0}, np.zeros(1), u, z)
    assert r.success and float(r.theta["s"]) == 50.0
    assert r.stop_info["without_effect"] == ["theta['s']"]
    assert "though they do elsewhere" in str(r) and "start them where they act" in r.message
    again = oj.fit(model, {**r.theta, "s": 0.5}, r.x0, u, z)
    assert again.success and float(again.loss) < 1e-2 * float(r.loss)
    assert float(again.theta["s"]) == pytest.approx(1.5, rel=1e-2)


def test_the_checks_in_parts_find_what_one_part_finds(data, monkeypatch):
    """The columns of many unmoved entries are evaluated in parts of bounded memory (a
    network's dead units, 991 entries of a record of 1000 samples, asked for 4.8 GB after
    the solve had finished, and the fit was lost). Every part moves all the entries
    checked, so a coupling of two entries in different parts (k12 * g, both from 0; with
    one entry per part) is still found."""
    monkeypatch.setattr(internal.zero_gradient_checks, "_COLUMN_ENTRIES", 1)
    theta0 = {"a": 0.3, "k12": 0.0, "g": 0.0, "d": 0.1}
    with pytest.warns(RuntimeWarning, match=r"theta\['g'\], theta\['k12'\] never moved"):
        r = _fit(data, theta0)
    assert r.status == "zero_gradient"
    assert r.stop_info["zero_gradient"] == ["theta['g']", "theta['k12']"]
