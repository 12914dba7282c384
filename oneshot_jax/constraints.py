"""Projections onto convex parameter sets, Section 3.3 of the paper, as optax transforms.

"In case we need to constrain the parameters into a specified convex set, we can enhance
the identification algorithm introducing a projection step immediately after the parameters
update." Each factory here returns a `ProjectionTransformation`: an optax
`GradientTransformation` (chain it last, like `optax.keep_params_nonnegative`) whose update
is `P(params + updates) - params`, plus the projection `P` itself.

In floating point, `params + (P(params + u) - params)` can land one ulp outside the set, so
`fit` projects the parameters again after `optax.apply_updates`: every iterate of `fit` is
exactly feasible. Do the same in a hand-written loop: `params = tx.project(params)`.

Box-type sets (`non_negative`, `positive`, `box`) also expose their bounds, which the
least-squares solvers of `fit` use for an exact active-set treatment.

A projection is the proximal map of the indicator of its set, so `fit(constraints=...)`
also takes the proximal regularisers of `oneshot_jax.sparsity` (`l1`, `group_lasso`) in
the same list: the fit then minimises C + g(theta), applying the prox (with the solver's
step sizes) before the projection after every update (see `separate`).

A caveat on projected Adam (Algorithm 1 with a projection): for a box the projection acts
per coordinate, like Adam's scaling, and the iterates reach the constrained optimum. For a
general convex set (`project(fn)`, e.g. a half-space) Adam's per-coordinate step sizes do
not match the Euclidean projection, so projected Adam can settle at a feasible point that
is not the constrained optimum; use plain gradient descent (`optax.sgd`) or a
least-squares solver there.
"""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._checks import is_concrete

__all__ = ["ProjectionTransformation", "non_negative", "positive", "box", "project", "combine"]


class ProjectionTransformation(NamedTuple):
    """An optax `GradientTransformation` that projects the updated parameters onto a set.

    **Fields:**

    - `init`, `update`: the optax interface; `update` needs `params`.
    - `project`: `params -> params`, the Euclidean projection P onto the set.
    - `bounds`: `params -> (lower, upper)` pytrees shaped like `params` (with +-inf where
        unbounded) for box sets, or None for a general convex set.
    """

    init: Callable
    update: Callable
    project: Callable
    bounds: Callable | None = None


def _from_projection(proj, bounds=None) -> ProjectionTransformation:
    def init(params):
        del params
        return optax.EmptyState()

    def update(updates, state, params=None):
        if params is None:
            raise ValueError(
                "a projection transform needs `params` in `update(updates, state, params)`."
            )
        new = proj(optax.apply_updates(params, updates))
        return jax.tree_util.tree_map(lambda n, p: n - p, new, params), state

    return ProjectionTransformation(init, update, proj, bounds)


def _fill_like(bound, params, fill, name):
    """Broadcast a bound (scalar, pytree like params, or a partial dict) onto params."""
    # Bounds are constants: NumPy builds them without a JAX dispatch per leaf.
    if bound is None:
        return jax.tree_util.tree_map(
            lambda p: np.full(jnp.shape(p), fill, jnp.result_type(p)), params
        )
    if isinstance(params, dict) and isinstance(bound, dict):
        unknown = set(bound) - set(params)
        if unknown:
            raise ValueError(f"`{name}` names parameters that are not in theta: {sorted(unknown)}.")
        return {k: _fill_like(bound.get(k), v, fill, name) for k, v in params.items()}
    if isinstance(bound, (list, tuple)) and isinstance(params, (list, tuple)):
        if len(bound) != len(params):
            raise ValueError(f"`{name}` must have one entry per parameter leaf ({len(params)}).")
        return type(params)(_fill_like(b, p, fill, name) for b, p in zip(bound, params))
    leaves, treedef = jax.tree_util.tree_flatten(params)
    if jnp.ndim(bound) == 0 or len(leaves) == 1:
        xp = np if is_concrete(bound) else jnp
        b = xp.asarray(bound)
        out = []
        for p in leaves:
            try:
                out.append(xp.broadcast_to(b, jnp.shape(p)).astype(jnp.result_type(p)))
            except ValueError as err:
                raise ValueError(
                    f"`{name}` of shape {b.shape} does not fit a parameter of shape {jnp.shape(p)}."
                ) from err
        return jax.tree_util.tree_unflatten(treedef, out)
    raise ValueError(f"`{name}` must be a scalar or have the structure of the parameters.")


def box(lower=None, upper=None) -> ProjectionTransformation:
    """Projection onto the box `lower <= params <= upper` (elementwise clipping).

    **Arguments:**

    - `lower`, `upper`: a scalar (every element), a pytree with the parameters' structure
        (leaves broadcast to each parameter's shape), or for dict parameters a dict naming
        some of them; missing entries and None mean unbounded (-inf / +inf).

    **Returns:**

    A `ProjectionTransformation`.
    """

    def bounds(params):
        lo = _fill_like(lower, params, -jnp.inf, "lower")
        hi = _fill_like(upper, params, jnp.inf, "upper")
        bad = jax.tree_util.tree_map(lambda a, b: a > b, lo, hi)
        if is_concrete(bad) and any(bool(np.any(b)) for b in jax.tree_util.tree_leaves(bad)):
            raise ValueError("`box` needs lower <= upper for every parameter.")
        return lo, hi

    def proj(params):
        lo, hi = bounds(params)
        return jax.tree_util.tree_map(lambda p, a, b: jnp.clip(p, a, b), params, lo, hi)

    return _from_projection(proj, bounds)


def non_negative() -> ProjectionTransformation:
    """Projection onto `params >= 0` (the paper's theta_i > 0 up to the boundary)."""
    return box(lower=0.0)


