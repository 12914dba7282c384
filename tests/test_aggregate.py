"""Aggregated observations (`oj.Aggregate`): the loss, the one-shot gradient and the residual
Jacobian against jax autodiff of a direct implementation of the aggregated loss, written here
independently (a plain rollout, A @ y_c), through every strategy; a fit that recovers the
parameters from aggregated readings; the errors on bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.internal import (
    FitProblem,
    Params,
    aggregate_augment,
    build,
    check_cost,
    check_data,
)

T = 40
THETA = {"a": jnp.array(0.6), "b": jnp.array(1.3), "c": jnp.array(0.8)}
Q = np.array([1.0, 2.5])


def step(x, u, th):
    return x + 0.1 * jnp.stack(
        [
            -th["a"] * x[0] + th["b"] * jnp.tanh(x[1]) + u[0],
            -th["c"] * x[1] - 0.3 * x[0] * x[1] + 0.5 * u[1],
        ]
    )


def observe(x, u, th):
    """Channel 0: point samples with gaps; channel 1 (nonlinear in x and theta):
    aggregated, with a few point samples too."""
    return jnp.stack([x[0] + 0.2 * th["c"] * u[0], x[1] ** 2 + th["a"] * x[0]])


MODEL = oj.Model(step, observe)


def rollout(theta, x0, u):
    def f(x, u_k):
        return step(x, u_k, theta), x

    _, xs = jax.lax.scan(f, x0, u)
    return jax.vmap(observe, in_axes=(0, 0, None))(xs, u, theta)


def data(seed=0, n=T):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 2))
    x0 = np.array([0.4, -0.6])
    y = np.asarray(rollout(THETA, jnp.asarray(x0), jnp.asarray(u)))
    z = y + 0.02 * rng.standard_normal(y.shape)
    z[rng.random(n) < 0.3, 0] = np.nan  # missing samples of the point channel
    z[rng.random(n) < 0.8, 1] = np.nan  # channel 1 mostly aggregated
    return x0, u, z, y


def rows(form, n=T):
    """(A, intervals) of channel 1's readings, built here without `Aggregate.operator`."""
    if form == "overlap":
        intervals = [(0, 10), (5, 15), (8, 30), (12, 13), (30, 40), (0, 40)]
    else:
        intervals = [(0, 7), (7, 19), (19, 20), (22, 35), (35, 40)]
    A = np.zeros((len(intervals), n))
    for i, (a, b) in enumerate(intervals):
        A[i, a:b] = 1.0 if form in ("sum", "overlap") else 1.0 / (b - a)
    if form == "matrix":  # a general matrix: irregular weights, gaps inside a row
        rng = np.random.default_rng(5)
        A = rng.uniform(0.1, 1.0, A.shape) * (A > 0)
        A[1, 10] = 0.0
    return A, intervals


def aggregate_of(form, values, weight=None):
    A, intervals = rows(form)
    if form == "matrix":
        return oj.Aggregate(1, values=values, matrix=A, weight=weight)
    kind = "mean" if form == "mean" else "sum"
    return oj.Aggregate(1, intervals, values, kind=kind, weight=weight)


def readings(form, y, seed=1):
    A, _ = rows(form)
    v = A @ y[:, 1] + 0.02 * np.random.default_rng(seed).standard_normal(A.shape[0])
    v[2] = np.nan  # a missing reading
    return v


def direct_loss(theta, x0, u, z, A, v, w):
    """(sum_k e_k^T Q e_k over measured samples + sum_i w_i (A y_1 - v)_i^2) / T."""
    y = rollout(theta, x0, u)
    e = jnp.where(jnp.isnan(z), 0.0, y - jnp.nan_to_num(z))
    r = jnp.where(jnp.isnan(v), 0.0, A @ y[:, 1] - jnp.nan_to_num(v))
    return (jnp.sum(Q * e**2) + jnp.sum(w * r**2)) / u.shape[0]


