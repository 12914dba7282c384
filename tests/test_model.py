"""`Model`, `Model.from_ode`, `simulate` and `loss`: semantics, integrator order, jit."""

import dataclasses
import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    PROBLEMS,
    diffrax_rollout,
    fitted_order,
    lotka_volterra_rhs,
    own_step,
    pendulum_rhs,
    tree_allclose,
)

import oneshot_jax as oj

#
# simulate
#


def _linear_model():
    A = jnp.array([[0.9, 0.2, 0.0], [-0.1, 0.8, 0.3], [0.0, 0.0, 0.5]])
    B = jnp.array([[1.0, 0.0], [0.0, 0.5], [0.2, 0.1]])
    step = lambda x, u, th: th * (A @ x) + B @ u  # noqa: E731
    observe = lambda x, u, th: jnp.stack([x[0] + th * u[1], x[1] * x[2]])  # noqa: E731
    return oj.Model(step, observe)


@pytest.fixture(scope="module")
def linear():
    rng = np.random.default_rng(0)
    T = 12
    return dict(
        model=_linear_model(),
        theta=jnp.asarray(0.95),
        x0=jnp.asarray(rng.standard_normal(3)),
        u=jnp.asarray(rng.standard_normal((T, 2))),
    )


@pytest.mark.parametrize("case", ["pendulum", "observe_u_theta_unused_entry", "linear"])
def test_simulate_semantics(case, linear):
    if case == "linear":
        model, theta, x0, u = linear["model"], linear["theta"], linear["x0"], linear["u"]
    else:
        p = PROBLEMS[case]()
        model, theta, x0, u = p.model(), p.theta, p.x0, p.u
    x, z = oj.simulate(model, theta, x0, u)
    T = u.shape[0]
    n_z = model.observe(x0, u[0], theta).shape[0]
    assert x.shape == (T, x0.shape[0]) and z.shape == (T, n_z)
    assert x.dtype == z.dtype == jnp.float64
    # x[0] = x0 exactly; x[k+1] = step(x[k], u[k]); z[k] = observe(x[k], u[k]) (eq. 2).
    assert np.array_equal(x[0], x0)
    for k in range(T - 1):
        assert tree_allclose(x[k + 1], model.step(x[k], u[k], theta), rtol=1e-12, atol=1e-15)
    for k in range(T):
        assert tree_allclose(z[k], model.observe(x[k], u[k], theta), rtol=1e-12, atol=1e-15)


def test_simulate_matches_own_rk4_loop():
    p = PROBLEMS["pendulum"]()
    step = own_step(p.rhs, p.dt, p.substeps)
    x, _ = oj.simulate(p.model(), p.theta, p.x0, p.u)
    x_ref = [p.x0]
    for k in range(p.u.shape[0] - 1):
        x_ref.append(step(x_ref[-1], p.u[k], p.theta))
    assert tree_allclose(x, jnp.stack(x_ref), rtol=1e-12, atol=1e-14)


def test_last_input_only_reaches_last_output(linear):
    # T inputs give T states x_0..x_{T-1}: u_{T-1} feeds no state, only z_{T-1} (observe
    # reads u here).
    m, th, x0, u = linear["model"], linear["theta"], linear["x0"], linear["u"]
    x, z = oj.simulate(m, th, x0, u)
    x2, z2 = oj.simulate(m, th, x0, u.at[-1].add(1.0))
    assert np.array_equal(x, x2)
    assert np.array_equal(z[:-1], z2[:-1]) and not np.array_equal(z[-1], z2[-1])


def test_single_sample_horizon(linear):
    m, th, x0, u = linear["model"], linear["theta"], linear["x0"], linear["u"]
    x, z = oj.simulate(m, th, x0, u[:1])
    assert x.shape == (1, 3) and np.array_equal(x[0], x0)
    assert tree_allclose(z[0], m.observe(x0, u[0], th))


def test_simulate_batched_equals_per_trajectory():
    p = PROBLEMS["multi_trajectory"]()
    model = p.model()
    x, z = oj.simulate(model, p.theta, p.x0, p.u)
    N, T = p.u.shape[:2]
    assert x.shape == (N, T, 2) and z.shape == (N, T, 1)
    for i in range(N):
        x_i, z_i = oj.simulate(model, p.theta, p.x0[i], p.u[i])
        assert tree_allclose(x[i], x_i, rtol=1e-13, atol=1e-15)
        assert tree_allclose(z[i], z_i, rtol=1e-13, atol=1e-15)


def test_default_observe_is_identity(linear):
    step = _linear_model().step
    model = oj.Model(step)
    x, z = oj.simulate(model, linear["theta"], linear["x0"], linear["u"])
    assert np.array_equal(x, z)


