"""Parallel-in-time rollout, gradient and sensitivities against the sequential library.

Every parallel result is compared with the sequential path it replaces, in float64 to
1e-12 (norm-wise relative, per leaf): the rollout with `oneshot_jax._simulate.rollout`
(`lax.scan`), the gradient with `oneshot_jax.value_and_grad` (strategies "jacobian" and
"vjp"), the residual Jacobian with `oneshot_jax._sensitivity.trajectory_jacobian`. The
building blocks (linear recurrences, the ELK step) are checked against Python loops and a
dense least-squares solve. Each model also asserts which solve produced its states, so a
test of the parallel path cannot pass on the sequential fallback.
"""

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_tree_rel_close, duffing_rhs, motor_observe, motor_rhs
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.internal import (
    DAMPED,
    NEWTON,
    SEQUENTIAL,
    Cost,
    diagonal_elk_increment,
    diagonal_linear_recurrence,
    elk_increment,
    linear_recurrence,
    matrix_linear_recurrence,
    newton_rollout,
    reverse_diagonal_linear_recurrence,
    reverse_linear_recurrence,
    rollout,
    trajectory_jacobian,
    value_and_grad_of_states,
)


def parallel_value_and_grad(model, cost, theta, x0, u, z, *, strategy):
    """The states by the strategy's parallel rollout, then the one-shot recursion by its
    associative scans; with the rollout's info."""
    xs, info = strategy.rollout(model, theta, x0, u)
    return value_and_grad_of_states(model, cost, theta, xs, u, z, strategy), info


def parallel_sensitivities(model, cost, theta_of, p_theta, x0_of, p_x0, u, z, *, scale, strategy):
    """The states by the strategy's parallel rollout, then the sensitivities by its
    associative scans; with the rollout's info."""
    xs, info = strategy.rollout(model, theta_of(p_theta), x0_of(p_x0), u)
    args = (model, cost, theta_of, p_theta, x0_of, p_x0, u, z)
    return trajectory_jacobian(*args, scale=scale, strategy=strategy, xs=xs), info


RTOL = 1e-12

#
# Models: each returns (model, theta, x0, u, z, weight, penalty, penalty_weight).
#


def satellite_rhs(w, M, theta):
    """Euler's equations I w' = M - w x (I w), diagonal inertia (the paper's Section 4)."""
    inertia = theta["I"]
    return (M - jnp.cross(w, inertia * w)) / inertia


def satellite(T=200, dtype=jnp.float64):
    rng = np.random.default_rng(0)
    model = oj.Model.from_ode(satellite_rhs, 0.1)
    theta = {"I": jnp.array([0.05, 0.03, 0.01], dtype)}
    x0 = jnp.array([9.915e-6, -1.102e-3, 1.3179e-5], dtype)
    u = jnp.asarray(rng.normal(1e-5, 1e-7, (T, 3)), dtype)
    z = jnp.asarray(rng.normal(0.0, 1e-3, (T, 3)), dtype)
    return model, theta, x0, u, z, None, None, 1.0


def duffing(T=200, damping=0.3):
    """A damped Duffing oscillator (n_x = 2, RK4 at dt = 0.05), observed through q."""
    model = oj.Model.from_ode(
        lambda x, u, th: duffing_rhs(x, u, th) - jnp.stack([0.0, th["c"] * x[1]]),
        0.05,
        observe=lambda x, u, th: x[:1],
    )
    theta = {
        "k": jnp.asarray(1.0),
        "eps": jnp.asarray(0.5),
        "m": jnp.asarray(1.0),
        "c": jnp.asarray(damping),
    }
    u = jnp.asarray(0.5 * np.sin(0.05 * np.arange(T)))[:, None]
    z = jnp.asarray(np.cos(0.07 * np.arange(T)))[:, None]
    return model, theta, jnp.array([1.0, 0.0]), u, z, None, None, 1.0


def linear8(T=200):
    """x_{k+1} = A x_k + B u_k with n_x = 8 (a contraction), three outputs, a matrix weight."""
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.standard_normal((8, 8)))
    theta = {"A": jnp.asarray(0.95 * Q), "B": jnp.asarray(0.3 * rng.standard_normal((8, 2)))}
    model = oj.Model(lambda x, u, th: th["A"] @ x + th["B"] @ u, lambda x, u, th: x[:3])
    u = jnp.asarray(rng.standard_normal((T, 2)))
    z = jnp.asarray(rng.standard_normal((T, 3)))
    L = rng.standard_normal((3, 3))
    return model, theta, jnp.asarray(rng.standard_normal(8)), u, z, jnp.asarray(L @ L.T), None, 1.0


def motor_barrier(x, theta):
    """Strictly positive, depends on x and theta."""
    return jnp.exp((x[1] - 3.0) / 0.5) + 0.1 * theta["b"] ** 2 + 0.01


def motor(T=200):
    """DC motor with Coulomb friction; outputs depend on u and theta; a penalty."""
    theta = {"R": 1.0, "L": 0.5, "K": 0.1, "b": 0.2, "J": 0.02, "fc": 0.01}
    theta = {k: jnp.asarray(v) for k, v in theta.items()}
    model = oj.Model.from_ode(motor_rhs, 0.02, observe=motor_observe)
    u = jnp.asarray(np.where(np.arange(T) % 50 < 25, 1.0, -0.5)[:, None])
    z = jnp.asarray(np.random.default_rng(2).normal(0.0, 0.1, (T, 3)))
    return model, theta, jnp.array([0.0, 0.5]), u, z, jnp.array([1.0, 2.0, 0.5]), motor_barrier, 0.7


