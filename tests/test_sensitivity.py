"""The closed-form residual Jacobian (forward sensitivities, `_sensitivity.py`) against
`jax.jacfwd` of the residual rollout, through `FitProblem.jacobian` / `FitProblem.residuals`.

The FitProblems are built here the way `fit` builds them: the free parameters are the entries
of the flattened theta and of each trajectory's x0 that are not fixed, so the Jacobian's
columns are exactly the free variables.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.internal import Cost, FitProblem, Params
from oneshot_jax.internal import OptimistixHeld as _Held
from oneshot_jax.internal import optimistix_loss as _loss
from oneshot_jax.internal import optimistix_residuals as _residuals


def make_problem(
    model,
    theta,
    x0,
    u,
    z,
    *,
    fixed=None,
    x0_mask=None,
    weight=None,
    penalty=None,
    penalty_weight=1.0,
):
    """A FitProblem for N trajectories: x0 (N, n_x), u (N, T, n_u), z (N, T, n_z)."""
    flat, unravel = ravel_pytree(theta)
    fixed_flat = (
        np.zeros(flat.shape, bool)
        if fixed is None
        else np.asarray(
            ravel_pytree(jax.tree_util.tree_map(lambda f: jnp.asarray(f, float), fixed))[0]
        )
        > 0
    )
    x0_mask = np.ones(x0.shape[1], bool) if x0_mask is None else np.asarray(x0_mask)
    cost = Cost(
        None if weight is None else jnp.asarray(weight),
        penalty,
        jnp.asarray(penalty_weight if penalty is not None else 0.0, flat.dtype),
    )
    return FitProblem(
        model=model,
        cost=cost,
        u=jnp.asarray(u),
        z=jnp.asarray(z),
        theta_base=flat,
        theta_free=tuple(int(i) for i in np.flatnonzero(~fixed_flat)),
        unravel=unravel,
        x0_base=jnp.asarray(x0),
        x0_free=tuple(int(i) for i in np.flatnonzero(x0_mask)),
        project=None,
        lower=None,
        upper=None,
    )


def assert_columns_close(actual, expected, rtol):
    """Column by column (each free variable), ||a_j - e_j|| <= rtol ||e_j||: a norm over the
    whole matrix would hide a wrong column of small scale (x0 columns vs theta columns)."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    assert np.all(np.isfinite(actual))
    err = np.linalg.norm(actual - expected, axis=0)
    ref = np.linalg.norm(expected, axis=0)
    assert np.all(ref > 0), "a column of the reference Jacobian is zero: a useless test case"
    assert np.all(err <= rtol * ref), err / ref


@eqx.filter_jit
def closed_form(problem, pt, px, strategy):
    lin = problem.jacobian(Params(pt, px), strategy)
    return lin.r, lin.Jt, lin.Jx


def _residuals_of(problem):
    return lambda pt, px: problem.residuals(Params(pt, px))[0]


@eqx.filter_jit
def jacfwd_reference(problem, pt, px):
    return jax.jacfwd(_residuals_of(problem), argnums=(0, 1))(pt, px)


@eqx.filter_jit
def bridge(problem, pt, px, strategy):
    held = _Held(jnp.zeros(pt.shape, bool), pt)
    n = pt.shape[0]

    def f(pt, px):
        out = _residuals((pt, px), problem=problem, held=held, strategy=strategy, beyond=True)
        return out[: -n or None]

    return f(pt, px), jax.jacfwd(f, argnums=(0, 1))(pt, px)


#
# Test problems.
#


def rich_step(x, u, th):
    """Nonlinear 3-state map with a dict theta (vector, scalar and matrix leaves)."""
    k, c, M = th["k"], th["c"], th["M"]
    return x + 0.1 * jnp.stack(
        [
            k[0] * x[1] - c * x[0] ** 3 + u[0],
            -k[1] * jnp.sin(x[0]) + M[0, 0] * x[2] + M[0, 1] * u[1],
            -k[2] * x[2] + M[1, 0] * x[0] * x[1] + M[1, 1] * u[0],
        ]
    )


def rich_observe(x, u, th):
    """Outputs that depend on u and theta too."""
    return jnp.stack([x[0] + th["c"] * u[0], x[1] * x[2], jnp.tanh(th["k"][0] * x[2])])


