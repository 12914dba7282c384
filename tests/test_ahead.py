"""K-step-ahead prediction by the extended Kalman filter (`predict_ahead`, MATLAB's
`predict(sys, data, K)`). The reference is a Kalman filter written here in NumPy for a
linear model (where the EKF is the Kalman filter), with its K-step propagation."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

A = np.array([[0.95, 0.1], [-0.2, 0.9]])
B = np.array([[0.0], [0.1]])
C = np.array([[1.0, 0.0]])
T = 80


def step(x, u, th):
    return th["A"] @ x + B @ u


def observe(x, u, th):
    del u, th
    return C @ x


LINEAR = oj.Model(step, observe)
rng = np.random.default_rng(0)
U = rng.standard_normal((T, 1))
Q = 0.05**2 * np.eye(2)  # the process noise the data were made with
R = np.array([[0.02**2]])
P0, M0 = np.eye(2), np.zeros(2)


def _record():
    x, zs = np.array([1.0, -0.5]), []
    for k in range(T):
        zs.append(C @ x + 0.02 * rng.standard_normal(1))
        x = A @ x + B @ U[k] + 0.05 * rng.standard_normal(2)
    return np.array(zs)


Z = _record()


def reference(K, z):
    """The Kalman filter's means x[k|k] (a NaN sample: no update) and the K-step
    predictions C A^K-propagated from x[k-K|k-K] (from the prior mean before sample K)."""
    m, P, filtered = M0.copy(), P0.copy(), []
    for k in range(T):
        if np.all(np.isfinite(z[k])):
            gain = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
            m, P = m + gain @ (z[k] - C @ m), (np.eye(2) - gain @ C) @ P
        filtered.append(m.copy())
        m, P = A @ m + B @ U[k], A @ P @ A.T + Q
    out = []
    for k in range(T):
        x, j, n = (filtered[k - K], k - K, K) if k >= K else (M0, 0, k)
        for i in range(n):
            x = A @ x + B @ U[j + i]
        out.append(C @ x)
    return np.array(out), np.array(filtered)


def _ahead(K, z=Z, **kwargs):
    return oj.predict_ahead(LINEAR, {"A": A}, U, z, K, x0=M0, process_noise=Q,
                            measurement_noise=R, prior_covariance=P0, **kwargs)  # fmt: skip


@pytest.mark.parametrize("K", [1, 3])
def test_a_linear_model_gives_the_kalman_filters_k_step_predictions(K):
    pred = _ahead(K)
    z_ref, filtered = reference(K, Z)
    np.testing.assert_allclose(pred.filtered, filtered, atol=1e-12)
    np.testing.assert_allclose(pred.z, z_ref, atol=1e-12)
    assert pred.K == K and pred.z.shape == (T, 1) and pred.x.shape == (T, 2)


def test_a_horizon_past_the_record_is_the_simulation_from_x0():
    _, z_sim = oj.simulate(LINEAR, {"A": A}, M0, U)
    for K in (T, T + 5, math.inf):
        pred = _ahead(K)
        assert pred.K == T
        np.testing.assert_allclose(pred.z, np.asarray(z_sim), rtol=1e-12, atol=1e-15)


def test_a_missing_sample_is_no_correction():
    z = Z.copy()
    z[[10, 11, 40]] = np.nan
    pred = _ahead(2, z, missing="mask")
    np.testing.assert_allclose(pred.z, reference(2, z)[0], atol=1e-12)
    with pytest.raises(ValueError, match="NaN"):
        _ahead(2, z)


def test_the_results_method_takes_the_fits_noise_and_x0():
    """`FitResult.predict_ahead` equals the function given the fit's measurement noise
    sigma^2 and the record's x0 estimated as `predict` does (the function's own default,
    1 % of the outputs' RMS, would give other predictions). Shorter horizons predict the
    record better than a longer one: the data were made with process noise. (Not the
    simulation: on the fitted record, from the x0 fitted to all of it, it is the
    output-error fit itself.)"""
    theta0 = {"A": np.array([[0.95, 0.1], [0.0, 0.8]])}  # (its first row known)
    result = oj.fit(LINEAR, theta0, M0, U, Z, fixed={"A": np.array([[True, True], [False, False]])})
    assert result.success
    mine = result.predict_ahead(U, Z, 2, process_noise=Q)
    x0 = result.predict(U, Z).x0
    noise = result._measurement_noise()
    same = oj.predict_ahead(LINEAR, result.theta, U, Z, 2, x0=x0, process_noise=Q,
                            measurement_noise=noise)  # fmt: skip
    np.testing.assert_allclose(mine.z, same.z, rtol=1e-12, atol=1e-14)
    other = oj.predict_ahead(LINEAR, result.theta, U, Z, 2, x0=x0, process_noise=Q)
    assert np.abs(other.z - mine.z).max() > 1e-4
    rmse = [oj.metrics.rmse(Z, result.predict_ahead(U, Z, K, process_noise=Q).z)[0]
            for K in (1, 5)]  # fmt: skip
    assert rmse[0] < 0.8 * rmse[1]


@pytest.mark.parametrize(
    "K, error, match",
    [
        (0, ValueError, "integer >= 1"),
        (2.5, TypeError, "integer >= 1"),
        (True, TypeError, "integer >= 1"),
        (jnp.array(2), TypeError, "integer >= 1"),
    ],
)
def test_bad_horizons_are_named(K, error, match):
    with pytest.raises(error, match=match):
        _ahead(K)


def test_bad_arguments_are_named():
    with pytest.raises(TypeError, match="process_noise"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, x0=M0)
    with pytest.raises(ValueError, match="`x0`"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, process_noise=Q)
    with pytest.raises(ValueError, match="process_noise"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, x0=M0, process_noise=-np.eye(2))
    result = oj.fit(LINEAR, {"A": A}, M0, U, Z, fixed=True)
    with pytest.raises(ValueError, match="one record per call"):
        result.predict_ahead(np.stack([U, U]), np.stack([Z, Z]), 2, process_noise=Q)


def test_compare_plots_a_k_step_prediction():
    """`plot.compare(z, ahead)` (MATLAB's `compare(data, sys, K)`) draws its `z` with its
    FIT against the record."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pred = _ahead(3)
    fig = oj.plot.compare(Z, pred)
    fit = 100 * (1 - np.linalg.norm(pred.z - Z) / np.linalg.norm(Z - Z.mean()))
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert f"model: FIT {fit:.2f} %" in texts
    plt.close(fig)
