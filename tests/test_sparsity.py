"""The proximal steps of `oneshot_jax.sparsity`: closed forms, exact zeros, and ISTA built
from `optax.sgd` + `l1` converging to the lasso solution computed by coordinate descent."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import oneshot_jax as oj
import oneshot_jax.sparsity as sp
from oneshot_jax import constraints as oc
from oneshot_jax.residual import MLP


def test_soft_threshold_closed_form_and_exact_zeros():
    rng = np.random.default_rng(0)
    v = rng.standard_normal(200)
    v[:5] = [0.3, -0.3, 0.0, 0.2999, -0.3001]
    t = 0.3
    out = np.asarray(sp.soft_threshold(jnp.asarray(v), t))
    expected = np.sign(v) * np.maximum(np.abs(v) - t, 0.0)
    np.testing.assert_array_equal(out == 0, np.abs(v) <= t)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-16)
    assert np.all(out[np.abs(v) <= t] == 0.0) and np.sum(np.abs(v) <= t) > 20
    # The prox of t|.|: y - v + t * subgradient(|y|) = 0.
    nz = out != 0
    np.testing.assert_allclose(out[nz] - v[nz] + t * np.sign(out[nz]), 0.0, atol=1e-15)
    assert np.all(np.abs(v[~nz]) <= t)


def test_a_nan_entry_stays_nan_not_a_zero():
    """`|v| > t` is False for NaN, so the thresholds returned an exact zero there: a failed
    step (a NaN gradient in a hand-written optax loop) read as a term selected out."""
    out = np.asarray(sp.soft_threshold(jnp.array([np.nan, 0.3, -np.inf, 0.05]), 0.1))
    assert np.isnan(out[0]) and out[1] == pytest.approx(0.2) and out[2] == -np.inf
    assert out[3] == 0.0
    W = jnp.array([[np.nan, 0.0, 0.0], [1e-3, 0.0, 0.0], [3.0, 4.0, 0.0]])
    out = np.asarray(sp.block_soft_threshold(W, 1.0, axis=-1))
    assert np.all(np.isnan(out[0])) and np.all(out[1] == 0.0)
    np.testing.assert_allclose(out[2], [2.4, 3.2, 0.0], rtol=1e-15)
    tx = optax.chain(optax.sgd(0.1), sp.l1(0.01, learning_rate=0.1))
    params = jnp.array([0.5, -0.2])
    updates, _ = tx.update(jnp.array([np.nan, 0.1]), tx.init(params), params)
    assert np.isnan(np.asarray(optax.apply_updates(params, updates))[0])


def test_prox_of_a_python_float_leaf_and_bad_steps():
    """A Python number is a parameter (`where=None` selects it): its prox raised
    AttributeError ('float' object has no attribute 'dtype'). A negative step moved entries
    away from zero, and a step of the wrong shape failed inside `gt`."""
    theta = {"a": jnp.array([0.5, -0.1]), "k": 1.0}
    for reg, k in ((sp.l1(2.0), 0.8), (sp.l2(2.0), 1.0 / 1.2), (sp.group_lasso(2.0), 0.8)):
        assert float(reg.prox(theta, 0.1)["k"]) == pytest.approx(k, rel=1e-12)
    with pytest.raises(ValueError, match="`step_size` must be finite and >= 0"):
        sp.l1(1.0).prox(theta, -0.1)
    with pytest.raises(ValueError, match="`step_size` must be finite and >= 0"):
        sp.l1(1.0).prox(theta, {"a": jnp.array([0.1, -0.1]), "k": 0.1})
    with pytest.raises(ValueError, match=r"`step_size`: its leaf 0 .* shape \(2,\), got \(3,\)"):
        sp.l1(1.0).prox(theta, {"a": jnp.ones(3), "k": 0.1})


def test_a_where_that_selects_no_parameter_is_refused():
    """`mask(lambda t: t["n"].activation)` picks a function, no parameter: the regulariser
    acted on nothing and the fit ran as if it were not there."""
    net = MLP(2, 1, (3,), key=jax.random.PRNGKey(0))
    theta = {"k": jnp.asarray(0.5), "n": net}
    reg = sp.l1(1.0, where=sp.mask(lambda t: t["n"].activation))
    with pytest.raises(ValueError, match="picks no floating parameter"):
        reg.prox(theta, 0.1)


def test_soft_threshold_idempotent_where_it_should_be():
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.standard_normal(50))
    once = sp.soft_threshold(v, 0.5)
    # A zero threshold is the identity; zeros of the prox are fixed points of any prox.
    np.testing.assert_array_equal(sp.soft_threshold(v, 0.0), v)
    twice = sp.soft_threshold(once, 0.5)
    np.testing.assert_array_equal(np.asarray(twice)[np.asarray(once) == 0], 0.0)
    # Thresholds add: prox_s(prox_t(v)) = prox_{s+t}(v) for the L1 norm.
    np.testing.assert_allclose(twice, sp.soft_threshold(v, 1.0), rtol=0, atol=1e-15)


def test_block_soft_threshold_zeroes_whole_groups():
    rng = np.random.default_rng(2)
    W = rng.standard_normal((12, 3))
    W[3] *= 1e-3  # a group far below the threshold
    t = 1.2
    out = np.asarray(sp.block_soft_threshold(jnp.asarray(W), t, axis=-1))
    norms = np.linalg.norm(W, axis=1)
    expected = W * np.maximum(1 - t / norms, 0)[:, None]
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-15)
    dead = norms <= t
    assert 0 < dead.sum() < len(dead)
    assert np.all(out[dead] == 0.0)  # whole rows, exactly
    assert np.all(out[~dead] != 0.0)
    # Optimality of a surviving group: y - v + t y / ||y|| = 0.
    y = out[~dead]
    np.testing.assert_allclose(
        y - W[~dead] + t * y / np.linalg.norm(y, axis=1, keepdims=True), 0.0, atol=1e-14
    )
    # axis=None: the whole array is one group.
    whole = np.asarray(sp.block_soft_threshold(jnp.asarray(W), t, axis=None))
    np.testing.assert_allclose(whole, W * (1 - t / np.linalg.norm(W)), rtol=1e-14)
    assert np.all(sp.block_soft_threshold(jnp.asarray(W), 100.0) == 0.0)


class Res(eqx.Module):
    coef: jax.Array
    net: jax.Array
    tag: str = eqx.field(static=True)


def params_tree():
    rng = np.random.default_rng(3)
    return {
        "k": jnp.asarray(0.05),
        "res": Res(
            jnp.asarray(rng.standard_normal((6, 2))), jnp.asarray(rng.standard_normal(4)), "r"
        ),
    }


def test_where_selects_leaves_and_entries():
    theta = params_tree()
    tx = sp.l1(1.0, where=sp.mask(lambda th: th["res"].coef))
    out = tx.prox(theta, 1.0)  # threshold 1.0 on the coefficients only
    assert out["k"] is theta["k"] and out["res"].net is theta["res"].net
    np.testing.assert_array_equal(out["res"].coef, sp.soft_threshold(theta["res"].coef, 1.0))
    assert out["res"].tag == "r"

    # Entry by entry: only the first column of coef.
    entries = jax.tree_util.tree_map(lambda _: False, theta)
    col = np.zeros((6, 2), bool)
    col[:, 0] = True
    entries = eqx.tree_at(lambda th: th["res"].coef, entries, col)
    out = sp.l1(1.0, where=entries).prox(theta, 1.0)
    c, c0 = np.asarray(out["res"].coef), np.asarray(theta["res"].coef)
    np.testing.assert_array_equal(c[:, 1], c0[:, 1])
    np.testing.assert_array_equal(c[:, 0], np.asarray(sp.soft_threshold(c0[:, 0], 1.0)))
    assert sp.l1(2.0, where=entries).value(theta) == pytest.approx(2 * np.abs(c0[:, 0]).sum())

    # None: every floating leaf; the per-coordinate step (a pytree) scales the threshold.
    steps = jax.tree_util.tree_map(lambda p: 0.5 * jnp.ones_like(p), theta)
    a = sp.l1(2.0).prox(theta, steps)
    b = sp.l1(1.0).prox(theta, 1.0)
    assert bool(eqx.tree_equal(a, b))
    assert float(a["k"]) == 0.0


def test_group_lasso_rows_of_a_dictionary():
    theta = params_tree()
    tx = sp.group_lasso(1.0, where=sp.mask(lambda th: th["res"].coef), axis=-1)
    out = tx.prox(theta, 1.2)
    np.testing.assert_array_equal(
        out["res"].coef, sp.block_soft_threshold(theta["res"].coef, 1.2, axis=-1)
    )
    assert out["res"].net is theta["res"].net
    norms = np.linalg.norm(np.asarray(theta["res"].coef), axis=1)
    assert tx.value(theta) == pytest.approx(norms.sum())


def test_update_is_prox_after_the_step_and_zeros_survive_apply_updates():
    theta = params_tree()
    grads = jax.tree_util.tree_map(lambda p: 0.3 * jnp.ones_like(p), theta)
    eta, lam = 0.1, 2.0
    tx = optax.chain(optax.sgd(eta), sp.l1(lam, learning_rate=eta))
    state = tx.init(theta)
    upd, state = tx.update(grads, state, theta)
    new = optax.apply_updates(theta, upd)
    ref = sp.l1(lam).prox(
        optax.apply_updates(theta, jax.tree_util.tree_map(lambda g: -eta * g, grads)), eta
    )
    zeros = np.asarray(ref["res"].coef) == 0
    assert zeros.any()
    assert np.all(np.asarray(new["res"].coef)[zeros] == 0.0)  # exact, through apply_updates
    assert bool(eqx.tree_equal(new, ref, rtol=1e-15, atol=1e-15))


def lasso_problem():
    rng = np.random.default_rng(4)
    m, n = 60, 20
    A = rng.standard_normal((m, n))
    x_true = np.zeros(n)
    x_true[[1, 5, 11]] = [2.0, -1.5, 0.8]
    b = A @ x_true + 0.1 * rng.standard_normal(m)
    return A, b, 0.1


def lasso_coordinate_descent(A, b, lam, sweeps=5000):
    """argmin (1/(2m)) ||A x - b||^2 + lam ||x||_1 by cyclic coordinate descent (NumPy)."""
    m, n = A.shape
    x = np.zeros(n)
    r = b.copy()
    col = (A * A).sum(axis=0) / m
    for _ in range(sweeps):
        x_old = x.copy()
        for j in range(n):
            r += A[:, j] * x[j]
            rho = A[:, j] @ r / m
            x[j] = np.sign(rho) * max(abs(rho) - lam, 0.0) / col[j]
            r -= A[:, j] * x[j]
        if np.max(np.abs(x - x_old)) < 1e-16:
            break
    return x


def test_sgd_plus_l1_converges_to_the_lasso_solution():
    A, b, lam = lasso_problem()
    m = A.shape[0]
    x_star = lasso_coordinate_descent(A, b, lam)
    support = x_star != 0
    assert 2 <= support.sum() < len(x_star) - 5  # a sparse, non-trivial solution

    A_j, b_j = jnp.asarray(A), jnp.asarray(b)
    grad = jax.grad(lambda x: 0.5 * jnp.sum((A_j @ x - b_j) ** 2) / m)
    eta = 1.0 / (np.linalg.norm(A, 2) ** 2 / m)  # 1 / L
    tx = optax.chain(optax.sgd(eta), sp.l1(lam, learning_rate=eta))

    def step(carry, _):
        x, state = carry
        upd, state = tx.update(grad(x), state, x)
        x = optax.apply_updates(x, upd)
        return (x, state), x == 0

    x0 = jnp.zeros(A.shape[1])
    (x, _), zero_trace = jax.lax.scan(step, (x0, tx.init(x0)), None, length=1500)
    x, zero_trace = np.asarray(x), np.asarray(zero_trace)
    np.testing.assert_allclose(x, x_star, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(x == 0, ~support)  # exact zeros off the support
    # Once the support is found, the zeros stay exactly zero at every later iterate.
    settled = np.all(zero_trace == ~support, axis=1)
    first = int(np.argmax(settled))
    assert settled[first:].all() and first < 500
    # The solution is a fixed point of the proximal gradient map.
    fixed = sp.l1(lam).prox(jnp.asarray(x_star) - eta * grad(jnp.asarray(x_star)), eta)
    np.testing.assert_allclose(fixed, x_star, rtol=0, atol=1e-12)


def run_adam(tx, A, b, steps):
    A_j, b_j = jnp.asarray(A), jnp.asarray(b)
    grad = jax.grad(lambda x: 0.5 * jnp.mean((A_j @ x - b_j) ** 2))

    def step(carry, _):
        x, state = carry
        upd, state = tx.update(grad(x), state, x)
        return (optax.apply_updates(x, upd), state), None

    x0 = jnp.zeros(A.shape[1])
    (x, _), _ = jax.lax.scan(step, (x0, tx.init(x0)), None, length=steps)
    return np.asarray(x)


def test_proximal_adam_converges_to_the_lasso_solution():
    A, b, lam = lasso_problem()
    x_star = lasso_coordinate_descent(A, b, lam)
    x = run_adam(sp.proximal_adam(1e-2, sp.l1(lam)), A, b, 2000)
    np.testing.assert_array_equal(x == 0, x_star == 0)  # the exact support, exact zeros
    np.testing.assert_allclose(x, x_star, rtol=0, atol=1e-10)
    # The same threshold chained after optax.adam (one step eta for every coordinate)
    # settles at the fixed points of a re-weighted penalty instead: far fewer zeros.
    chained = run_adam(optax.chain(optax.adam(1e-2), sp.l1(lam, learning_rate=1e-2)), A, b, 2000)
    assert np.sum(chained == 0) < np.sum(x_star == 0) // 2
    # Without a penalty proximal_adam is Adam.
    plain = run_adam(sp.proximal_adam(1e-2, sp.l1(0.0)), A, b, 200)
    np.testing.assert_allclose(plain, run_adam(optax.adam(1e-2), A, b, 200), rtol=1e-12)


def test_proximal_adam_floor_bounds_the_first_step():
    A, b, lam = lasso_problem()
    m = A.shape[0]
    x_ls = jnp.asarray(np.linalg.lstsq(A, b, rcond=None)[0])  # grad C = 0 up to round-off
    grad = jax.grad(lambda x: 0.5 * jnp.sum((jnp.asarray(A) @ x - jnp.asarray(b)) ** 2) / m)
    eta = 1e-3

    def one_step(tx):
        upd, _ = tx.update(grad(x_ls), tx.init(x_ls), x_ls)
        return np.asarray(optax.apply_updates(x_ls, upd))

    # Adam's own steps (floor 0): eta / |g| is huge where g ~ 0, and so is the threshold:
    # every coefficient lands on zero in one step, however large it was.
    collapsed = one_step(sp.proximal_adam(eta, sp.l1(lam), floor=0.0))
    assert np.all(collapsed == 0.0) and float(jnp.max(jnp.abs(x_ls))) > 1.0
    # The default floor (lam): no coordinate moves by more than 2 eta.
    moved = one_step(sp.proximal_adam(eta, sp.l1(lam))) - np.asarray(x_ls)
    assert np.max(np.abs(moved)) <= 2 * eta * (1 + 1e-12)
    assert sp.l1(lam).strength == lam


def test_group_prox_with_per_coordinate_steps_is_exact():
    rng = np.random.default_rng(5)
    V = rng.standard_normal((30, 4))
    D = rng.uniform(0.2, 2.0, size=V.shape)
    lam = 0.8
    Y = np.asarray(sp.group_lasso(lam, axis=-1).prox(jnp.asarray(V), jnp.asarray(D)))
    zero = np.all(Y == 0.0, axis=1)
    assert 0 < zero.sum() < len(zero)
    # Optimality of min lam sum ||y_G|| + sum (y - v)^2 / (2 d): zero iff ||v / d|| <= lam,
    # otherwise (y - v) / d + lam y / ||y|| = 0.
    np.testing.assert_array_equal(zero, np.linalg.norm(V / D, axis=1) <= lam)
    y, v, d = Y[~zero], V[~zero], D[~zero]
    kkt = (y - v) / d + lam * y / np.linalg.norm(y, axis=1, keepdims=True)
    np.testing.assert_allclose(kkt, 0.0, atol=1e-13)
    # Equal steps: block soft-thresholding.
    same = sp.group_lasso(lam, axis=-1).prox(jnp.asarray(V), jnp.full(V.shape, 0.7))
    np.testing.assert_allclose(same, sp.block_soft_threshold(V, 0.7 * lam, axis=-1), atol=1e-14)


def test_schedule_and_combine():
    theta = {"a": jnp.asarray([3.0, -0.2, 0.05]), "b": jnp.asarray([[1.0, 1.0], [0.1, 0.1]])}
    sched = optax.linear_schedule(1.0, 0.5, 10)
    tx = sp.combine(
        [
            sp.l1(0.1, {"a": True, "b": False}, learning_rate=sched),
            sp.group_lasso(1.0, {"a": False, "b": True}, axis=-1, learning_rate=sched),
        ]
    )
    state = tx.init(theta)
    zero = jax.tree_util.tree_map(jnp.zeros_like, theta)
    upd, state = tx.update(zero, state, theta)
    new = optax.apply_updates(theta, upd)
    np.testing.assert_allclose(new["a"], [2.9, -0.1, 0.0], atol=1e-15)
    np.testing.assert_allclose(new["b"][1], 0.0, atol=0)
    np.testing.assert_allclose(new["b"][0], 1 - 1 / np.sqrt(2), atol=1e-15)
    assert tx.value(theta) == pytest.approx(0.1 * 3.25 + np.sqrt(2) + 0.1 * np.sqrt(2))
    # The second update uses the schedule's second value (0.95).
    upd, _ = tx.update(zero, state, theta)
    np.testing.assert_allclose(optax.apply_updates(theta, upd)["a"][0], 3.0 - 0.095, atol=1e-15)
    # Sparse group lasso on the same leaf: l1 then group = the composition of the proxes.
    v = jnp.asarray([[3.0, -0.5], [0.2, 0.1]])
    both = sp.combine([sp.l1(1.0), sp.group_lasso(1.0, axis=-1)]).prox(v, 0.4)
    expected = sp.block_soft_threshold(sp.soft_threshold(v, 0.4), 0.4, axis=-1)
    np.testing.assert_array_equal(both, expected)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: sp.l1(-1.0), "`strength`"),
        (lambda: sp.l1(float("nan")), "`strength`"),
        (lambda: sp.l1("0.5"), "`strength` must be a finite scalar"),
        (lambda: sp.l1(True), "`strength` must be a finite scalar"),
        (lambda: sp.l1(0.1, learning_rate="0.1"), "`learning_rate` must be the step size"),
        (lambda: sp.l1(0.1, learning_rate=True), "`learning_rate` must be the step size"),
        (lambda: sp.l1(0.1, learning_rate=0.0), "`learning_rate`"),
        (lambda: sp.l1(0.1, learning_rate="fast"), "`learning_rate`"),
        (lambda: sp.group_lasso(0.1, axis="rows"), "`axis`"),
        (lambda: sp.group_lasso(0.1, axis=True), "`axis`"),
        (lambda: sp.group_lasso(0.1, axis=(0, 0)), "`axis`"),
        (lambda: sp.mask(3), "`select`"),
        (lambda: sp.combine([optax.sgd(0.1)]), "`regularisers`"),
    ],
)
def test_bad_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_where_and_step():
    theta = params_tree()
    with pytest.raises(ValueError, match="`where`"):
        sp.l1(0.1, where={"k": True}).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`where`"):
        entries = jax.tree_util.tree_map(lambda p: np.ones(np.shape(p), bool), theta)
        sp.group_lasso(0.1, where=entries).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`where`"):
        bad = jax.tree_util.tree_map(lambda p: np.ones(3, bool), theta)
        sp.l1(0.1, where=bad).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`select`"):
        sp.l1(0.1, where=sp.mask(lambda th: th["missing"])).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`axis`"):
        sp.group_lasso(0.1, axis=3).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`step_size`"):
        sp.group_lasso(0.1).prox(theta, {"k": 1.0})
    with pytest.raises(ValueError, match="`step_size`"):
        sp.l1(0.1).prox(theta, {"k": 1.0})
    with pytest.raises(ValueError, match="params"):
        tx = sp.l1(0.1, learning_rate=0.1)
        tx.update(theta, tx.init(theta))
    with pytest.raises(ValueError, match="`learning_rate`"):
        optax.chain(optax.sgd(0.1), sp.l1(0.1)).init(theta)
    with pytest.raises(ValueError, match="`regulariser`"):
        sp.proximal_adam(0.1, optax.sgd(0.1))
    with pytest.raises(ValueError, match="`learning_rate`"):
        sp.proximal_adam(-1.0, sp.l1(0.1))
    with pytest.raises(ValueError, match="`floor`"):
        sp.proximal_adam(0.1, sp.l1(0.1), floor=-1.0)


def test_soft_thresholds_check_their_threshold_and_compute_integers_in_floats():
    """A negative threshold moved entries away from zero ([0.5, -0.05] -> [0.6, -0.15]),
    an integer input truncated the threshold 0.5 to 0, and a threshold of the wrong shape
    failed inside JAX without naming it."""
    v = jnp.array([0.5, -0.05])
    for bad in (-0.1, np.nan, np.inf, jnp.array([0.1, -0.1])):
        with pytest.raises(ValueError, match="`threshold` must be finite and >= 0"):
            sp.soft_threshold(v, bad)
    with pytest.raises(ValueError, match="`threshold` must be finite and >= 0"):
        sp.block_soft_threshold(jnp.array([3.0, 4.0]), -1.0)
    with pytest.raises(TypeError, match="`threshold` must be a real number"):
        sp.soft_threshold(v, True)
    with pytest.raises(
        ValueError, match=r"`threshold` .* broadcasts to .* \(2,\), got shape \(3,\)"
    ):
        sp.soft_threshold(jnp.ones(2), jnp.ones(3))
    # A per-coordinate threshold is no block prox: one threshold per group at most.
    with pytest.raises(
        ValueError, match=r"`threshold` .* group norms \(3, 1\), got shape \(3, 2\)"
    ):
        sp.block_soft_threshold(jnp.ones((3, 2)), jnp.ones((3, 2)), axis=-1)
    per_group = sp.block_soft_threshold(jnp.ones((2, 2)), jnp.array([[0.0], [2.0]]), axis=-1)
    np.testing.assert_array_equal(per_group, [[1.0, 1.0], [0.0, 0.0]])
    np.testing.assert_allclose(sp.soft_threshold(jnp.array([3, -1]), 0.5), [2.5, -0.5])
    np.testing.assert_allclose(sp.block_soft_threshold(jnp.array([3, 4]), 1), [2.4, 3.2])
    # Traced thresholds (inside jit) are not checked by value, and still work.
    np.testing.assert_allclose(jax.jit(sp.soft_threshold)(v, 0.1), [0.4, 0.0])
    jitted = jax.jit(lambda t: sp.block_soft_threshold(jnp.array([3.0, 4.0]), t))
    np.testing.assert_allclose(jitted(1.0), [2.4, 3.2])


def test_group_lasso_axis_refuses_bools_and_repeats_and_takes_numpy_integers():
    """`axis=True` acted as axis 1, `axis=(1, 1)` failed later in JAX's sum, and a NumPy
    integer (np.int64(-1)) was refused."""
    with pytest.raises(ValueError, match="`axis` must be None, an int or a tuple of ints"):
        sp.group_lasso(1.0, axis=True)
    with pytest.raises(ValueError, match="`axis` must be None, an int or a tuple of ints"):
        sp.block_soft_threshold(jnp.ones((2, 2)), 1.0, axis=True)
    with pytest.raises(ValueError, match="`axis` must not repeat an axis"):
        sp.group_lasso(1.0, axis=(1, 1))
    with pytest.raises(ValueError, match=r"`axis` \(1, -1\) names one axis twice"):
        sp.group_lasso(1.0, axis=(1, -1)).prox(jnp.ones((2, 2)), 1.0)
    W = jnp.array([[3.0, 4.0], [0.1, 0.0]])
    expected = sp.block_soft_threshold(W, 1.0, axis=-1)
    np.testing.assert_array_equal(sp.group_lasso(1.0, axis=np.int64(-1)).prox(W, 1.0), expected)
    both = sp.group_lasso(1.0, axis=(np.int32(0), 1)).prox(W, 1.0)
    np.testing.assert_array_equal(both, sp.block_soft_threshold(W, 1.0))


def test_a_non_bool_scalar_in_where_is_refused():
    """`where={"a": 0.5}` acted as True (bool(0.5)); a float array was already refused."""
    theta = {"a": jnp.array([0.5, -0.05])}
    with pytest.raises(ValueError, match="`where` leaves must be bools.*got float64 of shape"):
        sp.l1(1.0, where={"a": 0.5}).prox(theta, 1.0)
    with pytest.raises(ValueError, match="`where`"):
        sp.l1(1.0, where={"a": "yes"}).value(theta)
    with pytest.raises(ValueError, match="`where`"):
        sp.group_lasso(1.0, where={"a": 1}).prox(theta, 1.0)
    # Boolean scalars, NumPy and JAX ones included, are still one bool for the leaf.
    for off in (False, np.bool_(False), np.array(False), jnp.array(False)):
        np.testing.assert_array_equal(
            sp.l1(1.0, where={"a": off}).prox(theta, 1.0)["a"], theta["a"]
        )


def test_update_with_params_of_another_structure_names_them():
    """Params of another structure than the updates failed with a bare pytree error."""
    tx = sp.l1(0.1, learning_rate=0.1)
    state = tx.init({"a": jnp.ones(3)})
    params = {"a": jnp.ones(3), "b": jnp.ones(3)}
    with pytest.raises(ValueError, match="`params` and `updates` .* must have the same"):
        tx.update({"a": jnp.ones(3)}, state, params)
    chained = sp.combine([sp.l1(0.1, learning_rate=0.1), sp.l2(0.1, learning_rate=0.1)])
    with pytest.raises(ValueError, match="`params` and `updates`"):
        chained.update({"a": jnp.ones(3)}, chained.init(params), params)
    upd, _ = tx.update({"a": jnp.zeros(3)}, state, {"a": jnp.ones(3)})
    np.testing.assert_allclose(upd["a"], -0.01)


def test_float32_parameters_stay_float32():
    theta = {"w": jnp.asarray([0.5, -0.01, 2.0], jnp.float32)}
    grads = {"w": jnp.asarray([0.1, 0.0, -0.2], jnp.float32)}
    for tx, zeros in [
        (optax.chain(optax.sgd(0.1), sp.l1(0.5, learning_rate=0.1)), [1]),
        (sp.proximal_adam(0.1, sp.l1(0.05)), [1]),
        (sp.proximal_adam(0.1, sp.group_lasso(100.0), floor=0.0), [0, 1, 2]),
    ]:
        upd, _ = tx.update(grads, tx.init(theta), theta)
        new = optax.apply_updates(theta, upd)
        assert new["w"].dtype == jnp.float32
        assert np.all(np.asarray(new["w"])[zeros] == 0.0)


#
# One proximal type: fit's `constraints=` (projections) and `regulariser=` keywords.
#


def _lin_step(x, u, theta):
    return theta["a"] * x + theta["b"] * u[0] + theta["c"] * u[0] ** 3


LIN = oj.Model(_lin_step)
LIN_THETA0 = {"a": np.array([0.5]), "b": np.array(0.3), "c": np.array(0.2)}


def _lin_data():
    u = np.random.default_rng(0).standard_normal((30, 1))
    z = np.asarray(oj.simulate(LIN, {"a": np.array([0.8]), "b": 0.6, "c": 0.0}, np.ones(1), u)[1])
    return u, z


def _lin_fit(**kw):
    u, z = _lin_data()
    return oj.fit(LIN, LIN_THETA0, np.ones(1), u, z, solver=oj.Adam(5e-2, max_steps=60), **kw)


def _same(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a.theta), jax.tree_util.tree_leaves(b.theta)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.x0, b.x0)
    assert float(a.loss) == float(b.loss)


def test_fit_takes_regulariser_and_constraints_as_two_keywords():
    where = {"a": False, "b": False, "c": True}
    reg, box = sp.l1(0.5, where=where), oc.box(upper={"a": 0.7})
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        new = _lin_fit(constraints=box, regulariser=reg)
        listed = _lin_fit(constraints=[box], regulariser=[reg])
    assert float(new.theta["c"]) == 0.0 and float(new.theta["a"][0]) == 0.7
    _same(new, listed)
    # The mixed form of 0.2 gives the same numbers, with a warning naming the new keyword;
    # so does a combination of both kinds in `constraints`.
    with pytest.warns(DeprecationWarning, match="regulariser="):
        old = _lin_fit(constraints=[reg, box])
    _same(new, old)
    with pytest.warns(DeprecationWarning, match="regulariser="):
        mixed = _lin_fit(constraints=sp.combine([reg, box]))
    _same(new, mixed)


@pytest.mark.parametrize(
    "where, fixed",
    [({"a": False, "b": False, "c": False}, None), ({"a": False, "b": False, "c": True}, "c")],
)
def test_a_regulariser_on_no_estimated_entry_is_refused(where, fixed):
    """A `where` selecting nothing ran as a plain fit in silence; one selecting held
    entries only added a constant lambda |c| to the loss. A zero strength is no error
    (a path of lambdas starts there), nor is a selection of held and estimated entries."""
    u, z = _lin_data()
    kw = dict(solver=oj.Adam(5e-2, max_steps=2), fixed=fixed)
    with pytest.raises(ValueError, match="`regulariser`: it acts on no entry of theta that"):
        oj.fit(LIN, LIN_THETA0, np.ones(1), u, z, regulariser=sp.l1(0.5, where=where), **kw)
    oj.fit(LIN, LIN_THETA0, np.ones(1), u, z, regulariser=sp.l1(0.0, where=where), **kw)
    both = {"a": False, "b": True, "c": True}
    oj.fit(LIN, LIN_THETA0, np.ones(1), u, z, regulariser=sp.l1(0.5, where=both), **kw)


def test_columns_a_regulariser_switched_off_are_not_blamed_on_the_data():
    """A strong l1 on a gain g sets it to 0 at the solution, where b (which g multiplies)
    acts on nothing: the warning said "not identifiable from these data", and called the
    regulariser's optimum (FIT below 0, the outputs' mean fits better) "likely a bad
    minimum", which `fit` itself does not say with a regulariser."""
    gain = oj.Model(lambda x, u, th: th["a"] * x + th["g"] * th["b"] * u[0])
    u = 1.0 + np.random.default_rng(0).standard_normal((30, 1))  # (z's mean is not 0)
    _, z = oj.simulate(gain, {"a": np.array([0.8]), "g": 1.0, "b": 0.6}, np.zeros(1), u)
    reg = sp.l1(100.0, where={"a": False, "g": True, "b": False})
    with pytest.warns(UserWarning) as rec:
        r = oj.fit(
            gain,
            {"a": np.array([0.8]), "g": 1.0, "b": 0.3},
            np.zeros(1),
            u,
            z,
            solver=oj.Adam(5e-2, max_steps=300),
            regulariser=reg,
            fixed={"a": True},
            estimate_x0=False,
        )
    assert r.success and float(r.theta["g"]) == 0.0 and r.metrics["fit_percent"][0] < 0
    (msg,) = [str(w.message) for w in rec if "rank-deficient" in str(w.message)]
    assert "at the solution of the regularised problem: parameters ['b']" in msg
    assert "from these data" not in msg and "bad minimum" not in msg


