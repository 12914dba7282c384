"""`fit(estimate_x0=mask)` with a mask per record (N, n_x): MATLAB's
`InitialStates(i).Fixed` of a multi-experiment model. One record starts at rest (x0
known), one estimates all of its x0, one knows its angle and estimates its rate.

The references are SciPy's `least_squares` on the free variables alone (theta and the
three estimated x0 entries) and sigma^2 (J^T J)^{-1} with J from `jax.jacfwd` of residuals
written here with a Python loop of the step (not the library's closed form), sigma^2 =
SSE / (n_obs - 5).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import EULER_PENDULUM, angle_only, euler_pendulum_step
from scipy.optimize import least_squares

import oneshot_jax as oj

MODEL = EULER_PENDULUM
THETA0 = {"w0sq": 7.0, "b": 0.3}
TRUE_X0 = np.array([[0.0, 0.0], [0.8, -0.5], [0.3, 0.4]])
MASK = np.array([[False, False], [True, True], [False, True]])
T = 60
U = np.stack([0.5 * np.sin(0.3 * np.arange(T) + i)[:, None] for i in range(3)])
Z = np.stack(
    [np.asarray(oj.simulate(MODEL, {"w0sq": 9.0, "b": 0.6}, TRUE_X0[i], U[i])[1]) for i in range(3)]
) + 0.02 * np.random.default_rng(0).standard_normal((3, T, 1))
# the held entries at their true values, the estimated ones started away from theirs
START = np.where(MASK, 0.5 * TRUE_X0, TRUE_X0)


def residuals(p):
    """The residuals zhat - z of every record for p = (w0sq, b, x0[1, q], x0[1, v],
    x0[2, v]), by a Python loop of the step."""
    th = {"w0sq": p[0], "b": p[1]}
    x0s = [jnp.asarray(TRUE_X0[0]), p[2:4], jnp.stack([TRUE_X0[2, 0], p[4]])]
    out = []
    for i, x in enumerate(x0s):
        for k in range(T):
            out.append(angle_only(x, U[i, k], th)[0] - Z[i, k, 0])
            x = euler_pendulum_step(x, U[i, k], th)
    return jnp.stack(out)


REFERENCE = {}


def reference():
    """SciPy's optimum of the free variables and their standard errors."""
    if not REFERENCE:
        sol = least_squares(lambda p: np.asarray(residuals(jnp.asarray(p))),
                            [7.0, 0.3, 0.4, -0.25, 0.2], xtol=1e-15, ftol=1e-15,
                            gtol=1e-15)  # fmt: skip
        J = np.asarray(jax.jacfwd(residuals)(jnp.asarray(sol.x)))
        r = np.asarray(residuals(jnp.asarray(sol.x)))
        s2 = r @ r / (r.size - sol.x.size)
        REFERENCE.update(p=sol.x, std=np.sqrt(np.diag(s2 * np.linalg.inv(J.T @ J))))
    return REFERENCE


def _free(result):
    return np.array([result.theta["w0sq"], result.theta["b"], *result.x0[1], result.x0[2, 1]])


@pytest.mark.parametrize(
    "solver",
    [
        oj.LevenbergMarquardt(),
        oj.GaussNewton(),
        oj.LBFGS(max_steps=2000),
        [oj.Adam(lr_theta=1e-2, lr_x0=1e-2, max_steps=300), oj.LevenbergMarquardt()],
    ],
    ids=["lm", "gn", "lbfgs", "adam_lm"],
)
def test_every_solver_holds_each_records_own_entries_and_reaches_the_optimum(solver):
    """The held entries keep the values `x0` gives them exactly; the free variables reach
    SciPy's optimum of the problem without them, and the fit reports success. Without
    the hold (every entry some record estimates, estimated in every record) the optimum
    differs: the held values are not those the data would choose."""
    result = oj.fit(MODEL, THETA0, START, U, Z, estimate_x0=MASK, solver=solver)
    assert result.success, result.message
    np.testing.assert_array_equal(result.x0[~MASK], TRUE_X0[~MASK])
    np.testing.assert_allclose(_free(result), reference()["p"], rtol=1e-6, atol=1e-8)
    assert "at_bound" not in result.stop_info
    np.testing.assert_array_equal(result.x0_estimated, MASK)


