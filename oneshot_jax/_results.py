"""Why a fit stopped: one enumeration whose members carry their messages."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class RESULTS(eqx.Enumeration):
    """Why a fit stopped (`FitResult.stop_reason`). `RESULTS[item]` is the message;
    `FitResult.success` is True for `converged`, `statistically_converged`,
    `zero_residual`, `tol_loss` and `tol_grad` only: the first three are tests of
    optimality at the returned point, the last two the user's thresholds (the message then
    says whether the first-order test holds there too).
    `FitResult.message` adds the values the test fired on."""

    converged = (
        "first-order optimality: the scaled projected gradient (the largest cosine between "
        "the residual and a Jacobian column, 0 at a constrained stationary point) is at "
        "most the solver's gtol, or at most its round-off limit where no step can decrease "
        "the loss any further (float32, or a tight gtol)"
    )
    zero_residual = (
        "zero residual: the loss is at the round-off level of the data, where no step can "
        "decrease it further: the model reproduces the outputs to within sqrt(eps) of their "
        "variation (a residual RMS of 1.5e-8 of it in float64, 3.5e-4 in float32) plus the "
        "outputs' own round-off (an RMS of 10 eps |z|: larger for an output far above its "
        "variation, a pressure of 1e5 Pa in float32), where the loss cannot tell noise from "
        "round-off"
    )
    tol_loss = "the loss fell below tol_loss (the paper's epsilon)"
    tol_grad = "the gradient norm fell below tol_grad (the paper's delta)"
    max_steps_reached = (
        "reached the solver's max_steps before the first-order test held: not a "
        "stationary point yet; raise max_steps (or the learning rates), or start a second "
        "solver where this one stopped"
    )
    stalled = (
        "stalled: the step or the predicted decrease reached round-off (or the optional "
        "step test rtol/atol fired), but the point is not stationary (the first-order "
        "measure is above gtol); this is not a solution. "
        "Check the scaling of the problem (an output with a large offset, 1e4 around a "
        "noise of 1e-4, leaves the loss too few digits: subtract it from the data "
        "first); bounds that keep the model stable, windows (multiple shooting) or a "
        "better start help. A model that is not differentiable there (abs, sign, clip, "
        "max, a switching mode: a kink, where the measure need not reach zero even at a "
        "minimum) stops so too"
    )
    no_progress = (
        "no step decreased the loss any more (the damping or the line search gave up, "
        "or a wrapped optimistix solver reported a failed step: a linear solve that "
        "returned NaN on a rank-deficient Jacobian, say) before the first-order test "
        "held; check the scaling of the problem (a large "
        "output offset leaves the loss too few digits: subtract it) or try another solver "
        "or starting point; at a point where the model is not differentiable (abs, sign, "
        "clip, max, a switching mode: a kink) no test of a derivative can hold"
    )
    diverged = (
        "the simulation diverged (a non-finite loss or gradient); the last finite iterate "
        "is returned (Levenberg-Marquardt and Gauss-Newton accept finite losses only: "
        "their last accepted point, where the gradient may be the non-finite one). "
        "Bounds that keep the model stable, windows (multiple shooting) or a "
        "better start help"
    )
    infeasible = (
        "after the solve: the solver stopped with a success, but the estimate lies outside "
        "the constraint set (the user's projection moves it): the projection onto an "
        "intersection (Dykstra's alternating projections, of `constraints.combine` or of a "
        "general projection with fixed entries) did not converge within its cycles (or the "
        "sets do not meet), so the iterates were not feasible and the test was judged at a "
        "point that is not a solution. Check that the sets meet; write the set as one "
        "projection (one that keeps the fixed entries at their values), or in parameters of "
        "similar scale"
    )
    validation = (
        "the iterate with the lowest validation loss (held-out data, `fit(validation=...)`), "
        "returned instead of the point the solver stopped at (or stopped early after "
        "`patience` iterations without improvement): not a stationary point of the "
        "training loss"
    )
    negative_penalty = (
        "lambda h(x, theta) became negative; the least-squares solvers need a non-negative "
        "penalty (they minimise a sum of squares that includes sqrt(lambda h)): use a "
        "non-negative h, or a first-order solver (Adam, LBFGS), which accept any sign"
    )
    zero_gradient = (
        "some free parameters had an exactly zero gradient and Jacobian column at the start "
        "and never moved: the start is a point where they have no effect on the outputs "
        "(a coupling or gain started at 0, say, or a network's unit saturated, its tanh "
        "at +-1 to the precision over the whole record), so they were not estimated. "
        "Start them away from that point (a saturated unit: smaller weights, or inputs "
        "scaled to order 1), or fix them. Where none of the parameters and initial "
        "states has a gradient there (`stop_info['no_effect']`), the model's outputs may "
        "be piecewise constant in them (rounded, cast to integers, compared with a "
        "threshold): keep such steps out of the model that is fitted"
    )
    statistically_converged = (
        "statistical convergence: where the Jacobian's theta columns have a null space "
        "once the initial states are fitted (an "
        "over-parameterised model, such as a network, on which the first-order test "
        "converges too slowly to be reached), the last accepted least-squares step, its "
        "predicted decrease confirmed by the actual one, changed the fit by at most the "
        "solver's stol standard errors, no parameter alone would move by a standard error, "
        "and the undamped Gauss-Newton step is within sqrt(rank J) standard errors; where "
        "they have full rank but no step lowers the loss at its round-off any more (an "
        "output offset far above the noise leaves the loss too few digits to confirm the "
        "last ones), the undamped Gauss-Newton step from the returned point is within stol "
        "standard errors and no parameter alone would move by one, and so is the Newton "
        "step with the loss's own curvature, checked after the solve (for a first-order "
        "solver's stall, that step alone, within 0.01). Either way no quantity "
        "the data determine can still change significantly (see "
        "`oneshot_jax._optimality.standard_errors`)"
    )
    unconverged_rollout = (
        "parallel rollouts of the fit did not converge and `ParallelInTime(fallback=False)` "
        "kept Newton's best iterate: the loss, gradients and stop were computed from "
        "states that are not the model's, so the solver's own stop is no evidence of a "
        "solution. Use the default fallback=True (the sequential loop where a rollout does "
        "not converge), or a sequential strategy"
    )
    noise_weight_unsettled = (
        "`weight='noise'`: the estimated output weight did not settle: its alternation of "
        "fits and re-estimated weights ran its rounds without converging, or ran away (a "
        "weight grew without bound while the residuals it weighs fell to zero: outputs or "
        "readings the model can fit exactly, whose noise level the data cannot tell). The "
        "estimate is the last fit's, a solution for that fit's weights, not the fixed "
        "point of `weight='noise'`: give the weight (`fit(weight=Q)`, "
        "`Aggregate(weight=...)`)"
    )


SUCCESS = ("converged", "statistically_converged", "zero_residual", "tol_loss", "tol_grad")


def _index(item) -> int:
    """The integer of a concrete enumeration item: its one pytree leaf."""
    (value,) = jax.tree_util.tree_leaves(item)
    return int(np.asarray(value))


def _members(enumeration) -> dict:
    """An equinox enumeration's items by name, in the order they are declared.

    Equinox (0.13) has no public way to list them: they are kept in the class's
    `_name_to_item` (equinox/_enum.py). This is the one read of that private attribute;
    an item's integer is read through the public pytree API (`_index`)."""
    return dict(enumeration._name_to_item)


_BY_NAME = _members(RESULTS)
_BY_INDEX = {_index(item): item for item in _BY_NAME.values()}
_NAME_BY_INDEX = {_index(item): name for name, item in _BY_NAME.items()}


def name_of(item) -> str:
    """The member name of a concrete `RESULTS` item (e.g. "converged")."""
    name = _NAME_BY_INDEX.get(_index(item))
    if name is None:
        raise ValueError(f"not a RESULTS item: {item!r}")
    return name


def from_name(name: str):
    """The `RESULTS` item called `name`."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown stop reason {name!r}; valid: {', '.join(_BY_NAME)}.") from None


def is_success(item) -> bool:
    return name_of(item) in SUCCESS


def succeeded(item):
    """Whether a `RESULTS` item, concrete or traced (one per start), is a success
    (`SUCCESS`): a boolean array."""
    return functools.reduce(jnp.logical_or, [item == from_name(name) for name in SUCCESS])


def from_index(index: int):
    """The `RESULTS` item with integer value `index`."""
    member = _BY_INDEX.get(int(index))
    if member is None:
        raise ValueError(f"no RESULTS item has index {index}.")
    return member
