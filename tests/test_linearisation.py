"""The pieces of GaussNewton / LevenbergMarquardt: the one x0 elimination
(`_linalg.eliminate_x0`) in the damped step and in the covariance, against dense solves of
the full normal equations of a random arrow-shaped Jacobian, and the searches."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.internal import (
    Backtracking,
    Cost,
    Damping,
    DenseLinearisation,
    FitProblem,
    NielsenDamping,
    Params,
    covariance,
    eliminate_x0,
    identifiable,
    linearise,
    normal_blocks,
    placeholder,
    schur_complement,
)


def _arrow(N=3, R=12, p=4, m=2, seed=0):
    """A random residual Jacobian with shared theta columns and per-trajectory x0 columns,
    and the same Jacobian as one dense (N R, p + N m) matrix."""
    rng = np.random.default_rng(seed)
    Jt = rng.standard_normal((N, R, p)) * np.logspace(-1, 1, p)
    Jx = rng.standard_normal((N, R, m)) + 0.5 * Jt[..., :m]  # coupled with theta
    r = rng.standard_normal((N, R))
    J = np.zeros((N * R, p + N * m))
    for i in range(N):
        J[i * R : (i + 1) * R, :p] = Jt[i]
        J[i * R : (i + 1) * R, p + i * m : p + (i + 1) * m] = Jx[i]
    return Jt, Jx, r, J


def _linearisation(Jt, Jx, r):
    Jt, Jx, r = jnp.asarray(Jt), jnp.asarray(Jx), jnp.asarray(r)
    blocks = normal_blocks(Jt, Jx, r)
    return DenseLinearisation(jnp.sum(r**2), *blocks, schur_complement(Jt, Jx, blocks[0]))


def _floor(d):
    return np.maximum(d, 1e-12 * max(d.max(), 1e-300))


@pytest.mark.parametrize("mu", [0.0, 1e-2, 3.0])
def test_the_damped_step_solves_the_full_normal_equations(mu):
    Jt, Jx, r, J = _arrow()
    N, _, p = Jt.shape
    m = Jx.shape[-1]
    M = J.T @ J
    g = J.T @ r.reshape(-1)
    D = np.concatenate(
        [_floor(np.diag(M)[:p])]
        + [_floor(np.diag(M)[p + i * m : p + (i + 1) * m]) for i in range(N)]
    )
    lin = _linearisation(Jt, Jx, r)
    for held in (None, 1):
        active = np.zeros(p, bool)
        free = np.ones(p + N * m, bool)
        if held is not None:
            active[held] = True
            free[held] = False
        h = np.zeros(p + N * m)
        K = M + mu * np.diag(D)
        h[free] = -np.linalg.solve(K[np.ix_(free, free)], g[free])
        step = lin.step(None, None, mu, jnp.asarray(active))
        np.testing.assert_allclose(step.theta, h[:p], rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(step.x0, h[p:].reshape(N, m), rtol=1e-10, atol=1e-13)
        # The model's curvature ||J s||^2 from the blocks.
        s = Params(step.theta, step.x0)
        Js = J @ np.r_[np.asarray(s.theta), np.asarray(s.x0).ravel()]
        np.testing.assert_allclose(lin.curvature(None, None, s.theta, s.x0), Js @ Js, rtol=1e-12)


def test_the_covariance_is_the_inverse_of_the_full_normal_equations():
    Jt, Jx, r, J = _arrow(seed=1)
    N, _, p = Jt.shape
    m = Jx.shape[-1]
    lin = _linearisation(Jt, Jx, r)
    cov = covariance(None, None, None, blocks=lin.covariance_blocks(lin.C))
    inv = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(cov.theta, inv[:p, :p], rtol=1e-9)
    for i in range(N):
        sl = slice(p + i * m, p + (i + 1) * m)
        np.testing.assert_allclose(cov.x0[i], inv[sl, sl], rtol=1e-9)
    assert np.all(cov.theta_identifiable) and np.all(cov.x0_identifiable)


def test_an_x0_entry_without_effect_gets_no_step_and_is_not_identifiable():
    Jt, Jx, r, J = _arrow(seed=2)
    Jx[1, :, 0] = 0.0  # trajectory 1's first x0 entry does not change its outputs
    lin = _linearisation(Jt, Jx, r)
    step = lin.step(None, None, 0.0, jnp.zeros(Jt.shape[-1], bool))
    assert step.x0[1, 0] == 0.0 and np.all(np.isfinite(step.x0))
    cov = covariance(None, None, None, blocks=lin.covariance_blocks(lin.C))
    assert not cov.x0_identifiable[1, 0] and cov.x0_identifiable[0].all()


def _ill_conditioned_x0(seed=0, R=300, p=3, m=2, kappa=1e6, rel=1e-4):
    """One trajectory whose x0 columns have a condition number `kappa` (C = J_x^T J_x:
    kappa^2) and whose theta columns lie in their range up to a part of relative size
    `rel` orthogonal to it (a partly observed oscillator near a poor x0): Jt, Jx and the
    exact Schur complement N^T N."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((R, m + p)))
    Q1, Q2 = Q[:, :m], Q[:, m:]
    V, _ = np.linalg.qr(rng.standard_normal((m, m)))
    Jx = Q1 @ np.diag(np.logspace(0, -np.log10(kappa), m)) @ V.T
    N_ = rel * rng.standard_normal((p, p))
    Jt = Q1 @ rng.standard_normal((m, p)) + Q2 @ N_
    return Jt[None], Jx[None], N_.T @ N_


