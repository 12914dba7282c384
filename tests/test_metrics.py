"""`oneshot_jax.metrics` against NumPy formulas (MATLAB System Identification definitions)."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from oneshot_jax import metrics


def np_metrics(z, zhat, n_params):
    """The definitions written out in NumPy on (n, n_z) arrays."""
    e = zhat - z
    n = e.shape[0]
    dev = z - z.mean(axis=0)
    return {
        "rmse": np.sqrt((e**2).mean(axis=0)),
        "nrmse": np.sqrt((e**2).mean(axis=0)) / z.std(axis=0),
        "fit_percent": 100 * (1 - np.linalg.norm(e, axis=0) / np.linalg.norm(dev, axis=0)),
        "r2": 1 - (e**2).sum(axis=0) / (dev**2).sum(axis=0),
        "aic": n * np.log(np.linalg.det(e.T @ e / n)) + 2 * n_params,
        "fpe": np.linalg.det(e.T @ e / n) * (1 + n_params / n) / (1 - n_params / n),
        "aicc": n * np.log(np.linalg.det(e.T @ e / n))
        + 2 * n_params
        + 2 * n_params * (n_params + 1) / (n - n_params - 1),
        "bic": n * np.log(np.linalg.det(e.T @ e / n)) + n_params * np.log(n),
    }


@pytest.mark.parametrize(
    "shape", [(50,), (50, 1), (40, 3), (4, 25, 2)], ids=["T", "T-1", "T-3", "N-T-2"]
)
def test_metrics_match_numpy(shape):
    rng = np.random.default_rng(sum(shape))
    z = rng.standard_normal(shape) * np.linspace(1, 3, shape[-1]) + 2.0
    zhat = z + 0.3 * rng.standard_normal(shape)
    n_z = 1 if len(shape) == 1 else shape[-1]
    ref = np_metrics(z.reshape(-1, n_z), zhat.reshape(-1, n_z), n_params=5)
    for name in ("rmse", "nrmse", "fit_percent", "r2"):
        got = np.asarray(getattr(metrics, name)(z, zhat))
        assert got.shape == (n_z,), (name, got.shape)
        np.testing.assert_allclose(got, ref[name], rtol=1e-12, err_msg=name)
    aic = metrics.aic(z, zhat, 5)
    assert np.shape(aic) == ()
    assert float(aic) == pytest.approx(ref["aic"], rel=1e-12)
    fpe = metrics.fpe(z, zhat, 5)
    assert np.shape(fpe) == () and float(fpe) == pytest.approx(ref["fpe"], rel=1e-12)
    for name in ("aicc", "bic"):
        got = getattr(metrics, name)(z, zhat, 5)
        assert np.shape(got) == () and float(got) == pytest.approx(ref[name], rel=1e-12), name
    few = z.reshape(-1, n_z)[:5], zhat.reshape(-1, n_z)[:5]
    assert float(metrics.fpe(*few, 5)) == np.inf  # as many parameters as samples
    assert float(metrics.aicc(*few, 4)) == np.inf  # (n - d - 1 = 0)


def test_fpe_of_a_singular_error_covariance():
    """E^T E / n singular (the same error in every sample: rank 1): inf where d >= n, as
    documented, and never below 0 (it was NaN or -inf, and -1e-19 with d < n, as the
    determinant's round-off fell)."""
    signs = set()
    for seed in range(8):
        z = np.random.default_rng(seed).standard_normal((3, 2))
        zhat = z + 0.01
        signs.add(np.sign(np.linalg.det((zhat - z).T @ (zhat - z) / 3)))
        assert float(metrics.fpe(z, zhat, 10)) == np.inf, seed
        assert 0.0 <= float(metrics.fpe(z, zhat, 1)) < 1e-15, seed
    assert -1.0 in signs  # (a case where round-off makes the determinant negative)
    exact = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 7.0]])
    zhat = exact.copy()
    zhat[:, 1] += [0.1, -0.2, 0.05]  # the first output fitted exactly: det 0
    assert float(metrics.fpe(exact, zhat, 10)) == np.inf
    assert float(metrics.fpe(exact, zhat, 1)) == 0.0
    # Two fully measured samples of three outputs: E^T E / n singular, no FPE (as no AIC;
    # it was the determinant's round-off, about 0, times the factor).
    rng = np.random.default_rng(0)
    z, zhat = rng.standard_normal((6, 3)), rng.standard_normal((6, 3))
    mask = np.ones((6, 3))
    mask[2:, 2] = 0.0
    assert np.isnan(float(metrics.aic(z, zhat, 1, mask)))
    assert np.isnan(float(metrics.fpe(z, zhat, 1, mask)))
    assert float(metrics.fpe(z, zhat, 2, mask)) == np.inf  # (d >= n)


