"""Projections onto convex parameter sets (Section 3.3) as optax transforms."""

import re
import typing
import warnings
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import oneshot_jax as oj
from oneshot_jax import constraints as oc
from oneshot_jax import sparsity as sp


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


#
# The documented hand-written loop: chain the projection last, apply the updates, then
# project once more so that round-off cannot leave the set.
#


def hand_loop(proj, params, target, optimiser, steps=200):
    """`optimiser` on sum ||p - target||^2 with `proj` chained last; yields each iterate."""
    tx = optax.chain(optimiser, proj)
    state = tx.init(params)

    def loss(p):
        return sum(
            jnp.sum((a - b) ** 2)
            for a, b in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(target))
        )

    @jax.jit
    def step(params, state):
        grads = jax.grad(loss)(params)
        updates, state = tx.update(grads, state, params)
        params = optax.apply_updates(params, updates)
        params = proj.project(params)  # the documented re-projection
        return params, state

    for _ in range(steps):
        params, state = step(params, state)
        yield params


PARAMS0 = {"k": jnp.array([0.5, 2.0, -0.3]), "m": jnp.array(1.0)}
# The unconstrained minimiser lies outside every set below in some entries.
TARGET = {"k": jnp.array([-1.0, 5.0, 1e-14]), "m": jnp.array(-2.0)}


@pytest.mark.parametrize("optimiser", ["adam", "sgd"])
@pytest.mark.parametrize("kind", ["box", "non_negative", "positive"])
def test_hand_loop_iterates_are_exactly_feasible(kind, optimiser):
    if kind == "box":
        proj = oc.box(lower={"k": jnp.array([-0.2, 0.0, 1e-3]), "m": 0.25}, upper={"k": 3.0})
    elif kind == "non_negative":
        proj = oc.non_negative()
    else:
        proj = oc.positive(1e-6)
    lo, hi = proj.bounds(PARAMS0)
    params0 = proj.project(PARAMS0)
    last = None
    opt = optax.adam(0.05) if optimiser == "adam" else optax.sgd(0.1)
    for last in hand_loop(proj, params0, TARGET, opt):
        for p, a, b in zip(leaves(last), leaves(lo), leaves(hi)):
            assert np.all(p >= a) and np.all(p <= b), (p, a, b)  # exact: no round-off outside
    if optimiser == "adam":
        return  # constant-step Adam only hovers near the optimum
    # Projected gradient descent converged to the projection of the unconstrained
    # minimiser (a box is separable).
    expected = jax.tree_util.tree_map(jnp.clip, TARGET, lo, hi)
    for p, e in zip(leaves(last), leaves(expected)):
        np.testing.assert_allclose(p, e, rtol=1e-6, atol=1e-6)
    # The active bounds are attained exactly.
    for p, e, a, b in zip(leaves(last), leaves(expected), leaves(lo), leaves(hi)):
        on_bound = (e == a) | (e == b)
        np.testing.assert_array_equal(p[on_bound], e[on_bound])


def test_apply_updates_alone_can_round_outside_and_project_restores_it():
    """Why the loop projects again: params + (P(params + u) - params) != P(params + u) in
    floating point, and here it lands one rounding below the lower bound."""
    lower = 4.431343583025715e-05
    proj = oc.box(lower=lower)
    params = jnp.array([0.1763570463792119])
    updates, _ = proj.update(jnp.array([-1.0]), proj.init(params), params)
    stepped = optax.apply_updates(params, updates)
    assert float(stepped[0]) < lower  # the update alone is infeasible by round-off
    assert float(stepped[0]) == pytest.approx(lower, rel=1e-12)
    assert float(proj.project(stepped)[0]) == lower


def test_projection_update_is_projected_step_minus_params():
    proj = oc.box(lower=0.0, upper=1.0)
    params = jnp.array([0.2, 0.9, 0.5])
    u = jnp.array([-0.5, 0.4, 0.1])
    updates, state = proj.update(u, proj.init(params), params)
    np.testing.assert_allclose(params + updates, [0.0, 1.0, 0.6], rtol=0, atol=1e-15)
    assert isinstance(state, optax.EmptyState)
    with pytest.raises(ValueError, match="params"):
        proj.update(u, proj.init(params), None)


def test_projection_works_under_jit():
    proj = oc.box(lower={"k": -1.0}, upper={"m": 0.5})
    tx = optax.chain(optax.sgd(1.0), proj)

    @jax.jit
    def step(params, state, grads):
        updates, state = tx.update(grads, state, params)
        return proj.project(optax.apply_updates(params, updates)), state

    grads = {"k": jnp.array([3.0, -1.0, 0.0]), "m": jnp.array(-4.0)}
    params, _ = step(PARAMS0, tx.init(PARAMS0), grads)
    np.testing.assert_array_equal(params["k"], [-1.0, 3.0, -0.3])
    assert float(params["m"]) == 0.5


#
# Bounds and projections themselves.
#


