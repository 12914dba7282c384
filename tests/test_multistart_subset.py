"""`fit(multistart={...})`: starts over some parts of theta (and x0), the rest shared.

A hybrid-like theta (a physical dict and an `MLP`) on a damped rotation by an angle w,
whose multi-step loss over w has local minima: from w = 2 a single start ends in one of
them, the starts over the physical part alone find the truth. Every other leaf (the
network) is theta0's own in every start. The errors: an unknown key, different numbers
of starts, a start of the wrong shape, a dict for a leaf, starts of a fixed entry or of a
non-parameter.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.internal import theta_starts
from oneshot_jax.residual import MLP

T = 40
W_TRUE, RHO_TRUE = 0.3, 0.98
W_STARTS = np.array([2.0, 0.25, 1.2, -1.5])  # the second one is in the truth's basin
HELD = {"phys": {"w": False, "rho": True}}  # rho known (and shared by the starts)


def step(x, u, theta):
    w, rho = theta["phys"]["w"], theta["phys"]["rho"]
    c, s = jnp.cos(w), jnp.sin(w)
    rotated = rho * jnp.stack([c * x[0] - s * x[1], s * x[0] + c * x[1]])
    return rotated + theta["net"](jnp.concatenate([x, u]))


MODEL = oj.Model(step)


@pytest.fixture(scope="module")
def theta0():
    # zero_last=False: the network's output is not zero, so which weights a start has
    # matters.
    net = MLP(3, 2, (4,), key=jax.random.PRNGKey(0), scale=1e-3, zero_last=False)
    return {"phys": {"w": 2.0, "rho": RHO_TRUE}, "net": net}


@pytest.fixture(scope="module")
def data(theta0):
    """The outputs of the model at w = W_TRUE with theta0's network: the truth is exact."""
    u = np.zeros((T, 1))
    x0 = np.array([1.0, 0.0])
    truth = {**theta0, "phys": {"w": W_TRUE, "rho": RHO_TRUE}}
    _, z = oj.simulate(MODEL, truth, x0, u)
    return x0, u, np.asarray(z)


def _leaves(tree):
    """The parameter leaves (the arrays; an `MLP` holds its activation too)."""
    return jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_array))


def test_starts_over_the_physics_with_the_network_held(data, theta0):
    """The network held (`fixed`): the single start theta0 (w = 2, the first start) ends
    in a local minimum, the starts over w alone reach the truth, and each start's network
    is theta0's."""
    x0, u, z = data
    r = oj.fit(
        MODEL,
        theta0,
        x0,
        u,
        z,
        estimate_x0=False,
        fixed={**HELD, "net": True},
        solver=oj.GaussNewton(),
        multistart={"phys": {"w": W_STARTS}},
    )
    assert W_STARTS[0] == theta0["phys"]["w"] and r.starts.loss[0] > 0.1  # theta0 alone
    assert r.best == 1 == int(np.argmin(r.starts.loss))
    assert r.loss == r.starts.loss[r.best] < 1e-20
    np.testing.assert_allclose(r.theta["phys"]["w"], W_TRUE, rtol=1e-10)
    assert np.all(np.delete(r.starts.loss, r.best) > 0.1)  # the others: local minima
    np.testing.assert_array_equal(r.starts.theta["phys"]["rho"], np.full(4, RHO_TRUE))
    for got, want in zip(_leaves(r.starts.theta["net"]), _leaves(theta0["net"]), strict=True):
        assert got.shape == (4, *want.shape)
        np.testing.assert_array_equal(got, np.broadcast_to(want, got.shape))