RICH_THETA = {
    "k": jnp.array([1.2, 0.8, 0.5]),
    "c": jnp.array(0.3),
    "M": jnp.array([[0.4, -0.7], [0.9, 0.2]]),
}


def barrier(x, th):
    """An exponential barrier on x[0] plus a theta term: strictly positive everywhere."""
    return jnp.exp((x[0] - 1.0) / 0.5) + 0.1 * th["c"] ** 2 + 0.01


def rich_problem(N, T, seed, **kwargs):
    rng = np.random.default_rng(seed)
    model = oj.Model(rich_step, rich_observe)
    x0 = jnp.asarray(rng.uniform(-0.5, 0.5, (N, 3)))
    u = jnp.asarray(rng.standard_normal((N, T, 2)))
    _, zs = jax.vmap(lambda x0, u: oj.simulate(model, RICH_THETA, x0, u))(x0, u)
    z = zs + 0.05 * rng.standard_normal(zs.shape)
    # Evaluate away from the data's parameters, so residuals and Jacobians are generic.
    theta = jax.tree_util.tree_map(
        lambda a: a * (1 + 0.1 * rng.standard_normal(a.shape)), RICH_THETA
    )
    return make_problem(model, theta, x0 + 0.05, u, z, **kwargs)


L = np.array([[1.0, 0.0], [0.5, 1.0], [-0.3, 0.8]])

CASES = {
    # Fixed entries inside leaves, an x0 mask, three trajectories, a non-diagonal singular
    # PSD weight and a penalty, all at once.
    "fixed_elements-x0_mask-N3-nondiagonal_Q-penalty": lambda: rich_problem(
        3,
        15,
        0,
        fixed={"k": [False, True, False], "c": False, "M": [[False, True], [False, False]]},
        x0_mask=[True, False, True],
        weight=L @ L.T,
        penalty=barrier,
        penalty_weight=0.7,
    ),
    # A whole leaf fixed, a diagonal weight, one trajectory, no penalty.
    "fixed_leaf-diagonal_Q-N1": lambda: rich_problem(
        1, 20, 1, fixed={"k": False, "c": True, "M": False}, weight=np.array([1.0, 2.5, 0.3])
    ),
    # The satellite of Section 4 (RK4 with two substeps, tiny scales: theta ~ 1e-2,
    # x0 ~ 1e-3 .. 1e-5), everything free.
    "satellite_rk4": lambda: satellite_problem(),
    # n_x = 20 > 16: the "jacobian" strategy's A @ S is a matrix product, not elementwise.
    "coupled_nx20": lambda: coupled_problem(),
}


def coupled_problem():
    rng = np.random.default_rng(3)
    n = 20
    W = jnp.asarray(0.3 * rng.standard_normal((n, n)) / np.sqrt(n))

    def step(x, u, th):
        return jnp.tanh(W @ (th["a"] * x)) + th["b"] * u[0]

    model = oj.Model(step, lambda x, u, th: x[:5] * th["b"])
    theta = {"a": jnp.asarray(1 + 0.2 * rng.standard_normal(n)), "b": jnp.array(0.7)}
    x0 = jnp.asarray(rng.standard_normal((2, n)))
    u = jnp.asarray(rng.standard_normal((2, 12, 1)))
    z = jnp.asarray(rng.standard_normal((2, 12, 5)))
    return make_problem(model, theta, x0, u, z, x0_mask=np.arange(n) < 7)


def satellite_problem():
    rng = np.random.default_rng(2)
    model = oj.Model.from_ode(lambda w, M, J: (M - jnp.cross(w, J * w)) / J, 0.1, substeps=2)
    theta = jnp.array([0.0403, 0.0404, 0.0080])
    w0 = jnp.array([[9.915e-6, -1.102e-3, 1.3179e-5]])
    M = jnp.asarray(1e-5 + 1e-7 * rng.standard_normal((1, 50, 3)))
    _, z = oj.simulate(model, theta, w0, M)
    z = z + 1e-4 * rng.standard_normal(z.shape)
    return make_problem(model, theta * jnp.array([1.1, 0.9, 1.05]), w0 * 1.3, M, z)