def test_box_bounds_broadcast_and_default_to_infinity():
    params = {"k": jnp.zeros(3), "m": jnp.array(0.0), "v": jnp.zeros((2, 2))}
    lo, hi = oc.box(lower={"k": jnp.array([0.0, 1.0, 2.0]), "m": -1.0}, upper=5.0).bounds(params)
    np.testing.assert_array_equal(lo["k"], [0.0, 1.0, 2.0])
    assert float(lo["m"]) == -1.0
    assert np.all(np.asarray(lo["v"]) == -np.inf) and lo["v"].shape == (2, 2)
    assert all(np.all(h == 5.0) for h in leaves(hi))
    p = oc.box(lower={"k": jnp.array([0.0, 1.0, 2.0]), "m": -1.0}, upper=5.0).project(
        {"k": jnp.array([-1.0, 7.0, 3.0]), "m": jnp.array(-3.0), "v": -9.0 * jnp.ones((2, 2))}
    )
    np.testing.assert_array_equal(p["k"], [0.0, 5.0, 3.0])
    assert float(p["m"]) == -1.0
    np.testing.assert_array_equal(p["v"], -9.0 * np.ones((2, 2)))
    # A list of parameters takes one bound per leaf; an array theta takes an array bound.
    lo, _ = oc.box(lower=[0.0, jnp.array([1.0, 2.0])]).bounds([jnp.array(3.0), jnp.zeros(2)])
    np.testing.assert_array_equal(lo[1], [1.0, 2.0])
    x = oc.box(lower=jnp.array([0.0, 1.0]), upper=jnp.array([1.0, 2.0])).project(
        jnp.array([-5.0, 5.0])
    )
    np.testing.assert_array_equal(x, [0.0, 2.0])
    # None entries of a list of numbers are unbounded, as a None bound is.
    lo, hi = oc.box(lower=[0.0, None, 1.0], upper=(None, 5.0, None)).bounds(jnp.zeros(3))
    np.testing.assert_array_equal(lo, [0.0, -np.inf, 1.0])
    np.testing.assert_array_equal(hi, [np.inf, 5.0, np.inf])
    with pytest.raises(
        ValueError, match=r"`lower` must hold real numbers .* got \[0.0, 'a', None\]"
    ):
        oc.box(lower=[0.0, "a", None]).bounds(jnp.zeros(3))


def test_non_negative_and_positive():
    x = jnp.array([-1.0, 0.0, 1e-300, 2.0])
    np.testing.assert_array_equal(oc.non_negative().project(x), [0.0, 0.0, 1e-300, 2.0])
    np.testing.assert_array_equal(oc.positive().project(x), [1e-12, 1e-12, 1e-12, 2.0])
    np.testing.assert_array_equal(oc.positive(0.5).project(x), [0.5, 0.5, 0.5, 2.0])
    lo, hi = oc.positive(0.5).bounds(x)
    assert np.all(np.asarray(lo) == 0.5) and np.all(np.asarray(hi) == np.inf)


def test_projections_are_idempotent():
    x = {"k": jnp.array([-3.0, 0.5, 9.0]), "m": jnp.array(2.0)}
    for proj in (
        oc.box(-1.0, 1.0),
        oc.non_negative(),
        oc.positive(),
        oc.project(lambda p: jax.tree_util.tree_map(lambda a: a / jnp.maximum(1.0, jnp.abs(a)), p)),
    ):
        once = proj.project(x)
        for a, b in zip(leaves(once), leaves(proj.project(once))):
            np.testing.assert_array_equal(a, b)


def simplex(p):
    """Euclidean projection onto the probability simplex (sort-based algorithm)."""
    u = jnp.sort(p)[::-1]
    css = jnp.cumsum(u) - 1.0
    k = jnp.arange(1, p.size + 1)
    rho = jnp.max(jnp.where(u - css / k > 0, k, 0))
    return jnp.maximum(p - css[rho - 1] / rho, 0.0)


def test_general_projection_in_a_hand_loop():
    proj = oc.project(simplex)
    assert proj.bounds is None
    target = jnp.array([0.9, 0.6, -0.2, 0.1])
    last = None
    for last in hand_loop(proj, simplex(jnp.ones(4)), target, optax.sgd(0.1)):
        assert np.all(np.asarray(last) >= 0.0)
        assert float(jnp.sum(last)) == pytest.approx(1.0, abs=1e-12)
    # Projected gradient descent: min ||p - t||^2 on the simplex is the projection of t.
    # (Adam would not do: its fixed points on the boundary of a non-box set are not this
    # point, since its diagonal scaling does not match the Euclidean projection.)
    np.testing.assert_allclose(last, simplex(target), atol=1e-12)
    np.testing.assert_allclose(simplex(target), [0.65, 0.35, 0.0, 0.0], atol=1e-15)


def test_combine():
    assert oc.combine(None) is None
    b = oc.box(0.0, 2.0)
    assert oc.combine(b) is b and oc.combine([b]) is b
    both = oc.combine([oc.box(lower=-1.0, upper=2.0), oc.box(lower=0.5, upper=3.0)])
    lo, hi = both.bounds(jnp.zeros(2))
    np.testing.assert_array_equal(lo, [0.5, 0.5])
    np.testing.assert_array_equal(hi, [2.0, 2.0])
    np.testing.assert_array_equal(both.project(jnp.array([-5.0, 5.0])), [0.5, 2.0])
    # A general projection in the list: no bounds, projections applied in order.
    mixed = oc.combine([oc.non_negative(), oc.project(lambda p: p / jnp.sum(p))])
    assert mixed.bounds is None
    np.testing.assert_allclose(mixed.project(jnp.array([-1.0, 1.0, 3.0])), [0.0, 0.25, 0.75])
    with pytest.raises(ValueError, match="`constraints`"):
        oc.combine("positive")
    with pytest.raises(ValueError, match="`constraints`"):
        oc.combine([b, lambda p: p])


def _sum_at_most_4(th):
    """The projection onto k + c + b <= 4."""
    e = jnp.maximum(th["k"] + th["c"] + th["b"] - 4.0, 0.0)
    return {n: v - e / 3 for n, v in th.items()}


