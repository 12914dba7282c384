"""K-step-ahead prediction by the extended Kalman filter (`predict_ahead`, MATLAB's
`predict(sys, data, K)`). The reference is a Kalman filter written here in NumPy for a
linear model (where the EKF is the Kalman filter), with its K-step propagation."""

import dataclasses
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
    """The Kalman filter's means x[k|k] (a NaN sample: no update), the K-step
    predictions C A^K-propagated from x[k-K|k-K] (from the prior mean before sample K),
    and the std of their errors, sqrt(C P[k|k-K] C^T + R) with P[k|k-K] A^K-propagated
    from P[k-K|k-K] (from the prior's P0 before sample K)."""
    m, P, filtered, covariances = M0.copy(), P0.copy(), [], []
    for k in range(T):
        if np.all(np.isfinite(z[k])):
            gain = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
            m, P = m + gain @ (z[k] - C @ m), (np.eye(2) - gain @ C) @ P
        filtered.append(m.copy())
        covariances.append(P.copy())
        m, P = A @ m + B @ U[k], A @ P @ A.T + Q
    out, std = [], []
    for k in range(T):
        if k >= K:
            x, S, j, n = filtered[k - K], covariances[k - K], k - K, K
        else:
            x, S, j, n = M0, P0, 0, k
        for i in range(n):
            x, S = A @ x + B @ U[j + i], A @ S @ A.T + Q
        out.append(C @ x)
        std.append(np.sqrt(np.diag(C @ S @ C.T + R)))
    return np.array(out), np.array(filtered), np.array(std)


def _ahead(K, z=Z, **kwargs):
    return oj.predict_ahead(LINEAR, {"A": A}, U, z, K, x0=M0, process_noise=Q,
                            measurement_noise=R, prior_covariance=P0, **kwargs)  # fmt: skip


@pytest.mark.parametrize("K", [1, 3])
def test_a_linear_model_gives_the_kalman_filters_k_step_predictions(K):
    pred = _ahead(K)
    z_ref, filtered, std = reference(K, Z)
    np.testing.assert_allclose(pred.filtered, filtered, atol=1e-12)
    np.testing.assert_allclose(pred.z, z_ref, atol=1e-12)
    np.testing.assert_allclose(pred.std, std, rtol=1e-10)
    assert pred.K == K and pred.z.shape == pred.std.shape == (T, 1) and pred.x.shape == (T, 2)
    # The data were made with this noise: the errors after the prior's first samples,
    # each divided by its std, have about unit variance (80 samples: 0.16 its std for
    # K = 1, more for the overlapping errors of K = 3).
    e = (Z - pred.z)[10:] / pred.std[10:]
    assert 0.6 < np.mean(e**2) < 1.5


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
    z_ref, _, std = reference(2, z)
    np.testing.assert_allclose(pred.z, z_ref, atol=1e-12)
    np.testing.assert_allclose(pred.std, std, rtol=1e-10)
    with pytest.raises(ValueError, match="NaN"):
        _ahead(2, z)


