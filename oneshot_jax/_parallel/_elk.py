r"""The damped Newton step of ELK: a Kalman smoother as two parallel scans.

DEER's Newton step for the rollout x_{k+1} = f(x_k) (eq. 7) solves, for the increment
d = x - xbar about the current iterate xbar,

    d_0 = 0,   d_{k+1} = A_k d_k + r_k,   A_k = f_x(xbar_k),   r_k = f(xbar_k) - xbar_{k+1},

which amplifies without bound where the A_k are unstable, and Newton then diverges. ELK
(Gonzalez et al., "Towards scalable and stable parallelization of nonlinear RNNs",
NeurIPS 2024) damps the step in the Levenberg-Marquardt way,

    d = argmin sum_k ||d_{k+1} - A_k d_k - r_k||^2 + lambda sum_k ||d_{k+1}||^2,

and evaluates it as the posterior mean of a linear-Gaussian state-space model: dynamics
d_{k+1} = A_k d_k + r_k + w_k with w_k ~ N(0, I), observations 0 = d_{k+1} + v_k with
v_k ~ N(0, I / lambda) (the trust region: stay near the current iterate). `damping` is
lambda: lambda -> 0 gives DEER's step back. Here the step is the *smoothed* mean, the
exact minimiser above (checked against a dense solve in the tests), so it is a descent
direction of ||r||^2 for every lambda > 0; the authors' code (lindermanlab/elk) takes the
filtered mean, which is cheaper but is not the Levenberg-Marquardt step.

The filter is the parallel scan of Sarkka and Garcia-Fernandez ("Temporal parallelization
of Bayesian smoothers", IEEE TAC 2021), whose elements (A, b, C, eta, J) describe
p(d_k | d_{i-1}, observations i..k). With unit process noise, an identity observation
and kappa = lambda / (1 + lambda) they are

    A = (1 - kappa) A_k,  b = (1 - kappa) r_k,  C = (1 - kappa) I,
    eta = -kappa A_k^T r_k,  J = kappa A_k^T A_k,

with A = eta = J = 0 for k = 0 (d_0 = 0 is known), and two elements combine (i then j) as

    M = (I + C_i J_j)^{-1},
    A = A_j M A_i,  b = A_j M (b_i + C_i eta_j) + b_j,  C = A_j M C_i A_j^T + C_j,
    eta = (M A_i)^T (eta_j - J_j b_i) + eta_i,  J = (M A_i)^T J_j A_i + J_i,

using (I + J_j C_i)^{-1} = M^T (C and J are symmetric). The filtered means m_k and
covariances P_k are the b and C of the prefix compositions. The Rauch-Tung-Striebel
smoother is then a reverse linear recurrence, m^s_k = g_k + E_k m^s_{k+1} with
E_k = P_k A_{k+1}^T (A_{k+1} P_k A_{k+1}^T + I)^{-1} and g_k = m_k - E_k (A_{k+1} m_k
+ r_{k+1}), m^s at the last step being the filtered mean.

A combine costs one n x n solve (O(n^3)); the diagonal form (quasi-ELK, diagonal A_k) is
elementwise, O(n). Both scans use recursive doubling (`doubling_scan`): this is the
safeguard stage, and its large combine would take several times longer to compile as an
`associative_scan`.
"""

import jax.numpy as jnp

from ._recurrence import _compose, _compose_diagonal, _matmul, _matvec, doubling_scan


def _combine(first, second):
    A1, b1, C1, eta1, J1 = first
    A2, b2, C2, eta2, J2 = second
    n = A1.shape[-1]
    eye = jnp.eye(n, dtype=A1.dtype)
    lhs = eye + _matmul(C1, J2)
    rhs = jnp.concatenate([A1, (b1 + _matvec(C1, eta2))[..., None], C1], axis=-1)
    X = jnp.linalg.solve(lhs, rhs)  # M [A1, b1 + C1 eta2, C1]
    MA1, Mb, MC1 = X[..., :n], X[..., n], X[..., n + 1 :]
    MA1t = jnp.swapaxes(MA1, -1, -2)
    A = _matmul(A2, MA1)
    b = _matvec(A2, Mb) + b2
    C = _matmul(_matmul(A2, MC1), jnp.swapaxes(A2, -1, -2)) + C2
    eta = _matvec(MA1t, eta2 - _matvec(J2, b1)) + eta1
    J = _matmul(_matmul(MA1t, J2), A1) + J1
    # Symmetric by construction; re-symmetrise so that roundoff does not accumulate.
    C = 0.5 * (C + jnp.swapaxes(C, -1, -2))
    J = 0.5 * (J + jnp.swapaxes(J, -1, -2))
    return A, b, C, eta, J


