"""From the solvers' raw output to a `FitResult`: the traced post-processing inside the
fit's compiled call (`post`), and the host-side assembly (`assemble`)."""

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from . import metrics as _metrics
from ._caller_warnings import warn
from ._covariance import NOT_COMPUTED, covariance, sandwich, scale
from ._fit_report import FLOAT64, below_float64
from ._fit_result import FitHistory, FitResult, Starts
from ._linalg import NULL_CUT
from ._model import model_labels
from ._optimality import promises_descent, resolution, roundoff_limit
from ._results import SUCCESS, from_index, name_of
from ._simulate import simulate_impl
from ._strategy import (
    COVARIANCE_MAX_THETA,
    DENSE_JACOBIAN_BYTES,
    dense_jacobian_bytes,
    dense_jacobian_fits,
)


class StageOut(NamedTuple):
    """What `assemble` reads of one solver's `Solution`, for the best start: its history
    rows with the last iterate written after them (row `rows`), so that the host slices
    `[: rows + 1]` and copies nothing."""

    step: jax.Array  # (size + 1,) the step of each history row (-1: unused)
    loss: jax.Array  # (size + 1,)
    grad_norm: jax.Array  # (size + 1,)
    theta: jax.Array  # (size + 1, p)
    rows: jax.Array  # the rows recorded before the last iterate (steps 0 .. num_steps - 1)
    num_steps: jax.Array
    validation: jax.Array | None  # (size + 1,) the validation loss of each row, or None


class Out(NamedTuple):
    """Everything `assemble` reads from a fit's compiled call (`collect`)."""

    moved: jax.Array  # (S, p): the entries each start had outside the constraint set
    best: jax.Array
    theta: jax.Array  # (n,) flat theta of the best start
    x0: jax.Array  # (N, n_x)
    residuals: jax.Array
    covariance: Any  # a `Scaled` covariance, or None above COVARIANCE_MAX_THETA
    metrics: dict
    stages: tuple  # a `StageOut` per solver
    results: jax.Array  # (S,) the last solver's RESULTS index per start
    losses: jax.Array  # (S,)
    start_theta: jax.Array  # (S, p) the free entries of theta each start ended at
    start_x0: jax.Array  # (S, ...) the free x0 each start ended at
    first_order: jax.Array  # the measures the best start's stop was tested on
    step: jax.Array
    decrease: jax.Array
    standard_errors: jax.Array
    step_test: jax.Array  # whether the optional step test (rtol, atol) fired
    limit: jax.Array  # the round-off limit of a stall at the best start's point (or NaN)
    validation_loss: jax.Array | None  # (S,) the validation loss of each start's returned point
    solver_results: jax.Array  # (S,) the last solver's own stop per start (before validation)
    # Per start (S,): whether its first-order measure is a stall's with vanished columns
    # (a degenerate minimum), the theta columns that vanished along its fit ((S, p), or
    # (S,) False), and whether its measure promises a decrease (a zero residual's,
    # `promises_descent`): the report, and the checks after the solve
    # (`_fit._flag_refuted_stop`).
    degenerate: jax.Array
    vanished: jax.Array
    promises_descent: jax.Array
    # With validation data: the solver (stage) and step of the best start's lowest-scored
    # iterate, which the fit returns where its stop is `validation`; else None.
    validation_at: jax.Array | None = None


def _stage_out(s, best) -> StageOut:
    """The best start's rows of one solver's bounded history (`_history`: a prefix of the
    buffer, steps increasing), its last iterate written after the rows before its last step
    (with its validation loss, the `Best`'s last score)."""
    n = s.num_steps[best]
    step = s.history.step
    if step.ndim == 2:  # (starts taken in turn: each start's own steps)
        step = step[best]
    rows = jnp.sum((step >= 0) & (step < n), dtype=jnp.int32)

    def after(a, last):
        return jnp.concatenate([a, last[None]]).at[rows].set(last)

    val = s.history.validation
    return StageOut(
        after(step, n.astype(step.dtype)),
        after(s.history.loss[:, best], s.final_loss[best]),
        after(s.history.grad_norm[:, best], s.final_grad_norm[best]),
        after(s.history.theta[:, best], s.final_theta[best]),
        rows,
        n,
        None if val is None else after(val[:, best], s.best.last[best].astype(val.dtype)),
    )


