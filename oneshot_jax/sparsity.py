r"""L1 and group-lasso regularisation as exact proximal steps, as optax transforms.

A sparse model (a dictionary of candidate terms with most coefficients exactly zero)
minimises C(theta) + g(theta), with C the multi-step cost of eq. (5) and g a non-smooth
penalty: g = lambda ||w||_1 (lasso) or g = lambda sum_G ||w_G||_2 (group lasso). g has no
gradient at zero, and a subgradient step never lands on zero. The proximal gradient step
(ISTA; Parikh and Boyd, "Proximal algorithms", 2014, Sec. 4.2) replaces it:

    theta+ = prox_{eta g}(theta - eta grad C(theta)),
    prox_{eta g}(v) = argmin_y  g(y) + ||y - v||^2 / (2 eta).

In closed form this is soft-thresholding for the L1 norm (Parikh and Boyd, Sec. 6.5.2),
prox(v)_i = sign(v_i) max(|v_i| - eta lambda, 0), and block soft-thresholding for the group
lasso (Sec. 6.5.4), prox(v)_G = max(1 - eta lambda / ||v_G||_2, 0) v_G. Both give exact
zeros, and a coordinate at zero stays there while |grad_i C| <= lambda.

Each factory returns a `ProximalTransformation`, the type of the projections of
`oneshot_jax.constraints` too (a projection is the prox of an indicator; see
`oneshot_jax._prox`): the map `prox(params, step_size)`, the penalty `value(params)`
= g(params), and an optax `GradientTransformation` (`init`, `update`) to chain *after* a
gradient step, whose update is `prox(params + updates, learning_rate) - params`.
`combine` (the same function as `constraints.combine`) composes regularisers and
projections: `l1`, then `group_lasso`, then `l2` (the order in which their composition is
the exact prox of the sum on shared entries), then the projections.

**Step sizes.** The threshold of coordinate i is `step_size_i * strength`; the prox must
be told the step of the update it follows.

- Plain gradient descent: `optax.chain(optax.sgd(eta), l1(lam, learning_rate=eta))` is
    exactly proximal gradient descent on C + g; its fixed points are the minimisers of
    C + g for convex C (the lasso solution, say).
- Adam: use `proximal_adam(eta, l1(lam))`. Adam moves coordinate i by a step
    d_i = eta / (sqrt(v_i) + eps) along its averaged gradient, and `proximal_adam` applies
    the prox with those same per-coordinate steps (the proximal step in Adam's diagonal
    metric, with sqrt(v_i) floored at lam so that no step moves a coordinate by much more
    than eta), so its fixed points are exactly the stationary points of C + g. Chaining
    `l1(lam, learning_rate=eta)` after `optax.adam(eta)` instead thresholds every
    coordinate at eta * lam: its fixed points are stationary points of the re-weighted
    penalty lam sum_i (sqrt(v_i) + eps) |theta_i|, whose weights vanish with the
    gradients, so full-batch training then gives few or no exact zeros.
- Any other solver calls `prox(params, step)` with the step it took (a scalar, or a
    pytree of per-coordinate steps >= 0; a zero step leaves its coordinate unchanged);
    `learning_rate` may be an optax schedule `count -> eta`.
- In `oneshot_jax.fit`, pass the regulariser as `regulariser=` (a list for several; the
    projections go in `constraints=`): the fit minimises C + g, `oneshot_jax.Adam`
    applies the prox with its own per-coordinate steps (as `proximal_adam`) and
    `oneshot_jax.Optax(transform)` with the regulariser's `learning_rate`.
    `fixed_zeros(result.theta, where)` then gives the `fixed=` mask of the zeros, to
    refit the selected terms alone with a least-squares solver (see `oneshot_jax.fit`).

**Weight decay** (an L2 penalty (lambda / 2) ||w||^2 on network weights) is smooth, but
its prox is exact too, w / (1 + step lambda): `l2(lam, where)` applies it like the others,
which is how to decay selected leaves of theta inside `oneshot_jax.fit` (whose optax
transforms see the flat free entries, not theta's leaves). In a hand-written loop over
theta, optax's masked transforms do the same with `mask` from this module, e.g.
`optax.adamw(eta, weight_decay=1e-4, mask=mask(lambda th: th["net"]))`.

**Selecting what is regularised** (`where`), as optax's masks:

- None: every floating leaf;
- a pytree of bools with the parameters' structure; for `l1` a leaf may also be a
    boolean array of the leaf's shape (entry by entry);
- a callable `params -> such a pytree`, e.g. `mask(lambda th: th["residual"].coef)`.

`params + (prox(...) - params)` is exactly 0 in floating point where the prox is 0, so
zeros survive `optax.apply_updates`.
"""

