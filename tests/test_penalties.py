"""State barriers of `oneshot_jax.penalties` as the penalty h of eq. (21): zero inside the
safe set, the closed form outside, smooth at the boundary, and their one-shot gradient
against `jax.grad` of a cost written here."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_tree_rel_close

import oneshot_jax as oj
from oneshot_jax.penalties import state_ball, state_box


def test_state_box_zero_inside_and_closed_form_outside():
    h = state_box(lower=[-1.0, -np.inf], upper=[2.0, 0.5], width=[0.5, 2.0], power=2)
    rng = np.random.default_rng(0)
    inside = np.column_stack([rng.uniform(-1, 2, 100), rng.uniform(-50, 0.5, 100)])
    assert all(float(h(jnp.asarray(x))) == 0.0 for x in inside)
    for x in [[-1.5, 0.0], [3.0, 1.5], [0.0, -1e6], [-2.0, 4.5]]:
        lo = np.array([-1.0, -np.inf])
        hi = np.array([2.0, 0.5])
        viol = np.maximum(np.maximum(np.array(x) - hi, lo - np.array(x)), 0) / np.array([0.5, 2.0])
        assert float(h(jnp.asarray(x))) == pytest.approx(np.sum(viol**2), rel=1e-15)
    # C^1 at the boundary: the gradient is zero there and continuous across it.
    g = jax.grad(h)
    np.testing.assert_array_equal(g(jnp.array([2.0, 0.0])), [0.0, 0.0])
    np.testing.assert_allclose(g(jnp.array([2.0 + 1e-9, 0.0])), [2 * 1e-9 / 0.25, 0.0], rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(g(jnp.array([0.0, -1e6])))))
    # Scalars apply to every state; power 4 is the fourth power of the violation.
    h4 = state_box(upper=1.0, power=4)
    assert float(h4(jnp.array([3.0, 0.0, 1.5]))) == pytest.approx(2.0**4 + 0.5**4)


def test_state_ball_zero_inside_and_closed_form_outside():
    h = state_ball(2.0, center=[1.0, 0.0], scale=[1.0, 10.0], width=0.5, power=2)
    assert float(h(jnp.array([1.0, 0.0]))) == 0.0
    assert float(h(jnp.array([2.0, 12.0]))) == 0.0  # ||(1, 1.2)|| < 2
    x = jnp.array([4.0, 30.0])  # ||(3, 3)|| = 3 sqrt 2
    assert float(h(x)) == pytest.approx(((3 * np.sqrt(2) - 2.0) / 0.5) ** 2, rel=1e-14)
    g = jax.grad(h)
    np.testing.assert_array_equal(g(jnp.array([1.0, 0.0])), [0.0, 0.0])  # no NaN at the center
    d = 3 * np.sqrt(2)
    expected = 2 * (d - 2.0) / 0.25 * np.array([3.0, 3.0 / 10.0]) / d
    np.testing.assert_allclose(g(x), expected, rtol=1e-13)


def unstable_step(x, u, theta):
    """x+ = A(theta) x + B u with a rotation of gain theta["a"]: unstable for a > 1."""
    c, s = jnp.cos(0.3), jnp.sin(0.3)
    A = theta["a"] * jnp.array([[c, -s], [s, c]])
    return A @ x + jnp.array([0.0, 1.0]) * u[0]


def test_barrier_as_penalty_of_the_one_shot_gradient():
    T = 60
    rng = np.random.default_rng(1)
    u = jnp.asarray(0.1 * rng.standard_normal((T, 1)))
    x0 = jnp.array([1.0, 0.0])
    theta = {"a": jnp.asarray(1.04)}  # the simulation grows past the barrier
    z = jnp.asarray(0.1 * rng.standard_normal((T, 2)))
    h = state_box(lower=-1.5, upper=1.5, width=0.5)
    model = oj.Model(unstable_step)

    def cost(theta, x0):
        def body(x, u_k):
            x_next = unstable_step(x, u_k, theta)
            return x_next, x_next

        _, xs = jax.lax.scan(body, x0, u[:-1])
        xs = jnp.concatenate([x0[None], xs])
        e = xs - z
        return jnp.mean(jnp.sum(e * e, axis=1) + 3.0 * jax.vmap(h)(xs))

    C, (g_theta, g_x0) = oj.value_and_grad(model, theta, x0, u, z, penalty=h, penalty_weight=3.0)
    C_ref, (g_theta_ref, g_x0_ref) = jax.value_and_grad(cost, argnums=(0, 1))(theta, x0)
    assert_tree_rel_close(C, C_ref, rtol=1e-12)
    assert_tree_rel_close(g_theta, g_theta_ref, rtol=1e-12)
    assert_tree_rel_close(g_x0, g_x0_ref, rtol=1e-12)
    C_free = oj.loss(model, theta, x0, u, z)
    assert float(C) > float(C_free)  # the barrier is active
    assert float(oj.loss(model, theta, x0, u, z, penalty=h, penalty_weight=3.0)) == pytest.approx(
        float(C), rel=1e-13
    )
    # It is a pytree-compatible, hashable module: the same compiled loss is reused.
    assert hash(h) == hash(state_box(lower=-1.5, upper=1.5, width=0.5))


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: state_box(upper=1.0, power=1), "`power`"),
        (lambda: state_box(upper=1.0, power=2.5), "`power`"),
        (lambda: state_box(lower=2.0, upper=1.0), "lower <= upper"),
        (lambda: state_box(lower=[0, 0], upper=[1, 1, 1]), "do not match"),
        (lambda: state_box(upper=1.0, width=0.0), "`width`"),
        (lambda: state_box(upper="high"), "`upper`"),
        (lambda: state_ball(0.0), "`radius`"),
        (lambda: state_ball(1.0, scale=[1.0, -1.0]), "`scale`"),
        (lambda: state_ball(1.0, width=-1.0), "`width`"),
        (lambda: state_ball(1.0, center=np.inf), "`center`"),
    ],
)
def test_bad_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bound_of_the_wrong_length_is_reported():
    model = oj.Model(unstable_step)
    u, z = jnp.zeros((5, 1)), jnp.zeros((5, 2))
    with pytest.raises(ValueError, match="`upper`"):
        oj.loss(model, {"a": 1.0}, jnp.ones(2), u, z, penalty=state_box(upper=[1.0, 1.0, 1.0]))


def test_crossed_state_bounds_name_the_states():
    # (The message named no state: which of the bounds was crossed was a search.)
    with pytest.raises(ValueError, match=r"x\[1\] \(lower 3 > upper 2\)\.$"):
        state_box(lower=[0.0, 3.0, -1.0], upper=2.0)
    with pytest.raises(ValueError, match=r"every state \(lower 1 > upper 0\)\.$"):
        state_box(lower=1.0, upper=0.0)


def test_state_box_none_entries_leave_that_side_unbounded():
    # (The docstring's "None ... entries" was refused: "must be ... real numbers".)
    h = state_box(lower=[0.0, None], upper=[None, 1.0])
    assert h == state_box(lower=[0.0, -np.inf], upper=[np.inf, 1.0])
    assert float(h(jnp.array([1e6, -1e6]))) == 0.0
    assert float(h(jnp.array([-2.0, 3.0]))) == pytest.approx(2.0**2 + 2.0**2)


def test_0d_jax_arrays_are_numbers():
    # (`radius` and `width` of a 0-d jax.Array were "must be a finite number > 0", and a
    # 0-d `power` "must be an integer", while NumPy scalars were taken.)
    for one, half, two in [
        (jnp.asarray(1.0), jnp.asarray(0.5), jnp.asarray(2)),
        (np.array(1.0), np.array(0.5), np.array(2)),
    ]:
        assert state_ball(one, width=half, power=two) == state_ball(1.0, width=0.5, power=2)
        assert state_box(lower=-one, upper=one, width=half, power=two) == state_box(
            lower=-1.0, upper=1.0, width=0.5, power=2
        )
    with pytest.raises(ValueError, match="`radius` must be a finite number > 0, got 0.0"):
        state_ball(jnp.asarray(0.0))
    with pytest.raises(ValueError, match="`width`"):
        state_ball(1.0, width=jnp.asarray([1.0]))


def test_state_box_without_a_bound_is_refused():
    # (it made a penalty that is zero everywhere)
    with pytest.raises(ValueError, match=r"`state_box` needs `lower` or `upper`"):
        state_box()
    with pytest.raises(ValueError, match=r"`state_box` needs `lower` or `upper`"):
        state_box(lower=[None, -np.inf], upper=np.inf)
