"""The terms of the multi-step cost: the weight Q of eq. (4) and the penalty of eq. (21)."""

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array


class Cost(eqx.Module):
    """The weight Q, the penalty h and its multiplier lambda of eq. (4), (21): the pieces
    that always travel together from `loss`, `value_and_grad` and `fit` to the loops.

    `weight` is None (Q = I), a (n_z,) diagonal or an (n_z, n_z) PSD matrix; `penalty` is
    None or `h(x, theta) -> scalar`; `penalty_weight` is a scalar array (0 without a
    penalty).
    """

    weight: Array | None
    penalty: Callable | None
    penalty_weight: Array

    def local(self, model, theta, x, u, z):
        """T times the local loss L_k of eq. (4) with the penalty of eq. (21):

        e^T Q e + lambda h(x, theta),  e = g(x, u, theta) - z  (eq. 3).
        """
        e = model.observe(x, u, theta) - z
        if self.weight is None:
            out = jnp.sum(e * e)
        elif self.weight.ndim == 1:
            out = jnp.sum(self.weight * e * e)
        else:
            out = e @ self.weight @ e
        if self.penalty is not None:
            out = out + self.penalty_weight * self.penalty(x, theta)
        return out

    def sqrt_weight(self):
        """Q^{1/2} (a vector for a diagonal Q, the symmetric root of a matrix Q), or None."""
        w = self.weight
        if w is None or w.ndim == 1:
            return None if w is None else jnp.sqrt(w)
        vals, vecs = jnp.linalg.eigh(w)
        return (vecs * jnp.sqrt(jnp.maximum(vals, 0.0))) @ vecs.T


def weigh(e, sqrt_q):
    """Q^{1/2} e for errors e (..., n_z)."""
    if sqrt_q is None:
        return e
    if sqrt_q.ndim == 1:
        return e * sqrt_q
    return e @ sqrt_q.T
