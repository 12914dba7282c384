"""Hybrid models (physics plus an `MLP` or a `Dictionary` in theta) through `fit`.

- gradients of `value_and_grad` and of `fit`'s problem against `jax.grad` of an
  independent rollout (a `lax.scan` of our own RK4, written here);
- the matrix-free Jacobian products (J v, J^T w) against `jax.jacfwd` of that rollout;
- `fit` with modules in theta: fixed parts, multistart, several trajectories, save/load;
- proximal regularisers in `fit(constraints=...)`: exact zeros that stay zero, the
  objective C + g, the errors of solvers that cannot take them;
- the staged pipelines of `experiments/duffing_hybrid.py` on a short record: support
  recovery of the missing cubic term and an MLP residual at the noise level;
- matrix-free Gauss-Newton / Levenberg-Marquardt against the dense solve.
"""

import sys
import types
import warnings
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import assert_tree_rel_close

import oneshot_jax as oj
from oneshot_jax import sparsity
from oneshot_jax.internal import (
    MATRIX_FREE_MIN_THETA,
    Cost,
    FitProblem,
    Params,
    check_data,
    fixed_mask,
    is_float_leaf,
    least_squares_solver,
    normal_blocks,
)
from oneshot_jax.residual import MLP, Dictionary, Features, count_parameters

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import duffing_hybrid as duffing  # noqa: E402

DT = duffing.DT


#
# An independent oracle: our own RK4 in a lax.scan, and the cost of eq. (5) by hand.
#


def rk4(rhs, x, u, theta, h):
    k1 = rhs(x, u, theta)
    k2 = rhs(x + (h / 2) * k1, u, theta)
    k3 = rhs(x + (h / 2) * k2, u, theta)
    k4 = rhs(x + h * k3, u, theta)
    return x + h * (k1 + 2 * k2 + 2 * k3 + k4) / 6


def scan_rollout(theta, x0, u):
    def body(x, u_k):
        x_next = rk4(duffing.hybrid_rhs, x, u_k, theta, DT)
        return x_next, x_next

    _, xs = jax.lax.scan(body, x0, u[:-1])
    return jnp.concatenate([x0[None], xs])


def oracle_value_and_grad(params, static, x0, u, z):
    """C of eq. (5) (mean over N trajectories' time points) and its autodiff gradient."""

    def cost(params, x0):
        theta = eqx.combine(params, static)
        xs = jax.vmap(lambda a, b: scan_rollout(theta, a, b))(x0, u)
        return jnp.mean(jnp.sum((xs[..., :1] - z) ** 2, axis=-1))

    return jax.jit(jax.value_and_grad(cost, argnums=(0, 1)))(params, x0)


def short_data(N=2, T=150, seed=0):
    us, zs, x0s = [], [], []
    for i in range(N):
        u, z, x0, _ = duffing.make_data(seed + i, T)
        us.append(u)
        zs.append(z)
        x0s.append(x0)
    return np.stack(x0s), np.stack(us), np.stack(zs)


def mlp_theta(key=0, widths=(8, 8), perturb=True):
    net = MLP(2, 1, widths, key=jax.random.PRNGKey(key))
    if perturb:  # move the zero last layer so that every layer's gradient is non-zero
        w = 0.1 * jax.random.normal(jax.random.PRNGKey(key + 1), net.layers[-1].weight.shape)
        net = eqx.tree_at(lambda m: m.layers[-1].weight, net, w)
    return {"c": jnp.asarray(0.25), "k": jnp.asarray(0.9), "r": net}


def dictionary_theta():
    feats = duffing.features()
    coef = 0.01 * jax.random.normal(jax.random.PRNGKey(3), (len(feats), 1))
    return {"c": jnp.asarray(0.25), "k": jnp.asarray(0.9), "r": Dictionary(feats, 1, coef=coef)}


THETAS = {"mlp": mlp_theta, "dictionary": dictionary_theta}


def fit_problem(theta, x0, u, z, fixed=None, penalty=None, weight=None):
    """The `FitProblem` that `fit` builds (no windows, no constraints)."""
    data = check_data(duffing.MODEL, theta, x0, u, z, weight)
    flat, unravel = jax.flatten_util.ravel_pytree(data.theta)
    free = np.flatnonzero(~fixed_mask(fixed, data.theta))
    pw = jnp.asarray(0.3 if penalty is not None else 0.0)
    return FitProblem(
        model=data.model,
        cost=Cost(data.weight, penalty, pw),
        u=jnp.asarray(data.u),
        z=jnp.asarray(data.z),
        theta_base=flat,
        theta_free=tuple(int(i) for i in free),
        unravel=unravel,
        x0_base=jnp.asarray(data.x0),
        x0_free=(0, 1),
        project=None,
        lower=None,
        upper=None,
    ), data


#
# Gradients and Jacobian products.
#


