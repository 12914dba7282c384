"""Records with time stamps (`Model.from_ode(rhs, dt=None)`, `t=`): step k integrates over
its own interval t[k+1] - t[k], which enters the step as data.

The one-shot gradient and the residual Jacobian are compared with JAX's autodiff of the
whole loss and residual rollout, with intervals that differ by 100x, through every
strategy, with the input held and interpolated, and with substeps sized to a maximum
step (masked beyond each interval's count). The simulation is compared with scipy's
`solve_ivp` at tight tolerances, and equal intervals with `from_ode(rhs, dt)`.
"""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp

import oneshot_jax as oj
from oneshot_jax.internal import Cost, FitProblem, Params, check_data

THETA = {"k": jnp.array([2.0, 1.2]), "c": jnp.array(0.3), "b": jnp.array([1.0, -0.5])}
RTOL = 1e-12


def rhs(x, u, th):
    """A forced Duffing oscillator coupled to a third state, two inputs."""
    q, v, w = x
    return jnp.stack(
        [
            v,
            -th["k"][0] * q - th["c"] * v - q**3 + th["b"][0] * u[0] + 0.3 * w,
            -th["k"][1] * w + th["b"][1] * u[1] * q,
        ]
    )


def observe(x, u, th):
    """Outputs that depend on the input and on theta too."""
    return jnp.stack([x[0] + 0.1 * th["c"] * u[0], x[1] * x[2] + th["b"][1] * u[1]])


def irregular_times(T, seed, short=0.01, long=1.0):
    """Time stamps whose intervals are `short` or `long` (100x apart), in random order."""
    rng = np.random.default_rng(seed)
    dt = np.where(rng.random(T - 1) < 0.5, short, long)
    dt[:2] = short, long  # both kinds, whatever the draw
    return np.concatenate([[0.3], 0.3 + np.cumsum(dt)])


def record(T=12, seed=0, N=None):
    rng = np.random.default_rng(seed)
    lead = () if N is None else (N,)
    t = (
        irregular_times(T, seed)
        if N is None
        else np.stack([irregular_times(T, seed + i) for i in range(N)])
    )
    u = rng.standard_normal((*lead, T, 2))
    x0 = np.array([0.5, -0.2, 0.3]) + 0.1 * rng.standard_normal((*lead, 3))
    z = 0.3 * rng.standard_normal((*lead, T, 2))
    return t, u, x0, z


def timed_model(input, max_step, substeps, method="rk4"):
    return oj.Model.from_ode(
        rhs, None, max_step=max_step, substeps=substeps, observe=observe, input=input, method=method
    )


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


# (strategy, input, max_step, substeps, trajectories): every strategy with both holds,
# and every kind of substep loop (masked: a fori_loop; unmasked: unrolled up to 8
# substeps, else a fori_loop).
CASES = [
    (oj.Jacobian(), "zoh", 0.25, 4, None),
    (oj.Jacobian(), "foh", 0.1, 10, 2),
    (oj.VJP(), "zoh", None, 3, 2),
    (oj.VJP(), "foh", None, 10, None),
    (oj.ParallelInTime(), "zoh", 0.1, 10, None),
    (oj.ParallelInTime(), "foh", 0.25, 4, 2),
]


@functools.cache
def _autodiff(input, max_step, substeps, N):
    """C and its gradient by JAX's autodiff of the whole loss (the reference)."""
    model = timed_model(input, max_step, substeps)
    t, u, x0, z = record(N=N)
    return jax.value_and_grad(lambda th, x0: oj.loss(model, th, x0, u, z, t=t), argnums=(0, 1))(
        THETA, jnp.asarray(x0)
    )


