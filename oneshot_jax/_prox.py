r"""The proximal transformation: one type for the projections of `oneshot_jax.constraints`
(Section 3.3 of the paper) and the regularisers of `oneshot_jax.sparsity`.

The proximal map of a convex function g with step eta (Parikh and Boyd, "Proximal
algorithms", 2014, Sec. 1.1),

    prox_{eta g}(v) = argmin_y  g(y) + ||y - v||^2 / (2 eta),

is the Euclidean projection onto a convex set S when g is the indicator of S (0 on S,
+inf outside; Parikh and Boyd, Sec. 1.2), whatever the step. So the paper's "projection
step immediately after the parameters update" (Section 3.3) and the proximal gradient
step on C + g (ISTA, Parikh and Boyd, Sec. 4.2),

    theta+ = prox_{eta g}(theta - eta grad C(theta)),

are one operation. A `ProximalTransformation` holds the map `prox(params, step_size)`,
the value `value(params)` = g(params) (0 for an indicator: its iterates stay in its set),
for an indicator the projection `project` and, for a box, its `bounds`; and, as an optax
`GradientTransformation` (`init`, `update`), the adapter that applies the prox after an
optimiser's update (chain it last, like `optax.keep_params_nonnegative`): the update is
`prox(params + updates, eta) - params`, with eta the transformation's `learning_rate` at
the update count (a projection takes no step). `combine` composes any of them in order.

`fit(constraints=..., regulariser=...)` takes them apart (`split`): the projections make
the feasible set (the least-squares solvers of `fit` use a box's bounds for an exact
active set), the regularisers the objective C + g. The proximal optimiser that matches
the prox to Adam's per-coordinate steps is `oneshot_jax._solver.optax.proximal_adam`,
beside `Adam`.
"""

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import _pytree
from ._caller_warnings import warn
from ._checks import is_concrete

__all__ = ["ProximalTransformation", "ProximalState", "combine"]


class ProximalTransformation(NamedTuple):
    """A proximal map of a convex function g, and an optax transform that applies it.

    A projection onto a convex set is the proximal map of the set's indicator (0 on the
    set, +inf outside), whatever the step: the projections of `oneshot_jax.constraints`
    (`box`, `non_negative`, `positive`, `project`) and the regularisers of
    `oneshot_jax.sparsity` (`l1`, `l2`, `group_lasso`) are all of this type.

    **Fields:**

    - `init`, `update`: the optax interface: chain it after a gradient step, e.g.
        `optax.chain(optax.sgd(eta), t)`; `update(updates, state, params)` needs
        `params` and returns `prox(params + updates, learning_rate) - params` (a
        regulariser needs its factory's `learning_rate` for this; a projection takes no
        step).
    - `prox`: `(params, step_size) -> params`, the proximal map of g with step
        `step_size` (a scalar, or a pytree of per-coordinate steps >= 0; a zero step
        holds its coordinate). For a projection it is `project`, whatever the step.
    - `value`: `params -> scalar`, g(params), to report C + g: 0 for a projection (the
        indicator on its set, where the iterates stay).
    - `project`: for a projection (the prox of an indicator), `params -> params`, the
        Euclidean projection P onto the set; None for a regulariser.
    - `bounds`: `params -> (lower, upper)` pytrees shaped like `params` (with +-inf where
        unbounded) for box sets, or None (a general convex set, or a regulariser).
    - `strength`: a regulariser's weight lambda (the largest one for `combine`), or None
        for a projection or when it is traced.
    - `learning_rate`: the step a regulariser's transform thresholds with after an
        optimiser (a scalar or an optax schedule), or None when none was given (for
        `combine`: the terms' common one, None when they differ).
    - `terms`: for `combine`, the transformations combined, in the order their proxes
        are applied (see `combine`); empty otherwise.
    - `kind`: `"l1"`, `"group_lasso"` or `"l2"` for the regularisers of
        `oneshot_jax.sparsity` (`combine` orders them by it); None otherwise.
    """

    init: Callable
    update: Callable
    prox: Callable
    value: Callable
    project: Callable | None = None
    bounds: Callable | None = None
    strength: float | None = None
    learning_rate: Any = None
    terms: tuple = ()
    kind: str | None = None


