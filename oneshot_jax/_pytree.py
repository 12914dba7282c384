"""Parameter pytrees on the host: trainable and static parts, flattening, names.

theta may be any pytree: a dict of named physical parameters, or one that also holds
equinox modules (a neural-network residual) whose leaves include functions and other
non-numeric parts. The library trains the floating leaves and carries the rest (functions,
integer and boolean arrays) as static data, so a user never calls `eqx.partition`
themselves.
"""

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree


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


@functools.lru_cache(maxsize=256)
def unravel_for(treedef, shapes, dtype):
    # Traced on abstract values: the inverse holds only the structure, shapes and dtype,
    # and nothing is computed (or compiled) to make it.
    out = []
    structs = [jax.ShapeDtypeStruct(shape, dtype) for shape in shapes]
    jax.eval_shape(
        lambda leaves: out.append(ravel_pytree(jax.tree_util.tree_unflatten(treedef, leaves))[1]),
        structs,
    )
    return out[0]


def ravel(tree):
    """`jax.flatten_util.ravel_pytree` of a tree of arrays of one dtype, on the host:
    the flat NumPy array and the (traceable) inverse, the same object for every tree of
    one structure, shapes and dtype."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    flat = flat_host(leaves) if leaves else np.zeros(0, jnp.result_type(float))
    unravel = unravel_for(treedef, tuple(np.shape(a) for a in leaves), flat.dtype)
    return flat, unravel


def unflatten_rows(rows, like, squeeze=False):
    """Rows of flattened parameters (E, n) as the pytree `like` with a leading axis E
    (the first row without it, with `squeeze`): the NumPy inverse of `flat_host`
    (`Layout`)."""
    lay = layout(like)
    return lay.one(np.asarray(rows)[0]) if squeeze else lay.rows(rows)


class Layout:
    """The structure and shapes of a parameter pytree, kept per structure (`layout`): the
    NumPy inverse of `flat_host` for one flat vector or rows of them, and the entries'
    names (`leaf_names`), without flattening the tree again."""

    __slots__ = ("treedef", "shapes", "bounds", "_names", "_free")

    def __init__(self, treedef, shapes):
        self.treedef, self.shapes = treedef, shapes
        ends = np.cumsum([int(np.prod(shape, dtype=int)) for shape in shapes]).tolist()
        self.bounds = tuple(zip([0, *ends[:-1]], ends))
        self._names = None
        self._free = {}

    def one(self, flat):
        """A flat vector (n,) as the pytree."""
        flat = np.asarray(flat)
        leaves = [flat[a:b].reshape(shape) for (a, b), shape in zip(self.bounds, self.shapes)]
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def rows(self, rows):
        """Rows (E, n) as the pytree with a leading axis E."""
        rows = np.asarray(rows)
        E = rows.shape[0]
        leaves = [
            rows[:, a:b].reshape(E, *shape) for (a, b), shape in zip(self.bounds, self.shapes)
        ]
        return jax.tree_util.tree_unflatten(self.treedef, leaves)

    def names(self, free=None) -> tuple[str, ...]:
        """`leaf_names` of the tree, of the entries `free` only where given."""
        if self._names is None:
            like = jax.tree_util.tree_unflatten(
                self.treedef, [np.zeros(shape) for shape in self.shapes]
            )
            self._names = leaf_names(like)
        if free is None or len(free) == len(self._names):
            return self._names
        names = self._free
        return kept(names, tuple(free), lambda: tuple(self._names[i] for i in free), size=8)


_LAYOUTS: dict = {}


def layout(tree) -> Layout:
    """The `Layout` of `tree` (its structure and leaf shapes), kept between calls."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    shapes = tuple(np.shape(a) for a in leaves)
    return kept(_LAYOUTS, (treedef, shapes), lambda: Layout(treedef, shapes))