def test_a_regularised_fit_says_what_its_standard_errors_are():
    """The covariance of a regularised fit is that of C alone at the shrunk estimate (a
    probe's intervals excluded the truth, and zeros had intervals): the printout says so
    and names the refit; a fit without a regulariser does not."""
    reg = sp.l1(0.5, where={"a": False, "b": False, "c": True})
    r = _lin_fit(regulariser=reg)
    assert r.diagnostics.get("regularised") is True
    assert "(regularised: the standard errors and intervals below" in str(r)
    assert "fixed_zeros" in str(r)
    plain = _lin_fit()
    assert "regularised" not in (plain.diagnostics or {}) and "regularised:" not in str(plain)


def test_a_regulariser_with_a_general_projection_warns_that_it_may_not_converge():
    """Adam's prox (in its per-coordinate metric) then the Euclidean projection onto a
    general set is not the prox of their sum, whose fixed points need not be stationary:
    a warning. `Optax` with one step size takes the exact prox of the sum: none."""
    reg = sp.l1(0.5, where={"a": False, "b": False, "c": True})
    halfspace = oc.project(lambda t: {**t, "a": jnp.minimum(t["a"], 0.7)})
    with pytest.warns(UserWarning, match="regulariser with a general projection") as rec:
        _lin_fit(regulariser=reg, constraints=halfspace)
    assert rec[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _lin_fit(regulariser=reg, constraints=oc.box(upper={"a": 0.7}))
        u, z = _lin_data()
        ista = oj.Optax(optax.sgd(1e-2), max_steps=5)
        reg = sp.l1(0.5, where={"a": False, "b": False, "c": True}, learning_rate=1e-2)
        oj.fit(
            LIN, LIN_THETA0, np.ones(1), u, z, solver=ista, regulariser=reg, constraints=halfspace
        )


def test_a_projection_given_as_regulariser_names_the_argument():
    for bad in (oc.positive(), [sp.l1(0.1), oc.box(0.0, 1.0)], sp.combine([sp.l1(0.1), oc.box()])):
        with pytest.raises(ValueError, match="`regulariser`.*`constraints=`"):
            _lin_fit(regulariser=bad)
    with pytest.raises(ValueError, match="`regulariser`"):
        _lin_fit(regulariser=optax.sgd(0.1))
    with pytest.raises(ValueError, match="`regulariser`"):
        _lin_fit(regulariser="l1")


def _own_regulariser(prox):
    return sp.ProximalTransformation(
        init=lambda p: optax.EmptyState(),
        update=lambda u, s, p=None: (u, s),
        prox=prox,
        value=lambda p: 0.0,
    )


def test_a_regulariser_whose_prox_changes_shapes_or_moves_at_step_zero_is_refused():
    """A prox of one's own that returned (2,) for a scalar leaf was read back as a flat
    vector: the fit ran with b = a + 1 (its leaves shifted into each other's places)."""
    stacked = _own_regulariser(lambda p, t: jax.tree.map(lambda v: jnp.stack([v, v + 1.0]), p))
    with pytest.raises(ValueError, match=r"`regulariser`: its prox returned shape \(2, 1\)"):
        _lin_fit(regulariser=stacked)
    shifted = _own_regulariser(lambda p, t: jax.tree.map(lambda v: v + 0.01, p))
    with pytest.raises(ValueError, match="prox with a step of 0 must return theta unchanged"):
        _lin_fit(regulariser=shifted)


@pytest.mark.parametrize(
    "call",
    [
        lambda where: _lin_fit(regulariser=sp.l1(0.1, where=where)),
        lambda where: sp.fixed_zeros(LIN_THETA0, where=where),
    ],
    ids=["l1-in-a-fit", "fixed_zeros"],
)
def test_a_where_that_fails_on_the_parameters_is_named(call):
    """A callable `where` that raises on theta (a wrong key) was a bare KeyError."""
    with pytest.raises(ValueError, match=r"`where` must pick nodes.*KeyError: 'zz'"):
        call(lambda theta: theta["zz"])


def _elastic_net(A, z, lam1, lam2):
    """argmin (1/T) ||A w - z||^2 + lam1 ||w||_1 + (lam2 / 2) ||w||^2 by coordinate
    descent (NumPy, to round-off)."""
    T, p = A.shape
    w, r = np.zeros(p), z.copy()
    for _ in range(10000):
        moved = 0.0
        for j in range(p):
            rho = 2 / T * A[:, j] @ (r + A[:, j] * w[j])
            new = np.sign(rho) * max(abs(rho) - lam1, 0.0) / (2 / T * A[:, j] @ A[:, j] + lam2)
            r += A[:, j] * (w[j] - new)
            moved, w[j] = max(moved, abs(new - w[j])), new
        if moved < 1e-16:
            break
    return w


def test_combine_applies_l1_group_lasso_l2_in_the_order_that_is_exact():
    """The proxes were composed in the order given: `[l2, l1]` thresholded the shrunk
    values (not the elastic net's prox), `[group_lasso, l1]` was not the sparse group
    lasso's, and a fit started at the elastic-net optimum with `regulariser=[l2, l1]`
    measured a first-order residual of 1e-2 there and never reported success."""
    v = jnp.asarray([[1.0, -0.2, 0.5], [-2.0, 0.31, 0.05]])
    eta, lam1, lam2, lamg = 0.8, 0.3, 0.5, 0.4
    enet = np.asarray(sp.soft_threshold(v, eta * lam1)) / (1 + eta * lam2)
    for order in ([sp.l2(lam2), sp.l1(lam1)], [sp.l1(lam1), sp.l2(lam2)]):
        np.testing.assert_allclose(sp.combine(order).prox(v, eta), enet, rtol=1e-15)
    # l2 after a group penalty: the quadratic's prox of the sum is the shrunk group prox
    group = np.asarray(sp.block_soft_threshold(v, eta * lamg, axis=-1)) / (1 + eta * lam2)
    both = sp.combine([sp.l2(lam2), sp.group_lasso(lamg, axis=-1)])
    np.testing.assert_allclose(both.prox(v, eta), group, rtol=1e-15)
    sgl = sp.block_soft_threshold(sp.soft_threshold(v, eta * lam1), eta * lamg, axis=-1)
    both = sp.combine([sp.group_lasso(lamg, axis=-1), sp.l1(lam1)])
    np.testing.assert_allclose(both.prox(v, eta), sgl, rtol=1e-15)
    assert [t.kind for t in both.terms] == ["l1", "group_lasso"]
    # projections after the regularisers, also from inside a given combination
    lower = oc.box(lower=0.1)
    inner = oc.combine([lower, sp.l2(lam2)])
    out = sp.combine([inner, sp.l1(lam1)]).prox(v, eta)
    np.testing.assert_allclose(out, np.maximum(enet, 0.1), rtol=1e-15)
    # In a fit: started at the elastic-net optimum, either order reports success there.
    rng = np.random.default_rng(0)
    A = rng.standard_normal((80, 5))
    z = A @ np.array([1.0, 0.0, -0.5, 0.0, 0.02]) + 0.1 * rng.standard_normal(80)
    w = _elastic_net(A, z, 0.02, 0.5)
    assert np.sum(w == 0) >= 1 and np.sum(w != 0) >= 2
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: u @ th["w"][:, None])
    for regs in ([sp.l2(0.5), sp.l1(0.02)], [sp.l1(0.02), sp.l2(0.5)]):
        result = oj.fit(
            model, {"w": w}, np.zeros(1), A, z[:, None], estimate_x0=False,
            solver=oj.Adam(1e-4, max_steps=20), regulariser=regs, covariance=None,
        )  # fmt: skip
        assert result.status == "converged", result.message
        np.testing.assert_allclose(result.theta["w"], w, atol=1e-9)


