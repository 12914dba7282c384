"""The first two of `fit`'s four stages (inputs, problem, solve, assemble): its
arguments checked and normalised (`check_inputs`), then the `FitProblem` its solvers see
and the starts they run from, built on the host (`build_problem`).

The data's own checks and normalisation (one dtype, ragged trajectories padded and
masked, the model bound and traced abstractly) are `check_data`'s, in `_checks.py`; a
constraint's or regulariser's checks on theta0 are `_prox.py`'s. What is here is what
only `fit` has: its keywords, the starts of a multistart fit, the windows of one record,
the free entries of theta and x0 and the bounds on them.
"""

from collections.abc import Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import numpy as np

from . import _pytree
from ._caller_warnings import warn
from ._checks import (
    Data,
    check_cost,
    check_data,
    check_fixed_bounds,
    check_outside_transformations,
    check_tree,
    check_x0_bounds,
    clip_x0,
    fixed_mask,
    x0_mask,
)
from ._cost import Cost
from ._counts import is_count
from ._fit_report import check_units
from ._normalise import is_ragged
from ._problem import FitProblem, Params, Regulariser
from ._progress import NoProgress, TqdmProgress
from ._prox import (
    check_projection,
    check_regulariser,
    check_regulariser_acts,
    separable,
    split,
)
from ._solver.least_squares import AbstractLeastSquares
from ._solver.optax import Adam
from ._solver.optimistix import Optimistix
from ._solver_arg import as_solvers
from ._starts import (
    as_multistart,
    check_finite_starts,
    check_fixed_starts,
    check_held_x0_starts,
    theta_starts,
)
from ._timing import split_intervals
from ._validation import monitor
from ._windows import BlowUp, cut

_NO_PROGRESS = NoProgress()


class FitInputs(NamedTuple):
    """`fit`'s arguments, checked: what `build_problem` and the solve read."""

    solvers: tuple  # the solver objects, run in order
    meter: Any  # the progress object (`NoProgress` for none)
    units: dict | None
    data: Data  # the data of the first start (per window with `window`)
    cost: Cost
    theta_starts: Any  # multistart: theta0's parameter leaves with their axis of starts
    n_starts: int | None  # multistart: the number of starts
    x0_starts: np.ndarray | None  # multistart: x0 with its axis of starts, if given
    window_starts: np.ndarray | None = None  # with `window`: each window's first sample
    # a dict `multistart`: theta0's own values (flat), which a fixed entry keeps
    theta_held: np.ndarray | None = None
    # with `window`, of a model that observes its state: the windows' x0 entries read
    # from a first sample of z that is missing (`_windows.cut`), or None
    window_unread: np.ndarray | None = None


class Built(NamedTuple):
    """What `build_problem` returns: the problem, the starts, and the masks `assemble`
    reads."""

    problem: FitProblem
    starts: Params  # (S, ...) free entries of theta and x0 per start
    fixed: np.ndarray  # (p,) True for the fixed entries of flat theta
    x0_estimated: np.ndarray  # (n_x,) True for the estimated entries of x0
    # With a general projection, the projection onto each set it intersects (each term of
    # a `combine`, on its own): the estimate must lie in every one (`_fit._flag_infeasible`;
    # the projection onto sets that do not meet maps into the last of them only).
    sets: tuple = ()
    # `fit(x0_bounds=...)` as (lower, upper) (N, n_x), held entries unbounded, or None
    x0_box: tuple | None = None


def _host(a):
    """Data as NumPy arrays (no device transfer until the compiled call), except arrays
    sharded over several devices (`oneshot_jax.sharding`), which stay where they are."""
    if isinstance(a, jax.Array) and len(a.sharding.device_set) > 1:
        return a
    return np.asarray(a)


def _least_squares(solver) -> bool:
    """Whether `solver` minimises a sum of squares (the library's Gauss-Newton and
    Levenberg-Marquardt, or an optimistix least-squares solver in `Optimistix`)."""
    if isinstance(solver, AbstractLeastSquares):
        return True
    return isinstance(solver, Optimistix) and not solver._minimise


