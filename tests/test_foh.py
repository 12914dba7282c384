"""The first-order hold (`input="foh"`): exact gradients and sensitivities, and the order
of convergence of the integrators with u interpolated linearly between the samples.

The references are written here: a foh RK4 / Euler rollout in `lax.scan` that evaluates
the input at a stage time t as (1 - t/dt) u[k] + (t/dt) u[k+1] (the library writes
u[k] + t (u[k+1] - u[k]) / dt), differentiated by JAX's autodiff; and diffrax's Tsit5 at
tight tolerances driven by the piecewise-linear (or the underlying smooth) input.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fitted_order
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.internal import Cost, FitProblem, Params

DT = 0.1
THETA = {"k": jnp.array([4.0, 1.5]), "c": jnp.array(0.3), "b": jnp.array([1.0, -0.4])}


def rhs(x, u, th):
    """A forced Duffing oscillator with a second, coupled state and two inputs."""
    q, v, w = x
    return jnp.stack(
        [
            v,
            -th["k"][0] * q - th["c"] * v - q**3 + th["b"][0] * u[0] + 0.2 * w,
            -th["k"][1] * w + th["b"][1] * u[1] * q,
        ]
    )


def observe(x, u, th):
    """Two outputs that depend on the input and on theta too."""
    return jnp.stack([x[0] + 0.1 * th["c"] * u[0], x[1] * x[2] + th["b"][1] * u[1]])


def own_foh_rollout(theta, x0, u, *, method="rk4", substeps=2, dt=DT):
    """States x[0..T-1] with u linear between the samples, written independently."""
    h = dt / substeps

    def u_at(uk, uk1, t):
        s = t / dt
        return (1.0 - s) * uk + s * uk1

    def interval(x, pair):
        uk, uk1 = pair
        for j in range(substeps):
            t = j * h
            if method == "euler":
                x = x + h * rhs(x, u_at(uk, uk1, t), theta)
                continue
            k1 = rhs(x, u_at(uk, uk1, t), theta)
            k2 = rhs(x + (h / 2) * k1, u_at(uk, uk1, t + h / 2), theta)
            k3 = rhs(x + (h / 2) * k2, u_at(uk, uk1, t + h / 2), theta)
            k4 = rhs(x + h * k3, u_at(uk, uk1, t + h), theta)
            x = x + h * (k1 + 2 * k2 + 2 * k3 + k4) / 6
        return x, x

    _, xs = jax.lax.scan(interval, x0, (u[:-1], u[1:]))
    return jnp.concatenate([x0[None], xs])


def own_outputs(theta, x0, u, **kw):
    xs = own_foh_rollout(theta, x0, u, **kw)
    return jax.vmap(observe, in_axes=(0, 0, None))(xs, u, theta)


def own_loss(theta, x0, u, z, **kw):
    """C of eq. (4)-(5) with Q = I: (1/T) sum_k |z_hat_k - z_k|^2."""
    e = own_outputs(theta, x0, u, **kw) - z
    return jnp.sum(e**2) / u.shape[0]


@functools.cache
def data(T=30, seed=0):
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    u = np.stack([np.sin(2.0 * t) + 0.3 * rng.standard_normal(T), np.cos(1.3 * t)], axis=1)
    x0 = np.array([0.4, -0.2, 0.1])
    z = own_outputs(THETA, jnp.asarray(x0), jnp.asarray(u)) + 0.05 * rng.standard_normal((T, 2))
    # Evaluate away from the data's parameters so that residuals and gradients are generic.
    theta = jax.tree_util.tree_map(lambda a: a * (1 + 0.1 * rng.standard_normal(a.shape)), THETA)
    return theta, jnp.asarray(x0 + 0.05), jnp.asarray(u), jnp.asarray(z)


def foh_model(method, substeps=2):
    return oj.Model.from_ode(
        rhs, DT, method=method, substeps=substeps, observe=observe, input="foh"
    )


@functools.cache
def autodiff_gradient(method):
    theta, x0, u, z = data()
    grad = jax.value_and_grad(functools.partial(own_loss, method=method), argnums=(0, 1))
    return eqx.filter_jit(grad)(theta, x0, u, z)


@functools.cache
def autodiff_jacobian(method):
    """The residuals r = (z_hat - z) / sqrt(T) and their Jacobians in (flat theta, x0)."""
    theta, x0, u, z = data()
    flat, unravel = ravel_pytree(theta)

    def residuals(pt, px):
        e = own_outputs(unravel(pt), px, u, method=method) - z
        return (e / jnp.sqrt(u.shape[0])).reshape(-1)

    return residuals(flat, x0), jax.jit(jax.jacfwd(residuals, argnums=(0, 1)))(flat, x0)


@pytest.mark.parametrize("strategy", ["jacobian", "vjp"])
@pytest.mark.parametrize("method", ["rk4", "euler"])
def test_foh_one_shot_gradient_equals_autodiff(method, strategy):
    theta, x0, u, z = data()
    C, (g_theta, g_x0) = oj.value_and_grad(foh_model(method), theta, x0, u, z, strategy=strategy)
    C_ref, (gt_ref, gx_ref) = autodiff_gradient(method)
    assert float(C) == pytest.approx(float(C_ref), rel=1e-12)
    for key in THETA:
        np.testing.assert_allclose(g_theta[key], gt_ref[key], rtol=1e-10, atol=0)
    np.testing.assert_allclose(g_x0, gx_ref, rtol=1e-10, atol=0)
    # The hold matters: the same model under "zoh" gives another loss.
    zoh = oj.Model.from_ode(rhs, DT, method=method, substeps=2, observe=observe)
    assert abs(float(oj.loss(zoh, theta, x0, u, z)) - float(C)) > 1e-6 * float(C)


def one_trajectory_problem(model, theta, x0, u, z):
    """A FitProblem with every entry of theta and x0 free, for one trajectory."""
    flat, unravel = ravel_pytree(theta)
    return FitProblem(
        model=model,
        cost=Cost(None, None, jnp.zeros((), flat.dtype)),
        u=u[None],
        z=z[None],
        theta_base=flat,
        theta_free=tuple(range(flat.size)),
        unravel=unravel,
        x0_base=x0[None],
        x0_free=tuple(range(x0.size)),
        project=None,
        lower=None,
        upper=None,
    )


@pytest.mark.parametrize("strategy", ["jacobian", "vjp"])
@pytest.mark.parametrize("method", ["rk4", "euler"])
def test_foh_sensitivities_equal_autodiff(method, strategy):
    theta, x0, u, z = data()
    problem = one_trajectory_problem(foh_model(method), theta, x0, u, z)
    flat, _ = ravel_pytree(theta)
    lin = eqx.filter_jit(lambda p, s: p.jacobian(Params(flat, x0[None]), s))(problem, strategy)
    r_ref, (Jt_ref, Jx_ref) = autodiff_jacobian(method)
    np.testing.assert_allclose(lin.r[0], r_ref, rtol=1e-12, atol=1e-15)
    # Column by column: a norm over the whole matrix would hide a wrong small column.
    for J, J_ref in ((lin.Jt[0], Jt_ref), (lin.Jx[0], Jx_ref)):
        J, J_ref = np.asarray(J), np.asarray(J_ref)
        assert J.shape == J_ref.shape
        ref = np.linalg.norm(J_ref, axis=0)
        assert np.all(ref > 0)
        assert np.all(np.linalg.norm(J - J_ref, axis=0) <= 1e-10 * ref)


#
# Order of convergence.
#

ORDER_THETA = jnp.array([4.0, 0.3, 1.0])
ORDER_X0 = jnp.array([0.5, 0.0])
T_END = 2.0


def duffing(x, u, th):
    q, v = x
    return jnp.stack([v, -th[0] * q - th[1] * v - th[2] * q**3 + u[0]])


def smooth_input(t):
    return jnp.stack([jnp.sin(3.0 * t) + 0.5 * jnp.cos(5.0 * t)])


def _tsit5(vector_field, t0, t1, y0, args):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        diffrax.Tsit5(),
        t0,
        t1,
        (t1 - t0) / 10,
        y0,
        args=args,
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        max_steps=100_000,
    )
    return sol.ys[-1]


@functools.cache
def piecewise_linear_reference(dt):
    """x(T_END) of the ODE driven by the linear interpolant of the samples u(k dt): one
    tight Tsit5 solve per interval (the input is smooth inside each)."""
    T = int(round(T_END / dt)) + 1
    u = jax.vmap(smooth_input)(dt * jnp.arange(T))

    def field(t, y, args):
        uk, uk1 = args
        return duffing(y, uk + (t / dt) * (uk1 - uk), ORDER_THETA)

    def interval(x, pair):
        x = _tsit5(field, 0.0, dt, x, pair)
        return x, None

    x, _ = jax.lax.scan(interval, ORDER_X0, (u[:-1], u[1:]))
    return u, x


@pytest.mark.parametrize(
    "method, substeps, lo, hi",
    [("rk4", (1, 2, 4, 8), 3.7, 4.3), ("euler", (16, 32, 64, 128), 0.9, 1.1)],
)
def test_foh_integrator_order(method, substeps, lo, hi):
    """At fixed samples (dt = 0.25), h = dt / substeps -> 0 converges to the ODE driven by
    the samples' linear interpolant at the integrator's order; "zoh" converges to another
    ODE (u held), so its error against this reference stays put."""
    dt = 0.25
    u, x_ref = piecewise_linear_reference(dt)
    errors, zoh_errors = [], []
    for s in substeps:
        for hold, out in (("foh", errors), ("zoh", zoh_errors)):
            model = oj.Model.from_ode(duffing, dt, method=method, substeps=s, input=hold)
            x, _ = oj.simulate(model, ORDER_THETA, ORDER_X0, u)
            out.append(float(jnp.linalg.norm(x[-1] - x_ref)))
    order = fitted_order([dt / s for s in substeps], errors)
    assert lo <= order <= hi, f"fitted order {order:.3f}, errors {errors}"
    assert min(errors) > 1e-11  # the reference is far more accurate than the finest run
    assert zoh_errors[-1] > 0.5 * zoh_errors[0], zoh_errors
    assert zoh_errors[-1] > 10 * errors[-1], (zoh_errors, errors)


@functools.cache
def smooth_reference():
    """x(T_END) of the ODE driven by the smooth input itself."""
    return _tsit5(
        lambda t, y, args: duffing(y, smooth_input(t), ORDER_THETA), 0.0, T_END, ORDER_X0, None
    )


@pytest.mark.parametrize("hold, lo, hi", [("zoh", 0.9, 1.1), ("foh", 1.9, 2.1)])
def test_hold_order_against_a_smooth_input(hold, lo, hi):
    """Sampling a smooth u(t) at dt -> 0, one RK4 step per sample: the hold limits the
    order. Holding u[k] is off by O(dt) inside the interval (order 1); the linear
    interpolant is exact at the samples and off by dt^2 u''/8 at the RK4 midpoint, so
    "foh" is order 2 against the smooth input (and order 4 against its interpolant,
    `test_foh_integrator_order`)."""
    x_ref = smooth_reference()
    dts = (0.1, 0.05, 0.025, 0.0125)
    errors = []
    for dt in dts:
        u = jax.vmap(smooth_input)(dt * jnp.arange(int(round(T_END / dt)) + 1))
        model = oj.Model.from_ode(duffing, dt, input=hold)
        x, _ = oj.simulate(model, ORDER_THETA, ORDER_X0, u)
        errors.append(float(jnp.linalg.norm(x[-1] - x_ref)))
    order = fitted_order(dts, errors)
    assert lo <= order <= hi, f"fitted order {order:.3f}, errors {errors}"


def test_foh_step_sees_pairs_and_checks_input():
    model = foh_model("rk4")
    u = jnp.arange(8.0).reshape(4, 2)
    pairs = model.step_inputs(u)
    assert pairs.shape == (3, 2, 2)
    np.testing.assert_array_equal(pairs[:, 0], u[:-1])
    np.testing.assert_array_equal(pairs[:, 1], u[1:])
    # A constant input: "foh" and "zoh" are the same discretisation.
    theta, x0, _, _ = data()
    u_const = jnp.ones((10, 2)) * jnp.array([0.3, -0.7])
    zoh = oj.Model.from_ode(rhs, DT, substeps=2, observe=observe)
    np.testing.assert_allclose(
        oj.simulate(model, theta, x0, u_const)[0],
        oj.simulate(zoh, theta, x0, u_const)[0],
        rtol=1e-14,
        atol=1e-15,
    )
    with pytest.raises(ValueError, match="`input` must be 'zoh' or 'foh'"):
        oj.Model.from_ode(rhs, DT, input="linear")
    with pytest.raises(ValueError, match="`input` must be 'zoh' or 'foh'"):
        oj.ode_step(rhs, x0, u[:2], theta, DT, input="cubic")