def test_shared_network_starts_equal_and_the_best_start_is_returned(data, theta0):
    """The network free and shared: every start begins from theta0's weights (the starts
    differ only in w), and the fit returns the start of least final loss."""
    params, n = theta_starts({"phys": {"w": W_STARTS}}, theta0, None)
    assert n == 4
    np.testing.assert_array_equal(params["phys"]["w"], W_STARTS)
    np.testing.assert_array_equal(params["phys"]["rho"], np.full(4, RHO_TRUE))
    for got, want in zip(_leaves(params["net"]), _leaves(theta0["net"]), strict=True):
        assert got.shape == (4, *want.shape)
        for k in range(4):
            np.testing.assert_array_equal(got[k], want)

    x0, u, z = data
    r = oj.fit(
        MODEL,
        theta0,
        x0,
        u,
        z,
        estimate_x0=False,
        fixed={**HELD, "net": False},
        solver=oj.LevenbergMarquardt(max_steps=30),
        multistart={"phys": {"w": W_STARTS}},
    )
    assert r.best == int(np.argmin(r.starts.loss)) == 1
    assert abs(r.theta["phys"]["w"] - W_TRUE) < 1e-3
    assert np.all(np.delete(r.starts.loss, r.best) > 100 * r.loss)
    assert r.starts.theta["phys"]["w"][r.best] == r.theta["phys"]["w"]
    for got, want in zip(_leaves(r.starts.theta["net"]), _leaves(r.theta["net"]), strict=True):
        np.testing.assert_array_equal(got[r.best], want)


def test_starts_over_x0_with_theta_shared(data, theta0):
    """An empty spec with x0's leading axis of starts: starts over x0 alone."""
    x0, u, z = data
    X0s = np.array([[0.5, 0.5], [1.0, 0.0], [-1.0, 0.3]])
    theta = {**theta0, "phys": {"w": W_TRUE, "rho": RHO_TRUE}}
    r = oj.fit(MODEL, theta, X0s, u, z, fixed=True, multistart={})
    assert r.starts.loss.shape == (3,)
    np.testing.assert_allclose(r.x0, x0, atol=1e-10)
    # A model without parameters (theta0 {} or None, the structure known): the same
    # starts over x0 (refused before: "`multistart` gives a dict for theta, which is a
    # leaf of theta0").
    known = oj.Model(lambda x, u, th: step(x, u, theta))
    for empty in ({}, None):
        e = oj.fit(known, empty, X0s, u, z, multistart={})
        np.testing.assert_array_equal(e.starts.loss, r.starts.loss)


def test_x0_starts_of_held_entries_are_refused(data, theta0):
    """x0 starts that differ in an entry `estimate_x0` holds used to run every start from
    the first one's value there (the other starts silently dropped): refused, as the
    starts of a fixed theta entry are. Starts that agree there are taken."""
    x0, u, z = data
    theta = {**theta0, "phys": {"w": W_TRUE, "rho": RHO_TRUE}}
    X0s = np.array([[0.5, 0.0], [1.0, 0.0], [-1.0, 0.3]])
    held = {**HELD, "net": True}  # (w free: something to estimate)
    for est, entries in ((False, r"\[0, 1\]"), (np.array([True, False]), r"\[1\]")):
        with pytest.raises(ValueError, match=rf"`x0` gives different starts .*{entries}"):
            oj.fit(MODEL, theta, X0s, u, z, fixed=held, estimate_x0=est, multistart={})
    agree = X0s[:2]  # (the held entry 1 is 0.0 in both)
    r = oj.fit(
        MODEL, theta, agree, u, z, fixed=True, estimate_x0=np.array([True, False]), multistart={}
    )
    np.testing.assert_allclose(r.x0, x0, atol=1e-10)


def test_starts_given_as_a_list_of_integers_are_floats(theta0):
    params, n = theta_starts({"phys": {"w": [2, 1, 0]}}, theta0, 3)
    assert n == 3 and params["phys"]["w"].dtype == np.float64
    np.testing.assert_array_equal(params["phys"]["w"], [2.0, 1.0, 0.0])


def test_multistart_true_still_needs_every_leaf(data, theta0):
    x0, u, z = data
    with pytest.raises(ValueError, match=r"multistart=\{"):
        oj.fit(MODEL, theta0, x0, u, z, multistart=True)


