"""Goodness-of-fit metrics for measured outputs `z` and model outputs `zhat`.

`rmse`, `nrmse`, `fit_percent`, `r2` and `aic` take arrays of shape (..., n_z) (time and
trajectory axes in front) and return one value per output channel (shape (n_z,)), except
`aic`, which is a scalar. The definitions are those of MATLAB's System Identification
Toolbox (`compare`, `fpe`/`aic`). They are JAX functions (jittable).

`benchmark_scores` scores a simulation under the community's benchmark protocol (the
first n samples are left out) with the definitions of `nonlinear_benchmarks.error_metrics`;
it runs on the host in NumPy float64 and returns a printable, JSON-friendly result.
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["rmse", "nrmse", "fit_percent", "r2", "aic", "benchmark_scores", "BenchmarkScores"]


def _flat(z, zhat, mask=None):
    """(n, n_z) views of z, zhat and the weights of the samples (1, or the mask)."""
    z, zhat = jnp.asarray(z), jnp.asarray(zhat)
    if z.shape != zhat.shape:
        raise ValueError(
            f"`z` and `zhat` must have the same shape, got {z.shape} and {zhat.shape}."
        )
    if mask is not None and jnp.shape(mask) != z.shape:
        raise ValueError(f"`mask` must have the shape of `z` {z.shape}, got {jnp.shape(mask)}.")
    if z.ndim == 1:
        z, zhat = z[:, None], zhat[:, None]
        mask = None if mask is None else jnp.asarray(mask)[:, None]
    n_z = z.shape[-1]
    w = jnp.ones(z.shape, z.dtype) if mask is None else jnp.asarray(mask, z.dtype)
    w = w.reshape(-1, n_z)
    # Missing samples may hold anything (NaN): they must not reach the sums.
    z = jnp.where(w > 0, z.reshape(-1, n_z), 0.0)
    zhat = jnp.where(w > 0, zhat.reshape(-1, n_z), 0.0)
    return z, zhat, w


def _mean(a, w):
    return jnp.sum(w * a, axis=0) / jnp.sum(w, axis=0)


def rmse(z, zhat, mask=None):
    """Root-mean-square error per output: sqrt(mean_k (zhat_k - z_k)^2), over the samples
    where `mask` (shaped like z, optional) is true."""
    z, zhat, w = _flat(z, zhat, mask)
    return jnp.sqrt(_mean((zhat - z) ** 2, w))


def nrmse(z, zhat, mask=None):
    """RMSE divided by the standard deviation of the measured output, per output."""
    z, zhat, w = _flat(z, zhat, mask)
    std = jnp.sqrt(_mean((z - _mean(z, w)) ** 2, w))
    return jnp.sqrt(_mean((zhat - z) ** 2, w)) / std


def fit_percent(z, zhat, mask=None):
    """FIT% = 100 (1 - ||zhat - z|| / ||z - mean(z)||) per output (MATLAB's `compare`)."""
    z, zhat, w = _flat(z, zhat, mask)
    num = jnp.sqrt(jnp.sum(w * (zhat - z) ** 2, axis=0))
    den = jnp.sqrt(jnp.sum(w * (z - _mean(z, w)) ** 2, axis=0))
    return 100.0 * (1.0 - num / den)


def r2(z, zhat, mask=None):
    """Coefficient of determination R^2 = 1 - SSE / SST per output."""
    z, zhat, w = _flat(z, zhat, mask)
    sse = jnp.sum(w * (zhat - z) ** 2, axis=0)
    sst = jnp.sum(w * (z - _mean(z, w)) ** 2, axis=0)
    return 1.0 - sse / sst


def aic(z, zhat, n_params, mask=None):
    """Akaike's information criterion, AIC = n log det(E^T E / n) + 2 n_params.

    E is the (n, n_z) matrix of errors over the n samples (those where every output is
    measured, when a `mask` is given) (MATLAB's raw AIC without the constant
    n n_z (log 2 pi + 1)). Lower is better; only differences between models on the same
    data mean anything.
    """
    z, zhat, w = _flat(z, zhat, mask)
    full = jnp.all(w > 0, axis=1).astype(z.dtype)
    e = (zhat - z) * full[:, None]
    n = jnp.sum(full)
    _, logdet = jnp.linalg.slogdet(e.T @ e / n)
    return n * logdet + 2.0 * n_params


# --------------------------------------------------------------------------- protocol


class BenchmarkScores(NamedTuple):
    """Scores of a model output under the benchmark protocol, one value per output channel
    (NumPy float64 arrays of shape (n_z,)).

    **Fields:**

    - `rmse`: sqrt(mean_k (yhat_k - y_k)^2), in the units of y.
    - `nrmse`: `rmse` / std(y), the standard deviation of the scored y (ddof 0).
    - `r2`: 1 - `nrmse`^2 = 1 - MSE / var(y).
    - `fit_percent`: 100 (1 - `nrmse`), the FIT index in percent.
    - `n`: the number of initial samples left out.
    - `n_scored`: the number of samples scored (T - n).

    `str()` gives a small table; `as_dict()` gives plain Python floats and lists for JSON.
    """

    rmse: np.ndarray
    nrmse: np.ndarray
    r2: np.ndarray
    fit_percent: np.ndarray
    n: int
    n_scored: int

    def as_dict(self) -> dict:
        """The scores as a JSON-friendly dict of lists of floats (and the two counts)."""
        out = {k: [float(v) for v in getattr(self, k)] for k in self._fields[:4]}
        out.update(n=int(self.n), n_scored=int(self.n_scored))
        return out

    def __str__(self):
        rows = [f"{'output':>6}  {'RMSE':>12}  {'NRMSE':>9}  {'R2':>9}  {'FIT %':>8}"]
        for i in range(len(self.rmse)):
            rows.append(
                f"{i:>6}  {self.rmse[i]:>12.6g}  {self.nrmse[i]:>9.5f}  {self.r2[i]:>9.5f}  "
                f"{self.fit_percent[i]:>8.3f}"
            )
        last = self.n + self.n_scored - 1
        rows.append(f"(scored: samples {self.n} to {last}, {self.n_scored} in all)")
        return "\n".join(rows)


def _outputs(value, name):
    """The output array of `value`: the `y` of a record-like object, else the value."""
    if hasattr(value, "y") and hasattr(value, "u"):
        value = value.y
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"`{name}` must be a numeric array of shape (T,) or (T, n_z), or a Record, got "
            f"{type(value).__name__} ({err})."
        ) from err
    if a.ndim not in (1, 2):
        raise ValueError(
            f"`{name}` must have shape (T,) or (T, n_z) (time first), got shape {a.shape}."
        )
    return a