@pytest.mark.parametrize(
    "strategy, input, max_step, substeps, N",
    CASES,
    ids=lambda a: type(a).__name__ if isinstance(a, oj.AbstractStrategy) else str(a),
)
def test_gradient_equals_autodiff(strategy, input, max_step, substeps, N):
    model = timed_model(input, max_step, substeps)
    t, u, x0, z = record(N=N)
    C, (g_theta, g_x0) = oj.value_and_grad(model, THETA, x0, u, z, t=t, strategy=strategy)
    C_ref, (r_theta, r_x0) = _autodiff(input, max_step, substeps, N)
    assert _rel(C, C_ref) <= RTOL
    assert _rel(g_x0, r_x0) <= RTOL
    for name in THETA:
        assert np.all(np.abs(np.asarray(r_theta[name])) > 1e-8)  # a case that can fail
        assert _rel(g_theta[name], r_theta[name]) <= RTOL, name


def test_literal_value_and_grad_takes_t():
    model = timed_model("zoh", 0.25, 4)
    t, u, x0, z = record()
    C, (g_theta, g_x0) = oj.literal_value_and_grad(model, THETA, x0, u, z, t=t)
    C_ref, (r_theta, r_x0) = _autodiff("zoh", 0.25, 4, None)
    assert _rel(C, C_ref) <= RTOL and _rel(g_x0, r_x0) <= 1e-10
    for name in THETA:
        assert _rel(g_theta[name], r_theta[name]) <= 1e-10


def _problem(model, t, u, x0, z):
    """The FitProblem `fit` would build, from the data as `check_data` gives it (the
    intervals appended to u)."""
    data = check_data(model, THETA, x0, u, z, t=t)
    flat, unravel = ravel_pytree(data.theta)
    return FitProblem(
        model=data.model,
        cost=Cost(None, None, jnp.asarray(0.0)),
        u=jnp.asarray(data.u),
        z=jnp.asarray(data.z),
        theta_base=flat,
        theta_free=tuple(range(flat.size)),
        unravel=unravel,
        x0_base=jnp.asarray(data.x0),
        x0_free=(0, 1, 2),
        project=None,
        lower=None,
        upper=None,
    )


@eqx.filter_jit
def _closed_form(problem, pt, px, strategy):
    lin = problem.jacobian(Params(pt, px), strategy)
    return lin.r, lin.Jt, lin.Jx


@eqx.filter_jit
def _jacfwd(problem, pt, px):
    return jax.jacfwd(lambda a, b: problem.residuals(Params(a, b))[0], argnums=(0, 1))(pt, px)


@pytest.mark.parametrize(
    "strategy, input, max_step, substeps",
    [(s, i, m, n) for s, i, m, n, _ in CASES],
    ids=lambda a: type(a).__name__ if isinstance(a, oj.AbstractStrategy) else str(a),
)
def test_residual_jacobian_equals_autodiff(strategy, input, max_step, substeps):
    model = timed_model(input, max_step, substeps)
    N = 2
    t, u, x0, z = record(N=N)
    problem = _problem(model, t, u, x0, z)
    pt, px = problem.theta_base, problem.x0_base
    r, Jt, Jx = _closed_form(problem, pt, px, strategy)
    Jt_ref, Jx_ref = _jacfwd(problem, pt, px)  # (N, R, p) and (N, R, N, n_x)
    Jt_ref, Jx_ref = np.asarray(Jt_ref), np.asarray(Jx_ref)
    assert np.all(np.linalg.norm(Jt_ref, axis=1) > 0)
    assert _rel(Jt, Jt_ref) <= RTOL
    for i in range(N):
        assert np.all(np.linalg.norm(Jx_ref[i, :, i, :], axis=0) > 0)
        assert _rel(Jx[i], Jx_ref[i, :, i, :]) <= RTOL
    assert _rel(r, problem.residuals(Params(pt, px))[0]) <= RTOL


#
# The simulation.
#