import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import is_concrete
from ._prox import (
    ProximalState,
    ProximalTransformation,
    check_non_negative_scalar,
    combine,
    penalty,
)
from ._solver.optax import ProximalAdamState, proximal_adam

__all__ = [
    "ProximalTransformation",
    "ProximalState",
    "ProximalAdamState",
    "l1",
    "l2",
    "group_lasso",
    "combine",
    "proximal_adam",
    "mask",
    "fixed_zeros",
    "soft_threshold",
    "block_soft_threshold",
]

# Bisection steps for the group prox with per-coordinate steps (each halves the bracket).
_BISECTION_STEPS = 80


def _as_float(v):
    """`v` as a JAX array of a floating (or complex) dtype: an integer or boolean input is
    computed in the default floating dtype (its threshold cast to the integer dtype would
    be truncated: 0.5 became 0)."""
    v = jnp.asarray(v)
    if not jnp.issubdtype(v.dtype, jnp.inexact):
        v = v.astype(jnp.result_type(float))
    return v


def _check_threshold(threshold, shape, against):
    """Refuse a threshold that is not real, whose shape does not broadcast to `shape`
    (that of `against`), or (where concrete) that is negative or not finite: a negative
    threshold pushes entries away from zero."""
    dtype = threshold.dtype if hasattr(threshold, "dtype") else np.asarray(threshold).dtype
    if np.dtype(dtype).kind not in "iuf":
        raise TypeError(
            f"`threshold` must be a real number >= 0 or an array of them, got {threshold!r}."
        )
    t_shape = np.shape(threshold)
    try:
        ok = np.broadcast_shapes(t_shape, shape) == tuple(shape)
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(
            f"`threshold` must be a scalar or an array that broadcasts to {against} "
            f"{tuple(shape)}, got shape {t_shape}."
        )
    if is_concrete(threshold):
        a = np.asarray(threshold)
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"`threshold` must be finite and >= 0, got {threshold!r}.")


def soft_threshold(v, threshold):
    """The proximal map of `threshold * ||.||_1`: sign(v) max(|v| - threshold, 0).

    `threshold` is a scalar >= 0 or an array of them that broadcasts to `v`'s shape
    (per-coordinate thresholds). Entries with |v| <= threshold become exactly +0.0 (Parikh
    and Boyd 2014, Sec. 6.5.2). An integer `v` is computed in the default floating dtype.
    """
    v = _as_float(v)
    _check_threshold(threshold, v.shape, "the shape of `v`")
    t = jnp.asarray(threshold, dtype=jnp.finfo(v.dtype).dtype)
    # `~(|v| <= t)`, not `|v| > t`: a NaN entry stays NaN (a failed step is not a zero).
    return jnp.where(jnp.abs(v) <= t, jnp.zeros_like(v), v - t * jnp.sign(v))


def block_soft_threshold(v, threshold, axis=None):
    """The proximal map of `threshold * sum_G ||v_G||_2`: max(1 - threshold / ||v_G||, 0) v_G.

    The groups G are the slices along `axis` (the axes the norm is taken over): `axis=None`
    makes the whole array one group, `axis=-1` makes each row of a matrix a group. A group
    with ||v_G|| <= threshold becomes exactly zero (Parikh and Boyd 2014, Sec. 6.5.4).
    `threshold` is a scalar >= 0, or an array of them (one per group) that broadcasts to
    the shape of the group norms (`v`'s with the `axis` axes of length 1). An integer `v`
    is computed in the default floating dtype.
    """
    v = _as_float(v)
    axis = _check_axes(_normalise_axis(axis), v.shape, "`v`")
    axes = range(v.ndim) if axis is None else (axis if isinstance(axis, tuple) else (axis,))
    axes = {a % v.ndim for a in axes}
    groups = tuple(1 if i in axes else n for i, n in enumerate(v.shape))
    _check_threshold(threshold, groups, "the shape of the group norms")
    t = jnp.asarray(threshold, dtype=jnp.finfo(v.dtype).dtype)
    norm = jnp.sqrt(jnp.sum(v * v, axis=axis, keepdims=True))
    keep = ~(norm <= t)  # (a NaN group stays NaN)
    safe = jnp.where(keep, norm, jnp.ones_like(norm))
    return jnp.where(keep, v * (1 - t / safe), jnp.zeros_like(v))


