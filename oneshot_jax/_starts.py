"""The starts of a multistart fit: `fit(multistart=...)` checked and expanded.

`multistart=True` reads a leading axis of starts on every parameter leaf of theta0. A
dict names some parts of theta0 instead (its keys, nested as theta0's dicts, an equinox
module's field names, a list's or tuple's indices) and gives their starts, each with a
leading axis of starts; every other parameter leaf (an equinox network's weights, say)
is theta0's own, shared by all starts. Both become the same thing here: theta0's
parameter leaves, each with a leading axis of starts, from which `build_problem` builds
the free variables of every start.
"""

from collections.abc import Mapping

import jax
import numpy as np

from . import _pytree


def as_multistart(multistart, theta0):
    """`multistart` with a NumPy bool read as Python's (`np.True_` from a config or an
    array's `any()`: the checks below test `is True` and `is False`), and a dict's dotted
    names ("phys.k", as `fixed=` and the printout name a nested parameter) nested as
    theta0's dicts."""
    if isinstance(multistart, np.bool_):
        return bool(multistart)
    if isinstance(multistart, Mapping) and not multistart and not jax.tree_util.tree_leaves(theta0):
        # (starts over x0 alone, of a theta0 without parameters: the rows of x0, as True)
        return True
    if isinstance(multistart, Mapping) and isinstance(theta0, dict):
        return _pytree.nest_dotted(dict(multistart), theta0, "multistart")
    return multistart


def _name(path) -> str:
    """theta's entry at `path`, written as a user indexes it: `theta['phys']['k']`."""
    return "theta" + jax.tree_util.keystr(tuple(path))


def _raw(entry):
    """The key a user writes for one step of a path: a dict key, an index, a field name."""
    for attr in ("key", "idx", "name"):
        if hasattr(entry, attr):
            return getattr(entry, attr)
    return entry


def _children(node):
    """The direct children of a pytree node with their path entries (none for a leaf)."""
    pairs, treedef = jax.tree_util.tree_flatten_with_path(node, is_leaf=lambda x: x is not node)
    if treedef.num_nodes == 1 and pairs and pairs[0][0] == ():  # `node` is itself a leaf
        return []
    return [(path[0], child) for path, child in pairs]


def _given(value, node, path, out):
    """The starts `value` of theta0's part `node` at `path`: each of its parameter leaves
    with a leading axis of starts, checked against theta0's, into `out` by full path."""
    if _pytree.is_parameter(node) and not _children(node):
        a = np.asarray(value) if isinstance(value, (list, tuple, int, float)) else value
        real = isinstance(a, (np.ndarray, jax.Array)) and a.dtype.kind in "iuf"
        if not real or np.ndim(a) < 1 or np.shape(a)[1:] != np.shape(node):
            shape = ", ".join(["S", *map(str, np.shape(node))]) + (
                "," if np.ndim(node) == 0 else ""
            )
            raise ValueError(
                f"`multistart`: the starts of {_name(path)} must be a real array of shape "
                f"({shape}) (a leading axis of S starts on its shape {np.shape(node)}), got "
                f"{'shape ' + str(np.shape(a)) if real else repr(value)}."
            )
        leaf_dtype = np.asarray(node).dtype
        out[tuple(path)] = np.asarray(a, leaf_dtype if leaf_dtype.kind == "f" else float)
        return
    params, _ = _pytree.split(node)
    if not jax.tree_util.tree_leaves(params):
        raise ValueError(
            f"`multistart` gives starts for {_name(path)}, which holds no parameter of theta0 "
            "(integer or boolean arrays and functions are not estimated)."
        )
    got, _ = _pytree.split(value)
    node_leaves, node_def = jax.tree_util.tree_flatten_with_path(params)
    got_leaves, got_def = jax.tree_util.tree_flatten(got)
    if got_def != jax.tree_util.tree_structure(params):
        raise ValueError(
            f"`multistart`: the starts of {_name(path)} must have theta0's structure there "
            f"(its parameter leaves, each with a leading axis of starts), got {got_def} for "
            f"{node_def}."
        )
    for (sub, leaf), a in zip(node_leaves, got_leaves, strict=True):
        _given(a, leaf, (*path, *sub), out)