@pytest.mark.parametrize("order", [1, -1])
def test_a_box_and_a_general_set_project_onto_their_intersection(order):
    """The composition of the two maps (4, 1, -1) to (3.67, 0.67, -0.33), outside the box
    (either order leaves one set); the projection onto the intersection is (3.5, 0.5, 0)
    (KKT: multipliers 0.5 for the sum, 1.5 for b >= 0)."""
    both = oc.combine([oc.non_negative(), oc.project(_sum_at_most_4)][::order])
    assert both.bounds is None and both.project is not None
    out = both.project({"k": jnp.array(4.0), "c": jnp.array(1.0), "b": jnp.array(-1.0)})
    np.testing.assert_allclose([out["k"], out["c"], out["b"]], [3.5, 0.5, 0.0], atol=1e-12)
    assert float(out["b"]) >= 0.0  # exactly inside the box (it goes last)
    inside = {"k": jnp.array(1.0), "c": jnp.array(2.0), "b": jnp.array(0.5)}
    assert both.project(inside) == inside  # a point of the intersection stays


def _below_the_plane(th):
    """The projection onto 1 b + 2 c + 0.5 k <= 2 (theta = (b, c, k))."""
    n = jnp.array([1.0, 2.0, 0.5])
    return th - jnp.maximum(n @ th - 2.0, 0.0) * n / (n @ n)


def test_dykstra_stops_only_when_its_increments_have_settled_too():
    """A halfspace then a box: from y = (2.035, 0.611, 5.520) the iterate stood still at
    the box's corner (0.8, 0.1, 3) for a cycle while the halfspace's increment was still
    changing, and the projection stopped there, outside the halfspace (n.x = 2.5), and a
    fit of z = theta reported `converged` at it, with a loss below the constrained
    minimum's. The projection is (0.3, 0.1, 3) (KKT, checked by SLSQP)."""
    from scipy.optimize import minimize

    box = oc.box(lower=np.array([0.0, 0.1, 1.0]), upper=np.array([0.8, 0.5, 3.0]))
    cons = [oc.project(_below_the_plane), box]
    P = oc.combine(cons).project
    n = np.array([1.0, 2.0, 0.5])
    for y in ([2.03500512, 0.61083562, 5.51985257], [0.01332983, 1.93441316, 0.41110532]):
        y = np.array(y)
        exact = minimize(
            lambda v: np.sum((v - y) ** 2), np.array([0.4, 0.3, 2.0]), method="SLSQP",
            bounds=list(zip([0.0, 0.1, 1.0], [0.8, 0.5, 3.0])),
            constraints=[{"type": "ineq", "fun": lambda v: 2.0 - n @ v}],
            options={"ftol": 1e-15, "maxiter": 500},
        ).x  # fmt: skip
        np.testing.assert_allclose(np.asarray(P(jnp.asarray(y))), exact, atol=1e-7)
    np.testing.assert_allclose(np.asarray(P(jnp.asarray(y))), [0.01332983, 0.5, 1.0])
    # the fit: z = theta, so its minimiser is the projection of the data
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: th + 0.0 * x[0])
    z = np.tile([2.03500512, 0.61083562, 5.51985257], (20, 1))
    for solver in (oj.LevenbergMarquardt(), oj.LBFGS()):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            warnings.filterwarnings("error", message=".*outside the constraint set")
            r = oj.fit(
                model, jnp.array([0.5, 0.2, 1.5]), np.zeros(1), np.zeros((20, 0)), z,
                solver=solver, constraints=cons, estimate_x0=False,
            )  # fmt: skip
        assert r.success, (solver, r.message)
        np.testing.assert_allclose(np.asarray(r.theta), [0.3, 0.1, 3.0], atol=1e-8)