def test_dotted_names_start_nested_parameters_as_fixed_takes_them(data, theta0):
    """`multistart={"phys.w": ...}` was refused ("names theta['phys.w']") while
    `fixed="phys.w"` took the printout's name; both spellings give the same starts."""
    x0, u, z = data
    solver = oj.LevenbergMarquardt(max_steps=3)
    nested = oj.fit(MODEL, theta0, x0, u, z, multistart={"phys": {"w": W_STARTS}}, solver=solver)
    dotted = oj.fit(MODEL, theta0, x0, u, z, multistart={"phys.w": W_STARTS}, solver=solver)
    np.testing.assert_array_equal(dotted.starts.loss, nested.starts.loss)
    np.testing.assert_array_equal(
        dotted.starts.theta["phys"]["w"], nested.starts.theta["phys"]["w"]
    )
    with pytest.raises(ValueError, match="`multistart` names a parameter twice"):
        oj.fit(MODEL, theta0, x0, u, z, multistart={"phys.w": W_STARTS, "phys": {"w": W_STARTS}})


def test_numpy_bools_are_read_as_python_bools(data, theta0):
    """`np.True_` (a config's or an array's `any()`) was refused as "got bool", and
    `np.False_` started a multistart fit."""
    x0, u, z = data
    with pytest.raises(ValueError, match=r"multistart=\{"):
        oj.fit(MODEL, theta0, x0, u, z, multistart=np.True_)
    solver = oj.LevenbergMarquardt(max_steps=2)
    r = oj.fit(MODEL, theta0, x0, u, z, multistart=np.False_, solver=solver)
    assert r.starts is None


@pytest.mark.parametrize(
    "spec, error, match",
    [
        ({"phys": {"k": W_STARTS}}, ValueError, r"names theta\['phys'\]\['k'\], which theta0"),
        ({"omega": W_STARTS}, ValueError, r"names theta\['omega'\]"),
        (
            {"phys": {"w": W_STARTS, "rho": np.array([0.9, 0.95])}},
            ValueError,
            r"same number of starts; got theta\['phys'\]\['w'\] 4, theta\['phys'\]\['rho'\] 2",
        ),
        (
            {"phys": {"w": np.ones((4, 2))}},
            ValueError,
            r"theta\['phys'\]\['w'\] must be .*\(4, 2\)",
        ),
        (
            {"phys": {"w": 2.0}},
            ValueError,
            r"theta\['phys'\]\['w'\] must be a real array of shape \(S,\) .*got shape \(\)",
        ),
        (
            {"phys": {"w": "2"}},
            ValueError,
            r"theta\['phys'\]\['w'\] must be a real array .*got '2'",
        ),
        ({"phys": {"w": {"a": 1.0}}}, ValueError, r"a dict for theta\['phys'\]\['w'\]"),
        ({"net": {"activation": W_STARTS}}, ValueError, r"holds no parameter"),
        ({"net": {"layers": [None, np.ones(3)]}}, ValueError, r"must have theta0's structure"),
        ({}, ValueError, "nothing to start from"),
        ([W_STARTS], TypeError, "`multistart` must be a bool or a dict"),
    ],
)
def test_bad_specs_are_clear_errors(data, theta0, spec, error, match):
    x0, u, z = data
    with pytest.raises(error, match=match):
        oj.fit(MODEL, theta0, x0, u, z, multistart=spec)


@pytest.mark.parametrize("starts", [W_STARTS, np.full(4, 0.25)])
def test_starts_of_a_fixed_entry_are_refused(data, theta0, starts):
    """Equal starts, unlike theta0's w = 2, replaced the held value without a word."""
    x0, u, z = data
    with pytest.raises(
        ValueError, match=r"starts for fixed entries of theta \(theta\['phys'\]\['w'\]\) that"
    ):
        oj.fit(
            MODEL,
            theta0,
            x0,
            u,
            z,
            fixed={"phys": True, "net": True},
            multistart={"phys": {"w": starts}},
        )


def test_x0_starts_must_match_the_theta_starts(data, theta0):
    x0, u, z = data
    with pytest.raises(ValueError, match="`x0` with a leading axis of starts must have 4"):
        oj.fit(MODEL, theta0, np.stack([x0, x0]), u, z, multistart={"phys": {"w": W_STARTS}})


def test_a_start_of_x0_that_is_not_finite_is_refused():
    model = oj.Model(lambda x, u, p: p["a"] * x + u)
    u = np.ones((20, 1))
    with pytest.raises(ValueError, match=r"the starts \[1\] \(first axis\) have a NaN"):
        oj.fit(
            model,
            {"a": np.array([0.5, 0.6])},
            np.array([[0.0], [np.nan]]),
            u,
            u,
            multistart=True,
        )


