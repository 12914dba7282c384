"""A bounded record of a solver's iterates, kept inside the compiled loop.

The buffer holds at most `size` rows whatever the step budget. Rows are written every
`stride` steps, starting at step 0; when a row is due and the buffer is full, every other
row is dropped and the stride doubles (a run that ends as the buffer fills keeps every
row). So a run of any length keeps its whole path at an even spacing of at most
2 (steps / size). The step counter is shared by all starting points run side by
side (they advance together, a finished one frozen), so the decisions to write and to
thin are plain conditionals, taken only when due; each row holds every start's values.
(Starts run in turn each keep a buffer of their own: `_iterate._unstack`.) The final
iterate of each start is kept apart (`FitHistory` puts it last).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class History(NamedTuple):
    loss: jax.Array  # (size, S)
    grad_norm: jax.Array  # (size, S)
    validation: jax.Array | None  # (size, S): the validation loss, None without validation
    theta: jax.Array  # (size, S, p): the free entries of theta
    step: jax.Array  # (size,) int: the step each row was recorded at (-1: unused)
    count: jax.Array  # rows in use
    stride: jax.Array  # rows are recorded every `stride` steps


def init(size, n_starts, n_theta, dtype, validation=False) -> History:
    if size < 2 or size % 2:
        raise ValueError(f"`history` must be an even number of rows >= 2, got {size}.")
    return History(
        loss=jnp.full((size, n_starts), jnp.nan, dtype),
        grad_norm=jnp.full((size, n_starts), jnp.nan, dtype),
        validation=jnp.full((size, n_starts), jnp.nan, dtype) if validation else None,
        theta=jnp.full((size, n_starts, n_theta), jnp.nan, dtype),
        step=jnp.full((size,), -1, jnp.int32),
        count=jnp.array(0, jnp.int32),
        stride=jnp.array(1, jnp.int32),
    )


def _compact(h: History) -> History:
    """Keep rows 0, 2, 4, ... (steps that are multiples of 2 stride) and double the stride."""
    size = h.step.shape[0]
    half = size // 2

    def thin(a, fill):  # a strided slice, not a gather: less to compile
        return jnp.concatenate([a[0::2], jnp.full((size - half, *a.shape[1:]), fill, a.dtype)])

    return History(
        loss=thin(h.loss, jnp.nan),
        grad_norm=thin(h.grad_norm, jnp.nan),
        validation=None if h.validation is None else thin(h.validation, jnp.nan),
        theta=thin(h.theta, jnp.nan),
        step=thin(h.step, -1),
        count=jnp.array(half, jnp.int32),
        stride=h.stride * 2,
    )


def first(h: History, loss, grad_norm, theta, validation=None) -> History:
    """`record` at step 0 of an empty buffer: row 0, no stride test and no thinning to
    trace (a buffer of size >= 2 cannot be full after one row)."""
    i = h.count
    if validation is not None:
        h = h._replace(validation=h.validation.at[i].set(validation))
    return h._replace(
        loss=h.loss.at[i].set(loss),
        grad_norm=h.grad_norm.at[i].set(grad_norm),
        theta=h.theta.at[i].set(theta),
        step=h.step.at[i].set(jnp.array(0, jnp.int32)),
        count=i + 1,
    )


def record(h: History, step, loss, grad_norm, theta, validation=None) -> History:
    """Record step `step` (shared by the starts) if it falls on the stride; a full buffer is
    thinned first, only when a row is due (so a run that ends as the buffer fills keeps
    every row)."""
    size = h.step.shape[0]
    h = jax.lax.cond((h.count == size) & (step % h.stride == 0), _compact, lambda h: h, h)
    due = step % h.stride == 0  # (the stride as it is after thinning)
    i = jnp.where(due, h.count, size - 1)
    if validation is not None:
        h = h._replace(
            validation=h.validation.at[i].set(jnp.where(due, validation, h.validation[i]))
        )
    h = h._replace(
        loss=h.loss.at[i].set(jnp.where(due, loss, h.loss[i])),
        grad_norm=h.grad_norm.at[i].set(jnp.where(due, grad_norm, h.grad_norm[i])),
        theta=h.theta.at[i].set(jnp.where(due, theta, h.theta[i])),
        step=h.step.at[i].set(jnp.where(due, step, h.step[i])),
        count=h.count + due,
    )
    return h