THETA_EVAL = {"a": jnp.array(0.5), "b": jnp.array(1.5), "c": jnp.array(0.7)}  # off the truth
FORMS = ("sum", "mean", "matrix", "overlap")
STRATEGIES = {
    "jacobian": oj.Jacobian(),
    "vjp": oj.VJP(),
    "parallel": oj.ParallelInTime(),
}


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_value_and_grad_equal_autodiff_of_the_direct_loss(form, strategy):
    x0, u, z, y = data()
    v = readings(form, y)
    w = np.linspace(0.5, 3.0, v.size) if form == "matrix" else Q[1]  # per-reading weights
    agg = aggregate_of(form, v, weight=w if form == "matrix" else None)
    x0e = jnp.asarray(x0 + 0.1)
    C, (g_theta, g_x0) = oj.value_and_grad(
        MODEL,
        THETA_EVAL,
        x0e,
        u,
        z,
        weight=Q,
        missing="mask",
        aggregate=agg,
        strategy=STRATEGIES[strategy],
    )
    A, _ = rows(form)
    args = (jnp.asarray(u), jnp.asarray(z), jnp.asarray(A), jnp.asarray(v), jnp.asarray(w))
    C_ref, (gt_ref, gx_ref) = jax.value_and_grad(direct_loss, argnums=(0, 1))(
        THETA_EVAL, x0e, *args
    )
    # The readings matter: without them the loss and gradient differ.
    C_pts = oj.loss(MODEL, THETA_EVAL, x0e, u, z, weight=Q, missing="mask")
    assert abs(float(C_ref) - float(C_pts)) > 1e-3 * float(C_ref)
    np.testing.assert_allclose(C, C_ref, rtol=1e-12)
    assert g_x0.shape == (2,)
    np.testing.assert_allclose(g_x0, gx_ref, rtol=1e-12, atol=1e-14)
    flat, _ = ravel_pytree(g_theta)
    flat_ref, _ = ravel_pytree(gt_ref)
    np.testing.assert_allclose(flat, flat_ref, rtol=1e-12, atol=1e-14)
    C_loss = oj.loss(
        MODEL,
        THETA_EVAL,
        x0e,
        u,
        z,
        weight=Q,
        missing="mask",
        aggregate=agg,
        strategy=STRATEGIES[strategy],
    )
    np.testing.assert_allclose(C_loss, C_ref, rtol=1e-12)


def _problem(form, seed=0):
    """The FitProblem of the aggregated data, built as `fit` builds it (every entry of
    theta free, the user's x0 entries free, the accumulators' fixed)."""
    x0, u, z, y = data(seed)
    v = readings(form, y)
    agg = aggregate_of(form, v)
    x0e = x0 + 0.1
    checked = check_data(MODEL, THETA_EVAL, x0e, u, z, Q, "mask")
    aug = aggregate_augment(checked, agg, MODEL, x0e, "mask")
    d = check_data(aug.model, THETA_EVAL, aug.x0, aug.u, aug.z, aug.weight, "mask")
    flat, unravel = ravel_pytree(d.theta)
    problem = build(
        FitProblem,
        model=d.model,
        cost=check_cost(d, None, 1.0),
        u=jnp.asarray(d.u)[None],
        z=jnp.asarray(d.z)[None],
        theta_base=flat,
        theta_free=tuple(range(flat.size)),
        unravel=unravel,
        x0_base=jnp.asarray(d.x0)[None],
        x0_free=(0, 1),
        project=None,
        lower=None,
        upper=None,
        mask=jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], d.mask),
    )
    A, _ = rows(form)
    direct = (jnp.asarray(u), jnp.asarray(z), jnp.asarray(A), jnp.asarray(v), Q[1])
    return problem, flat, jnp.asarray(x0e), direct


