"""`fit(weight="noise")`: the output weight estimated with theta (MATLAB's `OutputWeight`
"noise"), so that the standard errors hold for outputs of unequal noise."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

SIGMA = np.array([0.01, 0.3])  # the position is measured 30 times more precisely


def _rhs(x, u, p):
    return jnp.stack([x[1], -p["k"] * x[0] - p["c"] * x[1] + u[0]])


MODEL = oj.Model.from_ode(_rhs, 0.05, observe=lambda x, u, p: x)
THETA0 = {"k": 3.0, "c": 0.3}


def _data(seed=0, T=400):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((T, 1))
    _, z = oj.simulate(MODEL, {"k": 4.0, "c": 0.5}, np.array([1.0, 0.0]), u)
    return u, np.asarray(z) + SIGMA * rng.standard_normal((T, 2))


def test_the_noise_weight_gives_the_fit_and_standard_errors_of_the_true_weight():
    """With Q = I the standard errors pool the two noise levels (fit warns, and k's is
    about 10 times that of the true weight). `weight="noise"` reaches the fit of the true
    weight 1 / sigma^2 (the same estimate to a small part of its standard error, the
    same standard errors to 5 %) without the warning; its Q is the inverse covariance of
    its own residuals (the fixed point), up to its scale."""
    u, z = _data()
    with pytest.warns(UserWarning, match="differ in variance"):
        plain = oj.fit(MODEL, THETA0, np.zeros(2), u, z)
    true = oj.fit(MODEL, THETA0, np.zeros(2), u, z, weight=1 / SIGMA**2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no warning of unequal noise, or any other)
        r = oj.fit(MODEL, THETA0, np.zeros(2), u, z, weight="noise")
    assert r.success and true.success
    assert 2 <= r.stop_info["noise_weight_rounds"] <= 10
    # Its result keeps the warnings of its own fit, not those of the rounds before it
    # (the first, with Q = I, warned of the unequal variances that the last one settles).
    assert r.warnings == () and "differ in variance" not in str(r)
    assert "the output weight estimated from the residuals" in str(r)
    assert float(plain.std["k"]) > 5 * float(true.std["k"])
    for name in ("k", "c"):
        std = float(true.std[name])
        assert abs(float(r.theta[name]) - float(true.theta[name])) < 0.05 * std, name
        assert float(r.std[name]) == pytest.approx(std, rel=0.05), name
    e = np.asarray(r.residuals)
    Q = np.linalg.inv(e.T @ e / len(e))
    Q /= np.sqrt(np.linalg.det(Q))
    np.testing.assert_allclose(r.weight, Q, rtol=1e-2, atol=1e-2 * np.abs(Q).max())
    np.testing.assert_allclose(
        np.diag(r.weight) / np.diag(r.weight)[1], (SIGMA[1] / SIGMA) ** 2, rtol=0.2
    )


def test_a_noise_weighted_multistart_keeps_its_first_fits_starts():
    """The starts run in the first fit (Q = I) only; the result keeps them, and says so."""
    u, z = _data()
    starts = {"k": np.array([3.0, 5.0]), "c": np.array([0.3, 0.6])}
    r = oj.fit(MODEL, starts, np.zeros(2), u, z, weight="noise", multistart=True)
    assert r.success and len(r.starts.stop_reason) == 2 and r.best in (0, 1)
    assert "the starts those of the first (Q = I)" in str(r)
    assert float(r.theta["k"]) == pytest.approx(4.0, abs=0.02)


def test_the_noise_weight_of_outputs_with_missing_samples_is_diagonal():
    """Where some samples miss an output, the weight is each output's inverse mean squared
    residual over its own samples (no covariance of the pairs)."""
    u, z = _data(seed=1)
    z[::3, 0] = np.nan
    r = oj.fit(MODEL, THETA0, np.zeros(2), u, z, weight="noise", missing="mask")
    assert r.success and np.shape(r.weight) == (2,)
    e = np.asarray(r.residuals)
    q = 1 / np.nanmean(e**2, axis=0)
    np.testing.assert_allclose(r.weight, q / np.sqrt(q.prod()), rtol=1e-2)


def test_records_of_different_lengths_get_the_full_noise_weight():
    """Records of 200 and 199 samples with correlated output noise: the samples past the
    shorter record's end measure nothing and tell nothing about the noise. Q was the
    diagonal (as where a sample misses one output), its standard errors about twice
    those of the full Q; it is now the inverse covariance of the residuals of the
    measured samples (the fixed point), as for records of one length, and so is a record
    with a sample that measures no output."""
    rng = np.random.default_rng(0)
    mix = np.array([[0.01, 0.0], [0.15, 0.1]])  # correlated noise of the two outputs
    us, zs = [], []
    for T in (200, 199):
        u = rng.standard_normal((T, 1))
        _, z = oj.simulate(MODEL, {"k": 4.0, "c": 0.5}, np.array([0.5, 0.0]), u)
        us.append(u)
        zs.append(np.asarray(z) + rng.standard_normal((T, 2)) @ mix.T)
    x0 = np.stack([z[0] for z in zs])
    r = oj.fit(MODEL, THETA0, x0, us, zs, weight="noise")
    e = np.concatenate([np.asarray(a) for a in r.residuals])
    e = e[np.isfinite(e).all(axis=1)]
    assert len(e) == 399
    Q = np.linalg.inv(e.T @ e / len(e))
    Q /= np.sqrt(np.linalg.det(Q))
    assert np.shape(r.weight) == (2, 2)
    np.testing.assert_allclose(r.weight, Q, rtol=1e-2, atol=1e-2 * np.abs(Q).max())
    zs[1][50] = np.nan  # a sample of no output: left out as well
    r = oj.fit(MODEL, THETA0, x0, us, zs, weight="noise", missing="mask")
    assert np.shape(r.weight) == (2, 2)


def test_a_weight_that_is_no_array_nor_noise_is_named():
    u, z = _data()
    with pytest.raises(ValueError, match=r"`weight` must be None, an array .* or \"noise\""):
        oj.fit(MODEL, THETA0, np.zeros(2), u, z, weight="inverse")
    for weight in (True, np.array([True, False])):  # (was taken as Q = 1 and [1, 0])
        with pytest.raises(TypeError, match="`weight` must hold numbers"):
            oj.fit(MODEL, THETA0, np.zeros(2), u, z, weight=weight)


def _tanks_step(x, u, p):
    return jnp.stack([p["a"] * x[0] + p["b"] * u[0], p["c"] * x[1] + (1 - p["c"]) * x[0]])


TANKS = oj.Model(_tanks_step, lambda x, u, p: x)
TANKS_TRUE = {"a": 0.9, "b": 0.5, "c": 0.8}
SIGMA_POINT, SIGMA_READING = 0.1, 0.005  # the readings 20 times more precise


def _aggregated_data(seed=0, T=400, records=1):
    """Output 0 measured only as means over 10 samples (noise SIGMA_READING), output 1 at
    every sample (noise SIGMA_POINT), for `records` records from different states."""
    rng = np.random.default_rng(seed)
    us, zs, aggs = [], [], []
    for i in range(records):
        u = rng.standard_normal((T, 1))
        _, z = oj.simulate(TANKS, TANKS_TRUE, np.array([1.0 + i, -1.0]), u)
        z = np.asarray(z)
        spans = [(k, k + 10) for k in range(0, T, 10)]
        values = np.array([z[a:b, 0].mean() for a, b in spans])
        values = values + SIGMA_READING * rng.standard_normal(len(spans))
        z = z + SIGMA_POINT * rng.standard_normal(z.shape)
        z[:, 0] = np.nan
        us.append(u)
        zs.append(z)
        aggs.append(oj.Aggregate(0, spans, values, kind="mean"))
    return us, zs, aggs


def test_readings_weighted_unlike_the_point_samples_warn_that_the_errors_pool_one_level():
    """Aggregated readings of one output and point samples of another, with weights that
    do not invert their noise (the readings' 400 times smaller variance ignored): the
    standard errors pool one level, and fit says so, naming the readings; with weights
    that invert each noise level, it does not."""
    (u,), (z,), (agg,) = _aggregated_data()
    x0 = np.array([1.0, -1.0])
    with pytest.warns(UserWarning, match="the readings of output 0 the smallest"):
        oj.fit(TANKS, {"a": 0.8, "b": 0.4, "c": 0.7}, x0, u, z, missing="mask", aggregate=agg)
    agg.weight = np.full(len(agg.values), 1 / SIGMA_READING**2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.fit(
            TANKS,
            {"a": 0.8, "b": 0.4, "c": 0.7},
            x0,
            u,
            z,
            missing="mask",
            aggregate=agg,
            weight=np.array([1.0, 1 / SIGMA_POINT**2]),
        )


@pytest.mark.parametrize("records", [1, 2])
def test_the_noise_weight_weighs_aggregated_readings_too(records):
    """An output measured only in aggregate: `weight="noise"` estimates the readings'
    noise level with the point samples' (one factor per `Aggregate` for its weights), and
    reaches about the fit of the true weights (1 / each noise variance): the same estimate
    to a tenth of its standard error, the same standard errors to 20 % (the readings'
    level is estimated from 40 readings each: their weight over the point samples' came
    out 0.74 to 1.7 times the true ratio over 3 seeds). The fit with the default weights
    (1 for both) has standard errors several times larger."""
    us, zs, aggs = _aggregated_data(records=records)
    if records == 1:
        u, z, agg, x0 = us[0], zs[0], aggs[0], np.array([1.0, -1.0])
    else:
        u, z, agg, x0 = np.stack(us), np.stack(zs), aggs, np.array([[1.0, -1.0], [2.0, -1.0]])
    theta0 = {"a": 0.8, "b": 0.4, "c": 0.7}
    kw = dict(missing="mask")
    with pytest.warns(UserWarning, match="differ in variance"):
        plain = oj.fit(TANKS, theta0, x0, u, z, aggregate=agg, **kw)
    weighted = [
        oj.Aggregate(a.channel, a.intervals, a.values, weight=1 / SIGMA_READING**2) for a in aggs
    ]
    true = oj.fit(
        TANKS,
        theta0,
        x0,
        u,
        z,
        aggregate=weighted[0] if records == 1 else weighted,
        weight=np.array([1.0, 1 / SIGMA_POINT**2]),
        **kw,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = oj.fit(TANKS, theta0, x0, u, z, aggregate=agg, weight="noise", **kw)
    assert r.success and true.success
    assert 2 <= r.stop_info["noise_weight_rounds"] <= 10
    # Its result keeps the warnings of its own fit, not those of the rounds before it
    # (the first, with Q = I, warned of the unequal variances that the last one settles).
    assert r.warnings == () and "differ in variance" not in str(r)
    factors = r.stop_info["reading_weight_factors"]
    assert len(factors) == records
    # the printout names them next to Q (it showed Q alone, the readings' 1 in it)
    shown = ", ".join(f"{f:.4g}" for f in factors)
    assert f"the readings' weights times [{shown}] (one per Aggregate)" in str(r)
    # The readings' weight over the point samples' is the inverse ratio of their variances.
    for f in factors:
        assert 0.5 < f / float(r.weight[1]) / (SIGMA_POINT / SIGMA_READING) ** 2 < 2
    for name in TANKS_TRUE:
        std = float(true.std[name])
        assert abs(float(r.theta[name]) - float(true.theta[name])) < 0.1 * std, name
        assert float(r.std[name]) == pytest.approx(std, rel=0.2), name
    assert float(plain.std["a"]) > 3 * float(true.std["a"])


# one model of one output for the two tests below, whose noise-weighted fits (of records of
# the same length) share a compiled program
ONE_OUTPUT = oj.Model(lambda x, u, th: th["a"] * x + u)


def test_one_output_takes_one_fit():
    """One output's Q, normalised to det Q = 1, is 1 whatever its residuals: the first fit
    (Q = I) is the answer, and a second, identical, fit was run anyway."""
    model = ONE_OUTPUT
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    _, z = oj.simulate(model, {"a": 0.8}, np.array([1.0]), u)
    z = np.asarray(z) + 0.1 * rng.standard_normal((200, 1))
    noise = oj.fit(model, {"a": 0.5}, np.array([1.0]), u, z, weight="noise")
    plain = oj.fit(model, {"a": 0.5}, np.array([1.0]), u, z)
    assert noise.stop_info["noise_weight_rounds"] == 1
    assert noise.num_steps == plain.num_steps and noise.theta["a"] == plain.theta["a"]
    assert "estimated from the residuals of one fit; Q = I)" in str(noise)


def test_a_weight_the_residuals_cannot_give_is_not_called_estimated():
    """Residuals exactly zero give no noise level: the fit warns and keeps Q = I, and the
    printout said the weight had been "estimated from the residuals"."""
    model = ONE_OUTPUT
    u = np.full((200, 1), 0.5)  # x stays at 1, where it starts
    _, z = oj.simulate(model, {"a": 0.5}, np.array([1.0]), u)
    with pytest.warns(UserWarning, match="all zero, so there is no noise level"):
        r = oj.fit(model, {"a": 0.5}, np.array([1.0]), u, np.asarray(z), weight="noise")
    assert r.stop_info["noise_weight_estimated"] is False
    assert '(weight="noise": no output weight estimated, see the warning; Q = I)' in str(r)
    assert "estimated from the residuals" not in str(r)


def _three_outputs(seed=0, T=200):
    """x[k+1] = a x[k] + b u[k] seen as z = (x, 2 x, x + u): output 0 only in aggregate
    (10 means of 20 samples), output 1 at 60 % of the samples (noise 0.3), output 2 at
    every sample (noise 0.01)."""
    model = oj.Model(
        lambda x, u, th: th["a"] * x + th["b"] * u,
        lambda x, u, th: jnp.concatenate([x, 2.0 * x, x + u]),
    )
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((T, 1))
    _, y = oj.simulate(model, {"a": 0.9, "b": 0.5}, np.array([1.0]), u)
    y = np.asarray(y)
    z = np.full((T, 3), np.nan)
    keep = rng.random(T) < 0.6
    z[keep, 1] = y[keep, 1] + 0.3 * rng.standard_normal(keep.sum())
    z[:, 2] = y[:, 2] + 0.01 * rng.standard_normal(T)
    spans = [(k, k + 20) for k in range(0, T, 20)]
    means = y[:, 0].reshape(10, 20).mean(axis=1) + 0.05 * rng.standard_normal(10)
    return model, u, z, spans, means


@pytest.mark.parametrize("empty", ["weight 0", "all missing"])
def test_an_aggregate_without_readings_leaves_the_other_outputs_weighed(empty):
    """An `Aggregate` whose readings all have weight 0 (or are all missing) has nothing to
    weigh: `weight="noise"` gave up on every output ("the residuals of aggregate 0 are
    all zero or missing"), kept Q = I, and warned that the outputs differ in variance by
    a factor of 100 or so. It now keeps that Aggregate's factor at 1 and estimates Q for
    the outputs: their ratio is the inverse ratio of their noise variances (900)."""
    model, u, z, spans, means = _three_outputs()
    agg = (
        oj.Aggregate(0, spans, means, weight=0.0)
        if empty == "weight 0"
        else oj.Aggregate(0, spans, np.full(10, np.nan))
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = oj.fit(
            model, {"a": 0.8, "b": 0.4}, np.array([0.5]), u, z, aggregate=agg,
            missing="mask", weight="noise",
        )  # fmt: skip
    assert r.success and r.weight is not None
    assert r.stop_info["reading_weight_factors"] == [1.0]
    ratio = float(r.weight[2]) / float(r.weight[1])
    assert 900 / 1.5 < ratio < 900 * 1.5


def test_a_weight_that_runs_away_is_no_success():
    """Two readings of means that the model fits exactly (with x0 free): each round
    weighs them more (a factor of 1e13 after 10 fits) and the point samples less, until
    their residuals are all zero. The fit reported `converged`, a success, with the
    point samples weighted by 6e-14; it now ends `noise_weight_unsettled`, naming the
    last fit's own stop."""
    model = oj.Model(
        lambda x, u, th: (
            jnp.array([[th["a"], 0.1], [-0.1, 0.9]]) @ x + jnp.array([0.0, th["b"]]) * u[0]
        ),
        lambda x, u, th: x[:1],
    )
    rng = np.random.default_rng(0)
    x0, T = np.array([0.5, -0.3]), 40
    u = np.sin(0.3 * np.arange(T))[:, None] + 0.3 * rng.standard_normal((T, 1))
    _, z = oj.simulate(model, {"a": 0.8, "b": 0.5}, x0, u)
    z = np.asarray(z) + 0.01 * rng.standard_normal((T, 1))
    agg = oj.Aggregate(0, [(0, 10), (10, 20)], [z[:10].mean(), z[10:20].mean()])
    with pytest.warns(UserWarning, match="residuals of aggregate 0 are all zero"):
        r = oj.fit(model, {"a": 0.7, "b": 0.4}, x0, u, z, weight="noise", aggregate=agg)
    assert r.status == "noise_weight_unsettled" and not r.success
    assert r.stop_info["solver_stop"] in ("converged", "statistically_converged", "zero_residual")
    assert r.stop_info["reading_weight_factors"][0] > 1e6
    assert "the output weight did not settle in" in r.message


def test_a_weight_matrix_is_judged_by_the_residuals_it_whitens():
    """Three outputs of equal noise variance, two of them correlated 0.995: the exact
    weight inv(S) whitens the residuals (equal variances), yet fit warned that they differ
    by a factor 99 (each output's mean(e_j^2) Q_jj is 1 / (1 - R_j^2) there, not 1). The
    identity, which does not whiten them, is still warned of."""

    def step(x, u, th):
        return th["a"] * x + th["b"] * u[0]

    model = oj.Model(step)
    rng = np.random.default_rng(0)
    T = 300
    u = rng.standard_normal((T, 1))
    truth = {"a": np.array([0.9, 0.8, 0.7]), "b": np.array([1.0, 0.5, 0.2])}
    _, x = oj.simulate(model, truth, np.array([1.0, -1.0, 0.5]), u)
    S = 0.01 * np.array([[1.0, 0.995, 0.0], [0.995, 1.0, 0.0], [0.0, 0.0, 1.0]])
    z = np.asarray(x) + rng.multivariate_normal(np.zeros(3), S, T)
    theta0 = {"a": np.full(3, 0.5), "b": np.full(3, 0.1)}
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        r = oj.fit(model, theta0, z[0], u, z, weight=np.linalg.inv(S))
    assert r.success
    assert not [w for w in rec if "differ in variance" in str(w.message)]
    with pytest.warns(UserWarning, match="differ in variance"):
        oj.fit(model, theta0, z[0], u, z, weight=np.eye(3))


def test_an_output_fitted_to_its_round_off_is_no_noise_level():
    """An output measured without noise: each round weighed it more (Q diagonal 3e-15
    against 3e14 after 7 fits) until its residuals sat at round-off, where the weight
    "settled"; the fit ended `stalled`, blaming the problem's scaling, where the docs
    promise `noise_weight_unsettled`. Residuals at the round-off of their data now count
    as zero: no noise level to weigh by."""
    rng = np.random.default_rng(41)
    u = rng.standard_normal((150, 1))
    _, z = oj.simulate(MODEL, {"k": 4.0, "c": 0.5}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + np.array([0.05, 0.0]) * rng.standard_normal((150, 2))
    with pytest.warns(UserWarning, match="residuals of output 1 are all zero"):
        r = oj.fit(MODEL, THETA0, z[0], u, z, weight="noise")
    assert r.status == "noise_weight_unsettled" and not r.success
    assert r.stop_info["noise_weight_rounds"] < 10