@pytest.mark.parametrize("residual", ["mlp", "dictionary"])
def test_hybrid_gradient_with_modules_in_theta_matches_autodiff(residual):
    theta = THETAS[residual]()
    x0, u, z = short_data()
    # theta holds the module itself: the library splits off its static parts.
    C, (g_theta, g_x0) = oj.value_and_grad(duffing.MODEL, theta, x0, u, z)
    params, static = eqx.partition(theta, eqx.is_inexact_array)
    C_ref, (g_ref, g_x0_ref) = oracle_value_and_grad(params, static, x0, u, z)
    assert_tree_rel_close(C, C_ref, rtol=1e-12)
    assert_tree_rel_close(g_theta, g_ref, rtol=1e-11)
    assert_tree_rel_close(g_x0, g_x0_ref, rtol=1e-11)
    assert all(float(jnp.linalg.norm(g)) > 0 for g in jax.tree_util.tree_leaves(g_theta))

    # fit's problem: the free entries (the physical part fixed) of the same gradient.
    problem, data = fit_problem(theta, x0, u, z, fixed={"c": True, "k": True, "r": False})
    params0 = problem.split(problem.theta_base, problem.x0_base)
    assert params0.theta.shape[0] == count_parameters(theta["r"])
    C_p, g_p = problem.value_and_grad(params0, "auto")
    g_flat, _ = jax.flatten_util.ravel_pytree(g_ref)
    np.testing.assert_allclose(C_p, C_ref, rtol=1e-12)
    free = np.asarray(problem.theta_free)
    assert_tree_rel_close(g_p.theta, g_flat[free], rtol=1e-11)
    assert_tree_rel_close(g_p.x0, g_x0_ref, rtol=1e-11)


@pytest.mark.parametrize("strategy", ["jacobian", "vjp"])
def test_matrix_free_products_match_the_jacobian_of_an_independent_rollout(strategy):
    """J v and J^T w of the residuals (weight, penalty, two trajectories, a fixed entry)
    against jax.jacfwd of the residuals of our own rollout."""
    theta = mlp_theta(widths=(4,))
    x0, u, z = short_data(T=60)
    weight = jnp.asarray([2.0])

    def penalty(x, th):  # theta-dependent, positive
        return th["c"] ** 2 * jnp.sum(x**2)

    fixed = {"c": False, "k": True, "r": False}
    problem, data = fit_problem(theta, x0, u, z, fixed=fixed, penalty=penalty, weight=weight)
    params = problem.split(problem.theta_base, problem.x0_base)
    static = data.static

    def residuals(p_theta, p_x0):
        th = eqx.combine(problem.theta_of(p_theta), static)
        x0 = problem.x0_of(p_x0)
        xs = jax.vmap(lambda a, b: scan_rollout(th, a, b))(x0, u)
        T = u.shape[1]
        scale = 1 / jnp.sqrt(u.shape[0] * T)
        r_e = (jnp.sqrt(weight) * (xs[..., :1] - z) * scale).reshape(u.shape[0], -1)
        h = jax.vmap(jax.vmap(lambda x: penalty(x, th)))(xs)
        return jnp.concatenate([r_e, jnp.sqrt(0.3 * h) * scale], axis=1)

    r_ref = jax.jit(residuals)(params.theta, params.x0)
    Jt, Jx = jax.jit(jax.jacfwd(residuals, argnums=(0, 1)))(params.theta, params.x0)
    rng = np.random.default_rng(0)
    v = jnp.asarray(rng.standard_normal(params.theta.shape))
    vx = jnp.asarray(rng.standard_normal(params.x0.shape))
    w = jnp.asarray(rng.standard_normal(r_ref.shape))

    @eqx.filter_jit
    def products(problem, params, v, vx, w):
        r, _, traj = problem.linearise(params, strategy)
        return r, problem.jvp(params, traj, v, vx, strategy), problem.vjp(params, traj, w, strategy)

    r, Jv, (gt, gx) = products(problem, params, v, vx, w)
    np.testing.assert_allclose(r, r_ref, rtol=1e-12, atol=1e-15)
    Jv_ref = jnp.einsum("nrp,p->nr", Jt, v) + jnp.einsum("nrmq,mq->nr", Jx, vx)
    assert_tree_rel_close(Jv, Jv_ref, rtol=1e-12)
    assert_tree_rel_close(gt, jnp.einsum("nrp,nr->np", Jt, w), rtol=1e-12)
    assert_tree_rel_close(
        gx, jnp.einsum("nrmq,nr->nmq", Jx, w)[jnp.arange(2), jnp.arange(2)], rtol=1e-12
    )


#
# fit with modules in theta.
#