def _reference(t, u, x0, input):
    """scipy's solve_ivp (DOP853, rtol 1e-12) over each interval, u held or linear."""
    th = jax.tree_util.tree_map(np.asarray, THETA)
    f = jax.jit(rhs)
    xs = [np.asarray(x0, float)]
    for k in range(len(t) - 1):
        a, b = t[k], t[k + 1]

        def u_at(s, k=k, a=a, b=b):
            if input == "zoh":
                return u[k]
            return u[k] + (s - a) / (b - a) * (u[k + 1] - u[k])

        sol = solve_ivp(
            lambda s, x: np.asarray(f(x, u_at(s), th)),
            (a, b),
            xs[-1],
            method="DOP853",
            rtol=1e-12,
            atol=1e-12,
        )
        xs.append(sol.y[:, -1])
    return np.stack(xs)


@pytest.mark.parametrize("input", ["zoh", "foh"])
def test_simulation_matches_solve_ivp(input):
    t, u, x0, _ = record(T=10)
    ref = _reference(t, u, x0, input)
    errors = []
    for max_step in (0.1, 0.05):
        x, _ = oj.simulate(timed_model(input, max_step, 20), THETA, x0, u, t=t)
        errors.append(np.max(np.abs(np.asarray(x) - ref)))
    assert errors[0] < 1e-4
    # RK4: halving the step divides the error by about 16 (h^4).
    assert 8.0 < errors[0] / errors[1] < 32.0, errors


def test_timed_model_differs_from_regular():
    """The time stamps matter: a regular model at the mean interval, and the same model
    at other stamps, give other states (so a `t` that were ignored would be caught)."""
    t, u, x0, _ = record()
    model = timed_model("zoh", 0.1, 10)
    x, _ = oj.simulate(model, THETA, x0, u, t=t)
    regular = oj.Model.from_ode(rhs, float(np.mean(np.diff(t))), substeps=10, observe=observe)
    x_regular, _ = oj.simulate(regular, THETA, x0, u)
    assert np.max(np.abs(np.asarray(x) - np.asarray(x_regular))) > 0.1
    x_other, _ = oj.simulate(model, THETA, x0, u, t=t[0] + 0.5 * (t - t[0]))
    assert np.max(np.abs(np.asarray(x) - np.asarray(x_other))) > 0.1


@pytest.mark.default_optimisation  # (two programs, equal to the bit: conftest.py)
@pytest.mark.parametrize("input, max_step", [("zoh", None), ("foh", 0.25 / 3)])
def test_equal_intervals_reproduce_from_ode_exactly(input, max_step):
    """With t = k dt (exact in binary), the timed model is the regular one, bit for bit:
    with max_step = dt / 3 each interval takes 3 of the 5 substeps, the rest masked."""
    T, dt = 12, 0.25
    _, u, x0, z = record(T=T)
    t = dt * np.arange(T)
    substeps = 3 if max_step is None else 5
    regular = oj.Model.from_ode(rhs, dt, substeps=3, observe=observe, input=input)
    timed = timed_model(input, max_step, substeps)
    x_a, z_a = oj.simulate(regular, THETA, x0, u)
    x_b, z_b = oj.simulate(timed, THETA, x0, u, t=t)
    np.testing.assert_array_equal(np.asarray(x_a), np.asarray(x_b))
    np.testing.assert_array_equal(np.asarray(z_a), np.asarray(z_b))
    C_a, (g_a, gx_a) = oj.value_and_grad(regular, THETA, x0, u, z, strategy="jacobian")
    C_b, (g_b, gx_b) = oj.value_and_grad(timed, THETA, x0, u, z, t=t, strategy="jacobian")
    assert C_a == C_b
    np.testing.assert_allclose(np.asarray(gx_a), np.asarray(gx_b), rtol=1e-14, atol=0)
    for name in THETA:
        np.testing.assert_allclose(np.asarray(g_a[name]), np.asarray(g_b[name]), rtol=1e-14)


def tank(x, u, th):
    """A tank's outflow (module-level: both cases below share the regular model's
    compiled programs)."""
    return -th["k"][0] * jnp.sqrt(x) - th["k"][1] * x