def _meter(progress):
    """`progress=` of `fit` as a progress object."""
    if progress is True:
        return TqdmProgress()
    if progress is False or progress is None:
        return _NO_PROGRESS
    if isinstance(progress, type):
        raise TypeError(
            f"`progress` got the class {progress.__name__}: pass an instance, "
            f"{progress.__name__}()."
        )
    if all(callable(getattr(progress, m, None)) for m in ("open", "update", "close")):
        return progress
    raise TypeError(
        "`progress` must be a bool or a progress object with methods open, update and close "
        f"(and optionally finish, as oneshot_jax.TqdmProgress), got {progress!r}."
    )


def _starts_note(theta_params, n_starts) -> str:
    """What `multistart=True` made of theta0's leaves, for an error of the model's call
    with the first start (a leaf without an axis of starts reads as one)."""
    shapes = [np.shape(a)[1:] for a in jax.tree_util.tree_leaves(theta_params)]
    return (
        f"(With `multistart=True` the leading axis of every parameter leaf of theta0 holds "
        f"the starts: it was read as {n_starts} starts, each leaf of shape "
        f"{', '.join(map(str, shapes[:6]))}{' ...' if len(shapes) > 6 else ''}; for a leaf "
        "that is one start, give its starts an axis of their own, or name the starting "
        "values with `multistart={...}`.)"
    )


def check_inputs(
    model,
    theta0,
    x0,
    u,
    z,
    *,
    solver,
    weight,
    penalty,
    penalty_weight,
    window,
    missing,
    multistart,
    progress,
    history,
    units,
    t=None,
    readings=False,
) -> FitInputs:
    """`fit`'s arguments checked, in the order of its errors: the keywords, then the data
    (`check_data`: one record cut into windows with `window`; the first start's theta0
    and x0 with `multistart`), then the cost.

    **Arguments:** those of `fit`.

    **Returns:** a `FitInputs`.
    """
    if z is None:
        raise ValueError("`z` is required: the measured outputs, shape (T, n_z).")
    check_tree(theta0, "theta0")
    check_outside_transformations(theta0, x0, u, z, weight, penalty_weight)
    _warn_integer_entries(theta0)
    _warn_module_python_ints(theta0)
    units = check_units(units, theta0)
    solvers = as_solvers(solver)
    if not is_count(history, 2) or int(history) % 2:
        raise ValueError(f"`history` must be an even integer >= 2, got {history!r}.")
    meter = _meter(progress)

    # Starting points: theta0 (S, ...) and x0 (S, ...) with multistart, else one start.
    u_ndim = 3 if is_ragged(u) or is_ragged(z) else np.ndim(u)
    per_window_x0 = window is not None and np.ndim(x0) == 2 and u_ndim == 2
    data_x0_ndim = 2 if (u_ndim == 3 or per_window_x0) else 1
    multistart = as_multistart(multistart, theta0)
    starting = multistart is not False and multistart is not None
    if window is not None and starting and np.ndim(x0) == 3:
        raise ValueError(
            "`window` with per-start x0 is not supported: give one x0 (n_x,), or one per "
            "window (n_windows, n_x), shared by the starts of theta."
        )
    x0_axis = starting and np.ndim(x0) == data_x0_ndim + 1
    if starting:
        note = (
            f" (with `window`, x0 of shape {np.shape(x0)} is one state per window, not "
            "starts: multistart over x0 does not combine with `window`)"
            if per_window_x0
            else ""
        )
        theta_params, n_starts = theta_starts(
            multistart, theta0, np.shape(x0)[0] if x0_axis else None, note
        )
        theta_first = _pytree.combine(
            jax.tree_util.tree_map(lambda a: a[0], theta_params), _pytree.split(theta0)[1]
        )
    else:
        theta_params, n_starts, theta_first = None, None, theta0
    x0_starts = None
    if x0_axis:
        x0_starts = np.asarray(x0)
        x0 = x0_starts[0]
        check_finite_starts(x0_starts, "x0")

    if window is not None:
        if u_ndim != 2:
            given = (
                f"a list of {len(u)} records"
                if isinstance(u, (list, tuple))
                else f"shape {np.shape(u)}"
            )
            raise ValueError(f"`window` needs one record: `u` of shape (T, n_u), got {given}.")
        x0_record = np.asarray(x0)[0] if per_window_x0 else x0
        try:
            data = check_data(
                model, theta_first, x0_record, u, z, weight, missing, t, theta_name="theta0"
            )
        except ValueError as err:  # (the state checked is x0's first row: say so)
            if not per_window_x0:
                raise
            row, given = np.shape(x0_record), np.shape(x0)
            message = (
                str(err)
                .replace(
                    f"(from `x0` of shape {row})",
                    f"(a row of `x0` of shape {given}, one initial state per window)",
                )
                .replace(
                    f"`x0` (of shape {row})",
                    f"`x0` (of shape {given}, one initial state {row} per window)",
                )
            )
            raise ValueError(message) from err
        # The windows' starting states are estimated with one start's theta: the first
        # whose simulation stays finite over the windows (one start that blows up does not
        # refuse a multistart fit, whatever its place among the starts).
        for s in range(1 if theta_params is None else n_starts):
            theta_s = _pytree.combine(
                jax.tree_util.tree_map(lambda a, s=s: a[s], theta_params),
                _pytree.split(theta0)[1],
            ) if s else theta_first  # fmt: skip
            data_s = data if s == 0 else check_data(
                model, theta_s, x0_record, u, z, weight, missing, t, theta_name="theta0"
            )  # fmt: skip
            try:
                x0_w, u_w, z_w, mask_w, starts, unread = cut(
                    data_s, window, np.asarray(x0) if per_window_x0 else None
                )
                break
            except BlowUp as error:
                if theta_params is None:
                    raise
                if s == n_starts - 1:
                    raise ValueError(
                        f"every one of the {n_starts} starts of theta0 (multistart) makes the "
                        f"model blow up within the windows; the last: {error}"
                    ) from None
        u_w, t_w = split_intervals(data.model, u_w)  # each window keeps its intervals
        data = check_data(
            model, theta_first, x0_w, u_w, z_w, weight, t=t_w, theta_name="theta0"
        )._replace(mask=mask_w)
        if x0_starts is not None:
            raise ValueError("`window` with per-start x0 is not supported: give one x0.")
    else:
        starts = unread = None
        try:
            data = check_data(
                model, theta_first, x0, u, z, weight, missing, t, readings, theta_name="theta0"
            )
        except ValueError as err:
            if multistart is not True or not str(err).startswith("calling the model"):
                raise
            raise ValueError(f"{err} {_starts_note(theta_params, n_starts)}") from err
    cost = check_cost(data, penalty, penalty_weight)
    if cost.penalty is not None and float(cost.penalty_weight) < 0:
        if any(_least_squares(s) for s in solvers):
            raise ValueError(
                f"`penalty_weight` must be >= 0 with a least-squares solver, got "
                f"{float(cost.penalty_weight)}: it minimises a sum of squares that includes "
                "sqrt(penalty_weight h). Use a first-order solver (Adam, LBFGS) for a "
                "signed penalty."
            )
    held = None
    if isinstance(multistart, Mapping):  # (its starts replace theta0's values where given)
        held = _pytree.flat_host(_pytree.split(theta0)[0])
    return FitInputs(
        solvers, meter, units, data, cost, theta_params, n_starts, x0_starts, starts, held, unread
    )


