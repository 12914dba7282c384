"""`print(result)`: a `FitResult` as a report in the manner of MATLAB's nlgreyest
(`present`): the solver and why it stopped; the parameters, named, in the order theta0
was written, with units, standard errors and 95 % intervals; the initial states; the fit
to the data. Also the rows it is built from, which `fit` uses to record theta0's order
and to check `units=`."""

import warnings

import equinox as eqx
import jax
import numpy as np

from . import _pytree
from ._model import model_labels
from .metrics import residual_correlations

# The remedy where float32 normal equations cannot resolve a fit (`_fit`'s Gauss-Newton
# check): the printout's and `FitResult.message`'s words.
FLOAT64 = "fit in float64: enable jax_enable_x64 and pass float64 data"
# (the remedy where even float64's J^T J loses a direction that J resolves)
COLLINEAR = (
    "reparameterise the nearly collinear entries as the combinations the data determine "
    "(a sum and a difference, or one held)"
)


def unresolved_remedy(precision):
    """What to do where J^T J in `precision` (a dtype's name) loses a direction of J."""
    return COLLINEAR if precision == "float64" else FLOAT64


def _child(node, entry):
    """The child of `node` at one entry of a JAX key path (None where it cannot be read)."""
    if node is None:
        return None
    try:
        if isinstance(entry, jax.tree_util.DictKey):
            return node[entry.key]
        if isinstance(entry, jax.tree_util.SequenceKey):
            return node[entry.idx]
        if isinstance(entry, jax.tree_util.GetAttrKey):
            return getattr(node, entry.name)
    except (KeyError, IndexError, TypeError, AttributeError):
        pass
    return None


def _rows(theta):
    """`(name, key path, start, stop, module, shape)` per row of theta's parameters in
    JAX's leaf order: one row per leaf, except that an equinox module below the root (a
    neural residual) is one row, named by its path, with its class name as `module` (None
    for a leaf, whose `shape` is given)."""
    params, _ = _pytree.split(theta)
    rows, start = [], 0
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        size = int(np.size(leaf))
        node, module, cut = theta, None, len(path)
        for depth, entry in enumerate(path[:-1]):
            node = _child(node, entry)
            if isinstance(node, eqx.Module):
                module, cut = type(node).__name__, depth + 1
                break
        name = ".".join(_pytree._key(p) for p in path[:cut]) or "theta"
        if module is not None and rows and rows[-1][0] == name:  # the module's next leaf
            rows[-1] = (*rows[-1][:3], start + size, module, None)
        else:
            rows.append((name, path[:cut], start, start + size, module, np.shape(leaf)))
        start += size
    return rows


def theta_order(theta) -> tuple[str, ...]:
    """The names of theta's rows (`"k"`, `"phys.c"`, a module `"r"`) in the order they were
    written: dicts in their insertion order, where JAX sorts their keys."""

    def rank(path):
        node, out = theta, []
        for entry in path:
            keys = list(node) if isinstance(node, dict) else []
            # Outside dicts JAX's order is the written one: rank 0 keeps it (stable sort).
            out.append(keys.index(entry.key) if getattr(entry, "key", None) in keys else 0)
            node = _child(node, entry)
        return out

    return tuple(row[0] for row in sorted(_rows(theta), key=lambda row: rank(row[1])))


def _dotted(units: dict) -> dict:
    """Nested dicts of units ({"phys": {"k": "N/m"}}) as the rows' dotted names."""
    out = {}
    for key, value in units.items():
        if isinstance(value, dict):
            out.update({f"{key}.{k}": v for k, v in _dotted(value).items()})
        else:
            out[key] = value
    return out