MODELS = {"satellite": satellite, "duffing": duffing, "linear8": linear8, "motor": motor}


@functools.cache
def case(name):
    return MODELS[name]()


@functools.partial(jax.jit, static_argnums=(0,))
def sequential_states(step, theta, x0, u):
    return rollout(oj.Model(step), theta, x0, u)


@functools.partial(jax.jit, static_argnums=(0,), static_argnames=("jacobian", "chunk_size"))
def parallel_states(step, theta, x0, u, jacobian="full", chunk_size=None):
    return newton_rollout(step, theta, x0, u, jacobian=jacobian, chunk_size=chunk_size)


#
# Building blocks.
#


@functools.partial(jax.jit, static_argnums=(5,))
def all_recurrences(A, b, x0, B, S0, everything):
    a = jnp.einsum("kii->ki", A)
    out = (
        linear_recurrence(A, b, x0),
        reverse_diagonal_linear_recurrence(a, b, x0),
    )
    if not everything:
        return out
    return out + (
        matrix_linear_recurrence(A, B, S0),
        reverse_linear_recurrence(A, b, x0),
        diagonal_linear_recurrence(a, b, x0),
    )


# T = 37: recursive doubling, all five recurrences; T = 700: `jax.lax.associative_scan`, a
# forward full and a reverse diagonal one; n = 20: `einsum` products.
@pytest.mark.parametrize("T, n", [(37, 3), (700, 3), (37, 20)])
def test_linear_recurrences_equal_loops(T, n):
    rng = np.random.default_rng(n)
    m = 2
    A = rng.standard_normal((T, n, n)) / np.sqrt(n)
    b, x0 = rng.standard_normal((T, n)), rng.standard_normal(n)
    B, S0 = rng.standard_normal((T, n, m)), rng.standard_normal((n, m))
    x, S, lam = [x0], [S0], [x0]
    xd, lamd = [x0], [x0]
    a = np.einsum("kii->ki", A)
    for k in range(T):
        x.append(A[k] @ x[-1] + b[k])
        S.append(A[k] @ S[-1] + B[k])
        xd.append(a[k] * xd[-1] + b[k])
    for k in reversed(range(T)):
        lam.append(b[k] + A[k] @ lam[-1])
        lamd.append(b[k] + a[k] * lamd[-1])
    want = (x[1:], lamd[1:][::-1], S[1:], lam[1:][::-1], xd[1:])
    got = all_recurrences(*map(jnp.asarray, (A, b, x0, B, S0)), T < 100)
    assert len(got) == (5 if T < 100 else 2)
    for g, w in zip(got, want):
        assert_tree_rel_close(g, jnp.asarray(np.stack(w)), rtol=1e-12)


def dense_levenberg_marquardt(A, r, damping):
    """argmin_d sum_k ||d_{k+1} - A_k d_k - r_k||^2 + damping sum_k ||d_{k+1}||^2, d_0 = 0,
    by the normal equations; also returns their condition number."""
    T, n = r.shape
    D = np.eye(T * n)
    for k in range(1, T):
        D[k * n : (k + 1) * n, (k - 1) * n : k * n] = -A[k]
    H = D.T @ D + damping * np.eye(T * n)
    return np.linalg.solve(H, D.T @ r.reshape(-1)).reshape(T, n), np.linalg.cond(H)


@pytest.mark.parametrize("damping", [1e-6, 1.0, 30.0])
def test_elk_step_is_the_levenberg_marquardt_step(damping):
    """The Kalman filter + smoother scans give the Levenberg-Marquardt step, to the
    accuracy the problem allows (eps times the normal equations' condition number, 2e7
    for the nearly undamped unstable case)."""
    rng = np.random.default_rng(3)
    T, n = 30, 3
    A = 1.2 * rng.standard_normal((T, n, n))  # unstable: the undamped step would blow up
    r = rng.standard_normal((T, n))
    a = np.einsum("kii->ki", A)
    for got, (want, cond) in [
        (
            jax.jit(elk_increment)(jnp.asarray(A), jnp.asarray(r), damping),
            dense_levenberg_marquardt(A, r, damping),
        ),
        (
            jax.jit(diagonal_elk_increment)(jnp.asarray(a), jnp.asarray(r), damping),
            dense_levenberg_marquardt(np.stack([np.diag(d) for d in a]), r, damping),
        ),
    ]:
        rtol = max(1e-13, 10 * np.finfo(np.float64).eps * cond)
        assert_tree_rel_close(got, jnp.asarray(want), rtol=rtol)


#
# Rollout.
#


@pytest.mark.parametrize("name", list(MODELS))
def test_rollout_equals_sequential(name):
    model, theta, x0, u = case(name)[:4]
    xs, info = parallel_states(model.step, theta, x0, u)
    assert int(info.method) == NEWTON and bool(info.converged) and not bool(info.fallback)
    assert xs.shape == u.shape[:1] + x0.shape
    assert_tree_rel_close(xs, sequential_states(model.step, theta, x0, u), rtol=RTOL)


