"""The covariance of the estimates: sigma^2 (J^T J)^+ of the data residuals at the solution.

J is the Jacobian of the weighted, scaled data residuals r = Q^{1/2} e / sqrt(N T) in the
free variables (theta's free entries, and each trajectory's free x0 entries), taken from
the solver's last linearisation when it holds one, else evaluated here (closed form,
forward sensitivities). J^T J is an arrow matrix; its inverse is formed blockwise through
the Schur complement S = A - sum_i B_i C_i^+ B_i^T (`_linalg.eliminate_x0`, the elimination
the least-squares step uses, here with the pseudo-inverses C_i^+ formed), so a parameter or
an initial state that does not change the outputs is flagged as not identifiable instead
of producing NaN.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._linalg import eliminate_x0, identifiable, normal_blocks, psd_solve
from ._problem import FitProblem, Params


class Covariance(NamedTuple):
    """(J^T J)^+ blocks (unscaled: multiply by sigma^2 = SSE / dof, see `FitResult`)."""

    sse: jax.Array  # ||r_data||^2 (the data part of C)
    theta: jax.Array  # (p, p)
    x0: jax.Array  # (N, m, m): each trajectory's x0 block
    theta_identifiable: jax.Array  # (p,)
    x0_identifiable: jax.Array  # (N, m)


def covariance(problem: FitProblem, params: Params, strategy, blocks=None) -> Covariance:
    """The `Covariance` at `params`.

    `blocks`: (SSE, A, B, C_i) of the data residuals at `params` when the solver already
    holds them (its last linearisation); otherwise the Jacobian is evaluated here.
    """
    if blocks is None:
        lin = problem.jacobian(params, strategy, penalty=False)
        A, B, Cb, _, _ = normal_blocks(lin.Jt, lin.Jx, lin.r)
        sse = jnp.sum(lin.r**2)
    else:
        sse, A, B, Cb = blocks
    p, m = A.shape[0], Cb.shape[-1]
    elim = eliminate_x0(B, Cb, pseudo_inverse=True)
    x_ok = identifiable(Cb) if m else jnp.ones(Cb.shape[:2], bool)
    if p == 0:
        return Covariance(sse, A, elim.Cinv, jnp.ones((0,), bool), x_ok)
    S = elim.schur(A, B)
    S_inv = psd_solve(S, jnp.eye(p, dtype=S.dtype))
    t_ok = identifiable(S)
    return Covariance(sse, S_inv, elim.covariance(S_inv), t_ok, x_ok)


class Scaled(NamedTuple):
    """sigma^2 (J^T J)^+ on the host, with inf where a variable is not identifiable."""

    theta: np.ndarray  # (p, p) covariance of theta's free entries
    x0: np.ndarray  # (N, m, m) covariance of each trajectory's free x0 entries
    sigma2: float  # the residual variance, SSE / (n_obs - n_free)
    theta_identifiable: np.ndarray
    x0_identifiable: np.ndarray


def scale(cov: Covariance, n_obs: int) -> Scaled:
    """Multiply by sigma^2 = SSE / dof (dof = n_obs - n_free), on the host.

    With J = Q^{1/2} J_e / sqrt(N T), sigma^2 (J_e^T Q J_e)^{-1} = (SSE_r / dof) (J^T J)^{-1}.
    A variable outside the identifiable set gets an infinite variance, and so does every
    variable when there are no more observations than free variables (dof <= 0).
    """
    t_ok = np.asarray(cov.theta_identifiable, bool)
    x_ok = np.asarray(cov.x0_identifiable, bool)
    n_free = t_ok.size + x_ok.size
    dof = n_obs - n_free
    s2 = float(cov.sse) / dof if dof > 0 else float("inf")
    theta = np.array(cov.theta, dtype=float) * s2 if dof > 0 else np.full(cov.theta.shape, np.inf)
    x0 = np.array(cov.x0, dtype=float) * s2 if dof > 0 else np.full(cov.x0.shape, np.inf)
    if not t_ok.all():
        theta[~t_ok, :] = np.inf
        theta[:, ~t_ok] = np.inf
    if not x_ok.all():
        for i in range(x0.shape[0]):
            x0[i][~x_ok[i], :] = np.inf
            x0[i][:, ~x_ok[i]] = np.inf
    return Scaled(theta, x0, s2, t_ok, x_ok)
