"""`metrics.residual_correlations` against correlations written out with `np.correlate`,
and the figures of `oneshot_jax.plot` (Agg backend)."""

import dataclasses
import subprocess
import sys
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax import metrics

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

Z99 = 2.5758293035489004  # the 0.995 quantile of the standard normal


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def ar1(rng, T, a):
    w = rng.standard_normal(T)
    e = np.empty(T)
    e[0] = w[0]
    for k in range(1, T):
        e[k] = a * e[k - 1] + w[k]
    return e


def np_corr(a, b, max_lag):
    """sum_t a(t) b(t - tau) for tau = -max_lag..max_lag, by np.correlate."""
    full = np.correlate(a, b, "full")  # full[T - 1 + tau] = sum_t a(t + tau) b(t)
    T = len(a)
    return full[T - 1 - max_lag : T + max_lag]


# --------------------------------------------------------------------------- numbers


def test_autocorrelation_matches_numpy():
    rng = np.random.default_rng(0)
    T, M = 400, 12
    e = np.stack([ar1(rng, T, 0.8), ar1(rng, T, -0.5) + 0.3], axis=1)  # with a mean
    rc = metrics.residual_correlations(e, max_lag=M, demean=False)  # MATLAB's sums
    np.testing.assert_array_equal(rc.lags, np.arange(-M, M + 1))
    assert rc.auto.shape == (2 * M + 1, 2) and rc.cross is None and rc.independent is None
    for i in range(2):
        c = np_corr(e[:, i], e[:, i], M)
        np.testing.assert_allclose(rc.auto[:, i], c / c[M], rtol=1e-12, atol=1e-15)
    # AR(1): r(tau) close to a^|tau|, with the sign of a.
    assert rc.auto[M + 1, 0] == pytest.approx(0.8, abs=0.08)
    assert rc.auto[M + 2, 0] == pytest.approx(0.64, abs=0.1)
    np.testing.assert_allclose(rc.bound, Z99 / np.sqrt(T), rtol=1e-12)
    np.testing.assert_array_equal(rc.n, [T, T])
    # By default, the correlations of the centred signal.
    d = e[:, 1] - e[:, 1].mean()
    c = np_corr(d, d, M)
    got = metrics.residual_correlations(e, max_lag=M).auto[:, 1]
    np.testing.assert_allclose(got, c / c[M], rtol=1e-12, atol=1e-15)
    assert not np.allclose(got, rc.auto[:, 1])


def test_cross_correlation_matches_numpy_and_finds_the_lag():
    rng = np.random.default_rng(1)
    T, M = 1000, 8
    u = rng.standard_normal((T, 2)) + np.array([0.0, 1.0])
    # e(t) = 0.8 u0(t - 3) + noise: a past input the model missed. Output 1 depends on
    # a future input only (as under feedback): not part of the independence verdict.
    e = 0.2 * rng.standard_normal((T, 2))
    e[3:, 0] += 0.8 * u[:-3, 0]
    e[:-2, 1] += 0.8 * (u[2:, 0] - 0.0)
    for demean in (False, True):
        rc = metrics.residual_correlations(e, u, max_lag=M, demean=demean)
        assert rc.cross.shape == (2 * M + 1, 2, 2)
        ec, uc = (e - e.mean(0), u - u.mean(0)) if demean else (e, u)
        for i in range(2):
            for j in range(2):
                ref = np_corr(ec[:, i], uc[:, j], M)
                ref = ref / np.sqrt(ec[:, i] @ ec[:, i] * (uc[:, j] @ uc[:, j]))
                np.testing.assert_allclose(rc.cross[:, i, j], ref, rtol=1e-12, atol=1e-15)
    assert rc.lags[np.argmax(rc.cross[:, 0, 0])] == 3
    assert rc.lags[np.argmax(rc.cross[:, 1, 0])] == -2
    np.testing.assert_array_equal(rc.independent, [False, True])
    assert rc.cross_outside[0, 0] == pytest.approx(1 / (M + 1))  # lag 3 only, of 0..M


def test_missing_samples_and_trajectories_are_pooled():
    rng = np.random.default_rng(2)
    N, T, M = 3, 150, 6
    e = np.stack([ar1(rng, T, 0.6) for _ in range(N)])[..., None]
    u = rng.standard_normal((N, T, 1))
    e[0, 10:14, 0] = np.nan
    e[2, -1, 0] = np.nan
    n = int(np.isfinite(e).sum())
    for demean in (False, True):
        e0 = np.nan_to_num(e - np.nanmean(e) if demean else e)[..., 0]
        u0 = u[..., 0] - u.mean() if demean else u[..., 0]
        see = sum(np_corr(e0[k], e0[k], M) for k in range(N))  # pairs within each record
        seu = sum(np_corr(e0[k], u0[k], M) for k in range(N))
        r0, ru0 = see[M] / n, np.sum(u0**2) / (N * T)
        rc = metrics.residual_correlations(e, u, max_lag=M, demean=demean)
        np.testing.assert_allclose(rc.auto[:, 0], see / see[M], rtol=1e-12)
        np.testing.assert_allclose(rc.cross[:, 0, 0], seu / n / np.sqrt(r0 * ru0), rtol=1e-12)
        np.testing.assert_allclose(rc.bound, Z99 / np.sqrt(n), rtol=1e-12)
    assert rc.n[0] == n == N * T - 5
    # Not the correlation of the records laid end to end (no pairs across two).
    glued = metrics.residual_correlations(e.reshape(-1, 1), max_lag=M)
    assert not np.allclose(glued.auto, rc.auto)