def test_damped_stage_converges_where_newton_diverges():
    """Lightly damped Duffing over 1000 steps: Newton from the constant guess overshoots
    into the cubic term and overflows; the Levenberg-Marquardt (ELK) stage converges."""
    model, theta, x0, u = duffing(T=1000, damping=0.1)[:4]
    xs, info = parallel_states(model.step, theta, x0, u)
    assert int(info.method) == DAMPED and bool(info.converged) and not bool(info.fallback)
    assert int(info.damped_iterations) > 0
    assert_tree_rel_close(xs, sequential_states(model.step, theta, x0, u), rtol=RTOL)


def pitchfork_step(x, u, theta):
    """x' = theta x - x^3 by Euler: x = 0 is unstable, the state runs off to sqrt(theta)."""
    return x + 0.1 * (theta * x - x**3) + u


def lorenz_step(x, u, theta):
    """Lorenz '63 (sigma = 10, rho = theta = 28, beta = 8/3), one RK4 step of 0.01."""
    del u

    def rhs(x):
        return jnp.stack(
            [10.0 * (x[1] - x[0]), x[0] * (theta - x[2]) - x[1], x[0] * x[1] - 8.0 / 3.0 * x[2]]
        )

    return oj.ode_step(lambda x, u, th: rhs(x), x, None, None, 0.01)


def logistic_step(x, u, theta):
    return theta * x * (1.0 - x) + 0.0 * u


FALLBACK_CASES = {
    # Unstable: the linearisation about the initial guess grows like 1.1^k.
    "unstable_pitchfork": (pitchfork_step, jnp.asarray(1.0), jnp.array([1e-3]), 400),
    # Chaotic: perturbations grow like e^{0.9 t}; over t = 20 no parallel solve can
    # reproduce the sequential rounding, so the rollout must be the sequential one.
    "chaotic_lorenz": (lorenz_step, jnp.asarray(28.0), jnp.array([1.0, 1.0, 1.0]), 2000),
    "chaotic_logistic": (logistic_step, jnp.asarray(3.9), jnp.array([0.3]), 300),
}


@pytest.mark.parametrize("name", list(FALLBACK_CASES))
def test_unstable_and_chaotic_fall_back_to_the_sequential_rollout(name):
    step, theta, x0, T = FALLBACK_CASES[name]
    u = jnp.zeros((T, 1))
    xs, info = parallel_states(step, theta, x0, u)
    assert bool(info.fallback) and int(info.method) == SEQUENTIAL and not bool(info.converged)
    assert int(info.damped_iterations) > 0  # the damped stage was tried first
    want = sequential_states(step, theta, x0, u)
    assert np.all(np.isfinite(np.asarray(want)))
    assert_tree_rel_close(xs, want, rtol=RTOL)


def test_without_fallback_a_nonconverged_rollout_is_flagged():
    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    xs, info = jax.jit(lambda x0, u: newton_rollout(step, theta, x0, u, fallback=False))(
        x0, jnp.zeros((T, 1))
    )
    assert not bool(info.converged) and not bool(info.fallback)
    assert int(info.method) == DAMPED


def test_vmap_falls_back_only_where_needed():
    """Under vmap the fallback is per trajectory: x0 = 1 sits at the stable equilibrium
    (Newton converges at once), x0 = 1e-3 starts at the unstable one."""
    x0 = jnp.array([[1.0], [1e-3]])
    u = jnp.zeros((2, 400, 1))
    theta = jnp.asarray(1.0)
    xs, info = jax.jit(jax.vmap(lambda x0, u: newton_rollout(pitchfork_step, theta, x0, u)))(x0, u)
    assert list(np.asarray(info.fallback)) == [False, True]
    assert list(np.asarray(info.method)) == [NEWTON, SEQUENTIAL]
    want = jax.vmap(lambda x0, u: sequential_states(pitchfork_step, theta, x0, u))(x0, u)
    assert_tree_rel_close(xs, want, rtol=RTOL)


def leaky_rnn_step(x, u, theta):
    """A leaky tanh network: diagonally dominant Jacobians, where quasi-DEER converges."""
    return 0.8 * x + 0.2 * jnp.tanh(theta["W"] @ x + theta["b"] * u[0])


def test_diagonal_jacobian_variant():
    rng = np.random.default_rng(4)
    n = 4
    theta = {
        "W": jnp.asarray(0.3 * rng.standard_normal((n, n)) / np.sqrt(n)),
        "b": jnp.asarray(rng.standard_normal(n)),
    }
    u = jnp.asarray(rng.standard_normal((300, 1)))
    x0 = jnp.asarray(rng.standard_normal(n))
    xs, info = parallel_states(leaky_rnn_step, theta, x0, u, jacobian="diagonal")
    assert int(info.method) == NEWTON and bool(info.converged)
    assert_tree_rel_close(xs, sequential_states(leaky_rnn_step, theta, x0, u), rtol=RTOL)


def test_chunked_rollout_equals_unchunked():
    model, theta, x0, u = case("duffing")[:4]
    whole, _ = parallel_states(model.step, theta, x0, u)
    # 199 steps: three chunks of 64 and one padded with 57 holding steps.
    xs, info = parallel_states(model.step, theta, x0, u, chunk_size=64)
    assert int(info.chunks) == 4 and bool(info.converged)
    assert_tree_rel_close(xs, whole, rtol=RTOL)