@eqx.filter_jit
def linearise(problem, pt, px, strategy):
    return problem.jacobian(Params(pt, px), strategy)


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_residual_jacobian_equals_autodiff_of_the_direct_residuals(form, strategy):
    """The Gauss-Newton quantities J^T J, J^T r and r^T r of the closed-form Jacobian
    (forward sensitivities through the accumulators) equal those of jax.jacfwd of the
    direct residuals (sqrt(Q) e_k and sqrt(w) (A y - v), over sqrt(T))."""
    problem, flat, x0e, (u, z, A, v, w) = _problem(form)
    pt, px = problem.split(problem.theta_base, problem.x0_base)
    lin = linearise(problem, pt, px, STRATEGIES[strategy])
    J = np.concatenate([lin.Jt[0], lin.Jx[0]], axis=1)
    r = np.asarray(lin.r[0])

    _, unravel = ravel_pytree(THETA_EVAL)

    def direct(p):
        theta, x0 = unravel(p[:3]), p[3:]
        y = rollout(theta, x0, u)
        e = jnp.where(jnp.isnan(z), 0.0, (y - jnp.nan_to_num(z)) * np.sqrt(Q))
        rr = jnp.where(jnp.isnan(v), 0.0, (A @ y[:, 1] - jnp.nan_to_num(v)) * np.sqrt(w))
        return jnp.concatenate([e.reshape(-1), rr]) / np.sqrt(u.shape[0])

    p = jnp.concatenate([flat, x0e])
    r_ref, J_ref = direct(p), jax.jacfwd(direct)(p)
    np.testing.assert_allclose(r @ r, r_ref @ r_ref, rtol=1e-12)
    np.testing.assert_allclose(J.T @ r, J_ref.T @ r_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(J.T @ J, J_ref.T @ J_ref, rtol=1e-12, atol=1e-15)
    # one nonzero residual per point sample and per reading, the rest zero (masked)
    assert np.count_nonzero(r) == np.count_nonzero(np.asarray(r_ref))


def test_the_loss_with_an_aggregate_under_grad_jit_and_vmap():
    """`oj.loss(..., aggregate=)` traced (jax.grad over x0, jit over z and over t, vmap
    over x0) equals the eager values and `value_and_grad`; it used to fail deep inside
    with a TracerArrayConversionError. A traced `t` with a reading over time (trapezoid
    weights from the stamps) is refused by name."""
    lag = lambda x, u, th: (-x + th["K"] * u) / th["tau"]  # noqa: E731
    model = oj.Model.from_ode(lag, dt=None, max_step=0.1, substeps=20)
    th = {"K": 2.0, "tau": 0.7}
    t = np.array([0.0, 0.1, 0.2, 1.5, 1.6, 1.7])
    u, x0 = np.ones((6, 1)), np.array([0.1])
    z = np.full((6, 1), np.nan)
    z[4] = 1.0
    agg = oj.Aggregate(0, [(0, 3)], [1.0], kind="mean")

    def loss(x0, z=z, t=t, agg=agg):
        return oj.loss(model, th, x0, u, z, t=t, aggregate=agg, missing="mask")

    C, (_, g_x0) = oj.value_and_grad(model, th, x0, u, z, t=t, aggregate=agg, missing="mask")
    assert float(loss(x0)) == pytest.approx(float(C), rel=1e-14)
    np.testing.assert_allclose(np.asarray(jax.grad(loss)(x0)), np.asarray(g_x0), rtol=1e-13)
    assert float(jax.jit(lambda z: loss(x0, z))(z)) == pytest.approx(float(C), rel=1e-14)
    assert float(jax.jit(lambda t: loss(x0, t=t))(t)) == pytest.approx(float(C), rel=1e-14)
    both = np.asarray(jax.vmap(loss)(np.stack([x0, 2 * x0])))
    np.testing.assert_allclose(both, [float(loss(x0)), float(loss(2 * x0))], rtol=1e-14)
    over_time = oj.Aggregate(0, [(0, 3)], [1.0], kind="time_mean")
    with pytest.raises(ValueError, match="`t` must be concrete"):
        jax.jit(lambda t: loss(x0, t=t, agg=over_time))(t)


def test_batch_of_records_with_an_aggregate_per_record():
    """Two records of different lengths (a list), aggregates on the first only: the loss
    and gradient equal the direct ones summed over records over the total time points."""
    x0a, ua, za, ya = data(0)
    x0b, ub, zb, _ = data(3, n=25)
    v = readings("overlap", ya)
    agg = aggregate_of("overlap", v)
    X0 = jnp.asarray(np.stack([x0a, x0b]) + 0.1)
    C, (g_theta, g_x0) = oj.value_and_grad(
        MODEL,
        THETA_EVAL,
        X0,
        [ua, ub],
        [za, zb],
        weight=Q,
        missing="mask",
        aggregate=[agg, None],
    )
    A, _ = rows("overlap")

    def ref(theta, X0):
        one = direct_loss(theta, X0[0], ua, za, A, v, Q[1]) * T
        two = direct_loss(theta, X0[1], ub, zb, np.zeros((1, 25)), np.zeros(1), 0.0) * 25
        return (one + two) / (T + 25)

    C_ref, (gt_ref, gx_ref) = jax.value_and_grad(ref, argnums=(0, 1))(THETA_EVAL, X0)
    np.testing.assert_allclose(C, C_ref, rtol=1e-12)
    np.testing.assert_allclose(g_x0, gx_ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ravel_pytree(g_theta)[0], ravel_pytree(gt_ref)[0], rtol=1e-12)


def test_operator_kinds():
    """The rows of A for each kind, against hand-computed weights (trapezoid rule)."""
    t = np.array([0.0, 1.0, 3.0, 3.5, 6.0])
    agg = oj.Aggregate(0, [(0, 3), (2, 5)], [1.0, 2.0], kind="integral")
    np.testing.assert_allclose(
        agg.operator(5, t), [[0.5, 1.5, 1.0, 0, 0], [0, 0, 0.25, 1.5, 1.25]], rtol=1e-15
    )
    np.testing.assert_allclose(
        agg.operator(5, np.arange(5)), [[0.5, 1, 0.5, 0, 0], [0, 0, 0.5, 1, 0.5]]
    )
    tm = oj.Aggregate(0, [(0, 3)], [1.0], kind="time_mean").operator(5, t)
    np.testing.assert_allclose(tm, [[0.5 / 3, 1.5 / 3, 1.0 / 3, 0, 0]], rtol=1e-15)
    # over samples 1..3 the duration (2.5) and the number of samples (3) differ
    tm = oj.Aggregate(0, [(1, 4)], [1.0], kind="time_mean").operator(5, t)
    np.testing.assert_allclose(tm, [[0, 1.0 / 2.5, 1.25 / 2.5, 0.25 / 2.5, 0]], rtol=1e-15)
    np.testing.assert_allclose(
        oj.Aggregate(0, [(1, 3)], [1.0], kind="mean").operator(4), [[0, 0.5, 0.5, 0]]
    )
    y = np.arange(10.0)[:, None] ** 2
    np.testing.assert_allclose(oj.Aggregate(0, [(2, 5)], [0.0], kind="sum").predict(y), [29.0])


def test_an_integral_of_a_fixed_dt_ode_model_is_over_time():
    """A reading of the integral of x1 over 1 s (11 samples, dt = 0.1): the loss is 0 at
    the truth. Over unit spacing it was 10 times too large (3.56 at the truth)."""
    rhs = lambda x, u, th: jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])  # noqa: E731
    model = oj.Model.from_ode(rhs, dt=0.1, substeps=2)
    truth, x0 = {"k": 2.0, "c": 0.3}, np.array([1.0, -0.5])
    u = np.random.default_rng(7).standard_normal((30, 1))
    xs, z = oj.simulate(model, truth, x0, u)
    z = np.array(z)
    z[:, 1] = np.nan  # the second output only as its integral
    v = np.asarray(xs)[0:11, 1]
    reading = 0.1 * (np.sum(v) - (v[0] + v[-1]) / 2)  # the trapezoid rule
    agg = oj.Aggregate(1, [(0, 11)], [reading], kind="integral")
    C = oj.loss(model, truth, x0, u, z, missing="mask", aggregate=agg)
    assert float(C) < 1e-25
    # Stand-alone, `predict` takes the time stamps; without them it cannot know dt (over
    # unit spacing it gave 10 times the reading): refused, naming t.
    np.testing.assert_allclose(agg.predict(np.asarray(xs), 0.1 * np.arange(30)), [reading])
    for kind in ("integral", "time_mean"):
        with pytest.raises(ValueError, match=rf"`t` is needed for kind='{kind}'"):
            oj.Aggregate(1, [(0, 11)], [reading], kind=kind).predict(np.asarray(xs))
    assert oj.Aggregate(1, [(0, 11)], [reading], kind="mean").predict(np.asarray(xs)).shape == (1,)


