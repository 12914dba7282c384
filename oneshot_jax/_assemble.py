"""From the solvers' raw output to a `FitResult`: the traced post-processing inside the
fit's compiled call (`post`), and the host-side assembly (`assemble`)."""

import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from . import metrics as _metrics
from ._covariance import covariance, scale
from ._fit_result import FitHistory, FitResult, Starts
from ._optimality import roundoff_limit
from ._results import from_index, name_of
from ._simulate import simulate_impl
from ._strategy import COVARIANCE_MAX_THETA


class StageOut(NamedTuple):
    """What `assemble` reads of one solver's `Solution`, for the best start."""

    step: jax.Array  # (size,) the step of each history row (-1: unused)
    loss: jax.Array  # (size,)
    grad_norm: jax.Array  # (size,)
    theta: jax.Array  # (size, p)
    num_steps: jax.Array
    final_theta: jax.Array  # (p,) its last iterate, its loss and gradient norm
    final_loss: jax.Array
    final_grad_norm: jax.Array
    validation: jax.Array | None  # (size,) the validation loss of each row, or None


class Out(NamedTuple):
    """Everything `assemble` reads from a fit's compiled call (`collect`)."""

    moved: jax.Array  # whether a start was projected onto the constraint set
    best: jax.Array
    theta: jax.Array  # (n,) flat theta of the best start
    x0: jax.Array  # (N, n_x)
    residuals: jax.Array
    covariance: Any  # a `Covariance`, or None above COVARIANCE_MAX_THETA
    metrics: dict
    stages: tuple  # a `StageOut` per solver
    results: jax.Array  # (S,) the last solver's RESULTS index per start
    losses: jax.Array  # (S,)
    start_theta: jax.Array  # (S, p) the free entries of theta per start
    first_order: jax.Array  # the measures the best start's stop was tested on
    step: jax.Array
    decrease: jax.Array
    standard_errors: jax.Array
    validation_loss: jax.Array | None  # the best start's lowest validation loss, or None


def collect(stages, best, moved, posted) -> Out:
    """`Out` from the solvers' `Solution`s and `post`'s output (traced, inside the fit's
    compiled call: indexing only)."""
    theta, x0, e, cov, met, _ = posted
    final = stages[-1]
    per_stage = tuple(
        StageOut(
            s.history.step,
            s.history.loss[:, best],
            s.history.grad_norm[:, best],
            s.history.theta[:, best],
            s.num_steps[best],
            s.final_theta[best],
            s.final_loss[best],
            s.final_grad_norm[best],
            None if s.history.validation is None else s.history.validation[:, best],
        )
        for s in stages
    )
    m = final.measures
    return Out(
        moved,
        best,
        theta,
        x0,
        e,
        cov,
        met,
        per_stage,
        final.result._value,
        final.loss,
        final.params.theta,
        m.first_order[best],
        m.step[best],
        m.decrease[best],
        m.standard_errors[best],
        None if final.best is None else final.best.score[best],
    )


def post(problem, params, blocks, strategy):
    """Everything `FitResult` needs from the solution, traced inside the fit's compiled
    call: theta (flat), x0, the residuals, the covariance blocks and the metrics; and the
    simulated states (for `_stability`)."""
    theta = problem.theta_of(params.theta)
    X0 = problem.x0_of(params.x0)
    xs, zhat = simulate_impl(problem.model, theta, X0, problem.u, True, strategy)
    # Above COVARIANCE_MAX_THETA free entries of theta the covariance (a dense Jacobian with
    # a column per parameter, and a p x p eigendecomposition) is not computed.
    cov = None
    if params.theta.shape[0] <= COVARIANCE_MAX_THETA:
        cov = covariance(problem, params, strategy, blocks)
    zs = problem.z
    m = None if problem.mask is None else problem.mask.outputs
    n_free = params.theta.shape[0] + params.x0.size
    met = {
        "rmse": _metrics.rmse(zs, zhat, m),
        "nrmse": _metrics.nrmse(zs, zhat, m),
        "fit_percent": _metrics.fit_percent(zs, zhat, m),
        "r2": _metrics.r2(zs, zhat, m),
        "aic": _metrics.aic(zs, zhat, n_free, m),
    }
    theta_flat = problem.theta_base.at[np.asarray(problem.theta_free, int)].set(params.theta)
    e = zhat - zs if m is None else jnp.where(m > 0, zhat - zs, jnp.nan)
    return theta_flat, X0, e, cov, met, xs


