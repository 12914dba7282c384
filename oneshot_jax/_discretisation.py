"""Whether a fit of a `Model.from_ode` model describes the ODE or its integrator's steps.

The discrete step f of eq. (1) is the integrator's (RK4 or explicit Euler over h = dt /
substeps), not the ODE's flow. Its error per step is small below the stability check's
range (RK4's factor R(-0.6) = 0.5490 against e^-0.6 = 0.5488), but a long, quiet record
resolves the parameters finely enough that even that error moves the estimates by
standard errors, with white residuals and no other sign. `check_discretisation` refits
the model with steps `factor` times finer, warm-started at the estimate, and measures how
far each parameter moves, in the fit's standard errors: what the estimates owe to the
step rather than to the data.
"""

import numbers

import equinox as eqx
import jax
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._caller_warnings import at_caller, warn
from ._continuation import _check_fitted_record, _held, check_fit_keywords
from ._counts import is_count
from ._fit import fit
from ._fit_result import FitResult
from ._model import _ODEStep, _TimedODEStep


class DiscretisationCheck(eqx.Module):
    """What `check_discretisation` found.

    **Fields:**

    - `depends`: whether a parameter moved by more than `margin` standard errors when
        the integrator's steps were made `factor` times finer.
    - `shift`: theta's parameters' moves, (finer estimate - estimate) / standard error,
        shaped like theta's parameters; NaN where an entry was held (`fixed`) or its
        standard error is not finite (not identifiable: no scale to measure it by).
    - `largest`: the largest |shift| (NaN where no entry has one).
    - `name`: the parameter of `largest` (`"a"`, `"I[2]"`), or None.
    - `factor`: how many times finer the refit's steps are.
    - `refit`: the `FitResult` of the model with the finer steps (its model is
        `refit.model`): the better estimate where `depends` is True.

    `print(check)` gives one line: the largest move and the verdict (the estimates depend
    on the step, they do not, or inconclusive where the refit did not converge).
    """

    depends: bool
    shift: PyTree
    largest: float
    name: str | None
    factor: int
    refit: FitResult
    margin: float = 0.5

    def __str__(self):
        if self.name is None:
            moved = "no parameter has a finite standard error to measure a move by"
        else:
            moved = f"the largest move is {self.name}'s, {self.largest:.3g} standard errors"
        if self.depends:
            verdict = (
                f"the estimates depend on the integrator's step (more than {self.margin:g} "
                "standard errors): use the finer model (`refit`), and check it in turn"
            )
        elif not self.refit.success:
            verdict = "inconclusive: the refit with finer steps did not converge"
        else:
            verdict = "the estimates do not depend on the step"
        return (
            f"Discretisation check, steps {self.factor} times finer ({self.refit.status}): "
            f"{moved}; {verdict}."
        )

    __repr__ = __str__


def finer(model, factor: int):
    """`model` with its integrator's steps `factor` times shorter: `substeps * factor` for
    a fixed `dt` (and for a time-stamped model without `max_step`); for a time-stamped
    model with `max_step`, `max_step / factor`, with the bound `substeps` of its loop
    `factor` times larger."""
    step = model.step
    if isinstance(step, _ODEStep):
        new = _ODEStep(step.rhs, step.dt, step.method, step.substeps * factor, step.input)
    else:
        max_step = None if step.max_step is None else step.max_step / factor
        new = _TimedODEStep(step.rhs, step.method, step.substeps * factor, max_step, step.input)
    return eqx.tree_at(lambda m: m.step, model, new)


def _moves(result, refit):
    """(each parameter's move in standard errors, shaped like theta's parameters; the
    moves, the estimates and the refit's estimates over the free entries, flat)."""
    params = lambda th: eqx.filter(th, eqx.is_inexact_array)  # noqa: E731

    def leaf(new, old, std):
        new, old, std = (np.asarray(a, float) for a in (new, old, std))
        with np.errstate(divide="ignore", invalid="ignore"):
            # (a standard error of 0, from a fit to exact data, makes any move infinite)
            out = np.where(std > 0, (new - old) / std, np.where(new == old, 0.0, np.inf))
        return np.where(np.isfinite(std), out, np.nan)

    shift = jax.tree.map(leaf, params(refit.theta), params(result.theta), params(result.std))
    flat = [_flat(t) for t in (shift, params(result.theta), params(refit.theta))]
    free = ~np.asarray(result.fixed, bool)
    if free.size == flat[0].size:
        flat = [a[free] for a in flat]
        shift = _held_as_nan(shift, ~free)
    return shift, *flat


def _flat(tree):
    leaves = [np.ravel(np.asarray(a, float)) for a in jax.tree_util.tree_leaves(tree)]
    return np.concatenate(leaves) if leaves else np.zeros(0)


def _held_as_nan(shift, fixed):
    """`shift` with NaN at the entries `fixed` (flat, in theta's order) marks held."""
    leaves, treedef = jax.tree_util.tree_flatten(shift)
    out, at = [], 0
    for a in leaves:
        n = np.size(a)
        out.append(np.where(fixed[at : at + n].reshape(np.shape(a)), np.nan, a))
        at += n
    return jax.tree_util.tree_unflatten(treedef, out)


