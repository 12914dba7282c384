"""`FitResult.sample_theta`: draws of theta from N(estimate, covariance) (MATLAB's
`rsample`), checked on their moments and against the first-order output band
(`output_std`, the delta method), which a Monte Carlo of the draws must reproduce on a
mildly nonlinear model."""

import jax
import numpy as np
import pytest
from helpers import EULER_PENDULUM, angle_only, euler_pendulum_step

import oneshot_jax as oj

MODEL = EULER_PENDULUM
T = 60
U = 0.5 * np.sin(0.3 * np.arange(T) + 1.0)[:, None]
X0 = np.array([0.8, -0.5])
_, Z = oj.simulate(MODEL, {"w0sq": 9.0, "b": 0.6}, X0, U)
Z = np.asarray(Z) + 0.02 * np.random.default_rng(0).standard_normal((T, 1))
RESULT = []


def result():
    if not RESULT:
        RESULT.append(oj.fit(MODEL, {"w0sq": 7.0, "b": 0.3}, X0, U, Z))
    return RESULT[0]


def test_the_draws_have_the_estimates_mean_and_covariance():
    r = result()
    n = 20000
    draws = r.sample_theta(n, seed=1)
    assert draws["w0sq"].shape == (n,) and list(draws) == ["w0sq", "b"]  # (theta0's order)
    X = np.stack([draws[name] for name in r.names], axis=1)  # (the covariance's order)
    est = np.array([r.theta[name] for name in r.names])
    sd = np.sqrt(np.diag(r.covariance))
    assert np.all(np.abs(X.mean(axis=0) - est) < 4 * sd / np.sqrt(n))
    np.testing.assert_allclose(np.cov(X.T), r.covariance, rtol=0.05, atol=0.05 * sd.min() ** 2)
    again = r.sample_theta(n, seed=1)
    np.testing.assert_array_equal(again["b"], draws["b"])
    assert not np.array_equal(r.sample_theta(n, seed=2)["b"], draws["b"])


def test_a_monte_carlo_of_the_draws_gives_the_first_order_band():
    """The spread of the outputs simulated from 2000 draws (MATLAB's `simsd`) is
    `output_std` with x0 known, within the Monte Carlo error (1.6 % per sample)."""
    r = result()
    draws = r.sample_theta(2000, seed=3)
    sims = jax.vmap(lambda th: oj.simulate(MODEL, th, r.x0, U)[1])(draws)
    # (samples 0 and 1 do not depend on theta: no spread; the angle's Euler step adds
    # its rate times dt)
    spread = np.std(np.asarray(sims), axis=0)[2:]
    ratio = spread / r.output_std(U, x0=r.x0)[2:]
    assert np.all((ratio > 0.9) & (ratio < 1.1)), (ratio.min(), ratio.max())


def test_fixed_entries_keep_their_values_and_unknown_covariances_are_refused():
    held = oj.fit(MODEL, {"w0sq": 7.0, "b": 0.6}, X0, U, Z, fixed={"b": True})
    draws = held.sample_theta(5)
    np.testing.assert_array_equal(draws["b"], 0.6)
    assert np.unique(draws["w0sq"]).size == 5
    # Every entry fixed (x0 estimated alone): n copies of theta (NumPy's draw failed on a
    # covariance of no entries).
    x0_only = oj.fit(MODEL, {"w0sq": 9.0, "b": 0.6}, X0, U, Z, fixed=True)
    draws = x0_only.sample_theta(3)
    np.testing.assert_array_equal(draws["w0sq"], [9.0] * 3)
    np.testing.assert_array_equal(draws["b"], [0.6] * 3)
    with pytest.raises(ValueError, match="not computed"):
        oj.fit(MODEL, {"w0sq": 7.0, "b": 0.3}, X0, U, Z, covariance=None).sample_theta(5)

    def idle(x, u, th):  # "g" never acts: its std is inf
        return euler_pendulum_step(x, u, th) + 0.0 * th["g"]

    unknown = oj.fit(oj.Model(idle, angle_only), {"w0sq": 7.0, "b": 0.3, "g": 1.0}, X0, U, Z)
    with pytest.raises(ValueError, match=r"standard errors of g are inf"):
        unknown.sample_theta(5)
    for n in (0, 2.5, True):
        with pytest.raises(ValueError, match="`n`"):
            result().sample_theta(n)
    for seed in ("a", -1, 1.5):  # (NumPy's SeedSequence messages named no argument)
        with pytest.raises(ValueError, match="`seed` must be a non-negative integer"):
            result().sample_theta(3, seed=seed)


def test_the_correlation_matrix_is_the_covariance_at_unit_diagonal():
    """C_ij / sqrt(C_ii C_jj), by name; NaN for a parameter the data do not determine
    (std inf), the others' entries unchanged by it."""
    r = result()
    C, std = np.asarray(r.covariance), [float(r.std[name]) for name in r.names]
    np.testing.assert_allclose(r.correlation, C / np.outer(std, std), rtol=1e-12)
    np.testing.assert_array_equal(np.diag(r.correlation), 1.0)
    assert -1.0 < r.correlation[0, 1] < 1.0 and r.correlation[0, 1] != 0.0

    def idle(x, u, th):  # "g" never acts: its std is inf
        return euler_pendulum_step(x, u, th) + 0.0 * th["g"]

    three = oj.fit(oj.Model(idle, angle_only), {"w0sq": 7.0, "b": 0.3, "g": 1.0}, X0, U, Z)
    assert three.names == ("b", "g", "w0sq")
    rho = three.correlation
    assert np.all(np.isnan(rho[1])) and np.all(np.isnan(rho[:, 1]))
    np.testing.assert_allclose(rho[0, 2], r.correlation[0, 1], rtol=1e-6)
    assert oj.fit(MODEL, {"w0sq": 7.0, "b": 0.3}, X0, U, Z, covariance=None).correlation.shape == (
        0,
        0,
    )