def test_standard_errors_and_criteria_count_only_the_estimated_entries():
    """theta's and the estimated x0 entries' standard errors are sigma^2 (J^T J)^{-1} of
    the free variables alone (five, not the eight of theta and every record's two
    entries); the held entries' are 0; the AIC counts five estimates."""
    result = oj.fit(MODEL, THETA0, START, U, Z, estimate_x0=MASK)
    ref = reference()
    std = np.array([result.std["w0sq"], result.std["b"], *result.x0_std[1], result.x0_std[2, 1]])
    np.testing.assert_allclose(std, ref["std"], rtol=1e-6)
    np.testing.assert_array_equal(result.x0_std[~MASK], 0.0)
    # (the covariance spans the entries some record estimates: zero where held)
    assert result.x0_covariance.shape == (3, 2, 2)
    np.testing.assert_array_equal(result.x0_covariance[0], 0.0)
    np.testing.assert_array_equal(result.x0_covariance[2][0], 0.0)
    zhat = Z + np.asarray(result.residuals)
    np.testing.assert_allclose(result.metrics["aic"], oj.metrics.aic(Z, zhat, 5), rtol=1e-12)
    text = str(result)
    assert "3 of 6 initial states (3 trajectories, each its own) estimated" in text
    assert text.count("(fixed)") == 3
    sigma = np.sqrt(np.mean(np.asarray(result.residuals) ** 2) * Z.size / (Z.size - 5))
    assert result._noise_variance() == pytest.approx(sigma**2, rel=1e-12)


def test_newey_west_takes_the_held_entries_out_too():
    """The sandwich covariance without lags: theta's block is H J^T diag(r^2) J H
    (H = (J^T J)^{-1} of the free variables alone, J from `jax.jacfwd`) times
    n_obs / (n_obs - 5); the held entries' standard errors are 0, the others finite."""
    result = oj.fit(MODEL, THETA0, START, U, Z, estimate_x0=MASK, covariance=oj.NeweyWest(0))
    p = jnp.asarray(_free(result))
    J, r = np.asarray(jax.jacfwd(residuals)(p)), np.asarray(residuals(p))
    H = np.linalg.inv(J.T @ J)
    cov = H @ (J.T * r**2) @ J @ H * r.size / (r.size - 5)
    order = [result.names.index(n) for n in ("w0sq", "b")]  # (result.names: b, w0sq)
    np.testing.assert_allclose(result.covariance[np.ix_(order, order)], cov[:2, :2], rtol=1e-6)
    np.testing.assert_array_equal(result.x0_std[~MASK], 0.0)
    assert np.all(np.isfinite(result.x0_std[MASK])) and np.all(result.x0_std[MASK] > 0)