def check_units(units, theta) -> dict:
    """`fit(units=...)` as a dict of strings, checked against theta's row names (nested dicts
    read as dotted names)."""
    if units is None:
        return {}
    if not isinstance(units, dict):
        raise TypeError(
            "`units` must be a dict from parameter names to unit strings, e.g. "
            f"{{'k': 'N/m'}}; got {type(units).__name__}."
        )
    valid = (*theta_order(theta), *(name for name, _ in _data(theta)))
    units = _dotted(units)
    for name, unit in units.items():
        if name not in valid:
            raise ValueError(
                f"`units` names {name!r}, which is not a parameter of theta0; valid names: "
                f"{', '.join(valid)}."
            )
        if not isinstance(unit, str):
            raise ValueError(f"`units[{name!r}]` must be a string (e.g. 'kg m^2'), got {unit!r}.")
    return dict(units)


def _interval(value, std, fixed, computed) -> str:
    """`computed`: whether the covariance was computed, or "diverged" (the fit's stop:
    the linearisation at a diverged simulation says nothing of identifiability)."""
    if fixed:
        return "(fixed)"
    if computed == "diverged":
        return "(undefined: diverged)"
    if not computed:
        return "(not computed)"
    if not np.isfinite(std):
        if computed == "no_dof":
            return "(unknown: no more data than estimates)"
        if isinstance(computed, str):  # (a precision below float64: `_computed`)
            return f"(not resolved in {computed})"
        return "(not identifiable)"
    d = _digits(value, std)
    return f"[{value - 1.96 * std:.{d}g}, {value + 1.96 * std:.{d}g}]"


def _digits(value, std) -> int:
    """Significant digits that show an estimate's standard error: 6, or more where it is
    below 1e-4 of the value (an interval printed [2, 2] at 6 digits), at most 17."""
    if not (np.isfinite(value) and np.isfinite(std)) or std <= 0 or value == 0:
        return 6
    return int(min(17, max(6, np.ceil(np.log10(abs(value) / std)) + 2)))


def _std(std, computed) -> str:
    """A standard error as printed: none after a diverged fit (its linearisation)."""
    return "-" if computed == "diverged" else f"{std:.3g}"


def _computed(result):
    """Whether the covariance was computed: an empty one stands for "not computed" (above
    the size limit) only where some entry of theta is free; "diverged" after that stop;
    "no_dof" where the fit had no more measured output values than estimated entries
    (sigma^2 unknown: every standard error inf, identifiable or not); the precision's
    name where it was computed below float64 (an inf standard error is then J^T J's
    round-off, not resolved in that precision, `below_float64`)."""
    if result.status == "diverged":
        return "diverged"
    if (result.diagnostics or {}).get("degrees_of_freedom", 1) <= 0:
        return "no_dof"
    computed = np.shape(result.covariance) != (0, 0) or bool(np.all(result.fixed))
    low = below_float64(np.asarray(result.x0).dtype)
    return low if computed and low is not None else computed


def _has_intervals(result) -> bool:
    """Whether the printout shows standard errors and intervals (`_computed`: not after a
    divergence, without a covariance or without degrees of freedom)."""
    return _computed(result) not in (False, "diverged", "no_dof")


def below_float64(dtype):
    """The name of `dtype` where it is a floating precision below float64, else None."""
    dtype = np.dtype(dtype)
    if not np.issubdtype(dtype, np.floating):
        return None
    return dtype.name if np.finfo(dtype).eps > np.finfo(np.float64).eps else None


def _entry_names(name, shape):
    if not shape:
        return [name]
    if len(shape) == 1:
        return [f"{name}[{i}]" for i in range(shape[0])]
    return [f"{name}[{', '.join(map(str, ix))}]" for ix in np.ndindex(shape)]


def _module_row(module, values, fixed) -> str:
    """A module in a few words: its class, its number of weights, how many are fixed
    and (a sparse residual) how many are exactly zero."""
    n, n_fixed = values.size, int(np.sum(fixed))
    desc = f"{module}, {n} weights"
    if n_fixed == n:
        return desc + " (fixed)"
    if n_fixed:
        desc += f", {n_fixed} fixed"
    n_zero = int(np.sum(values == 0))
    return desc + (f", {n_zero} zero" if n_zero else "")


# An array parameter of more entries than this prints as one line (`_array_row`).
ARRAY_ROWS = 100