def test_tol_grad_with_a_regulariser_is_refused():
    """||grad C|| is small at the least-squares point, where l1 has not acted yet: Adam
    with tol_grad and l1, started there, stopped at step 0 as a success with every term
    in. `tol_grad` is refused with a regulariser, for Adam and Optax alike."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((80, 5))
    z = A @ np.array([1.0, 0.0, -0.5, 0.0, 0.02]) + 0.1 * rng.standard_normal(80)
    w = np.linalg.lstsq(A, z, rcond=None)[0]
    model = oj.Model(lambda x, u, th: x, lambda x, u, th: u @ th["w"][:, None])
    for solver, reg in (
        (oj.Adam(1e-3, tol_grad=1e-3), sp.l1(0.02)),
        (oj.Optax(optax.sgd(0.1), tol_grad=1e-3), sp.l1(0.02, learning_rate=0.1)),
    ):
        with pytest.raises(ValueError, match=r"`tol_grad` \(0.001\) tests \|\|grad C\|\|"):
            oj.fit(model, {"w": w}, np.zeros(1), A, z[:, None], estimate_x0=False,
                   solver=solver, regulariser=reg)  # fmt: skip


def test_a_where_of_another_structure_is_named_briefly():
    """A `where` not shaped like theta printed both whole structures, hundreds of
    characters for a Dictionary's names and products."""
    from oneshot_jax.residual import Dictionary, Features

    theta = {"r": Dictionary(Features(2, 1, degree=3), 1), "c": jnp.array(0.3)}
    with pytest.raises(ValueError) as err:
        sp.l1(0.1, where={"c": True}).prox(theta, 1.0)
    text = str(err.value)
    assert "got a structure of 1 leaves" in text and "for parameters of" in text
    assert len(text) < 600, len(text)


