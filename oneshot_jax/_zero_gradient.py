"""Parameters a fit left where they started because they have no effect there.

A parameter whose gradient and Jacobian column are exactly zero at the start (a coupling
or a gain started at 0 that multiplies another one at 0) gives every solver nothing to
move it by: the fit returns it unchanged, and a first-order test at the returned point
passes, although a little away from the start it does act on the outputs.
`flag_zero_gradient` finds these on the host after the solve, from what the solve
returned (the entries of the best start that never moved) and, only where some never
moved, one evaluation of the gradient (eq. 17, 20) at the start and, only where it is
exactly zero for some of them, one of their Jacobian columns at the start and a little
away from it; it warns, naming them, and makes the stop reason
`zero_gradient`. The compiled solve is unchanged. A parameter without effect away from
the start too, and every parameter of a fit that reproduces the outputs exactly
(`zero_residual`), is one these data do not determine, which the covariance reports
(std inf): not a start to move from. The exception is a success where nothing moved and
the gradient of every free entry of theta and x0 is exactly zero while the loss changes
a little away from the start (`_no_effect`): outputs piecewise constant in them (a
rounding sensor), which no solver can fit; the stop is then `zero_gradient` too, with
`stop_info["no_effect"]`. Outputs that depend on none of them keep their success: their
loss is the same everywhere. A success that left a parameter (not a network's weight)
where its column is zero there and a little away, though not at points further away
(`acting_elsewhere`: its start times 0.01 to 10, -1, plus or minus 1 and 10), keeps its
success too, a flat local minimum, but names it (`stop_info["without_effect"]`) and warns:
the start lies on a flat piece of the model (a saturation above the data's range).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._caller_warnings import warn
from ._fit_report import without_effect_note
from ._fit_result import stop_detail
from ._jit import jit
from ._problem import Params
from ._results import RESULTS, SUCCESS, name_of

# How far the entries are moved from the start to see whether they act away from it:
# relative to their size, at least this much (any nonzero move shows a product of them).
_AWAY = 1e-3


def _columns(problem, params, entries, strategy):
    """The Jacobian columns of the free entries `entries` of theta at `params` (the
    forward sensitivity recursion), (k, N * R)."""
    _, _, traj = problem.linearise(params, strategy)
    zeros_x = jnp.zeros_like(params.x0)

    def column(i):
        e = jnp.zeros_like(params.theta).at[i].set(1.0)
        return problem.jvp(params, traj, e, zeros_x, strategy).reshape(-1)

    return jax.vmap(column)(entries)


@jit
def _moved_losses(problem, params, strategy):
    """The loss with every free entry of theta and x0 moved together by 1e-3, 1e-2 and
    1e-1 of its size (at least of 1), up and down, in two patterns of signs (all alike,
    alternating), each within the box: (12,)."""

    def moved(v, size, sign, pattern):
        signs = jnp.where(pattern & (jnp.arange(v.size) % 2 == 1), -sign, sign)
        return v + size * signs.reshape(v.shape) * jnp.maximum(jnp.abs(v), 1.0)

    def loss(size, sign, pattern):
        theta = moved(params.theta, size, sign, pattern)
        x0 = moved(params.x0, size, sign, pattern)
        if problem.constrained:
            theta = problem.feasible(theta)
        if problem.x0_bounded:
            x0 = problem.feasible_x0(x0)
        return problem.loss(Params(theta, x0), strategy)

    grid = [(a, b, c) for a in (1e-3, 1e-2, 1e-1) for b in (1.0, -1.0) for c in (False, True)]
    return jnp.stack([loss(a, b, c) for a, b, c in grid])


@jit
def _value_and_gradient(problem, params, strategy):
    """The loss and its gradient (eq. 17, 20) in the free entries of theta and x0 at
    `params` (one compiled program for both checks)."""
    return problem.value_and_grad(params, strategy)


@jit
def _stuck(problem, params, entries, valid, moving, strategy):
    """Whether each free entry `entries` of theta (where `valid`; the others pad the
    array to a size that is compiled once, `_padded`), all of an exactly zero gradient
    at `params` (`_value_and_gradient`), has an exactly zero Jacobian column there too,
    and one that is not zero once the entries `moving` ((p,) booleans: all those checked,
    in every part of them, `_chunks`) are all moved a little away from it, up or down
    within the box (not zero, or not finite: it acts away from the start); and whether
    it has an exactly zero column there and at both moved points (no effect around the
    start). The columns at the start and at the two moved points are one vmapped
    evaluation (one copy of the sensitivities to compile)."""
    values = params.theta[entries]
    step = jnp.where(moving, _AWAY * jnp.maximum(jnp.abs(params.theta), 1.0), 0.0)
    # Both ways (relu(-k) acts below a start at 0 only), each within the box.
    signs = jnp.array([0.0, 1.0, -1.0], values.dtype)
    thetas = jax.vmap(lambda sgn: params.theta + sgn * step)(signs)
    cols = jax.vmap(
        lambda theta: _columns(problem, params._replace(theta=theta), entries, strategy)
    )(thetas)
    zero = valid & jnp.all(cols[0] == 0, 1)
    acts = jnp.zeros(values.shape, bool)
    for k in (1, 2):
        moved = thetas[k][entries]
        inside = jnp.ones(values.shape, bool)
        if problem.lower is not None:
            inside = (moved >= problem.lower[entries]) & (moved <= problem.upper[entries])
        c = cols[k]
        acts = acts | (inside & (jnp.any(c != 0, 1) | ~jnp.all(jnp.isfinite(c), 1)))
    return zero & acts, zero & ~acts


# Where an entry without effect around its start is tried further away (`_acts_elsewhere`):
# its start times these factors, and these offsets from it.
_FACTORS = (2.0, 10.0, 0.5, 0.1, 0.01, 0.0, -0.01, -0.1, -1.0)
_OFFSETS = (1.0, -1.0, 10.0, -10.0)


@jit
def _acts_elsewhere(problem, params, entries, valid, moving, strategy):
    """For the free entries `entries` of theta (where `valid`, as for `_stuck`), without
    effect around `params`: the values they are tried at further away (`_FACTORS` times
    them, `_OFFSETS` from them, with all the entries `moving` moved alike), (n_points, k),
    and whether each one's Jacobian column is finite and not zero there, within the box
    (it acts there: the start lies on a flat piece of the model, a saturation above the
    data's range, say)."""
    theta = params.theta
    factors = jnp.asarray(_FACTORS, theta.dtype)[:, None]
    offsets = jnp.asarray(_OFFSETS, theta.dtype)[:, None]
    thetas = jnp.concatenate([factors * theta[None, :], theta[None, :] + offsets])
    thetas = jnp.where(moving, thetas, theta)
    cols = jax.vmap(lambda t: _columns(problem, params._replace(theta=t), entries, strategy))(
        thetas
    )
    tried = thetas[:, entries]
    inside = jnp.ones(tried.shape, bool)
    if problem.lower is not None:
        inside = (tried >= problem.lower[entries]) & (tried <= problem.upper[entries])
    finite = jnp.all(jnp.isfinite(cols), axis=-1)
    return tried, valid & inside & finite & jnp.any(cols != 0, axis=-1)


def _padded(unmoved, p, size=None):
    """`unmoved` (k entries of p) padded by repeating its first entry to a size that
    changes rarely (8, then powers of two, at most p; or `size`), so that the checks of
    fits and starts with different counts of unmoved entries share one compiled
    `_stuck`; and the mask of the real entries."""
    if size is None:
        size = min(p, max(8, 1 << (len(unmoved) - 1).bit_length()))
    entries = np.full(size, unmoved[0], unmoved.dtype)
    entries[: len(unmoved)] = unmoved
    return entries, np.arange(size) < len(unmoved)


# The most entries of Jacobian columns one evaluation of the checks holds (columns times
# the record's N T n_z, each at 3 points or more): a network's dead units leave hundreds
# of unmoved entries, whose columns of a long record at once ran out of memory after
# the solve had finished.
_COLUMN_ENTRIES = 2**21


def _chunks(flat, problem, p, points):
    """`flat` (the entries to check) in parts of at most a power of two of entries whose
    columns at `points` points hold at most `_COLUMN_ENTRIES` numbers (at least 1), each
    padded (`_padded`: all parts but a single one to that one size, one compiled check)."""
    rows = max(int(np.prod(np.shape(problem.z))), 1) * points
    cap = 1 << max(int(_COLUMN_ENTRIES // rows).bit_length() - 1, 0)
    if len(flat) <= cap:
        yield flat, _padded(flat, p)
        return
    for i in range(0, len(flat), cap):
        part = flat[i : i + cap]
        yield part, _padded(part, p, cap)


def zero_gradient_entries(
    problem, start: Params, final_theta, strategy, *, without_effect=False
) -> np.ndarray:
    """The free entries of theta (indices into `problem.theta_free`) that never moved from
    `start`, whose gradient and Jacobian column are exactly zero there, and which act on
    the outputs a little away from it (a parameter that acts nowhere is one the data do not
    determine, which the covariance reports).

    **Arguments:**

    - `problem`: the fit's `FitProblem`.
    - `start`: the best start's free variables (theta (p,), x0 (N, m)).
    - `final_theta`: the free entries of theta the fit returned (p,).
    - `strategy`: the strategy of the derivatives.
    - `without_effect`: also return the unmoved entries whose Jacobian column is exactly
        zero at the start and a little away from it (no effect around the start).

    **Returns:** the indices, a NumPy integer array (empty for an ordinary fit); with
    `without_effect`, a pair of them.
    """
    unmoved = np.flatnonzero(np.asarray(final_theta) == np.asarray(start.theta))
    none = (unmoved[:0], unmoved[:0]) if without_effect else unmoved[:0]
    if not unmoved.size:  # every free entry moved: nothing to evaluate
        return none
    params = Params(jnp.asarray(start.theta), jnp.asarray(start.x0))
    # The gradient first (one reverse pass): an entry held where it is not flat (at a
    # bound, say) needs no Jacobian columns.
    gradient = _value_and_gradient(problem, params, strategy)[1].theta
    flat = unmoved[np.asarray(gradient)[unmoved] == 0]
    if not flat.size:
        return none
    stuck, idle = [], []
    moving = np.zeros(np.size(start.theta), bool)
    moving[flat] = True
    for part, (entries, valid) in _chunks(flat, problem, np.size(start.theta), 3):
        s, i = _stuck(problem, params, jnp.asarray(entries), valid, moving, strategy)
        stuck.append(part[np.asarray(s)[: len(part)]])
        idle.append(part[np.asarray(i)[: len(part)]])
    stuck, idle = np.concatenate(stuck), np.concatenate(idle)
    return (stuck, idle) if without_effect else stuck


def acting_elsewhere(problem, start: Params, idle, strategy) -> dict:
    """Of the free entries `idle` of theta (indices into `problem.theta_free`) without
    effect around `start` (`zero_gradient_entries(..., without_effect=True)`), those that
    act further away (`_acts_elsewhere`): {index: the first value tried where it acts}.
    The others act nowhere tried: the data do not determine them (the covariance says
    so), not a start to move from."""
    params = Params(jnp.asarray(start.theta), jnp.asarray(start.x0))
    out = {}
    points = len(_FACTORS) + len(_OFFSETS)
    moving = np.zeros(np.size(start.theta), bool)
    moving[np.asarray(idle)] = True
    for part, (entries, valid) in _chunks(np.asarray(idle), problem, np.size(start.theta), points):
        tried, acts = _acts_elsewhere(
            problem, params, jnp.asarray(entries), valid, moving, strategy
        )
        tried, acts = np.asarray(tried), np.asarray(acts)
        for j, i in enumerate(part):
            if acts[:, j].any():
                out[int(i)] = float(tried[np.flatnonzero(acts[:, j])[0], j])
    return out


def _starts_flagged(result, problem, starts: Params, finals, strategy):
    """`result` with `zero_gradient` as the stop of each start other than the best that
    reported a success while some free entries never moved from where their gradient and
    Jacobian column are exactly zero (`zero_gradient_entries`): a multistart listed such
    a start as `statistically_converged` where a fit from it alone says `zero_gradient`."""
    if result.starts is None or finals is None:
        return result
    reasons = list(result.starts.stop_reason)
    finals = np.asarray(finals)
    for s, reason in enumerate(reasons):
        # (zero_residual: the outputs reproduced exactly, as for the best start below)
        if s == result.best or reason not in SUCCESS or reason == "zero_residual":
            continue
        if not (finals[s] == np.asarray(starts.theta[s])).any():
            continue
        start = Params(starts.theta[s], starts.x0[s])
        if zero_gradient_entries(problem, start, finals[s], strategy).size:
            reasons[s] = "zero_gradient"
    if reasons == list(result.starts.stop_reason):
        return result
    return _with_stops(result, reasons)


def _with_stops(result, reasons):
    """`result` with the starts' stop reasons `reasons`."""
    return dataclasses.replace(
        result, starts=dataclasses.replace(result.starts, stop_reason=tuple(reasons))
    )


def _flag_without_effect(result, acting):
    """`result` with `stop_info["without_effect"]`, the free entries of theta that a
    success left at their start, where their Jacobian columns are exactly zero and stay
    zero a little away, though they act further away (`acting`: {name: a value where it
    acts}), and a warning: the start lies on a flat piece of the model (a saturation
    above the data's range, a relu or a dead zone that is off), where a first-order test
    passes though elsewhere they act."""
    names = list(acting)
    warn(f"{without_effect_note(names, acting)}.", RuntimeWarning, stacklevel=4)  # (fit's caller)
    return dataclasses.replace(result, stop_info={**result.stop_info, "without_effect": names})


def _no_effect(problem, start: Params, final_theta, final_x0, strategy) -> bool:
    """Whether no free entry of theta or x0 moved from `start`, where the gradient (eq.
    17, 20) of every one of them is exactly zero (with a loss that is not): the outputs
    do not change with anything the fit estimates there (piecewise-constant outputs, from
    a `jnp.round`, an integer cast or a comparison in the model, have a zero derivative
    everywhere), so a first-order test passes at a point that no solver could leave."""
    if not (np.asarray(final_theta) == np.asarray(start.theta)).all():
        return False
    if final_x0 is not None and not (np.asarray(final_x0) == np.asarray(start.x0)).all():
        return False
    params = Params(jnp.asarray(start.theta), jnp.asarray(start.x0))
    value, grads = _value_and_gradient(problem, params, strategy)
    if not np.isfinite(value) or value == 0:
        return False
    if np.asarray(grads.theta).any() or np.asarray(grads.x0).any():
        return False
    # Outputs that do not depend on any of them at all: the loss is the same everywhere,
    # and the start one of its minima (a success). Piecewise-constant ones change it.
    moved = np.asarray(_moved_losses(problem, params, strategy))
    return bool(np.any(np.isfinite(moved) & (moved != np.asarray(value))))


def flag_zero_gradient(
    result, problem, starts: Params, theta_flat, strategy, finals=None, finals_x0=None
):
    """`result`, with the stop reason `zero_gradient` and a warning if some free entries of
    theta never moved from the best start, where their gradient and Jacobian column are
    exactly zero though they act away from it (`zero_gradient_entries`), or if a success
    left every free entry of theta and x0 where the gradient of each is exactly zero
    (`_no_effect`: `stop_info["no_effect"]`); with a warning and
    `stop_info["without_effect"]` if a success left free entries of theta outside a
    network (an equinox module) at their start, without effect around it though with
    effect further away (`acting_elsewhere`: a start on a flat piece of the model); else
    `result` itself. With several starts,
    each other start that reported a success is checked the same way for the first case
    (its stop in `result.starts` becomes `zero_gradient`, without a warning).

    **Arguments:**

    - `result`: the assembled `FitResult`.
    - `problem`: the fit's `FitProblem`.
    - `starts`: the starts (S, ...) the fit ran from.
    - `theta_flat`: the returned theta, flat (fixed entries included).
    - `strategy`: the strategy of the derivatives.
    - `finals`: the free entries of theta each start ended at (S, p), or None.
    - `finals_x0`: the free entries of x0 each start ended at (S, N, m), or None.

    **Returns:** a `FitResult`.
    """
    result = _starts_flagged(result, problem, starts, finals, strategy)
    free = problem.theta_free
    final = np.asarray(theta_flat)
    final = final if len(free) == final.size else final[list(free)]
    best = result.best
    if not (final == starts.theta[best]).any():  # every free entry moved (an ordinary fit)
        return result
    start = Params(starts.theta[best], starts.x0[best])
    if name_of(result.stop_reason) == "zero_residual":
        # The outputs are reproduced exactly: a parameter without effect there is one the
        # data do not determine (the covariance reports it), not a start to move from.
        return result
    entries, idle = zero_gradient_entries(problem, start, final, strategy, without_effect=True)
    all_names = _pytree.indexed_names(_pytree.split(result.theta)[0])
    free = np.asarray(free, int)
    stop = name_of(result.stop_reason)
    # (a network's weights: units dead over the data are many, and no start to pick)
    idle = idle[~_pytree.module_entries(result.theta)[free[idle]]] if idle.size else idle
    if idle.size and not entries.size and result.success:
        elsewhere = acting_elsewhere(problem, start, idle, strategy)
        if elsewhere:
            result = _flag_without_effect(
                result, {all_names[free[i]]: v for i, v in elsewhere.items()}
            )
    info = {**result.stop_info, "solver_stop": stop}
    if entries.size:
        info["zero_gradient"] = [all_names[free[i]] for i in entries]
    elif result.success and _no_effect(
        problem, start, final, None if finals_x0 is None else finals_x0[best], strategy
    ):
        info["zero_gradient"] = [all_names[i] for i in free]
        info["no_effect"] = True
    else:
        return result
    warn(
        f"{stop_detail('zero_gradient', info)}; {RESULTS[RESULTS.zero_gradient]}.",
        RuntimeWarning,
        stacklevel=3,  # `fit`'s caller
    )
    if stop == "diverged":  # the more pressing report: keep it
        return result
    out = dataclasses.replace(result, stop_reason=RESULTS.zero_gradient, stop_info=info)
    if result.starts is not None:  # (the best start's own stop, as the status line's)
        reasons = list(result.starts.stop_reason)
        reasons[best] = "zero_gradient"
        out = _with_stops(out, reasons)
    return out
