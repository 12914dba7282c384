"""The initial state of a new record from its first samples, and prediction from it.

A fitted model used on a record it has never seen needs that record's x0. `estimate_x0`
takes it from the head of the record (MATLAB's `findstates`): by least squares on x0
alone (`oneshot_jax._x0_lsq`: the solvers of `fit` with every parameter fixed, so the
closed-form sensitivities of eq. (20)'s forward twin give the Jacobian), or by an extended
Kalman filter and Rauch-Tung-Striebel smoother (`oneshot_jax._x0_smoother`). `predict`
then simulates the whole record from it, which is the community's benchmark protocol: the
model may use the test input and the first n test outputs, and is scored on the rest
(`oneshot_jax.metrics.benchmark_scores(z, prediction.z, n)`). This module holds the public
functions, their checks and results, and the observability check of an estimate.
"""

import math
from typing import Any, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._caller_warnings import frames_to_user, warn
from ._checks import (
    check_cost,
    check_data,
    check_outside_transformations,
    check_tree,
    check_x0_bounds,
    clip_x0,
    is_concrete,
    require_inputs,
)
from ._cost import weigh
from ._counts import is_count
from ._jit import jit
from ._model import model_labels
from ._results import RESULTS, is_success, name_of
from ._simulate import simulate_impl
from ._timing import head_times
from ._x0_lsq import identifiable_x0, solve_x0
from ._x0_smoother import MEASUREMENT_NOISE_REL, KalmanPath, _rms, kalman_path

METHODS = ("lsq", "smoother")


class X0Estimate(eqx.Module):
    """An initial state estimated from the head of a record (what `estimate_x0` returns).

    **Fields:**

    - `x0`: the estimate, shape (n_x,).
    - `covariance`: its (n_x, n_x) covariance; `std` the standard deviations. For
        `"lsq"`, sigma^2 (J^T Q J)^+ with sigma^2 = SSE / (m - n_x) estimated from the
        residuals, m the measured output entries of the head (n n_z without missing
        samples; inf in the rows of an entry the head does not determine, and everywhere
        when m <= n_x); for `"smoother"`, the smoothed posterior covariance P[0 | n-1]
        under the given noise covariances and prior.
    - `identifiable`: (n_x,) booleans, False for an entry the head's outputs do not
        determine (a numerically null direction of J^T Q J, J = d z[0..n-1] / d x0).
    - `loss`: C of eq. (5) over the head from `x0` (mean over k of e_k^T Q e_k).
    - `method`: `"lsq"` or `"smoother"`; `n`: the number of samples used.
    - `stop_reason`: for `"lsq"`, the `RESULTS` item saying why Gauss-Newton stopped
        (None for the smoother); `success` and `message` as in `FitResult`.
    - `kalman`: for `"smoother"`, the filtered and smoothed states over the head (a
        `KalmanPath`); None for `"lsq"`.
    - `states`: the model's names of the state's entries (`Model(states=...)`), which
        `print` shows; None without them.
    - `head`: the outputs z[:n] it was estimated from, as given (None under a JAX
        transformation): `plot.compare` warns where a `Prediction` is scored against
        another record.
    - `at_bound`: with `bounds`, (n_x,) booleans, True for an entry that ended on its
        bound (the head asks for a value beyond it; `print` says so); else None.
    """

    x0: np.ndarray
    covariance: np.ndarray
    std: np.ndarray
    identifiable: np.ndarray
    loss: np.ndarray
    method: str = eqx.field(static=True)
    n: int = eqx.field(static=True)
    stop_reason: Any = None
    kalman: KalmanPath | None = None
    states: tuple | None = eqx.field(static=True, default=None)
    head: np.ndarray | None = None
    at_bound: np.ndarray | None = None

    def __str__(self) -> str:
        """A few lines for `print`: the estimate with its standard deviations, how it was
        made, and the solver's stop (the fields hold the arrays)."""
        how = f"x0 from the first {self.n} samples by {self.method}"
        if self.stop_reason is not None:
            how += f" ({name_of(self.stop_reason)})"
        rows = [how + f", loss {float(self.loss):.6g} (the head's mean of e'Qe)"]
        names = model_labels(self.states, len(self.x0)) or range(len(self.x0))
        rows_of = [f"x0[{i}]" for i in names]
        width = max(map(len, rows_of), default=0)
        bound = np.zeros(len(self.x0), bool) if self.at_bound is None else self.at_bound
        for label, v, s, ok, edge in zip(
            rows_of, self.x0, self.std, self.identifiable, bound, strict=True
        ):
            note = "" if ok else "  (not determined by the head)"
            if edge:  # (its std is that of the unbounded estimate there)
                note += "  (at a bound)"
            rows.append(f"  {label:<{width}} {float(v):12.6g}  std {float(s):.3g}{note}")
        return "\n".join(rows)

    __repr__ = __str__

    @property
    def success(self) -> bool:
        """Gauss-Newton converged (`"lsq"`), or the smoother's estimate is finite."""
        if self.stop_reason is not None:
            return is_success(self.stop_reason)
        return bool(np.all(np.isfinite(self.x0)) and np.all(np.isfinite(self.covariance)))

    @property
    def message(self) -> str:
        """Why Gauss-Newton stopped (`"lsq"`), or whether the smoother's estimate is
        finite, in words."""
        if self.stop_reason is not None:
            return RESULTS[self.stop_reason]
        return "smoothed" if self.success else "the smoother's estimate is not finite"