def test_a_fit_with_a_box_and_a_general_set_stays_in_both():
    rng = np.random.default_rng(0)
    dt = 0.05

    def step(x, u, th):
        a = -th["k"] * x[0] - th["c"] * x[1] + th["b"] * u[0]
        return jnp.array([x[0] + dt * x[1], x[1] + dt * a])

    model = oj.Model(step, lambda x, u, th: x[:1])
    u = rng.standard_normal((400, 1))
    _, z = oj.simulate(model, {"k": 4.0, "c": 0.5, "b": 1.0}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + 1e-2 * rng.standard_normal(np.shape(z))
    cons = [oc.positive(), oc.project(_sum_at_most_4)]
    losses = []
    for solver in (oj.LevenbergMarquardt(), oj.LBFGS()):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = oj.fit(
                model,
                {"k": 3.0, "c": 0.2, "b": 0.5},
                np.array([1.0, 0.0]),
                u,
                z,
                solver=solver,
                constraints=cons,
            )
        th = {n: float(v) for n, v in r.theta.items()}
        assert min(th.values()) > 0.0 and sum(th.values()) <= 4.0 + 1e-12, (solver, th)
        losses.append(float(r.loss))
        if isinstance(solver, oj.LevenbergMarquardt):
            assert r.success, r.message  # the constrained optimum: b at 0, the sum at 4
            np.testing.assert_allclose([th["b"], sum(th.values())], [0.0, 4.0], atol=1e-9)
    np.testing.assert_allclose(losses[1], losses[0], rtol=1e-6)


def test_a_general_set_active_at_the_optimum_with_a_parameter_in_small_units_converges():
    """a + b <= C active at the optimum, b entering the model as 0.01 b (its column 0.019
    of a's): started at the constrained optimum (SciPy's, on the face), LM, Gauss-Newton
    and L-BFGS said `stalled` or `no_progress`, "not a solution", with the measure 1.6e-6:
    each moved entry's cosine divided the gradient's round-off along the face by its own
    small column norm. The entries the projection moves are measured together now."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(0)
    T, S = 300, 0.01
    u = rng.standard_normal((T, 1))

    def simulate(a, b, d, x0):
        x, out = x0, []
        for k in range(T):
            out.append(x)
            x = a * x + b * u[k, 0] + d
        return np.array(out)

    z = (simulate(0.8, 0.5, -0.1, 1.0) + 0.05 * rng.standard_normal(T))[:, None]
    C = 0.8 + 0.4 / S  # (the unconstrained optimum has a + b = 0.8 + 0.5 / S)
    model = oj.Model(lambda x, u, th: th["a"] * x + S * th["b"] * u + th["d"])

    def face(th):
        over = jnp.maximum(th["a"] + th["b"] - C, 0.0)
        return {"a": th["a"] - over / 2, "b": th["b"] - over / 2, "d": th["d"]}

    ref = least_squares(
        lambda p: simulate(p[0], S * (C - p[0]), p[1], p[2]) - z[:, 0],
        [0.5, 0.0, 0.0], xtol=1e-15, ftol=1e-15, gtol=1e-15,
    )  # fmt: skip
    start = {"a": ref.x[0], "b": C - ref.x[0], "d": ref.x[1]}
    for solver in (oj.LevenbergMarquardt(), oj.GaussNewton(), oj.LBFGS()):
        r = oj.fit(model, start, ref.x[2:], u, z, solver=solver, constraints=oc.project(face))
        assert r.status == "converged", (solver, r.message)
        assert float(r.loss) == pytest.approx(np.mean(ref.fun**2), rel=1e-12)


def test_an_estimate_a_slow_intersection_leaves_outside_is_named():
    """The wedge 0 <= I1 <= 0.01 I0 as a box and a halfspace: they meet at an angle of
    0.01, and Dykstra's alternating projections need about 1e4 cycles; capped at 1000 they
    stop short, and LM returned I = (-0.962, 0), outside the halfspace, in silence. The fit
    warns with the distance; a fit whose estimate lies in the set does not."""
    s = 1e-2

    def half(th):  # the Euclidean projection onto {I1 <= s I0}
        a = jnp.array([-s, 1.0])
        return {"I": th["I"] - jnp.maximum(th["I"] @ a, 0.0) * a / (a @ a)}

    cons = [oc.box(lower={"I": np.array([-np.inf, 0.0])}), oc.project(half)]
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: x + th["I"] @ u)
    u = np.random.default_rng(0).standard_normal((100, 2))
    start = {"I": np.array([1.0, 0.005])}
    with pytest.warns(RuntimeWarning, match=r"outside the constraint set: the projection moves"):
        r = oj.fit(
            model, start, np.zeros(1), u, (u @ np.array([-1.0, -0.5]))[:, None],
            constraints=cons, estimate_x0=False,
        )  # fmt: skip
    assert float(r.theta["I"][1] - s * r.theta["I"][0]) > 1e-3 and not r.success
    with warnings.catch_warnings():  # data from inside the set: a feasible optimum
        warnings.simplefilter("error")
        r = oj.fit(
            model, start, np.zeros(1), u, (u @ np.array([2.0, 0.01]))[:, None],
            constraints=cons, estimate_x0=False,
        )  # fmt: skip
    assert r.success


def test_a_success_outside_the_constraint_set_is_not_reported():
    """z = theta = (k, b), k fixed at 2, and the halfspace k + 0.01 b <= 2.005 (so b <=
    0.5): the halfspace and {k = 2} meet at an angle of 0.01, and the fixed rounds of
    Dykstra's projections barely move b. LM reported `converged` at b = 0.997, outside
    the set, with a warning only. Its success is now the status `infeasible`, naming the
    solver's own stop; a set the estimate lies in keeps the success."""
    n = jnp.array([1.0, 1e-2])

    def half(th):
        return th - jnp.maximum(n @ th - 2.005, 0.0) * n / (n @ n)

    model = oj.Model(lambda x, u, th: x, lambda x, u, th: th + 0.0 * x[0])
    z, u = np.tile([2.0, 1.0], (20, 1)), np.zeros((20, 0))
    fixed = jnp.array([True, False])
    kw = dict(fixed=fixed, estimate_x0=False)
    # (the distance is the projection's, which moves the fixed entry too: the warning says
    # the free ones can lie further out)
    held = r"outside the constraint set.*with fixed entries held, the free ones can lie further"
    with pytest.warns(RuntimeWarning, match=held + r".*status 'infeasible'"):
        r = oj.fit(model, jnp.array([2.0, 0.4]), np.zeros(1), u, z,
                   constraints=oc.project(half), **kw)  # fmt: skip
    assert float(n @ r.theta) > 2.005 + 1e-3  # outside: the case this test is about
    assert r.status == "infeasible" and not r.success
    assert r.stop_info["solver_stop"] == "converged" and r.stop_info["infeasible"] > 1e-3
    assert r.message.startswith("the estimate lies outside the constraint set"), r.message
    assert "infeasible" in str(r)
    with warnings.catch_warnings():  # inside the set: the success stands, in silence
        warnings.simplefilter("ignore")
        warnings.filterwarnings("error", message=".*outside the constraint set")
        r = oj.fit(model, jnp.array([2.0, 0.4]), np.zeros(1), u, np.tile([2.0, 0.3], (20, 1)),
                   constraints=oc.project(half), **kw)  # fmt: skip
    assert r.success and float(r.theta[1]) == pytest.approx(0.3)


def test_a_success_on_sets_that_do_not_meet_is_not_reported():
    """A general projection (a <= 0.5) combined with a box (a >= 1): the sets do not meet.
    Dykstra's projection then ends in the box, the last set, where the combined
    projection stands still: LM reported `converged` at a = 1, outside the first set.
    Each set of the combination is now checked on its own, a nested combination's too,
    at every start. Where the sets meet, the success stands."""
    model = oj.Model.from_ode(lambda x, u, th: -th["a"] * x + u, 0.1)
    u = np.ones((40, 1))
    z = np.asarray(oj.simulate(model, {"a": jnp.array(2.0)}, jnp.array([0.5]), u)[1])
    below = oc.project(lambda th: {**th, "a": jnp.minimum(th["a"], 0.5)})
    theta0, x0 = {"a": jnp.array(2.0)}, jnp.array([0.5])
    for cons in (
        oc.combine([below, oc.box(lower={"a": 1.0})]),
        oc.combine([oc.combine([below, oc.positive()]), oc.box(lower={"a": 1.0})]),
    ):
        with warnings.catch_warnings(record=True) as caught:  # one fit: its warning and r
            warnings.simplefilter("always")
            r = oj.fit(model, theta0, x0, u, z, constraints=cons)
        outside = [w for w in caught if str(w.message).startswith("the estimate lies outside")]
        assert outside and issubclass(outside[0].category, RuntimeWarning)
        assert re.search("sets that do not meet never do", str(outside[0].message))
        assert float(r.theta["a"]) > 0.5 + 1e-3  # outside `below`: the case of this test
        assert r.status == "infeasible" and not r.success, r.status
        assert r.stop_info["solver_stop"] == "converged"
    # With several starts, each start's success is checked (the other start's stood).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(model, {"a": jnp.array([2.0, 3.0])}, x0, u, z, constraints=cons,
                   multistart=True)  # fmt: skip
    assert r.starts.stop_reason == ("infeasible", "infeasible"), r.starts.stop_reason
    assert r.starts.solver_stop == ("converged", "converged")
    with warnings.catch_warnings():  # sets that meet (0.2 <= a <= 0.5): the success stands
        warnings.simplefilter("ignore")
        warnings.filterwarnings("error", message="the estimate lies outside")
        r = oj.fit(
            model, theta0, x0, u, z, constraints=oc.combine([below, oc.box(lower={"a": 0.2})])
        )
    assert r.success and float(r.theta["a"]) == pytest.approx(0.5)