def _first_order_rhs(x, u, th):
    return -th["a"] * x + th["b"] * u


# (one model object for the tests below, so that they share its compiled programs)
TIMED_FIRST_ORDER = oj.Model.from_ode(_first_order_rhs, dt=None)


def _timed_first_order():
    T = 60
    t = np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(0.05, 1.0, T - 1)])
    u = (np.sin(0.5 * t) > 0).astype(float)[:, None]
    return TIMED_FIRST_ORDER, {"a": 0.5, "b": 2.0}, t, u


def test_an_output_measured_only_in_aggregate_is_identified():
    """A meter read once per period: z all NaN, the output known only through its
    time-mean readings. Accepted (it was refused as "NaN everywhere") and identified; with
    neither samples nor readings the augmented data are still refused."""
    model, truth, t, u = _timed_first_order()
    _, y = oj.simulate(model, truth, np.array([1.0]), u, t=t)
    spans = [(a, a + 6) for a in range(0, 60, 6)]
    values = oj.Aggregate(0, spans, np.zeros(10), kind="time_mean").predict(y, t)
    agg = oj.Aggregate(0, spans, np.asarray(values), kind="time_mean")
    z = np.full((60, 1), np.nan)
    kw = dict(t=t, missing="mask", aggregate=agg)
    assert float(oj.loss(model, truth, np.array([1.0]), u, z, **kw)) < 1e-25
    r = oj.fit(model, {"a": 0.6, "b": 1.5}, np.array([1.0]), u, z, estimate_x0=False, **kw)
    assert r.success
    np.testing.assert_allclose([r.theta["a"], r.theta["b"]], [0.5, 2.0], rtol=1e-8)
    # No point sample to score: the criteria are NaN floats, as in any other fit (0-d
    # arrays, and the printout gave the reason of too few fully measured samples).
    for name in ("aic", "aicc", "bic", "fpe"):
        assert type(r.metrics[name]) is float and np.isnan(r.metrics[name]), name
    assert "AIC nan (no output has a point sample: aggregated readings only)" in str(r)
    # check_basin's windows cannot take the readings: the output would drop out of its
    # comparison (it ran the windows on no data and called the basin fine)
    assert r.diagnostics["aggregated"] is True
    with pytest.raises(ValueError, match="`check_basin` does not take the result of a fit with"):
        oj.check_basin(r, u, z, window=20)
    empty = oj.Aggregate(0, spans, np.full(10, np.nan), kind="time_mean")
    with pytest.raises(ValueError, match="NaN everywhere"):
        oj.loss(model, truth, np.array([1.0]), u, z, t=t, missing="mask", aggregate=empty)
    with pytest.raises(ValueError, match="NaN everywhere"):
        oj.loss(model, truth, np.array([1.0]), u, z, t=t, missing="mask")


