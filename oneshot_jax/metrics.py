"""Goodness-of-fit metrics for measured outputs `z` and model outputs `zhat`.

`rmse`, `nrmse`, `fit_percent`, `r2`, `aic`, `aicc`, `bic` and `fpe` take arrays of
shape (..., n_z) (time and trajectory axes in front) and return one value per output
channel (shape (n_z,)), except the criteria `aic`, `aicc`, `bic` and `fpe`, which are
scalars. The definitions are those of MATLAB's System Identification Toolbox (`compare`,
`aic`, `fpe`), but for two: `aic`, `aicc` and `bic` leave out the raw criteria's constant
term, which depends on n and n_z only (n n_z (log 2 pi + 1) in the raw AIC) and which
differences between models on the same data do not see, and `nrmse` is the normalised
error (0 for a perfect fit), where MATLAB's `goodnessOfFit` 'NRMSE' is 1 minus it. They
are compiled JAX functions (and jittable). Where an output channel is constant over the
samples scored, `nrmse`, `fit_percent` and `r2` divide by its zero deviation from its
mean: inf, -inf and -inf for a model that misses it, NaN (0 / 0) for one that reproduces
it exactly; `aic`, `aicc` and `bic` are -inf and `fpe` 0 where the errors are exactly
zero (det 0). `benchmark_scores` refuses a constant channel instead. A NaN sample (a
missing one) counts only through `mask`: without one, a NaN in z or zhat makes that
output's value NaN (a NaN in a concrete z warns); pass `mask=~np.isnan(z)` to leave
missing samples out, as `FitResult.metrics` does.

`benchmark_scores` scores a simulation under the community's benchmark protocol (the
first n samples are left out) with the definitions of `nonlinear_benchmarks.error_metrics`;
it runs on the host in NumPy float64 and returns a printable, JSON-friendly result.

`residual_correlations` is the residual analysis of MATLAB's `resid` (NumPy, on the host):
the residuals' autocorrelation and their cross-correlation with the inputs, with 99 %
bounds and a whiteness and an independence verdict (`oneshot_jax.plot.resid` draws it).
"""

from __future__ import annotations

import math
import numbers
import statistics
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._caller_warnings import warn
from ._counts import integral, real
from ._masked import unmasked

__all__ = [
    "rmse",
    "nrmse",
    "fit_percent",
    "r2",
    "aic",
    "aicc",
    "bic",
    "fpe",
    "benchmark_scores",
    "BenchmarkScores",
    "residual_correlations",
    "ResidualCorrelations",
]


# The criteria of a whole fit (one float each in `FitResult.metrics`), each computed by
# this module's function of that name.
_CRITERIA = ("aic", "aicc", "bic", "fpe")


def _widened(a):
    """`a` with half-precision floats (float16, bfloat16) widened to float32: scored in
    their own precision, a sum of squares of outputs of a few hundred overflows (the
    largest float16 is 65504), and FIT% is off in its third digit."""
    if jnp.issubdtype(a.dtype, jnp.floating) and jnp.finfo(a.dtype).bits < 32:
        return a.astype(np.float32)
    return a


def _check(z, zhat, mask):
    """`z`, `zhat` and `mask`, a NumPy masked array none of whose entries is masked read
    as its data; refuse what is not a record of numbers, and, on concrete values (not under
    a transformation), an empty record and a mask that is negative or selects no sample of
    an output."""
    for name, a in (("z", z), ("zhat", zhat), ("mask", mask)):
        if isinstance(a, np.ma.MaskedArray) and np.ma.is_masked(a):
            raise TypeError(
                f"`{name}` is a NumPy masked array with masked entries, which the scores do not "
                f"read: pass its data (`np.ma.getdata({name})`) and the samples to score as "
                "`mask=` (true where scored, `~np.ma.getmaskarray(z)` for a masked z)."
            )
    z, zhat, mask = (unmasked(a, name) for a, name in ((z, "z"), (zhat, "zhat"), (mask, "mask")))
    named = (("z", z), ("zhat", zhat)) + ((("mask", mask),) if mask is not None else ())
    arrays = {}
    for name, a in named:
        if isinstance(a, jax.Array):  # (a tracer too: its dtype, without its values)
            if a.dtype.kind not in "biuf":
                raise TypeError(
                    f"`{name}` must be a numeric array (T,) or (T, n_z), got a JAX array of "
                    f"dtype {a.dtype}."
                )
            arrays[name] = _widened(a)
            continue
        try:
            # (an array of NumPy's: a pandas Series or DataFrame, a list, read by value)
            array = np.asarray(a)
        except (TypeError, ValueError) as err:
            raise TypeError(
                f"`{name}` must be a numeric array (T,) or (T, n_z), got {type(a).__name__} "
                f"({err})."
            ) from err
        if array.dtype.kind not in "biuf":
            raise TypeError(
                f"`{name}` must be a numeric array (T,) or (T, n_z), got {type(a).__name__}"
                + (f" of dtype {array.dtype}" if array.dtype.kind != "O" else "")
                + "."
            )
        arrays[name] = _widened(array)
    z, zhat, mask = arrays["z"], arrays["zhat"], arrays.get("mask")
    named = tuple((name, arrays[name]) for name, _ in named)
    if any(isinstance(a, jax.core.Tracer) for _, a in named):
        return z, zhat, mask
    if np.size(z) == 0:
        raise ValueError(f"`z` holds no samples (shape {np.shape(z)}).")
    shape = np.shape(z)
    if len(shape) == 2 and shape[0] == 1 and shape[1] >= 2:  # (a (T,) record as a row)
        raise ValueError(
            f"`z` holds T = 1 sample of {shape[-1]} outputs (shape {shape}): is it transposed? "
            "(z is (T, n_z), time first)"
        )
    if len(shape) == 2 and 2 <= shape[0] < shape[1]:  # (a transposed record of n_z >= 2)
        warn(
            f"`z` holds T = {shape[0]} samples of {shape[1]} outputs (shape {shape}): is it "
            "transposed? (z is (T, n_z), time first; the scores are one per output)",
            UserWarning,
            stacklevel=3,
        )
    if mask is None and np.isnan(np.asarray(z, dtype=float)).any():
        warn(
            "`z` holds NaN (missing samples), and every output with one scores NaN: pass "
            "`mask=~np.isnan(z)` to score the measured samples only (as `FitResult.metrics` "
            "does).",
            UserWarning,
            stacklevel=3,
        )
    if mask is not None and np.shape(mask) == np.shape(z):
        m = np.asarray(mask, dtype=float)
        if not np.all((m == 0) | (m == 1)):
            raise ValueError(
                "`mask` must be true where a sample is scored and false elsewhere, 1 or 0 "
                "(it selects samples; it does not weight them)."
            )
        per_output = m.reshape(-1, m.shape[-1]).sum(axis=0) if m.ndim > 1 else m.sum()[None]
        if not np.all(per_output > 0):
            empty = np.flatnonzero(per_output <= 0).tolist()
            raise ValueError(f"`mask` selects no sample of output(s) {empty}.")
    return z, zhat, mask