class Prediction(NamedTuple):
    """What `predict` returns: the simulated outputs `z` (T, n_z) and states `x` (T, n_x)
    of the whole record from the estimated initial state `x0` (n_x,), and the
    `X0Estimate` it came from. `print` gives the shapes and that estimate."""

    z: np.ndarray
    x: np.ndarray
    x0: np.ndarray
    estimate: X0Estimate

    def __str__(self) -> str:
        """A few lines for `print`: the record simulated and the x0 it started from (the
        fields hold the arrays)."""
        return (
            f"Prediction of {np.shape(self.z)[0]} samples (`z` {np.shape(self.z)}, `x` "
            f"{np.shape(self.x)}) from the estimated x0:\n{self.estimate}"
        )

    __repr__ = __str__


#
# Validation.
#


def several_records(a):
    """Whether `a` is a list (or tuple) of records: of 2-D arrays, or of 1-D ones of
    unequal lengths (rows of one record have equal lengths)."""
    if not isinstance(a, (list, tuple)) or not a:
        return False
    ndims = [np.ndim(r) for r in a]
    if any(n >= 2 for n in ndims):
        return True
    return all(n == 1 for n in ndims) and len({len(r) for r in a}) > 1


def _check_head(u, z, n, z_name="z"):
    """u (T, n_u), z (T_z <= T, n_z) and 1 <= n <= T_z, as the number of samples used
    (`z_name`: the caller's name of z)."""
    for name, a in (("u", u), (z_name, z)):
        if several_records(a):
            raise ValueError(
                f"`{name}` must have shape (T, n) (one record), got a {type(a).__name__} of "
                f"{len(a)} records (several records: one call each, or `FitResult.predict`, "
                "which takes them all)."
            )
    require_inputs(u)
    if np.ndim(u) != 2:
        several = (
            " (several records: one call each, or `FitResult.predict`, which takes them all)"
            if np.ndim(u) == 3
            else ""
        )
        raise ValueError(
            f"`u` must have shape (T, n_u) (one record), got shape {np.shape(u)}{several}."
        )
    if np.ndim(z) != 2:
        raise ValueError(
            f"`{z_name}` must have shape (T, n_z) (one record), got shape {np.shape(z)}."
        )
    T, T_z = np.shape(u)[0], np.shape(z)[0]
    if T == 0:
        raise ValueError(f"`u` must hold at least one sample (T >= 1), got shape {np.shape(u)}.")
    if n is None:  # (n is z's length: name z)
        if not 1 <= T_z <= T:
            raise ValueError(
                f"`{z_name}` must have 1 to {T} rows (the first outputs of the record of `u`), "
                f"got {T_z}."
            )
        n = T_z
    if T_z > T:  # (only z[:n] is read: more outputs than inputs is another record)
        hint = ""
        if np.shape(u)[1] == T_z:
            hint = f" (is `u` transposed? it has shape {np.shape(u)})"
        raise ValueError(
            f"`{z_name}` has {T_z} rows, more than the {T} samples of `u`{hint}: give the "
            "record's outputs (T rows) or only its first ones."
        )
    if not is_count(n, -math.inf):
        raise TypeError(f"`n` (the number of head samples) must be an integer, got {n!r}.")
    n = int(n)
    if n < 1:
        raise ValueError(f"`n` (the number of head samples) must be >= 1, got {n}.")
    if n > T_z:
        hint = ""
        if np.ndim(z) == 2 and np.shape(z)[1] == T and T_z < T:
            hint = f" (is `{z_name}` transposed? it has shape {np.shape(z)}, u has T = {T})"
        raise ValueError(f"`n` = {n} is more than the {T_z} samples of `z`{hint}.")
    return n  # (n <= T_z <= T)