def test_integer_inputs_are_promoted():
    model = oj.Model(lambda x, u, th: th * x + u)
    x, z = oj.simulate(model, 2, jnp.array([1, 2]), jnp.ones((3, 2), dtype=jnp.int32))
    assert x.dtype == jnp.float64
    assert np.array_equal(x, jnp.array([[1.0, 2.0], [3.0, 5.0], [7.0, 11.0]]))


#
# loss
#


def _hand_loss(model, theta, x0, u, z, Q, h, lam):
    """numpy: mean over trajectories of (1/T) sum_k e_k^T Q e_k + lam h(x_k, theta)."""
    x0, u, z = (np.asarray(a) for a in (x0, u, z))
    if x0.ndim == 1:
        x0, u, z = x0[None], u[None], z[None]
    N, T = u.shape[:2]
    total = 0.0
    for i in range(N):
        x = x0[i]
        traj = 0.0
        for k in range(T):
            if k > 0:
                x = np.asarray(model.step(x, u[i, k - 1], theta))
            e = np.asarray(model.observe(x, u[i, k], theta)) - z[i, k]
            Qm = np.eye(e.size) if Q is None else (np.diag(Q) if np.ndim(Q) == 1 else Q)
            traj += e @ Qm @ e + (0.0 if h is None else lam * float(h(x, theta)))
        total += traj / T
    return total / N


@pytest.mark.parametrize(
    "weight, with_penalty, batched",
    [
        ("identity", False, False),
        ("diagonal", False, True),
        ("matrix", False, False),
        ("identity", True, True),
        ("diagonal", True, False),
        ("matrix", True, True),
    ],
)
def test_loss_equals_hand_formula(weight, with_penalty, batched, linear):
    rng = np.random.default_rng(1)
    m, th = linear["model"], linear["theta"]
    x0, u = linear["x0"], linear["u"]
    if batched:
        x0 = jnp.stack([x0, -x0, 2 * x0])
        u = jnp.stack([u, jnp.flip(u, 0), 0.5 * u])
    z = jnp.asarray(rng.standard_normal((*u.shape[:-1], 2)))
    Q = {
        "identity": None,
        "diagonal": jnp.array([2.0, 0.5]),
        "matrix": jnp.array([[2.0, 0.7], [0.7, 1.0]]),
    }[weight]
    h = (lambda x, th: jnp.exp(x[0] - 1.0) + th**2) if with_penalty else None  # noqa: E731
    C = oj.loss(m, th, x0, u, z, weight=Q, penalty=h, penalty_weight=0.3)
    assert C.shape == () and C.dtype == jnp.float64
    assert np.isclose(float(C), _hand_loss(m, th, x0, u, z, Q, h, 0.3), rtol=1e-12, atol=0)
    C_vg, _ = oj.value_and_grad(m, th, x0, u, z, weight=Q, penalty=h, penalty_weight=0.3)
    assert np.isclose(float(C_vg), float(C), rtol=1e-12, atol=0)


def test_loss_is_zero_on_noise_free_data(linear):
    m, th, x0, u = linear["model"], linear["theta"], linear["x0"], linear["u"]
    _, z = oj.simulate(m, th, x0, u)
    # Zero up to round-off (simulate and loss are compiled separately).
    assert float(oj.loss(m, th, x0, u, z)) < 1e-28
    C, (g_theta, g_x0) = oj.value_and_grad(m, th, x0, u, z)
    assert float(C) < 1e-28 and abs(float(g_theta)) < 1e-13 and np.all(np.abs(g_x0) < 1e-13)


#
# Model.from_ode: the integrators
#


@pytest.mark.parametrize(
    "method, substeps",
    [("rk4", 1), ("rk4", 3), ("rk4", 12), ("euler", 1), ("euler", 5), ("euler", 10)],
)
def test_from_ode_step_is_the_integrator(method, substeps):
    # substeps > 8 also exercises the fori_loop path.
    theta = jnp.array([9.81, 0.4])
    model = oj.Model.from_ode(pendulum_rhs, 0.3, method=method, substeps=substeps)
    x, u = jnp.array([1.0, -0.5]), jnp.array([0.7])
    expected = own_step(pendulum_rhs, 0.3, substeps, method)(x, u, theta)
    assert tree_allclose(model.step(x, u, theta), expected, rtol=1e-13, atol=1e-15)
    assert tree_allclose(jax.jit(model.step)(x, u, theta), expected, rtol=1e-13, atol=1e-15)


ORDER_PROBLEMS = {
    "pendulum": (pendulum_rhs, jnp.array([9.81, 0.4]), jnp.array([1.0, 0.0]), 0.25),
    "lotka_volterra": (
        lotka_volterra_rhs,
        jnp.array([1.1, 0.4, 0.1, 0.4]),
        jnp.array([2.0, 1.0]),
        0.5,
    ),
}
# A held input that changes from sample to sample, over 5 samples (4 integration intervals).
ORDER_INPUT = jnp.stack([0.3 * jnp.sin(jnp.arange(5.0)), 0.1 * jnp.cos(jnp.arange(5.0))], axis=1)