#
# A regulariser whose prox does not compose with the set's projection.
#


def _linear_gains():
    """x+ = A x + B u with A known and x0 = 0: C is a quadratic in B (2 x 3), its outputs
    Phi vec(B); returns (model, theta0, u, z, Phi, zv)."""
    rng = np.random.default_rng(0)
    A = np.array([[0.8, 0.2], [-0.1, 0.7]])
    u = rng.standard_normal((200, 3))
    model = oj.Model(lambda x, u, th: th["A"] @ x + th["B"] @ u)

    def outputs(B):
        x, out = np.zeros(2), []
        for k in range(u.shape[0]):
            out.append(x.copy())
            x = A @ x + B @ u[k]
        return np.array(out)

    B_true = np.array([[1.0, 0.0, 0.5], [0.0, 0.0, -0.8]])
    z = outputs(B_true) + 0.05 * rng.standard_normal((200, 2))
    Phi = np.stack([outputs(e.reshape(2, 3)).ravel() for e in np.eye(6)], axis=1)
    return model, {"A": A, "B": np.full((2, 3), 0.3)}, u, z, Phi, z.ravel()


@pytest.mark.parametrize("solver", ["sgd", "adam"])
def test_a_group_lasso_in_a_box_reaches_the_prox_gradient_fixed_point(solver):
    """group_lasso on B's columns with B >= 0: clip(block_soft(v)) is not the prox of the
    sum (block_soft(max(v, 0)) is). ISTA converged to the composition's fixed point, above
    the optimum, and Adam, at the optimum, never passed its measure (max_steps)."""
    model, theta0, u, z, Phi, zv = _linear_gains()
    T, lam = u.shape[0], 0.1
    L = np.linalg.eigvalsh(2 / T * Phi.T @ Phi).max()
    B = np.zeros(6)  # the exact proximal gradient in NumPy
    for _ in range(20000):
        v = np.maximum(B - (-2 / T * Phi.T @ (zv - Phi @ B)) / L, 0.0).reshape(2, 3)
        norms = np.linalg.norm(v, axis=0, keepdims=True)
        B = (np.maximum(1 - lam / L / np.maximum(norms, 1e-300), 0) * v).ravel()
    where = sp.mask(lambda th: th["B"])
    if solver == "sgd":
        reg = sp.group_lasso(lam, where=where, axis=0, learning_rate=1 / L)
        solver = oj.Optax(optax.sgd(1 / L), max_steps=20000)
    else:
        reg, solver = sp.group_lasso(lam, where=where, axis=0), oj.Adam(1e-2, max_steps=20000)
    r = oj.fit(
        model,
        theta0,
        np.zeros(2),
        u,
        z,
        solver=solver,
        regulariser=reg,
        constraints=oc.box(lower={"B": 0.0}),
        fixed={"A": True},
        estimate_x0=False,
    )
    assert r.success, r.message
    np.testing.assert_allclose(np.ravel(r.theta["B"]), B, atol=1e-6)