class ProximalState(NamedTuple):
    """The number of updates made, for a `learning_rate` schedule."""

    count: jax.Array


# The arguments of the factories, and what `fit` checks of a projection and a
# regulariser on theta0 before the compiled solve.


def check_non_negative_scalar(value, name):
    """Raise a ValueError unless `value` is a finite scalar >= 0 (or traced)."""
    try:
        # (a string or a bool converts with float() but is no strength)
        ok = not isinstance(value, (str, bytes, bool, np.bool_))
        ok = ok and np.ndim(value) == 0 and (not is_concrete(value) or np.isfinite(float(value)))
        ok = ok and (not is_concrete(value) or float(value) >= 0)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`{name}` must be a finite scalar >= 0, got {value!r}.")


def check_schedule(schedule, name):
    """Raise a TypeError unless the callable `schedule` maps a step count to a learning
    rate (a finite real scalar >= 0: a warm-up may start at 0), tried at count 0."""
    try:
        rate = schedule(jnp.asarray(0, jnp.int32))
        detail = f"returned {rate!r}"
        rate = jnp.asarray(rate)
        ok = (
            rate.ndim == 0
            and (
                jnp.issubdtype(rate.dtype, jnp.integer) or jnp.issubdtype(rate.dtype, jnp.floating)
            )
            and (not is_concrete(rate) or (np.isfinite(float(rate)) and float(rate) >= 0))
        )
    except Exception as err:  # (a user's function: whatever it raises)
        ok, detail = False, f"raised {type(err).__name__}: {err}"
    if not ok:
        raise TypeError(
            f"{name} must be a learning rate or an optax schedule mapping the step count "
            f"to one (a finite real number >= 0: a warm-up may start at 0); called with the "
            f"count 0 it {detail}."
        )


def check_learning_rate(learning_rate, allow_none):
    """Raise a ValueError unless `learning_rate` is a step size: a finite scalar > 0 or an
    optax schedule (or None where `allow_none`)."""
    if learning_rate is None and allow_none:
        return
    if callable(learning_rate):
        check_schedule(learning_rate, "`learning_rate`")
        return
    try:
        ok = not isinstance(learning_rate, (str, bytes, bool, np.bool_))
        ok = (
            ok
            and np.ndim(learning_rate) == 0
            and (
                not is_concrete(learning_rate)
                or (np.isfinite(float(learning_rate)) and float(learning_rate) > 0)
            )
        )
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(
            "`learning_rate` must be the step size of the update the prox follows (a "
            f"finite scalar > 0, or an optax schedule count -> step), got {learning_rate!r}."
        )


def _check_like(out, theta, what="`constraints`: the projection"):
    """Raise a ValueError unless `out` has theta's leaves: the same paths (dict keys,
    attributes, indices), shapes and dtypes. `fit` reads a projection's (or a prox's,
    `what`) output back as a flat vector, so a missing leaf would shift the others into
    its place."""
    want = jax.tree_util.tree_flatten_with_path(theta)[0]
    got = jax.tree_util.tree_flatten_with_path(out)[0]
    want_paths = [jax.tree_util.keystr(p) for p, _ in want]
    got_paths = [jax.tree_util.keystr(p) for p, _ in got]
    if got_paths != want_paths:
        missing = [p for p in want_paths if p not in got_paths]
        extra = [p for p in got_paths if p not in want_paths]
        detail = "; ".join(
            f"{what} {', '.join(f'theta{p}' for p in paths)}"
            for what, paths in (("it drops", missing), ("it adds", extra))
            if paths
        )
        raise ValueError(
            f"{what} must return parameters with the structure of "
            f"theta (leaves {', '.join(want_paths)}), got leaves {', '.join(got_paths) or 'none'}"
            f"{'; ' + detail if detail else ' (in another order)'}."
        )
    for path, (_, a), (_, b) in zip(want_paths, got, want):
        if jnp.shape(a) != jnp.shape(b):
            raise ValueError(
                f"{what} returned shape {jnp.shape(a)} for theta{path} "
                f"of shape {jnp.shape(b)}; it must keep the structure, shapes and dtypes of theta."
            )
        weak = isinstance(a, (int, float)) and not isinstance(a, bool)
        if not weak and jnp.result_type(a) != jnp.result_type(b):
            raise ValueError(
                f"{what} returned dtype {jnp.result_type(a)} for "
                f"theta{path} of dtype {jnp.result_type(b)}; it must keep the structure, shapes "
                "and dtypes of theta."
            )


