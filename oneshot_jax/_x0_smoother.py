"""The initial state by an extended Kalman filter and Rauch-Tung-Striebel smoother.

`estimate_x0(method="smoother")`: the EKF forward and the extended RTS smoother backward
over the head of a record (Särkkä, *Bayesian Filtering and Smoothing*, Cambridge
University Press, 2013: Algorithm 5.4 and Chapter 9), each a `lax.scan`, with f and g
linearised by `jax.jacfwd`; the smoothed mean and covariance at k = 0 are the estimate.
The noise covariances and the prior default to the scales of the head
(`_smoother_defaults`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ._checks import as_float
from ._jit import jit
from ._linalg import psd_solve
from ._simulate import simulate_impl

# Defaults of the smoother, relative to the scales of the head (see `estimate_x0`).
MEASUREMENT_NOISE_REL = 1e-2
PROCESS_NOISE_REL = 1e-3
PRIOR_STD_REL = 1e2


class KalmanPath(eqx.Module):
    """The states over the head from the extended Kalman filter and the RTS smoother.

    **Fields:**

    - `filtered_mean`, `filtered_covariance`: x[k | k] (n, n_x) and P[k | k] (n, n_x, n_x),
        given z[0..k].
    - `smoothed_mean`, `smoothed_covariance`: x[k | n-1] and P[k | n-1], given the whole
        head; `smoothed_mean[0]` is the estimate of x0.
    """

    filtered_mean: np.ndarray
    filtered_covariance: np.ndarray
    smoothed_mean: np.ndarray
    smoothed_covariance: np.ndarray


def reads_weight(weight) -> bool:
    """Whether the smoother can read `weight` (per-output weights, or Q) as the inverse of
    the measurement noise covariance: finite and positive definite."""
    w = np.asarray(weight, np.float64)
    q = np.diag(np.atleast_1d(w)) if w.ndim <= 1 else w
    return bool(np.all(np.isfinite(q)) and np.min(np.linalg.eigvalsh(q)) > 0)


def _covariance_arg(value, size, name, *, definite):
    """A covariance from a scalar (times I), a vector (its diagonal) or a matrix (symmetric,
    positive semi-definite, or definite where `definite`)."""
    if np.asarray(value).dtype == bool or isinstance(value, str):
        raise TypeError(
            f"`{name}` must be a variance or a covariance (numbers: a scalar, a ({size},) "
            f"vector of variances or a ({size}, {size}) matrix), got {value!r}."
        )
    a = np.asarray(as_float(value, name), dtype=np.float64)
    if a.shape == ():
        a = np.full(size, float(a))
    if a.shape == (size,):
        a = np.diag(a)
    if a.shape != (size, size):
        raise ValueError(
            f"`{name}` must be a scalar, a ({size},) vector of variances or a ({size}, {size}) "
            f"covariance matrix, got shape {np.shape(value)}."
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"`{name}` contains NaN or inf values.")
    scale = max(float(np.max(np.abs(a), initial=0.0)), 1e-300)  # (n_x = 0: empty)
    if not np.allclose(a, a.T, rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"`{name}` must be a symmetric matrix.")
    low = float(np.min(np.linalg.eigvalsh(a), initial=np.inf))
    if definite and low <= 0:
        raise ValueError(f"`{name}` must be positive definite (variances > 0).")
    if low < -1e-10 * scale:
        raise ValueError(f"`{name}` must be positive semi-definite (variances >= 0).")
    return 0.5 * (a + a.T)


def _rms(a, axis=0):
    """Root-mean-square per column over its finite entries (NaN: a missing sample), with
    1 where it is zero or has none."""
    a = np.asarray(a, np.float64)
    seen = np.isfinite(a)
    count = np.maximum(np.sum(seen, axis=axis), 1)  # (a column without one: 0, then 1)
    s = np.sqrt(np.sum(np.where(seen, a * a, 0.0), axis=axis) / count)
    return np.where(np.isfinite(s) & (s > 0), s, 1.0)


# The simulation that sizes the states (`_smoother_defaults`) counts until its outputs
# leave the measured ones' range by this many times their RMS.
LEFT_DATA = 1e2


def _within_data(xs, zhat, z):
    """The simulated states (T, n_x) up to the first sample whose simulated outputs leave
    the measured outputs' range by more than `LEFT_DATA` times their RMS (at least x0; an
    unstable model's simulation grows without bound, and the RMS of all of it made a prior
    of 1e21 on which the filter broke down), and up to the first non-finite state."""
    span = np.max(np.where(np.isfinite(z), np.abs(z), 0.0), axis=0) + LEFT_DATA * _rms(z)
    out = ~np.all(np.isfinite(zhat) & (np.abs(zhat) <= span), axis=1)
    out |= ~np.all(np.isfinite(xs), axis=1)
    k = int(np.argmax(out)) if out.any() else xs.shape[0]
    return xs[: max(k, 1)]


def with_gaps(data):
    """The checked data's z with NaN at its missing samples (`missing="mask"`, which the
    checks replace by a value and a mask): the filter's missing measurements
    (`ekf_forward`)."""
    z = jnp.asarray(data.z)
    if data.mask is None:
        return z
    seen = jnp.asarray(data.mask.outputs) > 0
    return jnp.where(seen if seen.ndim == 2 else seen[:, None], z, jnp.nan)


def ekf_forward(model, theta, m0, P0, Qp, R, u, z):
    """The extended Kalman filter over a record (Särkkä 2013, Algorithm 5.4): the model
    x[k+1] = f(x[k], u_step[k]) + w_k, w_k ~ N(0, Qp); z[k] = g(x[k], u[k]) + v_k,
    v_k ~ N(0, R); x[0] ~ N(m0, P0); f and g linearised by `jax.jacfwd` at the predicted
    and filtered means. A NaN entry of z is a missing measurement: its row of the update
    is left out (zero row of the Jacobian of g, zero innovation, and R's covariances
    between it and the measured entries dropped, so zero gain and the measured entries'
    update that of their own block of R), and a sample with none measured is a
    prediction alone. Traced (inside the caller's compiled call).

    **Returns:** the filtered means and covariances m[k|k], P[k|k] for k = 0..T-2, the
    predicted m[k+1|k], P[k+1|k] and the Jacobians F_k of f there (the smoother's
    inputs), m[T-1|T-1], P[T-1|T-1], and the log-likelihood of z under the filter's
    model: its innovations e_k = z[k] - g(m[k|k-1]) are independent, N(0, S_k), S_k =
    H_k P[k|k-1] H_k^T + R (the prediction-error decomposition, Särkkä 2013, Chapter
    12), the missing entries left out.
    """
    eye = jnp.eye(m0.shape[0], dtype=m0.dtype)

    def update(m, P, u_k, z_k):
        seen = jnp.isfinite(z_k)
        H = jax.jacfwd(model.observe)(m, u_k, theta) * seen[:, None].astype(m.dtype)
        both = seen[:, None] & seen[None, :]
        R_k = jnp.where(both | jnp.eye(R.shape[0], dtype=bool), R, 0.0)  # (measured block)
        S = H @ P @ H.T + R_k
        Kt = jsl.cho_solve(jsl.cho_factor(S), H @ P)  # K^T = S^{-1} H P
        e = jnp.where(seen, z_k - model.observe(m, u_k, theta), 0.0)
        m = m + Kt.T @ e
        A = eye - Kt.T @ H  # Joseph form: stays symmetric PSD
        P = A @ P @ A.T + Kt.T @ R_k @ Kt
        # (the innovation's density over the measured entries: S's other rows unit)
        S_seen = jnp.where(both, S, jnp.eye(S.shape[0], dtype=S.dtype))
        _, logdet = jnp.linalg.slogdet(S_seen)
        quad = e @ jnp.linalg.solve(S_seen, e)
        loglik = -0.5 * (logdet + quad + jnp.sum(seen) * jnp.log(2 * jnp.pi))
        return m, 0.5 * (P + P.T), loglik

    def forward(carry, inp):
        m, P, total = carry
        u_k, z_k, u_step = inp
        mf, Pf, loglik = update(m, P, u_k, z_k)
        F = jax.jacfwd(model.step)(mf, u_step, theta)
        Pp = F @ Pf @ F.T + Qp
        mp = model.step(mf, u_step, theta)
        return (mp, 0.5 * (Pp + Pp.T), total + loglik), (mf, Pf, mp, Pp, F)

    n = u.shape[0]
    zero = jnp.zeros((), m0.dtype)
    (m, P, total), (mf, Pf, mp, Pp, F) = jax.lax.scan(
        forward, (m0, P0, zero), (u[: n - 1], z[: n - 1], model.step_inputs(u))
    )
    m_last, P_last, loglik = update(m, P, u[n - 1], z[n - 1])
    return (mf, Pf, mp, Pp, F), (m_last, P_last), total + loglik


@jit
def _smooth(model, theta, m0, P0, Qp, R, u, z):
    """Extended Kalman filter (`ekf_forward`) and Rauch-Tung-Striebel smoother over one
    head. The backward pass is the extended RTS smoother (Särkkä 2013, Chapter 9;
    Theorem 8.2 for the linear case):

        G_k = P[k|k] F_k^T P[k+1|k]^+,   m[k|n] = m[k|k] + G_k (m[k+1|n] - m[k+1|k]),
        P[k|n] = P[k|k] + G_k (P[k+1|n] - P[k+1|k]) G_k^T.
    """
    (mf, Pf, mp, Pp, F), (m_last, P_last), _ = ekf_forward(model, theta, m0, P0, Qp, R, u, z)

    def backward(carry, inp):
        ms, Ps = carry
        mf, Pf, mp, Pp, F = inp
        G = psd_solve(Pp, F @ Pf).T  # P[k|k] F^T P[k+1|k]^+ (P symmetric)
        ms = mf + G @ (ms - mp)
        Ps = Pf + G @ (Ps - Pp) @ G.T
        Ps = 0.5 * (Ps + Ps.T)
        return (ms, Ps), (ms, Ps)

    _, (ms, Ps) = jax.lax.scan(backward, (m_last, P_last), (mf, Pf, mp, Pp, F), reverse=True)
    filtered = (jnp.concatenate([mf, m_last[None]]), jnp.concatenate([Pf, P_last[None]]))
    smoothed = (jnp.concatenate([ms, m_last[None]]), jnp.concatenate([Ps, P_last[None]]))
    return filtered, smoothed


def _smoother_defaults(
    data,
    observes_state,
    guess,
    process_noise,
    measurement_noise,
    prior_covariance,
    process_name="process_noise",
):
    """The covariances of the smoother, defaults from the scales of the head
    (`process_name`: the argument that gave `process_noise`, for the errors)."""
    n_x, n_z = guess.shape[0], data.n_z
    z = np.asarray(data.z)
    s_z = _rms(z)
    if observes_state:
        s_x = s_z
    else:
        xs, zhat = simulate_impl(data.model, data.theta, jnp.asarray(guess), data.u, False)
        s_x = _rms(_within_data(np.asarray(xs, np.float64), np.asarray(zhat, np.float64), z))
    if measurement_noise is not None:
        R = _covariance_arg(measurement_noise, n_z, "measurement_noise", definite=True)
    elif data.weight is not None:
        w = np.asarray(data.weight, np.float64)
        if not reads_weight(w):
            raise ValueError(
                "the smoother reads `weight` as the inverse of the measurement noise "
                "covariance, which needs a positive definite weight; give "
                "`measurement_noise` for a singular one."
            )
        R = np.diag(1.0 / w) if w.ndim == 1 else np.linalg.inv(w)
    else:
        R = np.diag((MEASUREMENT_NOISE_REL * s_z) ** 2)
    if process_noise is not None:
        Qp = _covariance_arg(process_noise, n_x, process_name, definite=False)
    else:
        Qp = np.diag((PROCESS_NOISE_REL * s_x) ** 2)
    if prior_covariance is not None:
        P0 = _covariance_arg(prior_covariance, n_x, "prior_covariance", definite=True)
    else:
        P0 = np.diag((PRIOR_STD_REL * s_x) ** 2)
    return P0, Qp, R


def kalman_path(
    data, observes_state, process_noise, measurement_noise, prior_covariance
) -> KalmanPath:
    """The filtered and smoothed states over the head of checked data (one trajectory,
    `_checks.check_data`; missing samples left out of the updates), from `data.x0` as
    the prior mean, with the covariances of `_smoother_defaults`."""
    guess = np.asarray(data.x0)
    z = with_gaps(data)
    P0, Qp, R = _smoother_defaults(
        data._replace(z=z), observes_state, guess, process_noise, measurement_noise,
        prior_covariance,
    )  # fmt: skip
    dtype = data.x0.dtype
    (mf, Pf), (ms, Ps) = _smooth(
        data.model,
        data.theta,
        jnp.asarray(guess),
        *(jnp.asarray(a, dtype) for a in (P0, Qp, R)),
        jnp.asarray(data.u),
        z,
    )
    return KalmanPath(*(np.asarray(a) for a in (mf, Pf, ms, Ps)))
