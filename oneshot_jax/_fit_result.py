"""`FitResult`: what `fit` returns (cf. scipy's OptimizeResult and MATLAB's idnlgrey
reports), a pytree of data that prints as a parameter table; its `simulate`, `predict`
and `save` are thin calls of `oneshot_jax.simulate`, `oneshot_jax._initial_state` and
`oneshot_jax._io`, and `load_result` builds one from a saved file."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _io, _pytree
from ._ahead import estimate_process_noise, predict_ahead_impl
from ._caller_warnings import at_caller, frames_to_user, warn
from ._checks import as_float, check_data, check_state_size
from ._cost import Cost
from ._delta import delta_method
from ._fit_report import (
    report,
    returned_start,
    unresolved_remedy,
    vanished_note,
    without_effect_note,
)
from ._initial_state import predict_impl
from ._model import model_labels
from ._normalise import is_ragged
from ._operating_point import find_equilibrium, linearise
from ._output_std import output_std
from ._results import RESULTS, is_success, name_of
from ._simulate import simulate
from ._x0_smoother import reads_weight


def _g(x):
    return "?" if x is None else f"{x:.3g}"


def _pair(a, b) -> tuple[str, str]:
    """`a` and `b` as `_g` writes them, with more digits where those read the same (a
    loss just below `tol_loss` printed as "0.00247 < tol_loss 0.00247")."""
    x, y = _g(a), _g(b)
    digits = 3
    while x == y and a != b and digits < 17:
        digits += 1
        x, y = f"{a:.{digits}g}", f"{b:.{digits}g}"
    return x, y


def _statistical_unmet(info: dict) -> str:
    """The clause of a least-squares fit that took its max_steps at a point where theta's
    columns are rank deficient (`stop_info["theta_null_space"]`), where the statistical
    test (`RESULTS.statistically_converged`) could have stopped it: its last step's size
    in standard errors next to stol, or, where that size passed, that another of the
    test's conditions did not hold (empty where the test did not apply)."""
    se, stol = info.get("standard_errors", np.nan), info.get("stol", np.nan)
    if not info.get("theta_null_space") or not np.isfinite(se) or not stol > 0:
        return ""
    if se > stol:
        return (
            ", nor the statistical test of a theta with a null space (the last step "
            f"{_g(se)} standard errors > stol {_g(stol)})"
        )
    return (
        f", nor the statistical test of a theta with a null space (the last step {_g(se)} "
        f"standard errors <= stol {_g(stol)}, but not a step whose decrease the loss "
        "confirmed, with no parameter alone a standard error away and the undamped step "
        "within the confidence region)"
    )


def stop_detail(status: str, info: dict) -> str:
    """The test that fired and its values, in one line without a semicolon (empty where
    unknown): `FitResult.message` appends to it after one, and `print(result)` shows it up
    to there."""
    fo, gtol = info.get("first_order", np.nan), info.get("gtol", np.nan)
    step, decrease = info.get("step", np.nan), info.get("decrease", np.nan)
    at = info.get("at_step")
    known = np.isfinite(fo)
    fo_s, gtol_s = _pair(fo, gtol)
    vs = f"first-order measure {fo_s}" + (f" (gtol {gtol_s})" if np.isfinite(gtol) else "")
    tolerances = f"rtol {_g(info.get('rtol'))}, atol {_g(info.get('atol'))}"
    step_test = ""
    if info.get("step_test"):
        step_test = (
            f"the step test fired (step {_g(step)} relative to the scaled parameters, {tolerances})"
            if np.isfinite(step)
            # (A wrapped solver's own test, such as optimistix's on the step and the loss.)
            else f"the solver's own test on its step and loss fired ({tolerances})"
        )
    hidden = info.get("unresolved_outputs")
    if hidden and status in ("stalled", "max_steps_reached"):  # (`_fit._flag_hidden_outputs`)
        listed = ", ".join(hidden[:6]) + (f" and {len(hidden) - 6} more" if len(hidden) > 6 else "")
        ran_out = "took its max_steps" if status == "max_steps_reached" else "stalled"
        return (
            "the loss is at the round-off level of the outputs taken together, but output "
            f"{listed} is far from its own (a larger output's precision hid its misfit): "
            f"not a zero residual, and the solver {ran_out} with the {vs}"
        )
    if status == "converged" and known:
        degenerate = (
            ", with the Jacobian columns that vanished along the fit measured at the largest "
            "norm they had (a degenerate minimum, such as c at 0 for a term c**2 u)"
            if info.get("degenerate")
            else ""
        )
        if not fo > gtol:
            where = f", where {step_test}" if step_test else ""
            return f"first-order measure {fo_s} <= gtol {gtol_s}{degenerate}{where}"
        floor = info.get("resolution", np.nan)
        if gtol > 0 and fo <= floor:  # (False where NaN: a solver without that test)
            return (
                f"first-order measure {_g(fo)} <= {_g(floor)}, the resolution of the measure "
                f"in this precision (gtol {_g(gtol)} is below it)"
            )
        limit = info.get("roundoff_limit", np.nan)
        why = step_test or "no step decreases the loss at round-off"
        which = (
            "its round-off limit at the precision of the outputs, which are far above the residuals"
            if info.get("outputs_precision")
            else "its round-off limit"
        )
        return (
            f"first-order measure {_g(fo)} <= {_g(limit)}, {which} (gtol "
            f"{_g(gtol)}){degenerate}, where the fit stopped for lack of progress ({why})"
        )
    if status in ("tol_loss", "tol_grad"):
        what, value = (
            ("loss", info.get("loss_at_stop", np.nan))
            if status == "tol_loss"
            else ("gradient norm", info.get("grad_norm", np.nan))
        )
        shown, threshold = _pair(value, info.get(status, np.nan))
        out = f"{what} {shown} < {status} {threshold}"
        if known and fo > gtol:
            out += f", {vs} > gtol: not a stationary point"
        return out
    if status == "statistically_converged":
        se, stol = info.get("standard_errors", np.nan), info.get("stol", np.nan)
        if info.get("settled") and info.get("solver_stop") == "stalled":
            return (
                "the solver stalled (no step lowers the loss at its round-off), and the "
                f"Newton step from here is {_g(se)} standard errors <= {_g(stol)}; {vs}"
            )
        if info.get("settled"):
            return (
                "no step lowers the loss at its round-off, and the undamped Gauss-Newton "
                f"step from here is {_g(se)} standard errors <= stol {_g(stol)}; {vs}"
            )
        return f"last step {_g(se)} standard errors <= stol {_g(stol)} (theta rank-deficient, {vs})"
    if status == "stalled":
        # (A first-order solver has no scaled step or linear model: NaN, not shown.)
        limit = info.get("roundoff_limit", np.nan)
        beyond = f" and > {_g(limit)}, its round-off limit" if np.isfinite(limit) else ""
        tail = vs + " > gtol" + beyond if known else "not stationary"
        if info.get("descends_along_vanished"):
            return (
                "the solver stopped at what read as a degenerate minimum, but a step along "
                f"the Jacobian columns that vanished along the fit still lowers the loss: {tail}"
            )
        if info.get("all_vanished"):
            return (
                "the solver reported statistically_converged, but the Jacobian columns of "
                "every parameter vanished along the fit: the parameters ran to where they no "
                "longer move the outputs (a limit, not a minimum; the data determine none of "
                "them there); a start nearer the data's, windows (`fit_continuation`) or "
                f"multistart find the basin ({tail})"
            )
        if "start_loss" in info:
            return (
                f"the solver reported {info.get('solver_stop', 'converged')} where Jacobian "
                "columns vanished along the fit, but the loss there is above the start's "
                f"({_g(info['start_loss'])}): a plateau reached by a step that switched a term "
                "off, not a minimum; a smaller step (learning rate), bounds or another start "
                "keep the term acting"
            )
        if info.get("regular_jacobian"):
            return (
                "the solver reported statistically_converged (theta rank-deficient in J^T "
                "J), but the Jacobian itself has full rank, theta's columns by themselves "
                "too, and its Gauss-Newton step moves the estimates by "
                f"{_g(info['gauss_newton_se'])} standard errors: {tail}"
            )
        if info.get("gauss_newton_refuted"):
            return (
                f"the solver reported {info.get('solver_stop', 'converged')}, but the "
                "Gauss-Newton step from the Jacobian itself (not from J^T J, which loses "
                f"half the digits of {info.get('precision', 'this precision')}) lowers the loss "
                f"and moves the estimates by {_g(info['gauss_newton_se'])} standard errors: "
                "the problem is too ill-conditioned for J^T J in this precision; "
                f"{unresolved_remedy(info.get('precision'))} ({vs})"
            )
        if info.get("newton_refuted"):
            return (
                "the solver stopped at its round-off limit, but the Newton step from here "
                f"moves the estimates by {_g(info['newton_se'])} standard errors (nearly "
                f"collinear parameters, which the first-order measure does not see): {tail}"
            )
        if info.get("solver_stop") == "statistically_converged" and "newton_se" in info:
            gn = _g(info.get("standard_errors", np.nan))
            if not np.isfinite(info["newton_se"]):
                return (
                    "no step lowers the loss at its round-off, and the undamped "
                    f"Gauss-Newton step from here is {gn} standard errors, but the loss's "
                    "Hessian there is not positive definite (a saddle or a flat direction: "
                    f"no Newton step to measure): not settled, {tail}"
                )
            return (
                "no step lowers the loss at its round-off, and the undamped Gauss-Newton "
                f"step from here is {gn} standard errors, but the Newton step with the "
                f"residuals' curvature is {_g(info['newton_se'])} (a large misfit whose "
                f"curvature cancels part of J^T J): not settled, {tail}"
            )
        if info.get("unmeasured_claim"):
            return (
                "the solver reported converged without a first-order measure of its own; "
                f"measured at the returned point: {tail}"
            )
        if info.get("descends_from_zero_residual"):
            return (
                "the solver stopped with the loss below the round-off level of the data (a "
                f"zero residual), but a step still lowers the loss beyond round-off: {tail}"
            )
        if info.get("line_search_failed"):
            return (
                "the line search found no step that lowers the loss, twice in a row (the "
                f"second from a fresh quasi-Newton memory): stalled, {tail}"
            )
        if step_test:
            return f"{step_test}: stalled, {tail}"
        if np.isfinite(step) and np.isfinite(decrease):
            return (
                f"step {_g(step)} (scaled) with predicted decrease {_g(decrease)}: stalled, {tail}"
            )
        return f"no step decreases the loss, {tail}"
    if status == "zero_residual":
        nrmse = info.get("residual_nrmse", np.nan)
        rms = (
            f" (residual RMS at most {_g(nrmse)} of each output's standard deviation)"
            if np.isfinite(nrmse)
            else ""
        )
        return "loss at the round-off level of the data" + rms + (f", {vs}" if known else "")
    if status == "diverged":
        at_step = f" at step {at}" if at is not None else ""
        if info.get("nonfinite") == "gradient":
            return (
                f"the loss stayed finite but its gradient did not{at_step}: the gradient "
                "overflowed (a simulation growing without bound: keep the parameters where "
                "the model is stable, e.g. with bounds) or the model is not differentiable "
                "there (a parameter at a bound where it is not, such as sqrt(c) at c = 0: "
                "keep it off that point, e.g. with constraints.positive())"
            )
        big = info.get("overflow")
        if big is not None:  # (a finite loss beyond sqrt of the largest float)
            if at == 0:
                where, cause = "at the start", "the simulation from theta0 and x0 blows up"
                remedy = "start where the model is stable, e.g. with bounds, or in windows"
            else:
                where, cause = at_step.strip(), "a step took the simulation where it blows up"
                remedy = (
                    "keep the parameters where the model is stable, e.g. with bounds, or take "
                    "shorter steps"
                )
            return (
                f"the loss {where}, {_g(big)}, is finite but beyond the square root of the "
                f"largest float, where its gradient overflows: {cause} ({remedy})"
            )
        if at == 0:
            return (
                "the loss at the start is not finite: the simulation from theta0 and x0 "
                "blows up or gives NaN, or a penalty does there (start where the model is "
                "stable, e.g. with bounds, or in windows)"
            )
        return "the loss became non-finite" + at_step
    if status == "zero_gradient" and info.get("no_effect"):
        return (
            "no estimated parameter or initial state moved from the start, where the "
            "gradient of every one of them is exactly zero: the outputs do not change with "
            "any of them there (piecewise-constant outputs, from a `jnp.round`, an integer "
            "cast or a comparison in the model, have no derivative for any solver) (the "
            f"solver stopped with {info.get('solver_stop', '?')})"
        )
    if status == "zero_gradient":
        names = info.get("zero_gradient", [])
        listed = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10 else "")
        return (
            f"{listed} never moved from the start, where their gradient and Jacobian column "
            f"are exactly zero (the solver stopped with {info.get('solver_stop', '?')})"
        )
    if status == "noise_weight_unsettled":
        rounds = info.get("noise_weight_rounds", "?")
        return (
            f"the output weight did not settle in {rounds} fits (the last one stopped with "
            f"{info.get('solver_stop', '?')})"
        )
    if status == "unconverged_rollout":
        return (
            f"{info.get('unconverged_rollouts', '?')} of {info.get('parallel_rollouts', '?')} "
            "parallel rollouts kept Newton's unconverged iterate (the solver stopped with "
            f"{info.get('solver_stop', '?')})"
            + (
                ""
                if info.get("model_loss") is None
                else f"; the model's loss there, simulated sequentially, is "
                f"{_g(info['model_loss'])}, where `loss` is the rollouts'"
            )
        )
    if status == "infeasible":
        return (
            f"the estimate lies outside the constraint set: the projection moves it by "
            f"{_g(info.get('infeasible'))} (the solver stopped with "
            f"{info.get('solver_stop', '?')})"
        )
    if status == "validation":
        patience = info.get("patience")
        solver = info.get("solver_stop")
        return (
            f"lowest validation loss {_g(info.get('validation_loss'))}"
            + (f" (patience {patience})" if patience is not None else "")
            + (f", the solver itself stopped with {solver}" if solver else "")
        )
    if status in ("max_steps_reached", "no_progress") and known:
        eps = info.get("below_eps")
        small = (
            f", with the gradient's norm {_g(info.get('grad_norm'))} far below Adam's eps "
            f"{_g(eps)}, whose steps are then lr |g| / eps rather than lr: lower eps "
            "(`Adam(eps=...)`) below the gradient's scale"
            if eps is not None
            else ""
        )
        if not fo > gtol:
            return f"{vs} met, after the solver failed"
        return f"{vs} not met{small}{_statistical_unmet(info)}"
    return ""