def test_the_schur_complement_is_formed_without_the_normal_equations_cancellation():
    """S = A - B C^+ B^T from the blocks loses about cond(C) eps ||A||: here (cond(C) =
    1e12, theta's columns in the x0 columns' range up to 1e-4) it comes out indefinite and
    every parameter looks not identifiable; from the Jacobian it is exact to 1e-6 and all
    three are identifiable."""
    Jt, Jx, exact = _ill_conditioned_x0()
    A, B, Cb, _, _ = normal_blocks(jnp.asarray(Jt), jnp.asarray(Jx), jnp.zeros(Jt.shape[:2]))
    from_blocks = eliminate_x0(B, Cb, pseudo_inverse=True).schur(A, B)
    S = schur_complement(jnp.asarray(Jt), jnp.asarray(Jx), A)
    scale = np.linalg.norm(exact)
    assert np.linalg.norm(from_blocks - exact) > 10 * scale  # the old way: cancellation
    np.testing.assert_allclose(S, exact, atol=1e-6 * scale)
    assert not np.all(identifiable(from_blocks, jnp.diag(A)))
    assert np.all(identifiable(S, jnp.diag(A)))
    lin = _linearisation(Jt, Jx, np.zeros(Jt.shape[:2]))
    assert [int(r) for r in lin.rank()] == [Jt.shape[-1] + Jx.shape[-1], Jt.shape[-1]]
    cov = covariance(None, None, None, blocks=lin.covariance_blocks(jnp.array(1.0)))
    np.testing.assert_allclose(cov.theta, np.linalg.inv(exact), rtol=1e-5)
    assert np.all(cov.theta_identifiable)


def test_a_parameter_that_x0_reproduces_is_not_identifiable():
    """A theta column in the range of the x0 columns (rel = 0) leaves a remainder of
    round-off after the elimination: judged against diag(A) it is null, as the
    parameter is (its own diagonal would make it look regular)."""
    Jt, Jx, _ = _ill_conditioned_x0(kappa=10.0, rel=0.0, p=1)
    lin = _linearisation(Jt, Jx, np.zeros(Jt.shape[:2]))
    assert not np.any(identifiable(lin.S, jnp.diag(lin.A)))
    assert np.all(identifiable(lin.S))  # the round-off remainder on its own scale
    assert [int(r) for r in lin.rank()] == [Jx.shape[-1], 0]
    cov = covariance(None, None, None, blocks=lin.covariance_blocks(jnp.array(1.0)))
    assert not np.any(cov.theta_identifiable)