def test_each_start_of_an_aggregated_fit_keeps_the_models_initial_state():
    """`result.starts.x0` of an aggregated fit has the user's model's states (not the
    augmented model's, whose accumulators are appended), and each start's loss is
    recomputed from it."""
    model, truth, t, u = _timed_first_order()
    _, z = oj.simulate(model, truth, np.array([1.0]), u, t=t)
    z = np.asarray(z) + 0.02 * np.random.default_rng(5).standard_normal(np.shape(z))
    spans = [(a, a + 6) for a in range(0, 60, 6)]
    agg = oj.Aggregate(0, spans, oj.Aggregate(0, spans, np.zeros(10)).predict(z), kind="mean")
    kw = dict(t=t, missing="mask", aggregate=agg)
    starts = {"a": np.array([0.6, 0.3]), "b": np.array([1.5, 2.5])}
    r = oj.fit(model, starts, np.array([0.8]), u, z, multistart=True, **kw)
    assert r.starts.x0.shape == (2, 1)
    for s in range(2):
        theta = {k: r.starts.theta[k][s] for k in starts}
        C = oj.loss(model, theta, r.starts.x0[s], u, z, **kw)
        assert float(C) == pytest.approx(float(r.starts.loss[s]), rel=1e-9)


def test_readings_of_weight_zero_add_no_observations():
    """Readings of weight 0 leave the loss and the standard errors as without them (they
    counted as observations: std smaller by sqrt(57 / 37) with 20 such readings next to
    40 samples)."""
    model, truth, t, u = _timed_first_order()
    _, z = oj.simulate(model, truth, np.array([1.0]), u, t=t)
    z = np.asarray(z) + 0.05 * np.random.default_rng(3).standard_normal(z.shape)
    spans = [(a, a + 3) for a in range(0, 60, 3)]
    idle = oj.Aggregate(0, spans, np.zeros(len(spans)), kind="mean", weight=0.0)
    start, kw = {"a": 0.6, "b": 1.5}, dict(t=t, missing="mask")
    plain = oj.fit(model, start, np.array([1.0]), u, z, **kw)
    with_idle = oj.fit(model, start, np.array([1.0]), u, z, aggregate=idle, **kw)
    assert float(with_idle.loss) == pytest.approx(float(plain.loss), rel=1e-10)
    for k in ("a", "b"):
        assert float(with_idle.std[k]) == pytest.approx(float(plain.std[k]), rel=1e-8)


def test_records_of_their_own_lengths_take_their_times_as_a_tuple():
    """Times of records of different lengths as a tuple, as a list (a tuple raised a NumPy
    error with an aggregate, though accepted without one)."""
    model, truth, t, u = _timed_first_order()
    us, zs = [u, u[:30]], [np.full((60, 1), 0.5), np.full((30, 1), 0.5)]
    agg = oj.Aggregate(0, [(0, 5)], [1.0], kind="time_mean")
    kw = dict(missing="mask", aggregate=[agg, agg])
    x0 = np.zeros((2, 1))
    as_list = oj.loss(model, truth, x0, us, zs, t=[t, t[:30]], **kw)
    as_tuple = oj.loss(model, truth, x0, us, zs, t=(t, t[:30]), **kw)
    assert float(as_tuple) == float(as_list) > 0