def test_fit_with_an_mlp_in_theta_fixed_parts_multistart_and_save_load(tmp_path):
    x0, u, z = short_data(N=2, T=100)
    theta0 = mlp_theta(widths=(4,), perturb=False)
    arrays = lambda tree: jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))  # noqa: E731
    weights0 = arrays(theta0["r"])

    # The physics first: one boolean fixes the whole network.
    phys = oj.fit(
        duffing.MODEL,
        theta0,
        x0,
        u,
        z,
        fixed={"c": False, "k": False, "r": True},
        solver=oj.LevenbergMarquardt(max_steps=10),
    )
    assert isinstance(phys.theta["r"], MLP) and phys.theta["r"].activation is jax.nn.tanh
    for a, b in zip(arrays(phys.theta["r"]), weights0, strict=True):
        np.testing.assert_array_equal(a, b)
    assert float(phys.theta["k"]) != 0.9 and phys.x0.shape == (2, 2)

    # Then the network alone, the physical part fixed.
    net = oj.fit(
        duffing.MODEL,
        phys.theta,
        phys.x0,
        u,
        z,
        fixed={"c": True, "k": True, "r": False},
        solver=oj.Adam(1e-2, 1e-3, max_steps=20),
    )
    assert float(net.theta["c"]) == float(phys.theta["c"])
    assert float(net.theta["k"]) == float(phys.theta["k"])
    moved = [not np.array_equal(a, b) for a, b in zip(arrays(net.theta["r"]), weights0)]
    assert all(moved) and float(net.loss) < float(phys.loss)
    assert len(net.names) == count_parameters(theta0["r"])
    # The result simulates with the trained module.
    _, zhat = net.simulate(u, x0=net.x0)
    np.testing.assert_allclose(zhat - z, net.residuals, atol=1e-12)

    # Save and load: the arrays round-trip, `like=` rebuilds the module.
    path = tmp_path / "hybrid.npz"
    net.save(path)
    back = oj.load_result(path, like=theta0)
    assert isinstance(back.theta["r"], MLP)
    for a, b in zip(arrays(back.theta), arrays(net.theta), strict=True):
        np.testing.assert_array_equal(a, b)
    feats = jnp.asarray([0.3, -0.2])
    np.testing.assert_array_equal(back.theta["r"](feats), net.theta["r"](feats))

    # Multistart: two networks (vmapped initialisation) on the two trajectories.
    nets = eqx.filter_vmap(lambda k: MLP(2, 1, (4,), key=k, zero_last=False, scale=0.1))(
        jax.random.split(jax.random.PRNGKey(5), 2)
    )
    starts = {"c": jnp.asarray([0.25, 0.35]), "k": jnp.asarray([0.9, 1.1]), "r": nets}
    ms = oj.fit(
        duffing.MODEL,
        starts,
        x0,
        u,
        z,
        multistart=True,
        solver=oj.Adam(1e-2, 1e-3, max_steps=20),
    )
    assert ms.starts.loss.shape == (2,) and np.all(np.isfinite(ms.starts.loss))
    assert float(ms.loss) == float(np.min(ms.starts.loss))
    assert isinstance(ms.theta["r"], MLP) and ms.theta["r"].layers[0].weight.shape == (4, 2)
    best = int(np.argmin(ms.starts.loss))
    np.testing.assert_array_equal(
        ms.theta["r"].layers[0].weight, ms.starts.theta["r"].layers[0].weight[best]
    )
    # Each start's whole theta (the module's activation with its row of parameters, which
    # `starts.theta` holds without it) and x0 give its loss, also after save and load.
    ms.save(tmp_path / "starts.npz")
    for r in (ms, oj.load_result(tmp_path / "starts.npz", like=ms.theta)):
        for s in (0, 1, -1):
            theta_s = r.start_theta(s)
            assert isinstance(theta_s["r"], MLP)
            C = oj.loss(duffing.MODEL, theta_s, r.starts.x0[s], u, z)
            np.testing.assert_allclose(float(C), r.starts.loss[s], rtol=1e-9)
    with pytest.raises(ValueError, match=r"`s` must be the index of one of the 2 starts"):
        ms.start_theta(2)
    with pytest.raises(ValueError, match=r"not of a multistart fit"):
        back.start_theta(0)


#
# Proximal regularisers in fit.
#


def sparse_start(u):
    feats = duffing.features()
    rms = feats.rms(duffing.physical_states(u), u)
    return {**duffing.PHYSICAL_START, "r": Dictionary(feats, 1, scale=rms)}


def test_a_bound_for_every_parameter_on_a_hybrid_names_the_network_weights_it_moved():
    """positive() holds every parameter, a network's weights too: the start's negative
    weights are clipped. The warning names the leaves the projection moved and says how
    to bound the physical parameters alone (a plain theta gets no such advice)."""
    x0, u, z = short_data(N=1, T=40)
    theta0 = mlp_theta(widths=(4,), perturb=False)
    with pytest.warns(UserWarning) as record:
        oj.fit(
            duffing.MODEL,
            theta0,
            x0,
            u,
            z,
            solver=oj.LevenbergMarquardt(max_steps=2),
            constraints=oj.constraints.positive(),
        )
    (msg,) = [str(w.message) for w in record if "outside the constraint set" in str(w.message)]
    weights = np.concatenate(
        [np.ravel(a) for a in jax.tree_util.tree_leaves(eqx.filter(theta0["r"], eqx.is_array))]
    )
    assert f"{int(np.sum(weights <= 0))} entries moved, in r." in msg
    assert "box(lower={'k': 0.0})" in msg


class _Scalars(eqx.Module):
    a: Any
    b: Any


def test_a_module_of_physical_parameters_gets_no_advice_about_network_weights():
    """A theta that is a module of scalar parameters, its start outside a bound given for
    one of them: the warning spoke of "a network's weights" there too (it fired for any
    module in theta)."""
    model = oj.Model(lambda x, u, th: th.a * x + th.b * u)
    u = np.random.default_rng(0).standard_normal((30, 1))
    _, z = oj.simulate(model, _Scalars(0.5, 1.0), np.zeros(1), u)
    with pytest.warns(UserWarning, match="outside the constraint set") as record:
        oj.fit(
            model,
            _Scalars(jnp.asarray(0.95), jnp.asarray(1.0)),
            np.zeros(1),
            u,
            np.asarray(z),
            constraints=oj.constraints.box(upper={"a": 0.9}),
            estimate_x0=False,
        )
    assert not any("network" in str(w.message) for w in record)