def _same_point(a, b, rtol=1e-10):
    """Whether the pytrees `a` and `b` hold the same values, leaf by leaf in order, to
    `rtol` of `a`'s largest entry (a check on theta0, outside the compiled solve)."""

    def flat(tree):
        leaves = [np.ravel(np.asarray(v, float)) for v in jax.tree_util.tree_leaves(tree)]
        return np.concatenate(leaves) if leaves else np.zeros(0)

    x, y = flat(a), flat(b)
    scale = max(np.max(np.abs(x), initial=0.0), 1e-300)
    return x.shape == y.shape and np.allclose(x, y, rtol=rtol, atol=rtol * scale)


def _projected(proj, theta):
    """`proj.project(theta)`, an error of the user's function re-raised as a ValueError
    naming `constraints` (this library's own errors, which name their argument, as
    they are)."""
    try:
        return proj.project(theta)
    except Exception as err:  # noqa: BLE001 - a user's function: whatever it raises
        if isinstance(err, (ValueError, TypeError)) and str(err).startswith("`"):
            raise
        raise ValueError(
            f"`constraints`: the projection failed when called on theta0 "
            f"({type(err).__name__}: {err}); it must take theta (a pytree of theta0's "
            "structure) and return one of the same structure."
        ) from err


def check_projection(proj, theta, rtol=1e-10):
    """Raise a ValueError unless `proj.project` maps theta to a pytree of theta's structure
    (leaves, shapes, dtypes) and is idempotent there: a projection satisfies P(P(p)) =
    P(p); a map that is not one (p -> p/2, say) would make every fit report convergence
    wherever it happens to stop. `rtol` is at least 100 eps of theta's lowest float
    precision (a half-space's projection in float32 repeats to 6e-8 only)."""
    dtypes = [_pytree.leaf_dtype(v) for v in jax.tree_util.tree_leaves(theta)]
    eps = [np.finfo(d).eps for d in dtypes if np.issubdtype(d, np.inexact)]
    rtol = max([rtol, *(100 * float(e) for e in eps)])
    once = _projected(proj, theta)
    _check_like(once, theta)
    if not _same_point(once, _projected(proj, once), rtol):
        raise ValueError(
            "`constraints`: the projection is not idempotent (P(P(theta0)) != P(theta0)); "
            "a projection onto a convex set must map every point of the set to itself."
        )


def check_regulariser(regulariser, theta):
    """Evaluate the regulariser (a `_problem.Regulariser`) once on theta0 (outside the
    compiled solve), so that a `where` that does not fit theta is reported here, naming
    the argument."""
    value = regulariser.value(theta)
    if np.ndim(value) != 0 or not np.isfinite(float(value)):
        raise ValueError(
            f"`regulariser`: its value g(theta0) must be a finite scalar, got {value!r}."
        )
    steps = jax.tree_util.tree_map(jnp.zeros_like, theta)
    out = regulariser.prox(theta, steps)
    # (`fit` reads the prox's output back as a flat vector: a leaf of another shape
    # would shift the others into its place)
    _check_like(out, theta, "`regulariser`: its prox")
    if not _same_point(theta, out):
        raise ValueError(
            "`regulariser`: its prox with a step of 0 must return theta unchanged (the "
            "proximal map of t g at t = 0 is the identity), but it moved theta0."
        )