def collect(problem, stages, best, moved, posted) -> Out:
    """`Out` from the solvers' `Solution`s and `post`'s output (traced, inside the fit's
    compiled call: indexing, and `promises_descent` at each start's stop)."""
    theta, x0, e, cov, met, _ = posted
    final = stages[-1]
    per_stage = tuple(_stage_out(s, best) for s in stages)
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
        final.params.x0,
        m.first_order[best],
        m.step[best],
        m.decrease[best],
        m.standard_errors[best],
        m.step_test[best],
        m.limit[best],
        None if final.best is None else final.best.returned_score(),
        final.solver_result._value,
        m.degenerate,
        m.vanished,
        promises_descent(problem, final.loss, m.first_order),
        None if final.best is None else jnp.stack([final.best.stage[best], final.best.step[best]]),
    )


def post(problem, params, blocks, strategy, lags=None):
    """Everything `FitResult` needs from the solution, traced inside the fit's compiled
    call: theta (flat), x0, the residuals, the covariance blocks and the metrics; and the
    simulated states (for `_stability`). `lags`: the Newey-West sandwich's L (the
    covariance is then `sandwich`), None, or `NOT_COMPUTED` (`fit(covariance=None)`: no
    covariance)."""
    theta = problem.theta_of(params.theta)
    X0 = problem.x0_of(params.x0)
    xs, zhat = simulate_impl(problem.model, theta, X0, problem.u, True, strategy)
    # Above COVARIANCE_MAX_THETA free entries of theta, or where its dense Jacobian would
    # not fit (`dense_jacobian_fits`; the blocks a dense least-squares solve held are
    # used as they are), the covariance (a dense Jacobian with a column per parameter, and
    # a p x p eigendecomposition) is not computed.
    zs = problem.z
    m = None if problem.mask is None else problem.mask.outputs
    e = zhat - zs if m is None else jnp.where(m > 0, zhat - zs, jnp.nan)
    cov = None
    # the solver's own Jacobian's blocks (not where a record holds x0 entries the solver
    # estimates in others: `_covariance.covariance` takes them out of its own)
    x_held = problem.x0_held
    if x_held is not None:
        blocks = None
    held = blocks is not None and lags is None
    n_cols = params.theta.shape[0] + params.x0.shape[-1]
    if (
        lags != NOT_COMPUTED
        and params.theta.shape[0] <= COVARIANCE_MAX_THETA
        and (held or dense_jacobian_fits(problem, n_cols))
    ):
        cost = problem.cost
        if lags is None:
            cov = scale(covariance(problem, params, strategy, blocks), e, cost, held=x_held)
        else:
            cov = sandwich(problem, params, strategy, lags)
            cov = scale(cov, e, cost, robust=True, held=x_held)
    n_free = params.theta.shape[0] + params.x0.size
    if x_held is not None:
        n_free = n_free - jnp.sum(x_held)
    met = {
        "rmse": _metrics.rmse(zs, zhat, m),
        "nrmse": _metrics.nrmse(zs, zhat, m),
        "fit_percent": _metrics.fit_percent(zs, zhat, m),
        "r2": _metrics.r2(zs, zhat, m),
        "aic": _metrics.aic(zs, zhat, n_free, m),
        "aicc": _metrics.aicc(zs, zhat, n_free, m),
        "bic": _metrics.bic(zs, zhat, n_free, m),
        "fpe": _metrics.fpe(zs, zhat, n_free, m),
    }
    # MATLAB's compare reports a FIT per experiment: the pooled one above measures each
    # record against the mean of all, which records at different operating points inflate.
    one = zs.ndim == 2  # (one record: its row)
    rec = [None if a is None else (a[None] if one else a) for a in (zs, zhat, m)]
    met["fit_percent_per_record"] = jax.vmap(_metrics.fit_percent)(*rec)
    theta_flat = problem.theta_base.at[np.asarray(problem.theta_free, int)].set(params.theta)
    return theta_flat, X0, e, cov, met, xs