def _flat(z, zhat, mask=None):
    """(n, n_z) views of z, zhat and the weights of the samples (1, or the mask)."""
    z, zhat = jnp.asarray(z), jnp.asarray(zhat)
    # (T,) is one output channel, the same as (T, 1), as for `benchmark_scores`.
    if z.ndim == 1 and zhat.shape == (*z.shape, 1):
        z = z[:, None]
        mask = None if mask is None or jnp.ndim(mask) != 1 else jnp.asarray(mask)[:, None]
    elif zhat.ndim == 1 and z.shape == (*zhat.shape, 1):
        zhat = zhat[:, None]
    if z.shape != zhat.shape:
        raise ValueError(
            f"`z` and `zhat` must have the same shape, got {z.shape} and {zhat.shape}."
        )
    if mask is not None and jnp.shape(mask) != z.shape:
        raise ValueError(f"`mask` must have the shape of `z` {z.shape}, got {jnp.shape(mask)}.")
    if z.ndim == 0:
        raise ValueError(
            "`z` and `zhat` must be records of outputs, (T,) or (T, n_z) (or (N, T, n_z)); "
            "got scalars."
        )
    if z.ndim == 1:
        z, zhat = z[:, None], zhat[:, None]
        mask = None if mask is None else jnp.asarray(mask)[:, None]
    n_z = z.shape[-1]
    w = jnp.ones(z.shape, z.dtype) if mask is None else (jnp.asarray(mask) > 0).astype(z.dtype)
    w = w.reshape(-1, n_z)
    # Missing samples may hold anything (NaN): they must not reach the sums.
    z = jnp.where(w > 0, z.reshape(-1, n_z), 0.0)
    zhat = jnp.where(w > 0, zhat.reshape(-1, n_z), 0.0)
    return z, zhat, w


def _mean(a, w):
    return jnp.sum(w * a, axis=0) / jnp.sum(w, axis=0)


def _spread(z, w):
    """||z - mean(z)|| per output (the denominator of FIT% and R^2), NaN where it is at
    the round-off of the mean (a constant output, one measured sample): its value there
    is the mean's rounding, and FIT% came out as -3e17 %, -inf or NaN by chance."""
    spread = jnp.sqrt(jnp.sum(w * (z - _mean(z, w)) ** 2, axis=0))
    eps = jnp.finfo(z.dtype).eps
    noise = 16.0 * eps * jnp.sqrt(jnp.sum(w, axis=0)) * jnp.max(w * jnp.abs(z), axis=0)
    return jnp.where(spread > noise, spread, jnp.nan)


def rmse(z, zhat, mask=None):
    """Root-mean-square error per output: sqrt(mean_k (zhat_k - z_k)^2), over the samples
    where `mask` (shaped like z, optional) is true."""
    z, zhat, mask = _check(z, zhat, mask)
    return _rmse(z, zhat, mask)


@jax.jit  # (one compiled call per shape, not one per operation)
def _rmse(z, zhat, mask):
    z, zhat, w = _flat(z, zhat, mask)
    return jnp.sqrt(_mean((zhat - z) ** 2, w))


def nrmse(z, zhat, mask=None):
    """RMSE divided by the standard deviation of the measured output, per output:
    ||zhat - z|| / ||z - mean(z)||, 0 for a perfect fit (= 1 - FIT% / 100).

    MATLAB's `goodnessOfFit(..., 'NRMSE')` is the other way round, a fitness
    1 - ||zhat - z|| / ||z - mean(z)|| (1 for a perfect fit): 1 minus this. NaN for an
    output without spread (constant, or measured once), where it is undefined.
    """
    z, zhat, mask = _check(z, zhat, mask)
    return _nrmse(z, zhat, mask)


@jax.jit  # (one compiled call per shape, not one per operation)
def _nrmse(z, zhat, mask):
    z, zhat, w = _flat(z, zhat, mask)
    return jnp.sqrt(jnp.sum(w * (zhat - z) ** 2, axis=0)) / _spread(z, w)


