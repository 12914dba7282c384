"""K-step-ahead prediction: each output predicted from the measurements up to K samples
before it, by an extended Kalman filter that corrects the state from the outputs
(`predict_ahead`, MATLAB's `predict(sys, data, K)` for a model with a noise model).

The filter is the one of `estimate_x0(method="smoother")` (`_x0_smoother.ekf_forward`,
Särkkä, *Bayesian Filtering and Smoothing*, 2013, Algorithm 5.4) over the whole record;
from each filtered mean x[j|j] the model's step runs K times (all starts side by side,
one `vmap` per step), so that

    x[k|k-K] = f^K(x[k-K|k-K]),   zhat[k|k-K] = g(x[k|k-K], u[k]),

and for k < K, before any measurement counts, x[k|-1] = f^k(x0): the simulation from the
prior mean. K = 1 is the filter's one-step prediction (its innovations are z - zhat);
K >= T is the simulation from x0, the output-error prediction of `simulate`.

The covariance of each prediction follows the same K steps from the filtered covariance
P[k-K|k-K] (from the prior's P0 before sample K), with F_j the Jacobian of the step at
the propagated mean and H_k that of g at x[k|k-K] (the EKF's prediction step, Särkkä
2013, Algorithm 5.4, applied K times):

    P[j+1|k-K] = F_j P[j|k-K] F_j^T + Q_w,   S[k|k-K] = H_k P[k|k-K] H_k^T + R,

S the covariance of the prediction error z[k] - zhat[k|k-K] under the filter's noise
model; K = 1 gives the filter's innovation covariance.

`estimate_process_noise` sizes Q_w = q shape by the likelihood of the outputs under the
same filter: its K = 1 innovations are independent and N(0, S_k) (the prediction-error
decomposition of the likelihood, Särkkä 2013, Chapter 12), a one-dimensional search
over q.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._caller_warnings import warn
from ._checks import as_float, check_data, check_tree, is_concrete
from ._covariance import carried_variance
from ._initial_state import several_records
from ._jit import jit
from ._model import model_labels
from ._x0_smoother import _smoother_defaults, ekf_forward, with_gaps


class AheadPrediction(NamedTuple):
    """What `predict_ahead` returns.

    - `z`: (T, n_z) the K-step-ahead predictions zhat[k|k-K] of the outputs.
    - `x`: (T, n_x) the predicted states x[k|k-K].
    - `filtered`: (T, n_x) the filter's means x[k|k], given z[0..k].
    - `K`: the horizon (at most T: the simulation from `x0`).
    - `std`: (T, n_z) the standard deviation of each prediction's error z[k] -
        zhat[k|k-K] under the filter's noise model (the square root of the diagonal of
        S[k|k-K] in the module's docstring: the state's uncertainty K steps on, plus the
        measurement noise). An interval zhat +- 1.96 std holds a new measurement with
        probability 95 % where the process and measurement noise are the ones given; the
        uncertainty of theta is not in it (`FitResult.predict_ahead(parameters=True)`
        adds it).
    - `outputs`: the model's names of the outputs (`Model(outputs=...)`), which
        `plot.compare` shows; None without them.
    """

    z: np.ndarray
    x: np.ndarray
    filtered: np.ndarray
    K: int
    std: np.ndarray
    outputs: tuple | None = None

    def __str__(self) -> str:
        return (
            f"{self.K}-step-ahead prediction of {np.shape(self.z)[0]} samples (`z` "
            f"{np.shape(self.z)}, `x` {np.shape(self.x)}, `filtered` "
            f"{np.shape(self.filtered)}, `std` {np.shape(self.std)})"
        )

    __repr__ = __str__


def _ahead_impl(model, theta, m0, P0, Qp, R, u, z, K):
    """`AheadPrediction`'s z, x, filtered means and std (the module's docstring), traced:
    the filter's forward pass, then K steps of every start's mean and covariance at
    once."""
    (mf, Pf, _, _, _), (m_last, P_last), _ = ekf_forward(model, theta, m0, P0, Qp, R, u, z)
    filtered = jnp.concatenate([mf, m_last[None]])  # (T, n_x)
    covariances = jnp.concatenate([Pf, P_last[None]])
    T = u.shape[0]
    steps = model.step_inputs(u)  # (T-1, ...): the inputs of x[j] -> x[j+1]
    k = jnp.arange(T)
    first = k - K  # the sample each prediction starts from (before 0: the prior)
    started = (first >= 0)[:, None]
    X = jnp.where(started, filtered[jnp.clip(first, 0, T - 1)], m0[None])
    P = jnp.where(started[..., None], covariances[jnp.clip(first, 0, T - 1)], P0[None])

    def predict(x, P, u_step):  # the EKF's prediction step
        F = jax.jacfwd(model.step)(x, u_step, theta)
        P = F @ P @ F.T + Qp
        return model.step(x, u_step, theta), 0.5 * (P + P.T)

    def one(i, carry):  # the (i+1)-th step of every start that has reached sample 0
        X, P = carry
        j = first + i
        moved, P_moved = jax.vmap(predict, in_axes=(0, 0, 0))(X, P, steps[jnp.clip(j, 0, T - 2)])
        on = j >= 0
        return jnp.where(on[:, None], moved, X), jnp.where(on[:, None, None], P_moved, P)

    X, P = jax.lax.fori_loop(0, K, one, (X, P)) if T > 1 else (X, P)
    Z = jax.vmap(model.observe, in_axes=(0, 0, None))(X, u, theta)
    H = jax.vmap(jax.jacfwd(model.observe), in_axes=(0, 0, None))(X, u, theta)
    S = jnp.einsum("kia,kab,kjb->kij", H, P, H) + R
    std = jnp.sqrt(jnp.maximum(jnp.diagonal(S, axis1=1, axis2=2), 0.0))
    return Z, X, filtered, std


_ahead = jit(_ahead_impl)


@jit
def _ahead_jacobian(model, unravel, flat, free, m0, P0, Qp, R, u, z, K):
    """d zhat[k|k-K] / d theta (T, n_z, p) over theta's free entries `free` (an int array
    into theta's flat parameters `flat`, `unravel` their inverse), by forward-mode
    differentiation through the filter and its K steps."""
    base = jnp.asarray(flat, m0.dtype)

    def predictions(p):
        theta = unravel(base.at[free].set(p))
        return _ahead_impl(model, theta, m0, P0, Qp, R, u, z, K)[0]

    return jax.jacfwd(predictions)(base[free])


def _horizon(K, T) -> int:
    if hasattr(K, "item") and np.shape(K) == () and is_concrete(K):
        K = K.item()  # (a 0-d array)
    if isinstance(K, (bool, np.bool_)) or not (
        isinstance(K, (int, np.integer)) or (isinstance(K, float) and math.isinf(K))
    ):
        raise TypeError(f"`K` must be an integer >= 1 or math.inf, got {K!r}.")
    if K < 1:
        raise ValueError(f"`K` must be an integer >= 1 or math.inf, got {K!r}.")
    return int(min(K, T))


def predict_ahead(
    model,
    theta: PyTree,
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    K,
    *,
    x0: Float[ArrayLike, " n_x"] | None = None,
    process_noise,
    measurement_noise=None,
    prior_covariance=None,
    weight=None,
    t: Float[ArrayLike, " T"] | None = None,
    missing: str = "raise",
) -> AheadPrediction:
    """Predict each output of a record from the measurements up to K samples before it
    (MATLAB's `predict(sys, data, K)`; `compare(data, sys, K)` plots it): an extended
    Kalman filter corrects the state from the outputs z[0..k-K], and the model runs on
    for K steps from there (the module's docstring). The simulation error that `fit`
    minimises is an output-error model's, which has no process noise: its K-step
    prediction is the simulation whatever K (`predict`). With the process noise given
    here, short horizons show how well the model predicts where it is corrected by the
    data, long ones how it drifts.

    **Arguments:**

    - `model`, `theta`: a `Model` and its parameters.
    - `u`: the record's inputs (T, n_u); `z`: its measured outputs (T, n_z).
    - `K`: the horizon, an integer >= 1 (K >= T, or `math.inf`: the simulation from
        `x0`).
    - `x0`: the prior mean of the initial state (n_x,); default z[0] where the model has
        the default `observe` (z = x), else required.
    - `process_noise`: the covariance of the process noise w_k per step (n_x): a scalar
        (times I), a vector of variances or a matrix, or the `ProcessNoise` that
        `estimate_process_noise` returns (its `covariance`). Required: it sets how far the filter
        trusts the data over the model (0 trusts the model: each prediction is then a
        simulation from the initial state that the data up to K samples before it
        indicate).
    - `measurement_noise`, `prior_covariance`: the covariances of the measurement noise
        (n_z) and of the prior on x0 around `x0` (n_x), with the defaults of
        `estimate_x0(method="smoother")` (from `weight` as Q^{-1}, else (0.01 s_z)^2; the
        prior (100 s_x)^2, broad). `FitResult.predict_ahead` takes the fit's noise
        variance instead.
    - `weight`: Q of eq. (4), read as the inverse of the measurement noise covariance
        where `measurement_noise` is not given.
    - `t`: the sample times (T,), for a model of time-stamped records.
    - `missing`: `"mask"` takes NaN entries of z as missing measurements (no correction
        from them); `"raise"` (default) refuses them.

    **Returns:** an `AheadPrediction` (`z`, `x`, `filtered`, `K`, `std`).

    **Raises:** `TypeError` for a K that is not an integer (or inf), or a `process_noise`
    not given; `ValueError` for K < 1, arrays of the wrong shape, covariances that are not
    ones, NaN in z without `missing="mask"`, and a filter that breaks down in its
    arithmetic (NaN predictions: covariances of very different scales).
    """
    return predict_ahead_impl(
        model, theta, u, z, K, x0, process_noise, measurement_noise, prior_covariance, weight,
        t, missing,
    )  # fmt: skip


def predict_ahead_impl(
    model,
    theta,
    u,
    z,
    K,
    x0,
    process_noise,
    measurement_noise,
    prior_covariance,
    weight,
    t,
    missing,
    parameters=None,
):
    """`predict_ahead` with its arguments positional; `parameters`: None, or (fixed,
    covariance), the flat mask of theta's held entries and Sigma over the free ones:
    `std` then holds theta's uncertainty too, J Sigma J^T per sample to first order, J =
    d zhat[k|k-K] / d theta over the free entries (`_ahead_jacobian`; the prior mean
    held), inf where a prediction takes an unknown entry of Sigma
    (`_covariance.carried_variance`). Of `FitResult.predict_ahead(parameters=True)`."""
    if process_noise is None:
        raise TypeError(
            "`process_noise` must be given (a variance per step): it sets how far the "
            "filter trusts the data over the model."
        )
    data, guess, covariances, zs = _filter_inputs(
        model, theta, u, z, x0, process_noise, measurement_noise, prior_covariance, weight, t,
        missing,
    )  # fmt: skip
    K = _horizon(K, int(np.shape(data.u)[0]))
    # (K traced: one program for every horizon)
    args = (jnp.asarray(guess), *covariances, jnp.asarray(data.u), zs, jnp.asarray(K))
    Z, X, filtered, std = _ahead(data.model, data.theta, *args)
    bad = np.isnan(np.asarray(Z)).any(axis=-1) | np.isnan(np.asarray(std)).any(axis=-1)
    if bad.any():
        raise ValueError(
            f"predict_ahead: the filter's predictions are NaN from sample "
            f"{int(np.argmax(bad))} on ({int(bad.sum())} of {bad.size}): the filter broke "
            "down in its arithmetic (covariances of very different scales: a "
            "`prior_covariance` or `process_noise` far broader than the states' scale, or "
            "a model that blows up over the record). Give `prior_covariance` (x0's "
            "uncertainty in the states' units) and check `theta`."
        )
    if parameters is not None:
        fixed, covariance = parameters
        free = np.flatnonzero(~np.asarray(fixed, bool))
        flat, unravel = _pytree.ravel(data.theta)
        J = _ahead_jacobian(data.model, unravel, flat, free, *args)
        var = carried_variance(np.asarray(J, np.float64), covariance, free.size)
        std = np.sqrt(np.square(np.asarray(std, np.float64)) + var).astype(std.dtype)
    names = model_labels(getattr(model, "outputs", None), np.shape(Z)[-1])
    return AheadPrediction(
        np.asarray(Z),
        np.asarray(X),
        np.asarray(filtered),
        K,
        np.asarray(std),
        None if names is None else tuple(names),
    )


def _filter_inputs(
    model,
    theta,
    u,
    z,
    x0,
    process_noise,
    measurement_noise,
    prior_covariance,
    weight,
    t,
    missing,
    process_name="process_noise",
):
    """The checked data of the filter (`_checks.check_data`), its prior mean, its
    covariances (P0, Q_w, R) in the data's dtype and z with NaN at missing samples
    (`process_name`: the argument that gave `process_noise`)."""
    check_tree(theta, "theta")
    if isinstance(process_noise, ProcessNoise):  # (`estimate_process_noise`'s estimate)
        process_noise = process_noise.covariance
    if missing not in ("raise", "mask"):
        raise ValueError(f'`missing` must be "raise" or "mask", got {missing!r}.')
    for name, a, shape in (("u", u, "(T, n_u)"), ("z", z, "(T, n_z)")):
        if several_records(a) or np.ndim(a) == 3:
            raise ValueError(
                f"`{name}` must have shape {shape} (one record), got "
                + (f"a list of {len(a)} records" if several_records(a) else f"{np.shape(a)}")
                + " (several records: one call each, or the `FitResult` method of the same "
                "name, which takes them all)."
            )
    defaulted = x0 is None
    if defaulted:
        if not model.observes_state:
            raise ValueError(
                "`x0` (the prior mean of the initial state, shape (n_x,)) is needed: the "
                "model has an `observe` of its own, so the state's size is known only "
                "from x0."
            )
        if np.ndim(z) != 2 or np.shape(z)[0] == 0:
            raise ValueError(
                f"`z` must have shape (T, n_z) with T >= 1, got {np.shape(z)} (`x0` "
                "defaults to z[0], the model observing its state)."
            )
        x0 = np.asarray(z)[0]
    if np.ndim(x0) != 1:
        raise ValueError(f"`x0` must have shape (n_x,) (one record), got {np.shape(x0)}.")
    if missing == "mask" and is_concrete(x0) and not np.all(np.isfinite(np.asarray(x0))):
        raise ValueError("`x0` must be finite: give it where z[0] has a missing sample.")
    try:
        data = check_data(model, theta, x0, u, z, weight, missing=missing, t=t)
    except ValueError as err:
        if not defaulted:
            raise
        raise ValueError(
            f"{err} (`x0` was not given: it defaults to z[0], so `z` needs one column per "
            "state of the model; give `x0` of shape (n_x,) otherwise.)"
        ) from err
    guess = np.asarray(data.x0)
    zs = with_gaps(data)  # (missing samples as NaN: the filter leaves them out)
    P0, Qp, R = _smoother_defaults(
        data._replace(z=zs),
        model.observes_state,
        guess,
        process_noise,
        measurement_noise,
        prior_covariance,
        process_name,
    )
    dtype = data.x0.dtype
    return data, guess, tuple(jnp.asarray(a, dtype) for a in (P0, Qp, R)), zs


class ProcessNoise(NamedTuple):
    """What `estimate_process_noise` returns.

    - `covariance`: (n_x, n_x) the estimate, `scale` times `shape`.
    - `scale`: the scale q of `shape` that maximises the likelihood of the outputs.
    - `log_likelihood`: the log-likelihood of the outputs there (of the filter's
        innovations, as `estimate_process_noise` describes it).
    - `scales`, `log_likelihoods`: the grid searched and the log-likelihood at each.
    - `interior`: False where the highest likelihood of the grid is at its end (the
        estimate is then that end: the data ask for less, or more, process noise than
        the grid holds), or where it is the same at every scale (the outputs do not see
        the noise `shape` describes: q is not determined).
    """

    covariance: np.ndarray
    scale: float
    log_likelihood: float
    scales: np.ndarray
    log_likelihoods: np.ndarray
    interior: bool

    def __str__(self) -> str:
        """A few lines for `print`: the scale, its likelihood and where it lies in the grid
        (the fields hold the arrays)."""
        where = (
            "inside the grid"
            if self.interior
            else "at the grid's end: the data ask for less, or more, than the grid holds"
        )
        diagonal = np.diag(np.asarray(self.covariance))
        return (
            f"process noise q = {self.scale:.4g} times the shape (log-likelihood "
            f"{self.log_likelihood:.6g}, {where}; grid {float(self.scales[0]):.3g} .. "
            f"{float(self.scales[-1]):.3g}, {len(self.scales)} points)\n"
            f"  covariance diagonal [{', '.join(f'{v:.4g}' for v in diagonal)}]"
        )

    __repr__ = __str__


def _grid(scales):
    """The grid of scales, checked: increasing, positive, finite, at least 3."""
    if np.asarray(scales).dtype == bool:
        raise TypeError(f"`scales` must hold numbers, got {scales!r}.")
    grid = np.asarray(as_float(scales, "scales"), np.float64)
    if (
        grid.ndim != 1
        or grid.size < 3
        or not np.all(np.isfinite(grid))
        or not np.all(grid > 0)
        or np.any(np.diff(grid) <= 0)
    ):
        raise ValueError(
            "`scales` must be an increasing grid of at least 3 finite positive numbers, got "
            f"{scales!r}."
        )
    return grid


@jit
def _log_likelihood(model, theta, m0, P0, Qp, R, u, z):
    """The log-likelihood of the outputs under the filter's model (`ekf_forward`'s)."""
    return ekf_forward(model, theta, m0, P0, Qp, R, u, z)[2]


def estimate_process_noise(
    model,
    theta: PyTree,
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    shape,
    *,
    x0: Float[ArrayLike, " n_x"] | None = None,
    measurement_noise=None,
    prior_covariance=None,
    weight=None,
    t: Float[ArrayLike, " T"] | None = None,
    missing: str = "raise",
    scales=None,
) -> ProcessNoise:
    """The process noise covariance q `shape` of the extended Kalman filter of
    `predict_ahead` whose scale q maximises the likelihood of the record's outputs, the
    other covariances given (the prediction-error decomposition: the one-step
    innovations e_k = z[k] - g(x[k|k-1]) independent and N(0, S_k), S_k = H_k P[k|k-1]
    H_k^T + R, their log-likelihood -1/2 sum_k (log det S_k + e_k^T S_k^{-1} e_k +
    n_z log 2 pi)). A grid of scales, then a golden-section search in log q between the
    best one's neighbours.

    **Arguments:**

    - `model`, `theta`, `u`, `z`, `x0`, `measurement_noise`, `prior_covariance`,
        `weight`, `t`, `missing`: as for `predict_ahead`.
    - `shape`: the covariance's shape (n_x): a scalar (times I), a vector of variances or
        a matrix, e.g. `[0, 1]` for noise that enters through the second state only.
    - `scales`: the grid of q (increasing, positive); default 10^-12 .. 10^4, 65 points.

    **Returns:** a `ProcessNoise` (`covariance`, `scale`, `log_likelihood`, `scales`,
    `log_likelihoods`, `interior`); pass it (or its `covariance`) as `process_noise=`. With
    `interior` False the likelihood is highest at the grid's end, or flat (a warning says so).

    **Raises:** as `predict_ahead`; `ValueError` for a `scales` that is not an
    increasing grid of positive numbers, or where the filter's likelihood is not finite
    at any of its scales (at some of them, a warning names them and the search keeps to
    the others).
    """
    if shape is None:
        raise TypeError("`shape` must be given: the process noise covariance's shape (n_x).")
    data, guess, (P0, Qp, R), zs = _filter_inputs(
        model, theta, u, z, x0, shape, measurement_noise, prior_covariance, weight, t, missing,
        process_name="shape",
    )  # fmt: skip
    if not np.any(np.asarray(Qp) != 0):
        raise ValueError(
            "`shape` must have a nonzero entry: q `shape` is the process noise covariance, "
            f"zero for every q with `shape` = {shape!r}."
        )
    grid = np.logspace(-12.0, 4.0, 65) if scales is None else _grid(scales)
    args = (data.model, data.theta, jnp.asarray(guess), P0)
    rest = (R, jnp.asarray(data.u), zs)

    def loglik(q):
        value = float(_log_likelihood(*args, jnp.asarray(q, Qp.dtype) * Qp, *rest))
        return value if np.isfinite(value) else -np.inf

    values = np.array([loglik(q) for q in grid])
    finite = np.isfinite(values)
    if not finite.any():
        raise ValueError(
            "estimate_process_noise: the filter's log-likelihood is not finite at any scale "
            "of the grid: the filter breaks down on this record (a model that blows up over "
            "it, or a `prior_covariance` far broader than the states' scale); check `theta`, "
            "give `prior_covariance` (x0's uncertainty in the states' units), or `scales`."
        )
    if not finite.all():
        broke = grid[~finite]
        warn(
            f"estimate_process_noise: the filter broke down (a log-likelihood that is not "
            f"finite) at {broke.size} of the grid's {grid.size} scales (q from "
            f"{broke.min():.3g} to {broke.max():.3g}); the estimate comes from the others. "
            "A filter that breaks down at some scales is near the end of its arithmetic: "
            "give `prior_covariance` (x0's uncertainty in the states' units), check "
            "`theta`, or keep `scales` to a sensible range.",
            stacklevel=2,
        )
    best = int(np.argmax(values))
    interior = 0 < best < grid.size - 1
    # (flat: the same likelihood at every scale; a scale where the filter broke down is
    # no evidence of that, and the search keeps to the finite ones)
    spread = float(np.ptp(values[finite]))
    flat = finite.all() and spread <= 1e-9 * max(1.0, float(np.max(np.abs(values))))
    scale = float(grid[best])
    if flat:  # (no q is more likely than another: noise on states the outputs do not see)
        interior = False
        warn(
            f"estimate_process_noise: the likelihood is the same at every scale of the grid "
            f"(it spans {spread:.3g}): the outputs do not depend on the process noise that "
            "`shape` describes (noise on states they do not see), so these data do not "
            "determine q; give `shape` on the states the outputs see.",
            stacklevel=2,
        )
    elif interior:  # golden section on log q between the best point's neighbours
        lo, hi = np.log(grid[best - 1]), np.log(grid[best + 1])
        ratio = (np.sqrt(5.0) - 1.0) / 2.0
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        fa, fb = loglik(np.exp(a)), loglik(np.exp(b))
        for _ in range(40):
            if fa >= fb:
                hi, b, fb = b, a, fa
                a = hi - ratio * (hi - lo)
                fa = loglik(np.exp(a))
            else:
                lo, a, fa = a, b, fb
                b = lo + ratio * (hi - lo)
                fb = loglik(np.exp(b))
        scale = float(np.exp(0.5 * (lo + hi)))
    else:
        warn(
            f"estimate_process_noise: the likelihood is highest at the end of the grid of "
            f"scales (q = {scale:.3g}): the data ask for "
            + ("less" if best == 0 else "more")
            + " process noise than the grid holds (a model that fits without any, or one "
            "that does not fit, or a `shape` whose entries are not in the states' scales: "
            "q is one factor for all of them); extend `scales`, give `shape` per state, or "
            "check the model.",
            stacklevel=2,
        )
    covariance = np.asarray(scale * np.asarray(Qp), np.asarray(Qp).dtype)
    return ProcessNoise(covariance, scale, loglik(scale), grid, values, bool(interior))