def test_chunks_of_a_chaotic_map_can_drift_apart():
    """What the parallel guide says of `chunk_size` on chaotic dynamics: a logistic map at
    r = 3.9 over 150 steps. Unchunked, Newton sees the whole record's sensitivity, falls
    back and equals the sequential rollout; in chunks of 7 each chunk converges on its
    own, and the round-off handed on grows until the rollouts part, from about step 85."""
    step = lambda x, u, th: th * x * (1 - x)  # noqa: E731
    u, x0 = jnp.zeros((150, 0)), jnp.array([0.3])
    want, _ = oj.simulate(oj.Model(step), 3.9, x0, u, strategy="jacobian")
    whole, info = newton_rollout(step, 3.9, x0, u)
    assert bool(info.fallback) and np.array_equal(np.asarray(whole), np.asarray(want))
    chunked, _ = newton_rollout(step, 3.9, x0, u, chunk_size=7)
    off = np.abs(np.asarray(chunked - want))[:, 0]
    first = int(np.argmax(off > 1e-14))
    assert 60 <= first <= 110 and off.max() > 1e-3, (first, off.max())
    # every step is the model's to round-off: a trajectory, not the sequential one
    xs = np.asarray(chunked)[:, 0]  # (x0, x1, ...)
    np.testing.assert_allclose(xs[1:], 3.9 * xs[:-1] * (1 - xs[:-1]), rtol=0, atol=1e-14)


def test_float32():
    """float32 in, float32 out; the tolerance is 256 eps of float32 (3e-5) by default."""
    model, theta, x0, u, z = satellite(dtype=jnp.float32)[:5]
    xs, info = parallel_states(model.step, theta, x0, u)
    assert xs.dtype == jnp.float32 and bool(info.converged)
    assert_tree_rel_close(xs, sequential_states(model.step, theta, x0, u), rtol=1e-5)
    got = vg_of_states(model, theta, xs, u, z, None, None, jnp.float32(1.0))
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="jacobian")
    assert_tree_rel_close(got, want, rtol=1e-4)


def test_rollout_derivatives_equal_those_of_the_sequential_rollout():
    """`jax.grad` and `jax.jacfwd` go through the implicit-function tangent (custom_jvp)."""
    model, theta, x0, u = case("duffing")[:4]

    def loss(fn, theta, x0, u):
        return jnp.sum(jnp.sin(fn(theta, x0, u)))

    seq = lambda th, x0, u: rollout(model, th, x0, u)  # noqa: E731
    par = lambda th, x0, u: newton_rollout(model.step, th, x0, u, chunk_size=64)[0]  # noqa: E731
    want = jax.jit(jax.grad(functools.partial(loss, seq), argnums=(0, 1, 2)))(theta, x0, u)
    got = jax.jit(jax.grad(functools.partial(loss, par), argnums=(0, 1, 2)))(theta, x0, u)
    assert_tree_rel_close(got, want, rtol=RTOL)


def test_bad_options_raise():
    model, theta, x0, u = case("duffing")[:4]
    with pytest.raises(ValueError, match="jacobian"):
        newton_rollout(model.step, theta, x0, u, jacobian="dense")
    with pytest.raises(ValueError, match="chunk_size"):
        newton_rollout(model.step, theta, x0, u, chunk_size=0)
    with pytest.raises(ValueError, match="max_iter"):
        newton_rollout(model.step, theta, x0, u, max_iter=0)
    with pytest.raises(ValueError, match="x0"):
        newton_rollout(model.step, theta, x0[None], u)
    with pytest.raises(ValueError, match="us"):
        newton_rollout(model.step, theta, x0, u[0])


#
# Gradient and sensitivities.
#


def cost_of(weight, penalty, penalty_weight):
    pw = jnp.asarray(penalty_weight if penalty is not None else 0.0)
    return Cost(weight, penalty, pw)


@functools.partial(jax.jit, static_argnums=(0, 6), static_argnames=("chunk_size",))
def parallel_vg(model, theta, x0, u, z, weight, penalty, penalty_weight, chunk_size=None):
    return parallel_value_and_grad(
        model,
        cost_of(weight, penalty, penalty_weight),
        theta,
        x0,
        u,
        z,
        strategy=oj.ParallelInTime(chunk_size=chunk_size),
    )


@functools.partial(jax.jit, static_argnums=(0, 6))
def vg_of_states(model, theta, xs, u, z, weight, penalty, penalty_weight):
    cost = cost_of(weight, penalty, penalty_weight)
    return value_and_grad_of_states(model, cost, theta, xs, u, z, oj.ParallelInTime())


@pytest.mark.parametrize("name", list(MODELS))
def test_value_and_grad_equals_the_sequential_strategies(name):
    """The gradient recursion by the reverse scan, at the parallel states (the rollout
    test above compiled them)."""
    model, theta, x0, u, z, weight, penalty, pw = case(name)
    xs, info = parallel_states(model.step, theta, x0, u)
    assert int(info.method) == NEWTON
    got = vg_of_states(model, theta, xs, u, z, weight, penalty, jnp.asarray(pw))
    # Both sequential strategies agree to round-off (tests/test_gradient.py); "vjp" is
    # compared on the model with the richest cost (u- and theta-dependent outputs, a
    # weight, a penalty).
    for strategy in ("jacobian", "vjp") if name == "motor" else ("jacobian",):
        want = oj.value_and_grad(
            model,
            theta,
            x0,
            u,
            z,
            weight=weight,
            penalty=penalty,
            penalty_weight=pw,
            strategy=strategy,
        )
        assert_tree_rel_close(got, want, rtol=RTOL)