def _array_row(shape, values, fixed) -> str:
    """An array parameter of many entries in a few words: its shape, its range, how many
    entries are fixed (its values and standard errors: `result.theta`, `result.std`)."""
    n, n_fixed = values.size, int(np.sum(fixed))
    desc = f"array of shape {tuple(shape)}, {n} numbers in [{values.min():.4g}, "
    desc += f"{values.max():.4g}]"
    if n_fixed:
        desc += " (fixed)" if n_fixed == n else f", {n_fixed} fixed"
    return desc + " (each in result.theta, result.std)"


def _parameter_table(result):
    """The parameter rows (name, unit, value, std, interval) in theta0's order, and the
    indices of the module rows (name, unit and a description only)."""
    params, _ = _pytree.split(result.theta)
    flat, std = _pytree.flat_host(params), _pytree.flat_host(result.std)
    fixed = np.asarray(result.fixed, bool)
    computed = _computed(result)
    order = {name: i for i, name in enumerate(result.theta_order)}
    rows = sorted(_rows(result.theta), key=lambda row: order.get(row[0], len(order)))
    table, modules = [], set()
    for name, _, a, b, module, shape in rows:
        unit = result.units.get(name, "")
        if module is not None:
            modules.add(len(table))
            table.append((name, unit, _module_row(module, flat[a:b], fixed[a:b]), "", ""))
            continue
        if b - a > ARRAY_ROWS:  # (a 256 x 256 matrix printed 65536 rows)
            modules.add(len(table))
            table.append((name, unit, _array_row(shape, flat[a:b], fixed[a:b]), "", ""))
            continue
        for i, entry in enumerate(_entry_names(name, shape), start=a):
            v, s = flat[i], std[i]
            table.append(
                (
                    entry,
                    unit,
                    f"{v:.{_digits(v, s) if not fixed[i] else 6}g}",
                    _std(s, computed),
                    _interval(v, s, fixed[i], computed),
                )
            )
    table.extend(_data_rows(result))
    return table, modules


def _data(theta, listed_max=12):
    """`(name, leaf)` for the numbers of theta that are data, not parameters (an integer
    such as an exponent or an index, a boolean; at most `listed_max` entries each).
    Those inside an equinox module (its activation, its sizes) are the module's own."""
    _, static = _pytree.split(theta)
    if static is None:
        return []
    out = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(static)[0]:
        if not isinstance(leaf, (int, np.integer, np.bool_, np.ndarray, jax.Array)):
            continue
        if np.size(leaf) > listed_max or np.asarray(leaf).dtype.kind not in "biu":
            continue
        node = theta
        for entry in path[:-1]:
            node = _child(node, entry)
            if isinstance(node, eqx.Module):
                break
        if not isinstance(node, eqx.Module):
            out.append((".".join(_pytree._key(p) for p in path) or "theta", leaf))
    return out


def _data_rows(result):
    """The rows of theta's data (`_data`): their values, "(data, not estimated)"."""
    rows = []
    for name, leaf in _data(result.theta):
        unit = result.units.get(name, "")
        values = np.ravel(np.asarray(leaf))
        for entry, v in zip(_entry_names(name, np.shape(leaf)), values, strict=True):
            rows.append((entry, unit, f"{v}", "", "(data, not estimated)"))
    return rows


# The output weights `print(result)` shows; more are summed up by their count.
SHOWN_WEIGHTS = 8


def _weight_text(weight):
    """The output weight Q in a few words: its diagonal, and whether it has more (None:
    the identity)."""
    if weight is None:
        return "= I"
    w = np.atleast_1d(np.asarray(weight, float))
    diag = w if w.ndim == 1 else np.diag(w)
    shown = [f"{v:.4g}" for v in diag[:SHOWN_WEIGHTS]]
    more = f", ... ({len(diag)} outputs)" if len(diag) > SHOWN_WEIGHTS else ""
    text = "diagonal [" + ", ".join(shown) + more + "]"
    if w.ndim == 2 and np.any(w != np.diag(diag)):
        text += " and off-diagonal terms (`result.weight`)"
    return text