def test_prox_in_fit_gives_exact_zeros_that_stay_zero_and_reports_c_plus_g():
    u, z, x0, _ = duffing.make_data(0, 200)
    lam = 3e-3
    reg = sparsity.l1(lam, where=duffing.COEF)
    theta0 = sparse_start(u)
    start = 0.05 * np.random.default_rng(1).standard_normal((16, 1))  # every term non-zero
    theta0 = eqx.tree_at(lambda th: th["r"].coef, theta0, jnp.asarray(start))
    res = oj.fit(
        duffing.MODEL,
        theta0,
        x0,
        u,
        z,
        solver=oj.Adam(2e-2, 1e-3, max_steps=300),
        regulariser=reg,
        history=302,
    )
    coef = np.asarray(res.theta["r"].coef)
    zeros = coef == 0.0
    assert 0 < zeros.sum() < coef.size  # a sparse, not an empty, selection
    # The loss is the objective C + g, and so is the history's last row.
    C = float(oj.loss(duffing.MODEL, res.theta, res.x0, u, z))
    np.testing.assert_allclose(res.loss, C + lam * np.abs(coef).sum(), rtol=1e-12)
    np.testing.assert_allclose(res.history.loss[-1], res.loss, rtol=1e-12)

    # Once a coefficient of the final zero set reaches zero, it stays exactly zero at every
    # later step (the path is recorded at every step).
    path = np.asarray(res.history.theta["r"].coef)[:, :, 0]  # (rows, 16)
    assert len(path) == 301
    for j in np.flatnonzero(zeros[:, 0]):
        at_zero = path[:, j] == 0.0
        first = int(np.argmax(at_zero))
        assert 0 < first < 300 and np.all(at_zero[first:])
    fixed = sparsity.fixed_zeros(res.theta, where=duffing.COEF)
    np.testing.assert_array_equal(fixed["r"].coef, zeros)
    assert fixed["c"] is False and fixed["k"] is False
    assert int(fixed_mask(fixed, eqx.filter(res.theta, eqx.is_inexact_array)).sum()) == zeros.sum()


def test_optax_with_a_prox_is_ista():
    """`Optax(optax.sgd(eta))` with `l1(lam, learning_rate=eta)` takes exactly the steps of
    proximal gradient descent written by hand with `value_and_grad`."""
    u, z, x0, _ = duffing.make_data(0, 120)
    theta0 = sparse_start(u)
    eta, lam, steps = 2e-2, 0.3, 15
    where = duffing.COEF
    res = oj.fit(
        duffing.MODEL,
        theta0,
        x0,
        u,
        z,
        solver=oj.Optax(optax.sgd(eta), max_steps=steps),
        regulariser=sparsity.l1(lam, where=where, learning_rate=eta),
    )
    params, static = eqx.partition(theta0, lambda a: isinstance(a, (float, jax.Array)))
    x = jnp.asarray(x0)
    for _ in range(steps):
        _, (g, g_x0) = oj.value_and_grad(duffing.MODEL, eqx.combine(params, static), x, u, z)
        params = jax.tree_util.tree_map(lambda p, d: p - eta * d, params, g)
        params = eqx.tree_at(
            lambda p: p["r"].coef, params, sparsity.soft_threshold(params["r"].coef, eta * lam)
        )
        x = x - eta * g_x0
    for key in ("c", "k"):
        np.testing.assert_allclose(res.theta[key], params[key], rtol=1e-12)
    np.testing.assert_allclose(res.theta["r"].coef, params["r"].coef, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(res.x0, x, rtol=1e-12)
    assert np.array_equal(np.asarray(res.theta["r"].coef) == 0, np.asarray(params["r"].coef) == 0)
    assert np.any(np.asarray(params["r"].coef) == 0)


@pytest.mark.parametrize(
    "solver",
    [
        oj.LevenbergMarquardt(),
        oj.GaussNewton(),
        oj.LBFGS(),
        oj.Optimistix(__import__("optimistix").BFGS(rtol=1e-8, atol=1e-8)),
        [oj.Adam(), oj.LevenbergMarquardt()],
    ],
)
def test_solvers_that_need_a_smooth_objective_refuse_a_regulariser(solver):
    u, z, x0, _ = duffing.make_data(0, 30)
    with pytest.raises(ValueError, match="fixed_zeros"):
        oj.fit(
            duffing.MODEL,
            sparse_start(u),
            x0,
            u,
            z,
            solver=solver,
            regulariser=sparsity.l1(1e-3, where=duffing.COEF),
        )


def test_regulariser_errors_name_the_argument():
    u, z, x0, _ = duffing.make_data(0, 30)
    theta0 = sparse_start(u)
    with pytest.raises(ValueError, match="learning_rate"):
        oj.fit(
            duffing.MODEL,
            theta0,
            x0,
            u,
            z,
            solver=oj.Optax(optax.sgd(0.1)),
            regulariser=sparsity.l1(1e-3),
        )
    with pytest.raises(ValueError, match="`where`"):
        oj.fit(
            duffing.MODEL,
            theta0,
            x0,
            u,
            z,
            solver=oj.Adam(),
            regulariser=sparsity.l1(1e-3, where={"c": True}),
        )
    with pytest.raises(ValueError, match="`constraints`"):
        oj.fit(duffing.MODEL, theta0, x0, u, z, solver=oj.Adam(), constraints=[optax.sgd(1.0)])


def test_prox_with_fixed_entries_uses_a_zero_step():
    """`FitProblem.prox` on a group with a fixed entry: the fixed entry is held and the
    free entries get the exact prox in the metric (a group with a held non-zero entry is
    never zero)."""
    theta = {"a": jnp.asarray([0.5, 0.02, -0.01]), "b": jnp.asarray([0.01, -0.02])}
    x0, u = np.zeros(1), np.zeros((3, 1))
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: x)
    data = check_data(model, theta, x0, u, np.zeros((3, 1)))
    flat, unravel = jax.flatten_util.ravel_pytree(data.theta)
    fixed = {"a": np.array([True, False, False]), "b": False}
    reg = sparsity.group_lasso(1.0)
    from oneshot_jax.internal import Regulariser

    problem = FitProblem(
        model=data.model,
        cost=Cost(None, None, jnp.asarray(0.0)),
        u=jnp.asarray(u)[None],
        z=jnp.zeros((1, 3, 1)),
        theta_base=flat,
        theta_free=tuple(int(i) for i in np.flatnonzero(~fixed_mask(fixed, data.theta))),
        unravel=unravel,
        x0_base=jnp.zeros((1, 1)),
        x0_free=(),
        project=None,
        lower=None,
        upper=None,
        regulariser=Regulariser(reg.prox, reg.value, None, 1.0, None),
    )
    p = problem.split(flat, jnp.zeros((1, 1))).theta  # (0.02, -0.01, 0.01, -0.02)
    out = np.asarray(problem.prox(p, 0.1))
    # Group b has norm 0.0224 <= 0.1: zero. Group a keeps its fixed 0.5, so is not zero;
    # its free entries solve y_i (1 + 0.1 / ||y||) = v_i with ||y|| = sqrt(0.25 + |y_f|^2).
    np.testing.assert_array_equal(out[2:], 0.0)
    y = out[:2]
    norm = np.sqrt(0.25 + np.sum(y**2))
    np.testing.assert_allclose(y * (1 + 0.1 / norm), [0.02, -0.01], rtol=1e-12)
    assert np.all(y != 0)


