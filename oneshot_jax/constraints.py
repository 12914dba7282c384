"""Projections onto convex parameter sets, Section 3.3 of the paper, as optax transforms.

"In case we need to constrain the parameters into a specified convex set, we can enhance
the identification algorithm introducing a projection step immediately after the parameters
update." A projection P onto a convex set is the proximal map of the set's indicator, so
each factory here returns a `ProximalTransformation` (the one type of projections and of
the regularisers of `oneshot_jax.sparsity`, see `oneshot_jax._prox`): `project` is P
itself, `prox(params, step_size)` is P whatever the step, `value` is 0, and it is an optax
`GradientTransformation` (chain it last, like `optax.keep_params_nonnegative`) whose
update is `P(params + updates) - params`.

In floating point, `params + (P(params + u) - params)` can land one ulp outside the set, so
`fit` projects the parameters again after `optax.apply_updates`: every iterate of `fit` is
exactly feasible (for one set; the projection onto an intersection, Dykstra's, is capped at
its cycles, and `fit` checks the estimate against each set). Do the same in a hand-written
loop: `params = tx.project(params)`.

Box-type sets (`non_negative`, `positive`, `box`) also expose their bounds, which the
least-squares solvers of `fit` use for an exact active-set treatment.

`fit(constraints=...)` takes the projections; the proximal regularisers of
`oneshot_jax.sparsity` (`l1`, `group_lasso`, `l2`) go in `fit(regulariser=...)`: the fit
then minimises C + g(theta), applying the prox (with the solver's step sizes) before the
projection after every update. `combine` (the same function as `sparsity.combine`)
composes projections and regularisers: the regularisers (`l1`, then `group_lasso`, then
`l2`: the order in which their composition is the prox of the sum), then the projections.

A caveat on projected Adam (Algorithm 1 with a projection): for a box the projection acts
per coordinate, like Adam's scaling, and the iterates reach the constrained optimum. For a
general convex set (`project(fn)`, e.g. a half-space) Adam's per-coordinate step sizes do
not match the Euclidean projection, so projected Adam can settle at a feasible point that
is not the constrained optimum; use plain gradient descent (`optax.sgd`) or a
least-squares solver there.
"""

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._checks import is_concrete
from ._prox import ProximalTransformation, combine, indicator

__all__ = [
    "ProximalTransformation",
    "ProjectionTransformation",
    "non_negative",
    "positive",
    "box",
    "project",
    "combine",
]

ProjectionTransformation = ProximalTransformation
"""The type of the projections, the same as `ProximalTransformation` (a projection is the
prox of its set's indicator): `project` is the projection P, `bounds` a box's bounds (None
for a general convex set). The name of oneshot_jax 0.2, kept."""


def _dtype(p):
    """A leaf's dtype: its own where it has one (no JAX dtype promotion on the host), and
    a float one for an integer or bool leaf (a bound of 2.2 or -inf on an integer
    parameter is not an integer)."""
    dtype = getattr(p, "dtype", None)
    dtype = jnp.result_type(p) if dtype is None else dtype
    return dtype if jnp.issubdtype(dtype, jnp.inexact) else jnp.result_type(dtype, 1.0)