def _readings_text(result):
    """With `weight="noise"` and aggregated readings: the factors their weights got."""
    factors = (result.stop_info or {}).get("reading_weight_factors")
    if not factors:
        return ""
    shown = ", ".join(f"{f:.4g}" for f in factors[:SHOWN_WEIGHTS])
    more = f", ... ({len(factors)} Aggregates)" if len(factors) > SHOWN_WEIGHTS else ""
    return f"; the readings' weights times [{shown}{more}] (one per Aggregate)"


def _x0_table(result, shown_max=3):
    """The initial-state rows: every entry of one trajectory, or of the first two of more
    than `shown_max` (a window's with the sample it starts at); and the number of
    trajectories left out."""
    x0, x0_std = np.asarray(result.x0), np.asarray(result.x0_std)
    batched = x0.ndim == 2
    X0, S0 = (x0, x0_std) if batched else (x0[None], x0_std[None])
    # (n_x,) for every record, or (N, n_x): a mask per record
    estimated = np.broadcast_to(np.asarray(result.x0_estimated, bool), X0.shape)
    computed = _computed(result)
    n_traj, n_x = X0.shape
    shown = n_traj if n_traj <= shown_max else 2
    if batched and not estimated.any():
        return [], n_traj
    names = model_labels(getattr(result.model, "states", None), n_x) or range(n_x)
    # A windowed fit's rows: each window's state at its first sample of the record.
    starts = getattr(result, "window_starts", None)
    table = []
    for i in range(shown):
        at = "" if starts is None else f" (sample {int(starts[i])})"
        for j, name in zip(range(n_x), names, strict=True):
            entry = f"x0[{i}, {name}]{at}" if batched else f"x0[{name}]"
            v, s = X0[i, j], S0[i, j]
            table.append(
                (
                    entry,
                    "",
                    f"{v:.{_digits(v, s) if estimated[i, j] else 6}g}",
                    _std(s, computed),
                    _interval(v, s, not estimated[i, j], computed),
                )
            )
    return table, n_traj - shown


def _seconds(t: float) -> str:
    return f"{t:.3g}" if t < 1000 else f"{t:.0f}"


def vanished_note(names) -> str:
    """What the columns that vanished along the fit mean (`stop_info["vanished"]`)."""
    listed = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
    return (
        f"The Jacobian columns of {listed} vanished along the fit (shrunk 1e4 times more "
        "than the least-shrunk column): a term that switched itself off (a gain at 0, a "
        "closed gate, a dead unit), at a minimum or on a plateau; if it should act, start "
        "it elsewhere"
    )


def without_effect_note(names, acting=None) -> str:
    """What the parameters a success left where they have no effect mean
    (`stop_info["without_effect"]`, `_zero_gradient`); with `acting` ({name: a value
    where it acts}), each name says where it acts (the warning's text)."""
    shown = [n if acting is None else f"{n} (acts at {acting[n]:.3g})" for n in names[:8]]
    listed = ", ".join(shown) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
    return (
        f"{listed} never moved from the start, where the outputs do not depend on them "
        "(Jacobian columns exactly zero there and a little away), though they do "
        "elsewhere: the start lies on a flat piece of the model (a saturation or dead zone "
        "beyond the data's range, a relu, max or clip that is off), where any first-order "
        "test passes; start them where they act"
    )


def _stationary(result) -> bool:
    """Whether the returned point passed the first-order test (its measure at most gtol),
    as the status line judges a stop by a user's threshold (`stop_detail`)."""
    info = result.stop_info or {}
    fo, gtol = info.get("first_order", np.nan), info.get("gtol", np.nan)
    return not (np.isfinite(fo) and fo > gtol)