def test_records_sharing_one_time_axis_take_aggregates():
    """N records with one (T,) time axis, as without aggregates (it raised an IndexError):
    the same loss as the axis given per record."""
    model, truth, t, u = _timed_first_order()
    x0, U = np.array([[0.0], [0.5]]), np.stack([u, 1 - u])
    _, z = oj.simulate(model, truth, x0, U, t=t)
    agg = oj.Aggregate(0, [(0, 10), (20, 35)], [1.0, 2.0], kind="time_mean")
    kw = dict(missing="mask", aggregate=[agg, agg])
    shared = oj.loss(model, truth, x0, U, np.asarray(z), t=t, **kw)
    each = oj.loss(model, truth, x0, U, np.asarray(z), t=np.stack([t, t]), **kw)
    assert float(shared) == float(each) > 0


def test_fit_recovers_parameters_from_aggregates(tmp_path):
    """Channel 1 measured only as sums over 5-sample intervals (no point samples); a
    Levenberg-Marquardt fit recovers theta with finite standard errors, the readings
    counted as observations."""
    x0, u, z, y = data(0, n=60)
    z[:, 1] = np.nan
    intervals = [(k, k + 5) for k in range(0, 60, 5)]
    v = np.array([y[a:b, 1].sum() for a, b in intervals])
    v += 0.01 * np.random.default_rng(7).standard_normal(v.size)
    agg = oj.Aggregate(1, intervals, v, kind="sum")
    theta0 = {"a": jnp.array(0.45), "b": jnp.array(1.6), "c": jnp.array(0.65)}
    res = oj.fit(MODEL, theta0, x0 + 0.1, u, z, missing="mask", aggregate=agg)
    assert res.success, res.message
    assert res.x0.shape == (2,) and res.x0_std.shape == (2,)
    assert res.residuals.shape == z.shape
    for k in THETA:
        assert abs(float(res.theta[k]) - float(THETA[k])) < 4 * float(res.std[k]) + 1e-3, k
        assert 0 < float(res.std[k]) < 0.1, k
    # The covariance counts the readings as observations: sigma^2 (J^T J)^-1 of the
    # direct residuals (point samples and readings) at the estimate.
    seen = np.isfinite(z[:, 0])
    A = np.zeros((len(intervals), 60))
    for i, (a, b) in enumerate(intervals):
        A[i, a:b] = 1.0
    _, unravel = ravel_pytree(THETA)

    def direct(p):
        y = rollout(unravel(p[:3]), p[3:], jnp.asarray(u))
        return jnp.concatenate([(y[:, 0] - np.nan_to_num(z[:, 0]))[seen], A @ y[:, 1] - v])

    p = jnp.concatenate([ravel_pytree(res.theta)[0], jnp.asarray(res.x0)])
    r, J = np.asarray(direct(p)), np.asarray(jax.jacfwd(direct)(p))
    assert r.size == seen.sum() + len(intervals)
    cov = (r @ r) / (r.size - 5) * np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(res.covariance, cov[:3, :3], rtol=1e-5)
    assert res.metrics["rmse"].shape == (2,) and np.isnan(res.metrics["rmse"][1])
    assert np.isfinite(res.metrics["aic"])  # on channel 0's point samples
    e0 = np.asarray(res.residuals)[:, 0][seen]  # (the FPE too, with theta's and x0's 5)
    fpe = np.mean(e0**2) * (1 + 5 / e0.size) / (1 - 5 / e0.size)
    assert res.metrics["fpe"] == pytest.approx(fpe, rel=1e-9)
    bic = e0.size * np.log(np.mean(e0**2)) + 5 * np.log(e0.size)  # (point samples only too)
    assert res.metrics["bic"] == pytest.approx(bic, rel=1e-9)
    assert "x0[1]" in str(res) and "x0[2]" not in str(res)
    back = oj.load_result(res.save(tmp_path / "agg.npz"), model=MODEL)
    np.testing.assert_array_equal(back.x0, res.x0)
    np.testing.assert_array_equal(back.covariance, res.covariance)