#
# Observability of the estimate.
#


@jit
def _x0_identifiable(model, theta, x0, u, weight, free):
    """`identifiable_x0` in one compiled call."""
    return identifiable_x0(model, theta, x0, u, weight, free)


def _observable(data, estimate=None):
    """Per x0 entry, whether the head's (weighted) outputs determine it (`_linalg`'s rule,
    the one `fit` uses for its covariance), with the entries `estimate` (a boolean mask,
    or None: all) free and the others held (identifiable)."""
    sqrt_q = check_cost(data, None, 1.0).sqrt_weight()
    sqrt_q = None if sqrt_q is None else jnp.asarray(sqrt_q, data.x0.dtype)
    free = None if estimate is None else tuple(np.flatnonzero(estimate).tolist())
    x0, u = jnp.asarray(data.x0), jnp.asarray(data.u)
    return np.asarray(_x0_identifiable(data.model, data.theta, x0, u, sqrt_q, free))


#
# Public functions.
#


def estimate_x0(
    model,
    theta: PyTree,
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    *,
    n: int | None = None,
    method: str = "lsq",
    x0: Float[ArrayLike, " n_x"] | None = None,
    weight=None,
    solver=None,
    process_noise=None,
    measurement_noise=None,
    prior_covariance=None,
    t: Float[ArrayLike, " T"] | None = None,
    missing: str = "raise",
    estimate=None,
    bounds=None,
) -> X0Estimate:
    """Estimate the initial state x0 of a record from its first n samples (MATLAB's
    `findstates`), with theta known.

    - `method="lsq"` minimises the head's multi-step cost C of eq. (5) over x0 alone by
        Gauss-Newton on the closed-form Jacobian, with the numbers of `fit(model, theta,
        x0, u[:n], z[:n], fixed=True, solver=GaussNewton())`. For a deterministic model it is the
        maximum-likelihood x0 (the least-squares solution; with a nonlinear model, the
        local one nearest the starting guess). Directions of x0 that the head's outputs do
        not determine get no step in Gauss-Newton's variables, each entry scaled by the
        norm of its Jacobian column (the pseudo-inverse there): an entry that never
        reaches the outputs keeps its starting value (from zeros it stays 0), and along a
        direction that mixes entries (only x0[0] + 3 x0[1] seen) the estimate is the
        solution nearest the guess in those scaled variables, the minimum-norm one from
        zeros only where the entries' columns have equal norms; a warning names them and
        their std is inf.
    - `method="smoother"`: an extended Kalman filter forward and a Rauch-Tung-Striebel
        smoother backward over the head (Särkkä, *Bayesian Filtering and Smoothing*,
        Cambridge University Press, 2013: the EKF of Algorithm 5.4 and the extended RTS
        smoother of Chapter 9), each a `lax.scan`, with f and g linearised by
        `jax.jacfwd`. The process noise lets the estimate follow the data rather than
        one simulation of n steps: over a long head, a model that drifts from the data
        (slightly wrong parameters, unmodelled disturbances) biases the least-squares x0
        much more than the smoothed one, and the problem stays well conditioned. The
        smoothed mean and covariance at k = 0 are the estimate. Unobservable directions
        stay at the prior (mean `x0`) with the prior's variance; a warning names them.
        One pass, no iteration: jax-sysid's `learn_x0` runs the same EKF and RTS pair
        (optionally repeated, then refined by L-BFGS); `"lsq"` here is the refinement to
        the exact least-squares optimum, by Gauss-Newton rather than L-BFGS.

    **Arguments:**

    - `model`, `theta`: a `Model` and its parameters (any pytree, as for `simulate`).
    - `u`: inputs (T, n_u); `z`: measured outputs (T_z <= T, n_z). Only u[:n] and z[:n]
        are used, so a whole test record can be passed together with the protocol's n.
    - `n`: the number of head samples, 1 <= n <= T_z; default T_z.
    - `method`: `"lsq"` or `"smoother"`.
    - `x0`: the starting guess (lsq) or the prior mean (smoother), shape (n_x,). Default
        z[0] where the model has the default `observe` (z = x, `Model(step)` without
        one); otherwise it is required,
        since the state's size is known only from it (zeros are the usual neutral guess,
        a typical state of the system a better one where f or g are singular at 0).
    - `weight`: Q of eq. (4), as for `loss`. The smoother reads it as the inverse of the
        measurement noise covariance when `measurement_noise` is not given.
    - `solver`: for `"lsq"`, the least-squares solver (default `GaussNewton()`; any
        solver of `fit` works).
    - `process_noise`, `measurement_noise`, `prior_covariance`: for `"smoother"`, the
        covariances of the process noise w_k (n_x), of the measurement noise v_k (n_z) and
        of the prior on x0 around `x0` (n_x): each a scalar (times I), a vector of
        variances or a matrix. Defaults, from the head's scales (s_z the root-mean-square
        of each output over z[:n]; s_x the same of each state, over z[:n] when z = x,
        else over a simulation of the head from `x0` until its outputs leave the measured
        ones' range by 100 times their RMS (an unstable model's grows without bound), 1
        where zero): measurement noise
        Q^{-1} when `weight` is given, else (0.01 s_z)^2 (1 % noise); process noise
        (0.001 s_x)^2 per step; prior (100 s_x)^2 (broad). The smoother's covariance
        reflects these assumptions: give `measurement_noise` for calibrated ones. In
        float32 the defaults' range (1e8 between the prior's and the noise's variances)
        costs the smoother digits: its x0 can miss float64's by a few of float64's
        standard errors, and its covariance comes out inflated (larger than float64's);
        give covariances closer in scale, or use `"lsq"` (accurate to float32 there).
    - `t`: the sample times (T,) of the record, for a model of time-stamped records
        (`Model.from_ode(rhs, dt=None)`); t[:n] is used with the head.
    - `missing`: `"mask"` takes NaN entries of the head's z as missing samples, left out
        of the cost (`"lsq"`) or of the filter's updates (`"smoother"`; then `x0` is
        needed where z[0] has one); `"raise"` (default) refuses them.
    - `estimate`: `"lsq"` only: an (n_x,) boolean mask, True for the entries to
        estimate; the others are known and keep their value in `x0` (variance 0), as
        with `fit(estimate_x0=mask)` (MATLAB's `InitialStates(i).Fixed`); a mask that
        holds every entry returns `x0` as given (stop reason `converged`: there is
        nothing to move). Default: every
        entry. `FitResult.predict` takes it too, with the same default: it estimates
        every entry of a new record's x0, also those the fit held (their values were
        the fitted records'); pass `estimate=result.x0_estimated` there to hold them, at
        their values in `x0=`.
    - `bounds`: `"lsq"` only: `(lower, upper)` bounds on the estimated entries, each
        None, a number or (n_x,) (-inf / inf unbounded), as `fit(x0_bounds=...)` (MATLAB's
        `findstates` keeps a model's `InitialStates(i).Minimum` and `Maximum`); a guess
        outside them is clipped into them, with a warning. Default: none.

    **Returns:**

    An `X0Estimate` (x0, covariance, std, identifiable, loss, method, n, and the solver's
    stop reason or the smoother's states).

    **Raises:**

    `ValueError` for a method other than "lsq" or "smoother", n outside 1..T_z, more
    outputs than inputs (T_z > T), arrays of the wrong shape, a missing `x0` for a partly
    observed state, smoother arguments with "lsq" (or `solver` with "smoother"), or when
    the model's simulation of the head from the estimate is not finite (theta makes it
    blow up there); `TypeError` for a non-integer n.
    """
    return _estimate(
        model,
        theta,
        u,
        z,
        n=n,
        method=method,
        x0=x0,
        weight=weight,
        solver=solver,
        process_noise=process_noise,
        measurement_noise=measurement_noise,
        prior_covariance=prior_covariance,
        stacklevel=3,
        t=t,
        missing=missing,
        estimate=estimate,
        bounds=bounds,
    )[0]