def test_masked_metrics_match_numpy_on_the_measured_samples():
    """With a mask (missing samples, as a masked fit's metrics have them), each channel's
    metrics are those of its measured samples alone (its own mean, not the unmasked one)
    and AIC takes the rows where every channel is measured."""
    rng = np.random.default_rng(7)
    z = rng.standard_normal((60, 2)) * [1.0, 3.0] + 2.0
    zhat = z + 0.3 * rng.standard_normal((60, 2))
    mask = rng.random((60, 2)) > 0.25  # different gaps in each channel
    z = np.where(mask, z, np.nan)
    for c in range(2):
        m = mask[:, c]
        ref = np_metrics(z[m, c : c + 1], zhat[m, c : c + 1], n_params=3)
        for name in ("rmse", "nrmse", "fit_percent", "r2"):
            got = np.asarray(getattr(metrics, name)(z, zhat, mask))[c]
            np.testing.assert_allclose(got, ref[name][0], rtol=1e-12, err_msg=(name, c))
    rows = mask.all(axis=1)
    assert 0 < rows.sum() < 60 and rows.sum() < mask.any(axis=1).sum()
    ref = np_metrics(z[rows], zhat[rows], n_params=3)
    assert float(metrics.aic(z, zhat, 3, mask)) == pytest.approx(ref["aic"], rel=1e-12)
    assert float(metrics.fpe(z, zhat, 3, mask)) == pytest.approx(ref["fpe"], rel=1e-12)
    assert float(metrics.aicc(z, zhat, 3, mask)) == pytest.approx(ref["aicc"], rel=1e-12)
    assert float(metrics.bic(z, zhat, 3, mask)) == pytest.approx(ref["bic"], rel=1e-12)


def test_missing_samples_without_a_mask_warn_how_to_score_the_measured_ones():
    """A gappy record scored without `mask`: the outputs with a gap score NaN (silently,
    before); a warning names the mask, and with it the scores are finite."""
    rng = np.random.default_rng(3)
    z = rng.standard_normal((40, 2))
    zhat = z + 0.1 * rng.standard_normal((40, 2))
    z[5, 1] = np.nan
    for name in ("rmse", "nrmse", "fit_percent", "r2"):
        with pytest.warns(UserWarning, match=r"mask=~np\.isnan\(z\)"):
            got = np.asarray(getattr(metrics, name)(z, zhat))
        assert np.isfinite(got[0]) and np.isnan(got[1])
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert np.all(np.isfinite(getattr(metrics, name)(z, zhat, ~np.isnan(z))))


