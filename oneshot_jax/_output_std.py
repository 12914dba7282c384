r"""Standard errors of a fitted model's simulated outputs: the estimate's covariance
carried to the outputs to first order (the delta method).

The simulated outputs zhat_k(theta, x0) of a record carry the uncertainty of the
estimate. With J^z_theta,k = d zhat_k / d theta (theta's free entries) and J^z_x,k =
d zhat_k / d x0 from the closed-form forward sensitivities (the forward twin of eq. (17)
and (20), `_sensitivity.trajectory_jacobian`), and Sigma the covariance of theta's free
entries:

- x0 known: Var zhat_k = J^z_theta,k Sigma J^z_theta,k^T.
- x0 estimated from the record's first n outputs at theta, x0_hat(theta) =
  argmin sum_{k<n} e_k^T Q e_k (as `predict` does): by the implicit function theorem
  d x0_hat / d theta = -C^+ B^T over the head, C = J_x^T Q J_x, B^T = J_x^T Q J_theta (the
  blocks of the arrow matrix of eq. (17)/(20), `_linalg.eliminate_x0`), so with
  G_k = J^z_theta,k - J^z_x,k C^+ B^T

      Var zhat_k = G_k Sigma G_k^T + sigma^2 J^z_x,k C^+ J^z_x,k^T,

  the second term the head's own noise (sigma^2 Q^{-1} per sample, the fit's estimate).
  On the fitted record with the whole record as its head, this is sigma^2 J^z (J^T J)^+
  J^z^T: the joint covariance of theta and x0 carried to the outputs.
"""

import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._cost import Cost
from ._covariance import carried_variance
from ._jit import jit
from ._linalg import psd_solve
from ._sensitivity import trajectory_jacobian


@jit
def _output_jacobian(model, unravel, flat, free, x0, u):
    """zhat (T, n_z) and its Jacobians (T, n_z, p) in theta's free entries `free` (an
    int array into theta's flat parameters `flat`, `unravel` their inverse) and
    (T, n_z, n_x) in x0."""
    base = jnp.asarray(flat, x0.dtype)
    T, n_z = u.shape[0], model.observe(x0, u[0], unravel(base)).shape[-1]
    cost = Cost(None, None, jnp.zeros((), x0.dtype))
    lin = trajectory_jacobian(
        model,
        cost,
        lambda p: unravel(base.at[free].set(p)),
        base[free],
        lambda p: p,
        x0,
        u,
        jnp.zeros((T, n_z), x0.dtype),
        scale=1.0,
        strategy="auto",
    )
    return (
        lin.r.reshape(T, n_z),
        lin.Jt.reshape(T, n_z, -1),
        lin.Jx.reshape(T, n_z, -1),
    )


def output_std(model, params, fixed, covariance, x0, u, head=None):
    """The standard errors (T, n_z) of the simulated outputs of one record (module
    docstring): x0 known, or, with `head` = (n, z_head, Q, sigma^2, identifiable), x0
    estimated from the first n outputs `z_head` (NaN where missing) under the weight
    matrix Q, with the fit's noise variance sigma^2 and the
    x0 entries the head determines (`identifiable`, from its `X0Estimate`).

    `model`, `params`: the model with theta's static part bound in and theta's
    parameters (`_checks.Data`); `fixed`: the flat mask of the held entries;
    `covariance`: Sigma over the free entries. Where Sigma is not finite in an entry that
    an output sample takes (of two parameters that both move it: a parameter not
    identifiable, a covariance not computed), or an x0 entry the head does not determine
    moves it, its standard error is inf."""
    free = np.flatnonzero(~np.asarray(fixed, bool))
    flat, unravel = _pytree.ravel(params)
    out = _output_jacobian(model, unravel, flat, free, x0, u)
    _, Jt, Jx = (np.asarray(a, np.float64) for a in out)
    unknown = np.zeros(Jt.shape[:2], bool)
    if head is not None:
        n, z_head, Q, s2, identifiable = head
        Jh, Jxh = Jt[:n], Jx[:n]
        seen = np.isfinite(np.asarray(z_head, np.float64))[..., None]
        Jh, Jxh = np.where(seen, Jh, 0.0), np.where(seen, Jxh, 0.0)
        C = np.einsum("kia,ij,kjb->ab", Jxh, Q, Jxh)
        Bt = np.einsum("kia,ij,kjb->ab", Jxh, Q, Jh)
        # (C^+ [B^T, I]: the pseudo-inverse of `_linalg`, a zero step along C's null space)
        W = np.asarray(psd_solve(jnp.asarray(C), jnp.asarray(np.hstack([Bt, np.eye(len(C))]))))
        dx0, C_inv = W[:, : Bt.shape[1]], W[:, Bt.shape[1] :]
        Jt = Jt - np.einsum("kia,ap->kip", Jx, dx0)
        var = s2 * np.einsum("kia,ab,kib->ki", Jx, C_inv, Jx)
        blind = ~np.asarray(identifiable, bool)
        unknown |= np.any(np.abs(Jx[..., blind]) > 0, axis=-1)
    else:
        var = np.zeros(Jt.shape[:2])
    var = var + carried_variance(Jt, covariance, free.size)  # (inf where unknown)
    return np.where(unknown, np.inf, np.sqrt(np.maximum(var, 0.0)))