def test_chunked_parallel_value_and_grad_equals_sequential():
    """The whole `parallel_value_and_grad`, chunked (4 chunks, the last one padded): the
    rollout and the reverse recursion both carry between chunks."""
    model, theta, x0, u, z, weight, penalty, pw = case("satellite")
    got, info = parallel_vg(model, theta, x0, u, z, weight, penalty, jnp.asarray(pw), chunk_size=64)
    assert int(info.chunks) == 4 and int(info.method) == NEWTON
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="jacobian")
    assert_tree_rel_close(got, want, rtol=RTOL)


def test_value_and_grad_with_fallback_equals_sequential():
    step, theta, x0, T = FALLBACK_CASES["unstable_pitchfork"]
    model = oj.Model(step)
    u = jnp.zeros((T, 1))
    z = jnp.ones((T, 1))
    xs, info = parallel_states(step, theta, x0, u)  # compiled by the fallback test
    assert bool(info.fallback)
    got = vg_of_states(model, theta, xs, u, z, None, None, jnp.asarray(1.0))
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="jacobian")
    assert_tree_rel_close(got, want, rtol=RTOL)


def sensitivity_args(name):
    """The arguments of `trajectory_jacobian` as `fit` builds them: one fixed theta entry,
    one fixed x0 entry, the cost and the 1/sqrt(T) scale."""
    model, theta, x0, u, z, weight, penalty, pw = case(name)
    flat, unravel = ravel_pytree(theta)
    free = np.arange(flat.size) != 1
    p_theta = flat[free]
    theta_of = lambda p: unravel(flat.at[np.flatnonzero(free)].set(p))  # noqa: E731
    x0_of = lambda p: x0.at[1:].set(p)  # noqa: E731
    scale = 1.0 / np.sqrt(u.shape[0])
    cost = cost_of(weight, penalty, pw)
    return (model, cost, theta_of, p_theta, x0_of, x0[1:], u, z), scale


def test_sensitivities_equal_trajectory_jacobian():
    """Motor (a penalty, u- and theta-dependent outputs, fixed entries): the sensitivity
    recursion by the associative scan at the parallel states."""
    args, scale = sensitivity_args("motor")
    model, theta, x0, u = case("motor")[:4]
    xs, info = parallel_states(model.step, theta, x0, u)
    want = jax.jit(lambda: trajectory_jacobian(*args, scale=scale, strategy="jacobian"))()
    got = jax.jit(
        lambda xs: trajectory_jacobian(*args, scale=scale, strategy=oj.ParallelInTime(), xs=xs)
    )(xs)
    for a, b in zip(got[:3], want[:3]):  # r, J_theta, J_x0
        assert a.shape == b.shape
        assert_tree_rel_close(a, b, rtol=RTOL)
    assert float(got.h_min) == pytest.approx(float(want.h_min), rel=RTOL)


def test_chunked_parallel_sensitivities_equal_trajectory_jacobian():
    args, scale = sensitivity_args("satellite")
    want = jax.jit(lambda: trajectory_jacobian(*args, scale=scale, strategy="jacobian"))()
    got, info = jax.jit(
        lambda: parallel_sensitivities(
            *args, scale=scale, strategy=oj.ParallelInTime(chunk_size=64)
        )
    )()
    assert int(info.method) == NEWTON and int(info.chunks) == 4
    for a, b in zip(got[:3], want[:3]):  # r, J_theta, J_x0
        assert a.shape == b.shape
        assert_tree_rel_close(a, b, rtol=RTOL)
    assert float(got.h_min) == pytest.approx(float(want.h_min), rel=RTOL)


#
# The public entry points with strategy="parallel".
#


def test_public_functions_with_the_parallel_strategy_equal_the_sequential_ones():
    model, theta, x0, u, z, weight, penalty, pw = case("motor")
    kw = dict(weight=weight, penalty=penalty, penalty_weight=pw)
    xs, zs = oj.simulate(model, theta, x0, u)
    xp, zp = oj.simulate(model, theta, x0, u, strategy="parallel")
    assert_tree_rel_close((xp, zp), (xs, zs), rtol=RTOL)
    C = oj.loss(model, theta, x0, u, z, **kw)
    assert float(oj.loss(model, theta, x0, u, z, strategy="parallel", **kw)) == pytest.approx(
        float(C), rel=RTOL
    )
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="jacobian", **kw)
    got = oj.value_and_grad(model, theta, x0, u, z, strategy="parallel", **kw)
    assert_tree_rel_close(got, want, rtol=RTOL)


def test_parallel_strategy_with_foh_input_missing_samples_and_several_trajectories():
    """The parallel path sees what the step sees (u[k], u[k+1] under "foh"), the masks
    and the normalisation of several trajectories of different lengths."""
    model = oj.Model.from_ode(
        lambda x, u, th: jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]]),
        0.1,
        observe=lambda x, u, th: x[:1],
        input="foh",
    )
    theta = {"k": jnp.asarray(2.0), "c": jnp.asarray(0.4)}
    rng = np.random.default_rng(3)
    u = rng.standard_normal((60, 1))
    z = rng.standard_normal((60, 1))
    z[5:9] = np.nan
    x0 = np.array([[0.5, 0.0], [0.1, 0.2]])
    us, zs = [u, u[:40]], [z, z[:40]]
    want = oj.value_and_grad(model, theta, x0, us, zs, missing="mask", strategy="jacobian")
    got = oj.value_and_grad(model, theta, x0, us, zs, missing="mask", strategy="parallel")
    assert_tree_rel_close(got, want, rtol=RTOL)