def test_invalid_constraints_raise():
    # These made the parameter NaN or infinite and the fit "diverged at step 0".
    with pytest.raises(ValueError, match="`lower` holds NaN"):
        oc.box(lower={"c": np.nan}).bounds({"c": jnp.zeros(()), "k": jnp.zeros(())})
    with pytest.raises(ValueError, match=r"`upper` holds -inf \(use None or \+inf"):
        oc.box(upper=-np.inf).bounds(jnp.zeros(2))
    with pytest.raises(ValueError, match=r"`lower` holds \+inf"):
        oc.box(lower=np.inf).project(jnp.zeros(2))
    with pytest.raises(ValueError, match="lower <= upper"):
        oc.box(lower=1.0, upper=0.0).bounds(jnp.zeros(2))
    with pytest.raises(ValueError, match="lower <= upper"):
        oc.box(lower=1.0, upper=0.0).project(jnp.zeros(2))
    with pytest.raises(ValueError, match="`lower`.*not in theta"):
        oc.box(lower={"nope": 0.0}).bounds({"k": jnp.zeros(2)})
    with pytest.raises(ValueError, match="`upper`"):
        oc.box(upper=jnp.zeros(3)).bounds({"k": jnp.zeros(2), "m": jnp.zeros(())})
    with pytest.raises(ValueError, match="`lower`"):
        oc.box(lower=jnp.zeros(3)).bounds(jnp.zeros(2))
    with pytest.raises(ValueError, match="`lower`"):
        oc.box(lower=[0.0]).bounds([jnp.zeros(()), jnp.zeros(())])
    with pytest.raises(ValueError, match="`eps`"):
        oc.positive(0.0)
    with pytest.raises(ValueError, match="`fn`"):
        oc.project("not callable")


def test_crossed_bounds_name_the_parameters():
    # (The message named no parameter: which of a dozen bounds was crossed was a search.)
    theta = {"m": 1.0, "k": 2.0, "phys": {"c": jnp.zeros(2)}}
    box = oc.box(lower={"k": 5.0, "phys.c": [0.0, 3.0]}, upper={"k": 1.0, "phys": {"c": 2.0}})
    with pytest.raises(ValueError, match="lower <= upper") as err:
        box.bounds(theta)
    assert "k (lower 5 > upper 1), phys.c[1] (lower 3 > upper 2)." in str(err.value)
    assert " m " not in str(err.value) and "phys.c[0]" not in str(err.value)
    with pytest.raises(ValueError, match=r"theta\[1\] \(lower 3 > upper 2\)\.$"):
        oc.box(lower=np.array([0.0, 3.0]), upper=np.array([1.0, 2.0])).project(jnp.zeros(2))


def test_a_bound_of_the_wrong_shape_names_its_parameter():
    box = oc.box(lower={"p": {"a": np.zeros(3)}})
    with pytest.raises(ValueError, match=r"the parameter 'p.a' of shape \(2,\)"):
        box.bounds({"p": {"a": np.zeros(2)}, "b": 1.0})