def _fill_like(bound, params, fill, name, where=""):
    """Broadcast a bound (scalar, pytree like params, or a partial dict) onto params
    (`where`: the path of params in theta, for the messages)."""
    # Bounds are constants: NumPy builds them without a JAX dispatch per leaf.
    if bound is None:
        return jax.tree_util.tree_map(lambda p: np.full(np.shape(p), fill, _dtype(p)), params)
    if isinstance(params, dict) and isinstance(bound, dict):
        bound = _pytree.nest_dotted(bound, params, name)
        unknown = set(bound) - set(params)
        if unknown:
            raise ValueError(
                f"`{name}` names parameters that are not in theta: {sorted(unknown, key=str)}; "
                f"theta has {sorted(params, key=str)}."
            )
        return {
            k: _fill_like(bound.get(k), v, fill, name, f"{where}.{k}" if where else str(k))
            for k, v in params.items()
        }
    if isinstance(params, eqx.Module) and type(bound) is type(params):
        # (a module of bounds, theta's own class: field by field, a None field unbounded,
        # a network's among them; flattened whole, its None fields had no leaves)
        bound = {
            f.name: getattr(bound, f.name)
            for f in dataclasses.fields(params)
            if not f.metadata.get("static", False)
        }
    if isinstance(params, eqx.Module) and isinstance(bound, dict):
        # (a module's fields by name, as `fit`'s `fixed` and `units` take them)
        fields = [f.name for f in dataclasses.fields(params) if not f.metadata.get("static", False)]
        unknown = set(bound) - set(fields)
        if unknown:
            raise ValueError(
                f"`{name}` names fields that are not in theta's {type(params).__name__}: "
                f"{sorted(unknown, key=str)}; it has {fields}."
            )
        held = [f for f in fields if jax.tree_util.tree_leaves(getattr(params, f))]
        return eqx.tree_at(
            lambda m: [getattr(m, f) for f in held],
            params,
            [
                _fill_like(bound.get(f), getattr(params, f), fill, name, f"{where}.{f}".lstrip("."))
                for f in held
            ],
        )
    if isinstance(bound, (list, tuple)) and isinstance(params, (list, tuple)):
        if len(bound) != len(params):
            raise ValueError(f"`{name}` must have one entry per parameter leaf ({len(params)}).")
        filled = [_fill_like(b, p, fill, name) for b, p in zip(bound, params)]
        # (a NamedTuple takes its fields as arguments, a list or tuple one iterable)
        return type(params)(*filled) if hasattr(params, "_fields") else type(params)(filled)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    # A pytree of theta's own structure (an equinox module of bounds, say; None leaves
    # unbounded), leaf by leaf.
    b_leaves, b_def = jax.tree_util.tree_flatten(bound, is_leaf=lambda b: b is None)
    if len(leaves) > 1 and b_def == treedef:
        return jax.tree_util.tree_unflatten(
            treedef, [_fill_like(b, p, fill, name) for b, p in zip(b_leaves, leaves)]
        )
    given = bound
    if isinstance(bound, (list, tuple)) and any(b is None for b in bound):
        # (a list of numbers with None entries: those entries unbounded, as a None bound)
        bound = [fill if b is None else b for b in bound]
    kind = getattr(np.asarray(bound) if is_concrete(bound) else bound, "dtype", None)
    if isinstance(bound, (str, bytes, bool, np.bool_)) or (
        kind is not None and np.dtype(kind).kind not in "iuf"
    ):
        raise ValueError(f"`{name}` must hold real numbers (a bound), got {given!r}.")
    if (np.ndim(bound) if is_concrete(bound) else jnp.ndim(bound)) == 0 or len(leaves) == 1:
        xp = np if is_concrete(bound) else jnp
        b = xp.asarray(bound)
        out = []
        for p in leaves:
            try:
                out.append(xp.broadcast_to(b, np.shape(p)).astype(_dtype(p)))
            except ValueError as err:
                of = f" {where!r}" if where else ""
                raise ValueError(
                    f"`{name}` of shape {b.shape} does not fit the parameter{of} of shape "
                    f"{np.shape(p)}."
                ) from err
        return jax.tree_util.tree_unflatten(treedef, out)
    raise ValueError(f"`{name}` must be a scalar or have the structure of the parameters.")


def box(lower=None, upper=None) -> ProximalTransformation:
    """Projection onto the box `lower <= params <= upper` (elementwise clipping).

    **Arguments:**

    - `lower`, `upper`: a scalar (every element), a pytree with the parameters' structure
        (leaves broadcast to each parameter's shape), or for dict parameters a dict naming
        some of them (a nested one as `{"phys": {"c": 0.0}}` or `{"phys.c": 0.0}`), and
        for an equinox module a dict naming some of its fields; missing entries and None
        (also an entry of a list of numbers: `[0.0, None]`) mean unbounded (-inf / +inf).

    **Returns:**

    A `ProximalTransformation` (the prox of the box's indicator: elementwise clipping,
    whatever the step) with `bounds`.
    """
    kinds = [(_value_key(b) or ("other",))[0] for b in (lower, upper)]
    if kinds == ["scalar", "scalar"] and lower > upper:  # (`bounds` checks the rest)
        raise ValueError(f"`box` needs lower <= upper, got lower {lower!r} > upper {upper!r}.")

    bounds = _BoxBounds(lower, upper)
    return indicator(functools.partial(_clip, bounds), bounds)


