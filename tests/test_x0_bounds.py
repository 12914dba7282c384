"""`fit(x0_bounds=...)`: box bounds on the estimated initial state (MATLAB's
`InitialStates(i).Minimum` and `Maximum`).

The reference is SciPy's bounded trust-region least squares (`scipy.optimize.
least_squares`, method "trf") on the residuals of `oneshot_jax.simulate`, and the
first-order conditions of the box checked on the gradient of a loss written here with
`jax.grad` (not the library's closed form).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EULER_PENDULUM, angle_only, euler_pendulum_step
from scipy.optimize import least_squares

import oneshot_jax as oj

MODEL = EULER_PENDULUM
THETA0 = {"w0sq": 7.0, "b": 0.3}
TRUE_X0 = np.array([0.8, -0.5])
# the true x0 outside the box in both entries: the bounded optimum holds them at 0.7, -0.2
BOUNDS = (np.array([-np.inf, -0.2]), np.array([0.7, np.inf]))


def record(T=80, seed=0, x0=TRUE_X0):
    rng = np.random.default_rng(seed)
    u = 0.5 * np.sin(0.3 * np.arange(T) + seed)[:, None]
    _, z = oj.simulate(MODEL, {"w0sq": 9.0, "b": 0.6}, x0, u)
    return u, np.asarray(z) + 0.02 * rng.standard_normal(np.shape(z))


U, Z = record()


def plain_loss(p, u, z):
    """C of eq. (5) for p = (w0sq, b, x0), by a Python loop of the step: its gradient by
    jax.grad is independent of the library's."""
    th, x, total = {"w0sq": p[0], "b": p[1]}, p[2:], 0.0
    for k in range(len(z)):
        total = total + jnp.sum((angle_only(x, u[k], th) - z[k]) ** 2)
        x = euler_pendulum_step(x, u[k], th)
    return total / len(z)


def scipy_reference(u, z, lower, upper):
    def residuals(p):
        _, zh = oj.simulate(MODEL, {"w0sq": p[0], "b": p[1]}, p[2:], u)
        return (np.asarray(zh) - z).ravel()

    lo = np.r_[-np.inf, -np.inf, lower]
    hi = np.r_[np.inf, np.inf, upper]
    ref = least_squares(residuals, [7.0, 0.3, 0.5, 0.0], bounds=(lo, hi), xtol=1e-15,
                        ftol=1e-15, gtol=1e-15)  # fmt: skip
    return ref.x


REFERENCE = None


def reference():
    global REFERENCE
    if REFERENCE is None:
        REFERENCE = scipy_reference(U, Z, *BOUNDS)
    return REFERENCE


@pytest.mark.parametrize(
    "solver",
    [
        oj.LevenbergMarquardt(),
        oj.GaussNewton(),
        oj.LBFGS(max_steps=2000),
        [oj.Adam(lr_theta=1e-2, lr_x0=1e-2, max_steps=2000), oj.LevenbergMarquardt()],
    ],
    ids=["lm", "gn", "lbfgs", "adam_lm"],
)
def test_every_solver_reaches_the_bounded_optimum_and_says_the_bound_holds_x0(solver):
    """Every solver ends at SciPy's bounded optimum, with x0 at its two bounds, reports
    success, and the box's first-order conditions hold on an independent gradient: zero
    for theta, pointing out of the box for the two entries at a bound (where a test that
    ignored the box would never call the point stationary)."""
    result = oj.fit(MODEL, THETA0, np.array([0.5, 0.0]), U, Z, x0_bounds=BOUNDS, solver=solver)
    assert result.success, result.message
    p = np.array([result.theta["w0sq"], result.theta["b"], *result.x0])
    np.testing.assert_allclose(p, reference(), rtol=1e-6, atol=1e-8)
    assert result.x0[0] == 0.7 and result.x0[1] == -0.2
    g = np.asarray(jax.grad(plain_loss)(jnp.asarray(p), U, Z))
    scale = np.abs(g[2:]).max()
    assert np.all(np.abs(g[:2]) <= 1e-6 * scale), g
    assert g[2] < 0 and g[3] > 0  # (descent would leave the box: q0 up, v0 down)
    assert result.stop_info["at_bound"] == ["x0[q]", "x0[v]"]
    assert "at a bound: x0[q], x0[v]" in str(result)


def test_without_bounds_the_fit_leaves_the_box():
    """(The bounds act: the unbounded optimum is outside them, near the true x0.)"""
    result = oj.fit(MODEL, THETA0, np.array([0.5, 0.0]), U, Z)
    assert result.success
    assert result.x0[0] > 0.75 and result.x0[1] < -0.3