def _combine_diagonal(first, second):
    A1, b1, C1, eta1, J1 = first
    A2, b2, C2, eta2, J2 = second
    denom = 1.0 + C1 * J2
    A = A1 * A2 / denom
    b = A2 * (b1 + C1 * eta2) / denom + b2
    C = C1 * A2 * A2 / denom + C2
    eta = A1 * (eta2 - J2 * b1) / denom + eta1
    J = J2 * A1 * A1 / denom + J1
    return A, b, C, eta, J


def elk_increment(A, r, damping):
    """The damped (ELK) increment d_1..d_T for d_{k+1} = A_k d_k + r_k, d_0 = 0.

    **Arguments:**

    - `A`: (T, n, n), the Jacobians f_x at the current iterate x_0..x_{T-1}.
    - `r`: (T, n), the residuals f(x_k) - x_{k+1}.
    - `damping`: lambda = 1 / sigma^2 >= 0 (0: the undamped DEER step).

    **Returns:**

    (T, n): the smoothed increments d_1..d_T, the Levenberg-Marquardt step. Memory
    O(T n^2), work O(T n^3).
    """
    T, n = r.shape
    kappa = jnp.asarray(damping / (1.0 + damping), r.dtype)
    keep = 1.0 - kappa
    first = (jnp.arange(T) == 0)[:, None, None]
    At = jnp.swapaxes(A, -1, -2)
    elems = (
        jnp.where(first, 0.0, keep * A),
        keep * r,
        jnp.broadcast_to(keep * jnp.eye(n, dtype=r.dtype), (T, n, n)),
        jnp.where(first[..., 0], 0.0, -kappa * _matvec(At, r)),
        jnp.where(first, 0.0, kappa * _matmul(At, A)),
    )
    eye, zero = jnp.eye(n, dtype=r.dtype), jnp.zeros((n,), r.dtype)
    identity = (eye, zero, 0.0 * eye, zero, 0.0 * eye)
    _, m, P, _, _ = doubling_scan(_combine, identity, elems)
    # Smoother gains E_k = P_k F^T (F P_k F^T + I)^{-1} with F = A_{k+1} (symmetric P), then
    # the smoothed means m^s_k = g_k + E_k m^s_{k+1}, a reverse linear recurrence.
    F, c = A[1:], r[1:]
    PFt = _matmul(P[:-1], jnp.swapaxes(F, -1, -2))
    S = _matmul(F, PFt) + eye
    E = jnp.swapaxes(jnp.linalg.solve(S, jnp.swapaxes(PFt, -1, -2)), -1, -2)
    g = m[:-1] - _matvec(E, _matvec(F, m[:-1]) + c)
    g = jnp.concatenate([g, m[-1:]])
    E = jnp.concatenate([E, 0.0 * eye[None]])
    return doubling_scan(_compose, (eye, zero), (E, g), reverse=True)[1]


def diagonal_elk_increment(a, r, damping):
    """quasi-ELK: `elk_increment` with diagonal Jacobians `a` (T, n); elementwise, O(T n)."""
    T, n = r.shape
    kappa = jnp.asarray(damping / (1.0 + damping), r.dtype)
    keep = 1.0 - kappa
    first = (jnp.arange(T) == 0)[:, None]
    elems = (
        jnp.where(first, 0.0, keep * a),
        keep * r,
        jnp.full((T, n), keep, r.dtype),
        jnp.where(first, 0.0, -kappa * a * r),
        jnp.where(first, 0.0, kappa * a * a),
    )
    one, zero = jnp.ones((n,), r.dtype), jnp.zeros((n,), r.dtype)
    _, m, P, _, _ = doubling_scan(_combine_diagonal, (one, zero, zero, zero, zero), elems)
    F, c = a[1:], r[1:]
    E = P[:-1] * F / (F * F * P[:-1] + 1.0)
    g = m[:-1] - E * (F * m[:-1] + c)
    g = jnp.concatenate([g, m[-1:]])
    E = jnp.concatenate([E, zero[None]])
    return doubling_scan(_compose_diagonal, (one, zero), (E, g), reverse=True)[1]