def _is_int(a):
    return isinstance(a, (int, np.integer)) and not isinstance(a, (bool, np.bool_))


def _normalise_axis(axis):
    """`axis` as None, an int or a tuple of distinct ints (NumPy integers as ints); a bool
    (an int to Python: True acted as axis 1) or a repeated axis is refused."""
    if axis is None:
        return None
    if _is_int(axis):
        return int(axis)
    if isinstance(axis, tuple) and all(_is_int(a) for a in axis):
        axes = tuple(int(a) for a in axis)
        if len(set(axes)) != len(axes):
            raise ValueError(f"`axis` must not repeat an axis, got {axis!r}.")
        return axes
    raise ValueError(f"`axis` must be None, an int or a tuple of ints, got {axis!r}.")


def _check_axes(axis, shape, what):
    """`axis` (normalised), after checking that its axes exist in an array of `shape` and
    are distinct there (-1 and 1 are one axis of a matrix)."""
    axes = () if axis is None else (axis if isinstance(axis, tuple) else (axis,))
    ndim = len(shape)
    for a in axes:
        if not -ndim <= a < ndim:
            raise ValueError(f"`axis` {axis} does not exist in {what} of shape {tuple(shape)}.")
    if len({a % ndim for a in axes}) != len(axes):
        raise ValueError(f"`axis` {axis} names one axis twice for {what} of shape {tuple(shape)}.")
    return axis