def check_regulariser_acts(regulariser, unravel, flat0, theta_free):
    """Refuse a regulariser of positive strength whose value does not change with the
    free entries of theta (its `where` selects nothing that `fit` estimates: nothing, or
    held entries only, where it added a constant to the loss), checked at two points that
    differ in every free entry (0.5 and 2 there, theta0's values elsewhere)."""
    strength = regulariser.strength
    if strength is None or not strength > 0:  # (lambda = 0: no test to make)
        return
    values = []
    for v in (0.5, 2.0):
        flat = np.array(flat0, copy=True)
        flat[np.asarray(theta_free, int)] = v
        values.append(float(regulariser.value(unravel(flat))))
    if np.isfinite(values[0]) and values[0] == values[1]:
        raise ValueError(
            "`regulariser`: it acts on no entry of theta that the fit estimates (its `where` "
            "selects no parameter, or only entries held by `fixed`), so it would change "
            "nothing but add a constant to the loss. Select estimated parameters, or leave "
            "`regulariser` out."
        )


def step_at(learning_rate, count):
    """The step of `learning_rate` (a number or an optax schedule) at update `count`."""
    return learning_rate(count) if callable(learning_rate) else learning_rate


def _moved(prox, params, updates, step):
    """The optax update that lands on `prox(params + updates, step)`."""
    if params is None:
        raise ValueError(
            "a proximal transform (a projection or a regulariser) needs `params` in "
            "`update(updates, state, params)`."
        )
    want, got = jax.tree_util.tree_structure(updates), jax.tree_util.tree_structure(params)
    if got != want:  # (else optax's `apply_updates` fails with a bare pytree error)
        raise ValueError(
            "`params` and `updates` of a proximal transform's `update(updates, state, "
            f"params)` must have the same pytree structure, got {got} for `params` and "
            f"{want} for `updates`."
        )
    new = prox(optax.apply_updates(params, updates), step)
    return jax.tree_util.tree_map(lambda n, p: n - p, new, params)


def _zero(params):
    del params
    return 0.0


def _empty_init(params):
    del params
    return optax.EmptyState()


def _indicator_prox(project, params, step_size):
    del step_size
    return project(params)


def _indicator_update(prox, updates, state, params=None):
    return _moved(prox, params, updates, None), state


def indicator(project, bounds=None) -> ProximalTransformation:
    """The proximal transformation of the indicator of a convex set (Section 3.3).

    **Arguments:**

    - `project`: `params -> params`, the Euclidean projection P onto the set.
    - `bounds`: for a box, `params -> (lower, upper)`; None otherwise.

    **Returns:**

    A `ProximalTransformation` whose `prox(params, step)` is `project(params)` for every
    step, whose `value` is 0, and whose optax update is `P(params + updates) - params`
    (no state). Its functions are module-level functions and partials of them, so that
    it pickles where `project` and `bounds` do (a process pool takes it).
    """
    prox = functools.partial(_indicator_prox, project)
    update = functools.partial(_indicator_update, prox)
    return ProximalTransformation(_empty_init, update, prox, _zero, project, bounds)


class Keyed:
    """A function that compares and hashes by a key (its factory's name and arguments),
    not by identity: `fit` compiles per regulariser function (a static argument), so
    `l1(1e-3)` made anew on every call reuses the compiled solve."""

    __slots__ = ("fn", "key")

    def __init__(self, fn, key):
        self.fn, self.key = fn, key

    def __call__(self, *args, **kwargs):
        return self.fn(*args, **kwargs)

    def __eq__(self, other):
        return isinstance(other, Keyed) and self.key == other.key

    def __hash__(self):
        return hash(self.key)


def keyed(fn, key):
    """`fn` compared by `key`, or `fn` itself where `key` is None (not hashable)."""
    if key is None:
        return fn
    try:
        hash(key)
    except TypeError:
        return fn
    return Keyed(fn, key)


def _penalty_init(learning_rate, name, params):
    del params
    if learning_rate is None:
        raise ValueError(
            f"chaining `{name}` after an optimiser needs its `learning_rate` (the step "
            f"of that optimiser): {name}(..., learning_rate=eta). For Adam use "
            f"`proximal_adam(eta, {name}(...))`."
        )
    return ProximalState(count=jnp.zeros([], jnp.int32))


def _penalty_update(prox, learning_rate, updates, state, params=None):
    out = _moved(prox, params, updates, step_at(learning_rate, state.count))
    return out, ProximalState(count=optax.safe_increment(state.count))


