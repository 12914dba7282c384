"""`fit(weight="noise")`: the output weight Q estimated with theta, as MATLAB's
`nlgreyestOptions(OutputWeight="noise")`.

The covariance of a fit pools one noise level sigma^2 over the outputs (eq. (4)'s Q
weighs them): its standard errors are the Cramer-Rao bound only where Q is proportional
to the inverse of the noise covariance. With `weight="noise"` the fit alternates: fit
theta and x0 with Q, then set Q to the inverse of the residuals' covariance E^T E / n,
until Q settles (the relaxation algorithm of output-error estimation with an unknown
noise covariance, whose fixed point minimises det(E^T E / n): Ljung, *System
Identification*, 2nd ed., 1999, Section 7.3 and eq. (7.90)). Each round starts where the
last stopped, so its solve is short, and the fit's compiled program is reused."""

import dataclasses
import warnings

import numpy as np

# Rounds of the alternation at most, and the change of Q (relative, in the Frobenius
# norm, Q normalised to det Q = 1) at which it counts as settled.
NOISE_ROUNDS = 10
NOISE_RTOL = 1e-3


def noise_weight(residuals):
    """Q from a fit's residuals: the inverse of E^T E / n over the samples (every record's,
    pooled) where every output is measured, (n_z, n_z); where some sample misses an output,
    the diagonal 1 / (each output's mean squared residual over its samples), (n_z,).
    Normalised to det Q = 1 (a fit ignores Q's scale; the loss keeps its size). None
    where an output's residuals are all zero or missing (no noise level to weigh by)."""
    e = np.asarray(residuals, dtype=np.float64)
    e = e.reshape(-1, e.shape[-1])
    seen = np.isfinite(e)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an output with no sample: NaN)
        var = np.nanmean(np.where(seen, e**2, np.nan), axis=0)
    if not np.all(np.isfinite(var) & (var > 0)):
        return None
    n_z = e.shape[-1]
    if seen.all() and n_z > 1:
        S = e.T @ e / e.shape[0]
        if np.linalg.cond(S) < 1e12:
            Q = np.linalg.inv(S)
            Q = 0.5 * (Q + Q.T)
            return Q / np.linalg.det(Q) ** (1.0 / n_z)
    q = 1.0 / var
    return q / np.exp(np.mean(np.log(q)))


def _change(new, old):
    new, old = np.asarray(new), np.asarray(old)
    if new.shape != old.shape:  # (one round full, the next diagonal: compare matrices)
        new = np.diag(new) if new.ndim == 1 else new
        old = np.diag(old) if old.ndim == 1 else old
    return float(np.linalg.norm(new - old) / np.linalg.norm(old))


def fit_noise_weighted(fit, args):
    """`fit(**args)` with the weight estimated from the residuals (see the module
    docstring): from Q = I, at most `NOISE_ROUNDS` fits, each warm-started from the last
    (theta, and x0 where its shape is the one given; a multistart only in the first, whose
    `starts` and `best` the result keeps); the result of the last fit, whose Q the
    residuals reproduce to `NOISE_RTOL`, with `result.weight` that Q and
    `stop_info["noise_weight_rounds"]` the number of fits.
    Only the returned fit's warnings are shown; a Q that has not settled after the last
    round, or residuals that give none, get a warning of their own."""
    given_x0 = np.shape(args["x0"])
    w, change, rounds, result, first = None, np.inf, 0, None, None
    for rounds in range(1, NOISE_ROUNDS + 1):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = fit(**{**args, "weight": w})
        first = result if first is None else first
        if not np.isfinite(float(result.loss)):
            break
        Q = noise_weight(result.residuals)
        if Q is None:
            caught.append(
                warnings.WarningMessage(
                    "`weight='noise'`: an output's residuals are all zero or missing, so "
                    "there is no noise level to weigh it by; the result is that of the "
                    "last weight.",
                    UserWarning,
                    __file__,
                    0,
                )
            )
            break
        change = np.inf if w is None else _change(Q, w)
        if change <= NOISE_RTOL:
            break
        w = Q
        x0 = np.asarray(result.x0)
        args = {
            **args,
            "theta0": result.theta,
            "x0": x0 if x0.shape == given_x0 else args["x0"],
            "multistart": False,
        }
    else:
        caught.append(
            warnings.WarningMessage(
                f"`weight='noise'`: the weight had not settled after {NOISE_ROUNDS} fits "
                f"(its last relative change {change:.3g} > {NOISE_RTOL:g}); the result is "
                "that of the last fit.",
                RuntimeWarning,
                __file__,
                0,
            )
        )
    for c in caught:
        warnings.warn(c.message, c.category, stacklevel=3)
    info = {**result.stop_info, "noise_weight_rounds": rounds}
    result = dataclasses.replace(result, stop_info=info)
    if first.starts is not None and result.starts is None:  # (the first fit's multistart)
        result = dataclasses.replace(result, starts=first.starts, best=first.best)
    return result