@pytest.mark.parametrize("strategy", ["auto", "vjp"])
def test_masked_substeps_keep_the_gradient_finite(strategy):
    """The substeps an interval does not need were full RK4 steps from its end state,
    masked afterwards: a tank's outflow -k sqrt(x) stepped below x = 0 there, and the
    masked NaN reached the reverse-mode gradient (0 * nan); L-BFGS stopped at step 0 with
    'the gradient overflowed'. The gradient now equals the regular model's."""
    T, dt = 10, 0.1
    u, x0, th = np.zeros((T, 1)), np.array([1.0]), {"k": np.array([1.9, 0.0])}
    regular = oj.Model.from_ode(tank, dt)
    timed = oj.Model.from_ode(tank, dt=None, max_step=dt, substeps=2)  # one substep used
    x, _ = oj.simulate(regular, th, x0, u)
    z = np.asarray(x) + 0.01
    assert float(np.min(x)) > 0.0  # the record itself stays where sqrt is smooth
    _, (g_a, gx_a) = oj.value_and_grad(regular, th, x0, u, z, strategy="jacobian")
    _, (g_b, gx_b) = oj.value_and_grad(timed, th, x0, u, z, t=dt * np.arange(T), strategy=strategy)
    np.testing.assert_allclose(np.asarray(g_b["k"]), np.asarray(g_a["k"]), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(gx_b), np.asarray(gx_a), rtol=1e-12)


def test_ragged_records_and_traced_times():
    """A list of records of different lengths, each with its own stamps, is each record
    simulated alone; t may be traced (under jit)."""
    model = timed_model("foh", 0.1, 10)
    t1, u1, x1, _ = record(T=9, seed=1)
    t2, u2, x2, _ = record(T=6, seed=2)
    xs, zs = oj.simulate(model, THETA, np.stack([x1, x2]), [u1, u2], t=[t1, t2])
    for x, t, u, x0 in ((xs[0], t1, u1, x1), (xs[1], t2, u2, x2)):
        np.testing.assert_allclose(
            np.asarray(x), np.asarray(oj.simulate(model, THETA, x0, u, t=t)[0]), rtol=1e-13
        )
    jitted = jax.jit(lambda t: oj.simulate(model, THETA, x1, u1, t=t)[0])(jnp.asarray(t1))
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(xs[0]), rtol=1e-13)


#
# Fitting, x0 and prediction.
#


def _damped(x, u, th):
    return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] - 0.5 * x[0] ** 3 + u[0]])


TRUE = {"k": jnp.array(2.0), "c": jnp.array(0.4)}
START = {"k": jnp.array(1.4), "c": jnp.array(0.8)}


def _fit_data(T=60, seed=3):
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(rng.choice([0.02, 0.3, 0.6], T - 1))])
    u = np.sin(0.7 * t)[:, None] + 0.3 * rng.standard_normal((T, 1))
    model = oj.Model.from_ode(_damped, None, max_step=0.1, substeps=6)
    x0 = np.array([1.0, 0.0])
    _, z = oj.simulate(model, TRUE, x0, u, t=t)
    return model, t, u, x0, np.asarray(z) + 1e-4 * rng.standard_normal(np.shape(z))


@functools.cache
def _fitted(window):
    model, t, u, x0, z = _fit_data()
    return oj.fit(model, START, x0 + 0.2, u, z, t=t, window=window)


@pytest.mark.parametrize("window", [None, 20])
def test_fit_recovers_parameters(window):
    res = _fitted(window)
    assert res.success, res.message
    for name in TRUE:
        assert abs(float(res.theta[name]) - float(TRUE[name])) < 1e-3, (name, res.theta)
    if window is None:
        model, t, u, x0, z = _fit_data()
        x, _ = res.simulate(u, t=t)
        assert np.max(np.abs(np.asarray(x)[:, 0] - z[:, 0])) < 1e-3
        # the stamps matter: at the true theta a regular model at the mean interval is
        # far off the data, which the fit reproduces to the noise
        regular = oj.Model.from_ode(_damped, float(np.mean(np.diff(t))), substeps=6)
        assert oj.loss(regular, TRUE, x0, u, z) > 1e4 * res.loss