#
# Matrix-free Gauss-Newton / Levenberg-Marquardt.
#


def small_dictionary_theta():
    keep = ("q^2", "q*v", "q^3", "v^3")
    feats = Features(
        2,
        1,
        degree=3,
        x_names=("q", "v"),
        u_names=("u",),
        exclude=tuple(n for n in duffing.features().names + ("q", "v", "u") if n not in keep),
    )
    assert feats.names == keep
    return {"c": jnp.asarray(0.2), "k": jnp.asarray(1.3), "r": Dictionary(feats, 1)}


def test_matrix_free_levenberg_marquardt_takes_the_dense_steps():
    """Same iterates, dense and matrix-free (two trajectories, so the x0 blocks are
    eliminated; 6 parameters, so Marquardt's diagonal is exact)."""
    x0, u, z = short_data(N=2, T=150)
    runs = {
        ls: oj.fit(
            duffing.MODEL,
            small_dictionary_theta(),
            x0,
            u,
            z,
            solver=oj.LevenbergMarquardt(linear_solver=ls, max_steps=6, rtol=0.0, cg_rtol=1e-13),
        )
        for ls in ("dense", "cg")
    }
    dense, cg = runs["dense"], runs["cg"]
    assert dense.num_steps == cg.num_steps == 6
    np.testing.assert_allclose(cg.history.loss, dense.history.loss, rtol=1e-8)
    path_d = np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(dense.history.theta)])
    path_c = np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(cg.history.theta)])
    np.testing.assert_allclose(path_c, path_d, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(cg.x0, dense.x0, rtol=1e-8)
    assert float(dense.loss) < 0.01 * float(dense.history.loss[0])  # the steps did work
    # The covariance (from the blocks, or evaluated at the end by the matrix-free run).
    np.testing.assert_allclose(cg.covariance, dense.covariance, rtol=1e-6)


def _dense_step(A, B, Cb, g_t, g_x, D_t, mu, active):
    """(A + mu D_t - sum_i B_i (C_i + mu D_i)^-1 B_i^T) h = -(g_t - ...), by hand."""
    Cd = Cb + mu * np.stack([np.diag(np.diag(c)) for c in Cb])
    CinvBt = np.linalg.solve(Cd, np.swapaxes(B, 1, 2))
    Cinvg = np.linalg.solve(Cd, g_x[..., None])[..., 0]
    S = A + mu * np.diag(D_t) - np.einsum("npm,nmq->pq", B, CinvBt)
    rhs = g_t - np.einsum("npm,nm->p", B, Cinvg)
    free = ~active
    h_t = np.zeros_like(g_t)
    h_t[free] = -np.linalg.solve(S[np.ix_(free, free)], rhs[free])
    return h_t, -(Cinvg + np.einsum("nmp,p->nm", CinvBt, h_t))


def test_matrix_free_normal_equations_match_the_dense_solve():
    """The matrix-free blocks (x0 columns, B_i, J^T r) equal those of the dense Jacobian;
    Marquardt's D is exact up to DIAG_PROBES free entries and the probe estimate mean
    (J^T w)^2 above; the conjugate-gradient step solves the same damped system (Gauss-
    Newton and Levenberg-Marquardt, with entries held by an active set)."""
    from oneshot_jax.internal import DIAG_PROBES

    x0, u, z = short_data(N=2, T=40)
    for theta in (small_dictionary_theta(), mlp_theta(widths=(4,))):
        problem, _ = fit_problem(theta, x0, u, z)
        params = problem.split(problem.theta_base, problem.x0_base)
        p = params.theta.shape[0]
        solver = oj.LevenbergMarquardt(linear_solver="cg", cg_rtol=1e-14, cg_max_steps=100)
        active = np.zeros(p, bool)
        active[1] = True

        @eqx.filter_jit
        def run(problem, params):
            lin = problem.jacobian(params, "jacobian")
            blocks, _ = solver._linearise(problem, params)
            steps = [solver._solve(problem, params, blocks, mu, active) for mu in (0.0, 1e-2)]
            return lin, blocks, steps

        lin, blocks, steps = run(problem, params)
        A, B, Cb, g_t, g_x = (np.asarray(a) for a in normal_blocks(lin.Jt, lin.Jx, lin.r))
        np.testing.assert_allclose(blocks.B, B, rtol=1e-11, atol=1e-15)
        np.testing.assert_allclose(blocks.Cb, Cb, rtol=1e-11)
        np.testing.assert_allclose(blocks.g_t, g_t, rtol=1e-11)
        np.testing.assert_allclose(blocks.g_x, g_x, rtol=1e-11)
        if p <= DIAG_PROBES:
            np.testing.assert_allclose(blocks.D_t, np.diag(A), rtol=1e-11)
        else:
            signs = jax.random.rademacher(
                jax.random.PRNGKey(0), (DIAG_PROBES, *lin.r.shape), dtype=lin.r.dtype
            )
            ref = np.mean(np.einsum("knr,nrp->kp", signs, lin.Jt) ** 2, axis=0)
            np.testing.assert_allclose(blocks.D_t, ref, rtol=1e-10)
            ratio = np.asarray(blocks.D_t) / np.diag(A)
            assert 0.2 < np.median(ratio) < 5  # an estimate of the right size
        for mu, step in zip((0.0, 1e-2), steps):
            if mu == 0.0 and p > DIAG_PROBES:
                continue  # a network's Gauss-Newton system is singular: no unique step
            h_t, h_x = _dense_step(A, B, Cb, g_t, g_x, np.asarray(blocks.D_t), mu, active)
            assert_tree_rel_close(step.theta, h_t, rtol=1e-8)
            assert_tree_rel_close(step.x0, h_x, rtol=1e-8)
            assert step.theta[1] == 0.0


def test_auto_linear_solver_rule():
    n = MATRIX_FREE_MIN_THETA
    assert least_squares_solver("auto", n) == "dense"
    assert least_squares_solver("auto", n + 1) == "cg"
    assert least_squares_solver("dense", 10 * n) == "dense"
    assert least_squares_solver("cg", 3) == "cg"

    # (a problem's shapes: N = 1 record of T samples, one output, two states)
    def record(T):
        return types.SimpleNamespace(
            z=np.zeros((1, T, 1)), x0_base=np.zeros((1, 2)), dtype=np.dtype(np.float64)
        )

    for solver in (oj.LevenbergMarquardt(), oj.GaussNewton()):
        assert solver._matrix_free(record(100), Params(jnp.zeros(n + 1), jnp.zeros((1, 2))))
        assert not solver._matrix_free(record(100), Params(jnp.zeros(n), jnp.zeros((1, 2))))
        # A dense Jacobian beyond DENSE_JACOBIAN_BYTES (3 x 8 bytes a sample and column).
        long = record(2**30 // (3 * 8 * 12) + 1)
        assert solver._matrix_free(long, Params(jnp.zeros(10), jnp.zeros((1, 2))))
        assert not solver._matrix_free(record(10**5), Params(jnp.zeros(10), jnp.zeros((1, 2))))
    # An MLP residual of a few hundred parameters is above the threshold.
    assert count_parameters(mlp_theta(widths=(16, 16))) > n
    with pytest.raises(ValueError, match="linear_solver"):
        oj.LevenbergMarquardt(linear_solver="qr")
    with pytest.raises(ValueError, match="cg_max_steps"):
        oj.GaussNewton(cg_max_steps=-1)


#
# The staged pipelines of experiments/duffing_hybrid.py on a short record.
#


# The sparse-dictionary pipeline (every wrong candidate exactly zero, the cubic coefficient
# within 2 % at 40 dB SNR) is checked where it is documented: docs/guides/hybrid.md, which
# tests/test_docs.py runs.


def test_mlp_residual_reaches_the_noise_level():
    """The staged MLP fit (physics with the network held, then Adam and LM jointly) on two
    short records: the training loss reaches the noise variance and the simulation of a
    held-out record is 30 times closer than the physical model's. (The full claim,
    validation RMSE within 10 % of the noise level, needs three records of 2000 samples:
    `python experiments/duffing_hybrid.py`.)"""
    recs = [duffing.make_data(seed, 800) for seed in (0, 2)]
    u, z = np.stack([r[0] for r in recs]), np.stack([r[1] for r in recs])
    sigma2 = np.mean([r[3] ** 2 for r in recs])
    physics, joint = duffing.train_mlp(u, z, widths=(8, 8), adam_steps=700, lm_steps=50)
    assert isinstance(joint.theta["r"], MLP)
    assert float(joint.loss) < 1.1 * sigma2 < float(physics.loss)
    u_val, z_val, x0_val, sigma_val = duffing.make_data(1, 800)
    rmse = duffing.validation_rmse(joint.theta, u_val, z_val, x0_val) / sigma_val
    rmse_phys = duffing.validation_rmse(physics.theta, u_val, z_val, x0_val) / sigma_val
    assert rmse < 1.5 and rmse_phys > 30 * rmse


def test_l2_weight_decay_prox():
    v = {"w": jnp.asarray([1.0, -2.0, 0.5]), "b": jnp.asarray(3.0)}
    reg = sparsity.l2(0.5, where={"w": True, "b": False})
    out = reg.prox(v, {"w": jnp.asarray([0.2, 0.0, 0.2]), "b": jnp.asarray(0.2)})
    # argmin_y (lam / 2) y^2 + (y - v)^2 / (2 step): y = v / (1 + step lam); step 0 holds.
    np.testing.assert_allclose(out["w"], [1 / 1.1, -2.0, 0.5 / 1.1], rtol=1e-15)
    assert float(out["b"]) == 3.0
    np.testing.assert_allclose(reg.value(v), 0.25 * 5.25, rtol=1e-15)


def test_a_mask_on_a_whole_network_selects_its_arrays_only():
    """`sparsity.mask(lambda th: th["r"])` on an MLP selects the weights and biases, not
    the activation function, so weight decay on the whole network works in fit."""
    net = MLP(1, 1, (3,), key=jax.random.PRNGKey(0), zero_last=False)
    theta = {"a": jnp.asarray(0.5), "r": net}
    where = sparsity.mask(lambda th: th["r"])(theta)
    assert where["a"] is False and where["r"].activation is False
    assert all(b is True for b in jax.tree_util.tree_leaves(where["r"].layers))
    out = sparsity.l2(0.1, where=sparsity.mask(lambda th: th["r"])).prox(
        theta, jax.tree_util.tree_map(lambda p: 0.5 if is_float_leaf(p) else p, theta)
    )
    w0, w1 = net.layers[0].weight, out["r"].layers[0].weight
    np.testing.assert_allclose(w1, w0 / 1.05, rtol=1e-15)
    assert float(out["a"]) == 0.5 and out["r"].activation is net.activation


@pytest.mark.parametrize("solver", ["levenberg_marquardt", "lbfgs"])
def test_a_dense_jacobian_too_large_is_not_formed(monkeypatch, solver):
    """A long record with a few hundred parameters formed its dense Jacobian and forward
    sensitivities (gigabytes) for the first-order test's column norms and the covariance,
    even with a matrix-free solver, and the whole fit ended out of memory. Above the limit
    (lowered here to 1000 bytes, for a record of 40 samples and 4 free variables) "auto"
    solves by conjugate gradients, the column norms are estimated, the covariance is not
    computed (fit says why), and the fit still converges to the estimate of a fit within
    the limit."""
    from oneshot_jax.internal import strategy_module

    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u + th["c"] * jnp.tanh(x))
    rng = np.random.default_rng(1)
    u = rng.standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 0.5, "b": 1.0, "c": 0.2}, jnp.array([0.3]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))
    theta0 = {"a": 0.4, "b": 0.9, "c": 0.0}
    within = oj.fit(model, theta0, jnp.zeros(1), u, z, solver=solver)
    assert within.success and np.all(np.isfinite([float(within.std[k]) for k in theta0]))
    monkeypatch.setattr(strategy_module, "DENSE_JACOBIAN_BYTES", 1000)
    small = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u + th["c"] * jnp.tanh(x))
    with pytest.warns(UserWarning, match=r"not computed where its dense Jacobian would exceed"):
        r = oj.fit(small, theta0, jnp.zeros(1), u, z, solver=solver)
    assert r.success, r.message
    for k in theta0:
        assert float(r.theta[k]) == pytest.approx(float(within.theta[k]), abs=1e-5)
        assert np.isinf(float(r.std[k]))