def _estimate(
    model,
    theta,
    u,
    z,
    *,
    n,
    method,
    x0,
    weight,
    solver,
    process_noise,
    measurement_noise,
    prior_covariance,
    stacklevel,
    t=None,
    record=None,
    missing="raise",
    z_name="z",
    estimate=None,
    bounds=None,
):
    """`estimate_x0`, with its warnings attributed `stacklevel` frames up. With `record`
    (the whole record's `(u, t)`, whose head is `u`), also the record simulated from the
    estimate, `(x, z)` (for `predict`); else None. Returns (`X0Estimate`, that).
    `z_name`: the caller's name of z, for the errors."""
    if method not in METHODS:
        raise ValueError(f"`method` must be 'lsq' or 'smoother', got {method!r}.")
    check_tree(theta, "theta")
    check_outside_transformations(
        theta, u, z, x0, weight, record, name="`predict`" if record is not None else "`estimate_x0`"
    )
    n = _check_head(u, z, n, z_name)
    t = head_times(t, np.shape(u)[0], n)
    u, z = u[:n], z[:n]
    if method == "lsq":
        given = {
            "process_noise": process_noise,
            "measurement_noise": measurement_noise,
            "prior_covariance": prior_covariance,
        }
        extra = [k for k, v in given.items() if v is not None]
        if extra:
            raise ValueError(
                f"{', '.join(f'`{k}`' for k in extra)} "
                f"{'apply' if len(extra) > 1 else 'applies'} only to method='smoother'; "
                "method='lsq' weighs the outputs by `weight`."
            )
    elif solver is not None:
        raise ValueError("`solver` only applies to method='lsq'.")
    if estimate is not None and method != "lsq":
        raise ValueError(
            "`estimate` (a mask of the x0 entries to estimate) applies to method='lsq'; the "
            "smoother holds an entry known through a small `prior_covariance` for it."
        )
    if bounds is not None and method != "lsq":
        raise ValueError(
            "`bounds` (on x0) applies to method='lsq'; the smoother's estimate is a "
            "posterior mean, not a bounded least-squares solution."
        )
    if method == "smoother" and missing != "mask" and is_concrete(z):
        try:
            gaps = np.isnan(np.asarray(z, float)).any()
        except (TypeError, ValueError):  # (not numbers: `check_data` names it)
            gaps = False
        if gaps:
            raise ValueError(
                f'`{z_name}` contains NaN: pass missing="mask" to treat NaN as a missing '
                "sample (the filter then leaves it out of its update)."
            )
    defaulted = x0 is None
    if x0 is None:
        if not model.observes_state:
            raise ValueError(
                "`x0` (the starting guess, shape (n_x,)) is needed: the model has an "
                "`observe` of its own (not the default z = x of `Model(step)`), so the "
                "state's size is known only from x0. Zeros "
                "are the neutral guess; a typical state of the system (the fitted x0 of the "
                "training data, say) is better where the model is singular at zero."
            )
        x0 = z[0]
        if np.any(np.isinf(np.asarray(x0, float))):  # (not a missing sample: a bad value)
            raise ValueError(
                f"`{z_name}` contains inf values (in its first row, the default guess of "
                "`x0`): outputs must be finite, or NaN for a missing sample with "
                'missing="mask".'
            )
        if not np.all(np.isfinite(np.asarray(x0, float))):
            raise ValueError(
                "`x0` (the starting guess, shape (n_x,)) is needed: z[0], the default where "
                "the model observes its whole state, has a missing sample."
            )
    if np.ndim(x0) != 1:
        raise ValueError(f"`x0` must have shape (n_x,) (one record), got {np.shape(x0)}.")
    try:
        data = check_data(model, theta, x0, u, z, weight, missing=missing, t=t, z_name=z_name)
    except ValueError as err:
        if (
            not defaulted
            or (getattr(model, "timed", False) and t is None)
            or "shape" not in str(err)
        ):
            raise  # (a time-stamped model without its times, NaN: not the guess's fault)
        # The state's size came from z's columns: a wrong column count surfaces as a
        # wrong state size deep in the model.
        raise ValueError(
            f"{err}\n(`x0` was not given: its guess is the first row of `{z_name}`, so the "
            f"state's size is `{z_name}`'s number of columns, {np.shape(z)[-1]}; check that "
            f"`{z_name}` has the model's outputs as columns, or give `x0`.)"
        ) from err
    guess = np.asarray(data.x0)
    if estimate is not None:
        if estimate is True or estimate is False:
            raise TypeError(
                f"`estimate` must be an (n_x,) = ({guess.size},) boolean mask or None (every "
                f"entry), got {estimate!r}."
            )
        mask = np.asarray(estimate)
        if mask.dtype != bool or mask.shape != guess.shape:
            raise ValueError(
                f"`estimate` must be an (n_x,) = ({guess.size},) boolean mask, True for the "
                f"entries to estimate, got {estimate!r}."
            )
        if defaulted and not mask.all():
            raise ValueError(
                "`estimate` holds some x0 entries at their value in `x0`: give `x0` (the "
                "known values of the held entries, guesses for the others)."
            )
        estimate = None if mask.all() else mask

    stop_reason, kalman, e, ok, sim, at_bound = None, None, None, None, None, None
    if guess.size == 0:  # a model without state (n_x = 0): nothing to estimate
        x0_hat, cov, loss, ok = guess, np.zeros((0, 0), guess.dtype), None, np.zeros(0, bool)
    elif method == "lsq" and estimate is not None and not estimate.any():
        # Every entry held: x0 as given, the minimum over no variables (a first-order
        # test over none holds), known exactly (as a held entry of a partial mask).
        x0_hat, cov, loss = guess, np.zeros((guess.size, guess.size), guess.dtype), None
        ok, stop_reason = np.ones(guess.size, bool), RESULTS.converged
    elif method == "lsq":
        whole = None
        if record is not None:  # the whole record, simulated in the x0 solve's call
            whole = check_data(model, theta, guess, record[0], t=record[1]).u
            if whole.dtype != data.u.dtype:  # simulated apart, in its own dtype
                whole = None
        box = None
        if bounds is not None:
            shape = (1, guess.size)
            box = check_x0_bounds(bounds, shape, guess.dtype, False, "bounds", estimate)
        if box is not None:
            data = data._replace(x0=clip_x0(guess, box, "bounds", "estimate", stacklevel)[0])
        r = solve_x0(data, solver, record=whole, estimate=estimate, bounds=box)
        ok, sim = r.identifiable, r.record
        x0_hat = r.x0[0]
        if box is not None:
            lower, upper = (np.asarray(b)[0] for b in box)
            at_bound = np.asarray((x0_hat <= lower) | (x0_hat >= upper))
        cov = np.asarray(r.covariance[0], guess.dtype)
        loss = np.asarray(r.loss)
        stop_reason = r.stop_reason
        e = r.residuals[0]  # the head simulated from x0_hat, minus z
    else:
        kalman = kalman_path(
            data, model.observes_state, process_noise, measurement_noise, prior_covariance
        )
        x0_hat = kalman.smoothed_mean[0]
        cov = np.asarray(kalman.smoothed_covariance[0], guess.dtype)
        loss = None

    x0_hat = x0_hat.astype(guess.dtype)
    # (e is NaN at a missing sample)
    measured = np.isfinite(np.asarray(z, np.float64)).reshape(np.shape(data.z))
    if e is None:
        _, zhat = simulate_impl(data.model, data.theta, jnp.asarray(x0_hat), data.u, False)
        e = np.asarray(zhat, np.float64) - np.asarray(data.z, np.float64)
        e = np.where(measured, e, np.nan)
    if not (np.all(np.isfinite(x0_hat)) and np.all(np.isfinite(e)[measured])):
        raise ValueError(
            f"simulating the model over the first n = {n} samples from the estimated x0 "
            f"({x0_hat}) gives NaN or inf: with these parameters the model blows up over "
            "the head (or the starting guess `x0` is far off). Check theta, or use a "
            "shorter head."
        )
    if method == "smoother" and measurement_noise is None and weight is None:
        _warn_default_noise(e, z, n, stacklevel + 1)
    if loss is None:  # C of eq. (5) over the head: the mean over k of |Q^{1/2} e_k|^2
        # (a missing entry of e counts as zero, as in the fit's loss: `_cost.Cost.local`)
        e0 = np.where(measured, e, 0.0)
        weighted = weigh(jnp.asarray(e0), check_cost(data, None, 1.0).sqrt_weight())
        loss = np.asarray(np.mean(np.sum(np.square(np.asarray(weighted)), axis=1)), guess.dtype)

    if ok is None:
        ok = _observable(data._replace(x0=jnp.asarray(x0_hat)), estimate)
    if not np.all(ok):
        labels = model_labels(getattr(model, "states", None), len(ok)) or range(len(ok))
        bad = [f"x0[{labels[i]}]" for i in np.flatnonzero(~ok)]
        then = (
            "along that direction the estimate stays at the starting guess `x0` in "
            "Gauss-Newton's variables, each entry scaled by the norm of its Jacobian column "
            "(an entry that reaches no output keeps its guess), and their std is inf"
            if method == "lsq"
            else "along that direction the smoother leaves the estimate at the prior (mean `x0`, "
            "`prior_covariance`)"
        )
        warn(
            f"initial state entries {bad} are not determined by the first n = {n} outputs "
            "with these parameters (not observable from this head: a change of them, alone "
            f"or together, leaves those outputs unchanged): {then}.",
            stacklevel=stacklevel,
        )
    if stop_reason is not None and not is_success(stop_reason):
        warn(
            f"estimate_x0: the least-squares solver stopped: {RESULTS[stop_reason]}",
            stacklevel=stacklevel,
        )
    std = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
    return X0Estimate(
        x0=x0_hat,
        covariance=cov,
        std=std,
        identifiable=ok,
        loss=np.asarray(loss),
        method=method,
        n=n,
        stop_reason=stop_reason,
        kalman=kalman,
        states=model.states,
        head=np.asarray(z) if is_concrete(z) else None,
        at_bound=at_bound,
    ), sim


