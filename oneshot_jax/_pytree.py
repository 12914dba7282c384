"""Parameter pytrees on the host: trainable and static parts, flattening, names.

theta may be any pytree: a dict of named physical parameters, or one that also holds
equinox modules (a neural-network residual) whose leaves include functions and other
non-numeric parts. The library trains the floating leaves and carries the rest (functions,
integer and boolean arrays) as static data, so a user never calls `eqx.partition`
themselves.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def is_parameter(leaf) -> bool:
    """Trainable leaves: floating arrays (and complex ones, which the checks refuse), NumPy
    floating scalars and Python numbers (weakly typed: `{"k": 2}` is a parameter).

    Integer and boolean arrays (and NumPy integer and boolean scalars) are not parameters:
    an equinox module's exponent, index buffer or mask is data, carried unchanged like a
    function."""
    if isinstance(leaf, (bool, np.bool_)):
        return False
    if isinstance(leaf, (int, float, complex)):
        return True
    if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
        return bool(jnp.issubdtype(leaf.dtype, jnp.inexact))
    return False


def split(theta):
    """(parameters, static): theta's trainable leaves, and everything else (None when
    there is nothing static)."""
    params, static = eqx.partition(theta, is_parameter)
    if not any(leaf is not None for leaf in jax.tree_util.tree_leaves(static)):
        static = None
    return params, static


def combine(params, static):
    """The inverse of `split`."""
    return params if static is None else eqx.combine(params, static)


class Bound(eqx.Module):
    """`fn(x, u, combine(theta, static))`: a model function that sees the whole theta
    while the library only handles its trainable part."""

    fn: Any
    static: Any

    def __call__(self, x, u, theta):
        return self.fn(x, u, combine(theta, self.static))


class BoundPenalty(eqx.Module):
    fn: Any
    static: Any

    def __call__(self, x, theta):
        return self.fn(x, combine(theta, self.static))


def flat_host(tree) -> np.ndarray:
    """The leaves of `tree` concatenated into one 1-D NumPy array (leaf order), without a
    JAX call."""
    leaves = jax.tree_util.tree_leaves(tree)
    if not leaves:
        return np.zeros(0)
    return np.concatenate([np.ravel(np.asarray(a)) for a in leaves])


def unflatten_rows(rows, like, squeeze=False):
    """Rows of flattened parameters (E, n) as the pytree `like` with a leading axis E
    (dropped with `squeeze`): the NumPy inverse of `flat_host`."""
    rows = np.asarray(rows)
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, start = [], 0
    for leaf in leaves:
        size = int(np.size(leaf))
        block = rows[:, start : start + size].reshape(rows.shape[0], *np.shape(leaf))
        out.append(block[0] if squeeze else block)
        start += size
    return jax.tree_util.tree_unflatten(treedef, out)


def _key(entry) -> str:
    for attr in ("key", "idx", "name"):
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def leaf_names(theta) -> tuple[str, ...]:
    """One name per scalar of theta: the path of its leaf (dict keys, indices, attribute
    names joined by '.') with [i] or [i, j] for array entries."""
    names = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(theta)[0]:
        base = ".".join(_key(p) for p in path) or "theta"
        if np.ndim(leaf) == 0:
            names.append(base)
        elif np.ndim(leaf) == 1:
            names.extend(f"{base}[{i}]" for i in range(np.shape(leaf)[0]))
        else:
            names.extend(f"{base}[{', '.join(map(str, ix))}]" for ix in np.ndindex(np.shape(leaf)))
    return tuple(names)
