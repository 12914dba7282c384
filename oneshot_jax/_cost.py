"""The terms of the multi-step cost: the weight Q of eq. (4) and the penalty of eq. (21)."""

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array


class Mask(NamedTuple):
    """Which samples count, for trajectories of different lengths (padded) and missing
    outputs: `outputs` (..., T, n_z) is 1 where an output sample is measured, 0 where it
    is missing; `samples` (..., T) is 1 for the time points of a trajectory, 0 for its
    padding. C sums over the counted terms and divides by the number of time points."""

    outputs: jax.Array
    samples: jax.Array


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

    def local(self, model, theta, x, u, z, mask=None):
        """T times the local loss L_k of eq. (4) with the penalty of eq. (21):

        e^T Q e + lambda h(x, theta),  e = g(x, u, theta) - z  (eq. 3),

        with the missing entries of e set to zero and the penalty counted only at the
        time points of the trajectory when a `Mask` (of this sample) is given.
        """
        e = model.observe(x, u, theta) - z
        if mask is not None:
            e = e * mask.outputs
        if self.weight is None:
            out = jnp.sum(e * e)
        elif self.weight.ndim == 1:
            out = jnp.sum(self.weight * e * e)
        else:
            out = e @ self.weight @ e
        if self.penalty is not None:
            h = self.penalty_weight * self.penalty(x, theta)
            out = out + (h if mask is None else mask.samples * h)
        return out

    def observed(self):
        """The outputs the loss sees, (n_z,) booleans, or None where it sees all (Q = I):
        an output of zero weight (a zero diagonal entry, a zero row of a matrix Q) is not
        observed, and its residuals are no observations for sigma^2's degrees of freedom
        (`_covariance.scale`) or the least-squares stopping test (`_optimality`)."""
        w = self.weight
        if w is None:
            return None
        return w > 0 if w.ndim == 1 else jnp.any(w != 0, axis=-1)

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