def _with_row(h: StageOut, row) -> StageOut:
    """`h`'s rows with `row` = (step, loss, theta, validation) among them, at its step,
    unless a row of that step is there (its gradient norm NaN: not at hand)."""
    step, loss, theta, score = row
    k = int(h.rows) + 1
    steps = np.asarray(h.step[:k])
    if np.any(steps == step):
        return h
    i = int(np.searchsorted(steps, step))

    def put(a, value):
        a = np.asarray(a[:k])
        return np.concatenate([a[:i], np.asarray(value, a.dtype)[None], a[i:]])

    return StageOut(
        put(h.step, step),
        put(h.loss, loss),
        put(h.grad_norm, np.nan),
        put(h.theta, theta),
        k,
        h.num_steps,
        None if h.validation is None else put(h.validation, score),
    )


def _history(problem, stages, layout, chosen=None):
    """One `FitHistory` from every stage's bounded buffer (`StageOut`s): the best start's
    rows before its last step, then its last iterate. `chosen`: where a `validation` stop
    returns an earlier iterate, (stage, step, loss, free theta, score) of it: a row of the
    history wherever thinning left it out."""
    base = problem.theta_base
    free = problem.theta_free
    if chosen is not None:
        at, *row = chosen
        stages = tuple(_with_row(h, row) if i == at else h for i, h in enumerate(stages))
    losses, gnorms, paths, steps, stage_ids, scores = [], [], [], [], [], []
    for i, h in enumerate(stages):
        k = int(h.rows) + 1
        theta = h.theta[:k]
        if len(free) != base.shape[0] or theta.dtype != base.dtype:
            flat = np.empty((k, base.shape[0]), base.dtype)
            flat[:] = base
            flat[:, list(free)] = theta
            theta = flat
        losses.append(h.loss[:k])
        gnorms.append(h.grad_norm[:k])
        paths.append(theta)
        steps.append(h.step[:k])
        stage = np.empty(k, np.int32)
        stage.fill(i)
        stage_ids.append(stage)
        if h.validation is not None:
            scores.append(h.validation[:k])
    if len(stages) == 1:
        loss, grad_norm, path, step, stage = losses[0], gnorms[0], paths[0], steps[0], stage_ids[0]
        validation = scores[0] if scores else None
    else:
        loss, grad_norm, path = (
            np.concatenate(losses),
            np.concatenate(gnorms),
            np.concatenate(paths),
        )
        step, stage = np.concatenate(steps), np.concatenate(stage_ids)
        validation = np.concatenate(scores) if scores else None
    return _pytree.build(
        FitHistory,
        loss=loss,
        grad_norm=grad_norm,
        theta=layout.rows(path),
        step=step,
        stage=stage,
        validation=validation,
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


def _warn_identifiability(
    names, ok, what, stop, unconverged=0, worst_fit=None, low=None, shrunk=None, gone=()
):
    """Warn of the free entries `names` outside the Jacobian's range (`ok` False) at a fit
    that stopped with `stop`: at a solution, a property of the data; elsewhere (a stall
    at a blown-up simulation, say), after `unconverged` parallel rollouts that kept
    Newton's unconverged iterate, or at a success whose simulation fits an output worse
    than its mean (`worst_fit`, its FIT% below 0: a bad minimum, where a chaotic
    trajectory's sensitivities make every column parallel), it may be the point's or
    the rollouts' only, and the warning says so. `low`: the name of a precision below
    float64, where J^T J's round-off alone makes nearly collinear columns read null (an
    output offset next to an input of large mean: finite standard errors in float64),
    and the warning says that instead. `shrunk`: "regularised" or "penalised" for a fit
    with a regulariser or a penalty, whose solution (a term the regulariser set to zero,
    whose coefficients then act on nothing) may make columns vanish that the data
    determine elsewhere. `gone`: the names whose Jacobian columns vanished along the fit
    (`_optimality.vanished_columns`): a success there is a point where a term switched
    itself off (a time constant run off to -1e7, where the model is its limit), whose
    null space is the point's."""
    if ok.all():
        return
    bad = [n for n, k in zip(names, ok) if not k]
    if bad:
        # A network's weights are many and never all identifiable: name a few.
        listed = f"{bad}" if len(bad) <= 10 else f"{bad[:10]} and {len(bad) - 10} more"
        if unconverged:
            where, verdict = (
                f"at the returned point, after {unconverged} parallel rollouts of the fit "
                "did not converge (`ParallelInTime(fallback=False)`)",
                "not identifiable there, which may be the rollouts' and not the data's",
            )
        elif stop in SUCCESS and worst_fit is not None:
            where, verdict = (
                f"where the fit stopped ({stop}, but an output's FIT is {worst_fit:.3g} %, "
                "worse than its mean: likely a bad minimum, see `oj.check_basin`)",
                "not identifiable there, which may be the point's and not the data's",
            )
        elif stop in SUCCESS and shrunk is not None:
            where, verdict = (
                f"at the solution of the {shrunk} problem",
                "not identifiable there, which may be the point's (a term the "
                f"{'penalty' if shrunk == 'penalised' else 'regulariser'} switched "
                "off) and not the data's",
            )
        elif stop in SUCCESS and set(bad) & set(gone):
            shown = sorted(set(bad) & set(gone), key=bad.index)
            shown = f"{shown}" if len(shown) <= 10 else f"{shown[:10]} and more"
            where, verdict = (
                f"where the fit stopped ({stop}), after the Jacobian columns of {shown} "
                "vanished along the fit (a term that switched itself off, see the printout)",
                "not identifiable there, which may be the point's and not the data's",
            )
        elif stop in SUCCESS:
            where, verdict = (
                "at the solution",
                "not identifiable from these data around this estimate: the rank is the "
                "Jacobian's here, and in another minimum, or with bounds that keep the "
                "states physical, it may be full",
            )
        else:
            where, verdict = (
                f"where the fit stopped ({stop}: not a solution, see its message)",
                "not identifiable there, which may be the point's and not the data's",
            )
        hold = (
            "hold some of them (`fit(..., fixed=...)`"
            + (", `estimate_x0=...`" if what == "initial states" else "")
            + "), reparametrise (a product a * b as one parameter), or add data that "
            "excite them."
        )
        if low is not None:
            warn(
                f"J^T J is singular to {low} precision {where}: {what} {listed} enter its "
                f"numerical null space (its eigenvalues below {NULL_CUT:g} eps of the "
                f"largest are round-off in {low}: nearly collinear columns reach it though "
                "the data may determine them, and columns the outputs do not depend on "
                "are there in any precision); their std is inf, not resolved in this "
                f"precision. To tell, {FLOAT64}; if they stay unidentifiable there, {hold}",
                stacklevel=4,
            )
            return
        warn(
            f"the Jacobian is rank-deficient {where}: {what} {listed} enter its "
            "null space (a change of them, alone or together, that leaves the outputs "
            f"unchanged: {verdict}); their std is inf. {hold[0].upper()}{hold[1:]}",
            stacklevel=4,
        )


def weighed(per_output, weight=None):
    """A metric per output (n_z,) as float64, NaN for the outputs the fit does not weigh
    (Q's diagonal 0: an output of weight 0 is ignored on purpose)."""
    values = np.asarray(np.nan if per_output is None else per_output, np.float64)
    if weight is not None and values.ndim == 1:
        q = np.asarray(weight, np.float64)
        q = np.diagonal(q) if q.ndim == 2 else np.broadcast_to(q, values.shape)
        values = np.where(q > 0, values, np.nan)
    return values


def worst_fit(fit_percent, weight=None, residuals=None):
    """The lowest finite FIT% over the outputs the fit weighs (`weighed`) where it is below
    0 (a simulation that fits an output worse than that output's mean) by more than the
    noise explains, else None.

    An output whose signal s is small next to its noise (std ratio r) has FIT about
    50 r^2 % at the true parameters, give or take 100 r / sqrt(n) % over its n measured
    samples (`residuals`' finite entries, the last axis the outputs): a FIT below 0 is
    then no sign of a bad minimum. Three of those deviations less the FIT of the truth,
    300 r / sqrt(n) - 50 r^2, is largest at r = 3 / sqrt(n): 450 / n %. A FIT below
    -450 / n % (-2.25 % over 200 samples) is beyond three deviations of that chance at
    any r; a bad minimum's is far lower (-139 % in the minima guide)."""
    fits = weighed(fit_percent, weight)
    # (NaN: an output without spread, measured once or constant, has no FIT to judge by,
    # `metrics.fit_percent`; `fit_orthogonal`'s penalty rows, say)
    fits = np.where(np.isfinite(fits), fits, np.nan)
    if residuals is not None and fits.ndim == 1:
        e = np.asarray(residuals)
        n = np.isfinite(e.reshape(-1, e.shape[-1])).sum(axis=0) if e.ndim else np.zeros(0)
        if n.shape == fits.shape:
            fits = np.where(fits < -450.0 / np.maximum(n, 1), fits, np.nan)
    if not np.isfinite(fits).any() or np.nanmin(fits) >= 0:
        return None
    return float(np.nanmin(fits))


class Prepared(NamedTuple):
    """What `assemble` reads that does not depend on the solve's output (`prepare`)."""

    layout: _pytree.Layout  # of theta's trainable part
    names: tuple  # of theta's free entries
    solver: tuple  # each solver's settings
    fixed: np.ndarray
    x0_estimated: np.ndarray
    theta_order: tuple
    units: dict
    gtol: float  # the last solver's tolerances (NaN where it has none)
    stol: float
    roundoff_limit: float
    resolution: float  # (NaN where the last solver does not raise gtol to it)


def prepare(*, data, problem, solvers, fixed, x0_estimated, theta_order=(), units=None):
    """The host-side part of the `FitResult` that does not need the solve's output: `fit`
    forms it while the compiled call runs (asynchronous dispatch)."""
    layout = _pytree.layout(data.theta)
    return Prepared(
        layout,
        layout.names(problem.theta_free),
        tuple(_settings(s) for s in solvers),
        np.array(fixed, bool),
        np.array(x0_estimated, bool),
        tuple(theta_order),
        dict(units or {}),
        float(getattr(solvers[-1], "gtol", np.nan)),
        float(getattr(solvers[-1], "stol", np.nan)),
        roundoff_limit(problem.dtype),
        resolution(problem.dtype)
        if getattr(solvers[-1], "GTOL_AT_LEAST_RESOLUTION", False)
        else np.nan,
    )


def _chosen(out: Out, status, best):
    """The returned iterate's (stage, step, loss, free theta, validation loss) where a
    `validation` stop returns the lowest-scored one, for `_history`; else None."""
    if status != "validation" or out.validation_at is None:
        return None
    stage, step = (int(v) for v in np.asarray(out.validation_at))
    return (
        stage,
        step,
        out.losses[best],
        out.start_theta[best],
        out.validation_loss[best],
    )


def assemble(
    *,
    prepared: Prepared,
    model,
    problem,
    data,
    out: Out,
    wall_time,
    multistart,
    diagnostics=None,
    window_starts=None,
    n_u=None,
) -> FitResult:
    """The `FitResult` of the best start, on the host, from the compiled call's `Out`
    (NumPy arrays) and what `prepare` formed."""
    theta_flat, X0, e, cov, met = out.theta, out.x0, out.residuals, out.covariance, out.metrics
    best = int(out.best)
    layout, names = prepared.layout, prepared.names
    params = layout.one(theta_flat)
    free = problem.theta_free
    x0_free = problem.x0_free
    flat_std = np.zeros(theta_flat.shape, theta_flat.dtype)  # (the data's dtype, float32 too)
    x0_std = np.zeros(X0.shape, X0.dtype)
    theta_null = False  # (theta's columns rank deficient where the fit stopped)
    if cov is None:  # not computed (a large theta): no (p, p) matrix, unknown (inf) errors
        if (diagnostics or {}).get("covariance") == NOT_COMPUTED:  # asked for none
            why = None
        elif len(free) > COVARIANCE_MAX_THETA:
            why = f"above {COVARIANCE_MAX_THETA} free entries of theta ({len(free)} here)"
        else:
            size = dense_jacobian_bytes(problem, len(free) + len(x0_free))
            why = (
                f"where its dense Jacobian would exceed {DENSE_JACOBIAN_BYTES / 2**30:.3g} "
                f"GiB ({size / 2**30:.3g} GiB here: a long record with many parameters; "
                "fit a part of the record for standard errors)"
            )
        if why is not None:
            warn(
                f"the covariance of the estimates is not computed {why}: std and x0_std are "
                "inf (unknown).",
                stacklevel=3,
            )
        theta_cov = np.zeros((0, 0))
        flat_std[list(free)] = np.inf
        x0_std[:, list(x0_free)] = np.inf
        x0_cov = np.full((X0.shape[0], len(x0_free), len(x0_free)), np.inf)
    else:
        scaled = cov  # sigma^2 (J^T J)^+ and its standard errors (`scale`, in the solve)
        theta_null = not np.all(np.asarray(scaled.theta_identifiable))
        # (After a diverged simulation the linearisation says nothing of identifiability:
        # the stop reason speaks.)
        stop = name_of(from_index(int(out.results[best])))
        diverged = stop == "diverged"
        unconverged = int((diagnostics or {}).get("unconverged_rollouts", 0))
        worst = worst_fit(met.get("fit_percent"), problem.cost.weight, e)
        shrunk = "regularised" if problem.regulariser is not None else None
        if shrunk is None and problem.cost.penalty is not None:
            shrunk = "penalised"
        if shrunk is not None:
            worst = None  # (their optimum may fit worse than the mean, as `fit` says)
        low = below_float64(problem.dtype)
        gone = np.broadcast_to(np.asarray(out.vanished)[best], (len(free),))
        gone = [n for n, g in zip(names, gone) if g]
        if not diverged:
            _warn_identifiability(
                names,
                scaled.theta_identifiable,
                "parameters",
                stop,
                unconverged,
                worst,
                low,
                shrunk,
                gone,
            )
        if not diverged and not scaled.x0_identifiable.all():
            n_traj, n_x = X0.shape
            labels = model_labels(getattr(problem.model, "states", None), n_x) or range(n_x)
            x0_names = [
                f"x0[{i}, {labels[j]}]" if data.batched else f"x0[{labels[j]}]"
                for i in range(n_traj)
                for j in problem.x0_free
            ]
            _warn_identifiability(
                x0_names,
                scaled.x0_identifiable.reshape(-1),
                "initial states",
                stop,
                unconverged,
                worst,
                low,
                shrunk,
            )
        dof, n_free = int(scaled.dof), scaled.theta_std.size + scaled.x0_std.size
        if problem.x0_held is not None:
            n_free -= int(np.sum(problem.x0_held))
        if not diverged and dof <= 0 and n_free:
            diagnostics = {**(diagnostics or {}), "degrees_of_freedom": dof}
            warn(
                f"no more measured output values ({n_free + dof}) than estimated entries "
                f"({n_free}): the noise variance sigma^2 = SSE / (n_obs - n_free) is "
                "unknown, so every std is inf, whether or not the data determine the "
                "estimates. Use a longer record, or estimate fewer entries.",
                stacklevel=3,
            )
        theta_cov = scaled.theta
        if len(free) == flat_std.size:  # every entry free: no scatter
            flat_std = scaled.theta_std
        elif free:
            flat_std[list(free)] = scaled.theta_std
        if len(x0_free) == x0_std.shape[1]:
            x0_std = scaled.x0_std
        elif x0_free:
            x0_std[:, list(x0_free)] = scaled.x0_std
        x0_cov = scaled.x0
    std = layout.one(flat_std)

    results, losses = out.results, out.losses
    starts = None
    if multistart:
        rows = np.broadcast_to(np.asarray(problem.theta_base), (losses.shape[0], theta_flat.size))
        rows = rows.copy()
        rows[:, list(free)] = out.start_theta
        stops = tuple(name_of(from_index(int(c))) for c in results)
        own = (name_of(from_index(int(c))) for c in np.asarray(out.solver_results))
        # (each start's x0 as `FitResult.x0`: the held entries with the free ones set)
        base = np.asarray(problem.x0_base)
        start_x0 = np.broadcast_to(base, (losses.shape[0], *base.shape)).copy()
        start_x0[..., list(problem.x0_free)] = np.asarray(out.start_x0)
        starts = Starts(
            theta=layout.rows(rows),
            loss=losses,
            x0=start_x0 if data.batched else start_x0[:, 0],
            stop_reason=stops,
            solver_stop=tuple(o if r == "validation" else r for r, o in zip(stops, own)),
            validation_loss=None
            if out.validation_loss is None
            else np.asarray(out.validation_loss),
        )
    metrics = {k: (float(v) if k in _metrics._CRITERIA else v) for k, v in met.items()}
    stop_info = {
        "first_order": float(out.first_order),
        "gtol": prepared.gtol,
        "step": float(out.step),
        "decrease": float(out.decrease),
        "standard_errors": float(out.standard_errors),
        "stol": prepared.stol,
        "at_step": int(out.stages[-1].num_steps),
        "roundoff_limit": prepared.roundoff_limit,
    }
    limit = float(out.limit)
    if (
        np.isfinite(limit)
        and limit > prepared.roundoff_limit * (1.0 + 1e-5)
        and not float(out.first_order) <= prepared.gtol
    ):
        # (`_optimality.stall_limit`: raised by the precision of outputs far above the
        # residuals, where the measure is above gtol, so that the limit decides; the
        # margin: the limit computed in float32 rounds 10 sqrt(eps) up by 2e-8 relative,
        # which flagged every float32 stall as this)
        stop_info.update(roundoff_limit=limit, outputs_precision=True)
    if np.isfinite(prepared.resolution):  # (a first-order solver's floor under gtol)
        stop_info["resolution"] = prepared.resolution
    if problem.lower is not None and free:  # entries the box holds (`FitResult.__str__`)
        p = np.asarray(theta_flat)[list(free)]
        lo, hi = np.asarray(problem.lower), np.asarray(problem.upper)
        at = ((p <= lo) & np.isfinite(lo)) | ((p >= hi) & np.isfinite(hi))
        if at.any():
            stop_info["at_bound"] = [n for n, a in zip(names, at) if a]
    if problem.x0_bounded and x0_free:  # x0 entries its box holds (`fit(x0_bounds=...)`)
        x = np.asarray(X0)[:, list(x0_free)]
        lo, hi = np.asarray(problem.x0_lower), np.asarray(problem.x0_upper)
        at = ((x <= lo) & np.isfinite(lo)) | ((x >= hi) & np.isfinite(hi))
        if problem.x0_held is not None:  # (held by `estimate_x0` per record, not a bound)
            at &= ~np.asarray(problem.x0_held)
        state = model_labels(getattr(problem.model, "states", None), X0.shape[1]) or range(
            X0.shape[1]
        )
        state = list(state)
        rows_at = [
            f"x0[{i}, {state[x0_free[j]]}]" if data.batched else f"x0[{state[x0_free[j]]}]"
            for i, j in zip(*np.nonzero(at))
        ]
        if rows_at:
            stop_info["at_bound"] = stop_info.get("at_bound", []) + rows_at
    status = name_of(from_index(int(results[best])))
    chosen = _chosen(out, status, best)  # (a validation stop's returned iterate, or None)
    last_solver = prepared.solver[-1] if prepared.solver else {}
    if status == "stalled" and last_solver.get("solver") == "LBFGS":
        # (its stall: two steps in a row whose line search found no decrease, the second
        # from a fresh memory; not a round-off test)
        stop_info["line_search_failed"] = True
    if bool(out.step_test):  # which of the stopping tests fired, with its tolerances
        stop_info.update(step_test=True, rtol=last_solver.get("rtol"), atol=last_solver.get("atol"))
    if status == "statistically_converged" and float(out.step) == 0.0:
        # (no step taken: a stall that the undamped step's size settled,
        # `AbstractLeastSquares._settled`; the statistical test of a step needs one)
        stop_info["settled"] = True
    if status == "max_steps_reached" and theta_null and prepared.stol > 0:
        # (the statistical test, for a theta with a null space, did not fire either: the
        # message gives the last step's size in standard errors next to stol)
        stop_info["theta_null_space"] = True
    if bool(out.degenerate[best]):  # (`_optimality.stall_test`: a degenerate minimum)
        stop_info["degenerate"] = True
    gone = np.broadcast_to(np.asarray(out.vanished)[best], (len(free),))
    if gone.any():  # (`_optimality.vanished_columns`)
        stop_info["vanished"] = [n for n, g in zip(names, gone) if g]
    if status == "max_steps_reached" and last_solver.get("solver") == "Adam":
        # (a gradient far below Adam's eps: the steps are lr |g| / eps, not lr)
        last = out.stages[-1]
        norm, eps = float(last.grad_norm[int(last.rows)]), last_solver.get("eps")
        if np.isfinite(norm) and isinstance(eps, float) and norm < 0.01 * eps:
            stop_info.update(grad_norm=norm, below_eps=eps)
    if status in ("tol_loss", "tol_grad"):
        last = out.stages[-1]
        stop_info[status] = last_solver.get(status)
        stop_info["loss_at_stop"] = float(last.loss[int(last.rows)])
        stop_info["grad_norm"] = float(last.grad_norm[int(last.rows)])
    solver_stop = name_of(from_index(int(out.solver_results[best])))
    if status == "validation" and solver_stop != "validation":
        # (the solver's own stop, which the best-scoring iterate replaced: a divergence
        # must not vanish behind it)
        stop_info["solver_stop"] = solver_stop
    if "diverged" in (status, solver_stop):
        # Which was not finite where the solver stopped: the loss, or only its gradient
        # (a model not differentiable there, sqrt(c) at a bound c = 0, say). A loss
        # beyond sqrt(max) is a simulation that blows up: its gradient overflows first.
        last = out.stages[-1]
        C = last.loss[int(last.rows)]
        big = np.sqrt(np.finfo(np.asarray(C).dtype).max)
        stop_info["nonfinite"] = "gradient" if np.isfinite(C) and abs(C) < big else "loss"
        if np.isfinite(C) and abs(C) >= big:  # (finite, but its gradient overflows)
            stop_info["overflow"] = float(C)
    if status == "validation":  # the score that chose the point, and the patience
        stop_info["validation_loss"] = float(out.validation_loss[best])
        stop_info["patience"] = problem.validation.patience
        if chosen is not None:  # (a row of `FitResult.history`)
            stop_info.update(validation_stage=chosen[0], validation_step=chosen[1])
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
        history=_history(problem, out.stages, layout, chosen),
        residuals=e,
        names=names,
        fixed=prepared.fixed,
        covariance=theta_cov,
        std=std,
        x0_covariance=x0_cov,
        x0_std=x0_std,
        x0_estimated=prepared.x0_estimated,
        metrics=metrics,
        starts=starts,
        best=best,
        solver=prepared.solver,
        model=model,
        diagnostics=dict(diagnostics or {}),
        stop_info=stop_info,
        theta_order=prepared.theta_order,
        units=prepared.units,
        validation_loss=None if out.validation_loss is None else float(out.validation_loss[best]),
        window_starts=None if window_starts is None else np.asarray(window_starts),
        n_u=n_u,
    )