def fit_percent(z, zhat, mask=None):
    """FIT% = 100 (1 - ||zhat - z|| / ||z - mean(z)||) per output (MATLAB's `compare`);
    NaN for an output without spread (constant, or measured once: `_spread`), where it
    is undefined."""
    z, zhat, mask = _check(z, zhat, mask)
    return _fit_percent(z, zhat, mask)


@jax.jit  # (one compiled call per shape, not one per operation)
def _fit_percent(z, zhat, mask):
    z, zhat, w = _flat(z, zhat, mask)
    num = jnp.sqrt(jnp.sum(w * (zhat - z) ** 2, axis=0))
    den = _spread(z, w)
    return 100.0 * (1.0 - num / den)


def r2(z, zhat, mask=None):
    """Coefficient of determination R^2 = 1 - SSE / SST per output; NaN for an output
    without spread (constant, or measured once), where it is undefined."""
    z, zhat, mask = _check(z, zhat, mask)
    return _r2(z, zhat, mask)


@jax.jit  # (one compiled call per shape, not one per operation)
def _r2(z, zhat, mask):
    z, zhat, w = _flat(z, zhat, mask)
    sse = jnp.sum(w * (zhat - z) ** 2, axis=0)
    sst = _spread(z, w) ** 2
    return 1.0 - sse / sst


def aic(z, zhat, n_params, mask=None):
    """Akaike's information criterion, AIC = n log det(E^T E / n) + 2 n_params.

    E is the (n, n_z) matrix of errors over the n samples (those where every output is
    measured, when a `mask` is given) (MATLAB's raw AIC without the constant
    n n_z (log 2 pi + 1)). Lower is better; only differences between models on the same
    data mean anything. `ValueError` where `mask` leaves no sample with every output
    measured (outputs sampled at different times); NaN where fewer samples measure every
    output than there are outputs (E^T E / n is then singular).
    """
    _check_n_params(n_params)
    z, zhat, mask = _check(z, zhat, mask)
    _check_full_rows(z, mask)
    return _aic(z, zhat, n_params, mask)


def aicc(z, zhat, n_params, mask=None):
    """Akaike's criterion corrected for small samples (Hurvich and Tsai 1989),
    AICc = AIC + 2 d (d + 1) / (n - d - 1), d = `n_params`.

    AIC and n are those of `aic` (MATLAB's `aic(sys, 'AICc')` without its constant
    n n_z (log 2 pi + 1)); the correction penalises parameters more where they are not
    few against the samples. inf where n <= d + 1; NaN where the AIC is (fewer samples
    than outputs measure every output).
    """
    _check_n_params(n_params)
    z, zhat, mask = _check(z, zhat, mask)
    _check_full_rows(z, mask)
    return _aicc(z, zhat, n_params, mask)


def bic(z, zhat, n_params, mask=None):
    """Schwarz's Bayesian information criterion, BIC = n log det(E^T E / n) + d log n,
    d = `n_params`.

    E and n as for `aic` (MATLAB's `aic(sys, 'BIC')` without its constant
    n n_z (log 2 pi + 1): its constant term, which depends on n and n_z only). Its penalty,
    log n per parameter against AIC's 2, grows with
    the record: it picks smaller models than AIC from long records. Lower is better;
    only differences between models on the same data mean anything.
    """
    _check_n_params(n_params)
    z, zhat, mask = _check(z, zhat, mask)
    _check_full_rows(z, mask)
    return _bic(z, zhat, n_params, mask)


def fpe(z, zhat, n_params, mask=None):
    """Akaike's final prediction error, FPE = det(E^T E / n) (1 + d / n) / (1 - d / n),
    d = `n_params` (MATLAB's `fpe`).

    E is the (n, n_z) matrix of errors over the n samples (those where every output is
    measured, when a `mask` is given), as for `aic`. Lower is better; inf where
    d >= n (no samples left to judge the parameters by); NaN where, with d < n, fewer
    samples measure every output than there are outputs (E^T E / n is then singular, as
    for `aic`). `ValueError` where `mask` leaves no sample with every output measured
    (outputs sampled at different times), as for `aic`.
    """
    _check_n_params(n_params)
    z, zhat, mask = _check(z, zhat, mask)
    _check_full_rows(z, mask)
    return _fpe(z, zhat, n_params, mask)


def _check_n_params(n_params):
    dtype = getattr(n_params, "dtype", None)
    if isinstance(n_params, (bool, np.bool_)) or not (
        isinstance(n_params, numbers.Integral)
        or (dtype is not None and jnp.ndim(n_params) == 0 and jnp.issubdtype(dtype, jnp.integer))
    ):
        raise TypeError(
            f"`n_params` must be an integer, the number of estimated parameters, got {n_params!r}."
        )
    if not isinstance(n_params, jax.core.Tracer) and int(n_params) < 0:
        raise ValueError(f"`n_params` must be >= 0, got {n_params}.")


def _check_full_rows(z, mask):
    """Refuse (on concrete values) a mask under which no sample measures every output:
    E^T E / n of `aic` and `fpe` would have n = 0."""
    if mask is None or isinstance(mask, jax.core.Tracer) or np.shape(mask) != np.shape(z):
        return
    m = np.asarray(mask, dtype=float)
    m = m.reshape(-1, m.shape[-1]) if m.ndim > 1 else m[:, None]
    if not np.any(np.all(m > 0, axis=1)):
        raise ValueError(
            "`mask` leaves no sample where every output is measured: the AIC, AICc, BIC and "
            "FPE use the error covariance E^T E / n over such samples (n = 0 here). Score the "
            "outputs one at a time, or on the samples they share."
        )