def test_fits_in_threads_count_their_own_rollouts():
    """Two fits at once in two threads, one whose parallel rollouts all fall back (a
    chaotic logistic map), one whose never do: the counts of the open calls were one
    process-wide stack, so that each callback counted for whichever call opened last (the
    other thread's), and the exit removed its counts by value, which failed with
    `list.remove(x): x not in list`. Each fit now counts the rollouts its own thread
    reports, never the other's."""
    from concurrent.futures import ThreadPoolExecutor

    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    chaotic = oj.Model(step)
    u = np.zeros((T, 1))
    z = np.asarray(oj.simulate(chaotic, theta, x0, u)[0])
    benign = oj.Model(lambda x, u, th: th["a"] * x + u)
    ub = np.random.default_rng(0).standard_normal((T, 1))
    zb = np.asarray(oj.simulate(benign, {"a": 0.5}, np.zeros(1), ub)[0])

    def fit(model, theta, x0, u, z):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            solver = oj.Adam(max_steps=20, strategy="parallel")
            return oj.fit(model, theta, x0, u, z, fixed=True, solver=solver, covariance=None)

    alone = fit(chaotic, theta, x0, u, z).diagnostics
    assert alone["sequential_fallbacks"] == alone["parallel_rollouts"] > 0
    with ThreadPoolExecutor(2) as pool:
        for _ in range(3):
            a = pool.submit(fit, chaotic, theta, x0, u, z)
            b = pool.submit(fit, benign, {"a": 0.5}, np.zeros(1), ub, zb)
            # (a callback run on a thread of XLA's own while both calls are open cannot
            # say whose rollout it reports: it warns from there, counted by neither)
            da, db = a.result().diagnostics, b.result().diagnostics
            assert db.get("sequential_fallbacks", 0) == 0
            counted = da.get("parallel_rollouts", 0)
            assert da.get("sequential_fallbacks", 0) == counted <= alone["parallel_rollouts"]


def test_fit_with_parallel_solvers_equals_the_sequential_fit():
    model, theta, x0, u, z = case("satellite")[:5]
    _, zt = oj.simulate(model, theta, x0, u)
    z = np.asarray(zt) + 1e-4 * np.random.default_rng(4).standard_normal(zt.shape)
    theta0 = {"I": theta["I"] * 1.05}
    # gtol 1e-6: the first-order measure falls from above 1e-5 (step 2) to 1.2e-8 (step 3),
    # so the stop does not hang on round-off (the default 1e-8 is at the measure's
    # round-off floor here: on a GPU the two paths then stopped after 8 and 4 steps).
    seq = oj.fit(model, theta0, x0, u, z, solver=oj.GaussNewton(strategy="jacobian", gtol=1e-6))
    par = oj.fit(model, theta0, x0, u, z, solver=oj.GaussNewton(strategy="parallel", gtol=1e-6))
    assert seq.success and par.success
    assert seq.diagnostics == {} and par.diagnostics["sequential_fallbacks"] == 0
    assert par.diagnostics["parallel_rollouts"] >= par.num_steps
    assert par.num_steps == seq.num_steps
    assert_tree_rel_close(par.theta, seq.theta, rtol=1e-10)
    np.testing.assert_allclose(par.std["I"], seq.std["I"], rtol=1e-8)


def test_a_fallback_is_reported():
    """A chaotic logistic map: the parallel rollout falls back, with a warning outside
    fit and in FitResult.diagnostics inside it; the results are the sequential ones."""
    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    model = oj.Model(step)
    u = jnp.zeros((T, 1))
    with pytest.warns(RuntimeWarning, match="fell back to the sequential loop"):
        xp, _ = oj.simulate(model, theta, x0, u, strategy="parallel")
    xs, _ = oj.simulate(model, theta, x0, u)
    np.testing.assert_array_equal(np.asarray(xp), np.asarray(xs))
    z = np.asarray(xs)
    # A short first-order fit (cheaper to compile than the parallel least squares, which
    # test_fit_with_parallel_solvers_equals_the_sequential_fit covers).
    with pytest.warns(RuntimeWarning, match="fell back to the sequential loop"):
        r = oj.fit(
            model, theta, x0, u, z, fixed=True, solver=oj.Adam(max_steps=2, strategy="parallel")
        )
    assert r.diagnostics["sequential_fallbacks"] >= 1


def test_the_checks_after_a_parallel_fit_count_their_fallbacks_with_no_warning_of_their_own():
    """The checks of a least-squares success after the solve (a zero-loss fit of a
    chaotic map, rank-deficient there) ran parallel rollouts outside the fit's count: five
    more warnings after its one, from JAX's callback frame, and uncounted."""
    step, theta, x0, _ = FALLBACK_CASES["chaotic_logistic"]
    model = oj.Model(step)
    u = jnp.zeros((60, 1))
    z = np.asarray(oj.simulate(model, theta, x0, u)[1])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        r = oj.fit(model, theta, x0, u, z, solver=oj.GaussNewton(strategy="parallel", max_steps=2))
    fallbacks = [w for w in rec if "parallel rollout" in str(w.message)]
    assert len(fallbacks) == 1, [str(w.message)[:80] for w in fallbacks]
    assert str(r.diagnostics["sequential_fallbacks"]) in str(fallbacks[0].message)