def _clip(bounds, params):
    lo, hi = bounds(params)
    return jax.tree_util.tree_map(lambda p, a, b: jnp.clip(p, a, b), params, lo, hi)


class _BoxBounds:
    """`box`'s bounds, `params -> (lower, upper)` pytrees shaped like `params`. Bounds
    made of scalars (or dicts of them) have a `key` that names them by value (others have
    none): `fit` keeps what it derives from equal boxes (a `positive()` made anew on every
    call) between calls."""

    __slots__ = ("lower", "upper", "key")

    def __init__(self, lower, upper):
        self.lower, self.upper = lower, upper
        key = (_value_key(lower), _value_key(upper))
        if None not in key:  # (else no `key`, as for any other bounds)
            self.key = ("box", *key)

    def __call__(self, params):
        lower, upper = self.lower, self.upper
        lo = _fill_like(lower, params, -jnp.inf, "lower")
        hi = _fill_like(upper, params, jnp.inf, "upper")
        bad = jax.tree_util.tree_map(lambda a, b: a > b, lo, hi)
        if is_concrete(bad) and any(bool(np.any(b)) for b in jax.tree_util.tree_leaves(bad)):
            a, b = _pytree.flat_host(lo), _pytree.flat_host(hi)
            wrong = [
                f"{n} (lower {x:g} > upper {y:g})"
                for n, x, y in zip(_pytree.leaf_names(lo), a, b)
                if x > y
            ]
            more = f" and {len(wrong) - 8} more" if len(wrong) > 8 else ""
            raise ValueError(
                "`box` needs lower <= upper for every parameter; it is not so for "
                f"{', '.join(wrong[:8])}{more}."
            )
        for name, bound, wrong, what in (
            ("lower", lo, np.inf, "+inf (use None or -inf for no lower bound)"),
            ("upper", hi, -np.inf, "-inf (use None or +inf for no upper bound)"),
        ):
            for leaf in jax.tree_util.tree_leaves(bound):
                if not is_concrete(leaf):
                    continue
                if np.any(np.isnan(leaf)):
                    raise ValueError(f"`box`: `{name}` holds NaN: a bound must be a number.")
                if np.any(leaf == wrong):
                    raise ValueError(f"`box`: `{name}` holds {what}: no value satisfies it.")
        return lo, hi


def _value_key(bound):
    """A hashable stand-in for a bound made of Python or NumPy scalars (None, a scalar, or
    a dict of these), or None for any other bound."""
    if bound is None:
        return ("none",)
    if isinstance(bound, (int, float, np.number)) and not isinstance(bound, bool):
        return ("scalar", bound)
    if isinstance(bound, dict) and all(isinstance(k, str) for k in bound):
        items = tuple((k, _value_key(v)) for k, v in sorted(bound.items()))
        if all(v is not None for _, v in items):
            return ("dict", items)
    return None


def non_negative() -> ProximalTransformation:
    """Projection onto `params >= 0` (the paper's theta_i > 0 up to the boundary)."""
    return box(lower=0.0)


def positive(eps: float = 1e-12) -> ProximalTransformation:
    """Projection onto `params >= eps`, a closed stand-in for the open set `params > 0`."""
    try:
        ok = not isinstance(eps, (str, bytes, bool, np.bool_)) and np.ndim(eps) == 0
        ok = ok and not np.iscomplexobj(eps) and 0 < float(eps) < np.inf
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`eps` must be a finite number > 0, got {eps!r}.")
    return box(lower=eps)


def project(fn: Callable[[Any], Any]) -> ProximalTransformation:
    """A user projection `fn(params) -> params` onto a convex set, as a transform.

    `fn` must be idempotent (a projection); for sets that are not boxes the least-squares
    solvers of `fit` apply it after each step (a projected step) without an active set.
    """
    if not callable(fn):
        raise ValueError(f"`fn` must be callable params -> params, got {fn!r}.")
    return indicator(fn)