def _error_covariance(z, zhat, mask):
    """E^T E / n over the n samples where every output is measured, n, and the number of
    outputs measured anywhere (`aic`, `fpe`).
    An output with no measured sample (possible only inside `fit`, traced: a zero-weight
    output that is never measured) is left out (its row and column of E^T E / n are
    those of the identity)."""
    z, zhat, w = _flat(z, zhat, mask)
    seen = w > 0
    used = jnp.any(seen, axis=0)
    full = jnp.all(seen | ~used, axis=1).astype(z.dtype)
    e = (zhat - z) * full[:, None]
    n = jnp.sum(full)
    cov = e.T @ e / n
    keep = used[:, None] & used[None, :]
    return jnp.where(keep, cov, jnp.eye(cov.shape[0], dtype=cov.dtype)), n, jnp.sum(used)


@jax.jit
def _aic(z, zhat, n_params, mask):
    cov, n, used = _error_covariance(z, zhat, mask)
    _, logdet = jnp.linalg.slogdet(cov)
    # fewer full samples than measured outputs: E^T E / n is singular (rank <= n), its
    # log det -inf and the finite slogdet round-off: no AIC (as `fpe`'s d >= n is inf)
    return jnp.where(n >= used, n * logdet + 2.0 * n_params, jnp.nan)


@jax.jit
def _aicc(z, zhat, n_params, mask):
    _, n, _ = _error_covariance(z, zhat, mask)
    room = n - n_params - 1
    extra = jnp.where(room > 0, 2.0 * n_params * (n_params + 1) / jnp.where(room > 0, room, 1), 0)
    aic = _aic(z, zhat, n_params, mask)  # (NaN where E^T E / n is singular: n too small)
    return jnp.where(jnp.isnan(aic), jnp.nan, jnp.where(room > 0, aic + extra, jnp.inf))


@jax.jit
def _bic(z, zhat, n_params, mask):
    cov, n, used = _error_covariance(z, zhat, mask)
    _, logdet = jnp.linalg.slogdet(cov)
    return jnp.where(n >= used, n * logdet + n_params * jnp.log(n), jnp.nan)