def _block_soft_threshold_metric(v, steps, strength, axis):
    """argmin_y strength sum_G ||y_G|| + sum_i (y_i - v_i)^2 / (2 steps_i), steps_i >= 0.

    Per group: y = 0 iff ||v / steps|| <= strength; otherwise y_i = v_i r / (r + strength
    steps_i) with r = ||y|| the root of sum_i v_i^2 / (r + strength steps_i)^2 = 1, which
    lies in [||v|| - strength max(steps), ||v|| - strength min(steps)] and is found by
    bisection (for equal steps the bracket is a point: block soft-thresholding). A zero
    step holds its coordinate (y_i = v_i, the limit steps_i -> 0): a group with a held
    non-zero entry is never zero.
    """
    d = jnp.broadcast_to(jnp.asarray(steps, v.dtype), v.shape)
    red = lambda a, f: f(a, axis=axis, keepdims=True)  # noqa: E731
    norm = jnp.sqrt(red(v * v, jnp.sum))
    moves = d > 0
    ratio = jnp.where(moves, v / jnp.where(moves, d, 1), jnp.where(v == 0, 0.0, jnp.inf))
    zero = jnp.sqrt(red(ratio**2, jnp.sum)) <= strength
    lo = jnp.maximum(norm - strength * red(d, jnp.max), 0)
    hi = jnp.maximum(norm - strength * red(d, jnp.min), lo)

    def bisect(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        above = red(v * v / (mid + strength * d) ** 2, jnp.sum) > 1
        return jnp.where(above, mid, lo), jnp.where(above, hi, mid)

    lo, hi = jax.lax.fori_loop(0, _BISECTION_STEPS, bisect, (lo, hi))
    r = 0.5 * (lo + hi)
    safe = jnp.where(zero, jnp.ones_like(r), r)
    return jnp.where(zero, jnp.zeros_like(v), v * (safe / (safe + strength * d)))


def mask(select: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """A `where` (or optax `mask`) that is True on the nodes `select(params)` picks.

    `select` is written like the `where` of `equinox.tree_at`: a function of the
    parameters returning one node or a tuple of nodes, e.g.
    `lambda theta: theta["residual"].coef` or `lambda theta: (theta["a"], theta["b"])`.
    Every floating leaf at or below a selected node is True (so `lambda theta:
    theta["r"]` selects an `MLP`'s weights and biases, not its activation function), every
    other leaf False.
    """
    if not callable(select):
        raise ValueError(f"`select` must be callable params -> node(s), got {select!r}.")

    return functools.partial(_masked, select)


def _masked(select, params):
    """`mask(select)(params)`."""
    false = jax.tree_util.tree_map(lambda _: False, params)
    mark = lambda node: jax.tree_util.tree_map(lambda _: True, node)  # noqa: E731
    try:
        picked = eqx.tree_at(select, false, replace_fn=mark)
    except Exception as err:  # noqa: BLE001 - re-raised naming the argument
        raise ValueError(
            f"`select` must pick nodes of the parameter pytree: {type(err).__name__}: {err}"
        ) from err
    # Only floating leaves are parameters: a module's activation function or integer
    # buffers below a selected node stay unselected.
    out = jax.tree_util.tree_map(lambda b, p: b and _is_float(p), picked, params)
    if not any(jax.tree_util.tree_leaves(out)):
        raise ValueError(
            "`select` picks no floating parameter (an activation function, a static "
            "field or an integer array is not a parameter): the regulariser would act on "
            "nothing."
        )
    return out


def fixed_zeros(theta, where=None):
    """The `fixed=` mask of `oneshot_jax.fit` that holds the exact zeros of a sparse fit.

    True at every selected entry of `theta` that is exactly 0, False elsewhere, so that
    `fit(..., fixed=fixed_zeros(result.theta, where))` refits the surviving terms alone
    (e.g. with `LevenbergMarquardt`, which removes the debiasing shrinkage of the L1
    penalty) while the deselected terms stay exactly zero.

    **Arguments:**

    - `theta`: the parameters (any pytree; equinox modules allowed), e.g. `result.theta`.
    - `where`: the entries that may be fixed, as the regulariser's `where` (None: every
        floating leaf; a pytree of bools or boolean arrays; or a callable, see `mask`).
        Pass the regulariser's `where` so that a physical parameter that happens to be 0
        stays free.

    **Returns:**

    A pytree of booleans with theta's structure: a boolean array per selected leaf, False
    for the other leaves.
    """
    sel = _resolve_where(where, theta, entries=True)
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    out = []
    for p, b in zip(leaves, sel):
        if b is False:
            out.append(False)
        else:
            out.append(np.asarray(b, bool) & (np.asarray(p) == 0))
    return jax.tree_util.tree_unflatten(treedef, out)


def _key(strength, where, *extra):
    """The factory's arguments as a hashable key (`_prox.Keyed`), or None: a strength
    that is a Python or NumPy scalar, and a `where` that is None, a function (by
    identity) or a pytree of Python bools."""
    if not isinstance(strength, (int, float, np.number)) or isinstance(strength, bool):
        return None
    if where is None or callable(where):
        w = where
    else:
        leaves, treedef = jax.tree_util.tree_flatten(where)
        if not all(isinstance(b, (bool, np.bool_)) for b in leaves):
            return None
        w = (treedef, tuple(bool(b) for b in leaves))
    return (type(strength), strength, w, *extra)


def _is_float(p):
    if isinstance(p, float):
        return True
    return hasattr(p, "dtype") and jnp.issubdtype(p.dtype, jnp.floating)


def _short(treedef, most=120):
    """A pytree structure in at most about `most` characters (a module's is long)."""
    text = str(treedef)
    return text if len(text) <= most else text[: most - 5] + " ...)"


def _resolve_where(where, params, entries):
    """`where` as a list (one per leaf of params) of False, True or a boolean array."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    if where is None:
        return [_is_float(p) for p in leaves]
    if callable(where):
        try:
            m = where(params)
        except Exception as err:  # noqa: BLE001 - re-raised naming the argument
            raise ValueError(
                "`where` must pick nodes of the parameter pytree (a callable `where` returns "
                "a pytree of bools of its structure; `sparsity.mask(select)` builds one): "
                f"{type(err).__name__}: {err}"
            ) from err
    else:
        m = where
    m_leaves, m_def = jax.tree_util.tree_flatten(m)
    if m_def != treedef:
        raise ValueError(
            "`where` must be a pytree of bools with the structure of the parameters (or a "
            f"callable returning one; `sparsity.mask(select)` builds one); got a structure "
            f"of {m_def.num_leaves} leaves, {_short(m_def)}, for parameters of "
            f"{treedef.num_leaves} leaves, {_short(treedef)}."
        )
    out = []
    for p, b in zip(leaves, m_leaves):
        # (a float or a string is no bool: bool(0.5) made `where={"a": 0.5}` act as True)
        dtype = np.dtype(b.dtype if hasattr(b, "dtype") else np.asarray(b).dtype)
        if dtype == np.bool_ and np.ndim(b) == 0 and is_concrete(b):
            b = bool(b)
        elif not entries:
            raise ValueError(
                "`where` must hold one bool per parameter leaf for `group_lasso` (a group "
                f"is a slice of a whole leaf), got {dtype} of shape {np.shape(b)}."
            )
        elif np.shape(b) != np.shape(p) or dtype != np.bool_:
            raise ValueError(
                "`where` leaves must be bools or boolean arrays of the parameter's shape "
                f"{np.shape(p)}, got {dtype} of shape {np.shape(b)}."
            )
        if b is not False and not _is_float(p):
            raise ValueError(
                f"`where` selects a parameter of dtype {jnp.result_type(p)}; only floating "
                "parameters can be regularised."
            )
        out.append(b)
    return out


def _step_leaves(step, params):
    """A scalar step for every leaf, or the leaves of a pytree of per-coordinate steps."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    if not isinstance(step, (dict, list, tuple, eqx.Module)) and np.ndim(step) == 0:
        return [step] * len(leaves), True
    s_leaves, s_def = jax.tree_util.tree_flatten(step)
    if s_def != treedef:
        raise ValueError(
            "`step_size` must be a scalar or a pytree with the structure of the parameters, "
            f"got structure {s_def} for parameters {treedef}."
        )
    for i, (s, p) in enumerate(zip(s_leaves, leaves)):
        if np.ndim(s) and np.shape(s) != np.shape(p):
            raise ValueError(
                f"`step_size`: its leaf {i} must be a scalar or have its parameter's shape "
                f"{np.shape(p)}, got {np.shape(s)}."
            )
    return s_leaves, False


def _check_step(s):
    """Refuse a concrete negative or non-finite step of a selected leaf: the prox's
    threshold step * strength would push its entries away from zero."""
    if is_concrete(s):
        a = np.asarray(s)
        if a.dtype.kind not in "iuf" or not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"`step_size` must be finite and >= 0, got {s!r}.")


def _map_selected(fn, params, sel, step_size):
    """`fn(leaf, step, scalar_step)` on the selected leaves; the others are untouched."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    steps, scalar = _step_leaves(step_size, params)
    out = []
    for p, b, s in zip(leaves, sel, steps):
        if b is False:
            out.append(p)
            continue
        _check_step(s)
        p = jnp.asarray(p)  # (a Python float leaf is a parameter too)
        new = fn(p, jnp.asarray(s, p.dtype), scalar)
        out.append(new if b is True else jnp.where(b, new, p))
    return jax.tree_util.tree_unflatten(treedef, out)


# The regularisers' maps, as module-level functions: partials of them pickle (a process
# pool takes the regularisers) where `where` does.


def _l1_prox(strength, where, params, step_size):
    sel = _resolve_where(where, params, entries=True)
    return _map_selected(lambda p, s, _: soft_threshold(p, s * strength), params, sel, step_size)


def _l1_value(strength, where, params):
    sel = _resolve_where(where, params, entries=True)
    total = 0.0
    for p, b in zip(jax.tree_util.tree_leaves(params), sel):
        if b is not False:
            total = total + jnp.sum(jnp.where(b, jnp.abs(p), 0))
    return strength * total


def _l2_prox(strength, where, params, step_size):
    sel = _resolve_where(where, params, entries=True)
    return _map_selected(lambda p, s, _: p / (1 + s * strength), params, sel, step_size)


def _l2_value(strength, where, params):
    sel = _resolve_where(where, params, entries=True)
    total = 0.0
    for p, b in zip(jax.tree_util.tree_leaves(params), sel):
        if b is not False:
            total = total + jnp.sum(jnp.where(b, p * p, 0))
    return 0.5 * strength * total


def _group_lasso_prox(strength, where, axis, params, step_size):
    sel = _resolve_where(where, params, entries=False)

    def one(p, s, scalar):
        _check_axes(axis, jnp.shape(p), "a selected parameter")
        if scalar:
            return block_soft_threshold(p, s * strength, axis=axis)
        return _block_soft_threshold_metric(p, s, jnp.asarray(strength, p.dtype), axis)

    return _map_selected(one, params, sel, step_size)


def _group_lasso_value(strength, where, axis, params):
    sel = _resolve_where(where, params, entries=False)
    total = 0.0
    for p, b in zip(jax.tree_util.tree_leaves(params), sel):
        if b:
            _check_axes(axis, jnp.shape(p), "a selected parameter")
            total = total + jnp.sum(jnp.sqrt(jnp.sum(p * p, axis=axis)))
    return strength * total


def l1(strength, where=None, *, learning_rate=None) -> ProximalTransformation:
    """L1 regularisation `strength * ||w||_1` as an exact proximal (soft-thresholding) step.

    `optax.chain(optax.sgd(eta), l1(lam, learning_rate=eta))` is proximal gradient descent
    (ISTA) on C + lam ||w||_1; `proximal_adam(eta, l1(lam))` is its Adam counterpart.

    **Arguments:**

    - `strength`: lambda >= 0, the weight of the L1 norm in the objective.
    - `where`: which parameters (or entries) carry the penalty: None (every floating
        leaf), a pytree of bools or boolean arrays, or a callable returning one (`mask`).
    - `learning_rate`: only to chain the transform after an optimiser: the step size eta
        of that optimiser (a scalar > 0 or an optax schedule `count -> eta`).

    **Returns:**

    A `ProximalTransformation`: `prox(params, step_size)` soft-thresholds the selected
    entries at `step_size * strength` (`step_size` a scalar or a pytree of per-coordinate
    steps), and `value(params)` is `strength * sum |w|` over them.
    """
    check_non_negative_scalar(strength, "strength")
    prox = functools.partial(_l1_prox, strength, where)
    value = functools.partial(_l1_value, strength, where)
    return penalty(prox, value, strength, learning_rate, "l1", _key(strength, where))


def l2(strength, where=None, *, learning_rate=None) -> ProximalTransformation:
    """Weight decay `(strength / 2) ||w||^2` as an exact proximal step (a shrinkage).

    prox(v)_i = v_i / (1 + step_i strength): the implicit step on the penalty, stable for
    any step. No exact zeros (the penalty is smooth); with `proximal_adam` or `fit`'s
    `Adam` it is weight decay in Adam's diagonal metric.

    **Arguments:**

    - `strength`: lambda >= 0.
    - `where`, `learning_rate`: as for `l1`.

    **Returns:**

    A `ProximalTransformation`.
    """
    check_non_negative_scalar(strength, "strength")
    prox = functools.partial(_l2_prox, strength, where)
    value = functools.partial(_l2_value, strength, where)
    return penalty(prox, value, strength, learning_rate, "l2", _key(strength, where))


def group_lasso(strength, where=None, *, axis=None, learning_rate=None) -> ProximalTransformation:
    """Group lasso `strength * sum_G ||w_G||_2` as an exact (block soft-thresholding) prox.

    Zeroes whole groups: a dictionary term in every output (the rows of the coefficient
    matrix, `axis=-1`), an input of a layer (the columns of an `equinox.nn.Linear` weight,
    `axis=0`), or a whole leaf (`axis=None`). Every group has the same weight (no
    sqrt(group size) factor).

    **Arguments:**

    - `strength`: lambda >= 0.
    - `where`: which leaves carry the penalty (None: every floating leaf; a pytree of
        bools, one per leaf; or a callable returning one, see `mask`).
    - `axis`: the axes of a leaf that a group norm is taken over; every index of the
        remaining axes is one group. None makes each selected leaf a single group.
    - `learning_rate`: as for `l1`.

    **Returns:**

    A `ProximalTransformation`. With a scalar `step_size` its prox is block
    soft-thresholding at `step_size * strength`; with per-coordinate steps (as in
    `proximal_adam`) it is the exact prox in that diagonal metric, y_G = v_G r / (r +
    lambda steps_G) with r = ||y_G|| found by bisection.
    """
    check_non_negative_scalar(strength, "strength")
    axis = _normalise_axis(axis)
    prox = functools.partial(_group_lasso_prox, strength, where, axis)
    value = functools.partial(_group_lasso_value, strength, where, axis)
    return penalty(prox, value, strength, learning_rate, "group_lasso", _key(strength, where, axis))