# The default measurement noise of the smoother is called too small where the head's
# residuals from its estimate are this many times it (RMS, some output). Its std scales
# about with the noise: at 3 a noise 2.3 times the default left the std half the spread
# of the estimates, unwarned. At the default noise the ratio is about sqrt(1 - n_x / n)
# (0.97 at n = 40) with a sampling spread of 1 / sqrt(2 n) (0.11): 1.5 is 4 of those
# above it.
NOISE_MISMATCH = 1.5


def _warn_default_noise(e, z, n, stacklevel):
    """Warn where the smoother's default measurement noise, 1 % of each output's RMS over
    the head (`_x0_smoother.MEASUREMENT_NOISE_REL`), is far below the residuals of the
    head simulated from its estimate: its covariance then assumes data several times
    more precise than they are, and its std is too small (4 times, on a record of noise
    0.01 at an output RMS of 0.19)."""
    assumed = MEASUREMENT_NOISE_REL * _rms(np.asarray(z, np.float64))
    e = np.asarray(e, np.float64)
    seen = np.isfinite(e)
    rms = np.sqrt(np.sum(np.where(seen, e * e, 0.0), axis=0) / np.maximum(seen.sum(axis=0), 1))
    ratio = float(np.max(rms / assumed))
    if n >= 5 and ratio > NOISE_MISMATCH:
        warn(
            f"estimate_x0(method='smoother') assumed a measurement noise of 1 % of each "
            f"output's RMS over the head, and the head's residuals from its estimate are "
            f"{ratio:.3g} times that: its std (covariance) assumes data more precise than "
            "these, and is too small. Pass `measurement_noise` (e.g. the fit's residual "
            "variance, as `FitResult.predict` does) or `weight`, or use method='lsq', "
            "whose std is estimated from the residuals.",
            stacklevel=stacklevel,
        )


