"""Long records in chunks: a parallel solve inside each chunk, a sequential carry between."""

import jax
import jax.numpy as jnp


def chunked_scan(fn, carry, xs, chunk_size, *, reverse=False):
    """`lax.scan` of `fn(carry, (chunk, valid)) -> (carry, (per_step, per_chunk))` over
    chunks of a record.

    `xs` is a pytree of arrays with a common leading (time) axis of length L. It is padded
    at the end, by repeating its last entry, to a multiple of `chunk_size`, and cut into
    chunks of exactly `chunk_size` steps, so that `fn` is compiled once; `valid` (a bool
    array of the chunk's length) is False on the padding, which `fn` must make inert (a
    step that holds its state, a Jacobian of zero). `chunk_size=None`
    (or >= L) is one call on the whole record, all valid. With `reverse=True` the chunks
    are processed from the end of the record (the padding, at the end, comes first).

    **Returns:**

    `(carry, per_step, per_chunk)`: the leaves of `per_step` (leading axis: the chunk's
    steps) joined in time order and cut back to length L; those of `per_chunk` stacked
    with one row per chunk.
    """
    L = jax.tree_util.tree_leaves(xs)[0].shape[0]
    if chunk_size is None or chunk_size >= L:
        carry, (per_step, per_chunk) = fn(carry, (xs, jnp.ones((L,), bool)))
        return carry, per_step, jax.tree_util.tree_map(lambda a: a[None], per_chunk)
    n_chunks = -(-L // chunk_size)
    pad = n_chunks * chunk_size - L
    valid = (jnp.arange(n_chunks * chunk_size) < L).reshape(n_chunks, chunk_size)

    def split(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a
        return a.reshape(n_chunks, chunk_size, *a.shape[1:])

    chunks = (jax.tree_util.tree_map(split, xs), valid)
    carry, (per_step, per_chunk) = jax.lax.scan(fn, carry, chunks, reverse=reverse)
    join = lambda a: a.reshape(n_chunks * chunk_size, *a.shape[2:])[:L]  # noqa: E731
    return carry, jax.tree_util.tree_map(join, per_step), per_chunk