def check_discretisation(
    result: FitResult,
    u: Float[ArrayLike, "... T n_u"],
    z: Float[ArrayLike, "... T n_z"],
    *,
    factor: int = 2,
    margin: float = 0.5,
    **kwargs,
) -> DiscretisationCheck:
    """Check whether a fit of a `Model.from_ode` model describes the ODE or the steps of
    its integrator.

    Refits the result's model with the integrator's steps `factor` times shorter (h =
    dt / substeps, eq. (1)'s f made of more RK4 or Euler steps), from the result's theta
    and x0, on the same data, and measures each parameter's move in the result's standard
    errors. Where one moves by more than `margin`, the first estimates owe that much to
    the discretisation: it warns (RuntimeWarning), and the refit is the better estimate
    (check it in turn, with steps finer again). RK4's error falls 16-fold when h halves
    (Euler's 2-fold), so the move of a refit with `factor=2` is about 15/16 of the first
    estimate's error from the step (Euler's: half of it). `fit`'s stability warning
    (`check_stability`) covers steps past RK4's accurate range; this check covers the
    error of any step, which a long, quiet record resolves into a bias of standard errors
    with white residuals. Where the refit does not converge and no parameter moved past
    `margin`, it warns that the check is inconclusive.

    The check costs one fit of the model with finer steps (a compilation of its own,
    and `factor` times the steps per sample), so `fit` does not run it: call it where the
    estimates matter.

    **Arguments:**

    - `result`: a `FitResult` of `fit` holding its `Model.from_ode` model.
    - `u`, `z`: the data the result was fitted on, as passed to `fit`.
    - `factor`: how many times shorter the refit's steps are, an integer >= 2.
    - `margin`: the move, in standard errors, past which the estimates depend on the
        step (0.5 by default: a bias of half a standard error takes the 95 % intervals'
        coverage to 92 %, one of 1 to 83 %).
    - keyword arguments: passed to the refit (`solver`, `weight`, `constraints`, `t`,
        `window`, ...; use the ones the result was fitted with: a result does not record
        its constraints or windows). `fixed` defaults to what the result held
        (`FitResult.fixed`, per key of a dict theta), `missing` to the result's.

    **Returns:**

    A `DiscretisationCheck`: `depends`, each parameter's `shift`, the `largest` and its
    `name`, and the `refit`.
    """
    if not isinstance(result, FitResult):
        raise TypeError(f"`result` must be a FitResult, got {type(result).__name__}.")
    if result.model is None:
        raise ValueError("`result` holds no model (loaded without one): load it with `model=`.")
    if not isinstance(result.model.step, (_ODEStep, _TimedODEStep)):
        raise ValueError(
            "`check_discretisation` takes the result of a fit of a `Model.from_ode` model: "
            "it refits with the integrator's steps made finer, and this result's model "
            "steps with a function of its own (for an `ode_step` inside it, refit with "
            "more `substeps` there and compare)."
        )
    if not is_count(factor, -np.inf):
        raise TypeError(f"`factor` must be an integer >= 2, got {factor!r}.")
    if not is_count(factor, 2):
        raise ValueError(f"`factor` must be an integer >= 2, got {factor!r}.")
    factor = int(factor)
    if isinstance(margin, bool) or not isinstance(margin, numbers.Real):
        raise TypeError(f"`margin` must be a non-negative number, got {margin!r}.")
    if not margin >= 0:
        raise ValueError(f"`margin` must be a non-negative number, got {margin!r}.")
    check_fit_keywords(kwargs, "check_discretisation")
    if "multistart" in kwargs:
        raise ValueError(
            "`multistart` is not a keyword of `check_discretisation`: its refit starts from "
            "the result's estimate."
        )
    if np.ndim(result.x0) == 1 and np.shape(result.residuals) == np.shape(z):
        _check_fitted_record(result, u, z, kwargs.get("t"))
    if "fixed" not in kwargs:
        kwargs["fixed"] = _held(result)
        if kwargs["fixed"] is None and np.asarray(result.fixed, bool).any():
            warn(
                "`check_discretisation` cannot carry the result's fixed entries to its refit "
                "for this theta (not a dict of arrays): they are free there. Pass `fixed` "
                "as for the fit.",
                UserWarning,
                stacklevel=2,
            )
    if "missing" not in kwargs:
        kwargs["missing"] = result.missing
    with at_caller(__file__):
        refit = fit(finer(result.model, factor), result.theta, result.x0, u, z, **kwargs)
    shift, flat, before, after = _moves(result, refit)
    known = ~np.isnan(flat)  # (an infinite move counts: a standard error of 0)
    largest, name, moved = float("nan"), None, ""
    if known.any():
        at = int(np.argmax(np.where(known, np.abs(flat), -1.0)))
        largest = float(abs(flat[at]))
        names = list(result.names)
        name = names[at] if len(names) == flat.size else f"entry {at}"
        moved = f" (from {before[at]:.6g} to {after[at]:.6g})"
    depends = bool(largest > margin)
    check = DiscretisationCheck(depends, shift, largest, name, factor, refit, float(margin))
    if depends:
        warn(
            f"the estimates depend on the integrator's step: with steps {factor} times "
            f"finer, {name} moves by {largest:.3g} standard errors{moved}, more than "
            f"{margin:g}: an error of the step, not of the data, of about that size. Use "
            "the finer model's fit (`check.refit`, its model `check.refit.model`), and "
            "check it in turn.",
            RuntimeWarning,
            stacklevel=2,
        )
    elif not refit.success:
        warn(
            f"check_discretisation is inconclusive: its refit with steps {factor} times finer "
            f"did not converge ({refit.status}: {refit.message}), so its moves need not be "
            "the step's, and `depends=False` is no all-clear. Rerun it with a solver that "
            "converges (more `max_steps`, say).",
            RuntimeWarning,
            stacklevel=2,
        )
    return check