def _warn_integer_entries(theta0) -> None:
    """Warn where theta0 holds an integer scalar or array of NumPy or JAX outside an
    equinox module (`{"k": np.int64(1)}`, a value taken from an integer array,
    `{"a": np.array([1, 2])}`): it is carried as data, not estimated
    (`_pytree.is_parameter`), which a user rarely means there. A module's integer fields
    (an exponent, an index) and Python ints are not named."""
    is_module = lambda a: isinstance(a, eqx.Module)  # noqa: E731
    named = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(theta0, is_leaf=is_module)[0]:
        if isinstance(leaf, (bool, np.bool_)):  # (True: held as data, as an integer is)
            named.append(f"theta0{jax.tree_util.keystr(path)} (bool)")
            continue
        if is_module(leaf) or isinstance(leaf, (int, float)):
            continue
        dtype = getattr(leaf, "dtype", None)
        if dtype is not None and (np.issubdtype(dtype, np.integer) or dtype == np.bool_):
            shape = np.shape(leaf)
            kind = f"{dtype}" if not shape else f"{dtype}, shape {shape}"
            named.append(f"theta0{jax.tree_util.keystr(path)} ({kind})")
    if named:
        warn(
            f"{', '.join(named[:6])}{' and more' if len(named) > 6 else ''}: an integer "
            "scalar or array of NumPy or JAX, or a bool, is held fixed as data, not "
            "estimated (right for an exponent, an index or a switch). To estimate it, give "
            "floats (1.0, "
            "float(value), np.asarray(a, float)); `fixed=` holds a parameter fixed.",
            UserWarning,
            stacklevel=4,
        )


