"""`fit`: estimate theta and x0 by minimising the multi-step loss (eq. 5/21).

`fit` runs in four stages: its inputs checked and normalised, and the `FitProblem` and
starting points built from them (`oneshot_jax._fit_inputs`); the solve, the solvers'
loop (`oneshot_jax._iterate`) from every start as one compiled call (`_solve`, `_run`);
the `FitResult` assembled on the host (`oneshot_jax._assemble`).
"""

import dataclasses
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._aggregate import augment, check_window
from ._assemble import assemble, collect, post, prepare, weighed, worst_fit
from ._caller_warnings import recording, warn
from ._checks import record_x0_mask, x0_mask
from ._covariance import NOT_COMPUTED, NeweyWest, as_covariance
from ._fit_inputs import build_problem, check_inputs
from ._fit_report import UNEQUAL_NOISE, theta_order
from ._fit_result import FitResult
from ._iterate import run, starts_in_turn
from ._jit import jit
from ._model import model_labels
from ._noise_weight import fit_noise_weighted
from ._optimality import (
    CHECK_ENTRIES,
    CHECK_SE,
    NEWTON_COLUMNS,
    SETTLE_SE,
    first_order_at,
    gauss_newton_refutes,
    gtol_at_least_resolution,
    n_observations,
    newton_distance,
    output_norm,
    outputs_above_round_off,
    refuted,
)
from ._parallel._report import UNCONVERGED, counting
from ._problem import Params
from ._progress import NoProgress
from ._results import RESULTS, SUCCESS, name_of
from ._solver.least_squares import AbstractLeastSquares
from ._stability import (
    checked_states,
    rhs_of,
    row_bound,
    sample_points,
    stability,
    step_weights,
    warn_after_fit,
    warn_if_near_limit,
)
from ._zero_gradient import flag_zero_gradient


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
    except TypeError:
        return theta_order(theta)
    return _pytree.kept(_ORDERS, key, lambda: theta_order(theta))


def _warn_held_window_states(window, x0, estimate_x0, window_starts, model):
    """Warn where `estimate_x0` holds x0 entries of windows after the first that no data
    gave: with one x0 (n_x,) for a windowed record of a model that does not observe its
    whole state, those windows start from an estimate with theta0, and a held entry
    keeps that value (biased where theta0 is wrong). (A model that observes its state
    reads them off z: measured values.)"""
    if window is None or window_starts is None or len(window_starts) < 2:
        return
    if model.observes_state:
        return
    if np.ndim(x0) != 1 or estimate_x0 is True:
        return
    held = ~x0_mask(estimate_x0, np.shape(x0)[0])
    if not held.any():
        return
    warn(
        f"`estimate_x0` holds x0 entries {np.flatnonzero(held).tolist()} of every window, and "
        f"the {len(window_starts) - 1} windows after the first start from states estimated "
        "with theta0, not measured: those held states are theta0's, and the estimates are biased "
        "where theta0 is wrong. Pass estimate_x0=True for a windowed fit, or one x0 per "
        "window (n_windows, n_x) holding known values.",
        UserWarning,
        stacklevel=3,
    )


def _flag_diverged_stages(result):
    """Warn, and list in `stop_info["stages_diverged"]`, where a solver of a sequence
    other than the last diverged (a NaN or inf loss in its rows of the history): the next
    solver starts from its last finite iterate and the result reports the last solver's
    stop, so the divergence showed only as NaN in `history.loss`."""
    stage, loss = np.asarray(result.history.stage), np.asarray(result.history.loss)
    if stage.size == 0 or stage.max() == 0:
        return result
    last = int(stage.max())
    bad = [i for i in range(last) if not np.all(np.isfinite(loss[stage == i]))]
    if not bad:
        return result
    first = int(np.asarray(result.history.step)[(stage == bad[0]) & ~np.isfinite(loss)][0])
    warn(
        f"solver {bad[0] + 1} of the {last + 1} in the sequence "
        f"({result.solver[bad[0]]['solver']}) diverged: its "
        f"loss was not finite at step {first}"
        + (f" (and solvers {[i + 1 for i in bad[1:]]} likewise)" if len(bad) > 1 else "")
        + ". The next solver started from its last finite iterate; the result and its "
        "stop are the last solver's. A smaller learning rate (or Adam's scale='theta0') "
        "keeps the earlier stage finite.",
        RuntimeWarning,
        stacklevel=3,
    )
    info = {**result.stop_info, "stages_diverged": bad}
    return dataclasses.replace(result, stop_info=info)


@jit
def _solve(
    solvers,
    problem,
    starts,
    history_size,
    meter,
    bar_id,
    stability_at=None,
    lags=None,
    in_turn=False,
):
    """The whole fit as one compiled call: project the starts, run the solvers from all of
    them (side by side, or with `in_turn` one after another: `_iterate.run`), pick the best
    start and post-process it (covariance and metrics; with `lags`, the Newey-West
    sandwich of that many lags), and with `stability_at` (a `Model.from_ode` model's
    right-hand side, the flattened indices of the evenly spaced states to check and each
    state's step h, `_stability.checked_states`) the states checked and the Jacobians
    there. Returns what `assemble` reads (an `Out`) and those (or None), packed."""
    projected = jax.vmap(problem.feasible)(starts.theta)
    moved = projected != starts.theta  # (S, p): the entries each start had outside
    starts = Params(projected, starts.x0)
    stages = run(
        solvers,
        problem,
        starts,
        history_size=history_size,
        meter=meter,
        bar_id=bar_id,
        in_turn=in_turn,
    )
    final = stages[-1]
    # The best start: the lowest final loss, or with validation data the lowest score.
    # (where no start has a finite score, the held-out data tell nothing: the loss ranks)
    rank = final.loss
    if final.best is not None:
        score = final.best.returned_score()
        rank = jnp.where(jnp.any(jnp.isfinite(score)), score, rank)
    rank = jnp.where(jnp.isfinite(rank), rank, jnp.inf)
    # (a start stopped by a negative penalty, lambda h < 0, ranks after the others: its
    # loss is below what the least-squares solvers minimise, a sum of squares)
    penalised = final.result == RESULTS.negative_penalty
    fair = jnp.where(penalised, jnp.inf, rank)
    best = jnp.where(jnp.all(penalised), jnp.argmin(rank), jnp.argmin(fair))
    params = jax.tree_util.tree_map(lambda a: a[best], final.params)
    blocks = (
        None if final.blocks is None else jax.tree_util.tree_map(lambda a: a[best], final.blocks)
    )
    strategy = getattr(solvers[-1], "strategy", "auto")
    posted = post(problem, params, blocks, strategy, lags)
    out = collect(problem, stages, best, moved, posted)
    jacobians = None
    if stability_at is not None:
        rhs, idx, h = stability_at
        theta = problem.theta_of(params.theta)
        idx, xs, J = checked_states(rhs, theta, posted[-1], problem.u, idx, h)
        jacobians = (idx, xs, J, row_bound(xs, J))
    # One buffer per dtype to the host instead of one per array (`_pytree.pack`).
    return _pytree.pack((out, jacobians))


# The most memory the iterate history's theta rows take (`fit(history=...)`).
HISTORY_BYTES = 64 * 2**20