def _per_record_fit(result, rows, outputs, listed_max=6) -> list[str]:
    """The line of FIT% per trajectory (or window) of a fit of several: each one's
    values, or for more than `listed_max` the lowest and highest per output (none for a
    result saved before `fit_percent_per_record` existed); with the model's `outputs`
    names where it has them."""
    per = result.metrics.get("fit_percent_per_record")
    if per is None:
        return []
    per = np.asarray(per, dtype=np.float64)
    per = per.reshape(per.shape[0], -1)

    def values(v):
        return "[" + _per_output([f"{f:.2f}" for f in v], outputs) + "]"

    one = "window" if rows == "windows" else "trajectory"
    if per.shape[0] <= listed_max:
        return [f"FIT% per {one}: {', '.join(values(v) for v in per)}"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an output never measured: NaN)
        low, high = np.nanmin(per, axis=0), np.nanmax(per, axis=0)
    return [
        f"FIT% per {one}: from {values(low)} to {values(high)} over the {per.shape[0]} "
        f"{rows} (result.metrics['fit_percent_per_record'])"
    ]


def returned_start(result) -> bool:
    """Whether a diverged fit whose returned loss is not finite returned its start: it
    stopped at step 0, where the start's loss was not finite (the library's solvers keep
    their last finite iterate; a solver of one's own that does not returns its own
    non-finite point)."""
    return result.stop_info.get("at_step") in (0, None)


def _any_point_sample(residuals) -> bool:
    """Whether a fit's residuals (an array, or a list of ragged records) hold a finite
    entry: a point sample of some output (an aggregated fit may have readings only)."""
    records = residuals if isinstance(residuals, (list, tuple)) else [residuals]
    return any(np.isfinite(np.asarray(r, dtype=float)).any() for r in records)


def _per_output(values, outputs) -> str:
    """Values of each output, with the model's output names where it has them."""
    names = model_labels(outputs, len(values))
    if names is None:
        return ", ".join(values)
    return ", ".join(f"{o}: {v}" for o, v in zip(names, values, strict=True))


# The words of `fit`'s warning of outputs of unequal noise (`_fit._warn_unequal_noise`),
# by which the non-white line knows that the fit warned of them.
UNEQUAL_NOISE = "differ in variance by a factor"


def _whiteness_note(result, outputs) -> str | None:
    """The printout's line where the residuals are not white by MATLAB's `resid` test
    (`metrics.residual_correlations` at its defaults, lags 1..min(25, T - 1), each record
    or window on its own), for the outputs the fit weighs; None where they are, or where
    there is nothing to test (a zero residual, a diverged fit, a loss that is not
    finite). A model error, coloured noise and a bad minimum leave such residuals (and a
    weight far from unequal noise levels, where the fit warned of them), and the
    classical standard errors, where the printout has them, assume white ones."""
    e = np.asarray(result.residuals, np.float64)
    if result.status in ("zero_residual", "diverged") or not np.isfinite(float(result.loss)):
        return None  # (nothing to test, or a point that is not a fit's: a divergence's)
    if e.ndim < 2:
        return None
    T = e.shape[-2]
    if T < 3:
        return None
    # (an output reproduced exactly, a zero residual, has no correlations: the others')
    flat = e.reshape(-1, e.shape[-1])
    noisy = np.flatnonzero(np.any(np.isfinite(flat) & (flat != 0), axis=0))
    if not noisy.size:
        return None
    try:
        rc = residual_correlations(e[..., noisy], None, min(25, T - 1))
    except ValueError:  # (an output with fewer than two measured samples, or none left)
        return None
    weight = getattr(result, "weight", None)
    weighed = np.ones(e.shape[-1], bool)
    if weight is not None:
        q = np.asarray(weight)
        weighed = (q if q.ndim == 1 else np.diag(q)) > 0
    # (i: the column of `rc`, k: the output)
    bad = [(i, int(noisy[i])) for i in np.flatnonzero(~np.atleast_1d(rc.white))]
    bad = [(i, k) for i, k in bad if weighed[k]]
    if not bad:
        return None
    names = model_labels(outputs, e.shape[-1])
    lag = len(rc.lags) // 2 + 1  # (the row of lag 1)
    said = [
        f"{names[k] if names is not None else f'output {k}'}: r_e(1) = "
        f"{float(rc.auto[lag, i]):.3g}, {100 * float(rc.auto_outside[i]):.0f} % of the lags "
        f"outside +-{float(rc.bound[i]):.3g}"
        for i, k in bad[:3]
    ]
    more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
    robust = (result.diagnostics or {}).get("covariance_lags") is not None
    errors = (
        ""
        if robust or not _has_intervals(result)
        else "; the standard errors assume white residuals (`covariance=oj.NeweyWest()` "
        "allows for correlated ones)"
    )
    # (a weight far from the outputs' noise levels lets the noisy output pull the others
    # off their own fit: the fit's unequal-noise warning names it)
    unequal = any(UNEQUAL_NOISE in w for w in getattr(result, "warnings", ()))
    causes = (
        "a weight far from the outputs' unequal noise (see the warning below), a model "
        "error, coloured noise or a bad minimum"
        if unequal
        else "a model error, coloured noise or a bad minimum"
    )
    return (
        f"  residuals not white ({'; '.join(said)}{more}; 99 % band, lags 1.."
        f"{int(np.max(rc.lags))}): {causes}"
        f"{errors}; `oj.plot.resid(result.residuals)` shows them"
    )