class FitHistory(eqx.Module):
    """The recorded iterates of a fit (bounded: see `fit(history=...)`; a long run is
    thinned evenly, each solver's final iterate kept). Where the starts of a multistart run
    side by side (on an accelerator) they share one stride, that of the start with the most
    steps: the returned start can keep fewer rows than a single fit from it would.

    **Fields:**

    - `loss`, `grad_norm`: the objective (C, or C + g with a regulariser) and ||grad C||
        at each recorded step (NaN where a solver has no gradient at hand).
    - `theta`: the iterates, theta's parameter pytree with a leading axis of rows.
    - `step`: the step each row was recorded at, counted from the start of its stage.
    - `stage`: which solver of a sequence the row belongs to (0 for a single solver).
    - `validation`: with `fit(validation=...)`, the validation loss of each row, else
        None. Where a `validation` stop returns an earlier iterate, that iterate is a row
        (`stop_info["validation_stage"]` and `["validation_step"]` give its `stage` and
        `step`), put back where thinning left it out, with `grad_norm` NaN.
    """

    loss: np.ndarray
    grad_norm: np.ndarray
    theta: Any
    step: np.ndarray
    stage: np.ndarray
    validation: np.ndarray | None = None

    def __len__(self):
        return int(np.shape(self.loss)[0])


class Starts(eqx.Module):
    """Per-start outcomes of a multistart fit.

    **Fields:**

    - `theta`: theta's parameter pytree with a leading axis of starts.
    - `loss`: the final loss of each start.
    - `x0`: the initial state each start ended at, with a leading axis of starts (the
        shape of `FitResult.x0` after it): `oj.loss(model, result.start_theta(s),
        x0[s], u, z)` gives its `loss` (`FitResult.start_theta`: the row of `theta` with
        theta's parts that are not parameters, which `theta` leaves out). None in a file
        saved before it was kept.
    - `stop_reason`: the `RESULTS` name of each start's stop (a tuple of strings).
    - `solver_stop`: each start's own solver stop, the same as `stop_reason` except where
        a check after the solver replaced it (`validation`: the best-scoring iterate kept;
        `unconverged_rollout`; `zero_gradient`; `infeasible`; `stalled` where a step still
        lowers the loss from a degenerate minimum or a zero residual, each start checked):
        there the solver's stop (`diverged`, `converged`, ...), as
        `stop_info["solver_stop"]` for the returned start.
    - `validation_loss`: with `fit(validation=...)`, the validation loss of each start's
        returned point, which chose the returned start (the lowest; by the loss where no
        start has a finite score); else None.

    With `fit(weight="noise")` these are the starts of its first fit (Q = I); the later
    fits refine the best start only.
    """

    theta: Any
    loss: np.ndarray
    stop_reason: tuple = eqx.field(static=True)
    solver_stop: tuple = eqx.field(static=True)
    x0: np.ndarray | None = None
    validation_loss: np.ndarray | None = None


def _first_row_missing(z_head) -> bool:
    """Whether the first row of a record's head (n, n_z) has a NaN (False where it is not
    a numeric array: `predict` names that)."""
    try:
        first = np.asarray(z_head, dtype=float)[:1]
    except (TypeError, ValueError):
        return False
    return first.ndim == 2 and bool(np.isnan(first).any())


def _ndim(a) -> int:
    """np.ndim(a), or -1 for a list that is no array (arrays of different shapes)."""
    try:
        return np.ndim(a)
    except ValueError:
        return -1


def _several(u) -> bool:
    """Whether `u` holds several records: (N, T, n_u), or a list of N arrays (of different
    lengths or shapes: each record's own checks name what is wrong with it)."""
    if is_ragged(u):
        return True
    n = _ndim(u)
    return n == 3 or (n == -1 and isinstance(u, (list, tuple)))


def is_fitted_record(result, zhat, z) -> bool:
    """Whether z is the record `result` was fitted on, zhat the result's simulation of it
    from its fitted x0: zhat - residuals is that record's z (to 1e-5 of z's largest
    magnitude, whatever its units, and the round-off of zhat; after a `window=`
    fit, over its window at sample 0; a shorter z, the head of the fitted record). True
    where there is no one record to tell (a fit on several records)."""
    zhat, z = np.asarray(zhat), np.asarray(z)
    e = np.asarray(result.residuals)
    starts = result.window_starts
    if starts is not None:  # a `window=` fit, simulated from its window at sample 0
        first = e[int(np.flatnonzero(np.asarray(starts) == 0)[0])]
        e, zhat, z = first, zhat[: first.shape[0]], z[: first.shape[0]]
    elif np.ndim(result.x0) != 1:  # several records: no one record to tell
        return True
    if e.ndim == z.ndim and z.shape[0] < e.shape[0]:  # (the head of the fitted record)
        e = e[: z.shape[0]]
    if e.shape != z.shape:
        return False
    fitted = zhat.reshape(z.shape) - e
    both = np.isfinite(fitted) & np.isfinite(z)
    # (in z's units: a floor at 1 took any other record of outputs of order 1e-6 for it)
    scale = float(np.nanmax(np.abs(z[both]))) if both.any() else 0.0
    # zhat - e cancels: its round-off is that of zhat (huge after a fit that blew up).
    eps = np.finfo(np.result_type(zhat.dtype, e.dtype, np.float32)).eps
    big = float(np.nanmax(np.abs(zhat))) if np.isfinite(zhat).any() else 0.0
    return bool(
        both.any()
        and np.allclose(fitted[both], z[both], rtol=1e-5, atol=1e-5 * scale + 64 * eps * big)
    )