def _walk(spec, node, path, out):
    """Read the part of `spec` at theta0's `node` (at `path`): a dict (or a list or
    tuple with None for shared entries) goes down into `node`'s children; anything else
    is the starts of the whole part."""
    if spec is None:
        return
    children = _children(node)
    if isinstance(spec, Mapping):
        if not children:
            raise ValueError(
                f"`multistart` gives a dict for {_name(path)}, which is a leaf of theta0: "
                "give its starts as an array with a leading axis of starts."
            )
        by_key = {_raw(entry): (entry, child) for entry, child in children}
        for key, sub in spec.items():
            if key not in by_key:
                raise ValueError(
                    f"`multistart` names {_name((*path, _Entry(key)))}, which theta0 does not "
                    f"have; theta0's entries there: {list(by_key)}."
                )
            entry, child = by_key[key]
            _walk(sub, child, (*path, entry), out)
        return
    if isinstance(spec, (list, tuple)) and isinstance(node, (list, tuple)):
        if len(spec) != len(node):
            raise ValueError(
                f"`multistart` gives {len(spec)} entries for {_name(path)}, which has "
                f"{len(node)}; give None for the shared ones."
            )
        for (entry, child), sub in zip(children, spec, strict=True):
            _walk(sub, child, (*path, entry), out)
        return
    _given(spec, node, path, out)


class _Entry:
    """A path entry for a key theta0 does not have, written like a dict key."""

    def __init__(self, key):
        self.key = key

    def __str__(self):
        return f"[{self.key!r}]"


def theta_starts(multistart, theta0, n_x0_starts, x0_note=""):
    """theta0's parameter leaves with a leading axis of starts, from `fit`'s
    `multistart`, and the number of starts.

    **Arguments:**

    - `multistart`: True (every parameter leaf of `theta0` has its leading axis of starts)
        or a dict of starts for some parts of `theta0` (the rest shared).
    - `theta0`: `fit`'s theta0.
    - `n_x0_starts`: the number of starts on `x0`'s leading axis, or None where `x0` has
        none.
    - `x0_note`: what `x0`'s leading axis is instead, for the error where nothing has
        starts (with `window`: one state per window).

    **Returns:**

    `(params, n)`: theta0's parameter part with a leading axis of `n` starts on every leaf
    (NumPy arrays; a shared leaf repeated), and `n`.
    """
    params, _ = _pytree.split(theta0)
    if multistart is True and not jax.tree_util.tree_leaves(params):
        if n_x0_starts is None:
            raise ValueError(
                "with `multistart=True` and a `theta0` without parameters, the starts are "
                "the rows of `x0`: give x0 of shape (S, n_x), one row per start."
            )
        return params, n_x0_starts
    if multistart is True:
        sizes = {np.shape(a)[0] if np.ndim(a) else None for a in jax.tree_util.tree_leaves(params)}
        if len(sizes) != 1 or None in sizes:
            raise ValueError(
                "with `multistart=True` every parameter leaf of `theta0` needs the same "
                f"leading axis of starts; got leading sizes {sorted(map(str, sizes))}. To "
                "start some parameters only (a network in theta shared), pass them as "
                '`multistart={"name": starts, ...}`.'
            )
        n = sizes.pop()
        stacked = params
    elif isinstance(multistart, Mapping):
        given: dict = {}
        _walk(multistart, theta0, (), given)
        sizes = {_name(p): int(np.shape(a)[0]) for p, a in given.items()}
        if len(set(sizes.values())) > 1:
            raise ValueError(
                "`multistart`: every part given needs the same number of starts; got "
                + ", ".join(f"{k} {v}" for k, v in sizes.items())
                + "."
            )
        if not given and n_x0_starts is None:
            raise ValueError(
                "`multistart` names no parameter of theta0 and `x0` has no leading axis of "
                f"starts{x0_note}: there is nothing to start from."
            )
        n = next(iter(sizes.values())) if given else n_x0_starts

        def stack(path, leaf):
            a = given.get(tuple(path))
            return a if a is not None else np.broadcast_to(np.asarray(leaf), (n, *np.shape(leaf)))

        stacked = jax.tree_util.tree_map_with_path(stack, params)
    else:
        raise TypeError(
            "`multistart` must be a bool or a dict of starts for some parts of theta0 (e.g. "
            f'`{{"k": np.array([1.0, 2.0, 4.0])}}`), got {type(multistart).__name__}.'
        )
    if n_x0_starts is not None and n_x0_starts != n:
        raise ValueError(
            f"with `multistart`, `x0` with a leading axis of starts must have {n} starts like "
            f"`theta0`, got {n_x0_starts}."
        )
    if n < 1:
        raise ValueError("`multistart` needs at least one start; the leading axis has size 0.")
    for path, leaf in jax.tree_util.tree_leaves_with_path(stacked):
        # (a part given in a dict of starts is named where it came from)
        where = "multistart" if multistart is not True and tuple(path) in given else "theta0"
        check_finite_starts(leaf, f"{where}{jax.tree_util.keystr(path)}")
    return stacked, n