def test_fit_refuses_window():
    x0, u, z, y = data()
    agg = aggregate_of("sum", readings("sum", y))
    with pytest.raises(ValueError, match="window"):
        oj.fit(MODEL, THETA, x0, u, z, missing="mask", aggregate=agg, window=20)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: oj.Aggregate(-1, [(0, 2)], [1.0]), "channel"),
        (lambda: oj.Aggregate(0, [(3, 3)], [1.0]), "start < stop"),
        (lambda: oj.Aggregate(0, [(-1, 3)], [1.0]), "start < stop"),
        (lambda: oj.Aggregate(0, [(0, 3), (1, 4)], [1.0]), "one reading per interval"),
        (lambda: oj.Aggregate(0, [(0, 1)], [1.0], kind="integral"), "two samples"),
        (lambda: oj.Aggregate(0, [(0, 2)], [1.0], kind="median"), "kind"),
        (lambda: oj.Aggregate(0, values=[1.0], matrix=np.ones(4)), "2-D"),
        (lambda: oj.Aggregate(0, values=[1.0, 2.0], matrix=np.ones((1, 4))), "one reading per row"),
        (lambda: oj.Aggregate(0, values=[1.0], matrix=np.zeros((1, 4))), "no nonzero"),
        (lambda: oj.Aggregate(0, [(0, 2)], [1.0], matrix=np.ones((1, 4))), "exactly one"),
        (lambda: oj.Aggregate(0, [(0, 2)], [1.0], weight=-1.0), "non-negative"),
    ],
)
def test_bad_aggregate(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_an_aggregate_takes_numpy_integers_and_refuses_a_bool_weight():
    """Intervals from a NumPy array print as plain integers (they printed np.int64(0));
    `weight=True` is refused as `channel=True` is (it was read as 1)."""
    a = oj.Aggregate(1, np.array([[0, 5], [5, 10]]), [1.0, 2.0])
    assert repr(a) == "Aggregate(channel=1, intervals=[(0, 5), (5, 10)], kind='mean', 2 readings)"
    with pytest.raises(TypeError, match="`weight` must be a number"):
        oj.Aggregate(1, [(0, 5)], [1.0], weight=True)


@pytest.mark.parametrize(
    "agg, match",
    [
        (oj.Aggregate(2, [(0, 2)], [1.0]), "out of range"),
        (oj.Aggregate(1, [(30, 41)], [1.0]), "ends past"),
        (oj.Aggregate(1, values=[1.0], matrix=np.ones((1, 39))), "one column per sample"),
        ([oj.Aggregate(1, [(0, 2)], [1.0]), "x"], "Aggregate"),
        # (None stands for a record without readings in a list per record)
        ([oj.Aggregate(1, [(0, 2)], [1.0]), None], "one entry per record"),
        (oj.Aggregate(1, [(0, 2)], [np.nan]), "missing='mask'"),
    ],
)
def test_bad_aggregate_for_the_data(agg, match):
    x0, u, z, _ = data()
    z = np.nan_to_num(z)
    with pytest.raises((ValueError, TypeError), match=match):
        oj.loss(MODEL, THETA, x0, u, z, aggregate=agg)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        # They were NumPy's "could not convert string to float" and float()'s TypeError.
        ({"values": ["a", "b"]}, "`values` must hold real numbers"),
        ({"values": {"a": 1}}, "`values` must hold real numbers"),
        ({"values": [1.0, 2.0], "weight": "heavy"}, "`weight` must hold real numbers"),
    ],
)
def test_aggregate_names_values_and_weight_that_are_not_numbers(kwargs, match):
    with pytest.raises(ValueError, match=match):
        oj.Aggregate(0, [(0, 2), (2, 4)], **kwargs)


@pytest.mark.parametrize("z", [np.zeros(4), np.zeros((4, 1, 1))])
def test_predict_needs_z_of_shape_t_by_n_z(z):
    """A 1-D z was an IndexError."""
    with pytest.raises(ValueError, match=r"`z` must have shape \(T, n_z\)"):
        oj.Aggregate(0, [(0, 2)], [1.0]).predict(z)


def test_predict_names_z_for_the_length_of_t():
    """`t` of the wrong length was checked against "each sample of `u`", an argument
    `predict` does not have."""
    agg = oj.Aggregate(0, [(0, 3)], [1.0], kind="time_mean")
    with pytest.raises(ValueError, match=r"one time stamp per row of `z` \(T = 6\)"):
        agg.predict(np.zeros((6, 1)), np.arange(5.0))


@pytest.mark.parametrize(
    "t, match",
    [
        (-np.arange(6.0), "strictly increasing"),  # it built a matrix of negative intervals
        (np.array([0.0, 1.0, 1.0, 2.0, 3.0, 4.0]), "strictly increasing"),
        (np.array([0.0, 1.0, np.nan, 3.0, 4.0, 5.0]), "NaN or inf"),
        # (`operator` takes no `u`: it named one)
        (np.arange(5.0), r"shape \(6,\): one time stamp per sample of the record"),
    ],
)
def test_operator_checks_the_sample_times(t, match):
    agg = oj.Aggregate(0, [(0, 3), (3, 6)], [1.0, 2.0], kind="time_mean")
    with pytest.raises(ValueError, match=f"`t`.*{match}|{match}.*`t`"):
        agg.operator(6, t=t)


