"""A first `fit` and a first `predict` each compile one program (issue 19): the stability
check of a `Model.from_ode` fit and predict's observability check and simulation run
inside those calls, with the numbers of the separate functions."""

import logging
import os
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.internal import jit_module

DT, T = 0.05, 60


def cubic(x, u, p):
    # A state-dependent Jacobian (-3 a x0^2): the stability value depends on which states
    # are checked.
    return jnp.array([-p["a"] * x[0] ** 3 + x[1], -p["b"] * x[1] + u[0]])


def _data(model, theta, x0, n_traj=1, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1.0, 1.0, (n_traj, T, 1))
    X0 = np.broadcast_to(x0, (n_traj, 2))
    _, z = oj.simulate(model, theta, X0, u)
    return X0, u, np.asarray(z)


class _Compiles:
    """Counts XLA compilations (jax.monitoring) while active."""

    def __init__(self):
        self.n, self.on = 0, False
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, seconds, **kwargs):
        if self.on and event == "/jax/core/compile/backend_compile_duration":
            self.n += 1

    def count(self, fn):
        self.n, self.on = 0, True
        try:
            out = fn()
        finally:
            self.on = False
        return out, self.n


COMPILES = _Compiles()


def _stability_warning(fn):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn()
    found = [str(w.message) for w in caught if "stability limit" in str(w.message)]
    return out, found


@pytest.mark.parametrize("n_traj, window", [(2, None), (1, 20)])
def test_fit_warns_of_the_stability_limit_as_check_stability(n_traj, window):
    """The fit's stability check (Jacobians from its compiled call) reports the value
    `check_stability` finds on the fitted theta and x0, with several trajectories and
    with windows (each row of x0 starting its own window)."""
    model = oj.Model.from_ode(cubic, DT, observe=lambda x, u, p: x)
    # |lambda| h = 3 a x0^2 h = 2.59 at the start, past the 2.5 margin, smaller later.
    theta = {"a": 12.0, "b": 2.0}
    X0, u, z = _data(model, theta, np.array([1.2, 0.0]), n_traj)
    if n_traj == 1:
        X0, u, z = X0[0], u[0], z[0]
    result, found = _stability_warning(
        lambda: oj.fit(model, {"a": 10.0, "b": 1.5}, X0, u, z, window=window)
    )
    fitted_u = u if window is None else u.reshape(-1, window, 1)
    with pytest.warns(RuntimeWarning, match="stability limit") as direct:
        report = oj.check_stability(model, result.theta, result.x0, fitted_u)
    assert report.near_limit and len(found) == 1
    # (the same text, the fit's about "the fitted model", check_stability's "the model")
    assert found[0].startswith("the fitted model runs near")
    assert found[0].replace("the fitted model", "the model", 1) == str(direct[0].message)
    assert f"|lambda| h = {report.value:.3g}" in found[0]
    # (print: one line with the measure and the limits, not the raw tuple)
    assert str(report).startswith(f"RK4 with h = dt / substeps = {report.dt:g} / 1: largest ")
    assert f"|lambda| h {report.value:.3g}" in str(report) and "past its stability margin" in str(
        report
    )


def test_first_fit_and_predict_compile_one_program_each():
    model = oj.Model.from_ode(cubic, DT, observe=lambda x, u, p: x[:1])
    u = np.random.default_rng(1).uniform(-1.0, 1.0, (T + 7, 1))  # shapes no other test has
    _, z = oj.simulate(model, {"a": 0.5, "b": 2.0}, np.array([0.8, 0.1]), u)
    x0 = np.array([0.7, 0.0])
    jit_module.compiler_options()  # the process's one question to XLA, not the fit's
    result, n_fit = COMPILES.count(lambda: oj.fit(model, {"a": 0.4, "b": 1.5}, x0, u, z))
    assert n_fit == 1
    _, n_pred = COMPILES.count(lambda: result.predict(u[:-3], np.asarray(z)[:11]))
    assert n_pred == 1
    _, n_again = COMPILES.count(lambda: result.predict(u[:-3], np.asarray(z)[:11]))
    assert n_again == 0


