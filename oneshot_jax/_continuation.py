"""Bad minima of the simulation error: horizon continuation and the bad-basin check.

The multi-step cost C of eq. (5) over a long record has local minima that a short
horizon does not: a model whose oscillation drifts out of phase, or whose output shrinks
to nothing, is a stationary point only because the errors pile up over many periods.
Cut into short windows, each with its own initial state (multiple shooting: eq. (5) with
the windows as N trajectories, `fit(window=...)`), the cost is far closer to convex.
`fit_continuation` starts there and lengthens the windows, each stage warm-started from
the last, up to the whole record; `check_basin` compares a whole-record fit with a
short-window fit from the same theta and warns where the first is far worse.
"""

import inspect
import math
import numbers
import warnings

import equinox as eqx
import jax
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._caller_warnings import at_caller, warn
from ._checks import x0_mask
from ._counts import is_count
from ._fit import fit
from ._fit_result import FitResult, is_fitted_record
from ._simulate import simulate


class Stage(eqx.Module):
    """One stage of `fit_continuation`.

    **Fields:**

    - `window`: the window length in samples; None for the whole record.
    - `loss`: the stage's final loss (eq. 5 over its windows).
    - `fit_percent`: FIT% per output over its windows (each from its own x0).
    - `num_steps`: the solver steps it took.
    - `status`: its stop reason's name (`"converged"`, `"max_steps_reached"`, ...).
    - `success`: whether it converged.
    - `theta`: the stage's fitted theta. Besides a start for the next stage, a model of
        its own: where a model error accumulates over a long record, a fit over windows
        of it (each with its own initial state) can simulate new data better than the
        whole-record fit; compare the stages on held-out data.
    """

    window: int | None
    loss: float
    fit_percent: np.ndarray
    num_steps: int
    status: str
    success: bool
    theta: PyTree = None

    def __str__(self):
        w = "whole" if self.window is None else str(self.window)
        fits = ", ".join(f"{f:.2f}" for f in np.atleast_1d(self.fit_percent))
        return f"{w:>8}  {self.loss:>12.5g}  {fits:>10}  {self.num_steps:>6}  {self.status}"


class Continuation(eqx.Module):
    """What `fit_continuation` returns.

    **Fields:**

    - `result`: the `FitResult` of the last stage, the fit to the whole record. Its
        `success`, `status` and `message` are that fit's own: the continuation claims
        nothing the last fit did not reach.
    - `stages`: a `Stage` per stage, the whole record last (window, loss, FIT%, steps,
        stop reason).
    """

    result: FitResult
    stages: tuple

    @property
    def success(self) -> bool:
        """Whether the last stage, the whole-record fit, converged."""
        return self.result.success

    def __str__(self):
        head = f"{'window':>8}  {'loss':>12}  {'FIT %':>10}  {'steps':>6}  stop"
        rows = "\n".join(str(s) for s in self.stages)
        return f"Horizon continuation, {len(self.stages)} stages:\n{head}\n{rows}\n\n{self.result}"

    __repr__ = __str__


def _stage(window, r):
    return Stage(
        window=window,
        loss=float(r.loss),
        fit_percent=np.asarray(r.metrics["fit_percent"]),
        num_steps=int(r.num_steps),
        status=r.status,
        success=bool(r.success),
        theta=r.theta,
    )


def _schedule(windows, start, factor, T):
    """The window lengths, shortest first, each shorter than the record."""
    if windows is not None:
        if start is not None or factor is not None:
            raise ValueError(
                "`start` and `factor` make the window lengths when `windows` is not given: "
                "pass `windows` or them, not both."
            )
        if isinstance(windows, (dict, set, frozenset, str, bytes)):
            raise TypeError(
                f"`windows` must be a sequence of window lengths (a list or tuple, in the "
                f"stages' order), got {type(windows).__name__} {windows!r}."
            )
        try:
            windows = list(windows)
        except TypeError:
            raise TypeError(
                f"`windows` must be a sequence of window lengths, got {windows!r}."
            ) from None
        if not windows or not all(is_count(w, 1) for w in windows):
            raise ValueError(
                f"`windows` must be a non-empty sequence of positive integers, got {windows!r}."
            )
        if any(b <= a for a, b in zip(windows, windows[1:])):
            raise ValueError(f"`windows` must increase, got {windows!r}.")
        if windows[-1] >= T:
            raise ValueError(
                f"every window of `windows` must be shorter than the record (T = {T}): the "
                f"last stage fits the whole record; got {windows!r}."
            )
        return [int(w) for w in windows]
    start = 50 if start is None else start
    factor = 2 if factor is None else factor
    if not is_count(start, 1):
        raise ValueError(f"`start` must be a positive integer, got {start!r}.")
    if start >= T:
        raise ValueError(
            f"`start` ({start}) must be shorter than the record (T = {T}): the last stage "
            "fits the whole record."
        )
    if (
        isinstance(factor, bool)
        or not isinstance(factor, numbers.Real)
        or not factor > 1
        or not math.isfinite(factor)
    ):
        raise ValueError(f"`factor` must be a finite number > 1, got {factor!r}.")
    out = [int(start)]
    while True:
        w = max(out[-1] + 1, int(round(out[-1] * factor)))
        if w >= T:
            return out
        out.append(w)