def penalty(prox, value, strength, learning_rate, name, key=None) -> ProximalTransformation:
    """The proximal transformation of a penalty g (Parikh and Boyd 2014, Sec. 4.2).

    **Arguments:**

    - `prox`: `(params, step_size) -> params`, the proximal map of g.
    - `value`: `params -> scalar`, g(params).
    - `strength`: the penalty's weight lambda.
    - `learning_rate`: the step of the optimiser the transform follows (a scalar or an
        optax schedule of the update count), or None (then `init` names it as missing).
    - `name`: the factory's name, for that error.
    - `key`: the factory's arguments as a hashable value, or None: `prox` and `value`
        then compare equal between transformations made alike (`Keyed`).

    **Returns:**

    A `ProximalTransformation` whose optax update is
    `prox(params + updates, learning_rate(count)) - params`.
    """
    check_learning_rate(learning_rate, allow_none=True)
    init = functools.partial(_penalty_init, learning_rate, name)
    update = functools.partial(_penalty_update, prox, learning_rate)
    if key is not None:
        prox, value = keyed(prox, (name, "prox", *key)), keyed(value, (name, "value", *key))
    strength = float(strength) if is_concrete(strength) else None
    return ProximalTransformation(
        init, update, prox, value, None, None, strength, learning_rate, kind=name
    )


def _intersect(boxes):
    """The bounds of the intersection of boxes: the largest lower and smallest upper."""
    return functools.partial(_intersection_bounds, tuple(boxes))


def _intersection_bounds(boxes, params):
    los, his = zip(*(b(params) for b in boxes))
    lo = jax.tree_util.tree_map(lambda *a: jnp.max(jnp.stack(a), axis=0), *los)
    hi = jax.tree_util.tree_map(lambda *a: jnp.min(jnp.stack(a), axis=0), *his)
    if is_concrete(lo, hi):
        flat_lo = jax.tree_util.tree_leaves_with_path(lo)
        empty = [
            jax.tree_util.keystr(path)
            for (path, a), b in zip(flat_lo, jax.tree_util.tree_leaves(hi))
            if np.any(np.asarray(a) > np.asarray(b))
        ]
        if empty:
            raise ValueError(
                "`constraints`: the boxes' intersection is empty (a lower bound above "
                f"an upper bound) for theta{', theta'.join(empty)}."
            )
    return lo, hi


def dykstra(projections, max_cycles=1000):
    """The Euclidean projection onto the intersection of closed convex sets from the
    projections onto each, by Dykstra's algorithm (Boyle and Dykstra, "A method for
    finding projections onto the intersection of convex sets in Hilbert spaces", 1986;
    Bauschke and Combettes, "Convex analysis and monotone operator theory in Hilbert
    spaces", 2011, Thm. 30.7): with an increment p_i per set, one cycle is
    y = P_i(x + p_i), p_i <- x + p_i - y, x <- y for each set in turn, repeated until a
    cycle moves x and every increment by at most 10 eps max(1, |x|) (or `max_cycles`: x
    can stand still for a cycle while the increments still change). Plain alternating
    projections would reach a point of the intersection that is not the projection, and
    whose fixed points are not the constrained stationary points. A point already in the
    intersection is returned after one cycle, unchanged. The result lies exactly in the
    last set.

    **Arguments:** `projections`, a list of `params -> params`; `max_cycles`.

    **Returns:** `params -> params`.
    """
    return functools.partial(_dykstra_project, tuple(projections), max_cycles)