def predict(
    model,
    theta: PyTree,
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T_z n_z"],
    n: int,
    *,
    method: str = "lsq",
    t: Float[ArrayLike, " T"] | None = None,
    **kwargs,
) -> Prediction:
    """Simulate a record from an initial state estimated from its first n outputs: the
    benchmark protocol's prediction (the model may use the whole input and z[:n]). This
    is an open-loop simulation (MATLAB's `compare` with an estimated initial state). For an
    output-error model (no noise model, as `idnlgrey`) MATLAB's K-step-ahead `predict` is
    this same simulation whatever K; `predict_ahead` corrects the state from the outputs
    with a Kalman filter, given a process noise.

    **Arguments:**

    - `model`, `theta`: a `Model` and its parameters.
    - `u`: the record's inputs (T, n_u).
    - `z`: its measured outputs, the whole record or only the head (n <= T_z <= T rows);
        only z[:n] is used.
    - `n`: the number of head samples x0 is estimated from (EMPS 20, Cascaded Tanks 5,
        Silverbox and Wiener-Hammerstein 50 under the protocol).
    - `method` and further keyword arguments: as for `estimate_x0` (`x0=` the starting
        guess, `weight=`, the smoother's noise covariances, ...).
    - `t`: the record's sample times (T,), for a model of time-stamped records
        (`Model.from_ode(rhs, dt=None)`).

    **Returns:**

    A `Prediction(z, x, x0, estimate)`: the simulated outputs and states over the whole
    record, x0 and its `X0Estimate`.

    **Example:**

    ```python
    test = oneshot_jax.datasets.load_cascaded_tanks().test
    pred = oneshot_jax.predict(model, theta, test.u[:, None], test.y[:, None], test.n, x0=x0_guess)
    scores = oneshot_jax.metrics.benchmark_scores(test.y, pred.z, test.n)
    ```
    """
    if n is None:  # (`estimate_x0` takes None for all of z; the protocol needs its n)
        raise TypeError(
            "`n` (the number of head samples x0 is estimated from) must be an integer, got None."
        )
    return predict_impl(model, theta, u, z, n, method, kwargs, stacklevel=3, t=t)