def _x0_prior(estimate):
    """The prior covariance of the filter of `predict_ahead` whose mean is the x0
    estimated from the record (`X0Estimate`): that estimate's covariance, where it is
    finite and positive definite (every entry determined by the record); else None (the
    filter's broad default)."""
    P = np.asarray(estimate.covariance, np.float64)
    if P.ndim != 2 or not np.all(np.isfinite(P)) or not np.all(estimate.identifiable):
        return None
    P = 0.5 * (P + P.T)
    return P if np.min(np.linalg.eigvalsh(P)) > 1e-12 * max(np.max(np.abs(P)), 1e-300) else None


def _split_records(u, z, t, z_name, what, length):
    """Several records' inputs `u` ((N, T, n_u) or a list of N arrays), their outputs
    `z` (one per record, (N, ., n_z) or a list; `what` names one, `length` its sample
    count; None: no outputs) and `t` (None, one (T,) shared, or one per record), as
    three lists of N."""
    records = list(u)
    N = len(records)
    if N == 0:
        raise ValueError("`u` holds no records: give (N, T, n_u) or a list of N arrays, N >= 1.")
    try:
        zs = [None] * N if z is None else list(z)
    except TypeError:
        zs = None
    one = z is not None and zs is not None and not is_ragged(z) and _ndim(z) == 2
    if zs is None or len(zs) != N or one:
        shape = "" if zs is None or _ndim(z) < 0 or is_ragged(z) else f" of shape {np.shape(z)}"
        count = "." if not zs else f" ({len(zs)} given)."
        if one:  # (its rows are samples, not records)
            count = f", one {what} ({length}, n_z)."
        raise ValueError(
            f"`{z_name}` must hold one {what} per record of `u` ({N} records): shape "
            f"(N, {length}, n_z) or a list of N arrays ({length}, n_z), got "
            f"{type(z).__name__}{shape}{count}"
        )
    per_t = t is not None and (is_ragged(t) or _ndim(t) in (-1, 2))
    if per_t and len(t) != N:
        raise ValueError(
            f"`t` must hold the sample times of each of the {N} records, got {len(t)}."
        )
    return records, zs, list(t) if per_t else [t] * N