def test_records_of_different_lengths_pool_within_each_record():
    """Residuals of a fit on records of different lengths (NaN past each one's end) with
    their inputs as a list: refused with NumPy's "inhomogeneous shape" error, and a
    padded u counted its padding in u's mean and R_u(0) (lag-0 cross 0.032 with pad 0,
    0.066 with pad 3). Each record's inputs count over its own samples only."""
    rng = np.random.default_rng(4)
    M, lengths = 5, (120, 40)
    u = [3.0 + rng.standard_normal((T, 1)) for T in lengths]
    e = np.full((2, 120, 1), np.nan)
    for k, T in enumerate(lengths):
        e[k, :T, 0] = ar1(rng, T, 0.4) + 0.5 * u[k][:, 0]
    n = sum(lengths)
    e0 = [e[k, :T, 0] - np.nanmean(e) for k, T in enumerate(lengths)]
    u_mean = np.mean(np.concatenate(u))
    u0 = [r[:, 0] - u_mean for r in u]
    seu = sum(np_corr(a, b, M) for a, b in zip(e0, u0))
    r0 = sum(np.sum(a**2) for a in e0) / n
    ru0 = sum(np.sum(b**2) for b in u0) / n
    rc = metrics.residual_correlations(e, u, max_lag=M)
    np.testing.assert_allclose(rc.cross[:, 0, 0], seu / n / np.sqrt(r0 * ru0), rtol=1e-12)
    assert rc.n[0] == n
    oj.plot.resid(e, u, max_lag=M)
    with pytest.raises(ValueError, match=r"`u` must hold the N = 2 records of `e`, got 3"):
        metrics.residual_correlations(e, [*u, u[1][:10]], max_lag=M)
    # (in the other order, the first record's residuals past sample 39 were dropped)
    with pytest.raises(ValueError, match=r"`u\[0\]` has 40 samples but `e\[0\]` has .* 119"):
        metrics.residual_correlations(e, u[::-1], max_lag=M)


def test_whiteness_verdict():
    rng = np.random.default_rng(3)
    T = 2000
    white = metrics.residual_correlations(rng.standard_normal(T))
    assert white.white.tolist() == [True]
    assert white.auto_outside[0] <= 0.05
    # the fraction is over the lags 1..max_lag: lag 0 (r = 1, always outside) is not one
    lags = white.lags >= 1
    expect = np.mean(np.abs(white.auto[lags]) > white.bound, axis=0)
    np.testing.assert_array_equal(white.auto_outside, expect)
    # a white residual with no lag 1..25 outside the band is white even with tolerance 0
    strict = metrics.residual_correlations(
        np.random.default_rng(0).standard_normal(T), tolerance=0.0
    )
    assert strict.auto_outside.tolist() == [0.0] and strict.white.tolist() == [True]
    coloured = metrics.residual_correlations(ar1(rng, T, 0.5))
    assert coloured.white.tolist() == [False]
    # Independent input, white residual: independent; 0 tolerance is the strict reading.
    u = rng.standard_normal((T, 1))
    rc = metrics.residual_correlations(rng.standard_normal(T), u)
    assert rc.white.tolist() == [True] and rc.independent.tolist() == [True]


def test_one_large_peak_fails_the_verdicts():
    """The verdicts counted the lags outside the band and allowed one in 25, however far
    out: an MA(1) residual (r_e(1) = 0.4, seven times the band) read as white, a residual
    holding 0.6 u(t - 3) (r_eu(3) = 0.5) as independent of the inputs. No lag may leave the
    joint band of all the test's lags (Bonferroni), which keeps the false alarms of white
    residuals near 1 - confidence above the count's."""
    from scipy.special import ndtri

    rng = np.random.default_rng(0)
    T, M = 2000, 25
    w, u = rng.standard_normal(T + 1), rng.standard_normal(T)
    ma1 = metrics.residual_correlations(w[1:] + 0.5 * w[:-1], u, M)
    assert ma1.auto_outside[0] <= 0.05 and ma1.white.tolist() == [False]
    np.testing.assert_allclose(ma1.joint_bound, ndtri(1 - 0.005 / M) / np.sqrt(T), rtol=1e-12)
    assert "not white (4 % of the lags outside +-0.0576; r_e(1) = 0.391 beyond" in str(ma1)
    e = rng.standard_normal(T)
    e[3:] += 0.6 * u[:-3]
    missed = metrics.residual_correlations(e, u, M)
    assert missed.cross_outside[0, 0] <= 0.05 and missed.independent.tolist() == [False]
    assert "correlated with the inputs" in str(missed) and "r_eu(3) = 0.5" in str(missed)
    fig = oj.plot.resid(e, u, M)
    assert "correlated with past inputs (4 % of lags outside, 1 beyond the joint band)" in (
        fig._suptitle.get_text()
    )
    alarms = 0
    for draw in range(200):
        rc = metrics.residual_correlations(rng.standard_normal(T), rng.standard_normal(T), M)
        alarms += (not rc.white[0]) + (not rc.independent[0])
    assert alarms <= 30, alarms  # (of 400 verdicts; about 4 % each)
    # Over several inputs the joint band counts every input's lags (Bonferroni over all)
    two = metrics.residual_correlations(e, np.stack([u, w[:T]], axis=1), M)
    factor = ndtri(1 - 0.005 / (2 * (M + 1))) / ndtri(0.995)
    np.testing.assert_allclose(two.cross_joint_bound / two.cross_bound, factor, rtol=1e-12)
    # (a constant input of 3 V was said to be "zero": it is, once its mean is removed)
    with pytest.raises(ValueError, match=r"`u` is constant in input\(s\) \[0\]: zero once"):
        metrics.residual_correlations(e, np.full(T, 3.0), M)