def test_starts_outside_the_bounds_are_named_in_the_projection_warning():
    """theta0 itself is inside the box; three of the four starts are not: the warning names
    those starts (it said "theta0 lies outside", and not which starts collapsed)."""
    model = oj.Model(lambda x, u, p: p["a"] * x + u)
    u = np.random.default_rng(0).standard_normal((20, 1))
    _, z = oj.simulate(model, {"a": 0.5}, np.zeros(1), u)
    with pytest.warns(UserWarning, match=r"3 of the 4 starts \(starts 0, 2, 3\) lie outside"):
        r = oj.fit(
            model,
            {"a": 0.4},
            np.zeros(1),
            u,
            np.asarray(z),
            multistart={"a": np.array([-2.0, 0.4, 2.0, 3.0])},
            constraints=oj.constraints.box(lower=-0.9, upper=0.9),
        )
    assert abs(float(r.theta["a"]) - 0.5) < 1e-8


def test_window_states_are_not_read_as_starts_of_x0(data, theta0):
    """With `window`, x0 (n, n_x) is one state per window: `multistart={}` was refused
    saying that x0 has no leading axis of starts, and not why."""
    x0, u, z = data
    with pytest.raises(ValueError, match=r"is one state per window, not starts"):
        oj.fit(MODEL, theta0, np.stack([x0, x0]), u, z, window=T // 2, multistart={})


def test_multistart_true_says_how_it_read_a_leaf_without_starts():
    """A (2,) leaf indexed as a vector by the model, given to `multistart=True` without
    an axis of starts, is read as 2 starts of shape (): the model's IndexError said
    nothing of the starts."""
    model = oj.Model(lambda x, u, th: th["v"][0] * x + th["v"][1] * u)
    u = np.ones((20, 1))
    _, z = oj.simulate(model, {"v": np.array([0.5, 1.0])}, np.zeros(1), u)
    with pytest.raises(ValueError, match=r"read as 2 starts, each leaf of shape \(\)"):
        oj.fit(model, {"v": np.array([0.5, 1.0])}, np.zeros(1), u, z, multistart=True)


class _Gains(eqx.Module):
    a: jax.Array
    b: jax.Array


def test_the_printouts_names_of_a_modules_fields_work_in_every_option():
    """theta0 = {"p": a module with fields a, b}: the printout names them "p.a", "p.b",
    and `fixed="p.a"` held a; `fixed={"p.a": True}`, `fixed={"p": {"a": True}}`,
    `box(upper={"p.a": ...})` and `multistart={"p.a": ...}` were refused ("theta0 has
    ['p']"). Each spelling now gives what its nested or string form gives."""
    model = oj.Model(lambda x, u, th: th["p"].a * x + th["p"].b * u)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((30, 1))
    _, z = oj.simulate(model, {"p": _Gains(jnp.array(0.8), jnp.array(0.5))}, np.zeros(1), u)
    theta0 = {"p": _Gains(jnp.array(0.7), jnp.array(0.4))}
    solver = oj.LevenbergMarquardt(max_steps=5)

    def fit(**kw):
        return oj.fit(model, theta0, np.zeros(1), u, z, solver=solver, **kw)

    held = fit(fixed="p.a")
    assert held.names == ("p.b",) and float(held.theta["p"].a) == 0.7
    for fixed in ({"p.a": True}, {"p": {"a": True}}, {"p": {"a": True, "b": False}}):
        same = fit(fixed=fixed)
        np.testing.assert_array_equal(same.fixed, held.fixed)
        assert float(same.theta["p"].b) == float(held.theta["p"].b)
    with pytest.raises(ValueError, match=r"theta0 has \['p.a', 'p.b'\]"):
        fit(fixed={"p.c": True})
    bounded = fit(constraints=oj.constraints.box(upper={"p.a": 0.75}))
    assert float(bounded.theta["p"].a) == 0.75
    starts = fit(multistart={"p.a": jnp.array([0.6, 0.9])})
    nested = fit(multistart={"p": {"a": jnp.array([0.6, 0.9])}})
    np.testing.assert_array_equal(starts.starts.loss, nested.starts.loss)