def _window_states(model, result, u, w_prev, window, t=None):
    """Each new window's starting state: the last stage's windows (of `w_prev` samples)
    simulated from their own x0 with its theta, read at the new windows' starts (all
    inside the last stage's windows, since `window` > `w_prev`). `t`: the record's sample
    times, for a model of time-stamped records."""
    x0 = np.asarray(result.x0)
    N_prev, n_x = x0.shape
    u_prev = u[: N_prev * w_prev].reshape(N_prev, w_prev, -1)
    t_prev = None if t is None else np.asarray(t)[: N_prev * w_prev].reshape(N_prev, w_prev)
    xs, _ = simulate(model, result.theta, x0, u_prev, t=t_prev)
    xs = np.asarray(xs).reshape(N_prev * w_prev, n_x)
    return xs[np.arange(u.shape[0] // window) * window]


def _in_order(theta, like):
    """`theta` with its dicts' keys in the order of `like`'s (a fitted theta comes back
    with sorted keys; the printout shows theta0's written order)."""
    if isinstance(theta, dict) and isinstance(like, dict) and theta.keys() == like.keys():
        return {k: _in_order(theta[k], like[k]) for k in like}
    return theta


def fit_continuation(
    model,
    theta0: PyTree,
    x0: Float[ArrayLike, " n_x"],
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    *,
    windows=None,
    start: int | None = None,
    factor: float | None = None,
    **kwargs,
) -> Continuation:
    """Fit by horizon continuation: short windows first, then longer ones, then the whole
    record, each stage warm-started from the last.

    Stage 1 is `fit(..., window=windows[0])`: the record cut into windows, each with its
    own initial state (multiple shooting, eq. (5) with the windows as trajectories), whose
    cost has far fewer bad minima than the whole record's. Each later stage starts from
    the last stage's theta, and each of its windows from the last stage's states at its
    start (the last stage's windows simulated from their own x0). The last stage fits the
    whole record from the first window's state. Use it where a whole-record fit stops in a
    bad minimum (`check_basin` warns of one): an oscillation fitted over many periods, a
    start far from the truth.

    **Arguments:**

    - `model`, `theta0`, `x0`, `u`, `z`: as for `fit`, one record: `x0` (n_x,), `u`
        (T, n_u), `z` (T, n_z).
    - `windows`: the window lengths of the stages before the whole record, increasing,
        each shorter than the record, e.g. `(50, 100, 200)`.
    - `start`, `factor`: without `windows`, the lengths `start`, `start * factor`, ...
        while shorter than the record (by default 50 and 2: doubling from 50); with
        `windows`, neither.
    - keyword arguments: passed to every stage's `fit` (`solver`, `weight`, `fixed`,
        `constraints`, ...); not `window`, `multistart` or `aggregate`. `covariance`
        and `estimate_x0` go to the last stage only: the windowed stages compute no
        covariance (their `Stage` keeps no standard errors) and estimate every entry of
        every window's x0 (the states where a
        window after the first starts come from the last stage's fit, not from data,
        so holding some of them would hold guesses).

    **Returns:**

    A `Continuation`: `result`, the last stage's `FitResult` (whose `success` is its own),
    and `stages`, each stage's window, loss, FIT%, steps and stop reason.
    """
    check_fit_keywords(kwargs, "fit_continuation")
    if "window" in kwargs:
        raise ValueError(
            "`window` is not a keyword of `fit_continuation`: it sets each stage's windows "
            "itself (`windows=`, or `start=` and `factor=`)."
        )
    if "multistart" in kwargs:
        raise ValueError(
            "`multistart` is not a keyword of `fit_continuation`, which runs from one start: "
            "run a multistart fit first and continue from its theta."
        )
    if kwargs.get("aggregate") is not None:
        # (its stages are windowed fits, and a reading may span windows)
        raise ValueError(
            "`aggregate` is not a keyword of `fit_continuation`: an aggregated reading may "
            "span the windows of its stages. Fit the whole record with `fit(..., "
            "aggregate=...)`."
        )
    if np.ndim(x0) != 1 or np.ndim(u) != 2 or np.ndim(z) != 2:
        raise ValueError(
            "`fit_continuation` takes one record: `x0` of shape (n_x,), `u` (T, n_u) and `z` "
            f"(T, n_z); got shapes {np.shape(x0)}, {np.shape(u)}, {np.shape(z)}."
        )
    if np.shape(u)[0] != np.shape(z)[0]:  # (before the windows, which T sizes)
        flipped = " (is `u` transposed? u is (T, n_u))" if np.shape(u)[1] == np.shape(z)[0] else ""
        raise ValueError(
            f"`u` and `z` must hold the same number of samples T: got u {np.shape(u)}, z "
            f"{np.shape(z)}{flipped}."
        )
    covariance = kwargs.pop("covariance", "classical")
    estimate_x0 = kwargs.pop("estimate_x0", True)
    # (checked here, not after the windowed stages; the entries the last stage holds
    # keep the given values)
    held = None if estimate_x0 is True else ~x0_mask(estimate_x0, np.shape(x0)[0])
    u_np = np.asarray(u)
    T = u_np.shape[0]
    schedule = _schedule(windows, start, factor, T)
    stages = []
    with at_caller(__file__):  # (the stages' warnings, at the caller's line)
        theta, x0_stage, result, w_prev = theta0, x0, None, None
        for w in schedule:
            if result is not None:
                x0_stage = _window_states(model, result, u_np, w_prev, w, kwargs.get("t"))
            with warnings.catch_warnings():
                # The tail that fills no window is fitted by the last stage, the whole record.
                warnings.filterwarnings("ignore", message="the last .* do not fill a window")
                # (a stage keeps no standard errors: its covariance is not computed)
                result = fit(model, theta, x0_stage, u, z, window=w, covariance=None, **kwargs)
            stages.append(_stage(w, result))
            theta, w_prev = _in_order(result.theta, theta0), w
        final_x0 = np.asarray(result.x0)[0]
        if held is not None:
            final_x0 = np.where(held, np.asarray(x0, final_x0.dtype), final_x0)
        final = fit(
            model, theta, final_x0, u, z, covariance=covariance, estimate_x0=estimate_x0, **kwargs
        )
    stages.append(_stage(None, final))
    return Continuation(result=final, stages=tuple(stages))


class BasinCheck(eqx.Module):
    """What `check_basin` found.

    **Fields:**

    - `bad_basin`: whether the whole-record fit is far below the short-window fit.
    - `fit_percent`: the whole-record fit's FIT% per output.
    - `window_fit_percent`: the short-window fit's FIT% per output.
    - `window`: the window length.
    - `windowed`: the short-window fit's `FitResult` (its theta is a start to refit the
        whole record from).

    `print(check)` gives one line: both FITs and the verdict (a bad basin, none, or
    inconclusive where the windowed fit did not converge).
    """

    bad_basin: bool
    fit_percent: np.ndarray
    window_fit_percent: np.ndarray
    window: int
    windowed: FitResult

    def __str__(self):
        fmt = lambda a: ", ".join(f"{v:.3g}" for v in np.atleast_1d(a))  # noqa: E731
        if self.bad_basin:
            verdict = (
                "a bad basin: refit the whole record from `windowed.theta`, use "
                "`fit_continuation`, or multistart over the physical parameters"
            )
        elif not self.windowed.success:
            verdict = "inconclusive: the windowed fit did not converge"
        else:
            verdict = "no sign of a bad basin"
        return (
            f"Basin check, windows of {self.window} samples: FIT {fmt(self.fit_percent)} % "
            f"on the whole record, {fmt(self.window_fit_percent)} % in the windows (their "
            f"fit: {self.windowed.status}): {verdict}."
        )

    __repr__ = __str__


def _held(result):
    """`fit`'s `fixed` for what the result held (`FitResult.fixed`), per key of a dict
    theta: True or False for a key held or free as a whole, a mask for an array; None
    where nothing was held (or theta is not a dict)."""
    mask = np.asarray(result.fixed, bool)
    if not mask.any() or not isinstance(result.theta, dict):
        return None
    out, at = {}, 0
    for k in sorted(result.theta):  # the order JAX flattens a dict in
        leaves = jax.tree_util.tree_leaves(eqx.filter(result.theta[k], eqx.is_inexact_array))
        n = sum(int(np.size(a)) for a in leaves)
        part = mask[at : at + n]
        at += n
        if part.all() or not part.any():
            out[k] = bool(part.all())
        elif len(leaves) == 1:
            out[k] = part.reshape(np.shape(leaves[0]))
        else:  # entries of a module held in part: not expressible per key
            return None
    return out if at == mask.size else None


def check_margin(margin):
    """A TypeError or ValueError unless `margin` is a non-negative number."""
    if isinstance(margin, bool) or not isinstance(margin, numbers.Real):
        raise TypeError(f"`margin` must be a non-negative number, got {margin!r}.")
    if not margin >= 0:
        raise ValueError(f"`margin` must be a non-negative number, got {margin!r}.")


def carry_held(result, kwargs, where, refit, stacklevel):
    """`kwargs` of a check's refit (`refit`, in words) with `fixed` and `missing`
    defaulting to what the result held: its fixed entries (`_held`; a UserWarning, at
    `stacklevel` from here, where they cannot be said per key) and its missing samples
    (with missing="mask", z holds its NaN samples)."""
    kwargs = dict(kwargs)
    if "fixed" not in kwargs:
        kwargs["fixed"] = _held(result)
        if kwargs["fixed"] is None and np.asarray(result.fixed, bool).any():
            warn(
                f"{where} cannot carry the result's fixed entries to {refit} for this theta "
                "(not a dict of arrays): they are free there. Pass `fixed` as for the fit.",
                UserWarning,
                stacklevel=stacklevel,
            )
    kwargs.setdefault("missing", result.missing)
    return kwargs


def check_fit_keywords(kwargs, where):
    """A TypeError naming `where` for keywords that neither it nor `fit` takes (they were
    reported as `fit()`'s)."""
    known = inspect.signature(fit).parameters
    unknown = sorted(k for k in kwargs if k not in known)
    if unknown:
        raise TypeError(
            f"`{where}` got unexpected keyword arguments {unknown}: besides its own, it takes "
            "`fit`'s keywords (solver, fixed, constraints, ...)."
        )


def _check_fitted_record(result, u, z, t):
    """Refuse a record of the fitted shape that is not the fitted one: the result's
    simulation on `u` must be z + its residuals (`_fit_result.is_fitted_record`)."""
    if not is_fitted_record(result, result.simulate(u, t=t)[1], z):
        raise ValueError(
            "`u` and `z` must be the record the result was fitted on: the result's "
            "simulation on this `u` differs from the fitted outputs (z + residuals)."
        )


def _shape_text(a):
    """`a`'s shape, or where its rows differ in length (records of a ragged list) the
    words "a list of N records"."""
    try:
        return np.shape(a)
    except ValueError:
        return f"a list of {len(a)} records"


def check_basin(
    result: FitResult,
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    *,
    window: int = 50,
    margin: float = 20.0,
    **kwargs,
) -> BasinCheck:
    """Check a whole-record fit for a bad basin of the simulation error.

    Refits the same model from the result's theta with the record cut into windows of
    `window` samples, each with its own initial state (multiple shooting, eq. (5) with
    the windows as trajectories), and compares FIT%. A whole-record fit in the right basin
    fits about as well as the windows (they only restart the state; with a model error
    that accumulates they fit somewhat better); one whose FIT is more than `margin`
    points below theirs sits in a bad minimum, converged or not: then it warns
    (RuntimeWarning), naming the remedies (refit from the windowed theta,
    `fit_continuation`, multistart over the physical parameters). Where the windowed fit
    itself does not converge and no bad basin shows, it warns that the check is
    inconclusive (`bad_basin` False is then no all-clear).

    The check costs one windowed fit (about what the fit itself cost, plus a compilation
    for the windows' shapes), so `fit` does not run it: call it on a result you doubt.

    **Arguments:**

    - `result`: a `FitResult` of `fit` on one record (its `x0` of shape (n_x,)), holding
        its model; not of a fit with `aggregate=` (the windows cannot take its readings).
    - `u`, `z`: that record, (T, n_u) and (T, n_z).
    - `window`: the window length in samples (shorter than the record).
    - `margin`: how many FIT points below the windowed fit count as a bad basin.
    - keyword arguments: passed to the windowed `fit` (`solver`, `weight`, `fixed`,
        `constraints`, ...; use the ones the result was fitted with: a result does not
        record its constraints, and a windowed fit without the fit's bounds can reach a
        FIT the bounds forbid). `fixed` defaults to what the result held
        (`FitResult.fixed`, per key of a dict theta; for another theta with held
        entries, pass `fixed`: the check warns): a network held in the fit and freed in
        the windows would fit them better for that alone. `missing` defaults to the
        result's (`"mask"` after a fit that took NaN in z as missing samples).

    **Returns:**

    A `BasinCheck`: `bad_basin`, both FIT%s and the windowed fit.
    """
    if not isinstance(result, FitResult):
        raise TypeError(f"`result` must be a FitResult, got {type(result).__name__}.")
    if result.model is None:
        raise ValueError("`result` holds no model (loaded without one): load it with `model=`.")
    shapes = [_shape_text(a) for a in (result.x0, u, z)]
    if [len(s) if isinstance(s, tuple) else 0 for s in shapes] != [1, 2, 2]:
        raise ValueError(
            "`check_basin` takes the result of a fit on one record (`x0` of shape (n_x,)) and "
            f"that record, `u` (T, n_u) and `z` (T, n_z); got x0 {shapes[0]}, u "
            f"{shapes[1]}, z {shapes[2]} (for a fit on several records, check each record "
            "by a fit on it alone)."
        )
    result._check_u(u)  # (a transposed u before the window: its T would be wrong)
    if not is_count(window, -math.inf):  # (a float such as 2.5, a string: the type)
        raise TypeError(
            f"`window` must be a positive integer shorter than the record (T = "
            f"{np.shape(u)[0]}), got {window!r}."
        )
    if not is_count(window, 1) or window >= np.shape(u)[0]:
        raise ValueError(
            f"`window` must be a positive integer shorter than the record (T = "
            f"{np.shape(u)[0]}), got {window!r}."
        )
    window = int(window)
    check_margin(margin)
    check_fit_keywords(kwargs, "check_basin")
    for name in ("window", "multistart"):
        if name in kwargs:
            raise ValueError(f"`{name}` is not a keyword of the windowed fit of `check_basin`.")
    if (result.diagnostics or {}).get("aggregated"):
        raise ValueError(
            "`check_basin` does not take the result of a fit with `aggregate=`: its windowed "
            "fit cannot take aggregated readings (windows do not combine with them), so an "
            "output measured only in aggregate would drop out of the comparison. Compare "
            "with a fit from other starts (`multistart`) instead."
        )
    fitted = np.shape(result.residuals)
    if np.shape(z) != fitted or np.shape(u)[0] != fitted[0]:
        raise ValueError(
            f"`u` and `z` must be the record the result was fitted on (its residuals have "
            f"shape {fitted}); got u {np.shape(u)}, z {np.shape(z)}."
        )
    _check_fitted_record(result, u, z, kwargs.get("t"))
    kwargs = carry_held(result, kwargs, "`check_basin`", "the windowed fit", stacklevel=3)
    with at_caller(__file__):
        windowed = fit(result.model, result.theta, result.x0, u, z, window=window, **kwargs)
    whole = np.asarray(result.metrics["fit_percent"])
    short = np.asarray(windowed.metrics["fit_percent"])
    bad = bool(np.any(short - whole > margin))
    if bad:
        fmt = lambda a: ", ".join(f"{v:.3g}" for v in a)  # noqa: E731
        warn(
            f"the fit ({result.status}) reaches FIT {fmt(whole)} % on the whole record, but "
            f"a fit with windows of {window} samples from its theta reaches {fmt(short)} % "
            "(each window from its own x0): it sits in a bad minimum of the simulation "
            "error. Refit the whole record from the windowed theta "
            "(`check.windowed.theta`), use `fit_continuation` (short windows first), or "
            "multistart over the physical parameters.",
            RuntimeWarning,
            stacklevel=2,
        )
    elif not windowed.success:
        warn(
            f"check_basin is inconclusive: its windowed fit did not converge "
            f"({windowed.status}: {windowed.message}), so its FIT "
            f"{', '.join(f'{v:.3g}' for v in short)} % need not be what the windows can reach, "
            "and `bad_basin=False` is no all-clear. Rerun it with a solver that converges "
            "on the windows (more `max_steps`, say).",
            RuntimeWarning,
            stacklevel=2,
        )
    return BasinCheck(
        bad_basin=bad,
        fit_percent=whole,
        window_fit_percent=short,
        window=int(window),
        windowed=windowed,
    )