def test_equal_bounds_warn_that_the_entry_still_counts_as_estimated():
    """box(lower=upper) holds k at 0.3, but k stays a free entry: a standard error, one
    degree of freedom fewer; `fixed=` is what a known value needs."""
    model = oj.Model(lambda x, u, th: th["a"] * x + th["k"] * u)
    u = np.random.default_rng(0).standard_normal((60, 1))
    _, z = oj.simulate(model, {"a": 0.5, "k": 0.3}, np.zeros(1), u)
    pinned = oc.box(lower={"k": 0.3}, upper={"k": 0.3})
    with pytest.warns(UserWarning, match=r"equal for \['k'\].*fixed=") as rec:
        r = oj.fit(model, {"a": 0.4, "k": 0.3}, np.zeros(1), u, np.asarray(z), constraints=pinned)
    assert rec[0].filename == __file__ and "k" in r.names and float(r.theta["k"]) == 0.3


#
# One proximal type: a projection is the prox of its set's indicator.
#


def test_a_projection_is_the_prox_of_an_indicator():
    assert oc.ProjectionTransformation is oc.ProximalTransformation is sp.ProximalTransformation
    assert oc.combine is sp.combine
    x = {"k": jnp.array([-3.0, 0.5, 9.0]), "m": jnp.array(2.0)}
    for proj in (oc.box(-1.0, 1.0), oc.positive(), oc.project(lambda p: p)):
        for step in (0.0, 0.1, {"k": jnp.ones(3), "m": jnp.array(5.0)}):
            for a, b in zip(leaves(proj.prox(x, step)), leaves(proj.project(x))):
                np.testing.assert_array_equal(a, b)
        assert proj.value(x) == 0.0 and proj.strength is None and proj.learning_rate is None
    assert sp.l1(0.1).project is None and sp.l1(0.1).bounds is None


