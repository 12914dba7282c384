"""`fit`: estimate theta and x0 by minimising the multi-step loss (eq. 5/21).

`fit` only normalises its inputs into a `FitProblem` and starting points, hands them to
the solvers' loop (`oneshot_jax._iterate`) as one compiled call, and assembles the
`FitResult` (`oneshot_jax._assemble`).
"""

import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._assemble import assemble, collect, post
from ._checks import (
    _is_ragged,
    check_cost,
    check_data,
    check_fixed_bounds,
    check_outside_transformations,
    fixed_mask,
    x0_mask,
)
from ._fit_report import check_units, theta_order
from ._fit_result import FitResult
from ._iterate import run
from ._parallel._report import counting
from ._problem import FitProblem, Params, Regulariser
from ._progress import NoProgress, TqdmProgress
from ._prox import check_projection, check_regulariser, split
from ._solver.least_squares import AbstractLeastSquares
from ._solver_arg import as_solvers
from ._windows import cut

_NO_PROGRESS = NoProgress()


def _n_starts(theta0_params, x0, data_x0_ndim):
    """The number of starts of a multistart fit, from theta0's leading axes and x0's."""
    sizes = {
        jnp.shape(leaf)[0] if jnp.ndim(leaf) else None
        for leaf in jax.tree_util.tree_leaves(theta0_params)
    }
    if len(sizes) != 1 or None in sizes:
        raise ValueError(
            "with `multistart=True` every parameter leaf of `theta0` needs the same leading "
            f"axis of starts; got leading sizes {sorted(map(str, sizes))}."
        )
    n = sizes.pop()
    if np.ndim(x0) == data_x0_ndim + 1 and np.shape(x0)[0] != n:
        raise ValueError(
            f"with `multistart=True`, `x0` with a leading axis of starts must have {n} "
            f"starts like `theta0`, got {np.shape(x0)[0]} (shape {np.shape(x0)})."
        )
    return n


def _host(a):
    """Data as NumPy arrays (no device transfer until the compiled call), except arrays
    sharded over several devices (`oneshot_jax.sharding`), which stay where they are."""
    if isinstance(a, jax.Array) and len(a.sharding.device_set) > 1:
        return a
    return np.asarray(a)


def _written_order(tree):
    """The keys of theta's dicts in the order they were written (JAX's tree structure
    sorts them), down through dicts, lists and tuples to array and number leaves; a
    TypeError for any other node (a module's dicts count too: not keyed here)."""
    if isinstance(tree, dict):
        return tuple((k, _written_order(v)) for k, v in tree.items())
    if isinstance(tree, (list, tuple)):
        return tuple(_written_order(v) for v in tree)
    if tree is None or isinstance(tree, (np.ndarray, jax.Array, np.generic, int, float)):
        return None
    raise TypeError


_ORDERS: dict = {}


def _theta_order(theta):
    """`theta_order(theta)`, kept per structure and written order of dicts."""
    try:
        key = (jax.tree_util.tree_structure(theta), _written_order(theta))
        hash(key)
    except TypeError:
        return theta_order(theta)
    order = _ORDERS.get(key)
    if order is None:
        order = theta_order(theta)
        if len(_ORDERS) >= 256:
            _ORDERS.pop(next(iter(_ORDERS)))
        _ORDERS[key] = order
    return order


@eqx.filter_jit
def _solve(solvers, problem, starts, history_size, meter, bar_id):
    """The whole fit as one compiled call: project the starts, run the solvers from all of
    them at once, pick the best start and post-process it (covariance and metrics).
    Returns what `assemble` reads (an `Out`), packed."""
    projected = jax.vmap(problem.feasible)(starts.theta)
    moved = jnp.any(projected != starts.theta)
    starts = Params(projected, starts.x0)
    stages = run(solvers, problem, starts, history_size=history_size, meter=meter, bar_id=bar_id)
    final = stages[-1]
    best = jnp.argmin(jnp.where(jnp.isfinite(final.loss), final.loss, jnp.inf))
    params = jax.tree_util.tree_map(lambda a: a[best], final.params)
    blocks = (
        None if final.blocks is None else jax.tree_util.tree_map(lambda a: a[best], final.blocks)
    )
    strategy = getattr(solvers[-1], "strategy", "auto")
    out = collect(stages, best, moved, post(problem, params, blocks, strategy))
    # One buffer per dtype to the host instead of one per array (`_pytree.pack`).
    return _pytree.pack(out)