def test_metrics_of_a_perfect_and_of_a_mean_model():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((30, 2))
    np.testing.assert_array_equal(metrics.rmse(z, z), [0.0, 0.0])
    np.testing.assert_array_equal(metrics.fit_percent(z, z), [100.0, 100.0])
    np.testing.assert_array_equal(metrics.r2(z, z), [1.0, 1.0])
    mean_model = np.broadcast_to(z.mean(axis=0), z.shape)
    np.testing.assert_allclose(metrics.fit_percent(z, mean_model), [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(metrics.r2(z, mean_model), [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(metrics.nrmse(z, mean_model), [1.0, 1.0], rtol=1e-12)


def test_aic_penalises_parameters_and_rewards_smaller_errors():
    rng = np.random.default_rng(1)
    z = rng.standard_normal((100, 2))
    e = rng.standard_normal((100, 2))
    assert float(metrics.aic(z, z + e, 7) - metrics.aic(z, z + e, 3)) == pytest.approx(8.0)
    # Halving every error lowers log det(E^T E / n) by 2 n_z log 2.
    diff = float(metrics.aic(z, z + e, 3) - metrics.aic(z, z + 0.5 * e, 3))
    assert diff == pytest.approx(100 * 2 * 2 * np.log(2), rel=1e-12)


def test_metrics_are_jittable():
    rng = np.random.default_rng(2)
    z, zhat = rng.standard_normal((20, 2)), rng.standard_normal((20, 2))
    np.testing.assert_allclose(
        jax.jit(metrics.fit_percent)(z, zhat), metrics.fit_percent(z, zhat), rtol=1e-14
    )
    np.testing.assert_allclose(
        jax.jit(metrics.aic, static_argnums=2)(z, zhat, 4), metrics.aic(z, zhat, 4), rtol=1e-14
    )


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2"])
def test_shape_mismatch_raises(name):
    with pytest.raises(ValueError, match="same shape"):
        getattr(metrics, name)(jnp.zeros((10, 2)), jnp.zeros((10, 3)))
    with pytest.raises(ValueError, match="same shape"):
        metrics.aic(jnp.zeros((10, 2)), jnp.zeros((9, 2)), 1)


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2", "aic", "fpe"])
def test_one_output_as_1d_or_column(name):
    """A one-output record (T,) against a model's (T, 1) outputs, either way round (with a
    mask of z's shape), is that single channel, as for `benchmark_scores`: the scores of
    the two columns, never a broadcast (T, T) or an error."""
    z, zhat = _pair((60,), 4)
    mask = np.arange(60) % 7 != 3
    args = (3,) if name in ("aic", "fpe") else ()
    f = getattr(metrics, name)
    ref = f(z[:, None], zhat[:, None], *args, mask=mask[:, None])
    for a, b, m in ((z, zhat[:, None], mask), (z[:, None], zhat, mask[:, None])):
        got = f(a, b, *args, mask=m)
        assert np.shape(got) == np.shape(ref)
        np.testing.assert_array_equal(got, ref)


# ----------------------------------------------------------------------- benchmark protocol


def _pair(shape, seed):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal(shape) * 2.0 + 1.0
    return z, z + 0.3 * rng.standard_normal(shape)


@pytest.mark.parametrize("shape, n", [((200,), 0), ((200,), 20), ((150, 3), 50)])
def test_benchmark_scores_match_formulas(shape, n):
    """Written out in NumPy on samples n: (RMSE / std with ddof 0, R^2 = 1 - NRMSE^2,
    FIT = 100 (1 - NRMSE)); FIT and R^2 agree with this module's fit_percent and r2."""
    z, zhat = _pair(shape, n)
    s = metrics.benchmark_scores(z, zhat, n)
    y, yh = z[n:].reshape(len(z) - n, -1), zhat[n:].reshape(len(z) - n, -1)
    rmse = np.sqrt(((yh - y) ** 2).mean(axis=0))
    np.testing.assert_allclose(s.rmse, rmse, rtol=1e-13)
    np.testing.assert_allclose(s.nrmse, rmse / y.std(axis=0), rtol=1e-13)
    np.testing.assert_allclose(s.r2, 1 - ((yh - y) ** 2).mean(0) / y.var(0), rtol=1e-12)
    np.testing.assert_allclose(s.fit_percent, metrics.fit_percent(y, yh), rtol=1e-12)
    np.testing.assert_allclose(s.r2, metrics.r2(y, yh), rtol=1e-12)
    assert s.rmse.shape == (y.shape[1],) and s.rmse.dtype == np.float64
    assert (s.n, s.n_scored) == (n, len(z) - n)
    # The first n samples do not count: spoiling them changes nothing.
    zhat_bad_head = zhat.copy()
    zhat_bad_head[:n] += 100.0
    np.testing.assert_array_equal(metrics.benchmark_scores(z, zhat_bad_head, n).rmse, s.rmse)


@pytest.mark.parametrize("shape, n", [((300,), 0), ((300,), 50), ((120, 2), 5)])
def test_benchmark_scores_match_nonlinear_benchmarks(shape, n):
    """Against the package's own error metrics (`R_squared` ignores `n_init` for plain
    arrays, so it gets the scored samples directly; with Input_output_data it uses the
    record's window)."""
    em = pytest.importorskip("nonlinear_benchmarks.error_metrics")
    from nonlinear_benchmarks import Input_output_data

    z, zhat = _pair(shape, 7 + n)
    s = metrics.benchmark_scores(z, zhat, n)
    flat = np.atleast_1d
    np.testing.assert_allclose(s.rmse, flat(em.RMSE(z, zhat, n_init=n)), rtol=1e-13)
    np.testing.assert_allclose(s.nrmse, flat(em.NRMSE(z, zhat, n_init=n)), rtol=1e-13)
    np.testing.assert_allclose(s.fit_percent, flat(em.fit_index(z, zhat, n_init=n)), rtol=1e-13)
    np.testing.assert_allclose(s.r2, flat(em.R_squared(z[n:], zhat[n:])), rtol=1e-13)
    u = np.zeros(shape[0])
    true = Input_output_data(u=u, y=z, sampling_time=1.0, state_initialization_window_length=n)
    model = Input_output_data(u=u, y=zhat, sampling_time=1.0)
    np.testing.assert_allclose(s.r2, flat(em.R_squared(true, model)), rtol=1e-13)
    # A record carries its n: the package's object and ours give the same scores.
    s2 = metrics.benchmark_scores(true, model)
    np.testing.assert_array_equal(s2.rmse, s.rmse)
    assert s2.n == n


def test_benchmark_scores_of_a_record_and_its_output():
    from oneshot_jax.datasets import Record

    z, zhat = _pair((100,), 3)
    rec = Record(u=np.zeros(100), y=z, Ts=0.1, n=10, name="test")
    s = rec.score(zhat)
    assert s.n == 10
    np.testing.assert_array_equal(s.rmse, metrics.benchmark_scores(z, zhat, 10).rmse)
    np.testing.assert_array_equal(metrics.benchmark_scores(rec, zhat).nrmse, s.nrmse)


def test_benchmark_scores_one_output_as_1d_or_column():
    # A one-output record's y is (T,); a model's simulated outputs are (T, 1). Both are the
    # same single channel, scored as such (never broadcast to (T, T)).
    from oneshot_jax.datasets import Record

    z, zhat = _pair((100,), 3)
    rec = Record(u=np.zeros(100), y=z, Ts=0.1, n=10, name="test")
    ref = metrics.benchmark_scores(z[:, None], zhat[:, None], 10)
    for a, b in ((rec, zhat[:, None]), (z[:, None], zhat), (z, zhat[:, None])):
        s = metrics.benchmark_scores(a, b, 10)
        assert s.rmse.shape == (1,)
        np.testing.assert_array_equal(s.rmse, ref.rmse)
        np.testing.assert_array_equal(s.fit_percent, ref.fit_percent)


def test_benchmark_scores_print_and_json():
    import json

    z, zhat = _pair((80, 2), 4)
    s = metrics.benchmark_scores(z, zhat, 5)
    d = json.loads(json.dumps(s.as_dict()))
    assert set(d) == {"rmse", "nrmse", "r2", "fit_percent", "n", "n_scored"}
    assert d["rmse"] == pytest.approx(list(s.rmse), rel=1e-15) and d["n_scored"] == 75
    text = str(s)
    assert "RMSE" in text and "FIT" in text and len(text.splitlines()) == 4
    assert f"{s.rmse[1]:.6g}" in text


def test_benchmark_scores_perfect_and_mean_models():
    z, _ = _pair((60, 2), 5)
    s = metrics.benchmark_scores(z, z, 10)
    np.testing.assert_array_equal(s.rmse, [0.0, 0.0])
    np.testing.assert_array_equal(s.fit_percent, [100.0, 100.0])
    mean_model = np.broadcast_to(z[10:].mean(axis=0), z.shape)
    s = metrics.benchmark_scores(z, mean_model, 10)
    np.testing.assert_allclose(s.nrmse, [1.0, 1.0], rtol=1e-12)
    np.testing.assert_allclose(s.r2, [0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize(
    "z_shape, zhat_shape, n, error, pattern",
    [
        ((50, 2), (50, 3), 5, ValueError, "same shape"),
        ((50, 2), (2, 50), 5, ValueError, "same shape .* Is `zhat` transposed"),
        ((50,), (1, 50), 5, ValueError, "same shape .* Is `zhat` transposed"),
        ((4, 50, 2), (4, 50, 2), 5, ValueError, r"\(T,\) or \(T, n_z\)"),
        ((50,), (50,), 49, ValueError, r"0 <= n <= T - 2 = 48"),
        ((50,), (50,), -1, ValueError, r"0 <= n"),
        ((50,), (50,), 2.5, TypeError, "`n` must be an integer"),
        ((50,), (50,), True, TypeError, "`n` must be an integer"),
        ((50,), (50,), None, ValueError, "`n` .* is required"),
        ((0,), (0,), 0, ValueError, r"at least two samples to score, got T = 0"),
        ((1,), (1,), 0, ValueError, r"at least two samples to score, got T = 1"),
    ],
)
def test_benchmark_scores_bad_input(z_shape, zhat_shape, n, error, pattern):
    rng = np.random.default_rng(0)
    with pytest.raises(error, match=pattern):
        metrics.benchmark_scores(rng.standard_normal(z_shape), rng.standard_normal(zhat_shape), n)


def test_an_output_without_spread_has_no_fit_percent_r2_or_nrmse():
    """A constant output (a stuck sensor): ||z - mean(z)|| is 0 but for the mean's
    round-off, which made FIT% -3.3e17 % (and R^2 -1.1e31), -inf or NaN by chance. Each
    is undefined there: NaN. An output whose spread is small but real keeps its scores."""
    z = np.column_stack([np.full(100, 0.7382), np.linspace(0.0, 1.0, 100)])
    zhat = z + 0.1
    for name in ("fit_percent", "r2", "nrmse"):
        score = getattr(metrics, name)(z, zhat)
        assert np.isnan(score[0]) and np.isfinite(score[1]), name
    small = np.column_stack([0.7382 + 1e-9 * np.sin(np.arange(100.0))])
    assert np.isfinite(metrics.fit_percent(small, small + 1e-10)).all()


def test_benchmark_scores_refuses_diverged_output_and_constant_data():
    z, zhat = _pair((50, 2), 6)
    zhat[30:, 1] = np.nan
    with pytest.raises(
        ValueError,
        match=r"NaN or inf in 20 scored samples, the first at sample 30: the model output diverged",
    ):
        metrics.benchmark_scores(z, zhat, 5)
    # One bad sample is not called a divergence.
    zhat[30:, 1] = 0.0
    zhat[12, 1] = np.nan
    with pytest.raises(
        ValueError, match=r"NaN or inf in 1 scored samples, the first at sample 12\.$"
    ):
        metrics.benchmark_scores(z, zhat, 5)
    # NaN only in the head (not scored) is fine.
    z, zhat = _pair((50,), 6)
    zhat[:5] = np.inf
    assert np.isfinite(metrics.benchmark_scores(z, zhat, 5).rmse).all()
    z[10] = np.nan
    with pytest.raises(ValueError, match="`z` contains NaN"):
        metrics.benchmark_scores(z, np.zeros(50), 5)
    z = np.ones((50, 2))
    z[:, 0] = np.arange(50)
    with pytest.raises(ValueError, match=r"constant in output channel\(s\) \[1\]"):
        metrics.benchmark_scores(z, z + 0.1, 5)


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2"])
def test_metrics_refuse_what_is_no_record_of_numbers(name):
    fn = getattr(metrics, name)
    z = np.ones((10, 2))
    with pytest.raises(TypeError, match=r"`z` must be a numeric array"):
        fn("abc", "abd")
    with pytest.raises(TypeError, match=r"`z` must be a numeric array"):
        fn(None, z)
    with pytest.raises(TypeError, match=r"`zhat` must be a numeric array"):
        fn(z, [["a", "b"]] * 10)
    # (complex JAX arrays scored a complex "RMSE"; complex NumPy ones were refused)
    with pytest.raises(TypeError, match=r"`zhat` must be a numeric array .*complex128"):
        fn(z, jnp.asarray(z) + 1j)
    # a masked array: JAX's own error before, which named no argument
    with pytest.raises(TypeError, match=r"`zhat` is a NumPy masked array.*`mask=`"):
        fn(z, np.ma.masked_array(z, mask=z > 0))
    with pytest.raises(ValueError, match=r"`z` holds no samples"):
        fn(np.zeros((0, 1)), np.zeros((0, 1)))
    with pytest.raises(ValueError, match=r"`mask` selects no sample of output\(s\) \[1\]"):
        fn(z, z + 1, np.array([[True, False]] * 10))
    with pytest.raises(ValueError, match=r"`mask` must be true where"):
        fn(z, z + 1, -np.ones_like(z))
    # a (T,) record passed as a row, (1, T): each "output" had one sample (NaN scores)
    row = np.arange(30.0)[None]
    with pytest.raises(ValueError, match=r"T = 1 sample of 30 outputs .* is it transposed\?"):
        fn(row, row + 0.1)
    # a record of two outputs transposed, (2, T): scored in silence as T outputs
    wide = np.random.default_rng(1).standard_normal((2, 30))
    with pytest.warns(UserWarning, match=r"T = 2 samples of 30 outputs .* is it transposed\?"):
        fn(wide, wide + 0.1)


def test_a_masked_array_with_nothing_masked_scores_as_its_data():
    # (as `fit` reads one: refused with "pass its data" before, though no entry was masked)
    rng = np.random.default_rng(0)
    z, zhat = rng.normal(size=(20, 2)), rng.normal(size=(20, 2))
    nothing = np.zeros((20, 2), bool)
    for fn in (metrics.rmse, metrics.fit_percent, metrics.r2):
        np.testing.assert_array_equal(
            fn(np.ma.masked_array(z, mask=nothing), np.ma.masked_array(zhat, mask=nothing)),
            fn(z, zhat),
        )


def test_protocol_scores_and_residual_analysis_read_a_masked_array_by_its_mask():
    # (both read the data under the mask: a masked 1e6 made the protocol's RMSE 7e4)
    rng = np.random.default_rng(0)
    z = rng.standard_normal((50, 1))
    spiked = np.ma.masked_array(z.copy(), mask=np.zeros((50, 1), bool))
    spiked[3] = np.ma.masked
    spiked.data[3] = 1e6
    with pytest.raises(ValueError, match=r"`z` is a NumPy masked array with 1 masked entries"):
        metrics.benchmark_scores(spiked, z + 0.1, 5)
    assert metrics.benchmark_scores(np.ma.masked_array(z), z + 0.1, 5).rmse == pytest.approx(0.1)
    e = np.where(np.arange(50)[:, None] == 3, np.nan, z)  # the masked sample as missing
    got, ref = metrics.residual_correlations(spiked), metrics.residual_correlations(e)
    np.testing.assert_array_equal(got.auto, ref.auto)
    assert got.n[0] == 49


def test_aic_and_fpe_refuse_a_mask_without_a_fully_measured_sample():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((40, 2))
    zhat = z + 0.1 * rng.standard_normal((40, 2))
    mask = np.zeros((40, 2), bool)
    mask[::2, 0] = mask[1::2, 1] = True  # outputs measured at alternate samples
    for fn in (metrics.aic, metrics.aicc, metrics.bic, metrics.fpe):
        with pytest.raises(ValueError, match="no sample where every output is measured"):
            fn(z, zhat, 3, mask)
    assert "fpe" in metrics.__all__


def test_aic_is_nan_where_fewer_samples_measure_every_output_than_there_are_outputs():
    """Two outputs at alternate samples, with one sample where both are measured: E^T E / n
    has rank 1, its log det is -inf, and slogdet's finite round-off was reported as the
    AIC. It is NaN now (as `fpe` is inf); with two such samples it is a number."""
    rng = np.random.default_rng(0)
    z = rng.standard_normal((40, 2))
    zhat = z + 0.1 * rng.standard_normal((40, 2))
    mask = np.zeros((40, 2), bool)
    mask[::2, 0] = mask[1::2, 1] = True
    mask[4] = True
    assert np.isnan(float(metrics.aic(z, zhat, 2, mask)))
    assert np.isnan(float(metrics.bic(z, zhat, 2, mask)))
    assert np.isnan(float(metrics.aicc(z, zhat, 2, mask)))  # (inf before, beside NaN)
    assert np.isinf(float(metrics.fpe(z, zhat, 2, mask)))
    mask[6] = True
    e = (zhat - z)[mask.all(axis=1)]
    expected = 2 * np.linalg.slogdet(e.T @ e / 2)[1] + 2 * 2
    assert float(metrics.aic(z, zhat, 2, mask)) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2"])
def test_mask_selects_and_does_not_weight(name):
    rng = np.random.default_rng(0)
    z = rng.standard_normal((30, 1))
    zhat = z + 0.1 * rng.standard_normal((30, 1))
    mask = np.ones((30, 1))
    mask[:5] = 3.0
    with pytest.raises(ValueError, match="does not weight"):
        getattr(metrics, name)(z, zhat, mask)


def test_an_output_without_residuals_of_its_own_is_named_with_the_ones_to_pass():
    """An output read only as aggregates (NaN residuals throughout) was refused without
    saying which outputs can be analysed."""
    e = np.random.default_rng(0).standard_normal((50, 3))
    e[:, 1] = np.nan
    with pytest.raises(ValueError, match=r"output\(s\) \[1\] .* pass e\[\.\.\., \[0, 2\]\]"):
        metrics.residual_correlations(e)
    with pytest.raises(ValueError, match=r"output\(s\) \[0\]\.$"):
        metrics.residual_correlations(np.full((50, 1), np.nan))


def test_a_confidence_within_eps_of_one_gives_an_infinite_band():
    """The normal quantile at 1 (a confidence of 1 - 2^-53 rounds 0.5 + 0.5 c to 1) is
    inf, a band nothing leaves: the standard library's quantile refused it with its own
    error."""
    e = np.random.default_rng(0).standard_normal((100, 1))
    out = metrics.residual_correlations(e, confidence=np.nextafter(1.0, 0.0))
    assert np.isinf(out.bound) and bool(np.all(out.white))


class _Frame:
    """An array-like of another library (a pandas DataFrame, say): NumPy reads it through
    `__array__`, JAX does not take it as an argument."""

    def __init__(self, a):
        self._a = np.asarray(a)

    def __array__(self, dtype=None, copy=None):
        return self._a if dtype is None else self._a.astype(dtype)


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2", "aic", "fpe"])
def test_metrics_read_array_likes_and_score_half_precision_in_float32(name):
    """An array-like (a DataFrame) scored as its values (JAX's own error before, naming no
    argument); float16 outputs of a few hundred scored in float32 (their sum of squares
    overflowed float16: an RMSE of inf, a FIT of NaN)."""
    rng = np.random.default_rng(0)
    z = 300.0 + 100.0 * rng.standard_normal((200, 1))
    zhat = z + 30.0 * rng.standard_normal((200, 1))
    mask = rng.random((200, 1)) < 0.9
    fn = getattr(metrics, name)
    kw = {"n_params": 2} if name in ("aic", "fpe") else {}
    want = np.asarray(fn(z, zhat, mask=mask, **kw))
    got = np.asarray(fn(_Frame(z), _Frame(zhat), mask=_Frame(mask), **kw))
    np.testing.assert_array_equal(got, want)
    z16, zhat16 = z.astype(np.float16), zhat.astype(np.float16)
    want16 = np.asarray(fn(z16.astype(np.float64), zhat16.astype(np.float64), **kw))
    for a, b in ((z16, zhat16), (jnp.asarray(z16), jnp.asarray(zhat16))):
        got16 = np.asarray(fn(a, b, **kw))
        assert got16.dtype == np.float32
        np.testing.assert_allclose(got16, want16, rtol=1e-5)