def test_bounds_and_multistart_with_a_mask_per_record(tmp_path):
    """`x0_bounds` on an estimated entry acts beside the held ones (the held ones are no
    bound: `at_bound` names only the bounded entry, `x0_bounds` is the user's box); the
    mask is saved and loaded; multistart starts may differ only in estimated entries."""
    upper = np.array([[np.inf, np.inf], [0.7, np.inf], [0.1, np.inf]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (record 2's held angle, 0.3, is no start outside)
        result = oj.fit(MODEL, THETA0, START, U, Z, estimate_x0=MASK, x0_bounds=(None, upper))
    assert result.success, result.message
    assert result.x0[1, 0] == 0.7
    np.testing.assert_array_equal(result.x0[~MASK], TRUE_X0[~MASK])
    assert result.stop_info["at_bound"] == ["x0[1, q]"]
    held_free = upper.copy()
    held_free[2, 0] = np.inf  # (record 2's held angle: not bounded)
    np.testing.assert_array_equal(result.x0_bounds[1], held_free)
    path = tmp_path / "masked.npz"
    result.save(path)
    loaded = oj.load_result(path, model=MODEL)
    np.testing.assert_array_equal(loaded.x0_estimated, MASK)
    assert "each its own" in str(loaded)
    starts = np.stack([START, START])
    starts[1, 1] = [0.1, 0.1]  # (an estimated entry: allowed)
    multi = oj.fit(MODEL, {"w0sq": np.array([7.0, 11.0]), "b": np.array([0.3, 0.3])}, starts,
                   U, Z, estimate_x0=MASK, multistart=True)  # fmt: skip
    np.testing.assert_allclose(_free(multi), reference()["p"], rtol=1e-6, atol=1e-8)
    starts[1, 2, 0] = 0.0  # (record 2 holds its angle)
    with pytest.raises(ValueError, match=r"entries \[0\] of records \[2\]"):
        oj.fit(MODEL, {"w0sq": np.array([7.0, 11.0]), "b": np.array([0.3, 0.3])}, starts,
               U, Z, estimate_x0=MASK, multistart=True)  # fmt: skip


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(estimate_x0=MASK[:2]), r"shape \(N, n_x\) = \(3, 2\)"),
        (dict(estimate_x0=MASK.T), r"shape \(N, n_x\) = \(3, 2\)"),
        (dict(estimate_x0=MASK.astype(int)), r"array of int64 \(True / False"),
        (
            dict(solver=oj.Optimistix(optx.LevenbergMarquardt(1e-8, 1e-8))),
            r"mask per record is not available with `Optimistix` \(the entries a record holds",
        ),
        (dict(aggregate=oj.Aggregate(0, [(0, 3)], [1.0])), "with `aggregate`"),
    ],
    ids=["records", "transposed", "integers", "optimistix", "aggregate"],
)
def test_a_mask_per_record_that_cannot_apply_is_refused(kwargs, match):
    kwargs = {"estimate_x0": MASK, **kwargs}
    with pytest.raises(ValueError, match=match):
        oj.fit(MODEL, THETA0, START, U, Z, **kwargs)


def test_windows_refuse_a_mask_per_record():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match="with `window`"):
            oj.fit(MODEL, THETA0, START[1], U[1], Z[1], window=20,
                   estimate_x0=np.ones((3, 2), bool))  # fmt: skip
    with pytest.raises(ValueError, match=r"`estimate` must be an \(n_x,\) = \(2,\)"):
        oj.estimate_x0(MODEL, THETA0, U[1], Z[1], n=10, x0=START[1], estimate=MASK)


def test_predict_of_the_fitted_records_holds_each_records_own_entries():
    """`result.predict(U, Z, x0=result.x0, estimate=result.x0_estimated)` predicts each
    record with its own mask: the held entries keep their values, the others are
    estimated (from all of each record: the fitted x0 again). Record 0 holds every
    entry: its prediction is the simulation from its x0, known exactly."""
    result = oj.fit(MODEL, THETA0, START, U, Z, estimate_x0=MASK)
    preds = result.predict(U, Z, x0=result.x0, estimate=result.x0_estimated)
    for i, pred in enumerate(preds[1:], start=1):
        np.testing.assert_array_equal(pred.x0[~MASK[i]], TRUE_X0[i][~MASK[i]])
        np.testing.assert_allclose(pred.x0, result.x0[i], rtol=1e-6, atol=1e-8)
    rest = preds[0]
    np.testing.assert_array_equal(rest.x0, TRUE_X0[0])
    np.testing.assert_array_equal(rest.z, result.simulate(U[0], TRUE_X0[0])[1])
    assert rest.estimate.success and np.all(rest.estimate.std == 0.0)
    with pytest.raises(
        ValueError,
        match=r"`estimate` \(the x0 entries to estimate\) must have shape \(n_x,\) or \(3, n_x\)",
    ):
        result.predict(U, Z, x0=result.x0, estimate=MASK[:2])