def _run(solvers, problem, starts, history, meter, stability_at=None, meanwhile=None, lags=None):
    """The solve: `_solve` from every start, timed, with the progress bar open around it.
    Returns its output unpacked (an `Out`), the wall time, the counts of parallel
    rollouts and their fallbacks, the Jacobians of `stability_at` and what `meanwhile()`
    returned (host work that does not need the output, done while the compiled call runs),
    and warns of those fallbacks."""
    # (No bar: no calls of the meter's methods, which equinox wraps anew on each access.)
    bar = not isinstance(meter, NoProgress)
    n_starts = starts.theta.shape[0]
    in_turn = n_starts > 1 and starts_in_turn()
    steps = sum(s.max_steps for s in solvers) * (n_starts if in_turn else 1)
    bar_id = meter.open(steps) if bar else 0
    # No more rows than a start can have iterates (above the default, whose program is
    # shared by every step budget): `history=10**9` must not allocate 10**9 rows.
    most = sum(s.max_steps for s in solvers) + len(solvers) + 1
    history = min(history, max(1000, most + most % 2))
    # No more than `HISTORY_BYTES` of theta rows (a network of 1e5 weights: 1000 rows
    # were 0.8 GB per start); fewer rows only thin the record sooner.
    row = n_starts * max(starts.theta.shape[-1], 1) * np.dtype(problem.dtype).itemsize
    history = min(history, max(2, (HISTORY_BYTES // row) // 2 * 2))
    try:
        with counting() as counts:
            t0 = time.perf_counter()
            buffers, layout = _solve(
                tuple(s.traced_options(problem.dtype) for s in solvers),
                problem,
                starts,
                history,
                meter,
                np.asarray(bar_id, np.int32),
                stability_at,
                lags,
                in_turn,
            )
            during = None if meanwhile is None else meanwhile()
            jax.block_until_ready(buffers)
            jax.effects_barrier()
            wall = time.perf_counter() - t0
    finally:
        if bar:
            meter.close(bar_id)
    out, jacobians = _pytree.unpack(buffers, layout)
    diagnostics = dict(counts) if counts["parallel_rollouts"] else {}
    if counts["sequential_fallbacks"]:
        warn(
            f"{counts['sequential_fallbacks']} of {counts['parallel_rollouts']} parallel "
            "rollouts did not converge and fell back to the sequential loop (the results are "
            "exact; see FitResult.diagnostics).",
            RuntimeWarning,
            stacklevel=3,  # `fit`'s caller
        )
    if counts["unconverged_rollouts"]:
        warn(
            f"{counts['unconverged_rollouts']} of {counts['parallel_rollouts']} parallel "
            f"rollouts: {UNCONVERGED} The fit's result is not reliable.",
            RuntimeWarning,
            stacklevel=3,
        )
    return out, wall, diagnostics, jacobians, during


@jit
def _loss_at(problem, params, strategy):
    """The problem's loss at `params`, compiled once per problem structure and strategy
    (the data are arguments) for `_flag_unconverged_rollouts`' re-checks."""
    return problem.loss(params, strategy)


def _flag_unconverged_rollouts(result, problem, theta_flat, x0, strategy, finals=None):
    """`result` with the stop reason `unconverged_rollout` where it reported a success
    while the parallel rollout of the returned point keeps Newton's unconverged iterate
    (`ParallelInTime(fallback=False)`; `_run` has warned of every such rollout of the
    fit): the values its stop was judged on are not the model's. Where only rollouts of
    other points (trial steps) did not converge, the stop stands. With several starts,
    `finals` (the free variables each start ended at, a `Params` (S, ...)): each other
    start that reported a success is checked the same way (its stop in `result.starts`)."""
    counts = result.diagnostics or {}
    if not counts.get("unconverged_rollouts"):
        return result

    def unconverged(params):
        with counting() as again:  # the point's rollout, once more
            jax.block_until_ready(_loss_at(problem, params, strategy))
        return bool(again["unconverged_rollouts"])

    out = result
    if result.starts is not None and finals is not None:
        reasons = list(result.starts.stop_reason)
        for s, reason in enumerate(reasons):
            if s != result.best and reason in SUCCESS:
                if unconverged(Params(finals.theta[s], finals.x0[s])):
                    reasons[s] = "unconverged_rollout"
        if reasons != list(result.starts.stop_reason):
            starts = dataclasses.replace(result.starts, stop_reason=tuple(reasons))
            out = dataclasses.replace(out, starts=starts)
    point = problem.split(jnp.asarray(theta_flat), jnp.asarray(x0))
    if result.success and unconverged(point):
        # (`loss` stays the rollouts', as the history's; the model's, from the sequential
        # loop, goes with the reason)
        out = _restated(
            out,
            "unconverged_rollout",
            unconverged_rollouts=counts["unconverged_rollouts"],
            parallel_rollouts=counts["parallel_rollouts"],
            model_loss=float(_loss_at(problem, point, "vjp")),
        )
    return out


def _flag_plateau_above_start(result, problem, starts, best, strategy):
    """`result` with the stop `stalled` where it reported convergence at a point where
    Jacobian columns vanished along the fit (`stop_info["vanished"]`) and the loss is
    above the best start's: a step onto a plateau, not a minimum (SGD's first step sent
    a rate a of exp(a dt) to -1e180, where the term underflows to 0 and the gradient is
    exactly 0; the loss there was 6 times the start's). `stop_info["start_loss"]` is the
    start's loss. Not checked with a regulariser (its stop weighs C + g)."""
    if result.status not in ("converged", "statistically_converged"):
        return result
    if not result.stop_info.get("vanished") or problem.regulariser is not None:
        return result
    theta = jnp.asarray(starts.theta[best])
    if problem.constrained:  # (where the fit started: an infeasible start is projected)
        theta = problem.feasible(theta)
    start = Params(theta, jnp.asarray(starts.x0[best]))
    before = float(_loss_at(problem, start, strategy))
    eps = np.finfo(problem.dtype).eps
    if not (np.isfinite(before) and float(result.loss) > before * (1 + 64 * eps)):
        return result
    return _restated(result, "stalled", start_loss=before)


def _flag_every_column_vanished(result, problem):
    """`result` with the stop `stalled` where it reported statistical convergence after
    the Jacobian columns of every free parameter of theta vanished along the fit
    (`stop_info["vanished"]`): the parameters ran to where they no longer move the
    outputs (a mass-spring-damper fitted from a far start ran to m = 5e6, k = 2e7, c =
    2e6, its output then nearly the initial state's, FIT 7 %), so that "no quantity the
    data determine can still change" holds because the data determine none: a limit,
    not a solution. `stop_info["all_vanished"]`. Not checked with a regulariser (a
    sparse fit may switch every term off)."""
    if result.status != "statistically_converged" or problem.regulariser is not None:
        return result
    names = set(result.names)
    if not names or not names <= set(result.stop_info.get("vanished") or ()):
        return result
    return _restated(result, "stalled", all_vanished=True)


def _restated(result, reason, **info):
    """`result` with the stop reason `reason` where a check after the solve decides the
    stop (refutes the solver's success, or settles its stall: `_settle`):
    the solver's own stop in `stop_info["solver_stop"]` with `info`, and the best start's
    stop in `result.starts` too (as the status line's)."""
    info = {**result.stop_info, "solver_stop": name_of(result.stop_reason), **info}
    out = dataclasses.replace(result, stop_reason=getattr(RESULTS, reason), stop_info=info)
    if result.starts is not None:
        reasons = list(result.starts.stop_reason)
        reasons[result.best] = reason
        starts = dataclasses.replace(result.starts, stop_reason=tuple(reasons))
        out = dataclasses.replace(out, starts=starts)
    return out


def _flag_hidden_outputs(result, problem, max_steps):
    """A `zero_residual` that holds of the outputs together but not of each
    (`_optimality.outputs_above_round_off`: an output of a large size, reproduced
    exactly, can hide another output's misfit): not a solution. The stop is then what the
    solver's would have been without that test: `max_steps_reached` where its last stage
    took its `max_steps` (a first-order solver reads a zero residual at its last step),
    else `stalled` (no step progressed), with `stop_info["unresolved_outputs"]` naming
    the outputs and `solver_stop` "zero_residual"."""
    if result.status != "zero_residual":
        return result
    above = outputs_above_round_off(problem, np.reshape(result.residuals, problem.z.shape))
    if not above.any():
        return result
    labels = model_labels(getattr(problem.model, "outputs", None), above.size)
    names = [str(labels[j]) if labels is not None else str(j) for j in np.flatnonzero(above)]
    ran_out = max_steps is not None and result.stop_info.get("at_step", -1) >= max_steps
    reason = "max_steps_reached" if ran_out else "stalled"
    return _restated(result, reason, unresolved_outputs=names)


@jit
def _first_order_at(problem, params, strategy):
    return first_order_at(problem, params, strategy)


def _measure_unmeasured_success(result, problem, out, strategy):
    """A success that the solver reported without a first-order measure (a solver of
    one's own, whose `measures` are `AbstractSolver`'s default): the measure is taken at
    the returned point (`_optimality.first_order_at`). A `converged` whose measure is
    above the solver's gtol (1e-8 where it has none; at least the measure's resolution in
    the data's precision) and above the round-off limit is `stalled`
    (`stop_info["unmeasured_claim"]`), or `zero_residual` where the residual is at the
    round-off level of the data (where the measure says nothing): every solver's success
    is the same test. Its `max_steps_reached` is measured too, so that its message says
    how far from stationary the returned point is (the solver's own test may not be one
    that can pass in this precision); where the measure meets that test, the last step
    allowed left a solution: `converged` (as `Optimistix` at its last step; the message
    read "met" and "not a stationary point yet" together)."""
    info = result.stop_info
    if np.isfinite(info.get("first_order", np.nan)):
        return result
    if not result.success and result.status != "max_steps_reached":
        return result
    best = int(out.best)
    params = Params(jnp.asarray(out.start_theta[best]), jnp.asarray(out.start_x0[best]))
    fo, zero = _first_order_at(problem, params, strategy)
    fo = float(fo)
    gtol = info.get("gtol", np.nan)
    gtol = 1e-8 if not np.isfinite(gtol) else gtol
    tol = max(float(gtol_at_least_resolution(gtol, problem.dtype)), info["roundoff_limit"])
    result = dataclasses.replace(result, stop_info={**info, "first_order": fo, "gtol": gtol})
    if result.status == "max_steps_reached":
        return _restated(result, "converged") if fo <= tol else result
    if fo <= tol:
        return result
    if bool(zero):
        return dataclasses.replace(result, stop_reason=RESULTS.zero_residual)
    return _restated(result, "stalled", unmeasured_claim=True)


@jit
def _refuted_at(problem, params, along, strategy):
    """`_optimality.refuted`, compiled once per problem structure and strategy (the data
    are arguments)."""
    return refuted(problem, params, along, strategy)


def _refutation(problem, stop, degenerate, gone, promising, theta, x0, strategy):
    """The flag of `_flag_refuted_stop` where a start's stop `stop` (at a degenerate
    minimum where `degenerate`, with the vanished theta columns `gone`; `promising`: its
    `promises_descent`) is refuted at its free entries `theta` (p,), `x0` (N, m) by a step
    that lowers the loss (`_optimality.refuted`), with the plain first-order measure
    there; (None, None) where it stands or is not such a stop."""
    degenerate = degenerate and stop == "converged"
    if not (degenerate or (stop == "zero_residual" and promising)):
        return None, None  # (before any array operation: each would compile a program)
    if degenerate:
        along, flag = Params(gone, np.zeros(x0.shape, bool)), "descends_along_vanished"
    else:
        along = Params(np.ones(theta.shape, bool), np.ones(x0.shape, bool))
        flag = "descends_from_zero_residual"
    params = Params(jnp.asarray(theta), jnp.asarray(x0))
    down, fo = _refuted_at(problem, params, jax.tree_util.tree_map(jnp.asarray, along), strategy)
    return (flag, float(fo)) if bool(down) else (None, None)


def _measure_validated_point(result, problem, out, strategy):
    """After a `validation` stop the returned point is the best-scoring iterate, not the
    solver's last, whose first-order measure `stop_info` holds (a first-order solver's,
    estimated from column norms of an earlier iterate: 1.56 read where a cosine is at
    most 1): the measure taken at the returned point (`_optimality.first_order_at`)."""
    if result.status != "validation":
        return result
    best = int(out.best)
    params = Params(jnp.asarray(out.start_theta[best]), jnp.asarray(out.start_x0[best]))
    fo, _ = _first_order_at(problem, params, strategy)
    return dataclasses.replace(result, stop_info={**result.stop_info, "first_order": float(fo)})


def _flag_refuted_stop(result, problem, out, strategy, max_steps=None):
    """`result` with the stop `stalled` (`max_steps_reached` where a zero residual was
    read at the solver's last step, `max_steps`) where the solver's stop says no step
    lowers the loss but one does by more than sqrt(eps) of it and its round-off
    (`_optimality.refuted`), its first-order measure then the plain one and
    `stop_info["solver_stop"]` the solver's own stop:

    - converged at a degenerate minimum (`stop_info["degenerate"]`): a step along the
      theta columns that vanished (`descends_along_vanished`);
    - a zero residual where the first-order measure at the stop promises a decrease
      beyond round-off (`_optimality.promises_descent`): a step along every column
      (`descends_from_zero_residual`).

    With several starts, each other start's stop in `result.starts` is checked alike
    (`stalled` where refuted): a start that read as a success from its stop alone."""
    theta, x0 = np.asarray(out.start_theta), np.asarray(out.start_x0)
    degenerate, promising = np.asarray(out.degenerate), np.asarray(out.promises_descent)
    vanished = np.asarray(out.vanished)
    listed = result.starts is not None
    stops = list(result.starts.stop_reason) if listed else []
    for s in range(theta.shape[0]):
        best = s == int(out.best)
        stop = name_of(result.stop_reason) if best else stops[s]
        gone = np.broadcast_to(vanished[s], theta.shape[1:])
        flag, fo = _refutation(
            problem, stop, bool(degenerate[s]), gone, promising[s], theta[s], x0[s], strategy
        )
        if flag is None:
            continue
        if not best:
            stops[s] = "stalled"
            continue
        info = {k: v for k, v in result.stop_info.items() if k != "degenerate"}
        # (a first-order solver reads a zero residual at its last step: where the budget
        # ran out, that is the stop, with its remedy, more steps)
        ran_out = max_steps is not None and info.get("at_step", -1) >= max_steps
        reason = "max_steps_reached" if ran_out and flag != "descends_along_vanished" else "stalled"
        result = _restated(  # (the best start's stop in `result.starts` too)
            dataclasses.replace(result, stop_info={**info, "first_order": fo}),
            reason,
            **{flag: True},
        )
    if not listed:
        return result
    stops[int(out.best)] = result.starts.stop_reason[int(out.best)]
    if tuple(stops) == result.starts.stop_reason:
        return result
    return dataclasses.replace(
        result, starts=dataclasses.replace(result.starts, stop_reason=tuple(stops))
    )


@jit
def _gauss_newton_refutes_at(problem, params, strategy):
    """`_optimality.gauss_newton_refutes`, compiled once per problem structure and
    strategy."""
    return gauss_newton_refutes(problem, params, strategy)


def _unresolved_directions(result):
    """Whether the covariance of a fit calls some free entry not identifiable (an inf
    standard error from J^T J's null cut, `_linalg.scaled_eigh`), where it was computed
    and sigma^2 is known."""
    if np.shape(result.covariance) == (0, 0):
        return False
    if (result.diagnostics or {}).get("degrees_of_freedom", 1) <= 0:
        return False
    leaves = jax.tree_util.tree_leaves(eqx.filter(result.std, eqx.is_array))
    leaves = leaves + [np.asarray(result.x0_std)]
    return any(bool(np.isinf(np.asarray(leaf)).any()) for leaf in leaves)


def _flag_unresolved_success(result, problem, out, strategy, least_squares):
    """A fit in a precision below float64, or one in float64 whose covariance calls some
    free entry not identifiable, checked by the Gauss-Newton step from the Jacobian
    itself (`_optimality.gauss_newton_refutes`): the normal equations the solvers form
    lose half the precision's digits, and a direction the data determine can read as
    null there (in float64, two columns collinear to 3e-7, cond J 8e6: LM and GN said
    `statistically_converged` 2.3 standard errors from the optimum, the loss 1.027 times
    its own).

    - a success decided at the precision's limit, `statistically_converged` or
      `converged` with the measure above gtol (at its round-off limit), that the step
      refutes becomes `stalled` (`stop_info["gauss_newton_refuted"]`; a measure within
      gtol is the user's threshold, whatever the precision): a least-squares solver's
      normal equations, and a first-order solver's measure, whose columns' norms come
      from J^T J's diagonal and whose Newton check (`_settle`) has no step where J^T J
      is singular to this precision (L-BFGS in float32 stopped 2.2 standard errors from
      the optimum of an output offset next to an input of large mean);
    - in float64, a `statistically_converged` that is not a settled stall becomes
      `stalled` (`stop_info["regular_jacobian"]`) where J has full rank, theta's columns
      by themselves too, and the step is over `CHECK_SE` standard errors, confirmed or
      not: the test is for an over-parameterised theta, and none is (see below);
    - where the last solver is a least-squares one (`least_squares`: they form J^T J),
      a failure (`max_steps_reached`, `stalled`, `no_progress`) that the step refutes,
      where J^T J loses a direction that J keeps, is left as it is, its message then
      saying that more steps will not help.

    Either way `stop_info["gauss_newton_se"]` is the step's size in standard errors and
    `stop_info["precision"]` the dtype. In float64 a `converged` within gtol is checked
    too: the measure is a cosine per column, and does not see the collinear direction.
    So is such a `zero_residual` whose loss is above the residuals' round-off floor,
    (64 eps)^2 times the outputs' squared size (`_optimality.output_norm`), refuted where
    the step would remove half the loss (at round-off, about rank / R of it). Not
    checked: a float64 fit whose covariance finds every free entry identifiable or was
    not computed, a penalty or a regulariser (the step is that of the least-squares loss
    alone), a Jacobian of more than `CHECK_ENTRIES` entries, and the other starts of a
    multistart."""
    problem_ok = problem.cost.penalty is None and problem.regulariser is None
    eps = np.finfo(problem.dtype).eps
    low = eps > np.finfo(np.float64).eps
    unresolved = not low and _unresolved_directions(result)
    # (a zero residual in float64, along such a direction and above the residuals' own
    # round-off floor: noise-free data of two inputs collinear to 1e-7, where Adam read
    # `zero_residual` at gains 0.75 and 1.25, truth 1, the loss 8e-16; a fit that
    # reaches the floor, or whose covariance resolves every entry, is not checked)
    zero = unresolved and result.status == "zero_residual"
    zero = zero and float(result.loss) > (64 * eps) ** 2 * float(output_norm(problem))
    info = result.stop_info
    # (in float64 a measure within gtol too: it is a cosine per column, and two columns
    # collinear to 1e-7 read 8e-9 <= 1e-8 2.4 standard errors from the optimum)
    within_gtol = info.get("first_order", np.nan) <= info.get("gtol", np.nan)
    within_gtol = within_gtol and not unresolved
    status = result.status
    success = status == "statistically_converged" or (status == "converged" and not within_gtol)
    failure = least_squares and status in ("max_steps_reached", "stalled", "no_progress")
    checked = low or unresolved  # (`zero` implies `unresolved`)
    if not (checked and problem_ok and (success or failure or zero)) or "solver_stop" in info:
        return result
    N, T, n_z = problem.z.shape
    best = int(out.best)
    theta, x0 = np.asarray(out.start_theta[best]), np.asarray(out.start_x0[best])
    if N * T * n_z * (theta.size + x0.size) > CHECK_ENTRIES:
        return result
    settled = info.get("settled")
    params = Params(jnp.asarray(theta), jnp.asarray(x0))
    down, se, lost, regular = _gauss_newton_refutes_at(problem, params, strategy)
    info = dict(gauss_newton_se=float(se), precision=np.dtype(problem.dtype).name)
    regular = not low and bool(regular) and float(se) > CHECK_SE
    if status == "statistically_converged" and not settled and regular:
        # The test of an over-parameterised theta (a null space of its columns once the
        # x0 columns are eliminated, in J^T J), in float64: where J itself has full rank,
        # and theta's columns too by themselves, nothing is over-parameterised, and the
        # step from J moves the fit by more than a standard error: the rank was lost in
        # J^T J alone, along a direction of the data (an unstable gain on windows of 50
        # samples, a^49 about 1e14, its column within 4e-14 of the windows' x0 columns:
        # a success at a loss 600 times the optimum's, the step from J 15 standard
        # errors, which the loss cannot confirm so far from the point; with x0 refitted
        # the loss still fell along the gain). An exact null space (an output offset
        # beside an integrator's x0) leaves J rank-deficient: the stop stands.
        return _restated(result, "stalled", regular_jacobian=True, **info)
    if zero:
        # At a genuine round-off residual the part of r in J's range is about rank / R
        # of it (the step's decrease pred = se^2 C / (R - rank)); along a direction that
        # J^T J loses, most of it: refuted where the step would remove half the loss.
        spare = max(float(n_observations(problem)) - theta.size - x0.size, 1.0)
        if bool(down) and float(se) ** 2 > 0.5 * spare:
            return _restated(result, "stalled", gauss_newton_refuted=True, **info)
        return result
    if success and bool(down):
        return _restated(result, "stalled", gauss_newton_refuted=True, **info)
    if failure and bool(down) and bool(lost):
        return dataclasses.replace(result, stop_info={**result.stop_info, **info})
    return result


@jit
def _newton_distance_at(problem, params, strategy, held):
    """`_optimality.newton_distance`, compiled once per problem structure and strategy."""
    return newton_distance(problem, params, strategy, held)


def _settle(result, problem, out, strategy, least_squares):
    """A stall that the data have settled, checked with the loss's own curvature
    (`_optimality.newton_distance`: the Newton step, H = 2 (J^T J + sum r_i Hess r_i),
    measured in standard errors):

    - a least-squares solver's settled stall (`statistically_converged` with
      `stop_info["settled"]`: its undamped Gauss-Newton step was within stol standard
      errors, `AbstractLeastSquares._settled`) stays a success where the Newton step is
      within stol too; else it is `stalled` (`stop_info["newton_se"]`; the Newton step
      undefined, a saddle or a flat direction, counts as beyond). Where the residuals'
      curvature cancels most of J^T J the Gauss-Newton step is short of the distance
      left: a structured misfit stalled 0.6 standard errors from the optimum with a
      Gauss-Newton step of 1e-3;
    - a first-order solver's `converged` at its round-off limit (the measure above gtol,
      below the limit of a stall: `_optimality.stall_limit`, raised where the outputs are
      far above the residuals) is `stalled` (`stop_info["newton_refuted"]`) where the
      Newton step moves the estimates by more than `CHECK_SE` standard errors: a
      per-column cosine does not see a direction of nearly collinear columns, and L-BFGS
      stopped 3 standard errors from the optimum of an output offset 1e7 next to an
      input 1 + 0.01 N(0, 1) (the measure 2.4e-4 below its limit 2.2e-3);
    - a first-order solver's own stall at round-off (L-BFGS's line search failed; not a
      step test of the user's tolerances, an `Optimistix` solver's rtol and atol) is
      `statistically_converged` (`stop_info["settled"]`, the solver's stop in
      `stop_info["solver_stop"]`) where the Newton step is at most `SETTLE_SE` standard
      errors, no parameter alone would move by one (first-order measure times
      sqrt(R - columns) at most 1) and every estimated entry that reaches the outputs is
      identifiable there (its column of J, those at a bound included, of full rank by
      `newton_distance`'s cut): an output offset of 1e4 around a noise of 1e-3 left L-BFGS
      `stalled` 4e-5 standard errors from the optimum.

    Entries of theta at a bound are held (the step of the others). Not checked: a
    penalty, a regulariser or a general projection, more than `NEWTON_COLUMNS` free
    variables or `CHECK_ENTRIES` Jacobian entries (a least-squares settled stop then
    stands as its solver's, a first-order stall as a stall), other starts of a
    multistart."""
    info = result.stop_info
    settled = result.status == "statistically_converged" and bool(info.get("settled"))
    stalled = not least_squares and result.status == "stalled" and "solver_stop" not in info
    stalled = stalled and not info.get("step_test")  # (the user's tolerances fired: theirs)
    # (a first-order solver's success at its round-off limit, the measure above gtol)
    at_limit = not least_squares and result.status == "converged" and "solver_stop" not in info
    at_limit = at_limit and info.get("first_order", np.nan) > info.get("gtol", np.nan)
    if not (settled or stalled or at_limit):
        return result
    if problem.cost.penalty is not None or problem.regulariser is not None:
        return result
    if problem.project is not None:
        return result
    N, T, n_z = problem.z.shape
    best = int(out.best)
    theta, x0 = np.asarray(out.start_theta[best]), np.asarray(out.start_x0[best])
    columns = theta.size + x0.size
    if columns > NEWTON_COLUMNS or N * T * n_z * columns > CHECK_ENTRIES:
        return result
    held = np.zeros(theta.size, bool)
    if problem.lower is not None:
        lo, hi = np.asarray(problem.lower), np.asarray(problem.upper)
        held = ((theta <= lo) & np.isfinite(lo)) | ((theta >= hi) & np.isfinite(hi))
    params = Params(jnp.asarray(theta), jnp.asarray(x0))
    se, defined, identifiable = _newton_distance_at(problem, params, strategy, jnp.asarray(held))
    se, defined = float(se), bool(defined)
    if at_limit:
        if defined and se > CHECK_SE:
            return _restated(result, "stalled", newton_se=se, newton_refuted=True)
        return result
    if settled:
        stol = info.get("stol", SETTLE_SE)
        if defined and se <= stol:
            return dataclasses.replace(result, stop_info={**info, "newton_se": se})
        rest = {k: v for k, v in info.items() if k != "settled"}
        demoted = dataclasses.replace(result, stop_info=rest)
        return _restated(demoted, "stalled", newton_se=se if defined else float("inf"))
    dof = int(n_observations(problem)) - (columns - int(held.sum()))
    fo = info.get("first_order", np.nan)
    if not (defined and dof > 0 and se <= SETTLE_SE and fo * np.sqrt(dof) <= 1.0):
        return result
    # Every estimated entry that reaches the outputs identifiable there, those at a bound
    # included: sigma^2 is the point's, so a stall far from the optimum inflates the
    # standard errors that measure its step, and where a direction is unresolved the
    # quadratic model does not see how far the loss still falls along it (L-BFGS stalled
    # "0.006 standard errors" from a point of a loss 1e9 times the optimum's: an output
    # offset held at its bound and a pole near 1, which makes the offset and x0 collinear).
    if not bool(identifiable):
        return result
    return _restated(
        result,
        "statistically_converged",
        settled=True,
        standard_errors=se,
        newton_se=se,
        stol=SETTLE_SE,
    )


def _warn_narrowed_outputs(z, residuals, dtype, outputs=None):
    """Warn where the outputs `z` were given in float64 and the fit ran in a lower
    precision `dtype` (JAX's x64 off), and rounding them to it changed an output by more
    than a quarter of its residual RMS (`residuals`, the fit's): the noise of outputs
    far from zero (an offset of 300, noise 1e-6) is then below that precision's
    resolution of them, and a float32 fit read the rounded data exactly (loss 0,
    standard errors 0, a converged estimate 3 standard errors from float64's)."""
    if np.finfo(dtype).eps <= np.finfo(np.float64).eps:
        return
    records = list(z) if isinstance(z, (list, tuple)) else [z]
    given = [np.asarray(r) for r in records]
    if not all(g.dtype == np.float64 for g in given):
        return
    n_z = given[0].shape[-1]
    flat = np.concatenate([g.reshape(-1, n_z) for g in given])
    lost = flat - flat.astype(dtype).astype(np.float64)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an output with no sample: NaN)
        n = np.sqrt(np.nanmean(lost**2, axis=0))
        e = np.asarray(residuals, np.float64).reshape(-1, n_z)
        r = np.sqrt(np.nanmean(e**2, axis=0))
    bad = np.flatnonzero(n > 0.25 * r)
    if not bad.size:
        return
    labels = model_labels(outputs, n_z)
    j = int(bad[np.argmax(n[bad] / np.maximum(r[bad], np.finfo(np.float64).tiny))])
    name = f"output {labels[j] if labels is not None else j}"
    share = "" if r[j] == 0 else f", {n[j] / r[j]:.2g} times its residual RMS {r[j]:.3g}"
    more = f" (and {bad.size - 1} more)" if bad.size > 1 else ""
    warn(
        f"the outputs were given in float64 and the fit ran in {np.dtype(dtype).name} (JAX's "
        f"x64 is off): rounding them changed {name}{more} by an RMS of {n[j]:.3g}{share}. "
        "The fit, its standard errors and its stop read the rounded data, whose noise is "
        "partly lost (the resolution of outputs far from zero, an offset, is coarse): enable "
        'float64 before fitting, jax.config.update("jax_enable_x64", True).',
        RuntimeWarning,
        stacklevel=3,
    )


def _warn_unequal_noise(residuals, weight, std, readings=None):
    """Warn where the weighted residuals of the outputs differ in variance by more than a
    factor of 10: the covariance pools one noise level sigma^2 over all outputs, which is
    the Cramer-Rao bound only for a weight Q proportional to the inverse noise variance.
    `readings`: the mean squared weighted residual of each output's aggregated readings
    (`Augmented.reading_mean_squares`), pooled in sigma^2 with the point samples too."""
    e = np.asarray(residuals, dtype=np.float64)
    n_z = e.shape[-1]
    finite = [np.isfinite(s).any() for s in jax.tree_util.tree_leaves(std)]
    if not any(finite):
        return
    e = e.reshape(-1, n_z)
    q = np.ones(n_z) if weight is None else np.asarray(weight, dtype=np.float64)
    if q.ndim == 2:
        var = _whitened_variances(e, q)
        if var is None:
            return
        names = [f"whitened output {j}" for j in range(var.size)]
    else:
        q = np.broadcast_to(q, (n_z,))
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an output with no sample: NaN
            var = np.array([np.nanmean(e[:, j] ** 2) * q[j] for j in range(n_z)])
        names = [f"output {j}" for j in range(n_z) if np.isfinite(var[j]) and q[j] > 0]
        var = var[np.isfinite(var) & (q > 0)]
    readings = {c: v for c, v in (readings or {}).items() if np.isfinite(v)}
    names += [f"the readings of output {c}" for c in readings]
    var = np.concatenate([var, list(readings.values())])
    # (an output reproduced exactly has no noise to compare: `_warn_exact_outputs`)
    names, var = [n for n, v in zip(names, var) if v > 0], var[var > 0]
    if var.size < 2 or var.max() <= 10 * var.min():
        return
    which = (
        "outputs"
        if not readings
        else f"outputs and aggregated readings ({names[int(np.argmax(var))]} the largest, "
        f"{names[int(np.argmin(var))]} the smallest)"
    )
    remedy = (
        'refit with weight="noise", which estimates it with theta (see the uncertainty guide)'
        if not readings
        else "each `Aggregate`'s `weight` about 1 / (its readings' noise variance), on the "
        'same scale; or weight="noise", which estimates both with theta'
    )
    warn(
        f"the weighted residuals of the {which} {UNEQUAL_NOISE} "
        f"{var.max() / var.min():.3g}: the standard errors pool one noise level over all "
        "outputs, so they hold only where `weight` is about 1 / (each output's noise "
        f"variance); {remedy}.",
        stacklevel=3,
    )


def _warn_exact_outputs(residuals, weight, outputs=None):
    """Warn where the fit reproduces an output of nonzero weight exactly at every measured
    sample while others keep a residual (a logged setpoint or flag that `observe` returns
    as it is): such an output carries no noise, so it is left out of the noise level
    sigma^2 of the standard errors (`_covariance.scale`) and of the printout's residual
    tests, and it makes the AIC and BIC -inf and the FPE 0 (the log determinant of the
    errors' covariance)."""
    e = np.asarray(residuals, np.float64)
    n_z = e.shape[-1]
    e = e.reshape(-1, n_z)
    seen = np.isfinite(e)
    q = np.ones(n_z) if weight is None else np.asarray(weight, np.float64)
    weighed = np.any(q != 0, axis=-1) if q.ndim == 2 else np.broadcast_to(q, (n_z,)) > 0
    measured = seen.any(axis=0) & weighed
    exact = measured & np.all((e == 0) | ~seen, axis=0)
    if not exact.any() or not (measured & ~exact).any():
        return
    labels = model_labels(outputs, n_z)
    listed = ", ".join(
        f"output {labels[j] if labels is not None else j}" for j in np.flatnonzero(exact)
    )
    warn(
        f"the fit reproduces {listed} exactly at every sample (a zero residual: a logged "
        "setpoint or flag the model returns as it is, say): it carries no noise, so it is "
        "left out of the noise level of the standard errors and of the residual tests, and "
        "it makes the AIC and BIC -inf and the FPE 0, which then compare no models; leave "
        "it out of `z` to compare models by them.",
        stacklevel=3,
    )


def _whitened_variances(e, Q):
    """The variances of the residuals whitened by a weight matrix Q: the eigenvalues of
    Q^{1/2} (mean of e e^T) Q^{1/2} on the range of Q (all equal where Q is the inverse
    noise covariance, correlated outputs too: each output's own mean(e_j^2) Q_jj is not),
    from the samples where every output is present; None with fewer such samples than
    outputs."""
    rows = e[np.all(np.isfinite(e), axis=1)]
    if rows.shape[0] <= e.shape[1]:
        return None
    lam, V = np.linalg.eigh(0.5 * (Q + Q.T))
    keep = lam > lam.max() * e.shape[1] * np.finfo(np.float64).eps
    W = V[:, keep] * np.sqrt(lam[keep])  # Q = W W^T on its range
    w = rows @ W
    return np.linalg.eigvalsh(w.T @ w / rows.shape[0])


def _flag_infeasible(result, projections, rtol=1e-8):
    """`result` with the stop reason `infeasible` where it reported a success at a theta
    that one of the general projection's sets does not hold: `projections` (`Built.sets`)
    projects onto each set it intersects (the projection onto an intersection, Dykstra's
    alternating projections of `constraints.combine` or of `FitProblem.feasible` with
    fixed entries, is capped at its cycles: sets that meet at a small angle need about
    1 / angle^2 of them, and on sets that do not meet it ends in the last set only), and
    a warning with the largest distance wherever one moves it. The distances are to the
    user's sets alone; with fixed entries held, the estimate can lie further from the set
    it was to be in. With several starts, each other start that reported a success is
    checked the same way (its stop in `result.starts`)."""

    def gap(theta):  # the largest distance to a set, or 0 within rtol of theta's size
        params, _ = _pytree.split(theta)
        a, _ = ravel_pytree(params)
        a = np.asarray(a, np.float64)
        out = 0.0
        for project in projections:
            b, _ = ravel_pytree(project(jax.tree_util.tree_map(jnp.asarray, params)))
            out = max(out, float(np.max(np.abs(a - np.asarray(b, np.float64)), initial=0.0)))
        return out if out > rtol * max(float(np.max(np.abs(a), initial=0.0)), 1.0) else 0.0

    if result.starts is not None:
        reasons = list(result.starts.stop_reason)
        for s, reason in enumerate(reasons):
            theta = jax.tree_util.tree_map(
                lambda a, s=s: a[s] if eqx.is_array(a) else a, result.starts.theta
            )
            if s != result.best and reason in SUCCESS and gap(theta):
                reasons[s] = "infeasible"
        if reasons != list(result.starts.stop_reason):
            starts = dataclasses.replace(result.starts, stop_reason=tuple(reasons))
            result = dataclasses.replace(result, starts=starts)
    distance = gap(result.theta)
    if not distance:
        return result
    demoted = result.success
    held = (
        " (with fixed entries held, the free ones can lie further from the set than "
        "that: the projection moves the fixed entries too)"
        if np.any(np.asarray(result.fixed, bool))
        else ""
    )
    warn(
        f"the estimate lies outside the constraint set: the projection moves it by "
        f"{distance:.3g}{held}. The projection onto the intersection of the sets (Dykstra's "
        "alternating projections, of a constraint list or of a projection with fixed "
        "entries) did not converge within its cycles (sets that meet at a small angle "
        "converge slowly; sets that do not meet never do), so the iterates were not "
        "feasible either"
        + (
            f"; the solver's {name_of(result.stop_reason)} is not a solution (status 'infeasible')"
            if demoted
            else ""
        )
        + ": check that the sets meet, write the set as one projection (keeping any fixed "
        "entries at their values), or write it in parameters of similar scale.",
        RuntimeWarning,
        stacklevel=3,
    )
    return _restated(result, "infeasible", infeasible=distance) if demoted else result


def _warn_projected(moved, names, theta0, starts=None, lower=None):
    """Warn that theta0 (a start) lay outside the constraint set, naming the parameters the
    projection moved; where theta holds a network, say that a scalar bound applies to its
    weights too; where a positive start lay below a positive lower bound (`positive()`'s
    eps of 1e-12, a parameter small in its units), name the bound. `starts` (S, p), `lower`
    (p,): the starts' free entries and their lower bounds (or None)."""
    per_start = np.atleast_2d(np.asarray(moved, bool))  # (S, p)
    moved = per_start.any(axis=0)
    if not moved.any():
        return
    below = None
    if starts is not None and lower is not None:
        starts, lower = np.atleast_2d(np.asarray(starts)), np.asarray(lower)
        tiny = per_start & (starts > 0) & (starts < lower) & (lower > 0)
        if tiny.any():
            i = int(np.flatnonzero(tiny.any(axis=0))[0])
            below = (names[i], float(starts[tiny[:, i], i][0]), float(lower[i]))
    counts = {}
    for name, m in zip(names, moved):
        if m:
            leaf = name.split("[")[0]
            counts[leaf] = counts.get(leaf, 0) + 1
    listed = ", ".join(f"{k} ({n})" if n > 1 else k for k, n in list(counts.items())[:6])
    if len(counts) > 6:
        listed += f" and {len(counts) - 6} more"
    if per_start.shape[0] > 1:  # a multistart fit: name the starts
        out = np.flatnonzero(per_start.any(axis=1)).tolist()
        shown = ", ".join(map(str, out[:10])) + (
            f", ... ({len(out)} in all)" if len(out) > 10 else ""
        )
        msg = (
            f"{len(out)} of the {per_start.shape[0]} starts (starts {shown}) lie outside the "
            f"constraint set; they were projected onto it (starts projected onto the same "
            f"point run the same fit): entries moved in {listed}."
        )
    else:
        msg = (
            f"theta0 lies outside the constraint set; it was projected onto it: "
            f"{int(moved.sum())} entries moved, in {listed}."
        )
    is_module = lambda a: isinstance(a, eqx.Module)  # noqa: E731
    # A network's weights: entries of a matrix ("[i, j]") the projection moved, in a theta
    # that holds a module (not a module of scalar physical parameters alone).
    weights = any(m and "," in n.rsplit("[", 1)[-1] for n, m in zip(names, moved) if "[" in n)
    if weights and any(is_module(a) for a in jax.tree_util.tree_leaves(theta0, is_leaf=is_module)):
        msg += (
            " A bound given for every parameter (positive(), box(lower=0)) holds a "
            "network's weights too; bound the physical parameters by name, e.g. "
            "box(lower={'k': 0.0}) for a dict theta, or with a pytree of theta's own "
            "structure holding None where unbounded (a module of bounds)."
        )
    if below is not None:
        name, value, bound = below
        msg += (
            f" The start {name} = {value:.3g} is positive but below its lower bound "
            f"{bound:.3g} (`constraints.positive()` bounds every parameter by eps = 1e-12): "
            "for parameters that small in their units, give a smaller bound "
            "(`positive(eps=...)`, `box(lower=...)`) or rescale them to order 1."
        )
    warn(msg, stacklevel=3)


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
    window=None,
    missing: str = "raise",
    validation=None,
    multistart: bool | dict = False,
    progress=False,
    history: int = 1000,
    units: dict[str, str] | None = None,
    aggregate=None,
    t: Float[ArrayLike, "*N T"] | None = None,
    covariance="classical",
    x0_bounds=None,
) -> FitResult:
    """Estimate theta and x0 by minimising the multi-step cost C of eq. (5)/(21).

    **Arguments:**

    - `model`: a `Model`.
    - `theta0`: the starting parameters, any pytree (it may hold equinox modules: their
        floating arrays are estimated; integer and boolean arrays, static fields and other
        parts are kept; outside a module, integers of NumPy or JAX and bools are kept
        with a warning). Python numbers, int or float, are parameters wherever they are
        (`{"k": 2}`), in a module's fields too: make a module's exponent or count a
        static field (`eqx.field(static=True)`) or a NumPy integer to keep it. With
        `multistart=True` every parameter leaf has a leading axis of starts.
    - `x0`: the starting initial state (n_x,), or (N, n_x) for N trajectories (with
        `window`, optionally one per window; with `multistart`, optionally with a leading
        axis of starts too, except with `window`).
    - `u`, `z`: inputs (T, n_u) and measured outputs (T, n_z), or (N, T, .) for N
        trajectories sharing theta, each with its own x0.
    - `solver`: a solver object (`LevenbergMarquardt()` by default, `GaussNewton`,
        `Adam`, `LBFGS`, `Optax(transform)`, `Optimistix(optx_solver)`), one of the names
        "levenberg_marquardt", "gauss_newton", "adam", "lbfgs" (default settings), an
        optax transform or optimistix solver (wrapped), or a sequence of these, run in
        order, each starting where the last stopped (e.g. `[Adam(), LBFGS()]`).
    - `weight`, `penalty`, `penalty_weight`: Q and h, lambda of eq. (4), (21), as for
        `loss`. The least-squares solvers need lambda h >= 0. `weight="noise"` estimates
        Q with theta (MATLAB's `OutputWeight` "noise"): fits alternate with Q set to the
        inverse covariance of the residuals (of the samples that measure outputs; where
        some sample measures some outputs only, the diagonal of each output's inverse
        mean squared residual), scaled to det Q = 1 without `aggregate` (the estimate
        does not depend on Q's scale; the loss keeps the size of the outputs'), until it
        settles, each warm-started (at most 10 fits; one where the first fit's residuals
        give Q = I, as one output's always do without `aggregate`; `result.weight` is
        the Q of the returned fit, None for the first's,
        `stop_info["noise_weight_rounds"]` the number of fits, `num_steps` and
        `wall_time` those of all fits together), so that the standard
        errors hold for outputs of unequal noise. With `aggregate`, each `Aggregate`'s
        weights get a factor alike, the inverse mean square of its readings' residuals
        on the same scale as Q (`stop_info["reading_weight_factors"]`, one per
        Aggregate, records in order); an output measured only in aggregate gets Q's
        entry 1. A weight that does not settle in the 10 fits, or runs away (outputs or
        readings the model fits exactly, whose weight grows without bound), ends with
        the stop `noise_weight_unsettled`, not a success.
    - `constraints`: a projection from `oneshot_jax.constraints` (`box`, `non_negative`,
        `positive`, `project`), or a list of them, on theta: every iterate lies in the
        intersection of their sets (Section 3.3; the projection onto an intersection of
        a general set with others, or with fixed entries, is Dykstra's, capped at its
        cycles: the estimate is checked against each set, and a success outside one
        becomes the status `infeasible`). A regulariser here (the mixed form of
        earlier releases) still works, with a DeprecationWarning: pass it as `regulariser`.
    - `regulariser`: a proximal regulariser from `oneshot_jax.sparsity` (`l1`,
        `group_lasso`, `l2`), or a list of them, on theta (their `where` is written on
        theta as given, modules included). A regulariser g makes the objective
        C + g(theta): `loss` and the history then report C + g. Only `Adam` (proximal
        Adam: the prox with its per-coordinate steps) and `Optax(transform)` (the prox
        with the regulariser's `learning_rate`) take one; the other solvers raise a
        ValueError. Each update applies the prox (a list's in the order `l1`,
        `group_lasso`, `l2`: see `constraints.combine`), then the projection.
    - `fixed`: a pytree of booleans shaped like theta0 (per leaf, per element, or one
        boolean for a whole subtree): True entries keep their starting value and are
        removed from the variables. Where theta0 is a dict, `fixed` may name some of its
        keys (`fixed={"b": True}`; a nested one as `{"phys": {"c": True}}` or
        `{"phys.c": True}`), or list the names of those it holds (`fixed=["b"]`,
        `fixed="phys.c"`; for an equinox module theta0, its fields' names): the others are
        free. For an array (in theta0) a list of booleans is its mask, as an array:
        `fixed=[True, False, False]` for theta0 = np.array([m, c, k]). A leaf held whole
        is a constant of the
        fit; an entry held inside a leaf is not, and a non-finite derivative with
        respect to it (x**n with respect to n at x < 0) reaches the others: hold such an
        exponent as a leaf of its own, or give it as an integer (data).
    - `estimate_x0`: False keeps x0 fixed; a (n_x,) boolean mask estimates some entries
        (the same entries of every record); on N records (without `window` or
        `aggregate`), a (N, n_x) mask estimates each record's own entries (MATLAB's
        `InitialStates(i).Fixed` per experiment: a record that starts at rest holds its
        x0, another estimates it). A held entry keeps its value in `x0`; it counts
        neither in the degrees of freedom nor in the covariance (its `x0_std` is 0). The
        mask per record is not available with `Optimistix` (its held entries are kept as
        a box of one point, and optimistix has no bounds); the (n_x,) mask is.
    - `x0_bounds`: `(lower, upper)` bounds on the estimated entries of x0 (MATLAB's
        `InitialStates(i).Minimum` and `Maximum`): each None (unbounded), a number, an
        array (n_x,) (every record's, or every window's, x0) or, without `window`,
        (N, n_x) (one row per record); -inf / inf (or None in a list) leave an entry
        unbounded, entries held by `estimate_x0` are not bounded. Every iterate lies in
        the box (a start outside it is clipped into it, with a warning), and the
        first-order test is that of the box: an entry at a bound that the gradient
        pushes outwards is stationary there.
        Not with `Optimistix` or `aggregate`. Where every record's box is the same, the
        initial states of `validation`'s records are estimated within it too. (A state
        that must stay in the model's domain along the whole trajectory, not only at the
        start, needs a penalty: `oneshot_jax.penalties.state_box`.)
    - `window`: cut one record into consecutive windows of this many samples, each with
        its own x0 (multiple shooting), or an `oneshot_jax.Windows` for some of them
        (every k-th, a number spread over the record, or given starts).
        `result.window_starts` says where each row of `result.x0` starts.
    - `missing`: `"raise"` (default) rejects NaN in z; `"mask"` takes NaN entries of z
        as missing samples (zero weight in the loss, the gradient and the Jacobian).
        Trajectories of different lengths (lists for `u` and `z`) are masked the same way.
        With `"mask"`, `result.predict` takes NaN in a new record's head as missing too.
    - `validation`: an `oneshot_jax.Validation(u, z, n=...)` of held-out records: every
        iterate of every solver is scored on them (x0 estimated from each record's first
        n outputs, the loss over the rest), the iterate with the lowest score is
        returned (stop reason `validation` where it is not the one the solver stopped
        at; a solution within one standard deviation of the lowest score ties with it
        and is kept, see `Validation`) and `Validation(patience=k)` stops a solver
        after k iterations without improvement. The scores are
        `result.history.validation`. Where no iterate scores a finite loss (the model
        blows up on the held-out records), they choose nothing: no patience is spent,
        the final loss ranks the starts, and `fit` warns.
    - `multistart`: several starts, run in the one compiled call; the start with the
        least final loss (with `validation`, the lowest score) is returned and
        `result.starts` reports each (a start stopped by `negative_penalty`, its loss
        not the sum of squares a least-squares solver minimises, only where all were).
        `True`: every parameter leaf of `theta0` carries a leading axis of starts. A dict
        starts some parts of theta only, the rest (an equinox network, say) theta0's own
        in every start: its keys name theta0's entries (nested as theta0's dicts; an
        equinox module's field names, a list's indices), each with its starts along a
        leading axis, e.g. `multistart={"phys": {"w0sq": jnp.array([1.0, 4.0, 9.0, 16.0])}}`
        (or `{"phys.w0sq": ...}`, the printout's name, as `fixed=` takes it).
        Every part given needs the same number S of starts, and a shape (S, *its shape);
        starts of a fixed entry that differ from its value are refused. `x0` starts by
        its own leading axis of starts (S, ...) (`multistart={}` for starts over x0
        alone; starts that differ in an entry `estimate_x0` holds are refused). With
        `weight="noise"` the starts run in its first fit (Q = I): `result.starts` reports
        that fit's losses and points, and the later fits refine the best start's. On a CPU
        the starts run in turn, each stopping on its own tests (`lax.scan`); on an
        accelerator side by side (vmapped), every start stepping until the last one stops
        (`benchmarks/multistart.py`).
    - `progress`: True shows a progress bar with the loss (tqdm), or a progress object
        (`oneshot_jax.TqdmProgress(refresh_steps=...)`).
    - `history`: the most rows of iterates each solver keeps (even, >= 2), besides its
        final iterate (a sequence of solvers keeps that many per solver); longer runs are
        thinned evenly (see `FitHistory`). Fewer where the rows' copies of theta would
        take more than 64 MiB (a theta of more than about 8000 entries in float64).
    - `units`: a unit string per parameter name of theta0 (its dict keys, `"phys.c"` or
        `{"phys": {"c": ...}}` for a nested one), e.g. `{"I": "kg m^2"}`, shown by
        `print(result)`.
    - `aggregate`: aggregated readings of some outputs, as for `loss` (an `Aggregate`,
        a list of them, or a list per trajectory); not with `window`, `validation` or
        `x0_bounds`. The readings count
        as observations in the covariance; the result's `x0`, `residuals` and `metrics`
        are those of the model's own states and outputs.
    - `t`: the sample times of a timed model's records (`Model.from_ode(rhs, dt=None)`),
        as for `simulate`: (T,), (N, T) or a list like `u`. With `window`, each window
        keeps its own intervals.
    - `covariance`: how `covariance` and the standard errors are computed:
        `"classical"`, sigma^2 (J^T J)^+ (white residuals), or `NeweyWest(lags)`
        (`"newey_west"`: its default lags), a sandwich that holds when the residuals are
        correlated in time (a model error); the result's `diagnostics["covariance"]`
        names it where it is not the classical one (`diagnostics.get("covariance",
        "classical")`). None (or `"none"`, MATLAB's `EstimateCovariance` false): not computed,
        which saves its time and memory where theta is large (the dense Jacobian and a
        p x p eigendecomposition) or the fit is an intermediate stage; `std` and `x0_std`
        are then inf, `covariance` empty and the printout says "(not computed)".

    **Staged training** (physics first, then a residual, then sparsity), each stage a
    `fit` that starts from the last one's result:

    1. the physical part alone: `fixed={"k": False, "c": False, "r": True}` holds the
       residual (a prefix pytree: one boolean for a whole module);
    2. jointly: `solver=[Adam(...), LevenbergMarquardt()]`;
    3. selection: `solver=Adam(lr_theta)` with `regulariser=sparsity.l1(lam, where)`;
    4. debiasing on the support: `solver=LevenbergMarquardt()` with
       `fixed=sparsity.fixed_zeros(result.theta, where)` (the deselected terms stay 0).

    **Returns:**

    A `FitResult`. After a fit of a `Model.from_ode` model, `fit` warns (RuntimeWarning)
    when the fitted model runs near its integrator's stability limit (`check_stability`).
    For a fit that converges with a low FIT, see `check_basin` and `fit_continuation`.
    Free parameters that never moved from the start because their gradient
    and Jacobian column are exactly zero there, though they act on the outputs a little
    away from it (a coupling started at 0), are named in a warning, and the stop reason
    is then `zero_gradient` (not a success); parameters without effect in a whole
    neighbourhood (the weights of a network's units that are dead over the data) are
    ones the data do not determine: their std is inf and a warning names them. A success
    whose simulation fits an output worse than its mean (FIT below 0, by more than the
    noise explains: below -450 / n % over its n measured samples) warns of a bad minimum.

    **JAX's debugging flags.** `fit` runs with `jax_debug_nans` and `jax_debug_infs` off
    (its compiled outputs hold NaN where a quantity does not exist: the history's rows
    after the last step, a solver's measures it does not have), so that the flags leave
    a fit as it is; to find where a model first makes a NaN, call `value_and_grad` or
    `simulate` at the point under the flag. Under `jax.disable_jit()` `fit` raises a
    RuntimeError: its solve is one compiled program (step through the model with
    `simulate` or `value_and_grad` there).
    """
    if jax.config.jax_disable_jit:
        raise RuntimeError(
            "`fit` does not run under `jax.disable_jit()` (or jax_disable_jit): its solve "
            "is one compiled program, whose loop state is traced. To step through the model "
            "(print, a debugger), call `oneshot_jax.simulate` or `value_and_grad` under it, "
            "and `fit` outside it."
        )
    if jax.config.jax_debug_nans or jax.config.jax_debug_infs:
        # (the library's own NaN, where a quantity does not exist, are no model's NaN)
        with jax.debug_nans(False), jax.debug_infs(False):
            return fit(**locals())
    with recording() as record:
        if isinstance(weight, str):
            if weight != "noise":
                raise ValueError(
                    f'`weight` must be None, an array (Q of eq. 4) or "noise" (Q estimated '
                    f"from the residuals), got {weight!r}."
                )
            result = fit_noise_weighted(
                fit, {k: v for k, v in locals().items() if k not in ("weight", "record")}
            )
            return dataclasses.replace(result, warnings=tuple(record.messages))
        check_window(aggregate, window)
        robust = as_covariance(covariance)
        if isinstance(robust, NeweyWest) and penalty is not None:
            raise ValueError(
                "`covariance=NeweyWest(...)` is not available with `penalty`: the penalty's "
                'rows are not observations; use covariance="classical".'
            )
        if aggregate is not None and validation is not None:
            raise ValueError(
                "`validation` with `aggregate` is not supported: score the held-out records "
                "after the fit (`oneshot_jax.loss` takes `aggregate=`)."
            )
        inputs = check_inputs(
            model,
            theta0,
            x0,
            u,
            z,
            solver=solver,
            weight=weight,
            penalty=penalty,
            penalty_weight=penalty_weight,
            window=window,
            missing=missing,
            multistart=multistart,
            progress=progress,
            history=history,
            units=units,
            t=t,
            readings=aggregate is not None,
        )
        history = int(history)  # (checked: a NumPy integer or an integral float too)
        estimate_x0, x0_held = record_x0_mask(
            estimate_x0,
            np.shape(inputs.data.x0) if inputs.data.batched else (1, np.shape(inputs.data.x0)[-1]),
            windowed=inputs.window_starts is not None,
            aggregated=aggregate is not None,
        )
        _warn_held_window_states(window, x0, estimate_x0, inputs.window_starts, model)
        if aggregate is not None:  # the readings as accumulator states (`_aggregate`)
            agg = augment(inputs.data, aggregate, model, x0, missing, t=t)
            inputs = check_inputs(
                agg.model,
                theta0,
                agg.x0,
                agg.u,
                agg.z,
                solver=solver,
                weight=agg.weight,
                penalty=agg.penalty(penalty),
                penalty_weight=penalty_weight,
                window=window,
                missing="mask",
                multistart=multistart,
                progress=progress,
                history=history,
                units=units,
            )
            estimate_x0 = agg.x0_mask(estimate_x0)
        if x0_bounds is not None and aggregate is not None:
            raise ValueError(
                "`x0_bounds` with `aggregate` is not supported: bound the states by a penalty "
                "(`oneshot_jax.penalties.state_box`)."
            )
        built = build_problem(
            inputs,
            fixed=fixed,
            estimate_x0=estimate_x0,
            constraints=constraints,
            regulariser=regulariser,
            validation=validation,
            x0_bounds=x0_bounds,
            x0_held=x0_held,
        )
        lags = NOT_COMPUTED if robust is NOT_COMPUTED else None
        if isinstance(robust, NeweyWest):
            lengths = inputs.data.lengths
            lags = robust.resolved(
                int(built.problem.u.shape[1]), None if lengths is None else int(min(lengths))
            )
        # A `Model.from_ode` model near its integrator's stability limit (`_stability`): the
        # Jacobians along the fitted trajectory come from the solve's compiled call.
        rhs = rhs_of(model, inputs.data) if aggregate is None else None
        idx = None if rhs is None else sample_points(inputs.data, timed=model.timed)
        stability_at = None if idx is None else (rhs, idx, step_weights(inputs.data, model.step))
        out, wall, diagnostics, jacobians, prepared = _run(
            inputs.solvers,
            built.problem,
            built.starts,
            history,
            inputs.meter,
            stability_at,
            meanwhile=lambda: prepare(
                data=inputs.data,
                problem=built.problem,
                solvers=inputs.solvers,
                fixed=built.fixed,
                # (with a mask per record, that mask: the union less what each record holds)
                x0_estimated=built.x0_estimated
                if x0_held is None
                else built.x0_estimated & ~x0_held,
                theta_order=_theta_order(theta0),
                units=inputs.units,
            ),
            lags=lags,
        )
        if lags == NOT_COMPUTED:
            diagnostics = {**diagnostics, "covariance": NOT_COMPUTED}
        elif lags is not None:
            diagnostics = {**diagnostics, "covariance": "newey_west", "covariance_lags": lags}
        _warn_projected(out.moved, prepared.names, theta0, built.starts.theta, built.problem.lower)
        result = assemble(
            prepared=prepared,
            model=model,
            problem=built.problem,
            data=inputs.data,
            out=out,
            wall_time=wall,
            multistart=inputs.n_starts is not None,
            diagnostics=diagnostics,
            window_starts=inputs.window_starts,
            n_u=int(np.shape(u[0] if isinstance(u, (list, tuple)) else u)[-1]),
        )
        strategy = getattr(inputs.solvers[-1], "strategy", "auto")
        # The checks of the result after the solve (a Newton step, a Gauss-Newton step in low
        # precision, ...: programs of their own on a first call) count in its wall time.
        checking = time.perf_counter()
        # (their rollouts are the checks', not the fit's: counted apart, no second warning)
        with counting():
            max_steps = getattr(inputs.solvers[-1], "max_steps", None)
            result = _flag_hidden_outputs(result, built.problem, max_steps)
            result = flag_zero_gradient(
                result,
                built.problem,
                built.starts,
                out.theta,
                strategy,
                finals=out.start_theta,
                finals_x0=out.start_x0,
            )
            result = _flag_unconverged_rollouts(
                result,
                built.problem,
                out.theta,
                out.x0,
                strategy,
                finals=Params(out.start_theta, out.start_x0),
            )
            result = _flag_refuted_stop(result, built.problem, out, strategy, max_steps)
            result = _flag_plateau_above_start(
                result, built.problem, built.starts, int(out.best), strategy
            )
            result = _flag_every_column_vanished(result, built.problem)
            least_squares = isinstance(inputs.solvers[-1], AbstractLeastSquares)
            result = _flag_unresolved_success(result, built.problem, out, strategy, least_squares)
            result = _settle(result, built.problem, out, strategy, least_squares)
            result = _measure_unmeasured_success(result, built.problem, out, strategy)
            result = _measure_validated_point(result, built.problem, out, strategy)
            result = _flag_hidden_outputs(result, built.problem, max_steps)
        wall += time.perf_counter() - checking
        readings = None
        if aggregate is not None:
            readings = agg.reading_mean_squares(result)
            result = agg.restore(result)
        result = _flag_diverged_stages(result)
        if result.validation_loss is not None and not np.isfinite(result.validation_loss):
            warn(
                "`validation`: no iterate scored a finite validation loss (the model blows up "
                "on the held-out records, or their head estimate fails): the held-out data "
                "chose nothing, and the result is the solvers' own.",
                RuntimeWarning,
                stacklevel=2,
            )
        result = dataclasses.replace(
            result,
            theta=_pytree.ordered_like(result.theta, theta0),
            std=_pytree.ordered_like(result.std, theta0),
        )
        if built.problem.regulariser is not None and result.covariance.size:
            # (`FitResult.__str__` says what its standard errors are then)
            result = dataclasses.replace(
                result, diagnostics={**(result.diagnostics or {}), "regularised": True}
            )
        if penalty is not None and result.covariance.size:  # (likewise)
            result = dataclasses.replace(
                result, diagnostics={**(result.diagnostics or {}), "penalised": True}
            )
        if missing == "mask":  # (`result.predict` takes the head's NaN as missing too)
            result = dataclasses.replace(result, missing="mask")
        if weight is not None:  # (the default of `result.predict`'s x0 estimate)
            q = np.asarray(weight, result.x0.dtype)  # (a scalar: one output's (1,) diagonal)
            result = dataclasses.replace(result, weight=q.reshape(1) if q.ndim == 0 else q)
        _warn_narrowed_outputs(
            z, result.residuals, built.problem.dtype, getattr(model, "outputs", None)
        )
        if result.status != "zero_residual":  # (round-off residuals have no noise level)
            _warn_unequal_noise(result.residuals, weight, result.std, readings)
            _warn_exact_outputs(result.residuals, weight, getattr(model, "outputs", None))
        else:  # (how close to round-off: float32's limit, sqrt(eps), is 3.5e-4 of the outputs)
            nrmse = weighed(result.metrics.get("nrmse"), weight)  # (weight 0: not fitted)
            if np.isfinite(nrmse).any():
                info = {**result.stop_info, "residual_nrmse": float(np.nanmax(nrmse))}
                result = dataclasses.replace(result, stop_info=info)
        if built.x0_box is not None:  # (the box as `result.x0`'s shape: `predict` keeps it)
            box = tuple(b.reshape(np.shape(result.x0)) for b in built.x0_box)
            result = dataclasses.replace(result, x0_bounds=box)
        if built.problem.project is not None:  # (Dykstra's cycles are capped: check the estimate)
            result = _flag_infeasible(result, built.sets)  # (before a success is read below)
        # (Not with a regulariser or a penalty: their optimum may fit worse than the mean,
        # all-zero terms, say.)
        worst = worst_fit(result.metrics.get("fit_percent"), weight, result.residuals)
        if result.success and worst is not None and regulariser is None and penalty is None:
            held = "" if constraints is None else ", or constraints that keep it from the data"
            warn(
                f"the fit reports {result.status}, but its simulation fits an output worse than "
                f"that output's mean (FIT {worst:.3g} %): most often a bad minimum of the "
                f"simulation error (or a model that cannot describe these data{held}). "
                "`oj.check_basin(result, u, z)` compares it with a fit over short windows, "
                "each from its own x0; `oj.fit_continuation` starts from such windows.",
                RuntimeWarning,
                stacklevel=2,
            )
        if stability_at is not None:
            warn_after_fit(model.step, *jacobians, u=inputs.data.u, stacklevel=2)
        elif aggregate is not None and (window is None or not model.timed):
            # (with windows, the windows' records: for a timed model they carry their
            # intervals already, which `stability` would take for an input)
            checking = time.perf_counter()
            fitted_u, fitted_t = (u, t) if window is None else (inputs.data.u, None)
            report = stability(model, result.theta, result.x0, fitted_u, t=fitted_t)
            warn_if_near_limit(report, stacklevel=2)
            wall += time.perf_counter() - checking
        return dataclasses.replace(result, wall_time=wall, warnings=tuple(record.messages))