def _warn_module_python_ints(theta0) -> None:
    """Warn where an equinox module of theta0 holds a Python int field (`power: int = 1`)
    that is not static: it is a parameter like `{"k": 2}` (`_pytree.is_parameter`), fitted
    as a float, where equinox's own convention (`eqx.is_inexact_array`) leaves it alone;
    used as a size or an index it then fails to trace, used as an exponent its derivative
    is estimated."""
    is_module = lambda a: isinstance(a, eqx.Module)  # noqa: E731
    named = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(theta0, is_leaf=is_module)[0]:
        if not is_module(leaf):
            continue
        for inner, value in jax.tree_util.tree_flatten_with_path(leaf)[0]:
            if isinstance(value, int) and not isinstance(value, bool):
                named.append(f"theta0{jax.tree_util.keystr(path)}{jax.tree_util.keystr(inner)}")
    if named:
        warn(
            f"{', '.join(named[:6])}{' and more' if len(named) > 6 else ''}: a Python int "
            "field of an equinox module is a parameter here, estimated as a float (as "
            "{'k': 2} is). To keep it an integer, declare the field "
            "`eqx.field(static=True)` or give a NumPy integer (np.int64(1)), held as data; "
            "to estimate it, give a float.",
            UserWarning,
            stacklevel=4,
        )


_MODULE_ENTRIES: dict = {}


def _module_entries(theta):
    """`_pytree.module_entries(theta)`, kept per structure and shapes of theta."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    key = (treedef, tuple(np.shape(a) for a in leaves))

    def entries():
        found = _pytree.module_entries(theta)
        found.setflags(write=False)
        return found

    return _pytree.kept(_MODULE_ENTRIES, key, entries)


_BOUNDS: dict = {}


def _bounds(proj, theta):
    """A box's flat bounds on theta (`proj.bounds`, constants of the box), kept per
    projection (by its bounds' `key` where it has one: a box of scalar bounds, by value;
    else the object, immutable) and structure, shapes and dtypes of theta."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    named = getattr(proj.bounds, "key", None)
    key = (
        id(proj) if named is None else named,
        treedef,
        tuple((np.shape(a), _pytree.leaf_dtype(a)) for a in leaves),
    )

    def make():
        lo, hi = proj.bounds(theta)
        lo, hi = _pytree.flat_host(lo), _pytree.flat_host(hi)
        lo.setflags(write=False)
        hi.setflags(write=False)
        return proj, lo, hi  # (the object kept: its id is not reused while here)

    _, lo, hi = _pytree.kept(_BOUNDS, key, make, size=64)
    return lo, hi


class _Free(NamedTuple):
    """What `build_problem` derives from theta's structure and the masks alone (`_free`)."""

    unravel: Any  # flat theta -> theta (`_pytree.ravel`'s inverse)
    fixed: np.ndarray  # flat mask of the fixed entries of theta
    any_fixed: bool
    theta: np.ndarray  # indices of the free entries of theta
    theta_tuple: tuple
    x0_mask: np.ndarray  # (n_x,) the estimated entries of x0
    x0: np.ndarray  # their indices
    x0_tuple: tuple
    nuisance: tuple  # positions of a module's (network's) entries among the free ones
    lower: np.ndarray | None  # a box's bounds on the free entries, or None
    upper: np.ndarray | None


_FREE: dict = {}