def _l1_optimum_on_a_half_space(Phi, zv, T, lam, e, bound):
    """The minimiser of C + lam ||B||_1 over e . vec(B) >= bound, C quadratic in vec(B)
    (its outputs Phi vec(B)), and that minimum: SciPy's SLSQP on B = B+ - B-."""
    from scipy.optimize import minimize

    def objective(w):
        r = zv - Phi @ (w[:6] - w[6:])
        return r @ r / T + lam * w.sum()

    def gradient(w):
        g = -2 / T * Phi.T @ (zv - Phi @ (w[:6] - w[6:]))
        return np.concatenate([g + lam, -g + lam])

    face = {"type": "ineq", "fun": lambda w: e @ (w[:6] - w[6:]) - bound}
    face["jac"] = lambda w: np.concatenate([e, -e])
    best = minimize(
        objective,
        np.full(12, 0.1),
        jac=gradient,
        bounds=[(0, None)] * 12,
        method="SLSQP",
        constraints=[face],
        options={"ftol": 1e-15, "maxiter": 2000},
    )
    return best.x[:6] - best.x[6:], best.fun


def _ista_l1(problem, L, lam, projection, max_steps):
    """ISTA (`optax.sgd(1 / L)`) on C + lam ||B||_1 over a general projection's set, A
    held and x0 = 0 known: `problem` is (model, theta0, u, z)."""
    model, theta0, u, z = problem
    return oj.fit(
        model,
        theta0,
        np.zeros(2),
        u,
        z,
        solver=oj.Optax(optax.sgd(1 / L), max_steps=max_steps),
        regulariser=sp.l1(lam, where=sp.mask(lambda th: th["B"]), learning_rate=1 / L),
        constraints=oc.project(projection),
        fixed={"A": True},
        estimate_x0=False,
    )