def test_the_independence_band_allows_for_a_coloured_residual_and_input():
    """A residual and an input both coloured (AR 0.9 and 0.95, as after an output-error
    fit on a slow input) and independent by construction: with the white band z / sqrt(n)
    the verdict said "not independent" in 76 % of the draws. Ljung's band, z sqrt(P / n)
    with P = 1 + 2 sum_k r_e(k) r_u(k), keeps the false alarms near the nominal rate and
    still finds an unmodelled u(t - 3)."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(0)
    T, L = 1000, 25

    def coloured(a):
        return lfilter([1.0], [1.0, -a], rng.standard_normal(T))

    def r(a, k):  # the normalised autocorrelation at lag k, after the mean
        a = a - a.mean()
        return np.sum(a[k:] * a[: T - k]) / np.sum(a * a)

    alarms = found = 0
    for draw in range(100):
        e, u = coloured(0.9), coloured(0.95)
        rc = metrics.residual_correlations(e, u, L)
        P = 1.0 + 2.0 * sum(r(e, k) * r(u, k) for k in range(1, L + 1))
        np.testing.assert_allclose(rc.cross_bound[0, 0], rc.bound[0] * np.sqrt(max(P, 1.0)))
        alarms += not rc.independent[0]
        found += not metrics.residual_correlations(e + 0.5 * np.roll(u, 3), u, L).independent[0]
    assert alarms <= 12, alarms  # (about 4 in 100; the white band: about 76)
    assert found >= 95, found  # (99 in 100)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(max_lag=0), "max_lag"),
        (dict(max_lag=50), "max_lag"),
        (dict(max_lag=2.5), "max_lag"),
        (dict(max_lag=True), "max_lag"),
        (dict(confidence=1.0), "confidence"),
        (dict(confidence="0.99"), "confidence"),
        (dict(confidence=True), "confidence"),
        (dict(confidence=np.array([0.99])), "confidence"),
        # 3 finite samples: lags up to 5 rest on no pair (a verdict "white" from nothing)
        (dict(e=np.r_[1.0, -0.5, 0.2, np.full(47, np.nan)]), "max_lag"),
        (dict(tolerance=-0.1), "tolerance"),
        (dict(e=np.zeros((2, 3, 50, 1))), "e"),
        (dict(e=np.full(50, np.nan)), "e"),
        (dict(e=np.zeros(50)), "e"),
        (dict(e="residuals"), "e"),
        (dict(u=np.ones((49, 1))), "u"),
        (dict(u=np.r_[np.nan, np.ones(49)]), "u"),
        (dict(u=np.zeros(50)), "u"),
    ],
)
def test_bad_arguments_raise(kwargs, name):
    args = dict(e=np.random.default_rng(4).standard_normal(50), u=np.ones(50), max_lag=5)
    args.update(kwargs)
    e, u = args.pop("e"), args.pop("u")
    with pytest.raises(ValueError, match=f"`{name}`"):
        metrics.residual_correlations(e, u, **args)


def test_levels_given_as_jax_scalars_are_numbers():
    """A 0-d JAX array was refused as "not a number in (0, 1)"."""
    e = np.random.default_rng(4).standard_normal(50)
    want = metrics.residual_correlations(e, None, 5, confidence=0.95, tolerance=0.1)
    got = metrics.residual_correlations(
        e, None, 5, confidence=jnp.array(0.95), tolerance=jnp.array(0.1)
    )
    np.testing.assert_array_equal(got.bound, want.bound)
    assert got.white == want.white


# --------------------------------------------------------------------------- figures


def _step(x, u, theta):
    return theta["a"] * x + theta["b"] * u


def _observe(x, u, theta):
    del u, theta
    return x


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(5)
    model = oj.Model(_step, _observe)
    T = 200
    u = rng.standard_normal((T, 1))
    _, x = oj.simulate(model, {"a": 0.8, "b": 0.5}, np.array([1.0]), u)
    z = np.asarray(x) + 0.02 * rng.standard_normal((T, 1))
    result = oj.fit(model, {"a": 0.5, "b": 1.0}, np.array([0.0]), u, z)
    return model, u, z, result


def _legend_texts(ax):
    return [t.get_text() for t in ax.get_legend().get_texts()]


def test_compare_figure(fitted):
    model, u, z, result = fitted
    rng = np.random.default_rng(6)
    other = z + 0.1 * rng.standard_normal(z.shape)
    fig = oj.plot.compare(z, result, other, u=u, labels=["fit", "noisy"])
    assert len(fig.axes) == 1
    texts = _legend_texts(fig.axes[0])
    assert texts[0] == "measured"
    fit = 100 * (1 - np.linalg.norm(other - z) / np.linalg.norm(z - z.mean()))
    assert texts[2] == f"noisy: FIT {fit:.2f} %"
    assert texts[1].startswith("fit: FIT ") and texts[1].endswith(" %")
    title = fig.axes[0].get_title()
    assert title == "Measured and model outputs (FitResults simulated from their fitted x0)"
    title = oj.plot.compare(z, result, u=u, n=20).axes[0].get_title()
    assert title == "Measured and model outputs (x0 from the first 20 samples, FIT over the rest)"
    assert oj.plot.compare(z, other).axes[0].get_title() == "Measured and model outputs"
    # Several results may come as one list (as MATLAB's compare users may pass them).
    listed = oj.plot.compare(z, [result, result], u=u, labels=["a", "b"])
    assert _legend_texts(listed.axes[0])[1:] == [
        t.replace("fit:", s) for s in ("a:", "b:") for t in texts[1:2]
    ]

    # With the protocol's head n: a FitResult is predicted from z[:n], FIT over n:.
    n = 20
    pred = oj.predict(model, result.theta, u, z, n, x0=np.zeros(1))
    fig = oj.plot.compare(np.c_[z, 2 * z], np.c_[pred.z, 2 * pred.z], u=u, n=n)
    assert len(fig.axes) == 2
    fit = 100 * (1 - np.linalg.norm(pred.z[n:] - z[n:]) / np.linalg.norm(z[n:] - z[n:].mean()))
    for ax in fig.axes:
        texts = _legend_texts(ax)
        assert f"model: FIT {fit:.2f} %" in texts
        # (plain arrays: compare estimated no initial state from the head)
        assert f"first {n} samples (not scored)" in texts
    fig = oj.plot.compare(z, result, pred, u=u, n=n)
    texts = _legend_texts(fig.axes[0])
    assert texts[1].split(":")[1] == texts[2].split(":")[1] == f" FIT {fit:.2f} %"
    assert f"first {n} samples (x0, not scored)" in texts

    # A record brings u, n and the time axis; several models on given Axes.
    record = oj.datasets.Record(u=u[:, 0], y=z[:, 0], Ts=0.5, n=n)
    _, ax = plt.subplots()
    fig = oj.plot.compare(record, result, pred, ax=ax)
    assert fig is ax.figure and len(_legend_texts(ax)) == 4
    assert ax.get_xlabel() == "time (s)"


def test_compare_predicts_from_a_head_with_missing_samples(fitted):
    """A NaN (a lost sample) in the first n outputs is left out of x0's fit, as of the FIT
    (compare told the user to pass missing="mask", which it does not take); its FIT is
    that of `predict(..., missing="mask")`."""
    model, u, z, result = fitted
    gappy = z.copy()
    gappy[[3, 11]] = np.nan
    n = 20
    fig = oj.plot.compare(gappy, result, u=u, n=n)
    pred = result.predict(u, gappy[:n], missing="mask")
    fit = 100 * (1 - np.linalg.norm(pred.z[n:] - z[n:]) / np.linalg.norm(z[n:] - z[n:].mean()))
    assert f"model: FIT {fit:.2f} %" in _legend_texts(fig.axes[0])
    with pytest.raises(TypeError, match="`t` must be an array of sample times"):
        oj.plot.compare(z, result, u=u, t="abc")


def test_compare_and_predict_with_a_missing_first_sample_of_a_full_state_model():
    """A model that observes its whole state starts x0's fit at z[0]; with a NaN there the
    start is the fitted x0 instead (compare cannot pass `x0=`, and raised)."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])

    model = oj.Model.from_ode(rhs, 0.05)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((150, 1))
    _, z = oj.simulate(model, {"k": 4.0, "c": 0.3}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + 0.02 * rng.standard_normal(z.shape)
    res = oj.fit(model, {"k": 3.0, "c": 0.5}, z[0], u, z)
    gappy = z.copy()
    gappy[0, 1] = np.nan
    pred = res.predict(u, gappy[:10], missing="mask")
    given = res.predict(u, gappy[:10], missing="mask", x0=res.x0)
    np.testing.assert_allclose(pred.x0, given.x0, rtol=1e-10)
    fig = oj.plot.compare(gappy, res, u=u, n=10)
    fit = 100 * (
        1
        - np.linalg.norm(pred.z[10:] - z[10:], axis=0)
        / np.linalg.norm(z[10:] - z[10:].mean(0), axis=0)
    )
    assert f"model: FIT {fit[0]:.2f} %" in _legend_texts(fig.axes[0])


def test_compare_of_a_multi_record_result_without_n_says_to_pass_n():
    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] + u[0]])

    model = oj.Model.from_ode(rhs, 0.05, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u, x0 = rng.standard_normal((2, 60, 1)), rng.standard_normal((2, 2))
    _, z = oj.simulate(model, {"k": 4.0}, x0, u)
    res = oj.fit(model, {"k": 3.0}, x0, u, np.asarray(z))
    with pytest.raises(ValueError, match=r"fitted on 2 trajectories.*pass `n`") as err:
        oj.plot.compare(np.asarray(z[0]), res, u=u[0])
    fig = oj.plot.compare(np.asarray(z[0]), res, u=u[0], n=10)
    assert "FIT" in " ".join(_legend_texts(fig.axes[0]))
    # ... or the simulation of record i from its fitted x0, which the message shows
    assert "or, for record i of the fit, its simulation from the fitted initial state, " in (
        str(err.value)
    )
    assert "`result.simulate(u, x0=result.x0[i])[1]`, as the model output." in str(err.value)
    fig = oj.plot.compare(np.asarray(z[0]), res.simulate(u[0], x0=res.x0[0])[1])
    assert "FIT 100.00 %" in " ".join(_legend_texts(fig.axes[0]))
    # Both records at once: one at a time, with each record's prediction, which it shows.
    with pytest.raises(ValueError, match=r"2 records\. Compare them one at a time") as err:
        oj.plot.compare(np.asarray(z), res, u=u, n=10)
    assert "`compare(z[i], preds[i], n=n)`" in str(err.value)
    with pytest.raises(ValueError, match=r"got a list of 2 records\. Compare them one at a"):
        oj.plot.compare([np.asarray(z[0]), np.asarray(z[1])[:40]], res, u=u, n=10)
    preds = res.predict(u, np.asarray(z)[:, :10])
    fig = oj.plot.compare(np.asarray(z[1]), preds[1], n=10)
    assert "FIT 100.00 %" in " ".join(_legend_texts(fig.axes[0]))


def test_compare_of_a_windowed_fit_without_n_simulates_from_its_first_window():
    """A `window=` fit was refused without `n` ("fitted on 4 trajectories"), though
    `FitResult.simulate` starts it from its window at sample 0: compare does the same, and
    warns on another record as for a one-record fit."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])

    model = oj.Model.from_ode(rhs, 0.05, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u, u2 = rng.standard_normal((2, 200, 1))
    truth, x0 = {"k": 4.0, "c": 0.6}, np.array([0.5, -0.2])
    z = np.asarray(oj.simulate(model, truth, x0, u)[1]) + 0.01 * rng.standard_normal((200, 1))
    res = oj.fit(model, {"k": 3.0, "c": 1.0}, np.zeros(2), u, z, window=50)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = oj.plot.compare(z, res, u=u)
    zhat = np.asarray(res.simulate(u)[1])
    fit = 100 * (1 - np.linalg.norm(zhat - z) / np.linalg.norm(z - z.mean()))
    assert f"model: FIT {fit:.2f} %" in _legend_texts(fig.axes[0])
    # The time axis is the model's: k dt (it was the sample index); next to an array of
    # outputs too, and the index again where no FitResult says its dt
    for models in ((res,), (res, zhat)):
        ax = oj.plot.compare(z, *models, u=u).axes[0]
        assert ax.get_xlabel() == "time"
        np.testing.assert_allclose(ax.lines[0].get_xdata(), 0.05 * np.arange(200), rtol=1e-15)
    ax = oj.plot.compare(z, zhat).axes[0]
    assert ax.get_xlabel() == "sample" and ax.lines[0].get_xdata()[-1] == 199
    z2 = np.asarray(oj.simulate(model, truth, x0, u2)[1])
    with pytest.warns(UserWarning, match="pass `n`"):
        oj.plot.compare(z2, res, u=u2)
    # Windows none of which starts at 0: no state for the record's start; `n` is the remedy
    # inside compare (not simulate's advice of an x0 or `predict`), and n works. (Four
    # windows of 50, as above: the fit reuses its compiled program; the last two overlap.)
    with pytest.warns(UserWarning, match=r"up to 2 windows .*too large"):
        res = oj.fit(
            model, res.theta, np.zeros(2), u, z, window=oj.Windows(50, starts=[20, 70, 120, 150])
        )
    with pytest.raises(ValueError, match=r"none of which starts at sample 0.*pass `n`"):
        oj.plot.compare(z, res, u=u)
    # n=0 (the protocol's range) asks for what it already passed: the remedy says n >= 1
    with pytest.raises(ValueError, match=r"pass `n` >= 1"):
        oj.plot.compare(z, res, u=u, n=0)
    assert "FIT" in " ".join(_legend_texts(oj.plot.compare(z, res, u=u, n=10).axes[0]))


def test_transposed_records_and_windowed_residuals_get_a_hint(fitted):
    """A record given as (n, T) is named as possibly transposed (the messages spoke of
    max_lag, or blamed u); a windowed fit's residuals with the record's u say why."""
    model, u, z, result = fitted
    e = np.asarray(result.residuals)
    with pytest.raises(
        ValueError, match=r"`e` holds T = 1 samples of \d+ outputs: is it transposed"
    ):
        metrics.residual_correlations(e.reshape(1, -1), u)
    with pytest.raises(
        ValueError, match=r"`z` holds T = 1 samples of \d+ outputs: is it transposed"
    ):
        oj.plot.compare(z.reshape(1, -1), result, u=u, n=20)
    windowed = oj.fit(model, result.theta, result.x0, u[:100], z[:100], window=50)
    with pytest.raises(ValueError, match=r"residuals are per window \(2 windows"):
        oj.plot.resid(windowed, u[:100])


def test_compare_warns_on_a_record_the_result_was_not_fitted_on(fitted):
    """Without `n` a FitResult starts from its fitted x0: on its own data silently, on a
    new record with a warning that names `n` (MATLAB's compare estimates x0)."""
    model, u, z, result = fitted
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.plot.compare(z, result, u=u)  # the fitted data: no warning
        oj.plot.compare(z, result, u=u, n=20)
    rng = np.random.default_rng(7)
    u2 = rng.standard_normal((150, 1))
    _, z2 = oj.simulate(model, result.theta, np.array([2.0]), u2)
    with pytest.warns(UserWarning, match=r"pass `n` \(e.g. n=20\) to estimate x0"):
        oj.plot.compare(np.asarray(z2), result, u=u2)
    with pytest.warns(UserWarning, match="not this record"):  # same length, other data
        oj.plot.compare(z[::-1], result, u=u[::-1])
    with warnings.catch_warnings():  # (the head of the fitted record was called another)
        warnings.simplefilter("error")
        oj.plot.compare(z[:60], result, u=u[:60])
    with pytest.warns(UserWarning, match="not this record"):  # a head of other data
        oj.plot.compare(z[::-1][:60], result, u=u[::-1][:60])
    # The same in units where the outputs are of order 1e-6 (a micro-vibration in metres):
    # the linear model's result for the data times s is the result times s (its x0 and
    # residuals); a tolerance floored at 1e-5 took any other record for the fitted one.
    s = 1e-6
    small = dataclasses.replace(result, x0=result.x0 * s, residuals=result.residuals * s)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.plot.compare(z * s, small, u=u * s)
    with pytest.warns(UserWarning, match="not this record"):
        oj.plot.compare(z[::-1] * s, small, u=u[::-1] * s)


def test_compare_warns_on_a_prediction_of_another_record(fitted):
    """A list of per-record Predictions (what `FitResult.predict` returns for several
    records) passed whole with one record's `z` scores the other records' predictions
    against it: `compare` warns at the caller's line, naming the model. The Prediction of
    this record passes silently, also when the head was cast to float32 and back."""
    model, u, z, result = fitted
    rng = np.random.default_rng(8)
    u2 = rng.standard_normal(u.shape)
    _, z2 = oj.simulate(model, result.theta, np.array([0.5]), u2)
    z2 = np.asarray(z2) + 0.02 * rng.standard_normal(z.shape)
    ours, theirs = result.predict(u, z[:20]), result.predict(u2, z2[:20])
    np.testing.assert_array_equal(ours.estimate.head, z[:20])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.plot.compare(z, ours, n=20)
        oj.plot.compare(z, result.predict(u, z[:20].astype(np.float32)), n=20)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        oj.plot.compare(z, [ours, theirs], n=20)
    assert len(caught) == 1, [str(w.message) for w in caught]
    assert "`models[1]` is a Prediction made from the first 20 outputs of another record" in (
        str(caught[0].message)
    )
    assert caught[0].filename == __file__


def test_compare_refuses_what_simulate_returns(fitted):
    """`simulate` returns (x, z): passed whole, a model whose states are its outputs would
    be drawn twice, the states scored as a model; refused, naming the outputs' index."""
    model, u, z, result = fitted
    with pytest.raises(ValueError, match=r"`result.simulate\(u\)\[1\]`"):
        oj.plot.compare(z, result.simulate(u))
    fig = oj.plot.compare(z, [result.simulate(u)[1], z + 0.1])  # a list of two outputs
    assert len(_legend_texts(fig.axes[0])) == 3


def test_compare_takes_an_integral_float_head(fitted):
    """`n=20.0` (as a configuration file may write it) is the head of 20, as for
    `benchmark_scores`; 20.5 is refused."""
    model, u, z, result = fitted
    texts = _legend_texts(oj.plot.compare(z, result, u=u, n=20.0).axes[0])
    assert texts == _legend_texts(oj.plot.compare(z, result, u=u, n=20).axes[0])
    with pytest.raises(ValueError, match="`n` must be an integer"):
        oj.plot.compare(z, result, u=u, n=20.5)


def test_resid_figure(fitted):
    model, u, z, result = fitted
    rng = np.random.default_rng(7)
    u2 = np.c_[u, rng.standard_normal(u.shape)]
    fig = oj.plot.resid(result, u2, max_lag=10)
    assert len(fig.axes) == 3  # autocorrelation, and one cross-correlation per input
    rc = metrics.residual_correlations(result.residuals, u2, max_lag=10)
    title = fig._suptitle.get_text()
    assert ("e[0]: white" if rc.white[0] else "e[0]: not white") in title
    assert "99 % bounds" in title
    e = np.stack([ar1(rng, 300, 0.9), rng.standard_normal(300)], axis=1)
    fig = oj.plot.resid(e)
    assert len(fig.axes) == 2
    title = fig._suptitle.get_text()
    assert "e[0]: not white" in title and "e[1]: white" in title


def test_compare_draws_the_confidence_band_of_output_std(fitted):
    """`confidence=` shades zhat +- q std around each FitResult's output, q the normal
    quantile, std from `output_std` (from the head with `n`, else the whole record); a
    Prediction or an array gets none."""
    model, u, z, result = fitted
    n = 20
    pred = result.predict(u, z[:n])
    fig = oj.plot.compare(z, result, pred, u=u, n=n, confidence=0.9)
    ax = fig.axes[0]
    assert "model 1: 90 % band" in _legend_texts(ax)
    assert not any(t.startswith("model 2: 90") for t in _legend_texts(ax))
    (band,) = ax.collections
    vertices = band.get_paths()[0].vertices
    std = result.output_std(u, z_head=z[:n])[:, 0]
    q = 1.6448536269514722
    # (the path runs along the lower edge, then back along the upper one)
    lower, upper = vertices[1 : len(z) + 1, 1], vertices[len(z) + 2 : -1, 1][::-1]
    np.testing.assert_allclose(lower, pred.z[:, 0] - q * std, rtol=1e-12)
    np.testing.assert_allclose(upper, pred.z[:, 0] + q * std, rtol=1e-12)
    fig = oj.plot.compare(z, result, u=u, confidence=0.95)
    vertices = fig.axes[0].collections[0].get_paths()[0].vertices
    std = result.output_std(u, z_head=z)[:, 0]
    zhat = result.simulate(u)[1][:, 0]
    np.testing.assert_allclose(
        vertices[1 : len(z) + 1, 1], zhat - 1.959963984540054 * std, rtol=1e-9
    )
    for bad in (0.0, 1.0, True, "0.9"):
        with pytest.raises(ValueError, match="`confidence`"):
            oj.plot.compare(z, result, u=u, confidence=bad)


def test_plot_arguments_are_checked(fitted):
    model, u, z, result = fitted
    with pytest.raises(ValueError, match=r"`models\[0\]`"):
        oj.plot.compare(z, z[:-1])
    with pytest.raises(ValueError, match="`u`"):
        oj.plot.compare(z, result)
    with pytest.raises(ValueError, match="`labels`"):
        oj.plot.compare(z, z, labels=["a", "b"])
    with pytest.raises(ValueError, match="`n`"):
        oj.plot.compare(z, z, n=len(z))
    with pytest.raises(ValueError, match="`t`"):
        oj.plot.compare(z, z, t=np.arange(3))
    with pytest.raises(ValueError, match="`ax`"):
        oj.plot.compare(np.c_[z, z], np.c_[z, z], ax=plt.subplots()[1])
    with pytest.raises(ValueError, match="`models`"):
        oj.plot.compare(z)
    with pytest.raises(ValueError, match="`max_lag`"):
        oj.plot.resid(result, max_lag=0)
    # (no samples: said of `e`, not of the default max_lag its range leaves out)
    with pytest.raises(ValueError, match=r"`e` must have at least two samples, got shape \(0, 1\)"):
        oj.metrics.residual_correlations(np.zeros((0, 1)))


def test_missing_matplotlib_names_what_to_install(monkeypatch):
    """The message names `pip install matplotlib` (oneshot_jax is not on PyPI, so
    `pip install "oneshot_jax[plot]"` finds nothing) and the extra of a checkout."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    z = np.arange(10.0)
    with pytest.raises(
        ImportError, match=r'pip install matplotlib \(.*pip install -e "\.\[plot\]"'
    ):
        oj.plot.compare(z, z)
    with pytest.raises(ImportError, match=r"pip install matplotlib"):
        oj.plot.resid(z)


def test_import_does_not_import_matplotlib():
    code = "import sys, oneshot_jax; assert 'matplotlib' not in sys.modules, 'matplotlib'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_compare_of_a_fit_with_an_output_measured_only_in_aggregate():
    """Output 1 read only as 10-sample means (`Aggregate`, its column all NaN): compare
    drew nothing ("`mask` selects no sample of output(s) [1]", an argument never passed);
    it draws the model's output with FIT NaN, as the result's metrics have it."""

    def step(x, u, th):
        return jnp.stack([th["a"] * x[0] + th["b"] * u[0], th["c"] * x[1] + 0.5 * x[0]])

    model = oj.Model(step)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1))
    _, z = oj.simulate(model, {"a": 0.8, "b": 0.5, "c": 0.7}, np.array([0.3, -0.2]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal((60, 2))
    spans = [(k, k + 10) for k in range(0, 60, 10)]
    agg = oj.Aggregate(1, spans, [float(np.mean(z[a:b, 1])) for a, b in spans], kind="mean")
    za = z.copy()
    za[:, 1] = np.nan
    r = oj.fit(model, {"a": 0.6, "b": 0.3, "c": 0.5}, z[0], u, za, missing="mask", aggregate=agg)
    assert np.isnan(r.metrics["fit_percent"][1])
    fig = oj.plot.compare(za, r, u=u)
    legends = [a.get_legend().get_texts()[1].get_text() for a in fig.axes]
    assert "nan" in legends[1] and "nan" not in legends[0]
    plt.close(fig)
    # resid: the output without residual samples is left out, and the title says so.
    fig = oj.plot.resid(r, u)
    assert len(fig.axes) == 2  # e[0]: its autocorrelation and its cross-correlation with u
    assert "e[1]: no residual samples" in fig._suptitle.get_text()
    plt.close(fig)


def test_predict_names_a_head_with_the_wrong_number_of_outputs():
    """z_head's columns are the state's guess for a model that observes it: a wrong count
    surfaced as a wrong state size deep in the model."""

    def step(x, u, th):
        return jnp.stack([th["a"] * x[0] + u[0], 0.7 * x[1] + 0.5 * x[0]])

    model = oj.Model(step)
    u = np.random.default_rng(0).standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 0.8}, np.array([0.3, -0.2]), u)
    r = oj.fit(model, {"a": 0.6}, np.asarray(z[0]), u, np.asarray(z))
    for head in (np.asarray(z[:5, :1]), np.hstack([z[:5], z[:5, :1]])):
        with pytest.raises(ValueError, match=r"`z_head` must have shape \(5, 2\) \(its first"):
            r.predict(u, head)
    with pytest.raises(ValueError, match=r"`x0` was not given: its guess is the first row of `z`"):
        oj.predict(model, r.theta, u, np.asarray(z[:, :1]), 5)


def test_compare_names_bad_labels():
    z = np.ones((20, 1))
    with pytest.raises(TypeError, match=r"`labels` must be a string or a sequence of 1"):
        oj.plot.compare(z, z, labels=5)
    for empty in ((), ([],)):  # (an empty list was read as an output of shape (0, 1))
        with pytest.raises(ValueError, match="`models` is empty"):
            oj.plot.compare(z, *empty)
    # A list of outputs is a list of models, as a list of results is (it was read as one
    # array of two records).
    wave = np.sin(np.arange(20.0))[:, None]
    texts = _legend_texts(oj.plot.compare(wave, [wave, 2 * wave], labels=["a", "b"]).axes[0])
    assert [t.split(":")[0] for t in texts[-2:]] == ["a", "b"] and "FIT 100" in texts[-2]
    plt.close("all")


def test_compare_refuses_a_time_axis_that_does_not_increase():
    z = np.ones((20, 1))
    for t in (np.arange(20.0)[::-1], np.r_[np.nan, np.arange(19.0)]):
        with pytest.raises(ValueError, match="`t` must hold finite, increasing sample times"):
            oj.plot.compare(z, z, t=t)


def test_compare_names_its_outputs_and_time_axis():
    """MATLAB's OutputName/OutputUnit and TimeUnit: `outputs=` labels each output's axis,
    `time_label=` the time axis; wrong counts and types are named."""
    z = np.c_[np.sin(np.arange(30.0)), np.cos(np.arange(30.0))]
    fig = oj.plot.compare(z, z, t=np.arange(30) * 2.0, outputs=["q (mm)", "v (mm/s)"])
    assert [a.get_ylabel() for a in fig.axes] == ["q (mm)", "v (mm/s)"]
    assert fig.axes[-1].get_xlabel() == "time"
    fig = oj.plot.compare(z[:, :1], z[:, :1], outputs="q (mm)", time_label="time (ms)")
    assert fig.axes[0].get_ylabel() == "q (mm)" and fig.axes[0].get_xlabel() == "time (ms)"
    with pytest.raises(ValueError, match=r"`outputs` must hold 2 names"):
        oj.plot.compare(z, z, outputs=["q"])
    with pytest.raises(TypeError, match=r"`outputs` must be a string or a sequence of 2"):
        oj.plot.compare(z, z, outputs=[1, 2])
    with pytest.raises(TypeError, match=r"`time_label` must be a string"):
        oj.plot.compare(z, z, time_label=3)
    plt.close("all")


def test_compare_of_transposed_arrays_warns():
    """Model outputs given as arrays need no `u`, and z shaped (2, 60) drew 60 axes of two
    samples each without a word."""
    t = np.linspace(0.0, 1.0, 60)
    z = np.stack([np.sin(t), np.cos(t)], axis=1)
    with pytest.warns(UserWarning, match=r"`z` holds T = 2 samples of 8 outputs, .*: is it trans"):
        fig = oj.plot.compare(z.T[:, :8], 0.9 * z.T[:, :8])
    assert len(fig.axes) == 8
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.plot.compare(z, 0.9 * z)


def test_compare_refuses_a_record_at_another_sample_interval():
    """A record sampled at Ts with a FitResult of a `Model.from_ode` model of another dt:
    the simulation would run on the wrong time scale (FIT -77 % on noise-free data, no
    warning); MATLAB's compare simulates a continuous-time model at the data's Ts."""
    rhs = lambda x, u, th: -th["a"] * x + u  # noqa: E731
    model = oj.Model.from_ode(rhs, dt=0.05)
    u = np.random.default_rng(0).standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 1.0}, np.array([0.5]), u)
    result = oj.fit(model, {"a": 0.5}, np.array([0.5]), u, np.asarray(z))
    with pytest.raises(ValueError, match=r"sampled at Ts = 0.1.*dt = 0.05"):
        oj.plot.compare(oj.datasets.Record(u=u, y=np.asarray(z), Ts=0.1, n=5), result)
    oj.plot.compare(oj.datasets.Record(u=u, y=np.asarray(z), Ts=0.05, n=5), result)


def test_a_diverged_fit_is_plotted_readably_and_its_residuals_say_so(fitted):
    """A fit that failed: `compare`'s legend shows a huge FIT in exponent notation (its
    140 digits pushed the legend off the figure), and `resid`'s title says the fit did
    not succeed (the whiteness verdicts of its residuals mean nothing)."""
    model, u, z, result = fitted
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bad = oj.fit(
            model, {"a": 3.0, "b": 1.0}, np.array([0.0]), u, z, solver=oj.GaussNewton(max_steps=1)
        )
    assert not bad.success
    fit = float(np.asarray(bad.metrics["fit_percent"])[0])
    assert abs(fit) > 1e4
    texts = _legend_texts(oj.plot.compare(z, bad, u=u).axes[0])
    assert texts[1] == f"model: FIT {fit:.3g} %", texts
    title = oj.plot.resid(bad)._suptitle.get_text()
    assert f"the fit did not succeed (status {bad.status})" in title
    assert "did not succeed" not in oj.plot.resid(result)._suptitle.get_text()


def test_warnings_of_compare_and_predict_point_at_the_callers_line(fitted):
    """The warnings of `compare` and `FitResult.predict` name the user's line (not a frame
    of this library or of equinox), so each call warns once under Python's default
    filter."""
    model, u, z, result = fitted
    rng = np.random.default_rng(7)
    u2 = rng.standard_normal((150, 1))
    _, z2 = oj.simulate(model, result.theta, np.array([2.0]), u2)

    def step(x, u, th):  # position and velocity; the position measured
        return jnp.array([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - th["k"] * x[0])])

    two = oj.Model(step, lambda x, u, th: x[:1])
    _, zp = oj.simulate(two, {"k": 2.0}, np.array([1.0, 0.0]), u)
    fit2 = oj.fit(two, {"k": 1.0}, np.zeros(2), u, np.asarray(zp))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        oj.plot.compare(np.asarray(z2), result, u=u2)  # another record, without n
        fit2.predict(u, np.asarray(zp)[:1])  # one output: the velocity is not determined
        oj.plot.compare(np.asarray(zp), fit2, u=u, n=1)
    assert len(caught) == 3, [str(w.message)[:60] for w in caught]
    assert all(w.filename == __file__ for w in caught), [w.filename for w in caught]


def test_plot_and_resid_refuse_complex_and_ragged_arrays(fitted):
    model, u, z, result = fitted
    with pytest.raises(ValueError, match=r"`models\[0\]` must hold real numbers"):
        oj.plot.compare(z, z + 1j)
    with pytest.raises(ValueError, match=r"`e` must be a numeric array"):
        oj.plot.resid([np.zeros(3), np.zeros(4)])


def test_predictions_and_compared_outputs_that_are_not_finite_are_warned_of():
    """A tank model, sqrt of its level, fitted and then run on a record where the tank
    drains: the model leaves its domain (NaN from sample 89 on). `predict` returned the NaN
    samples without a word and `compare` showed "FIT nan %": each warns, once, at the
    caller's line, naming the first sample."""

    def step(x, u, th):
        return jnp.stack([x[0] + 0.1 * (th["b"] * u[0] ** 2 - th["a"] * jnp.sqrt(x[0]))])

    model = oj.Model(step)
    theta = {"a": 0.5, "b": 0.5}
    u = np.r_[np.ones((50, 1)), np.zeros((150, 1))]
    x, zhat = oj.simulate(model, theta, np.array([1.0]), u)
    nan = np.isnan(np.asarray(zhat))[:, 0]
    assert nan[89:].all() and not nan[:89].any()
    z = np.nan_to_num(np.asarray(zhat))  # the real tank is empty
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        p = oj.predict(model, theta, u, z, 20, x0=np.array([0.9]))
        oj.plot.compare(z, np.asarray(zhat))
        oj.plot.compare(z, p, n=20)  # (predict warned of it)
    messages = [str(w.message) for w in caught]
    assert len(caught) == 2, messages
    first = int(np.argmax(np.isnan(p.z[:, 0])))
    assert np.isnan(p.z[first:]).all() and 80 < first < 100
    assert f"prediction is not finite from sample {first} on ({200 - first} of 200" in messages[0]
    assert (
        "`models[0]` is not finite at 111 measured samples, the first at sample 89" in (messages[1])
    )
    assert all(w.filename == __file__ for w in caught), [w.filename for w in caught]