class FitResult(eqx.Module):
    """The estimate, why the solver stopped, its uncertainty and its fit to the data.

    `print(result)` reports it in the manner of MATLAB's nlgreyest: the solver, the stop
    (`status` and the test that fired), the loss, steps and wall time; the parameters in
    theta0's order with their units, standard errors and 95 % intervals (an equinox
    module, such as a neural residual, as one row with its number of weights; an integer
    of theta, which is data, with its value as "(data, not estimated)"); the initial
    states with their standard errors (the first trajectories of several); FIT% and RMSE
    per output, and the AIC and FPE (AICc and BIC are in `metrics`; pooled over the
    trajectories or windows of several,
    with the FIT% of each on a line of its own); where the residuals are not white by
    MATLAB's `resid` test (`metrics.residual_correlations`, lags 1..25), a line saying so
    with its numbers; last, what `fit` warned of about this fit, a line per warning
    (`warnings`).

    **Fields:**

    - `theta`: the estimated parameters, same pytree as `theta0` (a start of it for a
        multistart fit).
    - `x0`: the estimated initial state(s), shape (n_x,) or (N, n_x).
    - `loss`: the final objective at `theta`, `x0`: C of eq. (5)/(21), plus g(theta) when
        `fit(regulariser=...)` holds one from `oneshot_jax.sparsity`.
    - `stop_reason`: a `RESULTS` item; `message` says why in words, `success` whether it
        converged.
    - `num_steps`: the solver steps taken (all solvers of a sequence together; with
        `weight="noise"`, all its fits together).
    - `wall_time`: seconds of the compiled solve with its covariance and metrics and of
        the checks of its result after it (a Newton step, say: compilation included on the
        first call of a configuration), without the input checks, the setup (with
        `window`, the windows' starting states), the check that the estimate lies in a
        `project` set and the assembly of the `FitResult`; with `weight="noise"`, of all
        its fits.
    - `history`: a `FitHistory` of the iterates.
    - `residuals`: e = zhat - z, the shape of `z`; (n_windows, window, n_z) for a fit
        with `window=` (each window simulated from its own fitted x0); (N, T_max, n_z)
        for records of different lengths, NaN past each record's end.
    - `names`: a name per free parameter (`"k"`, `"I[2]"`, `"net.layers.0.weight[1, 3]"`).
    - `fixed`: a flat boolean mask over theta's parameter entries (True where fixed).
    - `covariance`: sigma^2 (J^T J)^+ of the free parameters of theta, its rows and
        columns in the order of `names` (JAX's, dict keys sorted, which may differ from
        theta0's written order and the printout's; `std` holds the diagonal by name) (J
        the data-residual Jacobian in the weighted error, sigma^2 = SSE / (n_obs -
        n_free), n_obs the measured samples of the outputs of non-zero weight); inf in
        the rows and columns of a parameter the data do not determine. The least-squares
        solvers take J from their last linearisation, at the returned point or one
        converged step (of scaled size <= rtol) before it. Not computed above 1024 free
        entries of theta (a neural residual, say), nor where its dense Jacobian would
        exceed 1 GiB (N T (n_z + n_x) entries per free variable: a long record with
        hundreds of parameters): then an empty (0, 0) array, `std`,
        `x0_std` and `x0_covariance` are inf (unknown), and `fit` warns.
    - `std`: standard errors shaped like theta's parameters (0 where fixed).
    - `x0_covariance`: (m, m) or (N, m, m) covariance of the estimated x0 entries;
        `x0_std`: standard errors shaped like `x0` (0 where not estimated).
    - `x0_estimated`: (n_x,) boolean mask of the estimated x0 entries, or (N, n_x) where
        `fit` was given a mask per record (the entries a record holds then have a zero
        row and column in its block of `x0_covariance`, which spans the entries some
        record estimates).
    - `metrics`: RMSE, NRMSE, FIT% and R^2 per output, and AIC, AICc, BIC and FPE
        (`aic`, `aicc`, `bic`, `fpe` of `oneshot_jax.metrics`: MATLAB's report of a fit
        gives these), on the fitted data:
        pooled over all its records (each against the mean of all, which records at
        different operating points inflate), over the windows of a fit with `window=`
        (each from its own fitted x0, so not the model's open-loop fit of the whole
        record: `simulate` or `predict` that). `fit_percent_per_record` (N, n_z) is the
        FIT% of each record (window), as MATLAB's `compare` reports one per experiment
        (one row for one record). The criteria count the estimated x0 entries as
        parameters; they are computed on the samples where every output that is ever
        measured is measured (an output never measured is left out), and are NaN where
        there is no such sample (outputs sampled at different times); the FPE is inf
        where the parameters are as many as those samples, the AICc where they are one
        fewer.
    - `starts`: for a multistart fit, a `Starts`; `best` is the index of the returned one.
    - `solver`: the settings of the solver(s) that ran, as dicts.
    - `model`: the fitted `Model` (None for a result loaded without one).
    - `stop_info`: the values the stop was tested on, at the last solver's last iterate
        (the returned point, except after a validation stop, which returns the best
        iterate, and whose `first_order` is measured there after the solve):
        `first_order` (the scaled projected gradient, see
        `oneshot_jax._optimality`; a first-order solver scales it by the Jacobian's
        column norms, which it forms anew only where the measure may pass gtol or the
        fit stalls, so after another stop it is an estimate with older norms),
        `gtol` (the last solver's first-order tolerance), `step` (the last step's scaled
        size relative to the scaled parameters), `decrease` (the decrease of the loss its
        linear model predicted, relative to the loss), `standard_errors` and `stol` (the
        last step's size in standard errors and the tolerance of the statistical test,
        see `RESULTS.statistically_converged`; with `settled` (True) where the fit
        stalled and the size is that of the undamped Gauss-Newton step from the returned
        point, or of the Newton step (`newton_se`) with `solver_stop` "stalled" where a
        first-order solver's stall was settled after the solve; `newton_se`, the Newton
        step's size with the loss's own curvature, where a settled stall was checked with
        it after the solve: `stalled` with `solver_stop` "statistically_converged" where
        it is beyond stol, and with `newton_refuted` (True) and `solver_stop` "converged"
        where a first-order solver's success at its round-off limit was refuted by it;
        with `theta_null_space` (True) where a least-squares fit took its max_steps at a
        point where theta's columns are rank deficient, so that the statistical test
        applied and did not fire either, as its message says)
        and `at_step` (the last solver's
        step count); NaN where the solver has no such quantity. With the stop
        `zero_gradient`, also `zero_gradient` (the names of the parameters left at the
        start), `solver_stop` (the solver's own stop) and, where no parameter or initial
        state had a gradient there, `no_effect` (True); with a success that left some
        free parameters at their start, where their Jacobian columns are exactly zero there
        and a little away though not further away (a flat piece of the model: a
        saturation above the data's range, say), `without_effect` (their names); with
        the stop
        `noise_weight_unsettled`, `solver_stop` (the last fit's); with the stop `validation`,
        `validation_loss`, `patience` and, where the last solver stopped on a test of its
        own (`diverged`, `converged`, ...), `solver_stop`; with the stop `diverged`
        (or a `solver_stop` `diverged`),
        `nonfinite` ("loss", or "gradient" where the loss stayed finite, below sqrt of
        the largest float) and, where the loss is finite but above that, `overflow` (the
        loss); with the stop `stalled` where the solver converged at a degenerate
        minimum that a step along the vanished columns still descends from (checked
        after the solve), `descends_along_vanished` and `solver_stop` `converged`; with
        the stop `stalled` where the solver reported a zero residual that a step along
        every column still descends from (checked after the solve),
        `descends_from_zero_residual` and `solver_stop` `zero_residual`; with the stop
        `max_steps_reached` or `stalled` where the solver read a zero residual of the
        outputs together that some output, on its own, is far from,
        `unresolved_outputs` (their names) and `solver_stop` `zero_residual`; with the
        stop `stalled` of LBFGS, `line_search_failed` (True: two steps in a row without
        a decrease); with the stop
        `stalled` where the solver converged where columns vanished, at a loss above the
        best start's (a plateau), `start_loss` (that start's loss) and `solver_stop`;
        with the stop `stalled` where the solver reported statistically_converged after
        the columns of every free parameter vanished along the fit (a limit),
        `all_vanished` and `solver_stop`; with the stop `stalled` where a float32 (lower
        than float64) success, or a float64 one whose covariance calls some free entry
        not identifiable, is refuted by the Gauss-Newton step from the Jacobian itself
        (checked after the solve, `_optimality.gauss_newton_refutes`),
        `gauss_newton_refuted`, `gauss_newton_se` (that step's size in standard errors),
        `precision` and `solver_stop`; with the
        stop `stalled` where a float64 `statistically_converged` (not settled) had a
        Jacobian of full rank, theta's columns too by themselves, and a step from it of
        more than a standard error, `regular_jacobian` with `gauss_newton_se`,
        `precision` and `solver_stop`; after such
        a least-squares failure that the same step refutes along a direction that J^T J
        loses, `gauss_newton_se` and `precision` (the message says to fit in float64,
        or in float64 to reparameterise); with the stop
        `zero_residual`, `residual_nrmse` (the largest of the outputs' NRMSE in
        `metrics`, over the outputs of weight above 0: how far below sqrt(eps) of their
        variation the residuals are).
    - `theta_order`: the names of theta's rows (`"k"`, `"phys.c"`, a module `"r"`) in the
        order theta0 was written (JAX sorts dict keys); `print(result)` follows it.
    - `units`: `fit(units=...)`, a unit string per parameter name, shown by `print`.
    - `window_starts`: for a fit with `window=`, the first sample of each window (one
        per row of `x0`); else None.
    - `validation_loss`: with `fit(validation=...)`, the validation loss of the returned
        iterate (the lowest, or the solver's last iterate where it ties with the lowest:
        `Validation`); else None.
    - `weight`: `fit(weight=...)`, the output weight Q (None for the identity; with
        `weight="noise"`, the Q estimated from the residuals, and `stop_info` holds
        `noise_weight_rounds`, the number of fits, and with aggregated readings
        `reading_weight_factors`, the factor of each `Aggregate`'s weights), which
        `predict` uses by default to
        estimate a new record's x0.
    - `x0_bounds`: `fit(x0_bounds=...)`, the (lower, upper) bounds on x0 shaped like `x0`
        (-inf / inf where unbounded or held), or None; `predict` bounds a record's x0 by
        them by default where every record's are the same (a fit on one record, or
        bounds of shape (n_x,)).
    - `warnings`: the messages of the warnings `fit` raised about this fit (an integrator
        near its stability limit, outputs of unequal noise, a fit worse than the mean,
        ...), in the order raised, whatever the warning filters showed; `print(result)`
        lists them. Empty in a file saved before they were kept.
    - `missing`: `fit(missing=...)`: with `"mask"` (NaN in z marked missing samples),
        `predict` takes NaN in a new record's head as missing too (`"raise"` otherwise).
    - `diagnostics`: counts about how the fit was computed; with a parallel-in-time
        strategy, `parallel_rollouts`, `sequential_fallbacks` (rollouts that did not
        converge in parallel and were computed sequentially, with the same result) and
        `unconverged_rollouts` (with `ParallelInTime(fallback=False)`: rollouts that kept
        Newton's best iterate, not the model's states; `fit` warns);
        `degrees_of_freedom` where the fit had no more measured output values than
        estimated entries (n_obs - n_free <= 0: the noise variance, and with it every
        standard error, is unknown; `fit` warns); `regularised` (True) after a fit with a
        regulariser, whose covariance is that of the smooth loss C at the regularised
        estimate, without the regulariser (the printout says so); `aggregated` (True)
        after a fit with `aggregate=`, whose readings `residuals` does not hold.
    """

    theta: Any
    x0: np.ndarray
    loss: np.ndarray
    stop_reason: RESULTS
    num_steps: int
    wall_time: float
    history: FitHistory
    residuals: np.ndarray
    names: tuple = eqx.field(static=True)
    fixed: np.ndarray
    covariance: np.ndarray
    std: Any
    x0_covariance: np.ndarray
    x0_std: np.ndarray
    x0_estimated: np.ndarray
    metrics: dict
    starts: Starts | None
    best: int
    solver: tuple
    model: Any = None
    diagnostics: dict = eqx.field(default_factory=dict)
    stop_info: dict = eqx.field(default_factory=dict)
    theta_order: tuple = eqx.field(static=True, default=())
    units: dict = eqx.field(default_factory=dict)
    validation_loss: float | None = None
    window_starts: np.ndarray | None = None
    n_u: int | None = eqx.field(static=True, default=None)
    weight: np.ndarray | None = None
    x0_bounds: tuple | None = None
    missing: str = eqx.field(static=True, default="raise")
    warnings: tuple = ()
    # What a loaded file recorded of the fitted model (`load_result`), kept so that a
    # result loaded without `model=` and saved again keeps the check of `load_result(model=)`.
    saved_model_signature: tuple | None = eqx.field(static=True, default=None, repr=False)

    def _check_u(self, u, point=None):
        """Refuse inputs with another number of columns than the fitted data's (each
        record of a ragged list alike). `point`: for an operating point's constant input
        (n_u,), the state given with it (or True), whose hint is not a record's."""
        if isinstance(u, (list, tuple)) and not u:
            raise ValueError(
                "`u` is empty: give one record's inputs (T, n_u), or several records, "
                "(N, T, n_u) or a list of N arrays."
            )
        if self.n_u is None:
            return
        for record in list(u) if is_ragged(u) else [u]:
            try:
                shape = np.shape(record)
            except ValueError:  # a list that is no array: `simulate`'s checks name it
                continue
            if shape and shape[-1] != self.n_u and point is not None:
                swapped = point is not True and np.shape(point) == (self.n_u,)
                hint = " (are `x` and `u` swapped?)" if swapped else ""
                raise ValueError(
                    f"`u` must be the operating point's constant input, of n_u = {self.n_u} "
                    f"entries as the fitted data had; got shape {shape}{hint}."
                )
            if shape and shape[-1] != self.n_u:
                hint = (
                    " (is it transposed? u is (T, n_u))"
                    if len(shape) >= 2 and shape[-2] == self.n_u
                    else " (a record of T samples of one input is (T, 1): u[:, None])"
                    if len(shape) == 1 and self.n_u == 1
                    else ""
                )
                raise ValueError(
                    f"`u` must have n_u = {self.n_u} input columns, as the fitted data had; "
                    f"got shape {shape}{hint}."
                )

    def _rows(self) -> str:
        """What the rows of a multi-record (or windowed) fit's x0 are, for the messages
        of `simulate` and `predict`."""
        what = "window" if self.window_starts is not None else "trajectory (record)"
        return (
            f"this result holds {np.shape(self.x0)[0]} initial states, one per {what} of "
            f"the fit (`result.x0` of shape {np.shape(self.x0)})"
        )

    def _measurement_noise(self):
        """The measurement noise covariance the fit estimated, sigma^2 Q^{-1} (Q the fit's
        weight, I without one; sigma^2 from `_noise_variance`), or None where Q is
        singular or sigma^2 is not known (no degrees of freedom, or residuals exactly
        zero)."""
        q = self._weight_matrix()
        if not reads_weight(q):
            return None
        s2 = self._noise_variance()
        return s2 * np.linalg.inv(q) if np.isfinite(s2) and s2 > 0 else None

    def _weight_matrix(self):
        """The fit's Q as a matrix (I without one)."""
        n_z = np.shape(self.residuals)[-1]
        w = np.ones(n_z) if self.weight is None else np.asarray(self.weight, np.float64)
        return np.diag(w) if w.ndim == 1 else w

    def _noise_variance(self) -> float:
        """sigma^2 = SSE / dof of the fit's weighted residuals at the point samples, as its
        covariance scales (`_covariance.scale`), less an aggregated fit's readings, which
        `residuals` does not hold; inf without degrees of freedom."""
        e = np.asarray(self.residuals, np.float64)
        q = self._weight_matrix()
        e = e.reshape(-1, q.shape[0])
        seen = np.isfinite(e)
        estimated = np.asarray(self.x0_estimated, bool)  # (n_x,), or (N, n_x) per record
        x0_free = estimated.sum() * (
            1 if estimated.ndim == 2 else max(1, np.size(self.x0) // max(1, np.shape(self.x0)[-1]))
        )
        # (the observations as the covariance counts them: the measured entries of outputs
        # of nonzero weight, or the rank of a matrix Q over each sample's measured ones)
        weight = None if self.weight is None else jnp.asarray(self.weight)
        observations = Cost(weight, None, jnp.zeros(())).observations(jnp.asarray(seen))
        dof = int(observations) - int(np.sum(~np.asarray(self.fixed, bool))) - int(x0_free)
        e = np.where(seen, e, 0.0)
        return float(np.einsum("ki,ij,kj->", e, q, e)) / dof if dof > 0 else np.inf

    def _shared_x0_bounds(self):
        """The fit's x0 bounds as one (n_x,) pair, where every record's (or window's) are
        the same; else None."""
        lo, hi = (np.atleast_2d(np.asarray(b)) for b in self.x0_bounds)
        if np.all(lo == lo[0]) and np.all(hi == hi[0]):
            return lo[0], hi[0]
        return None

    def _check_z_head(self, z_head):
        """Refuse a head with another number of output columns than the fitted data's (for a
        model that observes its whole state, z_head[0] is x0's default guess, so a wrong
        count would otherwise surface as a wrong state size deep in the model)."""
        n_z = np.shape(self.residuals)[-1] if np.ndim(self.residuals) else None
        try:
            shape = np.shape(z_head)
        except ValueError:  # not an array: `predict`'s checks name it
            return
        if n_z is not None and len(shape) == 2 and shape[-1] != n_z:
            n, hint = shape[0], ""
            if shape[0] == n_z and shape[1] > n_z:  # (n_z, n) given: n samples as columns
                n, hint = shape[1], " (is it transposed? z_head is (n, n_z))"
            raise ValueError(
                f"`z_head` must have shape ({n}, {n_z}) (its first samples of the "
                f"n_z = {n_z} outputs the fitted data had), got shape {shape}{hint}."
            )

    @property
    def success(self) -> bool:
        """Whether the solver converged (`converged`, `statistically_converged`,
        `zero_residual`, `tol_loss` or `tol_grad`)."""
        return is_success(self.stop_reason)

    @property
    def message(self) -> str:
        """Why the solver stopped, in words: the test that fired with its values, then
        the reason's explanation (`RESULTS`)."""
        detail = stop_detail(self.status, self.stop_info)
        why = RESULTS[self.stop_reason]
        info = self.stop_info
        if "start_loss" in info:
            why = (
                "this is not a solution: the first-order test holds on the plateau (its "
                "gradient is 0), but the fit ended higher than it started"
            )
        elif info.get("regular_jacobian"):
            why = (
                "this is not a solution: the statistical test is for an over-parameterised "
                "theta (a null space of its columns), and nothing is over-parameterised "
                "here: a direction the data determine lost its rank in J^T J alone, its "
                "columns nearly collinear with the initial states' (an unstable model's "
                "sensitivities growing over long windows, say). Try another start, shorter "
                "windows, or bounds that keep the model stable"
            )
        elif info.get("line_search_failed"):
            why = (
                "this is not a solution: a line search that fails away from a stationary "
                "point most often meets free entries of very different scales, whose "
                "Jacobian columns differ by orders of magnitude (an output offset next to "
                "small gains, say); rescale them to order 1, or go on from here with "
                "LevenbergMarquardt, which scales the columns itself. A model that is "
                "not differentiable there (abs, sign, clip, a switching mode: a kink) "
                "fails a line search too"
            )
        elif info.get("gauss_newton_refuted"):
            why = (
                "this is not a solution: the solver's own test held in its normal "
                "equations, which cannot resolve this problem in this precision"
            )
        elif "gauss_newton_se" in info:  # (a least-squares failure, `_fit`)
            why = (
                "this is not a solution, and more steps will not reach one: the "
                "Gauss-Newton step from the Jacobian itself moves the estimates by "
                f"{_g(info['gauss_newton_se'])} standard errors along a direction that "
                f"J^T J loses in {info.get('precision', 'this precision')} (its eigenvalue "
                f"below the round-off cut); {unresolved_remedy(info.get('precision'))}"
            )
        if self.status == "diverged" and not np.isfinite(self.loss):  # (no finite iterate)
            finite = all(
                np.all(np.isfinite(np.asarray(a, np.float64)))
                for a in (*jax.tree_util.tree_leaves(_pytree.split(self.theta)[0]), self.x0)
            )
            kept = (  # (finite values whose loss overflows, or values that are not)
                "the returned point's loss is not finite (its values are finite; the solver "
                "did not keep its last iterate of finite loss)"
                if finite
                else "the returned point is not finite (the solver did not keep its last "
                "finite iterate)"
            )
            why = why.replace(
                "the last finite iterate is returned",
                "the start is returned" if returned_start(self) else kept,
            )
        out = f"{detail}; {why}" if detail else why
        gone = self.stop_info.get("vanished")
        if gone:
            out += f". {vanished_note(gone)}"
        idle = self.stop_info.get("without_effect")
        if idle:
            out += f". {without_effect_note(idle)}"
        kept = (self.diagnostics or {}).get("unconverged_rollouts")
        if kept and not self.success and self.status != "unconverged_rollout":
            # (the stop's values may be the rollouts': the likelier cause of the failure)
            out += (
                f". {kept} of {self.diagnostics.get('parallel_rollouts', '?')} parallel "
                "rollouts kept Newton's unconverged iterate (`ParallelInTime(fallback=False)`):"
                " the loss the solver saw may not be the model's; fit with `fallback=True` or "
                "a sequential strategy"
            )
        return out

    @property
    def status(self) -> str:
        """The name of the stop reason (`"converged"`, `"max_steps_reached"`, ...)."""
        return name_of(self.stop_reason)

    @property
    def correlation(self) -> np.ndarray:
        """The correlation matrix of theta's free entries, C_ij / sqrt(C_ii C_jj) of
        `covariance` (rows and columns in the order of `names`): entries near +-1 mark
        parameters the data determine only together (MATLAB users read it from
        `getcov`). NaN in the rows and columns of a parameter whose std is inf or 0; an
        empty (0, 0) array where the covariance was not computed."""
        cov = np.asarray(self.covariance, np.float64)
        if cov.size == 0:
            return np.zeros((0, 0))
        d = np.sqrt(np.diag(cov))
        known = np.isfinite(d) & (d > 0)
        out = np.full(cov.shape, np.nan)
        k = np.flatnonzero(known)
        out[np.ix_(k, k)] = cov[np.ix_(k, k)] / np.outer(d[k], d[k])
        out[k, k] = 1.0
        return out

    @property
    def ci95(self):
        """95 % intervals theta -+ 1.96 std, as two pytrees (lower, upper) of NumPy arrays
        shaped like theta's parameters, as `std` (0-d for a scalar, not np.float64): the
        large-sample (normal) interval; on a record of a few tens of samples, where
        sigma^2's estimate varies, the t quantile of n_obs - n_free degrees of freedom
        gives a wider one that holds 95 % there."""
        params, _ = _pytree.split(self.theta)
        lo = jax.tree_util.tree_map(
            lambda v, s: np.asarray(np.asarray(v) - 1.96 * s), params, self.std
        )
        hi = jax.tree_util.tree_map(
            lambda v, s: np.asarray(np.asarray(v) + 1.96 * s), params, self.std
        )
        return lo, hi

    def start_theta(self, s):
        """The whole theta that start `s` of a multistart fit ended at: its row of
        `starts.theta` (the parameters) with the parts of theta that are not parameters
        (an equinox module's activation, an integer leaf held as data) as in `theta`, so
        that `oj.loss(result.model, result.start_theta(s), result.starts.x0[s], u, z)`
        gives `starts.loss[s]`.

        **Arguments:** `s`, the index of the start (an int, negative from the end).

        **Returns:** theta's pytree.
        """
        if self.starts is None:
            raise ValueError("`start_theta`: this result is not of a multistart fit (no `starts`).")
        n = int(np.shape(self.starts.loss)[0])
        if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)):
            raise TypeError(f"`s` must be the index of a start (an int), got {type(s).__name__}.")
        if not -n <= s < n:
            raise ValueError(f"`s` must be the index of one of the {n} starts, got {s}.")
        row = jax.tree_util.tree_map(lambda a: np.asarray(a)[s], self.starts.theta)
        return _pytree.combine(row, _pytree.split(self.theta)[1])

    def simulate(self, u, x0=None, *, t=None):
        """Simulate the fitted model on inputs `u` (T, n_u) (or (N, T, n_u)), from `x0`,
        at the sample times `t` for a model of time-stamped records.

        By default `x0` is the fitted initial state, which needs the shape of the fitted
        data: after a fit on N records, N records of `u` (for record i alone, pass
        `x0=result.x0[i]`); after a fit with `window=`, it is the state of the window
        that starts at sample 0 (the record's initial state, for a simulation of the whole
        record), and a ValueError says so where no window starts there.

        **Returns:**

        `(x, z)` as `oneshot_jax.simulate`.
        """
        self._model_or_raise("simulate")
        self._check_u(u)
        if x0 is not None and np.ndim(self.x0):
            check_state_size(x0, np.shape(self.x0)[-1])
        if x0 is None:
            x0 = self.x0
            if self.window_starts is not None and np.ndim(u) == 2:
                at_zero = np.flatnonzero(np.asarray(self.window_starts) == 0)
                if not at_zero.size:
                    starts = [int(s) for s in np.asarray(self.window_starts)]
                    shown = f"{starts[:5]}"[:-1] + (", ...]" if len(starts) > 5 else "]")
                    raise ValueError(
                        f"this fit's windows start at samples {shown}, none at 0: give `x0` "
                        "(a row of `result.x0` is the state at `result.window_starts` of "
                        "that row), or use `result.predict(u, z_head)`, which estimates it."
                    )
                x0 = np.asarray(self.x0)[at_zero[0]]
            if np.ndim(x0) == 2:
                n_rec = len(u) if is_ragged(u) else np.shape(u)[0] if np.ndim(u) == 3 else None
                if n_rec != np.shape(x0)[0]:
                    held = "one record" if n_rec in (None, 1) else f"{n_rec} records"
                    raise ValueError(
                        f"{self._rows()}, and `u` holds {held}: pass `x0=result.x0[i]` to "
                        "simulate from the fitted initial state of record i (or an x0 of "
                        "your own), or u of all the records, shape "
                        f"({np.shape(x0)[0]}, T, n_u)."
                    )
        return simulate(self.model, self.theta, x0, u, t=t)

    def predict(self, u, z_head, *horizon, t=None, **kwargs):
        """Predict a new record from its first measured outputs: estimate its x0 from
        `z_head` (the first n outputs, n = len(z_head)) and simulate the whole input `u`
        with the fitted model and theta (see `oneshot_jax.predict`).

        **Arguments:**

        - `u`: the new record's inputs (T, n_u); or several records, (N, T, n_u) or a
            list of N arrays (T_i, n_u).
        - `z_head`: its first n measured outputs (n, n_z); for several records, one head
            per record ((N, n, n_z) or a list).
        - `t`: the new record's sample times (T,), for a model of time-stamped records
            (for several records, one (T_i,) per record, or one shared).
        - keyword arguments: as for `oneshot_jax.estimate_x0` (`method="lsq"` or
            `"smoother"`, `x0=` the starting guess, `weight=` by default the fit's, ...).
            `missing=` is by default the fit's: after a fit with `missing="mask"`, NaN in
            `z_head` are missing samples. The smoother's measurement noise defaults to the
            one the fit estimated, sigma^2 Q^{-1} (Q the fit's weight, I without one;
            sigma^2 = SSE / dof of its weighted residuals at the point samples,
            `residuals`: as its standard errors use, less the readings of an aggregated
            fit): a weight's scale, which a fit ignores, does not change it. Where Q is
            singular (an output of weight 0) or the residuals are exactly zero,
            `estimate_x0`'s defaults apply (with a singular Q, the smoother's reads every
            output: pass `measurement_noise=` to trust one less).
            Where the model does not observe its whole state, or `z_head`'s first row has
            a missing (NaN) sample, the starting guess defaults to the fitted x0 (the mean
            over trajectories of a multi-trajectory fit): a typical state of the system.
            Every entry of x0 is estimated by default, also those the fit held
            (`fit(estimate_x0=mask)`: their values were those of the fitted records, not
            of a new one); `estimate=result.x0_estimated` holds them at their values in
            `x0=` (e.g. `x0=result.x0`, for a state known to be the same: a velocity 0
            at rest), as MATLAB's `findstates` holds a model's fixed initial states.
            `bounds=` defaults to the fit's `x0_bounds` where every record's are the same
            (as `findstates` keeps a model's bounds); `bounds=(None, None)` lifts them.

        **Returns:**

        A `oneshot_jax.Prediction(z, x, x0, estimate)`; score it with
        `oneshot_jax.metrics.benchmark_scores(z, prediction.z, n)`. For several records, a
        list of N `Prediction`s, each record predicted alone (as MATLAB's `predict` of
        multi-experiment data); `x0=` then takes one starting guess per record, (N, n_x)
        (`x0=result.x0` after a fit on the same N records), or one for all, (n_x,), and
        `estimate=` one mask per record, (N, n_x) (`result.x0_estimated` after a fit with
        a mask per record), or one for all.
        """
        if horizon:  # (MATLAB's predict(sys, data, K))
            raise TypeError(
                "`FitResult.predict` takes `u` and `z_head` only (a third argument was "
                "given): it simulates the whole record from an x0 estimated from the head. "
                "The K-step-ahead prediction of MATLAB's predict(sys, data, K) is "
                "`result.predict_ahead(u, z, K, process_noise=...)`."
            )
        self._model_or_raise("predict")
        self._check_u(u)
        if _several(u):
            return self._predict_records(u, z_head, t, kwargs)
        self._check_z_head(z_head)
        kwargs = dict(kwargs)
        given_x0 = kwargs.get("x0")
        if given_x0 is not None and np.ndim(self.x0):
            check_state_size(given_x0, np.shape(self.x0)[-1])
        if (
            given_x0 is not None
            and np.ndim(self.x0) == 2
            and np.shape(given_x0) == np.shape(self.x0)
        ):
            raise ValueError(
                f"`x0` (the starting guess of the record's initial state) must have shape "
                f"(n_x,); {self._rows()}: pass `x0=result.x0[i]` to start from that of "
                "record i."
            )
        method = kwargs.pop("method", "lsq")
        inherited = False
        if method == "lsq" and "bounds" not in kwargs and self.x0_bounds is not None:
            shared = self._shared_x0_bounds()
            if shared is not None:
                kwargs["bounds"] = shared  # the fit's box: a fitted record's x0 stays in it
                inherited = True
        if "missing" not in kwargs and self.missing == "mask":
            kwargs["missing"] = "mask"  # (the fit's NaN were missing samples: the head's too)
        noise = None
        given = kwargs.get("measurement_noise") is not None or kwargs.get("weight") is not None
        if method == "smoother" and not given:
            noise = self._measurement_noise()
        if noise is not None:  # Q's scale is arbitrary: the smoother gets sigma^2 Q^{-1}
            kwargs["measurement_noise"] = noise
        elif kwargs.get("weight") is None and self.weight is not None:
            if method != "smoother" or reads_weight(self.weight):
                kwargs["weight"] = self.weight  # the fit's Q: an output it ignored stays so
        if kwargs.get("x0") is None and (
            not self.model.observes_state or _first_row_missing(z_head)
        ):
            x0 = np.asarray(self.x0)
            kwargs["x0"] = x0 if x0.ndim == 1 else x0.mean(axis=0)
        level = 3 + frames_to_user()
        out = predict_impl(
            self.model, self.theta, u, z_head, None, method, kwargs, stacklevel=level, t=t,
            z_name="z_head",
        )  # fmt: skip
        if inherited:  # (a bound the caller did not give: say where it held an estimate)
            self._warn_at_fit_bounds(out, kwargs["bounds"], level)
        return out

    def _warn_at_fit_bounds(self, predictions, box, stacklevel):
        """Warn where a record's x0 estimate ended on the fit's `x0_bounds` (`box`), which
        `predict` applied by default: a new record can start outside the fitted one's box.
        (Also where the fit's own x0 is on that bound: the fitted record, predicted, starts
        there, but a new record that asks for a value beyond it cannot be told apart.)"""
        x0 = np.atleast_2d(np.asarray(self.x0))
        fitted = np.any((x0 == box[0]) | (x0 == box[1]), axis=0)
        several = isinstance(predictions, list)
        labels = model_labels(getattr(self.model, "states", None), np.shape(self.x0)[-1])
        names = labels or [str(j) for j in range(np.shape(self.x0)[-1])]
        hits = []
        for i, p in enumerate(predictions if several else [predictions]):
            edge = p.estimate.at_bound
            if edge is not None and edge.any():
                which = ", ".join(
                    f"x0[{names[j]}]" + (" (the fit's x0 is on it too)" if fitted[j] else "")
                    for j in np.flatnonzero(edge)
                )
                hits.append(f"{which} of record {i}" if several else which)
        if hits:
            warn(
                f"predict: the estimate of {'; '.join(hits)} ended on the fit's `x0_bounds`, "
                "which `predict` bounds a record's x0 by unless told otherwise: the head asks "
                "for a value beyond it. Where this record may start outside the fitted "
                "record's box, pass `bounds=(None, None)` (or bounds of its own).",
                stacklevel=stacklevel + 1,  # (`predict`'s level, from this method)
            )

    def predict_ahead(
        self,
        u,
        z,
        K,
        *,
        process_noise,
        x0=None,
        measurement_noise=None,
        prior_covariance=None,
        t=None,
        missing=None,
        parameters=False,
    ):
        """Predict each output of a record from the measurements up to K samples before
        it, with the fitted model and theta: an extended Kalman filter corrects the state
        from the outputs (`oneshot_jax.predict_ahead`; MATLAB's `predict(sys, data, K)`).

        **Arguments:**

        - `u`, `z`: one record's inputs (T, n_u) and measured outputs (T, n_z); or
            several records, (N, T, n_u) and (N, T, n_z), or lists of N arrays.
        - `K`: the horizon, an integer >= 1 (K >= T or `math.inf`: the simulation from
            `x0`).
        - `process_noise`: the covariance of the process noise per step, or the
            `ProcessNoise` of `estimate_process_noise` (required; the fit's
            output-error model has none).
        - `x0`: the prior mean of the initial state; default the record's x0 estimated
            from all of it as `predict(u, z)` does, by the smoother under the process
            noise given (`predict(u, z, method="smoother", process_noise=...)`; by least
            squares for a process noise of zero, or a `prior_covariance` given). For
            several records, one per record, (N, n_x), or one for all, (n_x,).
        - `measurement_noise`: default the one the fit estimated, sigma^2 Q^{-1} (as for
            `predict`'s smoother), else the defaults of `oneshot_jax.predict_ahead`.
        - `prior_covariance`: the covariance of the prior on x0; default, with the
            default `x0`, that estimate's covariance (the uncertainty of the mean the
            filter starts from, so the first K predictions' `std` is that of a simulation
            from it): the smoother's P[0 | T-1] under the process noise (the
            least-squares estimate's sigma^2 (J^T Q J)^{-1} takes the residuals as white,
            which the process noise makes them not, so it is too small and the first
            predictions' bands too narrow; the record's data, used again by the filter,
            make this one conservative there instead), or the broad default
            of `oneshot_jax.predict_ahead` where the record does not determine every entry
            of x0 or `x0` is given.
        - `t`: as for `oneshot_jax.predict_ahead` (for several records, one (T_i,) per
            record, or one shared).
        - `missing`: default the fit's (`"mask"`: NaN in z are missing measurements).
        - `parameters`: True adds theta's uncertainty to `std`: J Sigma J^T per sample,
            J = d zhat[k|k-K] / d theta by forward-mode differentiation through the filter
            and Sigma the fit's covariance (to first order, as `output_std`; inf where a
            prediction depends on a parameter of unknown std, such as a network's
            weights). Default False: the filter's noise model alone.

        **Returns:** an `AheadPrediction` (`z`, `x`, `filtered`, `K`, `std`); for several
        records, a list of N, each record filtered alone (as MATLAB's `predict` of
        multi-experiment data).
        """
        if not isinstance(parameters, (bool, np.bool_)):
            raise TypeError(f"`parameters` must be True or False, got {parameters!r}.")
        self._model_or_raise("predict_ahead")
        self._check_u(u)
        given = dict(
            process_noise=process_noise,
            measurement_noise=measurement_noise,
            prior_covariance=prior_covariance,
            missing=missing,
            parameters=parameters,
        )
        if _several(u):
            records, zs, times = _split_records(u, z, t, "z", "record's outputs", "T")
            N = len(records)
            if x0 is not None and np.ndim(x0) == 2 and np.shape(x0)[0] != N:
                raise ValueError(
                    f"`x0` (the prior means) must have shape (n_x,) or ({N}, n_x) (one per "
                    f"record of `u`), got shape {np.shape(x0)}."
                )
            rows = np.ndim(x0) == 2
            return [
                self.predict_ahead(
                    records[i], zs[i], K, x0=x0[i] if rows else x0, t=times[i], **given
                )
                for i in range(N)
            ]
        if np.ndim(u) != 2:
            raise ValueError(f"`u` must be one record's inputs (T, n_u), got shape {np.shape(u)}.")
        self._check_record_z(u, z, missing)
        # (the default x0 and its covariance under this process noise, where the prior's
        # covariance is the default: the smoother's x[0 | T-1])
        noise = process_noise if prior_covariance is None else None
        filter_args = self._filter_defaults(u, z, x0, measurement_noise, t, missing, noise)
        estimate = filter_args.pop("estimate")
        if prior_covariance is None and estimate is not None:
            prior_covariance = _x0_prior(estimate)
        return predict_ahead_impl(
            self.model,
            self.theta,
            u,
            z,
            K,
            filter_args["x0"],
            process_noise,
            filter_args["measurement_noise"],
            prior_covariance,
            filter_args["weight"],
            t,
            filter_args["missing"],
            parameters=(self.fixed, self.covariance) if parameters else None,
        )

    def _check_record_z(self, u, z, missing):
        """Refuse a record's measured outputs `z` for the filter that are not (T, n_z),
        T the samples of `u` and n_z the fitted data's, or hold NaN where `missing`
        (default the fit's) does not allow them (before the default x0's `predict(u, z)`,
        whose errors would name its `z_head`)."""
        T = np.shape(u)[0]
        if T == 0:
            raise ValueError(
                f"`u` must hold at least one sample (T >= 1), got shape {np.shape(u)}."
            )
        zs = np.asarray(as_float(z, "z", measured=True), np.float64)
        n_z = np.shape(self.residuals)[-1] if np.ndim(self.residuals) else None
        if zs.ndim != 2 or zs.shape[0] != T or (n_z is not None and zs.shape[1] != n_z):
            hint = " (is it transposed? z is (T, n_z))" if zs.shape[::-1] == (T, n_z) else ""
            raise ValueError(
                f"`z` must have shape ({T}, {'n_z' if n_z is None else n_z}) (the measured "
                f"outputs of the {T} samples of `u`), got shape {zs.shape}{hint}."
            )
        if np.isinf(zs).any():
            raise ValueError("`z` contains inf values.")
        if (self.missing if missing is None else missing) == "raise" and np.isnan(zs).any():
            raise ValueError(
                '`z` contains NaN values: pass missing="mask" to take them as missing samples.'
            )

    def _filter_defaults(self, u, z, x0, measurement_noise, t, missing, process_noise=None):
        """The filter's arguments of `predict_ahead` and `estimate_process_noise` with
        the fit's defaults: the record's x0 as `predict(u, z)` estimates it, the
        measurement noise the fit estimated (else its weight), its `missing`; and under
        `"estimate"` that x0's `X0Estimate` (None where `x0` is given). With a
        `process_noise` that is not zero, x0 is the smoother's under it (`predict(u, z,
        method="smoother", process_noise=...)`): the least-squares estimate assumes white
        residuals, and its covariance was 4 times too small in Mahalanobis terms on
        records with process noise (the first predictions' band held 72 % of the
        measurements at the 95 % level)."""
        missing = self.missing if missing is None else missing
        estimate = None
        if x0 is None:
            Qp = getattr(process_noise, "covariance", process_noise)
            if Qp is not None and np.any(np.asarray(Qp, np.float64) != 0):
                options = (
                    {"measurement_noise": measurement_noise}
                    if measurement_noise is not None
                    else {}
                )
                pred = self.predict(
                    u, z, t=t, missing=missing, method="smoother", process_noise=Qp, **options
                )
            else:
                pred = self.predict(u, z, t=t, missing=missing)
            x0, estimate = pred.x0, pred.estimate
        weight = None
        if measurement_noise is None:
            measurement_noise = self._measurement_noise()
            if measurement_noise is None and self.weight is not None:
                weight = self.weight if reads_weight(self.weight) else None
        return dict(
            x0=x0,
            measurement_noise=measurement_noise,
            weight=weight,
            missing=missing,
            estimate=estimate,
        )

    def estimate_process_noise(
        self,
        u,
        z,
        shape,
        *,
        x0=None,
        measurement_noise=None,
        prior_covariance=None,
        t=None,
        missing=None,
        scales=None,
    ):
        """The process noise covariance q `shape` that maximises the likelihood of a
        record's outputs under the extended Kalman filter of `predict_ahead`, with the
        fitted theta (`oneshot_jax.estimate_process_noise`), for `predict_ahead`'s
        `process_noise`.

        **Arguments:** one record's `u` (T, n_u) and `z` (T, n_z); `shape`, the
        covariance's shape (n_x): a scalar, a vector of variances or a matrix, in the
        states' units (the scale q is one for all its entries); the others with the
        defaults of `predict_ahead` (the record's x0 from `predict(u, z)` by least
        squares, the process noise being what is sought; the measurement noise the fit
        estimated, the fit's `missing`), except the prior
        covariance, broad by default (the likelihood's diffuse start), and `scales` as
        for `oneshot_jax.estimate_process_noise`.

        **Returns:** a `ProcessNoise` (`covariance`, `scale`, `log_likelihood`, ...).
        """
        self._model_or_raise("estimate_process_noise")
        self._check_u(u)
        if is_ragged(u) or _ndim(u) != 2:
            raise ValueError(f"`u` must be one record's inputs (T, n_u), got shape {np.shape(u)}.")
        self._check_record_z(u, z, missing)
        filter_args = self._filter_defaults(u, z, x0, measurement_noise, t, missing)
        filter_args.pop("estimate")
        with at_caller(__file__, frames_to_user()):  # (its warning at the caller's line)
            return estimate_process_noise(
                self.model,
                self.theta,
                u,
                z,
                shape,
                prior_covariance=prior_covariance,
                t=t,
                scales=scales,
                **filter_args,
            )

    def _predict_records(self, u, z_head, t, kwargs):
        """`predict` of several records (u (N, T, n_u) or a list of N records, z_head
        (N, n, n_z) or a list of N heads, `t` None, shared (T,) or one per record), each
        as one record; `x0=` of shape (N, n_x) (`result.x0` after a fit on N records)
        gives each its own starting guess. A list of N `Prediction`s (MATLAB's `predict`
        of multi-experiment data: one per experiment)."""
        records, heads, times = _split_records(u, z_head, t, "z_head", "head", "n")
        N = len(records)
        # (n_x,) for every record, or (N, n_x): a row per record (`x0=result.x0`, and
        # `estimate=result.x0_estimated` after a fit with a mask per record)
        rows = {}
        for key, what in (
            ("x0", "the starting guesses"),
            ("estimate", "the x0 entries to estimate"),
        ):
            value = kwargs.get(key)
            if value is None or np.ndim(value) != 2:
                continue
            if np.shape(value)[0] != N:
                raise ValueError(
                    f"`{key}` ({what}) must have shape (n_x,) or ({N}, n_x) (one per record "
                    f"of `u`), got shape {np.shape(value)}."
                )
            rows[key] = np.asarray(value)
        out = []
        for i in range(N):
            kw = dict(kwargs, **{key: value[i] for key, value in rows.items()})
            out.append(self.predict(records[i], heads[i], t=times[i], **kw))
        return out

    def find_equilibrium(self, u, x=None, *, hold=None, dt=None):
        """An equilibrium of the fitted model at the constant input `u` (MATLAB's
        `findop(sys, 'steady', u)`; `oneshot_jax.find_equilibrium` with the fitted
        theta).

        **Arguments:**

        - `u`: the constant input (n_u,), or a sweep of N inputs (N, n_u) (a list of N
            equilibria, each searched from the one before).
        - `x`: the start of the search (n_x,); default the fitted x0 (the mean over
            records or windows of a fit of several).
        - `hold`: an (n_x,) boolean mask of the entries of `x` held at their values.
        - `dt`: for a `Model(step, timed=True)`, the interval of the step (as
            `oneshot_jax.find_equilibrium`).

        **Returns:** an `Equilibrium` (`x`, `z`, `u`, `residual`, `success`, `steps`).
        """
        model = self._model_or_raise("find_equilibrium")
        self._check_u(u, point=True)
        if x is None:
            x0 = np.asarray(self.x0)
            x = x0 if x0.ndim == 1 else x0.mean(axis=0)
        elif np.ndim(self.x0):
            check_state_size(x, np.shape(self.x0)[-1], "`x`")
        return find_equilibrium(model, self.theta, u, x, hold=hold, dt=dt)

    def linearise(self, x, u, *, dt=None):
        """The linear model of the fitted model's deviations around (x, u) (MATLAB's
        `linearize(sys, u0, x0)`; `oneshot_jax.linearise` with the fitted theta), e.g.
        at `result.find_equilibrium(u).x`.

        **Returns:** a `LinearModel` (`A`, `B`, `C`, `D`; `Ac`, `Bc` for a model built
        from an ODE; `poles`).
        """
        model = self._model_or_raise("linearise")
        self._check_u(u, point=x)
        if np.ndim(self.x0):
            check_state_size(x, np.shape(self.x0)[-1], "`x`")
        return linearise(model, self.theta, x, u, dt=dt)

    def _model_or_raise(self, name=None):
        """The fitted model; a ValueError for a result loaded without one, naming the
        function `name` of the library that takes the model itself."""
        if self.model is None:
            raise ValueError(
                "this result holds no model (it was loaded without one): pass `model=` to "
                "`oneshot_jax.load_result`" + (f", or call `oneshot_jax.{name}`." if name else ".")
            )
        return self.model

    def delta_method(self, fn):
        """The value and standard errors of a quantity derived from the parameters,
        q = fn(theta): theta's covariance carried through fn to first order (the delta
        method, `oneshot_jax._delta`), e.g. a natural frequency, a time constant, the
        magnitude of a pole of the linearised model.

        **Arguments:**

        - `fn`: `fn(theta) -> q`, written in `jax.numpy` (it is differentiated in forward
            mode), returning real numbers (an array or a scalar); theta as `result.theta`
            (the fixed entries at their values, which add no uncertainty).

        **Returns:** a `Derived` (`value`, `std`, `covariance`, `ci95`); std inf where q
        depends on a parameter whose std is inf (not identifiable, a network's weights, or
        the covariance not computed).

        **Example:**

        ```python
        f0 = result.delta_method(lambda th: jnp.sqrt(th["w0sq"]) / (2 * jnp.pi))
        print(f0.value, f0.std)  # the natural frequency in Hz and its standard error
        ```
        """
        return delta_method(fn, self.theta, self.fixed, self.covariance)

    def sample_theta(self, n, *, seed=0):
        """n random draws of theta from the estimate's distribution, N(theta, covariance)
        over its free entries, the fixed ones at their values (MATLAB's `rsample`): for
        Monte Carlo studies of the parameters' uncertainty (MATLAB's `simsd`), to
        first order as `std`, and for starts of `fit(multistart=True)` around an estimate.

        **Arguments:**

        - `n`: the number of draws, an integer >= 1.
        - `seed`: the seed of NumPy's generator (`np.random.default_rng(seed)`): the same
            seed gives the same draws.

        **Returns:** theta's pytree with a leading axis n on every parameter leaf (the
        shape `fit(multistart=True)` takes as `theta0`); simulate the draws with
        `jax.vmap(lambda th: oneshot_jax.simulate(model, th, x0, u)[1])(draws)`.

        **Raises:** `ValueError` where the covariance is not known: not computed
        (`fit(covariance=None)`, too many parameters), or with an infinite standard error
        (a parameter the data do not determine, a network's weights); or for a bad `n`.
        The draws are Gaussian: they ignore constraints (a draw may leave a box).
        """
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"`n` (the number of draws) must be an integer >= 1, got {n!r}.")
        params, static = _pytree.split(self.theta)
        flat = _pytree.flat_host(params)
        free = np.flatnonzero(~np.asarray(self.fixed, bool))
        cov = np.asarray(self.covariance, np.float64)
        if flat.shape != np.shape(self.fixed) or cov.shape != (free.size, free.size):
            raise ValueError(
                "`sample_theta` needs the covariance of theta's free entries, which this "
                "result does not hold (not computed: `fit(covariance=None)`, or too many "
                "parameters)."
            )
        if not np.all(np.isfinite(cov)):
            unknown = [nm for nm, d in zip(self.names, np.diag(cov)) if not np.isfinite(d)]
            shown = ", ".join(unknown[:6]) + (" ..." if len(unknown) > 6 else "")
            raise ValueError(
                f"`sample_theta`: the standard errors of {shown} are inf (not determined by "
                "the data, or a network's weights): no distribution to draw from. Fix them "
                "(`fit(fixed=...)`) to draw the others."
            )
        try:
            rng = np.random.default_rng(seed)
        except (TypeError, ValueError):
            raise ValueError(
                "`seed` must be a non-negative integer (or a sequence of them, or a NumPy "
                f"Generator or SeedSequence; `np.random.default_rng(seed)`), got {seed!r}."
            ) from None
        rows = np.repeat(flat[None], int(n), axis=0)
        if free.size:  # (every entry fixed: n copies of theta)
            rows[:, free] = rng.multivariate_normal(flat[free], cov, size=int(n), method="eigh")
        drawn = _pytree.layout(params).rows(rows.astype(flat.dtype))
        return _pytree.ordered_like(_pytree.combine(drawn, static), self.theta)

    def output_std(self, u, x0=None, *, z_head=None, t=None):
        """The standard errors of the simulated outputs of one record that come from the
        estimate's uncertainty (MATLAB's `[y, ysd] = sim(...)`, the confidence region of
        `compare`): its covariance carried to the outputs to first order (the delta
        method, with the closed-form output sensitivities; `oneshot_jax._output_std`).

        **Arguments:**

        - `u`: the record's inputs (T, n_u); or several records, (N, T, n_u) or a list of
            N arrays (T_i, n_u), each taken alone.
        - `x0`: a known initial state (n_x,): the outputs `result.simulate(u, x0)`, their
            standard errors from theta's covariance alone (x0 exact). For several
            records, one per record, (N, n_x) (`x0=result.x0` on the fitted records), or
            one for all.
        - `z_head`: instead of `x0`, the record's first n measured outputs (n, n_z): the
            outputs `result.predict(u, z_head).z` (x0 estimated from the head at the
            fitted theta by least squares, with the fit's weight), their standard errors
            from theta's covariance, through the prediction and through the estimated x0,
            and from the head's noise (the fit's estimate of it, as for `std`). Every
            entry of x0 is estimated from the head (`predict`'s default). On the fitted
            record with `z_head=z` (all of it, MATLAB's default of `compare`) they are
            those of the joint covariance of theta and x0, for a fit that estimated
            every entry of x0. NaN in `z_head` are missing samples. For several records,
            one head per record ((N, n, n_z) or a list).
        - `t`: the record's sample times (T,), for a model of time-stamped records (for
            several records, one (T_i,) per record, or one shared).

        **Returns:**

        An array (T, n_z) (for several records (N, T, n_z), or a list of N (T_i, n_z)
        for a list of records): the standard deviation of each simulated output sample; inf
        where it is not known: the output depends on a parameter whose std is inf (not
        identifiable, or the covariance not computed, `fit(covariance=None)`; for a
        theta that holds a network, the network's weights) or on an entry of x0 the
        head does not determine. An interval zhat +- 1.96 std is the 95 % confidence
        interval of the model's output (the noise-free simulation), to first order and
        for a model structure that holds; a measurement adds its own noise.
        """
        self._model_or_raise()
        self._check_u(u)
        if (x0 is None) == (z_head is None):
            raise ValueError(
                "give one of `x0` (a known initial state, (n_x,)) and `z_head` (the "
                "record's first measured outputs, (n, n_z), x0 estimated from them as "
                "`predict` does; `z_head=z` on a fitted record), got "
                + ("both." if x0 is not None else "neither.")
            )
        if _several(u):
            N = len(u)
            if z_head is not None:
                records, heads, times = _split_records(u, z_head, t, "z_head", "head", "n")
                out = [self.output_std(records[i], z_head=heads[i], t=times[i]) for i in range(N)]
            else:
                records, _, times = _split_records(u, None, t, "z_head", "head", "n")
                if np.ndim(x0) == 2 and np.shape(x0)[0] != N:
                    raise ValueError(
                        f"`x0` must have shape (n_x,) or ({N}, n_x) (one per record of `u`), "
                        f"got shape {np.shape(x0)}."
                    )
                starts = list(x0) if np.ndim(x0) == 2 else [x0] * N
                out = [self.output_std(records[i], starts[i], t=times[i]) for i in range(N)]
            return out if is_ragged(u) or isinstance(u, list) else np.stack(out)
        if np.ndim(u) != 2:
            raise ValueError(
                f"`u` must be one record's inputs (T, n_u) or several, (N, T, n_u), got "
                f"shape {np.shape(u)}."
            )
        head = None
        if z_head is not None:
            self._check_z_head(z_head)
            kwargs = {"missing": "mask"} if np.isnan(as_float(z_head, "z_head")).any() else {}
            pred = self.predict(u, z_head, t=t, **kwargs)
            x0 = pred.x0
            s2 = self._noise_variance()
            head = (len(z_head), z_head, self._weight_matrix(), s2, pred.estimate.identifiable)
        else:
            if np.ndim(x0) != 1:
                raise ValueError(
                    f"`x0` must be one initial state (n_x,), got shape {np.shape(x0)}"
                    + (": pass `x0=result.x0[i]` for record i." if np.ndim(x0) == 2 else ".")
                )
            check_state_size(x0, np.shape(self.x0)[-1])
        data = check_data(self.model, self.theta, x0, u, t=t)
        std = output_std(data.model, data.theta, self.fixed, self.covariance, data.x0, data.u, head)
        return std.astype(data.x0.dtype)

    def save(self, path):
        """Save to one `.npz` file (`oneshot_jax.save_result`; read it back with
        `oneshot_jax.load_result`).

        **Returns:**

        The path written.
        """
        return _io.save_result(self, path)

    def __str__(self):
        return report(self)

    __repr__ = __str__