@pytest.mark.parametrize("kind", ["bogus", None])
def test_kind_is_checked_with_a_matrix_too(kind):
    """`kind` was ignored when `matrix` was given."""
    with pytest.raises(ValueError, match="`kind` must be one of"):
        oj.Aggregate(0, matrix=np.ones((1, 4)) / 4, values=[0.1], kind=kind)


def test_batch_needs_one_entry_per_record():
    x0, u, z, y = data()
    agg = aggregate_of("sum", readings("sum", y))
    X0, U, Z = np.stack([x0, x0]), np.stack([u, u]), np.stack([z, z])
    with pytest.raises(ValueError, match="one per trajectory"):
        oj.loss(MODEL, THETA, X0, U, Z, missing="mask", aggregate=agg)
    with pytest.raises(ValueError, match="one entry per trajectory"):
        oj.loss(MODEL, THETA, X0, U, Z, missing="mask", aggregate=[agg])


def test_penalty_sees_the_model_states_only():
    """A penalty h(x, theta) of eq. (21) gets the model's own states, not the accumulators
    (h = sum x^2 would differ), in the loss and in the gradient."""
    x0, u, z, y = data()
    v = readings("overlap", y)
    agg = aggregate_of("overlap", v)
    A, _ = rows("overlap")

    def h(x, th):
        return jnp.sum(x**2) + 0.1 * th["a"] ** 2

    def ref(theta, x0):
        def f(x, u_k):
            return step(x, u_k, theta), h(x, theta)

        _, hs = jax.lax.scan(f, x0, jnp.asarray(u))
        base = direct_loss(theta, x0, jnp.asarray(u), jnp.asarray(z), A, v, Q[1])
        return base + 0.7 * jnp.sum(hs) / T

    x0e = jnp.asarray(x0 + 0.1)
    kw = dict(weight=Q, missing="mask", aggregate=agg, penalty=h, penalty_weight=0.7)
    C, (g_theta, g_x0) = oj.value_and_grad(MODEL, THETA_EVAL, x0e, u, z, **kw)
    C_ref, (gt_ref, gx_ref) = jax.value_and_grad(ref, argnums=(0, 1))(THETA_EVAL, x0e)
    np.testing.assert_allclose(oj.loss(MODEL, THETA_EVAL, x0e, u, z, **kw), C_ref, rtol=1e-12)
    np.testing.assert_allclose(C, C_ref, rtol=1e-12)
    np.testing.assert_allclose(g_x0, gx_ref, rtol=1e-12)
    np.testing.assert_allclose(ravel_pytree(g_theta)[0], ravel_pytree(gt_ref)[0], rtol=1e-12)


def test_outputs_never_sampled_together_next_to_an_aggregate_have_no_aic():
    """Point samples of two outputs that never share a sample, a third output measured
    only in aggregate: the fit solved, then raised ("`mask` leaves no sample where every
    output is measured") from its AIC. Without the aggregate the AIC is NaN; with it too."""
    model = oj.Model(
        lambda x, u, th: th["a"] * x + th["b"] * u,
        lambda x, u, th: jnp.concatenate([x, 2.0 * x, x + u]),
    )
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    _, y = oj.simulate(model, {"a": 0.9, "b": 0.5}, np.array([1.0]), u)
    y = np.asarray(y)
    z = np.full((200, 3), np.nan)
    even = np.arange(200) % 2 == 0
    z[even, 1] = y[even, 1] + 0.1 * rng.standard_normal(even.sum())
    z[~even, 2] = y[~even, 2] + 0.1 * rng.standard_normal((~even).sum())
    spans = [(k, k + 20) for k in range(0, 200, 20)]
    agg = oj.Aggregate(0, spans, y[:, 0].reshape(10, 20).mean(axis=1))
    kw = dict(missing="mask")
    plain = oj.fit(model, {"a": 0.8, "b": 0.4}, np.array([0.5]), u, z, **kw)
    r = oj.fit(model, {"a": 0.8, "b": 0.4}, np.array([0.5]), u, z, aggregate=agg, **kw)
    for result in (plain, r):
        assert result.success
        assert np.isnan(result.metrics["aic"]) and np.isnan(result.metrics["fpe"])
    assert "AIC nan (fewer samples measure every output than there are outputs)" in str(r)