def test_each_call_outside_fit_warns_at_its_callers_line():
    """`simulate`, `loss` and `value_and_grad` warned from JAX's callback frame: under the
    default filters every later rollout kept unconverged (wrong states, loss and gradient)
    went unreported after the first, and an "error" filter gave an XLA error, not the
    RuntimeWarning. Each call now warns at its caller's line, after the call."""
    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    model = oj.Model(step)
    u = jnp.zeros((T, 1))
    z = np.asarray(oj.simulate(model, theta, x0, u)[1])
    kept = oj.ParallelInTime(fallback=False)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("default")
        oj.simulate(model, theta, x0, u, strategy=kept)
        oj.loss(model, theta, x0, u, z, strategy=kept)
        oj.value_and_grad(model, theta, x0, u, z, strategy=kept)
    kept_warnings = [w for w in rec if "kept Newton's best iterate" in str(w.message)]
    assert len(kept_warnings) == 3, [(w.filename, w.lineno) for w in rec]
    assert {w.filename for w in kept_warnings} == {__file__}
    assert len({w.lineno for w in kept_warnings}) == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(RuntimeWarning, match="kept Newton's best iterate"):
            oj.loss(model, theta, x0, u, z, strategy=kept)


def test_a_rollout_kept_without_fallback_is_reported():
    """With fallback=False a chaotic map's rollout keeps Newton's best iterate, whose loss
    is not the model's (0.38 against 0.18 in an audit): a warning outside fit, a count and
    a warning inside it (it was silent)."""
    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    model = oj.Model(step)
    u = jnp.zeros((T, 1))
    z = np.asarray(oj.simulate(model, theta, x0, u)[1])
    kept = oj.ParallelInTime(fallback=False)
    with pytest.warns(RuntimeWarning, match=r"kept Newton's best iterate"):
        C = oj.loss(model, theta, x0, u, z, strategy=kept)
    assert float(C) > 1e-3  # not the model's loss, which is 0 on its own outputs
    # Inside fit: a count and a warning. A test that would pass on those values (a loss
    # threshold) is no success there: the returned point's own rollout did not converge
    # (40 samples: over 300 the gradient of the chaotic map overflows).
    loose = oj.Adam(max_steps=2, tol_loss=1e9, strategy=kept)
    with pytest.warns(RuntimeWarning, match=r"parallel rollouts: the parallel rollout did not"):
        r = oj.fit(model, theta, x0, u[:40], z[:40], fixed=True, solver=loose)
    assert r.diagnostics["unconverged_rollouts"] >= 1
    assert r.diagnostics["sequential_fallbacks"] == 0
    assert r.status == "unconverged_rollout" and not r.success
    assert r.stop_info["solver_stop"] == "tol_loss"
    assert "parallel rollouts kept Newton's unconverged iterate" in r.message
    # `loss` is the rollouts' (as its history); the model's own goes with the reason.
    own = float(oj.loss(model, r.theta, r.x0, u[:40], z[:40]))
    assert r.stop_info["model_loss"] == pytest.approx(own, rel=1e-12, abs=1e-300)
    assert abs(own - float(r.loss)) > 1e-3 * float(r.loss)
    assert "the model's loss there, simulated sequentially" in r.message
    # With several starts every start's success is checked, not the best start's alone
    # (the other start was listed as `tol_loss`).
    with pytest.warns(
        RuntimeWarning, match=r"parallel rollouts: the parallel rollout did not"
    ) as rec:
        r = oj.fit(model, jnp.array([3.9, 3.85]), x0, u[:40], z[:40], solver=loose, multistart=True)
    assert r.starts.stop_reason == ("unconverged_rollout", "unconverged_rollout")
    # Its Jacobian is the rollouts', not the model's: its rank deficiency is not blamed on
    # the data (it read "at the solution ... not identifiable from these data").
    deficient = [str(w.message) for w in rec if "rank-deficient" in str(w.message)]
    assert deficient
    for text in deficient:
        assert "parallel rollouts of the fit did not converge" in text, text
        assert "from these data" not in text

    # Where the returned point's own rollout converges, the stop stands (its values are
    # the model's), though rollouts of trial steps did not: a Duffing oscillator with 3
    # Newton iterations per rollout.
    def duffing(x, u, th):
        acc = th["k"] * x[0] + th["d"] * x[1] + th["e"] * x[0] ** 3
        return jnp.stack([x[0] + 0.1 * x[1], x[1] - 0.1 * acc + 0.1 * u[0]])

    model = oj.Model(duffing, lambda x, u, th: x[:1])
    rng = np.random.default_rng(2)
    us, x0 = 0.5 * rng.standard_normal((41, 1)), np.array([1.0, 0.0])
    zs = oj.simulate(model, {"k": 1.0, "d": 0.3, "e": 0.5}, x0, us)[1]
    zs = np.asarray(zs) + 0.02 * rng.standard_normal(zs.shape)
    start = {"k": 0.8, "d": 0.2, "e": 0.6}
    few = oj.LevenbergMarquardt(strategy=oj.ParallelInTime(fallback=False, max_iter=3))
    with pytest.warns(RuntimeWarning, match=r"parallel rollouts: the parallel rollout did not"):
        r = oj.fit(model, start, x0, us, zs, solver=few)
    assert r.diagnostics["unconverged_rollouts"] >= 1 and r.success
    # (its loss is the model's: the sequential simulation's at the returned point)
    model_loss = oj.loss(model, r.theta, r.x0, us, zs, strategy="vjp")
    np.testing.assert_allclose(float(r.loss), float(model_loss), rtol=1e-9)