def test_without_a_covariance_the_errors_are_unknown_not_nan(monkeypatch):
    """Above the covariance limit (lowered here to 2 free entries) fit warns, reports inf
    (unknown) standard errors, never NaN, and still reports its convergence."""
    from oneshot_jax.internal import assemble_module as _assemble

    monkeypatch.setattr(_assemble, "COVARIANCE_MAX_THETA", 2)
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u + th["c"] * x**2)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((40, 1))
    true = {"a": jnp.asarray(0.5), "b": jnp.asarray(1.0), "c": jnp.asarray(0.05)}
    _, z = oj.simulate(model, true, jnp.zeros(1), u)
    theta0 = {"a": jnp.asarray(0.4), "b": jnp.asarray(0.9), "c": jnp.asarray(0.0)}
    with pytest.warns(UserWarning, match="not computed above 2 free entries"):
        r = oj.fit(model, theta0, jnp.zeros(1), u, z, estimate_x0=False)
    assert r.success and r.covariance.shape == (0, 0)
    std = np.array([float(r.std[k]) for k in ("a", "b", "c")])
    assert np.all(np.isinf(std)) and not np.any(np.isnan(std))
    assert "(not computed)" in str(r)


def test_covariance_none_skips_it_and_leaves_the_fit_alone(monkeypatch, tmp_path):
    """`fit(covariance=None)` (MATLAB's EstimateCovariance false) does not compute the
    covariance (the routine that forms it fails here if it is called), warns of nothing,
    reports inf (unknown) standard errors and the same estimate, loss and stop as the
    default fit, which does compute it; and the result saves and loads."""
    from oneshot_jax.internal import assemble_module as _assemble

    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u + th["c"] * x**2)
    rng = np.random.default_rng(1)
    u = rng.standard_normal((60, 1))
    true = {"a": jnp.asarray(0.5), "b": jnp.asarray(1.0), "c": jnp.asarray(0.05)}
    _, z = oj.simulate(model, true, jnp.asarray([0.2]), u)
    z = z + 0.01 * rng.standard_normal(z.shape)
    theta0 = {"a": jnp.asarray(0.4), "b": jnp.asarray(0.9), "c": jnp.asarray(0.0)}
    # with a penalty too (a Newey-West covariance is refused there; no covariance is not)
    kw = dict(penalty=lambda x, th: 1e-3 * x[0] ** 2)
    full = oj.fit(model, theta0, jnp.zeros(1), u, z, **kw)
    assert full.success and full.covariance.shape == (3, 3)
    assert np.all(np.isfinite([float(full.std[k]) for k in theta0]))

    def refuse(*args, **kwargs):
        raise AssertionError("the covariance was computed")

    monkeypatch.setattr(_assemble, "covariance", refuse)
    jax.clear_caches()  # (the default fit's program holds the covariance: trace anew)
    with pytest.raises(AssertionError, match="was computed"):  # the patch bites
        oj.fit(model, theta0, jnp.zeros(1), u, z, **kw)
    for none in (None, "none"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            r = oj.fit(model, theta0, jnp.zeros(1), u, z, covariance=none, **kw)
        assert r.stop_reason == full.stop_reason and r.success
        assert float(r.loss) == float(full.loss)
        for k in theta0:
            assert float(r.theta[k]) == float(full.theta[k])
            assert np.isinf(float(r.std[k]))
        assert np.all(np.isinf(r.x0_std)) and r.covariance.shape == (0, 0)
        assert r.diagnostics["covariance"] == "none"
        assert str(r).count("(not computed)") == 4
    oj.save_result(r, tmp_path / "r")
    back = oj.load_result(tmp_path / "r")
    assert back.diagnostics["covariance"] == "none" and "(not computed)" in str(back)


def _duffing_results(wrong=0, status="max_steps_reached", std=np.inf, c=0.214, k=4.64):
    """A run's results (`duffing.run`) with made-up numbers, for the page's reading."""
    stage = {"c": 0.3, "k": 1.0, "cubic_error": 0.0009, "loss": 8.5e-5, "validation": [1.0]}
    return {
        "T": 2000,
        "sigma": 0.0094,
        "physical": {"c": 0.44, "k": 2.67, "wall_s": 3.2, "validation": [50.7, 50.2, 48.1]},
        "dictionary": {
            "candidates": 16,
            "wall_s": 30.0,
            "stages": [
                {**stage, "label": "refit", "equations": "dv = -0.7993 q^3", "wrong": wrong}
            ],
        },
        "mlp": {
            "parameters": 107,
            "wall_s": 59.0,
            "noise_variance": 1e-4,
            "stages": [
                {
                    "label": "joint",
                    "c": c,
                    "k": k,
                    "loss": 1.05e-4,
                    "status": status,
                    "validation": [1.158, 1.141, 1.03],
                }
            ],
            "physics_std": {"c": std, "k": std},
        },
    }


def test_the_duffing_page_reads_its_numbers_and_verdicts_from_the_run():
    """docs/case-studies/duffing_hybrid.md is written by `duffing_hybrid.py --publish`: the
    printed stages and every number and verdict of its reading come from the run."""
    res = _duffing_results()
    md = duffing.page(res, "python experiments/duffing_hybrid.py", "machine M; Python 3.")
    assert "Printed by `python experiments/duffing_hybrid.py` (T = 2000 samples per record; " in md
    assert "float64; machine M; Python 3):" in md
    assert duffing.report(res) in md
    assert "keeps exactly the missing term" in md and "is 0.09 % from -0.8" in md
    assert "from 48.10 to 50.70 sigma (the physical model) to 1.03 to 1.16 times" in md
    assert "stops at `max_steps`" in md and "c = 0.214 and k = 4.640" in md
    assert "are not those of the true system" in md
    assert "standard errors in the joint fit are inf (`fit` finds them not identifiable" in md
    other = duffing.findings(_duffing_results(wrong=2, status="converged", std=0.01, c=0.3))
    assert "keeps 2 wrong non-zero terms besides q^3" in other
    assert "The joint fit ends `converged`." in other and "max_steps" not in other
    assert "k = 4.640 are within 5 % of those of the true system" not in other
    assert "are not those of the true system" in other  # (k = 4.64)
    assert "(standard errors 0.01 and 0.01)." in other and "inf" not in other
    close = duffing.findings(_duffing_results(std=0.01, c=0.301, k=0.99))
    assert "c = 0.301 and k = 0.990 are within 5 % of those of the true system" in close