def _free(theta, dtype, fixed, estimate_x0, n_x, proj) -> _Free:
    """The free entries of theta and x0, the network's entries among them and a box's
    bounds on them: checked and derived once per structure of theta, masks and box where
    the masks are None or booleans (`fixed`, `estimate_x0`) and the box is named by its
    values (`constraints.box`), else anew."""

    def make():
        leaves, treedef = jax.tree_util.tree_flatten(theta)
        unravel = _pytree.unravel_for(treedef, tuple(np.shape(a) for a in leaves), dtype)
        fixed_flat = fixed_mask(fixed, theta)
        theta_free = np.flatnonzero(~fixed_flat)
        x0_est = x0_mask(estimate_x0, n_x)
        x0_free = np.flatnonzero(x0_est)
        if len(theta_free) == 0 and len(x0_free) == 0:
            raise ValueError(
                "nothing to estimate: every parameter is fixed and estimate_x0 is False."
            )
        lower = upper = None
        if proj is not None and proj.bounds is not None:
            lo, hi = _bounds(proj, theta)
            lower, upper = lo[theta_free], hi[theta_free]
        for a in (fixed_flat, theta_free, x0_est, x0_free):
            a.setflags(write=False)
        return _Free(
            unravel,
            fixed_flat,
            bool(fixed_flat.any()),
            theta_free,
            tuple(int(i) for i in theta_free),
            x0_est,
            x0_free,
            tuple(int(i) for i in x0_free),
            tuple(int(i) for i in np.flatnonzero(_module_entries(theta)[theta_free])),
            lower,
            upper,
        )

    box = None if proj is None or proj.bounds is None else getattr(proj.bounds, "key", False)
    simple = (fixed is None or isinstance(fixed, bool)) and isinstance(estimate_x0, bool)
    if not simple or box is False:  # a mask of entries, or a box not named by its values
        return make()
    lay = _pytree.layout(theta)
    key = (lay.treedef, lay.shapes, dtype, fixed, estimate_x0, n_x, box)
    return _pytree.kept(_FREE, key, make, size=64)