def test_estimate_x0_and_predict_take_t():
    model, t, u, x0, z = _fit_data()
    est = oj.estimate_x0(model, TRUE, u, z, n=15, t=t)
    np.testing.assert_allclose(est.x0, x0, atol=1e-3)
    smoothed = oj.estimate_x0(model, TRUE, u, z, n=15, t=t, method="smoother")
    np.testing.assert_allclose(smoothed.x0, x0, atol=1e-2)
    pred = oj.predict(model, TRUE, u, z, 15, t=t)
    np.testing.assert_allclose(pred.z, z, atol=1e-3)
    again = _fitted(None).predict(u, z[:15], t=t)
    np.testing.assert_allclose(again.z, z, atol=1e-3)
    with pytest.raises(ValueError, match=r"`t` must have shape \(60,\)"):
        oj.estimate_x0(model, TRUE, u, z, n=15, t=t[:-1])
    with pytest.raises(ValueError, match="pass the sample times as `t=`"):
        oj.predict(model, TRUE, u, z, 15)


def test_compare_simulates_a_timed_fit_at_its_times():
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    model, t, u, x0, z = _fit_data()
    fig = oj.plot.compare(z, _fitted(None), u=u, t=t)
    line = fig.axes[0].lines[1]  # the model's output against t
    np.testing.assert_allclose(line.get_xdata(), t)
    np.testing.assert_allclose(
        line.get_ydata(), np.asarray(_fitted(None).simulate(u, t=t)[1])[:, 0]
    )
    assert "FIT 99" in line.get_label()


#
# Errors.
#


def test_models_without_stamps_refuse_t():
    t, u, x0, z = record()
    discrete = oj.Model(lambda x, u, th: x * th["c"] + u[0])
    with pytest.raises(ValueError, match="`t` .*needs a model of time-stamped records"):
        oj.simulate(discrete, THETA, x0, u, t=t)
    regular = oj.Model.from_ode(rhs, 0.1, observe=observe)
    assert not regular.timed and timed_model("zoh", None, 1).timed
    for call in (
        lambda: oj.loss(regular, THETA, x0, u, z, t=t),
        lambda: oj.value_and_grad(regular, THETA, x0, u, z, t=t),
        lambda: oj.fit(regular, THETA, x0, u, z, t=t),
        lambda: oj.estimate_x0(regular, THETA, u, z, x0=x0, t=t),
    ):
        with pytest.raises(ValueError, match="fixed sample interval"):
            call()
    with pytest.raises(ValueError, match="`max_step` applies to records with time stamps"):
        oj.Model.from_ode(rhs, 0.1, max_step=0.01)
    with pytest.raises(ValueError, match="`max_step` must be a finite positive"):
        oj.Model.from_ode(rhs, None, max_step=-1.0)
    with pytest.raises(ValueError, match="`observe` must be callable"):
        oj.Model.from_ode(rhs, None, observe=1)
    with pytest.raises(TypeError, match="`timed` must be a bool"):
        oj.Model(rhs, timed="yes")


def test_timed_model_needs_t():
    t, u, x0, z = record()
    model = timed_model("zoh", None, 2)
    for call in (
        lambda: oj.simulate(model, THETA, x0, u),
        lambda: oj.value_and_grad(model, THETA, x0, u, z),
        lambda: oj.fit(model, THETA, x0, u, z),
    ):
        with pytest.raises(ValueError, match="pass the sample times as `t=`"):
            call()
    # x0 guessed from z (a model that observes its state): the error is the missing
    # times alone, without the hint about the guess's columns (it added one)
    whole = oj.Model.from_ode(rhs, None)
    with pytest.raises(ValueError, match="pass the sample times as `t=`") as err:
        oj.estimate_x0(whole, THETA, u, np.zeros((12, 3)))
    assert "was not given" not in str(err.value)