def check_finite_starts(starts, name):
    """A ValueError naming the starts (first axis) of `starts` that have a NaN or inf."""
    a = np.asarray(starts)
    if np.issubdtype(a.dtype, np.number) and not np.all(np.isfinite(a)):
        bad = np.unique(np.argwhere(~np.isfinite(a))[:, 0]).tolist()
        raise ValueError(
            f"`{name}` must be finite; the starts {bad} (first axis) have a NaN or inf entry."
        )


def check_fixed_starts(starts_flat, fixed_flat, theta, held=None):
    """A ValueError if the starts (S, p) of a multistart fit differ in a fixed entry of
    theta (`fixed_flat`, (p,)): a fixed entry keeps one value, so its starts would be
    silently dropped. `held`: theta0's own values (p,) where the starts of a dict
    `multistart` replace them: a fixed entry keeps that value, so starts that all differ
    from it alike would replace the held value in silence."""
    differ = fixed_flat & np.any(starts_flat != starts_flat[:1], axis=0)
    if held is not None and np.shape(held) == starts_flat.shape[1:]:
        differ |= fixed_flat & np.any(starts_flat != held.astype(starts_flat.dtype), axis=0)
    if differ.any():
        names = [n for n, d in zip(_pytree.indexed_names(theta), differ) if d]
        listed = names if len(names) <= 10 else [*names[:10], f"... ({len(names)} in all)"]
        raise ValueError(
            "`multistart` gives starts for fixed entries of theta "
            f"({', '.join(listed)}) that differ from each other or from theta0: a fixed entry "
            "keeps its value in theta0. Start only free entries, or free them in `fixed`."
        )


def check_held_x0_starts(x0_starts, x0_est, x0_held=None):
    """A ValueError if the x0 starts (S, N, n_x) of a multistart fit differ in an entry
    that `estimate_x0` holds (`x0_est`, (n_x,) False there; with a mask per record,
    `x0_held` (N, n_x) True where a record holds an entry the others estimate): a held
    entry keeps one value, so its starts would be silently dropped."""
    held = np.broadcast_to(~np.asarray(x0_est), x0_starts.shape[1:])
    if x0_held is not None:
        held = held | x0_held
    differ = held & np.any(x0_starts != x0_starts[:1], axis=0)
    if differ.any():
        raise ValueError(
            "`x0` gives different starts for initial-state entries that `estimate_x0` holds "
            f"(entries {sorted(set(np.nonzero(differ)[1].tolist()))}"
            + (
                f" of records {sorted(set(np.nonzero(differ)[0].tolist()))}"
                if x0_held is not None
                else ""
            )
            + "): a held entry keeps one value. "
            "Start only estimated entries, or estimate them (`estimate_x0`)."
        )
