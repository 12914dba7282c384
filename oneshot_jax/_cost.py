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

    def observations(self, measured):
        """The number R of observations among the output entries `measured` ((..., n_z)
        booleans: the measured samples), for sigma^2's degrees of freedom
        (`_covariance.scale`) and the least-squares stopping test (`_optimality`): where Q
        is I or diagonal, the measured entries of the outputs of nonzero weight; where Q is
        a matrix, at each sample the rank of Q restricted to the outputs measured there,
        summed (a Q = v v^T of rank 1 weighs one combination of the outputs: one
        observation per sample, as the one-output model that observes v^T x has). The
        ranks are formed only where Q is singular: a principal part of a positive
        definite Q has full rank."""
        w = self.weight
        seen = self.observed()
        if w is None or w.ndim == 1:
            return jnp.sum(measured if seen is None else measured & seen)
        n_z = w.shape[-1]
        measured = jnp.broadcast_to(measured, measured.shape[:-1] + (n_z,)).reshape(-1, n_z)

        def rank(q):  # (eigenvalues above n_z eps of the largest one)
            vals = jnp.linalg.eigvalsh(q)
            top = jnp.max(jnp.abs(vals))
            return jnp.sum(vals > n_z * jnp.finfo(vals.dtype).eps * top)

        def per_sample():
            pairs = measured[:, :, None] & measured[:, None, :]
            return jnp.sum(jax.vmap(rank)(jnp.where(pairs, w, 0.0)))

        return jax.lax.cond(rank(w) == n_z, lambda: jnp.sum(measured), per_sample)

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