def predict_impl(model, theta, u, z, n, method, kwargs, *, stacklevel, t=None, z_name="z"):
    """`predict`, with its warnings attributed `stacklevel` frames up (`FitResult.predict`
    calls it too, its `z` named `z_name`)."""
    n = _check_head(u, z, n, z_name)
    head_times(t, np.shape(u)[0], n)  # `t`'s shape checked before the estimate
    options = dict(
        x0=None,
        weight=None,
        solver=None,
        process_noise=None,
        measurement_noise=None,
        prior_covariance=None,
        missing="raise",
        estimate=None,
        bounds=None,
    )
    unknown = sorted(set(kwargs) - set(options))
    if unknown:
        raise TypeError(
            f"unexpected keyword arguments {unknown}; `predict` takes those of "
            f"`estimate_x0`: {', '.join(options)}."
        )
    options.update(kwargs)
    est, sim = _estimate(
        model,
        theta,
        u,
        z[:n],
        n=n,
        method=method,
        stacklevel=stacklevel + 1,
        t=t,
        record=(u, t),
        z_name=z_name,
        **options,
    )
    if sim is None:  # the smoother's estimate
        data = check_data(model, theta, est.x0, u, t=t)
        sim = simulate_impl(data.model, data.theta, data.x0, data.u, False)
    x, zhat = sim
    zhat = np.asarray(zhat)
    _warn_not_finite(zhat)
    return Prediction(zhat, np.asarray(x), est.x0, est)


def _warn_not_finite(zhat):
    """Warn where a prediction (T, n_z) is not finite: returned as it is, with no word, its
    NaN samples showed only as a FIT of NaN."""
    bad = ~np.isfinite(zhat).reshape(len(zhat), -1).all(axis=1)
    if bad.any():
        warn(
            f"the prediction is not finite from sample {int(np.argmax(bad))} on "
            f"({int(bad.sum())} of {len(bad)} samples NaN or inf): simulated from the "
            "estimated x0 with these parameters, the model leaves its domain (a square root "
            "of a negative level, say) or blows up on this record.",
            RuntimeWarning,
            stacklevel=2 + frames_to_user(),
        )