def _history(problem, stages, like):
    """One `FitHistory` from every stage's bounded buffer (`StageOut`s): the best start's
    rows before its last step, then its last iterate."""
    losses, gnorms, paths, steps, stage_ids, scores = [], [], [], [], [], []
    base = np.asarray(problem.theta_base)
    free = np.asarray(problem.theta_free, int)
    all_free = free.size == base.size  # (then the rows are the free entries themselves)
    for i, h in enumerate(stages):
        n = int(h.num_steps)
        rows = np.flatnonzero((h.step >= 0) & (h.step < n))
        if not rows.size or rows[-1] == rows.size - 1:  # the usual prefix: slices, no gathers
            rows = slice(0, rows.size)
        theta = np.concatenate([h.theta[rows], h.final_theta[None]])
        if all_free and theta.dtype == base.dtype:
            flat = theta
        else:
            flat = np.empty((theta.shape[0], base.shape[0]), base.dtype)
            flat[:] = base
            flat[:, free] = theta
        losses.append(np.concatenate([h.loss[rows], h.final_loss[None]]))
        gnorms.append(np.concatenate([h.grad_norm[rows], h.final_grad_norm[None]]))
        paths.append(flat)
        steps.append(np.concatenate([h.step[rows], [n]]).astype(np.int32))
        stage_ids.append(np.full(theta.shape[0], i, np.int32))
        if h.validation is not None:  # (the final iterate's row: NaN, not recorded)
            scores.append(np.concatenate([h.validation[rows], [np.nan]]))
    one = len(stages) == 1
    return _pytree.build(
        FitHistory,
        loss=losses[0] if one else np.concatenate(losses),
        grad_norm=gnorms[0] if one else np.concatenate(gnorms),
        theta=_pytree.unflatten_rows(paths[0] if one else np.concatenate(paths), like),
        step=steps[0] if one else np.concatenate(steps),
        stage=stage_ids[0] if one else np.concatenate(stage_ids),
        validation=np.concatenate(scores) if scores else None,
    )


_SETTINGS: dict = {}


def _settings(solver) -> dict:
    """`solver.settings()`, kept per solver object (solvers are immutable); a fresh dict
    each time."""
    kept = _SETTINGS.get(id(solver))
    if kept is None or kept[0] is not solver:  # (an id can be reused by a new object)
        kept = (solver, solver.settings())
        if len(_SETTINGS) >= 64:
            _SETTINGS.pop(next(iter(_SETTINGS)))
        _SETTINGS[id(solver)] = kept
    return dict(kept[1])


_NAMES: dict = {}