def test_bounds_per_record_and_an_entry_held_by_estimate_x0():
    """(N, n_x) bounds give each record its own box: the first record's bound holds its
    x0, the second's leaves it inside. An entry `estimate_x0` holds keeps its value,
    even outside the box."""
    u2, z2 = record(seed=1, x0=np.array([-0.3, 0.4]))
    lower = np.array([[-np.inf, -np.inf], [-1.0, -1.0]])
    upper = np.array([[0.7, np.inf], [1.0, 1.0]])
    x0 = np.array([[0.5, 0.0], [0.0, 0.0]])
    result = oj.fit(MODEL, THETA0, x0, np.stack([U, u2]), np.stack([Z, z2]),
                    x0_bounds=(lower, upper))  # fmt: skip
    assert result.success, result.message
    assert result.x0[0, 0] == 0.7
    assert np.all(np.abs(result.x0[1]) < 0.9)
    assert result.stop_info["at_bound"] == ["x0[0, q]"]
    assert result.x0_bounds[0].shape == (2, 2)
    # (each record its own box: a new record's x0 is not bounded by either)
    assert result.predict(U, Z, x0=np.array([0.5, 0.0])).x0[0] > 0.7
    held = oj.fit(MODEL, THETA0, np.array([0.5, -0.5]), U, Z, x0_bounds=BOUNDS,
                  estimate_x0=[True, False])  # fmt: skip
    assert held.success and held.x0[1] == -0.5 and held.x0[0] <= 0.7


def test_none_entries_are_unbounded_and_equal_bounds_say_they_still_count():
    """A None entry in a list of bounds is unbounded, as `constraints.box` takes it (it
    was refused: "must be None, a number or an array of numbers, got list"); equal lower
    and upper bounds hold an entry but count it as estimated, which `fit` says, as it does
    for theta's box (it said nothing, and gave a standard error of a value that cannot
    move)."""
    listed = oj.fit(
        MODEL, THETA0, np.array([0.5, 0.0]), U, Z, x0_bounds=([None, -0.2], [0.7, None])
    )
    np.testing.assert_allclose(listed.x0, reference()[2:], rtol=1e-6)
    with pytest.warns(UserWarning, match=r"bounds are equal for x0 entries \[1\]: .* still count"):
        pinned = oj.fit(
            MODEL, THETA0, np.array([0.5, -0.5]), U, Z, x0_bounds=([None, -0.5], [0.7, -0.5])
        )
    assert pinned.x0[1] == -0.5