def benchmark_scores(z, zhat, n=None) -> BenchmarkScores:
    """RMSE, NRMSE, R² and FIT of a model output over samples n:, per output channel, as
    the community's benchmark protocol scores them.

    The protocol (Champneys et al. 2024; `nonlinear_benchmarks`): a model may use the test
    input and the first n measured outputs (to set its initial state), and is scored on
    the rest. The definitions are those of `nonlinear_benchmarks.error_metrics`, on
    y = z[n:] and yhat = zhat[n:]: RMSE = sqrt(mean (yhat - y)^2); NRMSE = RMSE / std(y);
    R² = 1 - NRMSE²; FIT = 100 (1 - NRMSE). (FIT equals `fit_percent` and R² equals `r2`
    of this module on the same samples.)

    **Arguments:**

    - `z`: measured outputs, shape (T,) or (T, n_z), or a `oneshot_jax.datasets.Record`
        or `nonlinear_benchmarks.Input_output_data` (its `y` is used).
    - `zhat`: model outputs, same shape (or a record-like object, its `y`).
    - `n`: number of initial samples left out, 0 <= n <= T - 2. Default: the `n` (or
        `state_initialization_window_length`) of `z` when it is a record.

    **Returns:**

    A `BenchmarkScores` of NumPy float64 arrays of shape (n_z,) (n_z = 1 for 1-D input).

    **Raises:**

    `ValueError` if the shapes differ or are not (T,) / (T, n_z), `n` is out of range or
    missing, a value is NaN or inf (for `zhat`, the first such sample is named), or a
    channel of z[n:] is constant (NRMSE undefined); `TypeError` if `n` is not an integer.

    **Reference:**

    M. D. Champneys, G. I. Beintema, R. Tóth, M. Schoukens, T. J. Rogers, "Baseline results
    for selected nonlinear system identification benchmarks", arXiv:2405.10779, 2024.
    """
    if n is None:
        n = getattr(z, "n", None)
        if n is None and hasattr(z, "state_initialization_window_length"):
            n = z.state_initialization_window_length or 0
        if n is None:
            raise ValueError(
                "`n` (the number of initial samples a model may use, left out of the score) "
                "is required unless `z` is a record that carries it."
            )
    if isinstance(n, bool) or not isinstance(n, numbers.Integral):
        raise TypeError(f"`n` must be an integer, got {type(n).__name__}.")
    n = int(n)
    y, yhat = _outputs(z, "z"), _outputs(zhat, "zhat")
    if y.shape != yhat.shape:
        raise ValueError(
            f"`z` and `zhat` must have the same shape, got {y.shape} and {yhat.shape}."
        )
    y, yhat = (a if a.ndim == 2 else a[:, None] for a in (y, yhat))
    T = y.shape[0]
    if not 0 <= n <= T - 2:
        raise ValueError(
            f"`n` must satisfy 0 <= n <= T - 2 = {T - 2} (at least two samples scored), got {n}."
        )
    y, yhat = y[n:], yhat[n:]
    if not np.all(np.isfinite(y)):
        raise ValueError("`z` contains NaN or inf values in the scored samples.")
    bad = ~np.all(np.isfinite(yhat), axis=1)
    if bad.any():
        raise ValueError(
            f"`zhat` contains NaN or inf from sample {n + int(np.argmax(bad))} on "
            f"({int(bad.sum())} scored samples): the model output diverged."
        )
    std = np.std(y, axis=0)
    if np.any(std <= 0):
        raise ValueError(
            f"`z[n:]` is constant in output channel(s) {np.flatnonzero(std <= 0).tolist()}: "
            f"NRMSE, R² and FIT are undefined."
        )
    rmse_ = np.sqrt(np.mean((yhat - y) ** 2, axis=0))
    nrmse_ = rmse_ / std
    return BenchmarkScores(
        rmse=rmse_,
        nrmse=nrmse_,
        r2=1.0 - nrmse_**2,
        fit_percent=100.0 * (1.0 - nrmse_),
        n=n,
        n_scored=T - n,
    )
