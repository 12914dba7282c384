"""`oneshot_jax.metrics` against NumPy formulas (MATLAB System Identification definitions)."""

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
    }


@pytest.mark.parametrize("shape", [(50,), (50, 1), (40, 3), (4, 25, 2)],
                         ids=["T", "T-1", "T-3", "N-T-2"])
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
    np.testing.assert_allclose(jax.jit(metrics.fit_percent)(z, zhat),
                               metrics.fit_percent(z, zhat), rtol=1e-14)
    np.testing.assert_allclose(jax.jit(metrics.aic, static_argnums=2)(z, zhat, 4),
                               metrics.aic(z, zhat, 4), rtol=1e-14)


@pytest.mark.parametrize("name", ["rmse", "nrmse", "fit_percent", "r2"])
def test_shape_mismatch_raises(name):
    with pytest.raises(ValueError, match="same shape"):
        getattr(metrics, name)(jnp.zeros((10, 2)), jnp.zeros((10, 3)))
    with pytest.raises(ValueError, match="same shape"):
        metrics.aic(jnp.zeros((10, 2)), jnp.zeros((9, 2)), 1)