def test_initial_states_that_move_with_a_parameter_are_not_identifiable():
    """theta_0's column is a multiple a_i of x0_i[0]'s in every trajectory: moving theta_0
    by 1 and each x0_i[0] by -a_i leaves the outputs unchanged. Each C_i alone is regular,
    and the x0 entries used to be reported identifiable (finite standard errors) while
    theta_0 was not. Now both are, as the dense null space of J says, and the rest stay
    identifiable."""
    Jt, Jx, r, J = _arrow(seed=3)
    N, _, p = Jt.shape
    m = Jx.shape[-1]
    a = np.array([0.5, -2.0, 1.5])
    Jt[:, :, 0] = a[:, None] * Jx[:, :, 0]
    for i in range(N):
        J[i * Jt.shape[1] : (i + 1) * Jt.shape[1], :p] = Jt[i]
    _, sv, Vt = np.linalg.svd(J)
    null = Vt[sv < 1e-10 * sv[0]]
    assert null.shape[0] == 1  # one direction: theta_0 with every x0_i[0]
    dense_ok = np.abs(null[0]) < 1e-8
    lin = _linearisation(Jt, Jx, r)
    cov = covariance(None, None, None, blocks=lin.covariance_blocks(lin.C))
    np.testing.assert_array_equal(cov.theta_identifiable, dense_ok[:p])
    np.testing.assert_array_equal(cov.x0_identifiable, dense_ok[p:].reshape(N, m))
    assert not cov.x0_identifiable[:, 0].any() and cov.x0_identifiable[:, 1].all()


def test_the_searches_own_their_state():
    C = jnp.array(1.0)
    # Backtracking halves until the loss decreases; it has no damping.
    losses = {1.0: 2.0, 0.5: 1.5, 0.25: 0.9}

    def trial(alpha):
        return Params(jnp.array([alpha]), jnp.zeros((1, 0))), jnp.array(
            losses.get(float(alpha), 3.0)
        )

    search = Backtracking()
    assert search.damping(search.init(jnp.float64)) == 0.0
    step = Params(jnp.array([1.0]), jnp.zeros((1, 0)))
    t, _ = jax.disable_jit()(lambda: search.search(trial, C, step, trial(1.0), 0.1, ()))()
    assert bool(t.accept) and float(t.params.theta[0]) == 0.25 and float(t.loss) == 0.9
    # Nielsen's damping: rho = 1 divides mu by 3 and resets nu; a rejection grows both.
    search = NielsenDamping(1e-3)
    state = search.init(jnp.float64)
    assert float(search.damping(state)) == 1e-3 and float(state.nu) == 2.0
    full = (step, jnp.array(0.5))
    t, state = search.search(trial, C, step, full, jnp.array(0.5), Damping(jnp.array(0.3), 8.0))
    assert bool(t.accept) and float(state.mu) == pytest.approx(0.1) and float(state.nu) == 2.0
    full = (step, jnp.array(1.5))
    t, state = search.search(trial, C, step, full, jnp.array(0.5), Damping(jnp.array(0.3), 4.0))
    assert not bool(t.accept) and float(state.mu) == pytest.approx(1.2) and float(state.nu) == 8.0


@pytest.mark.parametrize("matrix_free", [False, True])
@pytest.mark.parametrize("N, x0_free", [(1, (0, 1)), (3, (1,)), (2, ())])
def test_the_placeholder_has_the_structure_of_the_linearisation(matrix_free, N, x0_free):
    """A least-squares solver's state holds zeros of the linearisation's structure until
    its first step forms it: the same pytree, shapes and dtypes as `linearise` gives (a
    wrong one would fail in the solver loop's carry), for one and several trajectories,
    some or none of x0 free, dense and matrix-free."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * jnp.sin(x[0]) - th["c"] * x[1] + u[0]])

    model = oj.Model.from_ode(rhs, 0.1, observe=lambda x, u, th: x[:1])
    T = 20
    u = np.sin(0.3 * np.arange(N * T)).reshape(N, T, 1)
    z = np.cos(0.2 * np.arange(N * T)).reshape(N, T, 1)
    x0 = np.tile([0.3, 0.0], (N, 1))
    flat = jnp.array([2.0, 0.4])
    problem = FitProblem(
        model=model,
        cost=Cost(None, None, jnp.zeros((), flat.dtype)),
        u=u,
        z=z,
        theta_base=flat,
        theta_free=(0, 1),
        unravel=lambda v: {"c": v[0], "k": v[1]},
        x0_base=x0,
        x0_free=x0_free,
        project=None,
        lower=None,
        upper=None,
    )
    params = Params(flat, jnp.asarray(x0)[:, list(x0_free)])
    args = (problem, params, "jacobian", matrix_free, 1e-6, 50)
    made = placeholder(*args)
    ref = jax.eval_shape(lambda: linearise(*args))
    assert jax.tree_util.tree_structure(made) == jax.tree_util.tree_structure(ref)
    for a, b in zip(jax.tree_util.tree_leaves(made), jax.tree_util.tree_leaves(ref)):
        assert (a.shape, a.dtype) == (b.shape, b.dtype)
        assert not np.any(np.asarray(a))