def fit(
    model,
    theta0: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    z: Float[ArrayLike, "*N T n_z"],
    *,
    solver="levenberg_marquardt",
    weight=None,
    penalty=None,
    penalty_weight: float = 1.0,
    constraints=None,
    regulariser=None,
    fixed=None,
    estimate_x0=True,
    window: int | None = None,
    missing: str = "raise",
    multistart: bool = False,
    progress=False,
    history: int = 1000,
    units: dict[str, str] | None = None,
) -> FitResult:
    """Estimate theta and x0 by minimising the multi-step cost C of eq. (5)/(21).

    **Arguments:**

    - `model`: a `Model`.
    - `theta0`: the starting parameters, any pytree (it may hold equinox modules: their
        floating arrays are estimated; integer and boolean arrays and other parts are
        kept). With `multistart=True` every parameter leaf has a leading axis of starts,
        run in parallel (vmap); the start with the best final loss is returned.
    - `x0`: the starting initial state (n_x,), or (N, n_x) for N trajectories (with
        `window`, optionally one per window; with `multistart`, optionally with a leading
        axis of starts too).
    - `u`, `z`: inputs (T, n_u) and measured outputs (T, n_z), or (N, T, .) for N
        trajectories sharing theta, each with its own x0.
    - `solver`: a solver object (`LevenbergMarquardt()` by default, `GaussNewton`,
        `Adam`, `LBFGS`, `Optax(transform)`, `Optimistix(optx_solver)`), one of the names
        "levenberg_marquardt", "gauss_newton", "adam", "lbfgs" (default settings), an
        optax transform or optimistix solver (wrapped), or a sequence of these, run in
        order, each starting where the last stopped (e.g. `[Adam(), LBFGS()]`).
    - `weight`, `penalty`, `penalty_weight`: Q and h, lambda of eq. (4), (21), as for
        `loss`. The least-squares solvers need lambda h >= 0.
    - `constraints`: a projection from `oneshot_jax.constraints` (`box`, `non_negative`,
        `positive`, `project`), or a list of them, on theta: every iterate lies in the
        intersection of their sets (Section 3.3). A regulariser here (the mixed form of
        0.2) still works, with a DeprecationWarning: pass it as `regulariser`.
    - `regulariser`: a proximal regulariser from `oneshot_jax.sparsity` (`l1`,
        `group_lasso`, `l2`), or a list of them, on theta (their `where` is written on
        theta as given, modules included). A regulariser g makes the objective
        C + g(theta): `loss` and the history then report C + g. Only `Adam` (proximal
        Adam: the prox with its per-coordinate steps) and `Optax(transform)` (the prox
        with the regulariser's `learning_rate`) take one; the other solvers raise a
        ValueError. Each update applies the prox, then the projection.
    - `fixed`: a pytree of booleans shaped like theta0 (per leaf, per element, or one
        boolean for a whole subtree): True entries keep their starting value and are
        removed from the variables.
    - `estimate_x0`: False keeps x0 fixed; a (n_x,) boolean mask estimates some entries.
    - `window`: cut one record into windows of this many samples, each with its own x0.
    - `missing`: `"raise"` (default) rejects NaN in z; `"mask"` takes NaN entries of z
        as missing samples (zero weight in the loss, the gradient and the Jacobian).
        Trajectories of different lengths (lists for `u` and `z`) are masked the same way.
    - `progress`: True shows a progress bar with the loss (tqdm), or a progress object
        (`oneshot_jax.TqdmProgress(refresh_steps=...)`).
    - `history`: the most rows of iterates kept (even, >= 2); longer runs are thinned
        evenly (see `FitHistory`).
    - `units`: a unit string per parameter name of theta0 (its dict keys, `"phys.c"` for
        a nested one), e.g. `{"I": "kg m^2"}`, shown by `print(result)`.

    **Staged training** (physics first, then a residual, then sparsity), each stage a
    `fit` that starts from the last one's result:

    1. the physical part alone: `fixed={"k": False, "c": False, "r": True}` holds the
       residual (a prefix pytree: one boolean for a whole module);
    2. jointly: `solver=[Adam(...), LevenbergMarquardt()]`;
    3. selection: `solver=Adam(lr_theta)` with `regulariser=sparsity.l1(lam, where)`;
    4. debiasing on the support: `solver=LevenbergMarquardt()` with
       `fixed=sparsity.fixed_zeros(result.theta, where)` (the deselected terms stay 0).

    **Returns:**

    A `FitResult`.
    """
    check_outside_transformations(theta0, x0, u, z, weight, penalty_weight)
    units = check_units(units, theta0)
    solvers = as_solvers(solver)
    if isinstance(history, bool) or not isinstance(history, int) or history < 2 or history % 2:
        raise ValueError(f"`history` must be an even integer >= 2, got {history!r}.")
    if progress is True:
        meter = TqdmProgress()
    elif progress is False or progress is None:
        meter = _NO_PROGRESS
    elif hasattr(progress, "update") and hasattr(progress, "open"):
        meter = progress
    else:
        raise TypeError(f"`progress` must be a bool or a progress object, got {progress!r}.")

    # Starting points: theta0 (S, ...) and x0 (S, ...) with multistart, else one start.
    u_ndim = 3 if _is_ragged(u) or _is_ragged(z) else np.ndim(u)
    per_window_x0 = window is not None and np.ndim(x0) == 2 and u_ndim == 2
    data_x0_ndim = 2 if (u_ndim == 3 or per_window_x0) else 1
    if multistart:
        theta_params, theta_static = _pytree.split(theta0)
        n_starts = _n_starts(theta_params, x0, data_x0_ndim)
        theta_first = _pytree.combine(
            jax.tree_util.tree_map(lambda a: a[0], theta_params), theta_static
        )
    else:
        n_starts, theta_first = None, theta0
    x0_starts = None
    if multistart and np.ndim(x0) == data_x0_ndim + 1:
        x0_starts = np.asarray(x0)
        x0 = x0_starts[0]

    if window is not None:
        if u_ndim != 2:
            raise ValueError(
                f"`window` needs one record: `u` of shape (T, n_u), got {np.shape(u)}."
            )
        x0_record = np.asarray(x0)[0] if per_window_x0 else x0
        data = check_data(model, theta_first, x0_record, u, z, weight, missing)
        x0_w, u_w, z_w, mask_w = cut(data, window, np.asarray(x0) if per_window_x0 else None)
        data = check_data(model, theta_first, x0_w, u_w, z_w, weight)._replace(mask=mask_w)
        if x0_starts is not None:
            raise ValueError("`window` with per-start x0 is not supported: give one x0.")
    else:
        data = check_data(model, theta_first, x0, u, z, weight, missing)
    cost = check_cost(data, penalty, penalty_weight)
    if cost.penalty is not None and float(cost.penalty_weight) < 0:
        if any(isinstance(s, AbstractLeastSquares) for s in solvers):
            raise ValueError(
                f"`penalty_weight` must be >= 0 with a least-squares solver, got "
                f"{float(cost.penalty_weight)}: it minimises a sum of squares that includes "
                "sqrt(penalty_weight h). Use a first-order solver (Adam, LBFGS) for a "
                "signed penalty."
            )
    batched = data.batched
    # Host-side (NumPy) views with the trajectory axis: no eager JAX call per array; the
    # compiled call below takes them as they are.
    X0, U, Z = (_host(a) if batched else np.asarray(a)[None] for a in (data.x0, data.u, data.z))
    n_x = X0.shape[1]

    flat0, unravel = _pytree.ravel(data.theta)
    fixed_flat = fixed_mask(fixed, data.theta)
    theta_free = np.flatnonzero(~fixed_flat)
    x0_est = x0_mask(estimate_x0, n_x)
    x0_free = np.flatnonzero(x0_est)
    if len(theta_free) == 0 and len(x0_free) == 0:
        raise ValueError("nothing to estimate: every parameter is fixed and estimate_x0 is False.")

    proj, reg = split(constraints, regulariser)
    on_theta = None  # the regulariser on theta's trainable part
    if reg is not None:
        for s in solvers:
            s.check_regulariser(reg)
        on_theta = Regulariser(reg.prox, reg.value, data.static, reg.strength, reg.learning_rate)
        check_regulariser(on_theta, data.theta)
    lower = upper = None
    project = None
    if proj is not None:
        if proj.bounds is not None:
            lo, hi = proj.bounds(data.theta)
            lo, hi = _pytree.flat_host(lo), _pytree.flat_host(hi)
            check_fixed_bounds(data.theta, fixed_flat, lo, hi)
            lower, upper = lo[theta_free], hi[theta_free]
        else:  # a general projection: check that it is one (boxes are by construction)
            check_projection(proj, data.theta)
            project = proj.project

    problem = _pytree.build(
        FitProblem,
        model=data.model,
        cost=cost,
        u=U,
        z=Z,
        theta_base=flat0,
        theta_free=tuple(int(i) for i in theta_free),
        unravel=unravel,
        x0_base=X0,
        x0_free=tuple(int(i) for i in x0_free),
        project=project,
        lower=lower,
        upper=upper,
        regulariser=on_theta,
        mask=None
        if data.mask is None
        else jax.tree_util.tree_map(
            lambda a: np.asarray(a) if batched else np.asarray(a)[None], data.mask
        ),
    )

    # Every start as free-variable arrays (built on the host).
    if multistart:
        starts_flat = np.stack(
            [
                _pytree.flat_host(jax.tree_util.tree_map(lambda a, i=i: a[i], theta_params))
                for i in range(n_starts)
            ]
        ).astype(X0.dtype)
        if x0_starts is not None:
            X0s = np.asarray(x0_starts if batched else x0_starts[:, None], X0.dtype)
        else:
            X0s = np.broadcast_to(X0, (n_starts, *X0.shape))
    else:
        starts_flat, X0s = np.asarray(flat0)[None], X0[None]
    all_t, all_x = theta_free.size == starts_flat.shape[1], x0_free.size == n_x
    starts = Params(
        starts_flat if all_t else starts_flat[:, theta_free],
        X0s if all_x else X0s[:, :, x0_free],
    )

    # (No bar: no calls of the meter's methods, which equinox wraps anew on each access.)
    bar = not isinstance(meter, NoProgress)
    bar_id = meter.open(sum(s.max_steps for s in solvers)) if bar else 0
    try:
        with counting() as counts:
            t0 = time.perf_counter()
            buffers, layout = _solve(
                solvers, problem, starts, history, meter, np.asarray(bar_id, np.int32)
            )
            jax.block_until_ready(buffers)
            jax.effects_barrier()
            wall = time.perf_counter() - t0
    finally:
        if bar:
            meter.close(bar_id)
    out = _pytree.unpack(buffers, layout)
    diagnostics = dict(counts) if counts["parallel_rollouts"] else {}
    if counts["sequential_fallbacks"]:
        warnings.warn(
            f"{counts['sequential_fallbacks']} of {counts['parallel_rollouts']} parallel "
            "rollouts did not converge and fell back to the sequential loop (the results are "
            "exact; see FitResult.diagnostics).",
            RuntimeWarning,
            stacklevel=2,
        )
    if out.moved:
        warnings.warn(
            "theta0 lies outside the constraint set; it was projected onto it.", stacklevel=2
        )
    return assemble(
        model=model,
        problem=problem,
        data=data,
        out=out,
        wall_time=wall,
        solvers=solvers,
        fixed=fixed_flat,
        x0_estimated=x0_est,
        multistart=multistart,
        diagnostics=diagnostics,
        theta_order=_theta_order(theta0),
        units=units,
    )