def positive(eps: float = 1e-12) -> ProjectionTransformation:
    """Projection onto `params >= eps`, a closed stand-in for the open set `params > 0`."""
    if not eps > 0:
        raise ValueError(f"`eps` must be > 0, got {eps}.")
    return box(lower=eps)


def project(fn: Callable[[Any], Any]) -> ProjectionTransformation:
    """A user projection `fn(params) -> params` onto a convex set, as a transform.

    `fn` must be idempotent (a projection); for sets that are not boxes the least-squares
    solvers of `fit` apply it after each step (a projected step) without an active set.
    """
    if not callable(fn):
        raise ValueError(f"`fn` must be callable params -> params, got {fn!r}.")
    return _from_projection(fn, None)


def combine(constraints) -> ProjectionTransformation | None:
    """One projection from None, a `ProjectionTransformation` or a sequence of them.

    Projections are applied in order; the bounds of several boxes are intersected. A
    sequence that contains a general `project(fn)` has no bounds.
    """
    if constraints is None:
        return None
    if isinstance(constraints, ProjectionTransformation):
        return constraints
    if not isinstance(constraints, (list, tuple)) or not all(
        isinstance(c, ProjectionTransformation) for c in constraints
    ):
        raise ValueError(
            "`constraints` must be a ProjectionTransformation from oneshot_jax.constraints "
            f"(non_negative, positive, box, project) or a list of them, got {constraints!r}."
        )
    if len(constraints) == 1:
        return constraints[0]

    def proj(params):
        for c in constraints:
            params = c.project(params)
        return params

    bounds = None
    if all(c.bounds is not None for c in constraints):

        def bounds(params):
            los, his = zip(*(c.bounds(params) for c in constraints))
            lo = jax.tree_util.tree_map(lambda *a: jnp.max(jnp.stack(a), axis=0), *los)
            hi = jax.tree_util.tree_map(lambda *a: jnp.min(jnp.stack(a), axis=0), *his)
            return lo, hi

    return _from_projection(proj, bounds)


def separate(constraints):
    """(projection, regulariser): the `constraints` of `fit` split into one
    `ProjectionTransformation` (or None) and one `sparsity.ProximalTransformation` (or
    None), each combined from the list's entries of its kind in order.

    A step of `fit` applies the regulariser's prox, then the projection. For a box and a
    separable penalty (`l1`) this is the exact prox of g plus the box's indicator (in one
    dimension the constrained minimiser is the clipped unconstrained one); for a group
    penalty it is a feasible approximation of it.
    """
    if constraints is None:
        return None, None
    from .sparsity import ProximalTransformation
    from .sparsity import combine as combine_regularisers

    kinds = (ProjectionTransformation, ProximalTransformation)
    # Both kinds are NamedTuples (tuples): a single one is not a list of constraints.
    single = isinstance(constraints, kinds) or not isinstance(constraints, (list, tuple))
    items = [constraints] if single else list(constraints)
    for c in items:
        if not isinstance(c, kinds):
            raise ValueError(
                "`constraints` must hold projections from oneshot_jax.constraints "
                "(non_negative, positive, box, project) and proximal regularisers from "
                f"oneshot_jax.sparsity (l1, group_lasso, l2), or a list of them; got {c!r}."
            )
    projections = [c for c in items if isinstance(c, ProjectionTransformation)]
    regularisers = [c for c in items if isinstance(c, ProximalTransformation)]
    return (
        combine(projections) if projections else None,
        combine_regularisers(regularisers) if regularisers else None,
    )


def _check_like(out, theta):
    """Raise a ValueError unless `out` has theta's leaves: the same paths (dict keys,
    attributes, indices), shapes and dtypes. `fit` reads a projection's output back as a
    flat vector, so a missing leaf would shift the others into its place."""
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
            "`constraints`: the projection must return parameters with the structure of "
            f"theta (leaves {', '.join(want_paths)}), got leaves {', '.join(got_paths) or 'none'}"
            f"{'; ' + detail if detail else ' (in another order)'}."
        )
    for path, (_, a), (_, b) in zip(want_paths, got, want):
        if jnp.shape(a) != jnp.shape(b):
            raise ValueError(
                f"`constraints`: the projection returned shape {jnp.shape(a)} for theta{path} "
                f"of shape {jnp.shape(b)}; it must keep the structure, shapes and dtypes of theta."
            )
        weak = isinstance(a, (int, float)) and not isinstance(a, bool)
        if not weak and jnp.result_type(a) != jnp.result_type(b):
            raise ValueError(
                f"`constraints`: the projection returned dtype {jnp.result_type(a)} for "
                f"theta{path} of dtype {jnp.result_type(b)}; it must keep the structure, shapes "
                "and dtypes of theta."
            )


def check_projection(proj: ProjectionTransformation, theta, rtol=1e-10):
    """Raise a ValueError unless `proj.project` maps theta to a pytree of theta's structure
    (leaves, shapes, dtypes) and is idempotent there: a projection satisfies P(P(p)) =
    P(p); a map that is not one (p -> p/2, say) would make every fit report convergence
    wherever it happens to stop."""
    once = proj.project(theta)
    _check_like(once, theta)
    twice = proj.project(once)
    a = np.concatenate([np.ravel(np.asarray(v, float)) for v in jax.tree_util.tree_leaves(once)])
    b = np.concatenate([np.ravel(np.asarray(v, float)) for v in jax.tree_util.tree_leaves(twice)])
    if a.shape != b.shape or not np.allclose(
        a, b, rtol=rtol, atol=rtol * max(np.max(np.abs(a), initial=0.0), 1e-300)
    ):
        raise ValueError(
            "`constraints`: the projection is not idempotent (P(P(theta0)) != P(theta0)); "
            "a projection onto a convex set must map every point of the set to itself."
        )