def _dykstra_project(projections, max_cycles, params):
    """`dykstra(projections, max_cycles)(params)`."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    leaves = [jnp.asarray(a) for a in leaves]
    eps = max(float(jnp.finfo(a.dtype).eps) for a in leaves)

    def cycle(carry):
        x, increments, k, _ = carry
        start = x
        out = []
        for P, p in zip(projections, increments):
            shifted = [a + b for a, b in zip(x, p)]
            y = jax.tree_util.tree_leaves(P(jax.tree_util.tree_unflatten(treedef, shifted)))
            out.append([a - b for a, b in zip(shifted, y)])
            x = y
        # x can stand still for a cycle while the increments still change (the box
        # clips the same point twice): converged only when both have settled.
        changes = [jnp.max(jnp.abs(a - b), initial=0.0) for a, b in zip(x, start)]
        changes += [
            jnp.max(jnp.abs(a - b), initial=0.0)
            for new_p, old_p in zip(out, increments)
            for a, b in zip(new_p, old_p)
        ]
        moved = jnp.max(jnp.stack(changes))
        return x, out, k + 1, moved

    def going(carry):
        x, _, k, moved = carry
        size = jnp.max(jnp.stack([jnp.max(jnp.abs(a), initial=0.0) for a in x]))
        return (k < max_cycles) & (moved > 10.0 * eps * jnp.maximum(size, 1.0))

    zeros = [[jnp.zeros_like(a) for a in leaves] for _ in projections]
    first = cycle((leaves, zeros, jnp.asarray(0), jnp.asarray(0.0, leaves[0].dtype)))
    x, _, _, _ = jax.lax.while_loop(going, cycle, first)
    return jax.tree_util.tree_unflatten(treedef, x)


# The combined projections of general sets made so far, by their sets (`_set_key`).
_COMBINED: dict = {}


def _combined_projection(general, transforms):
    """`dykstra(general)`, compiled, one function per combination of the same sets:
    `fit` takes a combination apart and combines it again, and a new function there
    compiled the whole solve anew on every call (1.8 s each; its calls on the host, two
    more small programs). A set that cannot be hashed gets a function of its own."""
    key = ("dykstra", tuple(map(_set_key, transforms)))
    return _pytree.kept(
        _COMBINED, key, lambda: _Compiled(general, transforms, jax.jit(dykstra(general))), 32
    )


class _Compiled:
    """A combined projection, compiled, that pickles as its sets (`_combined_projection`
    of them again: a compiled function does not pickle)."""

    __slots__ = ("general", "transforms", "fn")

    def __init__(self, general, transforms, fn):
        self.general, self.transforms, self.fn = tuple(general), tuple(transforms), fn

    def __call__(self, params):
        return self.fn(params)

    def __reduce__(self):
        return _combined_projection, (self.general, self.transforms)


def _set_key(t):
    """A projection's stand-in in a key: a box's bounds where they name it by value
    (`constraints.box`), else its projection function."""
    key = getattr(t.bounds, "key", None)
    return key if key is not None else t.project


def _same_number(a, b):
    try:
        return not callable(a) and not callable(b) and float(a) == float(b)
    except (TypeError, ValueError):
        return False


# `combine`'s maps, as module-level functions (partials of them pickle).


def _proxes_in_turn(transforms, params, step_size):
    for t in transforms:
        params = t.prox(params, step_size)
    return params


def _projected_in_turn(projections, params):
    for project in projections:
        params = project(params)
    return params


def _clipped_in_turn(bounds, projections, params):
    bounds(params)  # (refuses an empty intersection where the bounds are concrete)
    return _projected_in_turn(projections, params)


def _sum_of_values(penalties, params):
    return sum(t.value(params) for t in penalties)


def _chain_init(transforms, params):
    """`optax.chain(*transforms).init(params)`."""
    return tuple(t.init(params) for t in transforms)


def _chain_update(transforms, updates, state, params=None):
    """`optax.chain(*transforms).update(updates, state, params)`."""
    new_state = []
    for t, s in zip(transforms, state, strict=True):
        updates, s = t.update(updates, s, params)
        new_state.append(s)
    return updates, tuple(new_state)


def combine(transforms) -> ProximalTransformation | None:
    """One proximal transformation from None, a `ProximalTransformation` or a sequence of
    them (projections and regularisers alike): their proximal maps combined.

    Projections alone make one projection onto the intersection of their sets: boxes clipped
    in turn (their bounds intersected); with a general `project(fn)`, Dykstra's algorithm
    (`dykstra`, the boxes last), and no bounds. Regularisers add up their penalties; their
    proxes are composed in a fixed order, whatever the order given: `l1`, then
    `group_lasso`, then `l2`, then the projections (a combination given inside the list is
    taken apart into its terms; with a regulariser not made by `oneshot_jax.sparsity`, the
    regularisers keep the order given, the projections still last). In that order the
    composition is the exact prox of the sum on the same leaves: `l1` then `group_lasso` is
    the sparse group lasso's (Friedman, Hastie and Tibshirani, "A note on the group lasso
    and a sparse group lasso", 2010; this also holds with per-coordinate steps), and `l2`
    last scales the result by 1 / (1 + step lambda_2), the prox of the sum with the
    quadratic (the other orders are not exact: `l2` then `l1` thresholds the shrunk values,
    so a fit's first-order test would measure the distance to the wrong fixed point); on
    different leaves every order is exact. A regulariser followed by a box projection is the
    exact prox of g plus the box's indicator for a separable g (`l1`, `l2`: in one
    dimension the constrained minimiser is the clipped unconstrained one), a feasible
    approximation of it for a group penalty. With a regulariser, `update` runs each term's
    update in turn, in that order, like `optax.chain`, each with its own `learning_rate`.

    **Arguments:**

    - `transforms`: None, a `ProximalTransformation`, or a non-empty list or tuple of
        them.

    **Returns:**

    None for None, the transformation itself for one, else a `ProximalTransformation`
    whose `terms` are the given ones (a combination among them taken apart into its
    terms; after regularisers, several sets as one combined projection), in the order
    they are applied.
    """
    if transforms is None:
        return None
    # A ProximalTransformation is a NamedTuple (a tuple): one is not a list of them.
    if isinstance(transforms, ProximalTransformation):
        return transforms
    if (
        not isinstance(transforms, (list, tuple))
        or not transforms
        or not all(isinstance(t, ProximalTransformation) for t in transforms)
    ):
        raise ValueError(
            "`combine` takes proximal transformations (the `constraints` or `regularisers` "
            "to combine): projections from oneshot_jax.constraints (non_negative, positive, "
            "box, project) and regularisers from oneshot_jax.sparsity (l1, group_lasso, l2), "
            f"one or a non-empty list of them; got {transforms!r}."
        )
    transforms = _in_order(transforms)
    sets = [t for t in transforms if t.project is not None]
    if len(sets) > 1 and len(sets) < len(transforms):
        # (after regularisers, the projection onto the sets' intersection: their
        # combination, not one set after another)
        transforms = (*transforms[: -len(sets)], combine(sets))
    if len(transforms) == 1:
        return transforms[0]

    penalties = [t for t in transforms if t.project is None]
    prox = keyed(
        functools.partial(_proxes_in_turn, transforms),
        ("combine", "prox", tuple(t.prox for t in transforms)),
    )
    if not penalties:
        boxes = [t.bounds for t in transforms]
        if None not in boxes:  # boxes: clipping in turn projects onto the intersection
            bounds = _intersect(boxes)
            projections = tuple(t.project for t in transforms)
            project = functools.partial(_clipped_in_turn, bounds, projections)
            return indicator(project, bounds)._replace(terms=transforms)
        # A general set with others: its composition with them is neither the projection
        # onto the intersection nor a map into it (positive() then project(fn) left an
        # entry at -0.06). Dykstra's algorithm is; the boxes go last, so that every
        # iterate is exactly inside them.
        general = [t.project for t in transforms if t.bounds is None]
        boxed = [t.project for t in transforms if t.bounds is not None]
        if boxed:
            general.append(functools.partial(_projected_in_turn, tuple(boxed)))
        return indicator(_combined_projection(general, transforms))._replace(terms=transforms)

    value = keyed(
        functools.partial(_sum_of_values, tuple(penalties)),
        ("combine", "value", tuple(t.value for t in penalties)),
    )
    strengths = [t.strength for t in penalties]
    strength = None if None in strengths else max(strengths)
    rates = [t.learning_rate for t in penalties]
    same = all(r is rates[0] or _same_number(r, rates[0]) for r in rates)
    return ProximalTransformation(
        functools.partial(_chain_init, transforms),
        functools.partial(_chain_update, transforms),
        prox,
        value,
        None,
        None,
        strength,
        rates[0] if same else None,
        transforms,
    )


# The order in which `combine` composes the regularisers of `oneshot_jax.sparsity`: the
# composition is then the exact prox of their sum on shared leaves.
_ORDER = {"l1": 0, "group_lasso": 1, "l2": 2}


def _leaves(t: ProximalTransformation) -> list:
    """The transformations a `combine` was made of (recursively), or `t` alone."""
    return [p for s in t.terms for p in _leaves(s)] if t.terms else [t]


def separable(t: ProximalTransformation) -> bool:
    """Whether a regulariser is a sum of per-entry terms (`sparsity.l1`, `l2` and their
    combinations): its prox then composes with a box's clip into the prox of the sum."""
    return all(p.kind in ("l1", "l2") for p in _leaves(t))


