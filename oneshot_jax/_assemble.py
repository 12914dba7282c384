"""From the solvers' raw output to a `FitResult`: the traced post-processing inside the
fit's compiled call (`post`), and the host-side assembly (`assemble`)."""

import warnings

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


def post(problem, params, blocks, strategy):
    """Everything `FitResult` needs from the solution, traced inside the fit's compiled
    call: theta (flat), x0, the residuals, the covariance blocks and the metrics."""
    theta = problem.theta_of(params.theta)
    X0 = problem.x0_of(params.x0)
    _, zhat = simulate_impl(problem.model, theta, X0, problem.u, True, strategy)
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
    return theta_flat, X0, e, cov, met


def _history(problem, stages, best, like):
    """One `FitHistory` from every stage's bounded buffer: the best start's rows before
    its last step, then its last iterate."""
    losses, gnorms, paths, steps, stage_ids = [], [], [], [], []
    base = np.asarray(problem.theta_base)
    free = list(problem.theta_free)
    for i, sol in enumerate(stages):
        h = sol.history
        n = int(np.asarray(sol.num_steps)[best])
        rows = (np.asarray(h.step) >= 0) & (np.asarray(h.step) < n)
        theta = np.concatenate(
            [np.asarray(h.theta)[rows, best], np.asarray(sol.final_theta)[best][None]]
        )
        flat = np.broadcast_to(base, (theta.shape[0], base.shape[0])).copy()
        flat[:, free] = theta
        losses.append(np.append(np.asarray(h.loss)[rows, best], np.asarray(sol.final_loss)[best]))
        gnorms.append(
            np.append(np.asarray(h.grad_norm)[rows, best], np.asarray(sol.final_grad_norm)[best])
        )
        paths.append(flat)
        steps.append(np.append(np.asarray(h.step)[rows], n).astype(np.int32))
        stage_ids.append(np.full(theta.shape[0], i, np.int32))
    return FitHistory(
        loss=np.concatenate(losses),
        grad_norm=np.concatenate(gnorms),
        theta=_pytree.unflatten_rows(np.concatenate(paths), like),
        step=np.concatenate(steps),
        stage=np.concatenate(stage_ids),
    )


def _warn_identifiability(names, ok, what):
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
    stages,
    best,
    posted,
    wall_time,
    solvers,
    fixed,
    x0_estimated,
    multistart,
    diagnostics=None,
    theta_order=(),
    units=None,
) -> FitResult:
    """The `FitResult` of the best start, on the host."""
    theta_flat, X0, e, cov, met = jax.tree_util.tree_map(np.asarray, posted)
    like = jax.tree_util.tree_map(np.asarray, data.theta)
    params = _pytree.unflatten_rows(theta_flat[None], like, squeeze=True)
    final = stages[-1]
    free = np.asarray(problem.theta_free, int)
    all_names = _pytree.leaf_names(params)
    names = tuple(all_names[i] for i in free)

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
        n_obs = int(np.sum(np.isfinite(e)))
        scaled = scale(cov, n_obs)
        _warn_identifiability(names, scaled.theta_identifiable, "parameters")
        x0_names = [
            f"x0[{i}, {j}]" if data.batched else f"x0[{j}]"
            for i in range(X0.shape[0])
            for j in problem.x0_free
        ]
        _warn_identifiability(x0_names, scaled.x0_identifiable.reshape(-1), "initial states")
        theta_cov = scaled.theta
        flat_std[free] = np.sqrt(np.maximum(np.diag(scaled.theta), 0.0)) if free.size else []
        if x0_free.size:
            diag = np.diagonal(scaled.x0, axis1=1, axis2=2)
            x0_std[:, x0_free] = np.sqrt(np.maximum(diag, 0.0))
        x0_cov = scaled.x0
    std = _pytree.unflatten_rows(flat_std[None], like, squeeze=True)

    results = np.asarray(final.result._value)
    losses = np.asarray(final.loss)
    starts = None
    if multistart:
        rows = np.broadcast_to(np.asarray(problem.theta_base), (losses.shape[0], theta_flat.size))
        rows = rows.copy()
        rows[:, free] = np.asarray(final.params.theta)
        starts = Starts(
            theta=_pytree.unflatten_rows(rows, like),
            loss=losses,
            stop_reason=tuple(name_of(from_index(int(c))) for c in results),
        )
    metrics = {k: (float(v) if k == "aic" else v) for k, v in met.items()}
    m = final.measures
    stop_info = {
        "first_order": float(np.asarray(m.first_order)[best]),
        "gtol": float(getattr(solvers[-1], "gtol", np.nan)),
        "step": float(np.asarray(m.step)[best]),
        "decrease": float(np.asarray(m.decrease)[best]),
        "at_step": int(np.asarray(final.num_steps)[best]),
        "roundoff_limit": roundoff_limit(problem.dtype),
    }
    if not data.batched:
        X0, e, x0_std, x0_cov = X0[0], e[0], x0_std[0], x0_cov[0]
    return FitResult(
        theta=_pytree.combine(params, data.static),
        x0=X0,
        loss=np.asarray(losses[best]),
        stop_reason=from_index(int(results[best])),
        num_steps=int(sum(int(np.asarray(s.num_steps)[best]) for s in stages)),
        wall_time=float(wall_time),
        history=_history(problem, stages, best, like),
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
        best=int(best),
        solver=tuple(s.settings() for s in solvers),
        model=model,
        diagnostics=dict(diagnostics or {}),
        stop_info=stop_info,
        theta_order=tuple(theta_order),
        units=dict(units or {}),
    )