def load_result(path, *, model=None, like=None) -> FitResult:
    """Load a `FitResult` written by `FitResult.save` (or `save_result`).

    **Arguments:**

    - `path`: the `.npz` file.
    - `model`: the `Model`, for `FitResult.simulate` (models are not saved). It must match
        what the file records of the fitted one (a `Model.from_ode`'s dt, method,
        substeps and input) and run with the saved theta, keeping the saved state's size
        and giving the saved number of outputs: a ValueError names a difference. The
        names of its states and outputs (`Model(states=..., outputs=...)`) are labels,
        not saved: `print` of a result loaded without a model shows indices (`x0[0]`),
        and with a model, that model's names.
    - `like`: a theta of the fitted structure (e.g. theta0), needed when theta holds
        equinox modules or other nodes that the file's JSON cannot describe; its
        non-numeric parts are put back around the loaded arrays. It must match the saved
        theta in its leaves' shapes, the parameters' names, and what the file records
        of the rest in words (an activation function's name, a `functools.partial`'s
        arguments, a module's static fields, integer arrays' values): a ValueError names
        the first difference. A function is compared by its name only, not its body (two
        lambdas look alike).

    **Returns:**

    The `FitResult`, equal to the saved one field by field.
    """
    fields = _io.read_result(path, like=like, model=model)
    _io.check_model_fits(model, fields)
    if model is not None:  # (the model itself is the record, as after `fit`)
        fields["saved_model_signature"] = None
    history = FitHistory(**fields.pop("history"))
    starts = fields.pop("starts")
    return FitResult(
        **fields,
        history=history,
        starts=None if starts is None else Starts(**starts),
        model=model,
    )
