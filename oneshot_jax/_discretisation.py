"""Whether a fit of a `Model.from_ode` model describes the ODE or its integrator's steps.

The discrete step f of eq. (1) is the integrator's (RK4 or explicit Euler over h = dt /
substeps), not the ODE's flow. Its error per step is small below the stability check's
range (RK4's factor R(-0.6) = 0.5494 against e^-0.6 = 0.5488), but a long, quiet record
resolves the parameters finely enough that even that error moves the estimates by
standard errors, with white residuals and no other sign. `check_discretisation` refits
the model twice from the estimate, on the same data, at its own step and with steps
`factor` times finer, and measures how far each parameter moves between the two, in
standard errors: what the estimates owe to the step rather than to the data.
"""

import equinox as eqx
import jax
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._caller_warnings import at_caller, warn
from ._continuation import (
    _check_fitted_record,
    _shape_text,
    carry_held,
    check_fit_keywords,
    check_margin,
)
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
        both estimates refitted from the result's (`refit` and `coarse`), the standard
        errors `coarse`'s; shaped like theta's parameters; NaN where an entry was held
        (`fixed`) or its standard error is not finite (not identifiable: no scale to
        measure it by).
    - `largest`: the largest |shift| (NaN where no entry has one).
    - `name`: the parameter of `largest` (`"a"`, `"I[2]"`), or None.
    - `factor`: how many times finer the refit's steps are.
    - `refit`: the `FitResult` of the model with the finer steps (its model is
        `refit.model`): the better estimate where `depends` is True.
    - `coarse`: the `FitResult` of the result's own model refitted from its estimate on
        the same data and keywords (where the result converged on these, it stays there;
        where it had not converged, this one goes on to the optimum).
    - `margin`: the move, in standard errors, past which `depends` is True.

    **Properties:**

    - `converged`: whether both refits converged (else the check is inconclusive).

    `print(check)` gives one line: the largest move and the verdict (the estimates depend
    on the step, they do not, or inconclusive where a refit did not converge).
    """

    depends: bool
    shift: PyTree
    largest: float
    name: str | None
    factor: int
    refit: FitResult
    coarse: FitResult
    margin: float = 0.5

    @property
    def converged(self) -> bool:
        """Whether both refits converged (else the check is inconclusive)."""
        return bool(self.refit.success and self.coarse.success)

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
        elif not self.converged:
            verdict = "inconclusive: a refit did not converge"
        else:
            verdict = "the estimates do not depend on the step"
        return (
            f"Discretisation check, steps {self.factor} times finer ({self.refit.status}; "
            f"at the fit's own step {self.coarse.status}): {moved}; {verdict}."
        )

    __repr__ = __str__


def finer(model, factor: int):
    """`model` with its integrator's steps `factor` times shorter everywhere: `substeps *
    factor` for a fixed `dt` (and for a time-stamped model without `max_step`); for a
    time-stamped model with `max_step`, each interval's ceil(dt / max_step) steps split
    `factor` times (`timed_ode_step`'s `refine`)."""
    step = model.step
    if isinstance(step, _ODEStep):
        new = _ODEStep(step.rhs, step.dt, step.method, step.substeps * factor, step.input)
    elif step.max_step is None:
        new = _TimedODEStep(step.rhs, step.method, step.substeps * factor, None, step.input)
    else:
        new = _TimedODEStep(
            step.rhs, step.method, step.substeps, step.max_step, step.input, step.refine * factor
        )
    return eqx.tree_at(lambda m: m.step, model, new)


def _moves(start, std, refit):
    """(each parameter's move from `start` to `refit.theta` in the standard errors `std`,
    shaped like theta's parameters; the moves, the starts and the refit's values over the
    free entries, flat)."""
    params = lambda th: eqx.filter(th, eqx.is_inexact_array)  # noqa: E731

    def leaf(new, old, std):
        new, old, std = (np.asarray(a, float) for a in (new, old, std))
        with np.errstate(divide="ignore", invalid="ignore"):
            # (a standard error of 0, from a fit to exact data, makes any move infinite)
            out = np.where(std > 0, (new - old) / std, np.where(new == old, 0.0, np.inf))
        return np.where(np.isfinite(std), out, np.nan)

    shift = jax.tree.map(leaf, params(refit.theta), params(start.theta), params(std))
    flat = [_flat(t) for t in (shift, params(start.theta), params(refit.theta))]
    free = ~np.asarray(refit.fixed, bool)
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


def _largest(moves, names):
    """(the largest |move|, its parameter's name, its index), NaN and None where no move
    is measured (an infinite one counts: a standard error of 0)."""
    known = ~np.isnan(moves)
    if not known.any():
        return float("nan"), None, None
    at = int(np.argmax(np.where(known, np.abs(moves), -1.0)))
    names = list(names)
    return float(abs(moves[at])), names[at] if len(names) == moves.size else f"entry {at}", at


def _values(before, after):
    """The two values of a move in words, with the digits that tell them apart and the
    relative move (data without noise resolve moves of 1e-8 and less)."""
    digits = 6
    while f"{before:.{digits}g}" == f"{after:.{digits}g}" and digits < 17:
        digits += 1
    rel = abs(after - before) / abs(before) if before != 0 else float("inf")
    return f"from {before:.{digits}g} to {after:.{digits}g}, relatively {rel:.2g}"


def _carried(result, kwargs):
    """`kwargs` with what the result records of its fit where they do not say otherwise:
    `fixed`, `missing`, `weight`, `estimate_x0`, `x0_bounds`; a ValueError where the
    result's fit took windows or aggregated readings that `kwargs` do not repeat."""
    if result.window_starts is not None and "window" not in kwargs:
        raise ValueError(
            f"`window`: the result is of a fit with windows (starts "
            f"{np.asarray(result.window_starts).tolist()[:6]}...): pass `window=` (and the "
            "other keywords) as for the fit."
        )
    if (result.diagnostics or {}).get("aggregated") and "aggregate" not in kwargs:
        raise ValueError(
            "`aggregate`: the result is of a fit with aggregated readings: pass `aggregate=` "
            "(and the other keywords) as for the fit."
        )
    kwargs = carry_held(result, kwargs, "`check_discretisation`", "its refits", stacklevel=4)
    if "weight" not in kwargs and result.weight is not None:
        kwargs["weight"] = result.weight
    if "estimate_x0" not in kwargs and result.x0_estimated is not None:
        mask = np.asarray(result.x0_estimated, bool)
        kwargs["estimate_x0"] = True if mask.all() else False if not mask.any() else mask
    if "x0_bounds" not in kwargs and result.x0_bounds is not None:
        kwargs["x0_bounds"] = result.x0_bounds
    return kwargs


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

    Refits the result's model twice from the result's theta and x0, on the same data
    and keywords: with its own step (`coarse`) and with the integrator's steps `factor`
    times shorter (`refit`: h = dt / substeps, eq. (1)'s f made of more RK4 or Euler
    steps); and measures each parameter's move between the two in `coarse`'s standard
    errors. The refit at the fit's own step makes the move the step's alone: where the
    result had not converged, or the data or keywords differ from its fit's, both refits
    share that. Where a parameter moves by more than `margin`, the estimates owe that
    much to the discretisation: it warns (RuntimeWarning), and `refit` is the better
    estimate (check it in turn, with steps finer again). RK4's error falls 16-fold when
    h halves (Euler's 2-fold), so the move with `factor=2` is about 15/16 of the
    estimate's error from the step (Euler's: half of it). `fit`'s stability warning
    (`check_stability`) covers steps past RK4's accurate range; this check covers the
    error of any step, which a long, quiet record resolves into a bias of standard
    errors with white residuals. Where a refit does not converge and no parameter moved
    past `margin`, it warns that the check is inconclusive; where the result converged
    and its own refit moved past `margin`, it warns that the data or keywords are not
    the fit's. Without noise every move counts (the standard errors are at round-off):
    the warning gives the relative move too.

    The check costs two fits (the finer one compiles a program of its own and takes
    `factor` times the steps per sample), so `fit` does not run it: call it where the
    estimates matter.

    **Arguments:**

    - `result`: a `FitResult` of `fit` holding its `Model.from_ode` model.
    - `u`, `z`: the data the result was fitted on, as passed to `fit`.
    - `factor`: how many times shorter the refit's steps are, an integer >= 2.
    - `margin`: the move, in standard errors, past which the estimates depend on the
        step (0.5 by default: a bias of half a standard error takes the 95 % intervals'
        coverage to 92 %, one of 1 to 83 %).
    - keyword arguments: passed to both refits (`solver`, `constraints`, `t`, `window`,
        `aggregate`, ...): the keywords of the fit that a result does not record. What
        it records is carried unless given: `fixed` (per key of a dict theta),
        `missing`, `weight`, `estimate_x0` (`x0_estimated`) and `x0_bounds`; a result
        of a fit with `window=` or `aggregate=` needs them given again.

    **Returns:**

    A `DiscretisationCheck`: `depends`, each parameter's `shift`, the `largest` and its
    `name`, the `refit` and the `coarse` refit.
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
    check_margin(margin)
    check_fit_keywords(kwargs, "check_discretisation")
    if "multistart" in kwargs:
        raise ValueError(
            "`multistart` is not a keyword of `check_discretisation`: its refits start from "
            "the result's estimate."
        )
    shapes = [_shape_text(a) for a in (u, z)]
    if (
        all(isinstance(s, tuple) and len(s) >= 2 for s in shapes)
        and shapes[0][:-1] != shapes[1][:-1]
    ):
        raise ValueError(
            f"`u` and `z` must be the data the result was fitted on, with the same records "
            f"and samples (all axes but the last); got u {shapes[0]}, z {shapes[1]}."
        )
    if np.ndim(result.x0) == 1 and np.shape(result.residuals) == np.shape(z):
        _check_fitted_record(result, u, z, kwargs.get("t"))
    kwargs = _carried(result, kwargs)
    with at_caller(__file__):
        coarse = fit(result.model, result.theta, result.x0, u, z, **kwargs)
        refit = fit(finer(result.model, factor), result.theta, result.x0, u, z, **kwargs)
    shift, moves, before, after = _moves(coarse, coarse.std, refit)
    largest, name, at = _largest(moves, result.names)
    depends = bool(largest > margin)
    check = DiscretisationCheck(depends, shift, largest, name, factor, refit, coarse, float(margin))
    if depends:
        exact = (
            " (The fit's residual is zero: the data are the model's own at its step, its "
            "standard errors are round-off, and any move counts; judge by the relative move.)"
            if coarse.status == "zero_residual" or np.isinf(largest)
            else ""
        )
        warn(
            f"the estimates depend on the integrator's step: with steps {factor} times "
            f"finer, {name} moves by {largest:.3g} standard errors "
            f"({_values(before[at], after[at])}), more than {margin:g}: an error of the "
            "step, not of the data, of about that size. Use the finer model's fit "
            f"(`check.refit`, its model `check.refit.model`), and check it in turn.{exact}",
            RuntimeWarning,
            stacklevel=2,
        )
    elif not check.converged:
        failed = refit if not refit.success else coarse
        which = "with finer steps" if failed is refit else "at the fit's own step"
        warn(
            f"check_discretisation is inconclusive: its refit {which} did not converge "
            f"({failed.status}: {failed.message}), so its moves need not be the step's, and "
            "`depends=False` is no all-clear. Rerun it with a solver that converges (more "
            "`max_steps`, say).",
            RuntimeWarning,
            stacklevel=2,
        )
    if result.success:
        drift = _moves(result, coarse.std, coarse)[1]
        far, which, _ = _largest(drift, result.names)
        if far > margin:
            warn(
                f"check_discretisation: the result converged, but its model refitted from "
                f"its estimate on these data and keywords moved {which} by {far:.3g} "
                "standard errors: `u`, `z` or the keywords are not the fit's (its "
                "`constraints`, `solver`, `t`, ...). The check compares the two refits, "
                "on these data and keywords.",
                RuntimeWarning,
                stacklevel=2,
            )
    return check