@functools.cache
def _reference_solution(name):
    """Tsit5 with rtol = atol = 1e-12 under the same zero-order hold, at the last sample."""
    rhs, theta, x0, dt = ORDER_PROBLEMS[name]
    xs = diffrax_rollout(
        rhs,
        dt,
        1,
        theta,
        x0,
        ORDER_INPUT,
        solver=diffrax.Tsit5(),
        controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
    )
    return xs[-1]


@pytest.mark.parametrize(
    "method, substeps, lo, hi",
    [("rk4", (1, 2, 4, 8), 3.7, 4.3), ("euler", (16, 32, 64, 128), 0.9, 1.1)],
)
@pytest.mark.parametrize("name", list(ORDER_PROBLEMS))
def test_convergence_order(name, method, substeps, lo, hi):
    # Global error at the end of the horizon against Tsit5; step size h = dt / substeps.
    rhs, theta, x0, dt = ORDER_PROBLEMS[name]
    x_ref = _reference_solution(name)
    errors = []
    for s in substeps:
        model = oj.Model.from_ode(rhs, dt, method=method, substeps=s)
        x, _ = oj.simulate(model, theta, x0, ORDER_INPUT)
        errors.append(float(jnp.linalg.norm(x[-1] - x_ref)))
    hs = [dt / s for s in substeps]
    order = fitted_order(hs, errors)
    print(f"{name} {method}: fitted order {order:.3f}, errors {errors}")
    assert lo <= order <= hi, f"fitted order {order:.3f}, errors {errors}"
    assert min(errors) > 1e-10  # the reference is far more accurate than the finest run


#
# jit and immutability
#


def test_model_is_jittable():
    p = PROBLEMS["observe_u_theta_unused_entry"]()
    model = p.model()
    expected = oj.simulate(model, p.theta, p.x0, p.u)

    # The model as an argument of eqx.filter_jit.
    f = eqx.filter_jit(lambda m, th, x0: oj.simulate(m, th, x0, p.u))
    assert tree_allclose(f(model, p.theta, p.x0), expected, rtol=1e-13, atol=1e-15)
    # The model as a static (hashable) argument, or closed over, under jax.jit.
    g = jax.jit(lambda m, th, x0: oj.simulate(m, th, x0, p.u), static_argnums=0)
    assert tree_allclose(g(model, p.theta, p.x0), expected, rtol=1e-13, atol=1e-15)
    h = jax.jit(lambda th, x0: oj.simulate(model, th, x0, p.u))
    assert tree_allclose(h(p.theta, p.x0), expected, rtol=1e-13, atol=1e-15)
    # loss and value_and_grad traced under jit give the eager answer.
    k = jax.jit(lambda th, x0: oj.loss(model, th, x0, p.u, p.z))
    assert np.isclose(
        float(k(p.theta, p.x0)), float(oj.loss(model, p.theta, p.x0, p.u, p.z)), rtol=1e-13, atol=0
    )


def test_model_is_immutable():
    model = oj.Model.from_ode(pendulum_rhs, 0.1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.step = lambda x, u, th: x  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.observe = lambda x, u, th: x  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.step.dt = 0.2  # type: ignore[misc]
    # Equal constructions are equal and hash alike (usable as a static jit argument).
    other = oj.Model.from_ode(pendulum_rhs, 0.1)
    assert model == other and hash(model) == hash(other)
    assert model != oj.Model.from_ode(pendulum_rhs, 0.2)


def test_an_unhashable_callable_is_refused_naming_it():
    """A plain @dataclass (eq=True sets __hash__ to None) cannot be a static argument of
    the compiled calls: refused when the model is built, not with JAX's error."""

    @dataclasses.dataclass
    class Step:
        a: float

        def __call__(self, x, u, theta):
            return self.a * x + theta["b"] * u

    with pytest.raises(TypeError, match="`step` must be hashable"):
        oj.Model(Step(0.9))
    with pytest.raises(TypeError, match="`observe` must be hashable"):
        oj.Model(lambda x, u, th: x, Step(1.0))
    with pytest.raises(TypeError, match="`rhs` must be hashable"):
        oj.Model.from_ode(Step(0.9), dt=0.1)

    @dataclasses.dataclass(frozen=True)
    class Frozen:
        a: float

        def __call__(self, x, u, theta):
            return self.a * x + theta["b"] * u

    u = np.ones((5, 1))
    x, _ = oj.simulate(oj.Model(Frozen(0.5)), {"b": 1.0}, np.zeros(1), u)  # hashable: runs
    assert np.allclose(x[:, 0], [0.0, 1.0, 1.5, 1.75, 1.875])