def test_combine_of_a_regulariser_and_a_projection_applies_them_in_order():
    """prox of l1, then the box: for v = 1.2, threshold 0.5 and lower bound 1.0 the
    soft-threshold gives 0.7 and the clip 1.0; the other order would give 0.7."""
    reg, lower = sp.l1(1.0, learning_rate=0.5), oc.box(lower=jnp.array([1.0, -1.0, 0.0]))
    both = oc.combine([reg, lower])
    v = jnp.array([1.2, -0.3, 0.2])
    expected = lower.project(reg.prox(v, 0.5))
    np.testing.assert_array_equal(expected, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(both.prox(v, 0.5), expected)
    assert not np.array_equal(reg.prox(lower.project(v), 0.5), expected)  # order matters
    # A mixed combination is a regulariser: no projection or bounds, g and lambda of l1.
    assert both.project is None and both.bounds is None
    assert both.strength == 1.0 and both.learning_rate == 0.5
    assert float(both.value(v)) == pytest.approx(1.7)
    assert both.terms == (reg, lower)
    # As an optax transform after sgd it is the two chained in that order.
    grads = jnp.array([0.4, 0.6, -0.1])
    params = jnp.array([2.0, 0.1, 0.1])
    tx_a = optax.chain(optax.sgd(0.5), both)
    tx_b = optax.chain(optax.sgd(0.5), reg, lower)
    sa, sb = tx_a.init(params), tx_b.init(params)
    pa = pb = params
    for _ in range(3):
        ua, sa = tx_a.update(grads, sa, pa)
        ub, sb = tx_b.update(grads, sb, pb)
        pa, pb = optax.apply_updates(pa, ua), optax.apply_updates(pb, ub)
        np.testing.assert_array_equal(pa, pb)
    # (1.8, -0.2, 0.15) -> (1.3, 0, 0); (1.1, -0.3, 0.05) -> (0.6, 0, 0) -> (1, 0, 0); ...
    np.testing.assert_allclose(pa, [1.0, 0.0, 0.0], rtol=0, atol=1e-15)
    # Projections alone combine into one projection whose update keeps no state.
    boxes = oc.combine([oc.box(lower=0.0), oc.box(upper=1.0)])
    assert boxes.project is not None and boxes.bounds is not None
    assert isinstance(boxes.init(params), optax.EmptyState)


def test_a_general_projection_with_a_fixed_entry_stays_in_the_set():
    """k + c + b <= 4.5 with b fixed at 0.8: projecting the whole theta and then restoring
    b left the set (k + c + b = 4.62 at the stop). With Dykstra's rounds every iterate
    is in the set, and the fit ends where the same fit with b written into the model and
    the projection onto k + c <= 3.7 ends."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + th["b"] * u[0]])

    model = oj.Model.from_ode(rhs, 0.05, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u = rng.standard_normal((300, 1))
    _, z = oj.simulate(model, {"k": 4.0, "c": 0.3, "b": 1.0}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)

    def sum_at_most(limit, names):
        def project(th):
            excess = jnp.maximum(sum(th[n] for n in names) - limit, 0.0) / len(names)
            return {k: v - excess if k in names else v for k, v in th.items()}

        return oj.constraints.project(project)

    x0 = np.array([z[0, 0], 0.0])
    held = oj.fit(
        model,
        {"k": 3.0, "c": 0.5, "b": 0.8},
        x0,
        u,
        z,
        solver=oj.LBFGS(),
        constraints=sum_at_most(4.5, ("k", "c", "b")),
        fixed={"b": True},
    )
    total = held.history.theta["k"] + held.history.theta["c"] + held.history.theta["b"]
    assert np.max(total) <= 4.5 + 1e-12 and float(held.theta["b"]) == 0.8

    def rhs_b(x, u, th):
        return rhs(x, u, {**th, "b": 0.8})

    plain = oj.Model.from_ode(rhs_b, 0.05, observe=lambda x, u, th: x[:1])
    direct = oj.fit(
        plain,
        {"k": 3.0, "c": 0.5},
        x0,
        u,
        z,
        solver=oj.LBFGS(),
        constraints=sum_at_most(3.7, ("k", "c")),
    )
    assert held.success and direct.success
    for name in ("k", "c"):
        assert abs(float(held.theta[name]) - float(direct.theta[name])) < 1e-6


class _Phys(eqx.Module):
    k: Any
    c: Any


def test_box_takes_bounds_written_as_thetas_own_module():
    """A Module theta bounded by a Module of bounds (None: unbounded): c >= 0.35 holds
    it above its true 0.3, k is free (the bounds were read as one scalar and raised)."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th.k * x[0] - th.c * x[1] + u[0]])

    model = oj.Model.from_ode(rhs, 0.05, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    _, z = oj.simulate(model, _Phys(jnp.array(4.0), jnp.array(0.3)), np.array([1.0, 0.0]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    res = oj.fit(
        model,
        _Phys(jnp.array(3.0), jnp.array(0.5)),
        np.array([1.0, 0.0]),
        u,
        z,
        constraints=oc.box(lower=_Phys(None, 0.35)),
    )
    assert float(res.theta.c) == 0.35 and abs(float(res.theta.k) - 4.0) < 0.2


class _Spring(eqx.Module):
    c: jax.Array
    k: jax.Array


def test_box_bounds_name_the_fields_of_a_module_theta():
    """A box on an equinox-module theta takes its fields by name, as on a dict theta (it
    said "`upper` must hold real numbers (a bound), got {'c': 0.2}"); an unknown field is
    named."""
    theta = _Spring(jnp.array(0.5), jnp.array([1.0, 2.0]))
    lo, hi = oc.box(lower={"k": 0.0}, upper={"c": 0.2}).bounds(theta)
    assert float(hi.c) == 0.2 and np.all(np.isinf(hi.k)) and np.all(lo.k == 0.0)
    assert np.isneginf(float(lo.c))
    with pytest.raises(ValueError, match=r"`upper` names fields that are not in theta's _Spring"):
        oc.box(upper={"q": 1.0}).bounds(theta)


def test_an_infeasible_estimate_is_not_called_a_converged_bad_minimum():
    """Sets that do not meet (w >= 1 and sum(w) <= 1): the fit warned "the fit reports
    converged, but its simulation fits an output worse than that output's mean ... a bad
    minimum" and only then that the estimate is infeasible, whose status it became."""
    rng = np.random.default_rng(1)
    U = rng.normal(size=(60, 4))
    z = (U @ np.array([1.5, -0.8, 0.05, 0.0]) + 0.1 * rng.normal(size=60))[:, None]
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: jnp.atleast_1d(u @ th["w"]))

    def half(th):
        return {"w": th["w"] - jnp.maximum(jnp.sum(th["w"]) - 1.0, 0.0) / 4}

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = oj.fit(model, {"w": np.ones(4)}, np.zeros(1), U, z, estimate_x0=False,
                   constraints=[oc.box(lower=1.0), oc.project(half)])  # fmt: skip
    texts = [str(w.message) for w in caught]
    assert r.status == "infeasible" and float(r.metrics["fit_percent"][0]) < 0
    assert any("outside the constraint set" in t for t in texts)
    assert not any("bad minimum" in t for t in texts), texts


def test_boxes_that_do_not_meet_are_refused_by_their_projection_too():
    """`combine([box(lower=1), box(upper=0)]).project(theta)` clipped in turn and returned
    zeros in silence (a hand-written loop's projection); `fit` refused the same boxes."""
    both = oc.combine([oc.box(lower=1.0), oc.box(upper=0.0)])
    with pytest.raises(ValueError, match="the boxes' intersection is empty"):
        both.project({"w": jnp.ones(3)})
    meet = oc.combine([oc.box(lower=-1.0), oc.box(upper=0.5)])
    np.testing.assert_array_equal(meet.project({"w": jnp.array([-3.0, 0.2, 4.0])})["w"],
                                  [-1.0, 0.2, 0.5])  # fmt: skip


def test_a_regulariser_with_two_sets_projects_onto_their_intersection():
    """`combine([l1, combine([general, box])])`: the inner combination (Dykstra's
    projection onto the intersection) was taken apart, and the sets applied one after
    the other; `combine([l1, general, box])` did so too. The regulariser's prox is now
    followed by the projection onto the intersection."""
    import oneshot_jax.sparsity as sp

    def half(th):  # sum(w) <= 1
        return {"w": th["w"] - jnp.maximum(jnp.sum(th["w"]) - 1.0, 0.0) / th["w"].size}

    sets = [oc.project(half), oc.box(lower=0.0)]
    v = {"w": jnp.array([2.0, -1.0, 0.5])}
    expected = oc.combine(sets).project(sp.l1(0.1).prox(v, 1.0))
    for both in (oc.combine([sp.l1(0.1), oc.combine(sets)]), oc.combine([sp.l1(0.1), *sets])):
        out = both.prox(v, 1.0)["w"]
        np.testing.assert_allclose(out, expected["w"], atol=1e-9)
        assert float(jnp.sum(out)) <= 1.0 + 1e-9 and float(jnp.min(out)) >= 0.0


def test_a_projection_of_a_jax_array_theta_is_checked_without_a_deprecated_call():
    """The projection's idempotence check read the dtype of a JAX array theta by
    `np.result_type(array)`, which NumPy deprecates (an error in its next releases)."""
    model = oj.Model(lambda x, u, th: th[0] * x + th[1] * u)
    u, z = np.ones((20, 1)), np.ones((20, 1))
    cap = oc.project(lambda th: th.at[1].set(jnp.minimum(th[1], 0.3)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warnings.simplefilter("error", DeprecationWarning)
        r = oj.fit(model, jnp.array([0.5, 0.2]), np.zeros(1), u, z, constraints=cap)
    assert float(r.theta[1]) <= 0.3


class _Phys(typing.NamedTuple):
    k: Any
    c: Any


def test_box_bounds_of_a_namedtuple_theta_in_its_own_form():
    """Bounds given as a NamedTuple (or a tuple, a list) of theta's own NamedTuple form,
    alone or inside a dict: a bare "P.__new__() missing 2 required positional arguments"
    before (a NamedTuple takes its fields as arguments)."""
    theta = _Phys(k=jnp.asarray(3.0), c=jnp.asarray([0.5, -2.0]))
    for upper in (_Phys(k=1.9, c=0.0), (1.9, 0.0), [1.9, 0.0]):
        projected = oc.box(upper=upper).project(theta)
        assert isinstance(projected, _Phys)
        np.testing.assert_array_equal(projected.k, 1.9)
        np.testing.assert_array_equal(projected.c, [0.0, -2.0])
    nested = {"phys": theta, "g": jnp.asarray(5.0)}
    projected = oc.box(upper={"phys": _Phys(k=1.9, c=0.0)}).project(nested)
    np.testing.assert_array_equal(projected["phys"].k, 1.9)
    np.testing.assert_array_equal(projected["g"], 5.0)


class _PhysNet(eqx.Module):
    k: Any
    c: Any
    net: eqx.nn.MLP


def test_a_module_of_bounds_with_none_for_its_network():
    """Bounds as a module of theta's own class, None where unbounded (the network's field,
    or a network of None leaves), as `fit`'s warning recommends: refused before ("`lower`
    must hold real numbers"), the None fields having no leaves when the module was
    flattened whole."""
    net = eqx.nn.MLP(2, 1, 4, 1, key=jax.random.PRNGKey(0))
    # (the arrays of theta, as `fit` projects them)
    theta = eqx.filter(_PhysNet(jnp.asarray(3.0), jnp.asarray(-1.0), net), eqx.is_array)
    nones = jax.tree_util.tree_map(lambda _: None, net)
    for unbounded in (None, nones):
        transform = oc.box(
            lower=_PhysNet(0.0, 0.0, unbounded), upper=_PhysNet(1.9, None, unbounded)
        )
        projected = transform.project(theta)
        assert float(projected.k) == 1.9 and float(projected.c) == 0.0
        for a, b in zip(leaves(eqx.filter(projected.net, eqx.is_array)), leaves(net)):
            np.testing.assert_array_equal(a, b)  # the network unbounded


#
# Pickling: a process pool (concurrent.futures, multiprocessing) sends its arguments
# pickled.
#


def _half_space(theta):
    """The projection onto a + b <= 1 (a module-level function: pickled by name)."""
    excess = jnp.maximum(theta["a"] + theta["b"] - 1.0, 0.0) / 2
    return {"a": theta["a"] - excess, "b": theta["b"] - excess}


def _pick_a(theta):
    return theta["a"]


def test_constraints_and_regularisers_pickle_and_act_alike_after():
    """Every factory's transformation (and their combinations, a `mask`) survives a
    pickle round trip (their maps were local closures: `Can't pickle local object`), and
    the copy projects, proxes, scores and updates as the original."""
    import pickle

    theta = {"a": jnp.asarray([1.5, -0.7]), "b": jnp.asarray(0.9)}
    steps = {"a": jnp.asarray([0.5, 0.2]), "b": jnp.asarray(0.3)}
    made = {
        "positive": oc.positive(),
        "box of arrays": oc.box(lower={"a": np.array([0.0, -1.0])}, upper=1.0),
        "project": oc.project(_half_space),
        "boxes": oc.combine([oc.positive(), oc.box(upper=1.2)]),
        "general and box": oc.combine([oc.project(_half_space), oc.non_negative()]),
        "l1 on a mask": sp.l1(0.4, where=sp.mask(_pick_a), learning_rate=0.1),
        "group_lasso": sp.group_lasso(0.3, learning_rate=0.1),
        "l2 and l1": sp.combine([sp.l2(0.2), sp.l1(0.1)]),
        "l1 and a set": oc.combine([sp.l1(0.1, learning_rate=0.1), oc.project(_half_space)]),
    }
    updates = jax.tree_util.tree_map(lambda p: 0.1 * jnp.ones_like(p), theta)
    for name, t in made.items():
        copy = pickle.loads(pickle.dumps(t))
        assert isinstance(copy, type(t)), name
        got = [copy.prox(theta, steps), copy.value(theta)]
        want = [t.prox(theta, steps), t.value(theta)]
        if t.project is not None:
            got.append(copy.project(theta))
            want.append(t.project(theta))
        if t.learning_rate is not None or t.project is not None:
            got.append(copy.update(updates, copy.init(theta), theta)[0])
            want.append(t.update(updates, t.init(theta), theta)[0])
        for g, w in zip(leaves(got), leaves(want), strict=True):
            np.testing.assert_array_equal(g, w, err_msg=name)
        # (and the copy is no identity: a projection moves theta, a regulariser shrinks it)
        moved = [np.ravel(a) for a in leaves(got[0])]
        assert not np.array_equal(np.concatenate(moved), [1.5, -0.7, 0.9]), name
    box = pickle.loads(pickle.dumps(oc.box(0.0, 2.0)))
    assert box.bounds.key == oc.box(0.0, 2.0).bounds.key