def module_entries(theta) -> np.ndarray:
    """Per entry of theta's flattened parameters (`ravel` of `split(theta)[0]`): True where
    it belongs to an equinox module below the root (a neural residual's weights), False for
    the named (physical) parameters."""
    params, _ = split(theta)

    def is_module(node):
        return isinstance(node, eqx.Module) and node is not params

    def mark(node):
        flag = is_module(node)
        return jax.tree_util.tree_map(lambda a: np.full(np.shape(a), flag, bool), node)

    marked = jax.tree_util.tree_map(mark, params, is_leaf=is_module)
    leaves = jax.tree_util.tree_leaves(marked)
    return np.concatenate([np.ravel(a) for a in leaves]) if leaves else np.zeros(0, bool)


def leaf_dtype(leaf):
    """A leaf's own dtype (a JAX or NumPy array's, a NumPy scalar's), else NumPy's for a
    Python scalar: `np.result_type` of a JAX array is deprecated."""
    dtype = getattr(leaf, "dtype", None)
    return np.result_type(leaf) if dtype is None else dtype


def kept(cache: dict, key, make, size: int = 256):
    """`make()`, kept in `cache` under `key` (what depends only on a structure, kept
    between calls); the oldest entry is dropped past `size`, and an unhashable `key`
    keeps nothing."""
    try:
        found = cache.get(key)
    except TypeError:
        return make()
    if found is None:
        if len(cache) >= size:
            cache.pop(next(iter(cache)))
        found = cache[key] = make()
    return found


def _key(entry) -> str:
    for attr in ("key", "idx", "name"):
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def named_mask(names, theta, name) -> np.ndarray:
    """Flat boolean mask (leaf order) of theta's entries under the dotted `names` ("k",
    "phys.c", a module's field "r" or "r.layers"): a leaf is selected where its path is a
    name or lies below one. A name that selects nothing is a ValueError (`name`: the
    argument) listing the names theta has."""
    flat = jax.tree_util.tree_flatten_with_path(theta)[0]
    paths = [".".join(_key(p) for p in path) for path, _ in flat]
    hit = set()
    parts = []
    for path, (_, leaf) in zip(paths, flat):
        under = [n for n in names if path == n or path.startswith(n + ".")]
        hit.update(under)
        parts.append(np.full(int(np.size(leaf)), bool(under)))
    unknown = [n for n in names if n not in hit]
    if unknown:
        raise ValueError(
            f"`{name}` names parameters that are not in theta0: {unknown}; theta0 has {paths}."
        )
    return np.concatenate(parts) if parts else np.zeros(0, bool)


def nest_dotted(named, theta, name):
    """A dict over theta's dict keys, with dotted names ("phys.k", as the printout and
    `units` name a nested parameter, or "net.a", a field of an equinox module in theta)
    turned into nested dicts ({"phys": {"k": ...}}), so that `fixed=`, the bounds and
    `multistart=` take either spelling. A key of theta that holds a dot
    is kept as it is; naming one parameter both ways is an error (`name`: the argument)."""
    if not (isinstance(named, dict) and isinstance(theta, dict)):
        return named
    out = {}
    for key, value in named.items():
        head, _, rest = str(key).partition(".")
        if key in theta or not rest or not isinstance(theta.get(head), (dict, eqx.Module)):
            parts = [(key, value)]
        else:
            parts = [(head, {rest: value})]
        for k, v in parts:
            if k in out:
                both = isinstance(out[k], dict) and isinstance(v, dict)
                if not both or set(out[k]) & set(v):
                    raise ValueError(f"`{name}` names a parameter twice (dotted and nested).")
                v = {**out[k], **v}
            out[k] = v
    return {k: nest_dotted(v, theta[k], name) if k in theta else v for k, v in out.items()}


def ordered_like(tree, like):
    """`tree` with the keys of its dicts in the order written in `like` (JAX returns them
    sorted): the same pytree, so that a fit started from a result's theta prints its
    parameters in the order of the first fit's theta0."""
    # (a plain dict only: a subclass, an OrderedDict or a user's attribute dict, is a
    # node of its own type, which a plain dict in its place would change)
    if type(tree) is dict and isinstance(like, dict):
        keys = [k for k in like if k in tree] + [k for k in tree if k not in like]
        return {k: ordered_like(tree[k], like.get(k)) for k in keys}
    return tree