@pytest.mark.parametrize(
    "bad, error, match",
    [
        (lambda t: t[:-1], ValueError, r"`t` must have shape \(12,\)"),
        (lambda t: t[::-1], ValueError, "`t` must be strictly increasing"),
        (lambda t: np.where(np.arange(t.size) == 3, t[2], t), ValueError, "strictly increasing"),
        (lambda t: np.where(np.arange(t.size) == 3, np.nan, t), ValueError, "`t` contains NaN"),
        (lambda t: "0 1 2", TypeError, "`t` must be an array of sample times"),
        (lambda t: t.astype(complex), TypeError, "`t` must hold real numbers"),
        (lambda t: t[None], ValueError, r"`t` must have shape \(12,\)"),
        # (a pandas index's differences: NumPy counts them as integers, of nanoseconds)
        (
            lambda t: (t * 1e9).astype("timedelta64[ns]"),
            TypeError,
            r"`t` must hold real numbers in the model's time unit, got dtype timedelta64\[ns\]",
        ),
        (lambda t: np.datetime64("2026-01-01") + t.astype(int), TypeError, "datetime64"),
    ],
)
def test_bad_t_names_t(bad, error, match):
    t, u, x0, _ = record()
    with pytest.raises(error, match=match):
        oj.simulate(timed_model("zoh", None, 2), THETA, x0, u, t=bad(t))