@jax.jit
def _fpe(z, zhat, n_params, mask):
    cov, n, used = _error_covariance(z, zhat, mask)
    ratio = n_params / jnp.maximum(n, 1)
    factor = (1 + ratio) / jnp.where(ratio < 1, 1 - ratio, 1.0)
    # (det of a singular E^T E / n, an output fitted exactly, can be round-off below 0)
    det = jnp.maximum(jnp.linalg.det(cov), 0.0)
    value = jnp.where(n >= used, det * factor, jnp.nan)  # (fewer full samples: as `aic`)
    return jnp.where(n == 0, jnp.nan, jnp.where(ratio < 1, value, jnp.inf))


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
    value = unmasked(value, name)  # (every sample is scored: a masked one is refused)
    try:
        if np.iscomplexobj(value):
            raise TypeError(f"it holds complex numbers ({np.asarray(value).dtype})")
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
    - `zhat`: model outputs, same shape (or a record-like object, its `y`); (T,) and
        (T, 1) are the same single output.
    - `n`: number of initial samples left out, 0 <= n <= T - 2. Default: the `n` (or
        `state_initialization_window_length`) of `z` when it is a record.

    **Returns:**

    A `BenchmarkScores` of NumPy float64 arrays of shape (n_z,) (n_z = 1 for 1-D input).

    **Raises:**

    `ValueError` if the shapes differ or are not (T,) / (T, n_z), `n` is out of range or
    missing, a value is NaN or inf (for `zhat`, the first such sample is named), or a
    channel of z[n:] is constant (NRMSE undefined); `TypeError` if `n` is not an integer
    (an integral float such as 20.0 counts, as for `predict` and `Record`).

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
    n = integral(n)  # (20.0, as a configuration file may write it, or a 0-d array)
    if isinstance(n, bool) or not isinstance(n, numbers.Integral):
        raise TypeError(f"`n` must be an integer, got {type(n).__name__}.")
    n = int(n)
    y, yhat = _outputs(z, "z"), _outputs(zhat, "zhat")
    # (T,) is one output channel, the same as (T, 1): a one-output record against a model's
    # (T, 1) outputs is not a mismatch.
    y, yhat = (a if a.ndim == 2 else a[:, None] for a in (y, yhat))
    if y.shape != yhat.shape:
        hint = " Is `zhat` transposed? (time first)" if yhat.shape == y.shape[::-1] else ""
        raise ValueError(
            f"`z` and `zhat` must have the same shape (T, n_z), got {y.shape} and "
            f"{yhat.shape}.{hint}"
        )
    T = y.shape[0]
    if T < 2 and y.shape[1] >= 2:
        raise ValueError(
            f"`z` holds T = {T} sample of {y.shape[1]} outputs: is it transposed? (z is "
            "(T, n_z), time first)"
        )
    if T < 2:
        raise ValueError(f"`z` must hold at least two samples to score, got T = {T}.")
    if not 0 <= n <= T - 2:
        raise ValueError(
            f"`n` must satisfy 0 <= n <= T - 2 = {T - 2} (at least two samples scored), got {n}."
        )
    y, yhat = y[n:], yhat[n:]
    if not np.all(np.isfinite(y)):
        raise ValueError("`z` contains NaN or inf values in the scored samples.")
    bad = ~np.all(np.isfinite(yhat), axis=1)
    if bad.any():
        first = n + int(np.argmax(bad))
        raise ValueError(
            f"`zhat` contains NaN or inf in {int(bad.sum())} scored samples, the first at "
            f"sample {first}" + (": the model output diverged." if bad[first - n :].all() else ".")
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


# --------------------------------------------------------------------------- residuals


class ResidualCorrelations(NamedTuple):
    """What `residual_correlations` returns (NumPy arrays, lags first).

    **Fields:**

    - `lags`: the lags tau = -max_lag, ..., max_lag, shape (2 max_lag + 1,).
    - `auto`: the normalised autocorrelation r_e(tau) of each output's residual, shape
        (2 max_lag + 1, n_z) (symmetric in tau, 1 at tau = 0).
    - `cross`: the normalised cross-correlation r_eu(tau) of each output's residual with
        each input, shape (2 max_lag + 1, n_z, n_u); None without `u`.
    - `bound`: the half-width of the confidence band of `auto` (a white residual's),
        z / sqrt(n) per output, shape (n_z,).
    - `white`: per output, whether at most a fraction `tolerance` of the lags 1..max_lag
        of `auto` lie outside the band and none outside `joint_bound` (whiteness test),
        shape (n_z,).
    - `independent`: per output, whether for every input at most a fraction `tolerance`
        of the lags 0..max_lag of `cross` lie outside its band `cross_bound` and none
        outside `cross_joint_bound` (independence of the current and past inputs), shape
        (n_z,); None without `u`.
    - `auto_outside`: the fraction of the lags 1..max_lag outside the band, (n_z,).
    - `cross_outside`: the fraction of the lags 0..max_lag outside the band, (n_z, n_u);
        None without `u`.
    - `n`: the number of measured residual samples per output, (n_z,).
    - `cross_bound`: the half-width of the band of `cross`, z sqrt(P / n) with Ljung's
        P = 1 + 2 sum_{k=1..max_lag} r_e(k) r_u(k) (at least 1: never narrower than
        `bound`), shape (n_z, n_u); None without `u`.
    - `joint_bound`: the half-width of the joint band of `auto`, z' / sqrt(n) with z' the
        normal quantile at 1 - (1 - confidence) / (2 max_lag) (Bonferroni over the
        max_lag lags: a white residual leaves it at some lag with probability at most
        1 - confidence), shape (n_z,).
    - `cross_joint_bound`: the same of `cross` over the (max_lag + 1) n_u lags of all
        the inputs together, z'' sqrt(P / n), shape (n_z, n_u); None without `u`.
    - `confidence`: the level of the bands (`residual_correlations(confidence=...)`),
        which `print` states.
    """

    lags: np.ndarray
    auto: np.ndarray
    cross: np.ndarray | None
    bound: np.ndarray
    white: np.ndarray
    independent: np.ndarray | None
    auto_outside: np.ndarray
    cross_outside: np.ndarray | None
    n: np.ndarray
    cross_bound: np.ndarray | None = None
    joint_bound: np.ndarray | None = None
    cross_joint_bound: np.ndarray | None = None
    confidence: float | None = None

    def __str__(self) -> str:
        """The verdicts per output, with the numbers they rest on (MATLAB's `resid`
        reading): what `print` shows; the arrays are the fields."""
        max_lag = int(np.max(self.lags))
        inputs = "" if self.independent is None else f" (0..{max_lag} with the inputs)"
        level = "" if self.confidence is None else f", {100 * self.confidence:g} % bands"
        out = [f"residual correlations over lags 1..{max_lag}{inputs}{level}"]
        for k in range(len(np.atleast_1d(self.white))):
            white = "white" if bool(np.atleast_1d(self.white)[k]) else "not white"
            line = (
                f"  output {k}: {white} ({100 * float(self.auto_outside[k]):.0f} % of the lags "
                f"outside +-{float(self.bound[k]):.3g}{self._peak(k)}, n = {int(self.n[k])})"
            )
            if self.independent is not None:
                ind = bool(self.independent[k])
                worst = 100 * float(np.max(self.cross_outside[k]))
                line += (
                    f"; {'independent of' if ind else 'correlated with'} the inputs (at most "
                    f"{worst:.0f} % of the lags outside the band{self._cross_peak(k)})"
                )
            out.append(line)
        return "\n".join(out)

    def _peak(self, k):
        """ ", r_e(tau) = .. beyond the joint band +-.." where a lag of output k's
        autocorrelation leaves the joint band (else "")."""
        if self.joint_bound is None:
            return ""
        r_e = np.asarray(self.auto)[len(self.lags) // 2 + 1 :, k]
        tau = int(np.argmax(np.abs(r_e)))
        if abs(r_e[tau]) <= float(self.joint_bound[k]):
            return ""
        return (
            f"; r_e({tau + 1}) = {float(r_e[tau]):.3g} beyond the joint band "
            f"+-{float(self.joint_bound[k]):.3g}"
        )

    def _cross_peak(self, k):
        """The same of output k's cross-correlations at lags >= 0, the worst input's."""
        if self.cross_joint_bound is None:
            return ""
        r = np.asarray(self.cross)[len(self.lags) // 2 :, k]  # (max_lag + 1, n_u)
        over = np.abs(r) / np.asarray(self.cross_joint_bound)[k]
        tau, j = np.unravel_index(int(np.argmax(over)), over.shape)
        if over[tau, j] <= 1.0:
            return ""
        return (
            f"; r_eu({tau}) = {float(r[tau, j]):.3g} of input {j} beyond the joint band "
            f"+-{float(self.cross_joint_bound[k, j]):.3g}"
        )


def _lag_sums(x, max_lag):
    """sum_t x(t) x(t - k) per channel within each trajectory of x (N, T, channels), for
    k = 0..max_lag: (max_lag + 1, channels)."""
    T = x.shape[1]
    return np.stack([np.sum(x[:, k:] * x[:, : T - k], axis=(0, 1)) for k in range(max_lag + 1)])


def _trajectories(a, name, shape=None, missing=False):
    """`a` as a float64 (N, T, n) array; `shape` the (N, T) it must have. A NumPy masked
    array has NaN at its masked entries where `missing` (residuals: a missing sample),
    else its masked entries are refused (`_masked.unmasked`)."""
    if missing and isinstance(a, np.ma.MaskedArray):
        a = np.ma.filled(a.astype(np.float64), np.nan)
    a = unmasked(a, name)
    try:
        complex_ = np.iscomplexobj(a)  # (np.asarray inside: a ragged object raises here)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must be a numeric array, got {type(a).__name__}.") from err
    if complex_:
        raise ValueError(f"`{name}` must hold real numbers, got dtype {np.asarray(a).dtype}.")
    try:
        a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must be a numeric array, got {type(a).__name__}.") from err
    if np.any(np.isinf(a)):
        raise ValueError(f"`{name}` contains inf values (NaN marks a missing sample).")
    if a.ndim not in (1, 2, 3):
        raise ValueError(
            f"`{name}` must have shape (T,), (T, n) or (N, T, n) (time before channels), "
            f"got shape {a.shape}."
        )
    a = a.reshape((1,) * (3 - a.ndim) + a.shape) if a.ndim > 1 else a[None, :, None]
    if shape is not None and a.shape[:2] != shape:
        raise ValueError(
            f"`{name}` must have the trajectories and samples (N, T) = {shape} of `e`, got "
            f"{a.shape[:2]}."
        )
    return a


def _ragged(u) -> bool:
    """A list of records that NumPy cannot stack (of different lengths)."""
    if not isinstance(u, (list, tuple)):
        return False
    try:
        np.asarray(u, dtype=np.float64)
    except (TypeError, ValueError):
        return all(np.ndim(r) >= 1 for r in u)
    return False


def _inputs(u, N, T):
    """`u` as (N, T, n_u) and where it is known (N, T): the records of a list of
    different lengths (as `fit` takes them) end where theirs do, and their residuals
    (`FitResult.residuals`, NaN past each record's end) with them."""
    if not _ragged(u):
        return _trajectories(u, "u", (N, T)), np.ones((N, T), bool)
    if len(u) != N:
        raise ValueError(f"`u` must hold the N = {N} records of `e`, got {len(u)}.")
    rows = [_trajectories(r, f"u[{i}]")[0] for i, r in enumerate(u)]
    if len({r.shape[1] for r in rows}) > 1 or max(r.shape[0] for r in rows) > T:
        raise ValueError(
            f"`u`: records of at most T = {T} samples (that of `e`) and the same inputs each, "
            f"got shapes {[r.shape for r in rows]}."
        )
    out = np.full((N, T, rows[0].shape[1]), np.nan)
    known = np.zeros((N, T), bool)
    for i, r in enumerate(rows):
        out[i, : r.shape[0]], known[i, : r.shape[0]] = r, True
    return out, known


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _normal_quantile(p):
    """The standard normal distribution's quantile at p in (0, 1] (the standard
    library's, Wichura's AS 241, accurate to about 1e-16: no SciPy import); inf at p
    rounded to 1 (a confidence within eps of 1)."""
    return math.inf if p >= 1.0 else statistics.NormalDist().inv_cdf(p)


def residual_correlations(
    e, u=None, max_lag=25, *, confidence=0.99, tolerance=0.05, demean=True
) -> ResidualCorrelations:
    """Residual analysis: the autocorrelation of the residuals and their cross-correlation
    with the inputs, with confidence bounds and a whiteness and an independence verdict
    (MATLAB's `resid`; Ljung, *System Identification*, Sec. 16.6).

    With R_e(tau) = (1/n) sum_t e(t) e(t - tau) and R_eu(tau) = (1/n) sum_t e(t) u(t - tau)
    (sums over the samples where both terms exist), the normalised correlations are

        r_e(tau) = R_e(tau) / R_e(0),    r_eu(tau) = R_eu(tau) / sqrt(R_e(0) R_u(0)).

    For a white residual, independent of the input, each is asymptotically normal with
    variance 1/n (Ljung, Sec. 16.6), so |r| <= z / sqrt(n) with z = 2.58 for 99 %. A
    residual is called white when at most a fraction `tolerance` of r_e(1..max_lag) leaves
    the band and none leaves the joint band of all max_lag lags, and independent of the
    inputs when the same holds of r_eu(0..max_lag) for every input: a peak at lag tau > 0
    says that the part of the output due to u(t - tau) is not explained by the model. The
    joint band is the band at the level that all the lags of the test together keep with
    probability `confidence` (Bonferroni: z' at 1 - (1 - confidence) / (2 m) for m lags,
    3.54 for 25 lags at 99 %; m = max_lag for whiteness, (max_lag + 1) n_u for
    independence, every input's lags together), so that one large peak (a residual
    correlated with u(t - 3) alone, say) fails the test, which a count of the lags
    outside allows. Correlation at negative lags (future inputs) is left out of the
    verdict: under feedback it appears even for a right model. The cross-correlation's
    band allows for a coloured residual and a coloured input (the usual case after an
    output-error fit): its variance is P / n with P = sum_k r_e(k) r_u(k) over
    |k| <= max_lag (Ljung, Sec. 16.6), taken at least 1 (the white band), so
    `cross_bound` is per output and input.

    Each signal's mean is removed first (`demean`): MATLAB's `resid` correlates the
    signals as given and expects data detrended before the estimation, but grey-box data
    keep their physical offsets (a pump voltage around 3 V, say), and an input's offset
    would shrink r_eu towards zero. The sign of `e` only flips `cross`:
    `FitResult.residuals` is zhat - z, MATLAB's residuals are z - zhat.

    **Arguments:**

    - `e`: the residuals, shape (T,), (T, n_z) or (N, T, n_z) (N trajectories, pooled:
        the sums run over each trajectory, never across two, and n counts all of them).
        NaN marks a missing sample (as in `FitResult.residuals`): the products with it
        are left out and it is not counted in n. The inputs, known at every sample of
        their records, keep all of them in their own mean and R_u(0), so that a missing
        output does not change what is measured of the input.
    - `u`: the inputs, shape (T,), (T, n_u) or (N, T, n_u) with the N and T of `e`, or
        a list of N records (T_i, n_u) of different lengths, as `fit` takes them (`e`
        then NaN past each record's end, as `FitResult.residuals` is); finite. None, or
        inputs of no columns (a model without inputs, u (T, 0)): autocorrelation only.
    - `max_lag`: the largest lag, an integer, 1 <= max_lag <= T - 1 (MATLAB's default 25).
    - `confidence`: the level of the band, 0 < confidence < 1 (z = 2.576 for 0.99).
    - `tolerance`: the fraction of lags allowed outside the band in a verdict,
        0 <= tolerance < 1; 0 is the strict reading, "no lag outside". The verdict allows
        floor(tolerance max_lag) lags outside the band, none outside the joint band. For a
        white residual the count outside is about Binomial(max_lag, 1 - confidence), so
        the count's false-alarm rate depends on max_lag: with the defaults it is 2.6 % at
        MATLAB's max_lag 25 (one lag allowed), but up to 1 - 0.99^max_lag for max_lag <
        20, where no lag is allowed (17 % at 19), and it jumps at each multiple of 20; the
        joint band adds at most 1 - `confidence` to each verdict. These rates hold on long
        records (T of some hundreds). On a short one the band, z / sqrt(n) at every lag,
        is wider than the spread of r(tau) (a sum of n - tau products over n: standard
        deviation sqrt(n - tau) / n), so the test alarms less often than that, and it
        detects coloured residuals less often too: a "white" verdict on a record of a few
        tens of samples says little. Each output is tested on its own: over several
        outputs the chance that some verdict alarms grows with their number.
    - `demean`: subtract each channel's mean (over its measured samples, all trajectories
        pooled) first (default); False: the sums of the signals as given, as MATLAB's
        `resid` forms them.

    **Returns:**

    A `ResidualCorrelations(lags, auto, cross, bound, white, independent, auto_outside,
    cross_outside, n, cross_bound, joint_bound, cross_joint_bound, confidence)` of NumPy
    arrays (and the level, a float).

    **Raises:**

    `ValueError` naming the argument: a shape that is not one of the above, `u` not
    finite or not matching `e`, `max_lag`, `confidence` or `tolerance` out of range, an
    output with fewer than two measured samples, a residual that is zero, or an input that
    is zero (or, with `demean`, constant).

    **Reference:**

    L. Ljung, *System Identification: Theory for the User*, 2nd ed., Prentice Hall, 1999,
    Sec. 16.6 (residual analysis).
    """
    given, e = e, _trajectories(e, "e", missing=True)
    N, T, n_z = e.shape
    if T < 2:  # (before `max_lag`, whose range it would leave empty)
        hint = (
            f" (`e` holds T = {T} samples of {n_z} outputs: is it transposed?)" if n_z > 1 else ""
        )
        raise ValueError(f"`e` must have at least two samples, got shape {np.shape(given)}{hint}.")
    if isinstance(max_lag, bool) or not isinstance(max_lag, numbers.Integral):
        raise ValueError(f"`max_lag` must be an integer, got {max_lag!r}.")
    if not 1 <= max_lag <= T - 1:
        hint = ""
        if T <= max_lag < n_z:  # more channels than samples: a residual given as (n_z, T)
            hint = f" (`e` holds T = {T} samples of {n_z} outputs: is it transposed?)"
        raise ValueError(
            f"`max_lag` must satisfy 1 <= max_lag <= T - 1 = {T - 1}, got {max_lag}{hint}."
        )
    max_lag = int(max_lag)
    # (a concrete 0-d array as the number it holds: `_counts.real`)
    level, share = real(confidence), real(tolerance)
    if not (_is_number(level) and 0.0 < level < 1.0):
        raise ValueError(f"`confidence` must be a number in (0, 1), got {confidence!r}.")
    if not (_is_number(share) and 0.0 <= share < 1.0):
        raise ValueError(f"`tolerance` must be a number in [0, 1), got {tolerance!r}.")
    confidence, tolerance = level, share
    if not isinstance(demean, (bool, np.bool_)):
        raise TypeError(f"`demean` must be True or False, got {demean!r}.")

    measured = np.isfinite(e)
    n = measured.sum(axis=(0, 1))
    if np.any(n < 2):
        few = np.flatnonzero(n < 2).tolist()
        keep = np.flatnonzero(n >= 2).tolist()
        raise ValueError(
            f"`e` has fewer than two finite samples in output(s) {few}"
            + (
                f" (an output read only as aggregates has no residuals of its own: pass "
                f"e[..., {keep}], the outputs that have them)."
                if keep
                else "."
            )
        )
    if np.any(n <= max_lag):  # (the larger lags would rest on no pair of samples)
        few = np.flatnonzero(n <= max_lag).tolist()
        raise ValueError(
            f"`max_lag` ({max_lag}) must be below the number of finite samples of `e`, "
            f"but output(s) {few} have only {n[few].tolist()}: choose a smaller max_lag."
        )
    e = np.where(measured, e, 0.0)  # a missing sample adds nothing to the sums
    if demean:
        e = np.where(measured, e - e.sum(axis=(0, 1)) / n, 0.0)
    r0 = np.sum(e**2, axis=(0, 1)) / n
    if np.any(r0 <= 0):
        raise ValueError(
            f"`e` is zero in output(s) {np.flatnonzero(r0 <= 0).tolist()}: its correlations "
            f"are undefined."
        )
    lags = np.arange(-max_lag, max_lag + 1)
    # R_e(tau) for tau >= 0 within each trajectory; R_e(-tau) = R_e(tau).
    half = _lag_sums(e, max_lag)
    auto = np.concatenate([half[:0:-1], half]) / n / r0
    r_e = auto[max_lag + 1 :]  # lags 1..max_lag
    z = _normal_quantile(0.5 + 0.5 * float(confidence))
    bound = z / np.sqrt(n)
    auto_outside = np.mean(np.abs(r_e) > bound, axis=0)

    def joint(m):  # the joint band's factor over the band: m lags together (Bonferroni)
        if math.isinf(z):  # (a confidence within eps of 1: both bands infinite)
            return 1.0
        return _normal_quantile(1.0 - 0.5 * (1.0 - float(confidence)) / m) / z

    joint_bound = bound * joint(max_lag)
    white = (auto_outside <= tolerance) & np.all(np.abs(r_e) <= joint_bound, axis=0)

    cross = independent = cross_outside = cross_bound = cross_joint_bound = None
    if u is not None:
        u, known = _inputs(u, N, T)
        beyond = measured.any(axis=-1) & ~known  # (records given in another order)
        if beyond.any():
            i = int(np.flatnonzero(beyond.any(axis=1))[0])
            last = int(np.flatnonzero(measured[i].any(axis=-1))[-1])
            raise ValueError(
                f"`u[{i}]` has {int(known[i].sum())} samples but `e[{i}]` has measured "
                f"residuals up to sample {last}: give the records of `u` in the order of "
                "`e`'s, each as long as its record."
            )
        if u.shape[-1] == 0:  # (a model without inputs, u (T, 0): nothing to correlate)
            u = None
    if u is not None:
        if not np.all(np.isfinite(u[known])):
            raise ValueError("`u` contains NaN or inf values: the inputs must be known.")
        count = known.sum()
        u = np.where(known[..., None], u, 0.0)  # past a record's end: adds nothing
        if demean:
            u = np.where(known[..., None], u - u.sum(axis=(0, 1)) / count, 0.0)
        ru0 = np.sum(u**2, axis=(0, 1)) / count
        if np.any(ru0 <= 0):
            flat = np.flatnonzero(ru0 <= 0).tolist()
            raise ValueError(
                f"`u` is constant in input(s) {flat}: zero once its mean is removed "
                "(`demean`), so its correlations are undefined; leave it out of `u`."
                if demean
                else f"`u` is zero in input(s) {flat}: its correlations are undefined."
            )

        def lagged(k):  # sum_t e(t) u(t - k), (n_z, n_u)
            if k >= 0:
                return np.einsum("ntz,ntu->zu", e[:, k:], u[:, : T - k])
            return np.einsum("ntz,ntu->zu", e[:, : T + k], u[:, -k:])

        scale = n[:, None] * np.sqrt(r0[:, None] * ru0[None, :])
        cross = np.stack([lagged(int(k)) for k in lags]) / scale
        # Ljung's variance of r_eu: P / n, P = sum_k r_e(k) r_u(k) (both coloured).
        r_u = _lag_sums(u, max_lag)[1:] / (count * ru0)
        P = np.maximum(1.0 + 2.0 * np.einsum("kz,ku->zu", r_e, r_u), 1.0)
        cross_bound = bound[:, None] * np.sqrt(P)
        cross_outside = np.mean(np.abs(cross[max_lag:]) > cross_bound, axis=0)
        cross_joint_bound = cross_bound * joint((max_lag + 1) * u.shape[-1])
        inside = np.all(np.abs(cross[max_lag:]) <= cross_joint_bound, axis=0)
        independent = np.all((cross_outside <= tolerance) & inside, axis=1)
    return ResidualCorrelations(
        lags=lags,
        auto=auto,
        cross=cross,
        bound=bound,
        white=white,
        independent=independent,
        auto_outside=auto_outside,
        cross_outside=cross_outside,
        n=n,
        cross_bound=cross_bound,
        joint_bound=joint_bound,
        cross_joint_bound=cross_joint_bound,
        confidence=float(confidence),
    )