def ordered_by_names(tree, names):
    """`tree` with the keys of its dicts in the order of `names`, rows written as paths
    ("k", "phys.c": `FitResult.theta_order`), for a theta rebuilt in JAX's sorted order
    (`load_result`)."""
    like: dict = {}
    for name in names:
        node = like
        for part in str(name).split("."):
            node = node.setdefault(part, {})
    return ordered_like(tree, like)


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


@functools.cache
def _fields(cls):
    """(the field names, the defaults of the fields that have one: a value, or a factory
    marked by `_FACTORY`)."""
    names, defaults = [], {}
    for f in dataclasses.fields(cls):
        names.append(f.name)
        if f.default_factory is not dataclasses.MISSING:
            defaults[f.name] = (_FACTORY, f.default_factory)
        elif f.default is not dataclasses.MISSING:
            defaults[f.name] = (None, f.default)
    return frozenset(names), defaults


_FACTORY = object()


def build(cls, **fields):
    """`cls(**fields)` for an equinox module without `__init__` logic or checks of its own
    (`FitProblem`, `FitResult`, `FitHistory`), built from checked parts on every `fit`:
    the fields are set as equinox's own unflattening sets them (defaults filled in),
    without `Module.__init__`'s walk over every leaf of every argument (the model and
    theta included), which costs more than the rest of a fit's host-side work."""
    names, defaults = _fields(cls)
    if not names.issuperset(fields):
        raise TypeError(f"{cls.__name__}: unknown fields {sorted(set(fields) - names)}.")
    if len(fields) < len(names):
        for name, (kind, value) in defaults.items():
            if name not in fields:
                fields[name] = value() if kind is _FACTORY else value
        if len(fields) < len(names):
            raise TypeError(
                f"{cls.__name__}: field(s) {sorted(names - set(fields))} was not given."
            )
    self = object.__new__(cls)
    object.__getattribute__(self, "__dict__").update(fields)
    return self


def pack(tree):
    """A pytree of arrays as one flat array per dtype, and the layout to rebuild it
    (`unpack`): inside a compiled call, so that its output reaches the host as a few
    buffers rather than one per leaf. Only data movement: the values are unchanged."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    groups: dict = {}
    items = []
    for leaf in leaves:
        leaf = jnp.asarray(leaf)
        group = groups.setdefault(leaf.dtype, [])
        start = sum(a.size for a in group)
        group.append(leaf.reshape(-1))
        items.append((leaf.dtype, start, start + leaf.size, leaf.shape))
    dtypes = tuple(groups)
    index = {d: k for k, d in enumerate(dtypes)}
    items = tuple((index[d], start, stop, shape) for d, start, stop, shape in items)
    buffers = tuple(jnp.concatenate(groups[d]) for d in dtypes)
    return buffers, (treedef, items)


def _to_host(a):
    """A NumPy copy of `a`, gathered from every process where its shards span several
    hosts (a fleet sharded with `oneshot_jax.sharding` after `jax.distributed.initialize`:
    every process runs the same program, so every one gathers)."""
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def unpack(buffers, layout):
    """The pytree `pack` packed, as NumPy views of the (host) buffers."""
    treedef, items = layout
    host = [_to_host(b) for b in buffers]
    leaves = [host[k][start:stop].reshape(shape) for k, start, stop, shape in items]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def indexed_names(theta) -> tuple[str, ...]:
    """One name per scalar of theta as a user indexes it (`theta['k12']`,
    `theta['I'][2]`, `theta['net'].layers[0].weight[1, 3]`): the names of warnings that
    point at entries of theta. (`leaf_names` gives the short names of `FitResult.names`.)"""
    names = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(theta)[0]:
        base = "theta" + jax.tree_util.keystr(path)
        if np.ndim(leaf) == 0:
            names.append(base)
        else:
            names.extend(f"{base}[{', '.join(map(str, ix))}]" for ix in np.ndindex(np.shape(leaf)))
    return tuple(names)