def _loss_meaning(result) -> str:
    """What the printed loss is: C of eq. (5) (with a regulariser g or a penalty, eq. 21,
    added)."""
    out = "the samples' mean of e'Qe, e the output error"
    diagnostics = result.diagnostics or {}
    if diagnostics.get("regularised"):
        out += ", plus the regulariser"
    elif diagnostics.get("penalised"):
        out += ", plus the penalty"
    return out


def report(result) -> str:
    """What `print(result)` shows (see `FitResult`)."""
    table, modules = _parameter_table(result)
    x0_table, left_out = _x0_table(result)
    header = ("parameter", "unit", "value", "std", "95% interval")
    x0_header = ("initial state", "", "value", "std", "95% interval")
    cells = [header, x0_header, *x0_table, *(r for k, r in enumerate(table) if k not in modules)]
    cells += [(table[k][0], table[k][1], "", "", "") for k in modules]
    w = [max(len(c[k]) for c in cells) for k in range(4)]
    has_units = any(r[1] for r in table)

    def line(r, module=False):
        unit = f"{r[1]:<{w[1]}}  " if has_units else ""
        if module:
            return f"  {r[0]:<{w[0]}}  {unit}{r[2]}"
        return f"  {r[0]:<{w[0]}}  {unit}{r[2]:>{w[2]}}  {r[3]:>{w[3]}}  {r[4]}".rstrip()

    fixed = np.asarray(result.fixed, bool)
    estimated = np.asarray(result.x0_estimated, bool)
    x0 = np.asarray(result.x0)
    states = f"{int(estimated.sum())} of {estimated.size} initial states"
    # A windowed fit (multiple shooting) has one initial state per window.
    rows = "windows" if result.window_starts is not None else "trajectories"
    row = "window" if rows == "windows" else "trajectory"
    count = f"{x0.shape[0]} {row if x0.shape[0] == 1 else rows}"
    if estimated.ndim == 2:  # (a mask per trajectory)
        states += f" ({count}, each its own)"
    elif x0.ndim == 2:
        states += f" (per {row}, {count})"
    solvers = " then ".join(str(s.get("solver", "?")) for s in result.solver) or "?"
    # The stop: FitResult.message's first part (the test that fired, with its values, or
    # the reason's own words), never the RESULTS repr.
    stop = " ".join(result.message.split(";")[0].split())
    out = [
        f"oneshot_jax fit by {solvers}: {int(np.sum(~fixed))} of {fixed.size} parameters "
        f"and {states} estimated",
        f"status: {result.status} ({stop})",
        f"loss {float(result.loss):.6e} ({_loss_meaning(result)}) after {result.num_steps} "
        f"steps in "
        f"{_seconds(result.wall_time)} s (wall; a first call includes compiling)",
    ]
    if result.validation_loss is not None:
        out.append(f"validation loss {result.validation_loss:.6e} (held-out records)")
    if result.starts is not None:

        def counts(reasons):
            tally = {}
            for r in reasons:
                tally[r] = tally.get(r, 0) + 1
            return ", ".join(f"{k} {n}" for k, n in tally.items())

        starts = result.starts
        own = ""
        if starts.solver_stop != starts.stop_reason:  # (validation or the rollout check)
            own = f" (the solvers' own stops: {counts(starts.solver_stop)})"
        scores = starts.validation_loss
        by = (
            " by validation loss"
            if scores is not None and np.any(np.isfinite(np.asarray(scores)))
            else ""
        )
        out.append(
            f"multistart: the best of {len(starts.stop_reason)} starts{by} (index "
            f"{result.best}); stops: {counts(starts.stop_reason)}{own}"
        )
    if result.status == "diverged":
        # (Where no iterate had a finite loss, the start is returned: `FitResult.message`.)
        which = "the returned point is its last finite iterate"
        if not np.isfinite(result.loss):
            which = (
                "the returned point is its start (no iterate was finite)"
                if returned_start(result)
                else "the solver returned a point that is not finite"
            )
        out.append(f"  (not a solution: the fit diverged; {which}, without standard errors)")
    elif not result.success:
        out.append(
            "  (not a solution: the standard errors and intervals below are those of the "
            "linearisation at the returned point)"
            if _computed(result)
            else "  (not a solution: see the status)"
        )
        if result.stop_info.get("regular_jacobian"):  # (`_fit._flag_unresolved_success`)
            out.append(
                "  (the Jacobian has full rank: the inf standard errors below come from "
                "J^T J, which loses a direction the data determine; the Gauss-Newton step "
                f"from the Jacobian moves the estimates by "
                f"{result.stop_info['gauss_newton_se']:.3g} standard errors; try another "
                "start, shorter windows, or bounds that keep the model stable)"
            )
        elif "gauss_newton_se" in result.stop_info:  # (`_fit._flag_unresolved_success`)
            precision = result.stop_info.get("precision", "this precision")
            out.append(
                f"  ({precision} cannot resolve this problem in J^T J: the Gauss-Newton "
                f"step from the Jacobian moves the estimates by "
                f"{result.stop_info['gauss_newton_se']:.3g} standard errors; "
                f"{unresolved_remedy(precision)})"
            )
    elif result.status in ("tol_loss", "tol_grad") and not _stationary(result):
        # (a success by the user's threshold, at a point the first-order test rejects)
        out.append(
            f"  (not a stationary point: {result.status} stopped the fit by your threshold"
            + (
                "; the standard errors and intervals below are those of the linearisation "
                "at the returned point, not of an estimate)"
                if _computed(result)
                else ")"
            )
        )
    kept = (result.diagnostics or {}).get("unconverged_rollouts")
    # (A success had the returned point's own rollout checked, and `unconverged_rollout`
    # says it itself; another stop's numbers may be the rollouts'.)
    if kept and not result.success and result.status != "unconverged_rollout":
        out.append(
            f"  ({kept} of {result.diagnostics.get('parallel_rollouts', '?')} parallel "
            "rollouts kept Newton's unconverged iterate (`ParallelInTime(fallback=False)`): "
            "the loss, metrics and standard errors below may be computed from states that "
            "are not the model's; `oneshot_jax.loss` with a sequential strategy gives the "
            "model's loss)"
        )
    if (result.diagnostics or {}).get("regularised") and _computed(result):
        out.append(
            "  (regularised: the standard errors and intervals below are those of the "
            "smooth loss at the shrunk estimate, without the regulariser, so they sit around "
            "a biased value and zeros get some too; for inference refit the selected terms "
            "with `fixed=sparsity.fixed_zeros(result.theta, where)`)"
        )
    if (result.diagnostics or {}).get("penalised") and _computed(result):
        out.append(
            "  (penalised: the standard errors and intervals below are those of the data "
            "term at the penalised estimate; the penalty lambda h does not enter them as "
            "information)"
        )
    rounds = (result.stop_info or {}).get("noise_weight_rounds")
    if rounds is not None:
        starts = ", the starts those of the first (Q = I)" if result.starts is not None else ""
        fits = f"{rounds} fits, the last one shown, its steps and time those of all {rounds}"
        if result.stop_info.get("noise_weight_estimated", True) is False:
            out.append('  (weight="noise": no output weight estimated, see the warning; Q = I)')
        elif rounds > 1:
            out.append(
                f'  (weight="noise": the output weight estimated from the residuals over '
                f"{fits}{starts}; Q {_weight_text(result.weight)}{_readings_text(result)})"
            )
        else:
            out.append(
                '  (weight="noise": the output weight estimated from the residuals of one '
                f"fit; Q {_weight_text(result.weight)}{_readings_text(result)})"
            )
    elif getattr(result, "weight", None) is not None:
        out.append(f"  (output weight Q {_weight_text(result.weight)}, as given)")
    lags = (result.diagnostics or {}).get("covariance_lags")
    if lags is not None:
        out.append(
            f"  (standard errors: Newey-West sandwich over {lags} lags, for residuals "
            "correlated in time)"
        )
    out.append(line(header))
    out.extend(line(r, k in modules) for k, r in enumerate(table))
    if not table:
        out.append("  (none: the model has no parameters, theta holds no floating leaf)")
    out.append(line(x0_header))
    out.extend(line(r) for r in x0_table)
    if not x0_table and np.shape(result.x0)[-1] == 0:
        out.append("  (none: the model has no state, n_x = 0)")
    elif not x0_table:
        out.append(f"  (fixed, not estimated: result.x0, {left_out} {rows})")
    elif left_out:
        out.append(f"  ... and {left_out} more {rows} (result.x0, result.x0_std)")
    outputs = getattr(result.model, "outputs", None)  # (a result loaded without a model)
    fitp = _per_output([f"{f:.2f}" for f in np.ravel(result.metrics["fit_percent"])], outputs)
    rmse = _per_output([f"{f:.4g}" for f in np.ravel(result.metrics["rmse"])], outputs)
    aic = float(result.metrics["aic"])
    fpe = result.metrics.get("fpe")  # (a result saved before FPE was reported has none)
    if np.isnan(aic):
        why = "fewer samples measure every output than there are outputs"
        if not np.isfinite(float(result.loss)):
            why = "the loss is not finite"
        elif not _any_point_sample(result.residuals):
            why = "no output has a point sample: aggregated readings only"
        criteria = f"AIC nan ({why})"
    else:
        criteria = f"AIC {aic:.4g}" + ("" if fpe is None else f"  FPE {float(fpe):.4g}")
    scores = f"FIT% [{fitp}]  RMSE [{rmse}]  {criteria}"
    if x0.ndim == 2 and x0.shape[0] > 1:
        # Pooled: each record against the mean of all (MATLAB's compare: one per experiment)
        out.append(f"pooled over the {x0.shape[0]} {rows}: {scores}")
        out.extend(_per_record_fit(result, rows, outputs))
    else:
        out.append(scores)
    white = _whiteness_note(result, outputs)
    if white is not None:
        out.append(white)
    at_bound = (result.stop_info or {}).get("at_bound")
    if at_bound:
        listed = ", ".join(at_bound[:8]) + (
            f" and {len(at_bound) - 8} more" if len(at_bound) > 8 else ""
        )
        out.append(
            f"  at a bound: {listed}"
            + (
                " (the intervals ignore the bound, which cuts the estimate's distribution)"
                if _has_intervals(result)
                else ""
            )
        )
    gone = (result.stop_info or {}).get("vanished")
    if gone:
        out.append(f"  ({vanished_note(gone)})")
    idle = (result.stop_info or {}).get("without_effect")
    if idle:
        out.append(f"  ({without_effect_note(idle)})")
    if result.window_starts is not None:
        # Multiple shooting restarts every window from its own fitted x0: the model's own
        # open-loop fit of the record can be far lower.
        out.append(
            f"  (over the {len(result.window_starts)} windows, each from its own fitted x0: "
            "not a simulation of the whole record; see result.simulate or result.predict)"
        )
    # (what `fit` warned of, also where the filters hid it: `FitResult.warnings`)
    out.extend(f"warning: {message}" for message in getattr(result, "warnings", ()))
    return "\n".join(out)