@pytest.fixture(
    scope="module",
    params=[(c, s) for c in CASES for s in ("jacobian", "vjp")],
    ids=lambda p: "-".join(p),
)
def case(request):
    """Each case with both ways of evaluating the sensitivity recursion: formed per-step
    Jacobians after the forward pass ("jacobian") and matrix-free JVPs in the scan ("vjp")."""
    name, strategy = request.param
    problem = CASES[name]()
    pt, px = problem.split(problem.theta_base, problem.x0_base)
    return problem, pt, px, strategy


def test_closed_form_jacobian_equals_jacfwd_of_residuals(case):
    problem, pt, px, strategy = case
    r, Jt, Jx = closed_form(problem, pt, px, strategy)
    N, R = r.shape
    assert Jt.shape == (N, R, len(problem.theta_free))
    assert Jx.shape == (N, R, len(problem.x0_free))
    np.testing.assert_allclose(r, _residuals_of(problem)(pt, px), rtol=1e-13, atol=0)
    Jt_ref, Jx_ref = jacfwd_reference(problem, pt, px)
    # Jt_ref: (N, R, p); Jx_ref: (N, R, N, m), where only trajectory i's x0 moves r_i.
    assert_columns_close(Jt.reshape(N * R, -1), Jt_ref.reshape(N * R, -1), rtol=1e-10)
    for i in range(N):
        assert_columns_close(Jx[i], Jx_ref[i, :, i, :], rtol=1e-10)
        for j in range(N):
            if j != i:
                assert np.all(np.asarray(Jx_ref[i, :, j, :]) == 0)


def test_residuals_square_to_the_loss(case):
    """||r||^2 is the multi-step cost C of eq. (5)/(21) (mean over trajectories)."""
    problem, pt, px, _ = case
    r = _residuals_of(problem)(pt, px)
    theta, x0 = problem.theta_of(pt), problem.x0_of(px)
    C = oj.loss(
        problem.model,
        theta,
        x0,
        problem.u,
        problem.z,
        weight=problem.cost.weight,
        penalty=problem.cost.penalty,
        penalty_weight=float(problem.cost.penalty_weight),
    )
    assert float(jnp.sum(r**2)) == pytest.approx(float(C), rel=1e-12)
    # Fixed entries are constants: theta_of / x0_of put the base values back.
    fixed = np.setdiff1d(np.arange(problem.theta_base.size), problem.theta_free)
    flat = ravel_pytree(theta)[0]
    assert np.array_equal(np.asarray(flat[fixed]), np.asarray(problem.theta_base[fixed]))
    kept = np.setdiff1d(np.arange(problem.x0_base.shape[1]), problem.x0_free)
    assert np.array_equal(np.asarray(x0[:, kept]), np.asarray(problem.x0_base[:, kept]))


def test_optimistix_bridge_jvp_is_the_closed_form_jacobian(case):
    """The custom JVP that feeds optimistix gives the same Jacobian."""
    problem, pt, px, strategy = case
    r_b, (Jt, Jx) = bridge(problem, pt, px, strategy)
    r, Jt_cf, Jx_cf = closed_form(problem, pt, px, strategy)
    N, R = r.shape
    np.testing.assert_allclose(r_b, r.reshape(-1), rtol=1e-13, atol=0)
    assert_columns_close(Jt, Jt_cf.reshape(N * R, -1), rtol=1e-12)
    for i in range(N):
        assert_columns_close(Jx.reshape(N, R, N, -1)[i, :, i, :], Jx_cf[i], rtol=1e-12)