def test_time_stamps_stored_too_coarsely_for_their_intervals_warn():
    """float32 stamps of a record that starts at t = 1e6 (a Unix-like clock), 0.1 apart:
    float32 resolves 0.0625 there, so the intervals came in rounded to 0, 0.0625 or 0.125
    and the state was 0.11 off, silently. They warn now, naming the remedies; the same
    stamps in float64, or relative to the start in float32, do not."""
    t, u, x0, _ = record()
    model = timed_model("zoh", None, 2)
    far = 1e6 + 0.1 * np.arange(t.size)
    with pytest.warns(UserWarning, match=r"`t` is stored in float32.*t - t\[0\]"):
        oj.simulate(model, THETA, x0, u, t=far.astype(np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.simulate(model, THETA, x0, u, t=far)
        oj.simulate(model, THETA, x0, u, t=(far - far[0]).astype(np.float32))


def test_estimate_x0_checks_the_whole_t_as_predict_does():
    """estimate_x0 uses the head of t but checks all of it, as predict does (it accepted a
    t that predict refused); the message shows plain numbers, not NumPy reprs."""
    t, u, x0, z = record()
    model = timed_model("zoh", None, 2)
    bad = t.copy()
    bad[8] = bad[6]
    msg = rf"`t` must be strictly increasing: t\[8\] = {float(bad[8])!r} does not come after"
    for call in (
        lambda: oj.estimate_x0(model, THETA, u, z, n=4, t=bad),
        lambda: oj.predict(model, THETA, u, z, 4, t=bad),
    ):
        with pytest.raises(ValueError, match=msg):
            call()


def test_bad_batched_t():
    t, u, x0, _ = record(N=2)
    model = timed_model("zoh", None, 2)
    with pytest.raises(ValueError, match=r"`t` must have shape \(2, 12\)"):
        oj.simulate(model, THETA, x0, u, t=np.stack([t[0], t[0], t[1]]))
    with pytest.raises(ValueError, match=r"`t\[1\]` must be strictly increasing"):
        oj.simulate(model, THETA, x0, u, t=np.stack([t[0], t[1][::-1]]))
    # one row of stamps shared by every trajectory
    x, _ = oj.simulate(model, THETA, x0, u, t=t[0])
    np.testing.assert_allclose(
        np.asarray(x[1]), np.asarray(oj.simulate(model, THETA, x0[1], u[1], t=t[0])[0])
    )


def test_too_few_substeps_for_max_step():
    t, u, x0, _ = record()  # longest interval 1.0
    model = timed_model("zoh", 0.1, 8)
    with pytest.raises(ValueError, match=r"needs 10 integrator steps.*`substeps` = 8.*substeps=10"):
        oj.simulate(model, THETA, x0, u, t=t)


def test_traced_times_the_host_cannot_check_give_nan_not_a_wrong_state():
    """Under `jax.jit` the host cannot check `t`: an interval that needs more steps of
    `max_step` than `substeps` allows (here 13 > 4 + 1), a decreasing `t` or a NaN in it
    give NaN states from that interval on, where they used to give steps longer than
    `max_step` (a wrong state, no error) or a frozen state. Valid traced stamps give the
    eager states."""
    lag = lambda x, u, th: (-x + th["K"] * u) / th["tau"]  # noqa: E731
    th, u, x0 = {"K": 2.0, "tau": 0.7}, np.ones((6, 1)), np.zeros(1)
    t = np.array([0.0, 0.1, 0.2, 1.5, 1.6, 1.7])  # the third interval needs 13 steps of 0.1
    model = oj.Model.from_ode(lag, None, max_step=0.1, substeps=4)
    sim = jax.jit(lambda t: oj.simulate(model, th, x0, u, t=t)[0][:, 0])
    with pytest.raises(ValueError, match="needs 13 integrator steps"):
        oj.simulate(model, th, x0, u, t=t)  # the host's check (eager)
    x = np.asarray(sim(t))
    assert np.all(np.isfinite(x[:3])) and np.all(np.isnan(x[3:]))
    whole = oj.Model.from_ode(lag, None, max_step=0.1, substeps=13)
    expected = np.asarray(oj.simulate(whole, th, x0, u, t=t)[0])[:3, 0]
    np.testing.assert_allclose(x[:3], expected, rtol=1e-14)
    assert np.all(np.isnan(np.asarray(sim(t[::-1].copy()))[1:]))
    assert np.all(np.isnan(np.asarray(sim(np.where(np.arange(6) == 2, np.nan, t)))[2:]))
    fine = np.linspace(0.0, 0.5, 6)  # intervals of 0.1: one step each
    np.testing.assert_allclose(
        np.asarray(sim(fine)),
        np.asarray(oj.simulate(model, th, x0, u, t=fine)[0])[:, 0],
        rtol=1e-14,
    )


def test_errors_about_u_name_the_users_n_u():
    """The interval column is the library's: a model error names the user's u."""
    t, u, x0, _ = record()
    model = oj.Model.from_ode(lambda x, u, th: rhs(x, jnp.eye(2) @ u, th), None)
    with pytest.raises(ValueError, match=r"input of shape \(1,\) \(from `u` of shape \(12, 1\)\)"):
        oj.simulate(model, THETA, x0, u[:, :1], t=t)


@pytest.mark.parametrize(
    "dtype, substeps, t1",
    [
        (np.float32, 4, 0.4000004529953003),  # a float32 number
        (np.float64, 1, 0.10000010000010001),  # max_step / (1 - 1e-6): the tolerance's edge
        (np.float64, 3, 0.30000030000030004),
    ],
)
def test_an_interval_next_to_a_multiple_of_max_step_is_integrated_whole(dtype, substeps, t1):
    """The host check counted n steps of max_step = 0.1 for these intervals and the compiled
    step n + 1 (XLA folds 1 / max_step and the tolerance into one constant), and the loop,
    bounded by `substeps`, integrated n / (n + 1) of the interval (half of it, for one
    substep). The count is capped at `substeps`: dx/dt = 1 crosses the whole interval."""
    model = oj.Model.from_ode(
        lambda x, u, p: p["c"] * jnp.ones_like(x), None, max_step=0.1, substeps=substeps
    )
    t = np.array([0.0, t1])
    x, _ = oj.simulate(model, {"c": dtype(1.0)}, np.zeros(1, dtype), np.zeros((2, 0), dtype), t=t)
    assert x.dtype == dtype
    np.testing.assert_allclose(float(x[1, 0]), float(dtype(t1)), rtol=4 * np.finfo(dtype).eps)