def test_the_results_method_takes_the_fits_noise_and_x0():
    """`FitResult.predict_ahead` equals the function given the fit's measurement noise
    sigma^2 and the record's x0 estimated as `predict` does with the smoother under the
    process noise given (the function's own default, 1 % of the outputs' RMS, would give
    other predictions). Shorter horizons predict the record better than a longer one: the
    data were made with process noise. (Not the simulation: on the fitted record, from
    the x0 fitted to all of it, it is the output-error fit itself.)"""
    theta0 = {"A": np.array([[0.95, 0.1], [0.0, 0.8]])}  # (its first row known)
    result = oj.fit(LINEAR, theta0, M0, U, Z, fixed={"A": np.array([[True, True], [False, False]])})
    assert result.success
    mine = result.predict_ahead(U, Z, 2, process_noise=Q)
    estimate = result.predict(U, Z, method="smoother", process_noise=Q).estimate
    x0, P0_fit = estimate.x0, estimate.covariance
    noise = result._measurement_noise()
    same = oj.predict_ahead(LINEAR, result.theta, U, Z, 2, x0=x0, process_noise=Q,
                            measurement_noise=noise, prior_covariance=P0_fit)  # fmt: skip
    np.testing.assert_allclose(mine.z, same.z, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(mine.std, same.std, rtol=1e-12)
    other = oj.predict_ahead(LINEAR, result.theta, U, Z, 2, x0=x0, process_noise=Q)
    assert np.abs(other.z - mine.z).max() > 1e-4
    # The prior is the x0 estimate's covariance, not the function's broad default: the
    # first predictions (a simulation from x0) have the std of that x0's uncertainty.
    # (Not the least-squares estimate's, which takes the residuals as white.)
    lsq = result.predict(U, Z).estimate
    assert np.abs(lsq.covariance - P0_fit).max() > 0.1 * np.abs(P0_fit).max()
    broad = oj.predict_ahead(LINEAR, result.theta, U, Z, 2, x0=x0, process_noise=Q,
                             measurement_noise=noise)  # fmt: skip
    assert np.all(np.isfinite(P0_fit)) and mine.std[0, 0] < 0.1 * broad.std[0, 0]
    np.testing.assert_allclose(mine.std[0], np.sqrt(C @ P0_fit @ C.T + noise).ravel(), rtol=1e-10)
    rmse = [oj.metrics.rmse(Z, result.predict_ahead(U, Z, K, process_noise=Q).z)[0]
            for K in (1, 5)]  # fmt: skip
    assert rmse[0] < 0.8 * rmse[1]


@pytest.mark.parametrize(
    "K, error, match",
    [
        (0, ValueError, "integer >= 1"),
        (2.5, TypeError, "integer >= 1"),
        (True, TypeError, "integer >= 1"),
        (jnp.array([2]), TypeError, "integer >= 1"),
        (np.array(2.0), TypeError, "integer >= 1"),
    ],
)
def test_bad_horizons_are_named(K, error, match):
    with pytest.raises(error, match=match):
        _ahead(K)
    assert _ahead(np.array(2)).K == _ahead(jnp.array(2)).K == 2  # (0-d integer arrays)


def test_bad_arguments_are_named():
    with pytest.raises(TypeError, match="process_noise"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, x0=M0)
    with pytest.raises(ValueError, match="`x0`"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, process_noise=Q)
    with pytest.raises(ValueError, match="process_noise"):
        oj.predict_ahead(LINEAR, {"A": A}, U, Z, 2, x0=M0, process_noise=-np.eye(2))
    result = oj.fit(LINEAR, {"A": A}, M0, U, Z, fixed=True)
    with pytest.raises(ValueError, match="`z` must hold one record's outputs per record"):
        result.predict_ahead(np.stack([U, U]), Z, 2, process_noise=Q)
    with pytest.raises(ValueError, match=r"`x0` \(the prior means\) must have shape"):
        result.predict_ahead([U, U], [Z, Z], 2, process_noise=Q, x0=np.zeros((3, 2)))
    # The result's methods name their own `z` (not the head of the default x0's
    # `predict`), and records that are not records.
    for z, match in (
        (Z[:, 0], r"`z` must have shape \(80, 1\)"),
        (Z.T, r"is it transposed\? z is \(T, n_z\)"),
        (Z[:70], r"`z` must have shape \(80, 1\)"),
        (np.where(np.arange(T)[:, None] == 5, np.nan, Z), "`z` contains NaN values: pass"),
        (None, "`z` is required"),
    ):  # fmt: skip
        for method in (result.predict_ahead, result.estimate_process_noise):
            with pytest.raises(ValueError, match=match):
                method(U, z, 2, **({"process_noise": Q} if method == result.predict_ahead else {}))
    with pytest.raises(ValueError, match=r"\(T, 1\): u\[:, None\]"):
        result.predict_ahead(U[:, 0], Z, 2, process_noise=Q)
    with pytest.raises(ValueError, match=r"`u` must hold at least one sample"):
        result.predict_ahead(U[:0], Z[:0], 2, process_noise=Q)
    with pytest.raises(ValueError, match="`u` holds no records"):
        result.predict_ahead(np.zeros((0, T, 1)), np.zeros((0, T, 1)), 2, process_noise=Q)
    with pytest.raises(ValueError, match="`u` is empty"):
        result.output_std([], x0=M0)
    with pytest.raises(ValueError, match="`z` must have shape"):  # (a record of two outputs)
        result.predict_ahead([U, U], [np.ones((T, 2)), Z], 2, process_noise=Q)
    # The free functions take one record, and name `z` where x0 defaults to z[0] (they
    # advised an x0 of shape (N, n_x), then refused it; named `x0` for a 1-D z; raised an
    # IndexError on an empty record; a step's error on z of too few columns).
    state = oj.Model(step)  # (z = x: x0 defaults to z[0])
    X = np.asarray(oj.simulate(state, {"A": A}, M0, U)[1])
    for f in (oj.predict_ahead, oj.estimate_process_noise):
        for u, z, x0, match in (
            (np.stack([U, U]), np.stack([X, X]), M0, r"`u` must have shape \(T, n_u\) \(one"),
            ([U, U], [X, X], None, "`u` must have shape .* got a list of 2 records"),
            (U, X[:, 0], None, r"`z` must have shape \(T, n_z\) with T >= 1, got \(80,\)"),
            (U[:0], X[:0], None, r"`z` must have shape \(T, n_z\) with T >= 1, got \(0, 2\)"),
            (U, X[:, :1], None, r"it defaults to z\[0\], so `z` needs one column per state"),
        ):  # fmt: skip
            with pytest.raises(ValueError, match=match):
                f(state, {"A": A}, u, z, 1.0 if f is oj.estimate_process_noise else 2,
                  x0=x0, **({"process_noise": Q} if f is oj.predict_ahead else {}))  # fmt: skip
    # `estimate_process_noise`'s `shape` and `scales` are named as such.
    for shape, match in ((-np.eye(2), "`shape` must be positive semi-definite"),
                         (np.ones(3), r"`shape` must be a scalar, a \(2,\) vector"),
                         (0.0, "`shape` must have a nonzero entry")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            oj.estimate_process_noise(LINEAR, {"A": A}, U, Z, shape, x0=M0, measurement_noise=R)
    for scales in ([1.0, 10.0, np.inf], "abc"):
        with pytest.raises(ValueError, match="`scales` must"):
            result.estimate_process_noise(U, Z, 1.0, scales=scales)


def test_the_results_method_predicts_each_of_several_records():
    """Several records (an (N, T, .) array or a list of different lengths) give one
    `AheadPrediction` per record, each the single-record call on it: the prior means
    one per row of an (N, n_x) `x0`, or each record's own estimate by default."""
    result = oj.fit(LINEAR, {"A": A}, M0, U, Z, fixed=True)
    other = Z[::-1].copy()  # (a second record of other outputs: another x0, other filtering)
    x0 = np.array([[0.5, 0.0], [-1.0, 0.2]])
    preds = result.predict_ahead(np.stack([U, U]), np.stack([Z, other]), 3, process_noise=Q,
                                 x0=x0)  # fmt: skip
    for pred, z, start in zip(preds, (Z, other), x0, strict=True):
        alone = result.predict_ahead(U, z, 3, process_noise=Q, x0=start)
        np.testing.assert_array_equal(pred.z, alone.z)
        np.testing.assert_array_equal(pred.std, alone.std)
    assert np.abs(preds[0].z - preds[1].z).max() > 0.1
    ragged = result.predict_ahead([U, U[:50]], [Z, other[:50]], 3, process_noise=Q)
    assert [p.z.shape for p in ragged] == [(T, 1), (50, 1)]
    np.testing.assert_array_equal(
        ragged[1].z, result.predict_ahead(U[:50], other[:50], 3, process_noise=Q).z
    )


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
    assert f"model (3-step ahead): FIT {fit:.2f} %" in texts  # (MATLAB names K too)
    assert not fig.axes[0].collections  # (no band without `confidence`)
    plt.close(fig)
    # With `confidence`, its prediction band: zhat +- q std (q of 90 %).
    fig = oj.plot.compare(Z, pred, confidence=0.9)
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "model (3-step ahead): 90 % prediction band" in texts
    vertices = fig.axes[0].collections[0].get_paths()[0].vertices
    # (the path runs along the lower edge, then back along the upper one)
    lower, upper = vertices[1 : T + 1, 1], vertices[T + 2 : -1, 1][::-1]
    q = 1.6448536269514722
    np.testing.assert_allclose(lower, pred.z[:, 0] - q * pred.std[:, 0], rtol=1e-12)
    np.testing.assert_allclose(upper, pred.z[:, 0] + q * pred.std[:, 0], rtol=1e-12)
    plt.close(fig)
    # A broad prior's band over the first K samples (std ~ 1000 against outputs of ~1)
    # is cut at the axis, which holds the outputs' range and no more than it beyond.
    broad = oj.predict_ahead(LINEAR, {"A": A}, U, Z, 3, x0=M0, process_noise=Q,
                             measurement_noise=R, prior_covariance=1e6)  # fmt: skip
    assert broad.std[0, 0] > 100
    fig = oj.plot.compare(Z, broad, confidence=0.95)
    low, high = fig.axes[0].get_ylim()
    values = np.concatenate([Z[:, 0], broad.z[:, 0]])
    span = values.max() - values.min()
    assert values.min() - span <= low < values.min() and values.max() < high <= values.max() + span
    plt.close(fig)
    # The model's names of its outputs label the axes.
    named = oj.predict_ahead(oj.Model(step, observe, outputs="q (m)"), {"A": A}, U, Z, 3, x0=M0,
                             process_noise=Q, measurement_noise=R)  # fmt: skip
    assert named.outputs == ("q (m)",) and pred.outputs is None
    fig = oj.plot.compare(Z, named)
    assert fig.axes[0].get_ylabel() == "q (m)"
    plt.close(fig)


def reference_log_likelihood(q, z):
    """The Kalman filter's log-likelihood of z, process noise q I: the innovations
    e_k = z[k] - C m[k|k-1], S_k = C P[k|k-1] C^T + R (a NaN sample left out)."""
    m, P, total = M0.copy(), P0.copy(), 0.0
    for k in range(T):
        if np.all(np.isfinite(z[k])):
            S = C @ P @ C.T + R
            e = z[k] - C @ m
            total -= 0.5 * (
                np.log(np.linalg.det(S)) + e @ np.linalg.solve(S, e) + np.log(2 * np.pi)
            )
            gain = P @ C.T @ np.linalg.inv(S)
            m, P = m + gain @ e, (np.eye(2) - gain @ C) @ P
        m, P = A @ m + B @ U[k], A @ P @ A.T + q * np.eye(2)
    return total


def test_the_process_noise_of_the_highest_likelihood():
    """The log-likelihood at each scale of the grid is the Kalman filter's of the record
    (a missing sample left out); the estimate maximises it between the grid's points,
    and on a long record made with process noise 0.05^2 I it finds that within 10 %."""
    z = Z.copy()
    z[20] = np.nan
    grid = np.array([1e-4, 1e-3, 1e-2, 1e-1])
    pn = oj.estimate_process_noise(LINEAR, {"A": A}, U, z, 1.0, x0=M0, measurement_noise=R,
                                   prior_covariance=P0, scales=grid, missing="mask")  # fmt: skip
    want = [reference_log_likelihood(q, z) for q in grid]
    np.testing.assert_allclose(pn.log_likelihoods, want, rtol=1e-11)
    assert pn.interior and grid[0] < pn.scale < grid[-1]
    for q in (0.98 * pn.scale, 1.02 * pn.scale):
        assert reference_log_likelihood(q, z) < pn.log_likelihood
    np.testing.assert_allclose(pn.log_likelihood, reference_log_likelihood(pn.scale, z),
                               rtol=1e-11)  # fmt: skip
    np.testing.assert_allclose(pn.covariance, pn.scale * np.eye(2))
    # (print: a few lines, not the dataclass with its 65-point grid)
    text = str(pn)
    assert text.startswith(f"process noise q = {pn.scale:.4g} times the shape (log-likelihood ")
    assert "inside the grid" in text and "array" not in text and repr(pn) == text
    # The estimate itself is a `process_noise` (it was refused as an array of 6 fields)
    kw = dict(x0=M0, measurement_noise=R, prior_covariance=P0, missing="mask")
    given = oj.predict_ahead(LINEAR, {"A": A}, U, z, 3, process_noise=pn, **kw)
    by_hand = oj.predict_ahead(LINEAR, {"A": A}, U, z, 3, process_noise=pn.covariance, **kw)
    np.testing.assert_array_equal(given.z, by_hand.z)
    np.testing.assert_array_equal(given.std, by_hand.std)
    rng = np.random.default_rng(1)
    n = 2000
    u, x, zs = rng.standard_normal((n, 1)), np.zeros(2), []
    for k in range(n):
        zs.append(C @ x + 0.02 * rng.standard_normal(1))
        x = A @ x + B @ u[k] + 0.05 * rng.standard_normal(2)
    long = oj.estimate_process_noise(LINEAR, {"A": A}, u, np.array(zs), 1.0, x0=M0,
                                     measurement_noise=R, prior_covariance=P0)  # fmt: skip
    assert abs(long.scale / 0.05**2 - 1) < 0.1


def test_no_process_noise_in_the_data_is_said():
    """A record simulated without process noise: the likelihood rises to the grid's
    lowest scale, which a warning names; the result's method takes the fit's noise."""
    _, z = oj.simulate(LINEAR, {"A": A}, np.array([1.0, -0.5]), U)
    z = np.asarray(z) + 0.02 * rng.standard_normal((T, 1))
    with pytest.warns(UserWarning, match="less process noise than the grid holds"):
        pn = oj.estimate_process_noise(LINEAR, {"A": A}, U, z, 1.0, x0=M0, measurement_noise=R)
    assert not pn.interior and pn.scale == pn.scales[0]
    result = oj.fit(LINEAR, {"A": A}, M0, U, z, fixed=True)
    with pytest.warns(UserWarning, match="less process noise") as rec:  # (at this line:
        result.estimate_process_noise(U, z, 1.0)  # it was the method's own, in the library)
    assert {w.filename for w in rec} == {__file__}
    mine = result.estimate_process_noise(U, Z, [0.0, 1.0], scales=np.logspace(-6, 0, 7))
    same = oj.estimate_process_noise(
        LINEAR, {"A": A}, U, Z, [0.0, 1.0], x0=result.predict(U, Z).x0,
        measurement_noise=result._measurement_noise(), scales=np.logspace(-6, 0, 7),
    )  # fmt: skip
    np.testing.assert_allclose(mine.log_likelihoods, same.log_likelihoods, rtol=1e-12)
    np.testing.assert_allclose(mine.covariance, np.diag([0.0, mine.scale]))
    with pytest.raises(ValueError, match="`scales` must be an increasing grid"):
        oj.estimate_process_noise(LINEAR, {"A": A}, U, Z, 1.0, x0=M0, scales=[1.0, 0.1, 2.0])
    with pytest.raises(TypeError, match="`shape` must be given"):
        oj.estimate_process_noise(LINEAR, {"A": A}, U, Z, None, x0=M0)
    # (a word such as "diagonal": what is wanted, not a dtype)
    with pytest.raises(TypeError, match=r"`shape` must be .* a \(2,\) vector of variances"):
        oj.estimate_process_noise(LINEAR, {"A": A}, U, Z, "diagonal", x0=M0)


def test_noise_on_a_state_the_outputs_do_not_see_is_not_estimated():
    """Process noise on a third state that neither the output nor the other states see:
    the likelihood is the same at every scale, and the warning said "the data ask for
    less process noise", advising a wider grid. It now says that q is not determined."""

    def step3(x, u, th):
        return jnp.concatenate([th["A"] @ x[:2] + B @ u, 0.5 * x[2:]])

    model = oj.Model(step3, lambda x, u, th: C @ x[:2])
    with pytest.warns(UserWarning, match="the likelihood is the same at every scale"):
        pn = oj.estimate_process_noise(
            model, {"A": A}, U, Z, [0.0, 0.0, 1.0], x0=np.zeros(3), measurement_noise=R
        )
    assert not pn.interior


def test_a_missing_entry_leaves_its_noise_covariances_out():
    """Two correlated measurement noises, one of them missing at some samples: the
    filter updates from the measured entry with its own variance (the Kalman filter of
    the measured rows), not with a covariance to the one not measured."""
    C2, R2 = np.eye(2), np.array([[4e-4, 3e-4], [3e-4, 9e-4]])
    model = oj.Model(step, lambda x, u, th: x)
    z = np.stack([C2 @ x for x in np.asarray(oj.simulate(LINEAR, {"A": A}, M0 + 1, U)[0])])
    z = z + 0.02 * rng.standard_normal(z.shape)
    z[[5, 6, 30], 1] = np.nan
    z[[12, 50], 0] = np.nan
    m, P, filtered = M0.copy(), P0.copy(), []
    for k in range(T):
        seen = np.isfinite(z[k])
        Cs, Rs = C2[seen], R2[np.ix_(seen, seen)]
        gain = P @ Cs.T @ np.linalg.inv(Cs @ P @ Cs.T + Rs)
        m, P = m + gain @ (z[k][seen] - Cs @ m), (np.eye(2) - gain @ Cs) @ P
        filtered.append(m.copy())
        m, P = A @ m + B @ U[k], A @ P @ A.T + Q
    pred = oj.predict_ahead(model, {"A": A}, U, z, 1, x0=M0, process_noise=Q,
                            measurement_noise=R2, prior_covariance=P0, missing="mask")  # fmt: skip
    np.testing.assert_allclose(pred.filtered, np.array(filtered), atol=1e-12)


def test_the_uncertainty_of_theta_adds_j_sigma_j_to_the_band():
    """`parameters=True` adds J Sigma J^T per sample, J = d zhat[k|k-K] / d theta over the
    free entries (here A's second row): checked with J by central differences of the
    function's predictions (x0, the noises and the prior held), to 1e-6. A covariance
    not computed makes every such std inf."""
    theta0 = {"A": np.array([[0.95, 0.1], [0.0, 0.8]])}
    fixed = {"A": np.array([[True, True], [False, False]])}
    result = oj.fit(LINEAR, theta0, M0, U, Z, fixed=fixed)
    plain = result.predict_ahead(U, Z, 3, process_noise=Q)
    both = result.predict_ahead(U, Z, 3, process_noise=Q, parameters=True)
    np.testing.assert_array_equal(both.z, plain.z)
    estimate = result.predict(U, Z, method="smoother", process_noise=Q).estimate
    kw = dict(x0=estimate.x0, process_noise=Q, measurement_noise=result._measurement_noise(),
              prior_covariance=estimate.covariance)  # fmt: skip
    A_hat, h, columns = np.asarray(result.theta["A"]), 1e-6, []
    for i, j in ((1, 0), (1, 1)):  # (the free entries, in `result.names`' order)
        step = np.zeros((2, 2))
        step[i, j] = h
        up = oj.predict_ahead(LINEAR, {"A": A_hat + step}, U, Z, 3, **kw).z
        down = oj.predict_ahead(LINEAR, {"A": A_hat - step}, U, Z, 3, **kw).z
        columns.append((up - down)[:, 0] / (2 * h))
    J = np.stack(columns, axis=1)
    added = np.einsum("kp,pq,kq->k", J, result.covariance, J)
    assert added.max() > 1e-3 * np.max(plain.std**2)  # (not negligible here)
    np.testing.assert_allclose(both.std[:, 0] ** 2 - plain.std[:, 0] ** 2, added, rtol=1e-6)
    # Without a covariance, every prediction that theta moves has std inf; the first two
    # (C x0 and C A x0, A's first row held) keep the filter's.
    unknown = dataclasses.replace(result, covariance=np.zeros((0, 0)))
    std = unknown.predict_ahead(U, Z, 3, process_noise=Q, parameters=True).std[:, 0]
    moved = np.abs(J).max(axis=1) > 0
    assert not moved[:2].any() and moved[2:].all()
    assert np.isinf(std[moved]).all() and np.array_equal(std[~moved], plain.std[~moved, 0])
    with pytest.raises(TypeError, match="`parameters` must be True or False"):
        result.predict_ahead(U, Z, 3, process_noise=Q, parameters="yes")


def _unstable_record():
    """A partly observed oscillator with negative damping (poles at 1/s and 2/s): its
    simulation over the 10 s record grows to about 3e8, the data are a stable one's."""
    rhs = lambda x, u, th: jnp.array([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])  # noqa: E731
    model = oj.Model.from_ode(rhs, dt=0.05, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    _, z = oj.simulate(model, {"k": 2.0, "c": 0.5}, np.array([0.5, -0.2]), u)
    return model, u, np.asarray(z) + 1e-3 * rng.standard_normal((200, 1))


def test_the_default_prior_of_an_unstable_model_is_sized_before_it_blows_up():
    """The default prior (100 s_x)^2 took s_x over the whole open-loop simulation: about
    3e8, a prior of 1e21 on which the filter broke down, and 197 of 200 predictions
    came back NaN without a word. s_x now counts the samples until the simulated output
    leaves the data's range; the one-step predictions are those of a prior of 1 to 1e-6
    of the outputs' scale. A prior that breaks the filter is refused, naming it."""
    model, u, z = _unstable_record()
    theta, x0 = {"k": 2.0, "c": -3.0}, np.array([0.5, -0.2])
    kw = dict(x0=x0, process_noise=[0.0, 1.0])
    default = oj.predict_ahead(model, theta, u, z, 1, **kw)
    given = oj.predict_ahead(model, theta, u, z, 1, prior_covariance=1.0, **kw)
    assert np.all(np.isfinite(default.z)) and np.all(np.isfinite(default.std))
    rms = lambda p: float(np.sqrt(np.mean((p.z - z) ** 2)))  # noqa: E731
    np.testing.assert_allclose(rms(default), rms(given), rtol=1e-5)
    assert rms(given) < 0.01
    with pytest.raises(ValueError, match=r"NaN from sample \d+ on .*Give `prior_covariance`"):
        oj.predict_ahead(model, theta, u, z, 1, prior_covariance=1e18, **kw)


def test_a_grid_scale_where_the_filter_breaks_down_is_not_a_flat_likelihood():
    """One scale of the grid where the filter's likelihood was -inf made it read as the
    same at every scale: the search was skipped and `interior` False (scale 1 of the
    grid, against 0.81 from the finite ones). Now the search keeps to the finite ones and
    a warning names the scales where the filter broke down; none finite is an error."""
    model, u, z = _unstable_record()
    z = z + 0.02 * np.random.default_rng(5).standard_normal(z.shape)
    theta, x0 = {"k": 2.0, "c": 0.5}, np.array([0.5, -0.2])
    grid = np.logspace(-8, 2, 21)
    plain = oj.estimate_process_noise(model, theta, u, z, [0.0, 1.0], x0=x0, scales=grid)
    assert plain.interior and not np.all(np.isin(plain.scale, grid))
    with pytest.warns(UserWarning, match=r"broke down .* at 1 of the grid's 22 scales"):
        wide = oj.estimate_process_noise(
            model, theta, u, z, [0.0, 1.0], x0=x0, scales=np.r_[grid, 1.5e308]
        )
    assert not np.isfinite(wide.log_likelihoods[-1])
    assert wide.interior and wide.scale == plain.scale
    with pytest.raises(ValueError, match="not finite at any scale of the grid"):
        oj.estimate_process_noise(
            model, theta, u, z, [0.0, 1.0], x0=x0, scales=[1.5e308, 1.6e308, 1.7e308]
        )


def test_the_first_bands_of_records_with_process_noise_are_not_too_narrow():
    """Records made with process noise Q from x0 drawn around M0: the default prior of
    `FitResult.predict_ahead` was the least-squares x0 estimate's covariance, which takes
    the residuals as white; under Q it was about 4 times too small, and the band of the
    first one-step prediction held 72 % of the measurements at the 95 % level (200
    records of another model; 81 % of these 100). The smoother's x[0 | T-1] under Q
    holds at least the level there (its data are the record's too: conservative, 100 %
    at sample 0)."""
    fixed = {"A": np.array([[True, True], [False, False]])}
    result = oj.fit(LINEAR, {"A": A}, M0, U, Z, fixed=fixed)
    rng = np.random.default_rng(7)
    inside = []
    for _ in range(100):
        x, zs = rng.normal(0.0, 1.0, 2), []
        for k in range(T):
            zs.append(C @ x + 0.02 * rng.standard_normal(1))
            x = A @ x + B @ U[k] + 0.05 * rng.standard_normal(2)
        z = np.array(zs)
        ahead = result.predict_ahead(U, z, 1, process_noise=Q)
        inside.append(np.abs(z[0] - ahead.z[0]) <= 1.96 * ahead.std[0])
    assert np.mean(inside) >= 0.9