class _Solves(logging.Handler):
    """Counts the compilations of the fit's solve (`jax.log_compiles`' records)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.n = 0

    def emit(self, record):
        self.n += record.getMessage().startswith("Finished XLA compilation of jit(_solve)")


@pytest.mark.parametrize("n_z", [2, 1])
def test_a_noise_weighted_fit_compiles_one_program(n_z):
    """`weight="noise"` fits with Q = I first, then with the estimated Q: the first fit
    ran without a weight and compiled the solve a second time (the first call took 4
    times a plain fit's). Q = I in the estimate's form shares one; the result's steps and
    time are those of all fits. (A round that starts at its optimum runs the check of
    entries that never moved, `_zero_gradient`: a small program of its own.)"""
    model = oj.Model.from_ode(cubic, DT, observe=lambda x, u, p: x[:n_z])
    rng = np.random.default_rng(5)
    u = rng.uniform(-1.0, 1.0, (T + 13 + n_z, 1))  # shapes no other test has
    _, z = oj.simulate(model, {"a": 0.5, "b": 2.0}, np.array([0.8, 0.1]), u)
    z = np.asarray(z) + rng.normal(0.0, [0.01, 0.1][:n_z], z.shape)

    def fit():
        return oj.fit(model, {"a": 0.4, "b": 1.5}, np.array([0.7, 0.0]), u, z, weight="noise")

    solves = _Solves()
    logger = logging.getLogger("jax")
    logger.addHandler(solves)
    try:
        with jax.log_compiles(True):
            result = fit()
    finally:
        logger.removeHandler(solves)
    assert solves.n == 1
    if n_z == 1:  # (one output's Q is 1: one fit, `test_noise_weight.py`)
        assert result.stop_info["noise_weight_rounds"] == 1
        return
    assert result.stop_info["noise_weight_rounds"] >= 2
    assert result.num_steps > result.history.loss.shape[0] - 1  # (the last fit's alone)


def test_a_regulariser_made_anew_reuses_the_compiled_fit():
    """`regulariser=l1(lam)` made anew for each fit, or a list of the same regularisers,
    compiled the whole solve again (4.6 s on a T = 100 problem): their functions compared
    by identity. Made alike, they compare equal; another strength still compiles."""
    from oneshot_jax import sparsity as sp

    model = oj.Model(lambda x, u, p: p["a"] * x + p["b"] * u)
    u = np.random.default_rng(3).uniform(-1.0, 1.0, (T + 11, 1))  # shapes no other test has
    _, z = oj.simulate(model, {"a": 0.5, "b": 1.0}, np.zeros(1), u)
    theta0 = {"a": 0.3, "b": 0.8}
    solver = oj.Adam(lr_theta=1e-2, max_steps=5)

    def fit(reg):
        return oj.fit(model, theta0, np.zeros(1), u, z, solver=solver, regulariser=reg)

    fit(sp.l1(1e-3))
    assert COMPILES.count(lambda: fit(sp.l1(1e-3)))[1] == 0
    pair = [sp.l1(1e-3), sp.l2(1e-2)]
    fit(pair)
    assert COMPILES.count(lambda: fit(pair))[1] == 0
    assert COMPILES.count(lambda: fit([sp.l1(1e-3), sp.l2(1e-2)]))[1] == 0
    assert COMPILES.count(lambda: fit(sp.l1(2e-3)))[1] > 0  # the strength is a constant


def test_a_general_set_with_a_box_made_anew_reuses_the_compiled_fit():
    """A general projection combined with a box (Dykstra's projection onto their
    intersection): `fit` takes the combination apart and combines it again, and the
    combined projection, a new function each time, compiled the whole solve on every
    call (1.8 s), the same combination or one made alike. It compares by its sets now;
    another box still compiles."""
    oc = oj.constraints
    model = oj.Model(lambda x, u, p: p["a"] * x + p["b"] * u)
    u = np.random.default_rng(4).uniform(-1.0, 1.0, (T + 13, 1))  # shapes no other test has
    _, z = oj.simulate(model, {"a": 0.5, "b": 1.0}, np.zeros(1), u)
    below = oc.project(lambda p: {**p, "b": jnp.minimum(p["b"], 0.9)})

    def fit(cons):
        return oj.fit(model, {"a": 0.3, "b": 0.8}, np.zeros(1), u, z, constraints=cons)

    both = oc.combine([below, oc.box(lower={"a": 0.1})])
    assert fit(both).theta["b"] == pytest.approx(0.9)  # (the general set binds)
    assert COMPILES.count(lambda: fit(both))[1] == 0
    assert COMPILES.count(lambda: fit([below, oc.box(lower={"a": 0.1})]))[1] == 0
    assert COMPILES.count(lambda: fit([below, oc.box(lower={"a": 0.2})]))[1] > 0


def test_predict_matches_estimate_x0_and_simulate():
    """predict's x0 estimate, its identifiable entries and the record simulated from it
    come from one compiled call: the same as `estimate_x0` and `simulate` apart, with an
    entry that the head does not determine (x1 reaches the output only through the
    input-free coupling c = 0)."""

    def rhs(x, u, p):
        return jnp.array([-p["a"] * x[0] + p["c"] * x[1] + u[0], -p["b"] * x[1]])

    model = oj.Model.from_ode(rhs, DT, observe=lambda x, u, p: x[:1])
    theta = {"a": 1.0, "b": 2.0, "c": 0.0}
    u = np.random.default_rng(2).uniform(-1, 1, (T, 1))
    _, z = oj.simulate(model, theta, np.array([0.3, 0.7]), u)
    guess = np.array([0.0, 0.5])
    with pytest.warns(UserWarning, match=r"x0\[1\]"):
        pred = oj.predict(model, theta, u, np.asarray(z), 12, x0=guess)
    with pytest.warns(UserWarning, match=r"x0\[1\]"):
        est = oj.estimate_x0(model, theta, u, np.asarray(z), n=12, x0=guess)
    assert list(pred.estimate.identifiable) == list(est.identifiable) == [True, False]
    np.testing.assert_array_equal(pred.x0, est.x0)
    np.testing.assert_array_equal(pred.estimate.covariance, est.covariance)
    x, zhat = oj.simulate(model, theta, pred.x0, u)
    np.testing.assert_allclose(pred.x, x, rtol=0, atol=1e-14)
    np.testing.assert_allclose(pred.z, zhat, rtol=0, atol=1e-14)
    assert pred.x.shape == (T, 2) and pred.z.shape == (T, 1)


def test_an_option_xla_refuses_falls_back_to_its_defaults(monkeypatch):
    """A compiler option this XLA does not know (jaxlib 0.11 dropped the elemental
    emitter's) costs nothing but the option: the first call on a CPU asks once, by a
    one-element program, and every call compiles with XLA's defaults from then on; the
    function is traced once, never twice."""
    on_cpu = jax.default_backend() == "cpu"
    traces = []

    def double(x):
        traces.append(x.shape)
        return 2.0 * x

    real = jit_module.CPU_OPTIONS
    # conftest.py set the same option as a flag where this XLA knows it.
    known = "xla_cpu_use_fusion_emitters" in os.environ.get("XLA_FLAGS", "")
    for options, taken in (({"xla_cpu_no_such_option": True}, False), (real, known)):
        monkeypatch.setattr(jit_module, "CPU_OPTIONS", options)
        monkeypatch.setattr(jit_module, "OPTIONS_TAKEN", [None])
        traces.clear()
        f = jit_module.jit(double)
        assert float(f(jnp.asarray(3.0))) == 6.0
        assert float(f(jnp.asarray(4.0))) == 8.0
        assert traces == [()]
        assert jit_module.OPTIONS_TAKEN == [taken if on_cpu else None]
        assert jit_module.compiler_options() == (options if on_cpu and taken else {})


def test_compiled_calls_return_the_static_outputs_of_their_own_shapes():
    """The library's compiled calls trace once per structure and shapes of their
    arguments; the non-array outputs (here the length) are those of the call's own
    shapes, also when a shape seen earlier comes back after another one."""
    calls = []

    def f(x, scale):
        calls.append(x.shape)
        return {"y": scale * x, "n": x.shape[0], "name": "f"}

    g = jit_module.jit(f)
    for n in (3, 5, 3, 5):
        out = g(np.arange(n, dtype=float), 2.0)
        assert out["n"] == n and out["name"] == "f"
        np.testing.assert_array_equal(out["y"], 2.0 * np.arange(n))
    assert calls == [(3,), (5,)]  # traced once per shape
    assert g(np.arange(3, dtype=float), 3.0)["y"][1] == 3.0  # a new static value: traced again
    assert len(calls) == 3


@pytest.mark.parametrize(
    "first, then",
    [
        (
            oj.LevenbergMarquardt(),
            oj.LevenbergMarquardt(gtol=1e-2, mu0=1e-2, rtol=1e-9, stol=0.05),
        ),
        (oj.GaussNewton(), oj.GaussNewton(gtol=1e-2, atol=1e-14, stol=0.05)),
        (oj.Adam(1e-2, max_steps=400), oj.Adam(1e-2, max_steps=400, tol_grad=1e-2, gtol=1e-2)),
        (oj.LBFGS(), oj.LBFGS(tol_grad=1e-2, gtol=1e-2)),
    ],
)
def test_a_new_tolerance_reuses_the_compiled_fit(first, then):
    """The tolerances (the statistical test's stol too) and LM's starting damping enter
    the compiled fit as traced numbers:
    a sweep over them compiles once, and the new values act (a looser tolerance stops
    earlier)."""
    model = oj.Model.from_ode(cubic, DT)
    x0, u, z = _data(model, {"a": 0.5, "b": 2.0}, np.array([0.3, -0.2]))
    z = z + 1e-3 * np.random.default_rng(5).standard_normal(z.shape)
    fit = lambda s: oj.fit(model, {"a": 0.4, "b": 1.5}, x0[0], u[0], z[0], solver=s)  # noqa: E731
    a, _ = COMPILES.count(lambda: fit(first))
    b, n = COMPILES.count(lambda: fit(then))
    assert n == 0
    assert len(b.history.loss) < len(a.history.loss)


@pytest.mark.parametrize(
    "solver",
    [oj.LevenbergMarquardt, oj.GaussNewton, lambda **k: oj.Adam(1e-2, **k), oj.LBFGS],
)
def test_a_new_step_budget_reuses_the_compiled_fit(solver):
    """`max_steps` bounds the loop alone (the history keeps its 1000 rows for every
    budget): a new budget reuses the compiled fit (each one compiled the whole solve
    again), and it acts: the short budget stops at it, the longer one goes on."""
    model = oj.Model.from_ode(cubic, DT)
    x0, u, z = _data(model, {"a": 0.5, "b": 2.0}, np.array([0.3, -0.2]))
    z = z + 1e-3 * np.random.default_rng(5).standard_normal(z.shape)
    fit = lambda s: oj.fit(model, {"a": 0.4, "b": 1.5}, x0[0], u[0], z[0], solver=s)  # noqa: E731
    short, _ = COMPILES.count(lambda: fit(solver(max_steps=2)))
    longer, n = COMPILES.count(lambda: fit(solver(max_steps=7)))
    assert n == 0
    assert short.status == "max_steps_reached" and short.num_steps == 2
    assert longer.num_steps > 2
    assert longer.status != "max_steps_reached" or longer.num_steps == 7


class _BudgetSized(oj.AbstractSolver):
    """Gradient descent of one's own whose `max_steps` is a static field and sizes an
    array: it must reach `init` as a Python number (the library's solvers trace theirs)."""

    max_steps: int = eqx.field(static=True, default=7)

    def init(self, problem, params):
        return problem.value_and_grad(params, "auto"), jnp.zeros(np.arange(self.max_steps).size)

    def step(self, problem, params, state):
        (_, g), seen = state
        lr = 0.1 if self.max_steps < 1000 else 0.01
        new = jax.tree.map(lambda p, d: p - lr * d, params, g)
        return new, (problem.value_and_grad(new, "auto"), seen)

    def terminate(self, problem, params, state):
        return jnp.array(False), oj.RESULTS.converged

    def summary(self, state):
        C, g = state[0]
        return C, jnp.sqrt(jnp.sum(g.theta**2) + jnp.sum(g.x0**2))


def test_a_solver_of_ones_own_gets_its_budget_as_a_number():
    """Tracing `max_steps` for every solver broke these (an equinox error for the static
    field, a tracer in np.arange and in `if`)."""
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((50, 1))
    _, z = oj.simulate(model, {"a": 0.5, "b": 1.0}, np.zeros(1), u)
    r = oj.fit(model, {"a": 0.2, "b": 0.5}, np.zeros(1), u, z, solver=_BudgetSized())
    assert r.status == "max_steps_reached" and r.num_steps == 7


def test_the_wall_time_covers_the_checks_after_the_solve():
    # A float32 L-BFGS success is checked after the solve (a Gauss-Newton and a Newton
    # step at the estimate, programs of their own on a first call): the printed wall time
    # ("a first call includes compiling") is the call's, checks included. Before, it was
    # the solve's alone: about 0.6 of the call here.
    def step(x, u, p):
        return jnp.stack([x[0] + DT * x[1], x[1] + DT * (-p["k"] * x[0] - p["c"] * x[1] + u[0])])

    model = oj.Model(step, lambda x, u, p: x[:1])
    rng = np.random.default_rng(3)
    u = rng.standard_normal((200, 1)).astype(np.float32)
    _, z = oj.simulate(model, {"k": 2.0, "c": 0.5}, np.array([1.0, 0.0], np.float32), u)
    z = (np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))).astype(np.float32)
    theta0 = {"k": np.float32(1.5), "c": np.float32(0.3)}
    start = time.perf_counter()
    result = oj.fit(model, theta0, np.zeros(2, np.float32), u, z, solver=oj.LBFGS())
    call = time.perf_counter() - start
    assert result.success and result.theta["k"].dtype == np.float32
    assert result.wall_time <= call
    assert result.wall_time >= 0.9 * call, (result.wall_time, call)
