"""A bounded record of a solver's iterates, kept inside the compiled loop.

The buffer holds at most `size` rows whatever the step budget. Rows are written every
`stride` steps, starting at step 0; when the buffer fills, every other row is dropped and
the stride doubles. So a run of any length keeps its whole path at an even spacing of at
most 2 (steps / size), and the final iterate is always the last row.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class History(NamedTuple):
    loss: jax.Array  # (size,)
    grad_norm: jax.Array  # (size,)
    theta: jax.Array  # (size, p): the free entries of theta
    step: jax.Array  # (size,) int: the step each row was recorded at
    count: jax.Array  # rows in use
    stride: jax.Array  # rows are recorded every `stride` steps


def init(size, n_theta, dtype) -> History:
    if size < 2 or size % 2:
        raise ValueError(f"`history` must be an even number of rows >= 2, got {size}.")
    return History(
        loss=jnp.full((size,), jnp.nan, dtype),
        grad_norm=jnp.full((size,), jnp.nan, dtype),
        theta=jnp.full((size, n_theta), jnp.nan, dtype),
        step=jnp.full((size,), -1, jnp.int32),
        count=jnp.array(0, jnp.int32),
        stride=jnp.array(1, jnp.int32),
    )


def _write(h: History, step, loss, grad_norm, theta) -> History:
    i = h.count
    return h._replace(
        loss=h.loss.at[i].set(loss),
        grad_norm=h.grad_norm.at[i].set(grad_norm),
        theta=h.theta.at[i].set(theta),
        step=h.step.at[i].set(step),
        count=i + 1,
    )


def _compact(h: History) -> History:
    """Keep rows 0, 2, 4, ... (steps that are multiples of 2 stride) and double the stride."""
    size = h.loss.shape[0]
    keep = jnp.arange(0, size, 2)
    half = size // 2

    def thin(a, fill):
        kept = a[keep]
        return jnp.concatenate([kept, jnp.full((size - half, *a.shape[1:]), fill, a.dtype)])

    return History(
        loss=thin(h.loss, jnp.nan),
        grad_norm=thin(h.grad_norm, jnp.nan),
        theta=thin(h.theta, jnp.nan),
        step=thin(h.step, -1),
        count=jnp.array(half, jnp.int32),
        stride=h.stride * 2,
    )


def record(h: History, step, loss, grad_norm, theta) -> History:
    """Record step `step` if it falls on the stride (compacting a full buffer)."""
    due = step % h.stride == 0
    h = jax.tree_util.tree_map(
        lambda new, old: jnp.where(due, new, old), _write(h, step, loss, grad_norm, theta), h
    )
    full = h.count == h.loss.shape[0]
    return jax.lax.cond(full, _compact, lambda h: h, h)


def finish(h: History, step, loss, grad_norm, theta) -> History:
    """Make the final iterate the last row: overwrite it if it is already recorded (the
    returned point may differ from the last iterate, e.g. the last finite one), append
    it otherwise (a record always leaves a free row)."""
    last = jnp.maximum(h.count - 1, 0)
    same = (h.count > 0) & (h.step[last] == step)
    h = h._replace(count=jnp.where(same, last, h.count))
    return _write(h, step, loss, grad_norm, theta)