def build_problem(
    inputs: FitInputs,
    *,
    fixed,
    estimate_x0,
    constraints,
    regulariser,
    validation=None,
    x0_bounds=None,
    x0_held=None,
) -> Built:
    """The `FitProblem` the solvers see and the starts they run from, on the host: the
    free entries of theta and x0, the bounds or projection and the regulariser on theta,
    each checked on theta0.

    **Arguments:**

    - `inputs`: `check_inputs`'s output.
    - `fixed`, `estimate_x0`, `constraints`, `regulariser`, `validation`, `x0_bounds`:
        those of `fit` (`estimate_x0` one mask for every record).
    - `x0_held`: (N, n_x) the entries of `estimate_x0` that a record holds at its value
        of x0 (`_checks.record_x0_mask`: `fit` given a mask per record), or None. The
        problem bounds each by its value (`FitProblem.x0_held`).

    **Returns:** a `Built`.
    """
    data, solvers = inputs.data, inputs.solvers
    batched = data.batched
    # Host-side (NumPy) views with the trajectory axis: no eager JAX call per array; the
    # compiled call takes them as they are.
    X0, U, Z = (_host(a) if batched else np.asarray(a)[None] for a in (data.x0, data.u, data.z))
    n_x = X0.shape[1]

    flat0 = _pytree.flat_host(data.theta)
    proj, reg = split(constraints, regulariser)
    free = _free(data.theta, flat0.dtype, fixed, estimate_x0, n_x, proj)
    fixed_flat, theta_free, x0_est, x0_free = free.fixed, free.theta, free.x0_mask, free.x0
    if inputs.window_unread is not None:
        held_unread = inputs.window_unread & ~np.asarray(x0_est, bool)[None, :]
        if held_unread.any():
            rows, cols = np.nonzero(held_unread)
            first = int(np.asarray(inputs.window_starts)[rows[0]])
            raise ValueError(
                f"`estimate_x0` holds x0 entries {sorted(set(cols.tolist()))} of the windows, "
                "which each window reads from its first sample of z (the model observes its "
                f"whole state), but z is missing there in {len(set(rows.tolist()))} "
                f"window(s), the first at sample {first}: estimate those entries, give the "
                "windows' states in `x0` (one row per window), or let the windows start at "
                "measured samples (`oj.Windows(starts=...)`)."
            )
    if free.lower is not None and np.any(free.lower == free.upper):
        names = np.asarray(_pytree.leaf_names(data.theta), object)[theta_free]
        pinned = [str(n) for n in names[free.lower == free.upper]]
        warn(
            f"the box's lower and upper bounds are equal for {pinned}: the fit holds them "
            "there, but they still count as estimated (a standard error of the "
            "linearisation, one fewer degree of freedom in sigma^2, and one more parameter in "
            "the AIC, AICc, BIC and FPE). "
            "To hold a known value, fix it (`fit(..., fixed=...)`, MATLAB's "
            "`Parameters(i).Fixed`).",
            stacklevel=3,
        )
    n_est = int(np.sum(x0_est))
    if len(theta_free) and Z.shape[1] * Z.shape[2] <= n_est and inputs.window_starts is None:
        # (as for windows below: each record's own x0 fits its samples, whatever theta)
        T, values, several = Z.shape[1], Z.shape[1] * Z.shape[2], X0.shape[0] > 1
        raise ValueError(
            f"{'each record' if several else 'the record'} of {T} sample{'s' * (T > 1)} "
            f"holds {values} output value{'s' * (values > 1)}, no more than the {n_est} "
            f"entries of {'its own x0' if several else 'x0'} that are estimated: x0 alone can "
            "fit the samples, whatever theta, so theta is not determined (unless some of "
            "those entries never act on the outputs: leave them out). Use a longer record, "
            "or estimate fewer x0 entries (`estimate_x0`)."
        )
    if inputs.window_starts is not None and len(theta_free) and Z.shape[1] * Z.shape[2] <= n_est:
        raise ValueError(
            f"`window` of {Z.shape[1]} samples holds {Z.shape[1] * Z.shape[2]} output values "
            f"per window, no more than the {n_est} entries of its own x0 that are estimated: "
            "each window's x0 alone fits its samples and theta is not determined. Use windows "
            f"of more than {n_est // Z.shape[2]} samples (several times more: the windows "
            "must show the dynamics), or estimate fewer x0 entries (`estimate_x0`)."
        )
    for s in solvers:
        s.check_dtype(flat0.dtype)
    on_theta = None  # the regulariser on theta's trainable part
    if reg is not None:
        for s in solvers:
            s.check_regulariser(reg)
        on_theta = Regulariser(
            reg.prox, reg.value, data.static, reg.strength, reg.learning_rate, separable(reg)
        )
        check_regulariser(on_theta, data.theta)
        check_regulariser_acts(on_theta, free.unravel, flat0, theta_free)
        if proj is not None and proj.bounds is None and any(isinstance(s, Adam) for s in solvers):
            warn(
                "a regulariser with a general projection (`constraints.project`, or sets "
                "combined) and `Adam`: Adam takes the regulariser's prox in its own "
                "per-coordinate metric, then the projection, which is Euclidean; their "
                "composition is not the prox of their sum, and its fixed points need not be "
                "stationary, so the fit can stop at max_steps with its first-order measure "
                "stuck above gtol, where more steps do not help. `Optax(optax.sgd(eta))` "
                "with the regulariser's learning_rate=eta takes exact proximal steps over the "
                "set; or use box bounds, or write the set's constraint as a penalty.",
                stacklevel=3,
            )
    x0_box = None
    if x0_bounds is not None:  # (an entry held in a record is not bounded there)
        windowed = inputs.window_starts is not None
        estimated = x0_est if x0_held is None else x0_est & ~x0_held
        x0_box = check_x0_bounds(
            x0_bounds, X0.shape, X0.dtype, per_record=not windowed, estimated=estimated
        )
        # (a box, None where no entry is bounded, whose bounded entries are all held)
        if x0_box is not None and not any(np.isfinite(b).any() for b in x0_box):
            warn(
                "`x0_bounds` bounds only x0 entries that `estimate_x0` holds, and held "
                "entries keep their values in `x0`: the bounds have no effect.",
                stacklevel=3,
            )
        if x0_box is not None and np.any(x0_box[0] == x0_box[1]):
            rows, cols = np.nonzero(x0_box[0] == x0_box[1])
            pinned = sorted({int(c) for c in cols})
            warn(
                f"`x0_bounds`' lower and upper bounds are equal for x0 entries {pinned}"
                + (f" (in {len(set(rows.tolist()))} records)" if X0.shape[0] > 1 else "")
                + ": the fit holds them there, but they still count as estimated (a "
                "standard error of the linearisation, one fewer degree of freedom in "
                "sigma^2). To hold a known value, hold it (`estimate_x0=` a mask, MATLAB's "
                "`InitialStates(i).Fixed`).",
                stacklevel=3,
            )
    # The box the solvers keep x0 in: `x0_bounds`, and an entry a record holds (a mask
    # per record) bounded above and below by its value.
    solve_box = x0_box
    if x0_held is not None:
        lo, hi = (
            (np.full(X0.shape, -np.inf, X0.dtype), np.full(X0.shape, np.inf, X0.dtype))
            if x0_box is None
            else (x0_box[0].copy(), x0_box[1].copy())
        )
        lo[x0_held], hi[x0_held] = X0[x0_held], X0[x0_held]
        solve_box = (lo, hi)
    if solve_box is not None and any(isinstance(s, Optimistix) for s in solvers):
        what = (
            "`x0_bounds` is not available with `Optimistix` (optimistix has no bounds)"
            if x0_box is not None
            else "`estimate_x0` as a mask per record is not available with `Optimistix` "
            "(the entries a record holds are kept as a box of one point, and optimistix has "
            "no bounds; an (n_x,) mask, the same entries of every record, is)"
        )
        raise ValueError(f"{what}: use LevenbergMarquardt, GaussNewton, Adam, LBFGS or Optax.")
    project, sets = None, ()
    if proj is not None:
        if proj.bounds is not None:
            if free.any_fixed:
                check_fixed_bounds(data.theta, fixed_flat, *_bounds(proj, data.theta))
        else:  # a general projection: check that it is one (boxes are by construction)
            check_projection(proj, data.theta)
            project, sets = proj.project, _sets(proj)

    problem = _pytree.build(
        FitProblem,
        model=data.model,
        cost=inputs.cost,
        u=U,
        z=Z,
        theta_base=flat0,
        theta_free=free.theta_tuple,
        unravel=free.unravel,
        x0_base=X0,
        x0_free=free.x0_tuple,
        project=project,
        lower=free.lower,
        upper=free.upper,
        regulariser=on_theta,
        x0_lower=None if solve_box is None else solve_box[0][:, x0_free],
        x0_upper=None if solve_box is None else solve_box[1][:, x0_free],
        x0_held=None if x0_held is None else x0_held[:, x0_free],
        validation=None
        if validation is None
        else monitor(
            validation,
            data.model,
            data.theta,
            X0,
            inputs.cost.sqrt_weight(),
            n_u=np.shape(data.u)[-1],
            x0_box=_shared_box(x0_bounds, X0, x0_est),
        ),
        nuisance=free.nuisance,
        mask=None
        if data.mask is None
        else jax.tree_util.tree_map(
            lambda a: _host(a) if batched else np.asarray(a)[None], data.mask
        ),
    )

    # Every start as free-variable arrays (built on the host).
    if inputs.n_starts is not None:  # multistart
        starts_flat = np.stack(
            [
                _pytree.flat_host(jax.tree_util.tree_map(lambda a, i=i: a[i], inputs.theta_starts))
                for i in range(inputs.n_starts)
            ]
        ).astype(X0.dtype)
        check_fixed_starts(starts_flat, fixed_flat, data.theta, inputs.theta_held)
        x0_starts = inputs.x0_starts
        if x0_starts is not None:
            X0s = np.asarray(x0_starts if batched else x0_starts[:, None], X0.dtype)
            check_held_x0_starts(X0s, x0_est, x0_held)
        else:
            X0s = np.broadcast_to(X0, (inputs.n_starts, *X0.shape))
    else:
        starts_flat, X0s = np.asarray(flat0)[None], X0[None]
    if x0_box is not None:
        # (a window's starting state, read off z or solved for, is clipped silently)
        windowed = inputs.window_starts is not None
        X0s = clip_x0(X0s, x0_box, "x0_bounds", "fit", stacklevel=3, warning=not windowed)
    if x0_held is not None:  # (the values `x0` gives them: `check_held_x0_starts`)
        X0s = np.where(x0_held, X0, X0s)
    all_t, all_x = theta_free.size == starts_flat.shape[1], x0_free.size == n_x
    starts = Params(
        starts_flat if all_t else starts_flat[:, theta_free],
        X0s if all_x else X0s[:, :, x0_free],
    )
    return Built(problem, starts, fixed_flat, x0_est, sets, x0_box)


def _shared_box(x0_bounds, X0, estimated):
    """`fit(x0_bounds=...)` as one (lower, upper) pair (n_x,) where every record's (or
    window's) are the same, for the held-out records' initial states
    (`_validation.Monitor`); None without bounds, or where the records' differ (as
    `FitResult.predict` takes the fit's box)."""
    if x0_bounds is None:
        return None
    lo, hi = check_x0_bounds(x0_bounds, X0.shape, X0.dtype, estimated=estimated) or (None, None)
    if lo is None or not (np.all(lo == lo[0]) and np.all(hi == hi[0])):
        return None
    return lo[0], hi[0]


def _sets(t):
    """The projections onto the sets that the projection `t` intersects: each term of a
    `combine` (nested ones taken apart), or `t`'s own."""
    if not t.terms:
        return (t.project,)
    return tuple(p for s in t.terms for p in _sets(s))