def test_optimistix_bridge_beyond_the_box_is_the_derivative_of_the_clipped_problem(case):
    """With bounds, LM and the minimisers get the derivatives of C(P(y)): jax.jacfwd of
    the residuals and jax.grad of the loss at the clipped point, where some entries of y
    lie below the box, some above and the rest inside (the clipped ones have zero
    columns; the unclipped model's Jacobian, which the bridge gave before, has none)."""
    problem, pt, px, strategy = case
    p = pt.shape[0]
    side = np.arange(p) % 3  # 0: below the box, 1: above it, 2: inside
    width = 0.1 * (1.0 + np.abs(np.asarray(pt)))
    lower = jnp.asarray(np.where(side == 0, pt + width, pt - width))
    upper = jnp.asarray(np.where(side == 1, pt - width, pt + width))
    boxed = eqx.tree_at(
        lambda q: (q.lower, q.upper), problem, (lower, upper), is_leaf=lambda x: x is None
    )
    held = _Held(jnp.zeros(p, bool), pt)

    def clipped(pt, px):
        return boxed.residuals(Params(jnp.clip(pt, lower, upper), px))[0].reshape(-1)

    @eqx.filter_jit
    def both(pt, px):
        def f(pt, px):
            out = _residuals((pt, px), problem=boxed, held=held, strategy=strategy, beyond=True)
            return out[:-p]

        def c(pt, px):
            return _loss((pt, px), problem=boxed, held=held, strategy=strategy, beyond=True)

        def c_ref(pt, px):
            return boxed.loss(Params(jnp.clip(pt, lower, upper), px))

        return (
            jax.jacfwd(f, argnums=(0, 1))(pt, px),
            jax.jacfwd(clipped, argnums=(0, 1))(pt, px),
            jax.jacfwd(c, argnums=(0, 1))(pt, px),
            jax.grad(c_ref, argnums=(0, 1))(pt, px),
        )

    (Jt, Jx), (Jt_ref, Jx_ref), (gt, gx), (gt_ref, gx_ref) = both(pt, px)
    inside = side == 2
    assert np.all(np.asarray(Jt)[:, ~inside] == 0.0) and np.all(np.asarray(gt)[~inside] == 0)
    assert_columns_close(np.asarray(Jt)[:, inside], np.asarray(Jt_ref)[:, inside], rtol=1e-12)
    Jx, Jx_ref = np.asarray(Jx).reshape(Jx.shape[0], -1), np.asarray(Jx_ref)
    assert_columns_close(Jx, Jx_ref.reshape(Jx_ref.shape[0], -1), rtol=1e-12)
    np.testing.assert_allclose(gt, gt_ref, rtol=1e-11, atol=1e-13 * np.abs(gt_ref).max())
    np.testing.assert_allclose(gx, gx_ref, rtol=1e-11, atol=1e-13 * np.abs(gx_ref).max())


def test_inactive_penalty_rows_are_zero_and_active_rows_match():
    """h = max(x0 - 0.1, 0)^2 enters as sqrt(lambda h): rows where h = 0 carry neither
    residual nor gradient (jacfwd gives 0 * inf = NaN there); active rows match jacfwd."""

    def one_sided(x, th):
        return jnp.maximum(x[0] - 0.1, 0.0) ** 2 + 0.0 * th["c"]

    problem = rich_problem(1, 20, 3, penalty=one_sided, penalty_weight=2.0)
    pt, px = problem.split(problem.theta_base, problem.x0_base)
    r, Jt, Jx = closed_form(problem, pt, px, "auto")
    n_data = 20 * 3
    h = np.asarray(r[0, n_data:])
    active = h > 0
    assert 2 <= active.sum() <= 18, h  # both kinds of rows are present
    J = np.concatenate([Jt[0], Jx[0]], axis=1)
    assert np.all(J[n_data:][~active] == 0.0)
    Jt_ref, Jx_ref = jacfwd_reference(problem, pt, px)
    J_ref = np.concatenate([Jt_ref[0], Jx_ref[0, :, 0, :]], axis=1)
    rows = np.concatenate([np.ones(n_data, bool), active])
    err = np.linalg.norm(J[rows] - J_ref[rows], axis=0)
    assert np.all(err <= 1e-10 * np.linalg.norm(J_ref[rows], axis=0))


def test_negative_penalty_is_reported_by_the_linearisation():
    """A signed h cannot be a squared residual: the linearisation reports min lambda h, which
    the least-squares solvers stop on (never a silent clip)."""

    def signed(x, th):
        return x[0] - 0.1 + 0.0 * th["c"]

    problem = rich_problem(1, 20, 3, penalty=signed, penalty_weight=2.0)
    params = problem.split(problem.theta_base, problem.x0_base)
    for strategy in ("jacobian", "vjp"):
        lin = eqx.filter_jit(problem.jacobian)(params, strategy)
        xs, _ = oj.simulate(
            problem.model, problem.theta_of(params.theta), problem.x0_base[0], problem.u[0]
        )
        assert float(lin.h_min) == pytest.approx(2.0 * float(jnp.min(xs[:, 0] - 0.1)), rel=1e-12)
        assert float(lin.h_min) < 0
    _, h_min = problem.residuals(params)
    assert float(h_min) < 0