def test_a_start_outside_the_box_is_clipped_with_a_warning_and_windows_share_the_box():
    with pytest.warns(UserWarning, match=r"outside `x0_bounds` in its entries \[0, 1\]"):
        result = oj.fit(MODEL, THETA0, np.array([0.9, -0.5]), U, Z, x0_bounds=BOUNDS)
    assert result.success
    np.testing.assert_allclose(result.x0, reference()[2:], rtol=1e-6)
    # (several records: the record is named; it said "entries [0]")
    starts = np.array([[0.5, 0.0], [0.9, 0.0]])
    with pytest.warns(UserWarning, match=r"outside `x0_bounds` in x0\[1, 0\] \(record, state\)"):
        oj.fit(MODEL, THETA0, starts, np.stack([U, U]), np.stack([Z, Z]), x0_bounds=BOUNDS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the windows' starting states read off z)
        windowed = oj.fit(MODEL, THETA0, np.array([0.5, 0.0]), U, Z, window=40,
                          x0_bounds=(-0.25, 0.25))  # fmt: skip
    assert windowed.x0.shape == (2, 2)
    assert np.all(np.abs(windowed.x0) <= 0.25)
    assert windowed.stop_info.get("at_bound")


def test_estimate_x0_and_predict_take_bounds_on_a_new_record():
    """x0 of a record's head alone, theta known, in a box: SciPy's bounded solution,
    the guess outside the box clipped with a warning; `predict` passes them on. The
    smoother refuses them."""
    theta = {"w0sq": 9.0, "b": 0.6}
    n = 30

    def residuals(x0):
        _, zh = oj.simulate(MODEL, theta, x0, U[:n])
        return (np.asarray(zh) - Z[:n]).ravel()

    ref = least_squares(residuals, [0.5, 0.0], bounds=([-np.inf, -0.2], [0.7, np.inf]),
                        xtol=1e-15, ftol=1e-15, gtol=1e-15).x  # fmt: skip
    with pytest.warns(UserWarning, match="outside `bounds`"):
        est = oj.estimate_x0(MODEL, theta, U, Z, n=n, x0=np.array([0.9, 0.0]), bounds=BOUNDS)
    assert est.success, est.message
    np.testing.assert_allclose(est.x0, ref, rtol=1e-7, atol=1e-10)
    assert est.x0[0] == 0.7 and est.x0[1] == -0.2
    free = oj.estimate_x0(MODEL, theta, U, Z, n=n, x0=np.array([0.5, 0.0]))
    assert free.x0[0] > 0.7 and free.x0[1] < -0.2  # (the box acts)
    pred = oj.predict(MODEL, theta, U, Z, n, x0=np.array([0.5, 0.0]), bounds=BOUNDS)
    np.testing.assert_allclose(pred.x0, est.x0, rtol=1e-12)
    with pytest.raises(ValueError, match="method='lsq'"):
        oj.estimate_x0(MODEL, theta, U, Z, n=n, x0=np.zeros(2), method="smoother",
                       bounds=BOUNDS)  # fmt: skip


def test_the_result_keeps_the_box_and_predict_bounds_x0_by_it(tmp_path):
    """`result.x0_bounds` holds the box shaped like x0 (held entries unbounded); it is
    saved and loaded; `predict` bounds a record's x0 by it by default, so that the fitted
    record predicted from all of it starts from the fitted x0 at its bounds (unbounded,
    its x0 leaves the box), and `bounds=(None, None)` lifts it."""
    result = oj.fit(MODEL, THETA0, np.array([0.5, 0.0]), U, Z, x0_bounds=(None, [0.7, np.inf]))
    lo, hi = result.x0_bounds
    np.testing.assert_array_equal(lo, [-np.inf, -np.inf])
    np.testing.assert_array_equal(hi, [0.7, np.inf])
    with pytest.warns(UserWarning, match=r"x0\[q\] \(the fit's x0 is on it too\) ended on"):
        pred = result.predict(U, Z)
    np.testing.assert_allclose(pred.x0, result.x0, rtol=1e-6, atol=1e-9)
    assert pred.x0[0] == 0.7
    assert pred.estimate.at_bound.tolist() == [True, False]
    assert "(at a bound)" in str(pred)
    assert result.predict(U, Z, bounds=(None, None)).x0[0] > 0.7
    path = tmp_path / "bounded.npz"
    result.save(path)
    loaded = oj.load_result(path, model=MODEL)
    for a, b in zip(loaded.x0_bounds, result.x0_bounds):
        np.testing.assert_array_equal(a, b)
    with pytest.warns(UserWarning, match="ended on the fit's `x0_bounds`"):
        assert loaded.predict(U, Z).x0[0] == 0.7


def test_a_new_record_held_by_the_fits_box_is_said():
    """A record that starts outside the fitted one's box (v = 0.4 above the fit's upper
    bound 0.0): `predict` held its x0 at the bound in silence, its printout the plain
    std. It now warns at the caller's line and marks the entry; a box the caller gives,
    or none, says nothing of the fit's."""
    result = oj.fit(MODEL, THETA0, np.array([0.5, -0.5]), U, Z, x0_bounds=(None, [np.inf, 0.0]))
    assert result.x0[1] < 0.0  # (the fitted record's x0 is inside the box)
    u, z = record(seed=3, x0=np.array([0.2, 0.4]))
    with pytest.warns(UserWarning, match=r"estimate of x0\[v\] ended on the fit's") as w:
        held = result.predict(u, z[:30])
    assert w[0].filename == __file__
    assert held.x0[1] == 0.0 and held.estimate.at_bound.tolist() == [False, True]
    assert "(at a bound)" in str(held.estimate)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        free = result.predict(u, z[:30], bounds=(None, None))
    assert free.x0[1] == pytest.approx(0.4, abs=0.05) and free.estimate.at_bound is None


@pytest.mark.parametrize(
    "x0_bounds, kwargs, error, match",
    [
        ((0.0,), {}, TypeError, "pair"),
        ((np.zeros(3), None), {}, ValueError, r"shape \(n_x,\) = \(2,\)"),
        ((None, np.array([np.nan, 1.0])), {}, ValueError, "NaN"),
        ((1.0, 0.0), {}, ValueError, "lower bound is above"),
        ((np.inf, None), {}, ValueError, "lower bound holds inf, which no value meets"),
        ((True, None), {}, TypeError, "booleans"),
        (("a", None), {}, TypeError, "numbers"),
        ((np.zeros((2, 2)), None), {"window": 40}, ValueError, r"shape \(n_x,\)"),
        ((0.0, None), {"solver": "optimistix"}, ValueError, "Optimistix"),
    ],
)
def test_bad_bounds_are_named(x0_bounds, kwargs, error, match):
    if "solver" in kwargs:
        import optimistix as optx

        kwargs = {"solver": oj.Optimistix(optx.LevenbergMarquardt(1e-8, 1e-8))}
    with pytest.raises(error, match=match), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        oj.fit(MODEL, THETA0, np.zeros(2), U, Z, x0_bounds=x0_bounds, **kwargs)


def test_bounds_on_held_entries_alone_are_said_to_do_nothing():
    """`estimate_x0=False` (or a mask holding every bounded entry) with `x0_bounds`: the
    bounds were dropped without a word (held entries keep their values)."""
    with pytest.warns(UserWarning, match="bounds only x0 entries that `estimate_x0` holds"):
        held = oj.fit(MODEL, THETA0, TRUE_X0, U, Z, estimate_x0=False, x0_bounds=BOUNDS)
    np.testing.assert_array_equal(held.x0, TRUE_X0)
    with pytest.warns(UserWarning, match="the bounds have no effect"):
        oj.fit(MODEL, THETA0, TRUE_X0, U, Z, estimate_x0=[False, True],
               x0_bounds=([-np.inf, -np.inf], [0.7, np.inf]))  # fmt: skip
    with warnings.catch_warnings():  # (a bound on an estimated entry: no such warning)
        warnings.filterwarnings("error", message=".*have no effect")
        oj.fit(MODEL, THETA0, np.array([0.5, 0.0]), U, Z, estimate_x0=[True, False],
               x0_bounds=([-np.inf, -np.inf], [0.7, np.inf]))  # fmt: skip