def _in_order(transforms) -> tuple:
    """`combine`'s terms in the order their proxes are applied: the regularisers first
    (ordered by `_ORDER` when every one has a kind there, else as given), then the
    projections, each group otherwise as given (`combine` makes several projections after
    regularisers one, the projection onto their intersection)."""
    leaves = [p for t in transforms for p in _leaves(t)]
    penalties = [t for t in leaves if t.project is None]
    if all(t.kind in _ORDER for t in penalties):
        penalties.sort(key=lambda t: _ORDER[t.kind])
    return tuple(penalties) + tuple(t for t in leaves if t.project is not None)


def _kind(t: ProximalTransformation) -> set:
    """{True} for a projection, {False} for a regulariser, both for a mixed `combine`."""
    if not t.terms:
        return {t.project is not None}
    return set().union(*(_kind(s) for s in t.terms))


def _parts(t: ProximalTransformation) -> list:
    """`t` alone, or a mixed `combine` taken apart into its projections and regularisers
    (a combination of one kind stays whole)."""
    if len(_kind(t)) == 1:
        return [t]
    return [p for s in t.terms for p in _parts(s)]


def _items(arg, name, what) -> list:
    """`fit`'s `constraints` or `regulariser` as a list of transformations of one kind
    each."""
    if arg is None:
        return []
    if isinstance(arg, ProximalTransformation):
        items = [arg]
    elif isinstance(arg, (list, tuple)) and all(isinstance(t, ProximalTransformation) for t in arg):
        items = list(arg)
    else:
        raise ValueError(f"`{name}` must be {what}, or a list of them; got {arg!r}.")
    return [p for t in items for p in _parts(t)]


