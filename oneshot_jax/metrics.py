"""Goodness-of-fit metrics for measured outputs `z` and model outputs `zhat`.

Each takes arrays of shape (..., n_z) (time and trajectory axes in front) and returns one
value per output channel (shape (n_z,)), except `aic`, which is a scalar. The definitions
are those of MATLAB's System Identification Toolbox (`compare`, `fpe`/`aic`).
"""

import jax.numpy as jnp

__all__ = ["rmse", "nrmse", "fit_percent", "r2", "aic"]


def _flat(z, zhat):
    z, zhat = jnp.asarray(z), jnp.asarray(zhat)
    if z.shape != zhat.shape:
        raise ValueError(
            f"`z` and `zhat` must have the same shape, got {z.shape} and {zhat.shape}."
        )
    if z.ndim == 1:
        z, zhat = z[:, None], zhat[:, None]
    return z.reshape(-1, z.shape[-1]), zhat.reshape(-1, z.shape[-1])


def rmse(z, zhat):
    """Root-mean-square error per output: sqrt(mean_k (zhat_k - z_k)^2)."""
    z, zhat = _flat(z, zhat)
    return jnp.sqrt(jnp.mean((zhat - z) ** 2, axis=0))


def nrmse(z, zhat):
    """RMSE divided by the standard deviation of the measured output, per output."""
    z, zhat = _flat(z, zhat)
    return rmse(z, zhat) / jnp.std(z, axis=0)


def fit_percent(z, zhat):
    """FIT% = 100 (1 - ||zhat - z|| / ||z - mean(z)||) per output (MATLAB's `compare`)."""
    z, zhat = _flat(z, zhat)
    num = jnp.linalg.norm(zhat - z, axis=0)
    den = jnp.linalg.norm(z - jnp.mean(z, axis=0), axis=0)
    return 100.0 * (1.0 - num / den)


def r2(z, zhat):
    """Coefficient of determination R^2 = 1 - SSE / SST per output."""
    z, zhat = _flat(z, zhat)
    sse = jnp.sum((zhat - z) ** 2, axis=0)
    sst = jnp.sum((z - jnp.mean(z, axis=0)) ** 2, axis=0)
    return 1.0 - sse / sst


def aic(z, zhat, n_params):
    """Akaike's information criterion, AIC = n log det(E^T E / n) + 2 n_params.

    E is the (n, n_z) matrix of errors over all n samples (MATLAB's raw AIC without the
    constant n n_z (log 2 pi + 1)). Lower is better; only differences between models on
    the same data mean anything.
    """
    z, zhat = _flat(z, zhat)
    e = zhat - z
    n = e.shape[0]
    _, logdet = jnp.linalg.slogdet(e.T @ e / n)
    return n * logdet + 2.0 * n_params