def _l1_on_a_half_space(lam, e, bound):
    """The linear-gains problem with l1 (`lam`) on B over the half-space e . vec(B) >= bound:
    ((model, theta0, u, z), the gradient's Lipschitz constant L, SciPy's optimum B and
    its C + g)."""
    model, theta0, u, z, Phi, zv = _linear_gains()
    T = u.shape[0]
    L = np.linalg.eigvalsh(2 / T * Phi.T @ Phi).max()
    B, best = _l1_optimum_on_a_half_space(Phi, zv, T, lam, e, bound)
    return (model, theta0, u, z), L, B, best


def test_an_l1_term_on_a_half_space_reaches_its_optimum_by_proximal_gradient():
    """l1 on B with sum(B[1]) >= 2 (a general projection): ISTA reported `converged` at a
    fixed point of prox-then-project 0.014 from the optimum (its KKT multipliers unequal
    along the active face). The optimum, from SciPy's SLSQP on B = B+ - B-."""
    lam = 0.05
    problem, L, B, best = _l1_on_a_half_space(lam, np.r_[0, 0, 0, 1, 1, 1.0], 2.0)

    def half_space(th):
        B = jnp.asarray(th["B"])
        return {**th, "B": B.at[1].add(-jnp.minimum(jnp.sum(B[1]) - 2.0, 0.0) / 3)}

    r = _ista_l1(problem, L, lam, half_space, 20000)
    assert r.success, r.message
    np.testing.assert_allclose(np.ravel(r.theta["B"]), B, atol=1e-6)
    assert float(r.loss) == pytest.approx(best, rel=1e-9)


def test_the_splitting_runs_until_its_corrections_settle():
    """A strong l1 term (30) with the half-space B00 + 2 B02 >= 1: the optimum is
    B02 = 1/2, the rest 0 (l1 pays 15 there, 18 at the projection of 0, (0.2, 0.4)).
    The splitting stopped at its second round, where x repeated while its corrections
    still moved: it returned the composition's point, and ISTA "converged" there at its
    first step."""
    lam = 30.0
    problem, L, B, _ = _l1_on_a_half_space(lam, np.r_[1.0, 0, 2.0, 0, 0, 0], 1.0)

    def half_space(th):
        b = jnp.asarray(th["B"])
        excess = jnp.minimum(b[0, 0] + 2 * b[0, 2] - 1.0, 0.0) / 5.0
        return {**th, "B": b.at[0, 0].add(-excess).at[0, 2].add(-2 * excess)}

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (theta0 is projected onto the set)
        r = _ista_l1(problem, L, lam, half_space, 2000)
    assert r.success, r.message
    np.testing.assert_allclose(np.ravel(r.theta["B"]), B, atol=1e-6)