def split(constraints, regulariser):
    """`fit`'s `constraints` and `regulariser` as (one projection or None, one
    regulariser or None), each combined from its terms (`combine`, which orders the
    regularisers by kind).

    A regulariser given in `constraints` (the mixed form of earlier releases) still works,
    with a DeprecationWarning naming `regulariser=`; it joins those of `regulariser`. A
    projection given in `regulariser` is a ValueError naming the argument. A step of
    `fit` applies the regulariser's prox, then the projection (see `combine`).
    """
    given = _items(
        constraints,
        "constraints",
        "a projection from oneshot_jax.constraints (non_negative, positive, box, project)",
    )
    extra = _items(
        regulariser,
        "regulariser",
        "a proximal regulariser from oneshot_jax.sparsity (l1, group_lasso, l2)",
    )
    moved = [t for t in given if t.project is None]
    if moved:
        warn(
            "a proximal regulariser (l1, group_lasso, l2) in `fit(constraints=...)` is "
            "deprecated: pass it as `fit(regulariser=...)`; `constraints=` takes the "
            "projections (box, non_negative, positive, project).",
            DeprecationWarning,
            stacklevel=4,
        )
    if any(t.project is not None for t in extra):
        raise ValueError(
            "`regulariser` takes proximal regularisers from oneshot_jax.sparsity (l1, "
            "group_lasso, l2), got a projection (box, non_negative, positive, project): "
            f"pass it as `constraints=`; got {regulariser!r}."
        )
    projections = [t for t in given if t.project is not None]
    penalties = moved + extra
    return (
        combine(projections) if projections else None,
        combine(penalties) if penalties else None,
    )