def _free_names(params, free):
    """The names of theta's free entries (`_pytree.leaf_names`), kept per structure."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    key = (treedef, tuple(np.shape(a) for a in leaves), tuple(free))

    def names():
        all_names = _pytree.leaf_names(params)
        return tuple(all_names[i] for i in free)

    return _pytree.kept(_NAMES, key, names)


def _warn_identifiability(names, ok, what):
    if ok.all():
        return
    bad = [n for n, k in zip(names, ok) if not k]
    if bad:
        # A network's weights are many and never all identifiable: name a few.
        listed = f"{bad}" if len(bad) <= 10 else f"{bad[:10]} and {len(bad) - 10} more"
        warnings.warn(
            f"the Jacobian is rank-deficient at the solution: {what} {listed} enter its "
            "null space (a change of them, alone or together, that leaves the outputs "
            "unchanged: not identifiable from these data); their std is inf.",
            stacklevel=4,
        )


def assemble(
    *,
    model,
    problem,
    data,
    out: Out,
    wall_time,
    solvers,
    fixed,
    x0_estimated,
    multistart,
    diagnostics=None,
    theta_order=(),
    units=None,
    window_starts=None,
) -> FitResult:
    """The `FitResult` of the best start, on the host, from the compiled call's `Out`
    (NumPy arrays)."""
    theta_flat, X0, e, cov, met = out.theta, out.x0, out.residuals, out.covariance, out.metrics
    best = int(out.best)
    like = jax.tree_util.tree_map(np.asarray, data.theta)
    params = _pytree.unflatten_rows(theta_flat[None], like, squeeze=True)
    free = np.asarray(problem.theta_free, int)
    names = _free_names(params, problem.theta_free)

    x0_free = np.asarray(problem.x0_free, int)
    flat_std = np.zeros(theta_flat.shape)
    x0_std = np.zeros(X0.shape)
    if cov is None:  # not computed (a large theta): no (p, p) matrix, unknown (inf) errors
        warnings.warn(
            f"the covariance of the estimates is not computed above {COVARIANCE_MAX_THETA} "
            f"free entries of theta ({free.size} here): std and x0_std are inf (unknown).",
            stacklevel=3,
        )
        theta_cov = np.zeros((0, 0))
        flat_std[free] = np.inf
        x0_std[:, x0_free] = np.inf
        x0_cov = np.full((X0.shape[0], x0_free.size, x0_free.size), np.inf)
    else:
        n_obs = int(np.count_nonzero(np.isfinite(e)))
        scaled = scale(cov, n_obs)
        _warn_identifiability(names, scaled.theta_identifiable, "parameters")
        if not scaled.x0_identifiable.all():
            x0_names = [
                f"x0[{i}, {j}]" if data.batched else f"x0[{j}]"
                for i in range(X0.shape[0])
                for j in problem.x0_free
            ]
            _warn_identifiability(x0_names, scaled.x0_identifiable.reshape(-1), "initial states")
        theta_cov = scaled.theta
        if free.size == flat_std.size:  # every entry free: no scatter
            flat_std = np.sqrt(np.maximum(np.diag(scaled.theta), 0.0))
        elif free.size:
            flat_std[free] = np.sqrt(np.maximum(np.diag(scaled.theta), 0.0))
        if x0_free.size:
            diag = np.sqrt(np.maximum(np.diagonal(scaled.x0, axis1=1, axis2=2), 0.0))
            if x0_free.size == x0_std.shape[1]:
                x0_std = diag
            else:
                x0_std[:, x0_free] = diag
        x0_cov = scaled.x0
    std = _pytree.unflatten_rows(flat_std[None], like, squeeze=True)

    results, losses = out.results, out.losses
    starts = None
    if multistart:
        rows = np.broadcast_to(np.asarray(problem.theta_base), (losses.shape[0], theta_flat.size))
        rows = rows.copy()
        rows[:, free] = out.start_theta
        starts = Starts(
            theta=_pytree.unflatten_rows(rows, like),
            loss=losses,
            stop_reason=tuple(name_of(from_index(int(c))) for c in results),
        )
    metrics = {k: (float(v) if k == "aic" else v) for k, v in met.items()}
    stop_info = {
        "first_order": float(out.first_order),
        "gtol": float(getattr(solvers[-1], "gtol", np.nan)),
        "step": float(out.step),
        "decrease": float(out.decrease),
        "standard_errors": float(out.standard_errors),
        "stol": float(getattr(solvers[-1], "stol", np.nan)),
        "at_step": int(out.stages[-1].num_steps),
        "roundoff_limit": roundoff_limit(problem.dtype),
    }
    if not data.batched:
        X0, e, x0_std, x0_cov = X0[0], e[0], x0_std[0], x0_cov[0]
    return _pytree.build(
        FitResult,
        theta=_pytree.combine(params, data.static),
        x0=X0,
        loss=np.asarray(losses[best]),
        stop_reason=from_index(int(results[best])),
        num_steps=int(sum(int(s.num_steps) for s in out.stages)),
        wall_time=float(wall_time),
        history=_history(problem, out.stages, like),
        residuals=e,
        names=names,
        fixed=np.asarray(fixed, bool),
        covariance=theta_cov,
        std=std,
        x0_covariance=x0_cov,
        x0_std=x0_std,
        x0_estimated=np.asarray(x0_estimated, bool),
        metrics=metrics,
        starts=starts,
        best=best,
        solver=tuple(_settings(s) for s in solvers),
        model=model,
        diagnostics=dict(diagnostics or {}),
        stop_info=stop_info,
        theta_order=tuple(theta_order),
        units=dict(units or {}),
        validation_loss=None if out.validation_loss is None else float(out.validation_loss),
        window_starts=None if window_starts is None else np.asarray(window_starts),
    )