def test_parallel_alias_equals_the_object_bit_for_bit():
    model, theta, x0, u, z, weight, penalty, pw = case("motor")
    kw = dict(weight=weight, penalty=penalty, penalty_weight=pw)
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="parallel", **kw)
    got = oj.value_and_grad(model, theta, x0, u, z, strategy=oj.ParallelInTime(), **kw)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_parallel_in_time_options_reach_newton_rollout(monkeypatch):
    """Every option of `ParallelInTime` is passed on to `newton_rollout` (a spy), and one
    that changes the result does so through the public `simulate`: one iteration without
    the fallback leaves a non-converged iterate, not the trajectory."""
    from oneshot_jax.internal import strategy_module as _strategy

    model, theta, x0, u = case("duffing")[:4]
    options = dict(chunk_size=7, jacobian="diagonal", max_iter=3, rtol=1e-6, damping=2.0)
    seen = {}

    def spy(step, theta, x0, us, **kwargs):
        seen.update(kwargs)
        return newton_rollout(step, theta, x0, us, **kwargs)

    monkeypatch.setattr(_strategy, "newton_rollout", spy)
    oj.ParallelInTime(**options, fallback=False).rollout(model, theta, x0, u)
    assert seen == {**options, "fallback": False}
    monkeypatch.undo()
    xs, _ = oj.simulate(model, theta, x0, u)
    xp, _ = oj.simulate(model, theta, x0, u, strategy=oj.ParallelInTime(max_iter=1, fallback=False))
    assert not np.allclose(np.asarray(xp), np.asarray(xs), rtol=1e-6)


@pytest.mark.parametrize(
    "option, value",
    [
        ("chunk_size", 0),
        ("chunk_size", 2.5),
        ("jacobian", "dense"),
        ("max_iter", 0),
        ("max_iter", "many"),
        ("rtol", 2.0),
        ("damping", -1.0),
        ("damping", float("nan")),
        ("fallback", "yes"),
    ],
)
def test_bad_parallel_in_time_options_raise_naming_the_option(option, value):
    with pytest.raises(ValueError, match=f"`{option}"):
        oj.ParallelInTime(**{option: value})


def test_solvers_take_strategy_objects():
    """A solver's `strategy=` takes the objects as their aliases: `ParallelInTime(...)` is
    recognised as parallel (no matrix-free products)."""
    with pytest.raises(ValueError, match="linear_solver='cg'"):
        oj.GaussNewton(strategy=oj.ParallelInTime(chunk_size=8), linear_solver="cg")
    with pytest.raises(ValueError, match="linear_solver='cg'"):
        oj.LevenbergMarquardt(strategy="parallel", linear_solver="cg")
    assert oj.Adam(strategy=oj.VJP()).strategy == oj.VJP()


def test_auto_takes_the_parallel_path_only_on_accelerators(monkeypatch):
    """On a CPU the sequential scan is faster at every size (benchmarks/parallel.py), so
    "auto" never takes the parallel path there; on a GPU or TPU it does for long records."""
    from oneshot_jax.internal import PARALLEL_MIN_T, is_parallel

    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    assert not is_parallel("auto", 10**7)
    assert is_parallel("parallel", 2)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert is_parallel("auto", PARALLEL_MIN_T)
    assert not is_parallel("auto", PARALLEL_MIN_T - 1)
    assert not is_parallel("jacobian", 10**7)
    assert oj.Auto().resolve(3, PARALLEL_MIN_T, 8) == oj.ParallelInTime()
    assert oj.Auto().resolve(3, 10**6, 8, sequential=True) == oj.Jacobian()
    # A large state stays matrix-free: the parallel path stacks T n_x^2 Jacobians (64 GiB
    # at n_x = 4096, T = 512).
    assert oj.Auto().resolve(64, PARALLEL_MIN_T, 8) == oj.VJP()
    assert oj.Auto().resolve(4096, PARALLEL_MIN_T, 8) == oj.VJP()


def test_a_stop_on_unconverged_rollouts_says_so_in_the_printout():
    """A fit that stops without success on rollouts that kept Newton's iterate printed
    its loss, FIT and standard errors with nothing saying they were the rollouts'."""
    step, theta, x0, T = FALLBACK_CASES["chaotic_logistic"]
    model = oj.Model(step)
    u = jnp.zeros((40, 1))
    z = np.asarray(oj.simulate(model, theta, x0, u)[1])
    kept = oj.Adam(max_steps=2, strategy=oj.ParallelInTime(fallback=False))
    with pytest.warns(RuntimeWarning, match=r"parallel rollouts: the parallel rollout did not"):
        r = oj.fit(model, theta, x0, u, z, fixed=True, solver=kept)
    assert not r.success and r.diagnostics["unconverged_rollouts"] >= 1
    assert "parallel rollouts kept Newton's unconverged iterate" in str(r)
    # and the message, which named only the stop's own advice
    assert "parallel rollouts kept Newton's unconverged iterate" in r.message
