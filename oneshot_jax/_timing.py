"""Time-stamped records: the sample times `t` checked, and the intervals appended to u.

A model of time-stamped records (`Model.timed`, built by `Model.from_ode(rhs, dt=None)`)
integrates step k over its own interval t[k+1] - t[k]. The interval enters the step as
data: `append_intervals` adds it to the input record as one more column (0 after each
record's last sample, where no step follows and where a padded trajectory repeats its
last row, so that the padding leaves the state unchanged). The step reads it from there
and the observation never sees it (`_model._TimedODEStep`, `_model._WithoutInterval`).
Every rollout, strategy, solver, window and x0 path then works on the augmented record
unchanged, and the closed-form derivatives of eq. (17)/(20) stay exact: an interval is a
constant of the step, like u[k]. `check_data` calls these functions after it has checked
u, so that its errors about u name the user's n_u.
"""

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._caller_warnings import warn


class Intervals(NamedTuple):
    """Intervals already checked and laid out like u's leading axes (*N, T), the last of
    each record 0: what `split_intervals` takes back off an augmented record (the windows
    of `fit(window=...)`), passed as `t` again."""

    dt: Any


def _is_tracer(a) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(a))


def as_times(a, name):
    """One record's time stamps as a 1-D float64 NumPy array (or a traced array)."""
    if _is_tracer(a):
        return a
    if isinstance(a, (str, bytes, dict)) or a is None:
        raise TypeError(
            f"`{name}` must be an array of sample times (increasing numbers), got "
            f"{type(a).__name__}."
        )
    try:
        arr = np.asarray(a)
    except (TypeError, ValueError) as err:
        raise TypeError(f"`{name}` must be an array of sample times, got {a!r}.") from err
    if arr.dtype.kind in "mM":  # (NumPy counts a timedelta64 as an integer: of its unit)
        raise TypeError(
            f"`{name}` must hold real numbers in the model's time unit, got dtype "
            f"{arr.dtype}: convert it, e.g. `(t - t[0]) / np.timedelta64(1, 's')` for seconds."
        )
    if arr.dtype == bool or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise TypeError(
            f"`{name}` must hold real numbers (the sample times), got dtype {arr.dtype}."
        )
    return arr.astype(np.float64)


def _intervals(t, name, T, of="`u`"):
    """t[k+1] - t[k] of one record of T samples (the samples `of` what), with 0 appended:
    (T,). Warns where `t` came in a precision that leaves its intervals fewer than 3 digits
    (float32 stamps far from 0: 1e6 + k 0.1 s rounds to steps of 0.0625 s)."""
    given = None if _is_tracer(t) else getattr(t, "dtype", None)
    t = as_times(t, name)
    if t.ndim != 1 or t.shape[0] != T:
        raise ValueError(
            f"`{name}` must have shape ({T},): one time stamp per sample of {of} (T = {T}), "
            f"got shape {t.shape}."
        )
    if _is_tracer(t):
        return jnp.concatenate([jnp.diff(t), jnp.zeros((1,), t.dtype)])
    if not np.all(np.isfinite(t)):
        raise ValueError(f"`{name}` contains NaN or inf values: sample times must be finite.")
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.flatnonzero(dt <= 0)[0])
        raise ValueError(
            f"`{name}` must be strictly increasing: {name}[{k + 1}] = {float(t[k + 1])!r} "
            f"does not come after {name}[{k}] = {float(t[k])!r}."
        )
    if given is not None and np.issubdtype(given, np.floating) and dt.size:
        top = float(np.max(np.abs(t)))
        resolution = float(np.finfo(given).eps) * top
        if resolution > 1e-3 * float(np.min(dt)):
            warn(
                f"`{name}` is stored in {given}, whose resolution at |{name}| up to "
                f"{top:.3g} is {resolution:.2g}, "
                f"{resolution / float(np.min(dt)):.2g} of the shortest interval: the "
                "intervals have lost digits before the fit sees them. Pass the time stamps "
                f"in float64, or relative to the record's start ({name} - {name}[0]).",
                UserWarning,
                stacklevel=2,
            )
    return np.concatenate([dt, np.zeros(1)])


def check_times(model, t, shape, lengths, dtype, step=None):
    """The intervals of the sample times `t` for a model and checked u, or None for a
    model that is not timed (which refuses `t`).

    **Arguments:**

    - `model`: the `Model`; `step`: the step to ask for `check_intervals` (the model's
        own step where it is bound to theta's static part).
    - `t`: (T,) for one record; (N, T), (T,) shared, or a list of N arrays (T_i,) for N
        records; or `Intervals`.
    - `shape`: u's leading axes (*N, T) (padded); `lengths`: each trajectory's T_i for
        ragged lists, else None; `dtype`: the data's floating dtype.

    **Returns:**

    The intervals (*N, T) in `dtype` (0 after each record's last sample and on padding).
    """
    if not model.timed:
        if t is not None:
            raise ValueError(
                "`t` (sample times) needs a model of time-stamped records, "
                "`Model.from_ode(rhs, dt=None, ...)`: this model has a fixed sample interval "
                "(a discrete-time `Model`, or `from_ode` with `dt`)."
            )
        return None
    if t is None:
        raise ValueError(
            "this model integrates over the intervals between time stamps "
            "(`Model.from_ode(rhs, dt=None)`): pass the sample times as `t=`, shape (T,) "
            "for one record, (N, T) or a list of arrays for several."
        )
    if isinstance(t, Intervals):
        return t.dt
    T = shape[-1]
    if len(shape) == 1:
        dt = _intervals(t, "t", T)
    elif lengths is not None:  # ragged lists: one array per trajectory
        if not isinstance(t, (list, tuple)) or len(t) != shape[0]:
            got = f"{len(t)} items" if isinstance(t, (list, tuple)) else type(t).__name__
            raise ValueError(
                f"`t` must be a list of {shape[0]} arrays of sample times (one per "
                f"trajectory of `u`, of lengths {list(lengths)}), got {got}."
            )
        parts = [_intervals(t_i, f"t[{i}]", n) for i, (t_i, n) in enumerate(zip(t, lengths))]
        dt = np.stack([np.concatenate([p, np.zeros(T - p.shape[0])]) for p in parts])
    else:
        if isinstance(t, (list, tuple)):
            if len(t) != shape[0]:
                raise ValueError(
                    f"`t` holds {len(t)} arrays of sample times but `u` has {shape[0]} "
                    "trajectories."
                )
            parts = [_intervals(t_i, f"t[{i}]", T) for i, t_i in enumerate(t)]
        else:
            arr = as_times(t, "t")
            if arr.ndim == 1:  # the same time stamps for every trajectory
                parts = [_intervals(arr, "t", T)] * shape[0]
            elif arr.shape[0] != shape[0] or arr.ndim != 2:
                raise ValueError(
                    f"`t` must have shape ({shape[0]}, {T}) (one row of sample times per "
                    f"trajectory of `u`) or ({T},), got shape {arr.shape}."
                )
            else:
                parts = [_intervals(arr[i], f"t[{i}]", T) for i in range(shape[0])]
        dt = jnp.stack(parts) if _is_tracer(parts) else np.stack(parts)
    check = getattr(step, "check_intervals", None)
    if check is not None and not _is_tracer(dt):
        check(np.asarray(dt, dtype))
    return dt.astype(dtype)


def append_intervals(u, dt):
    """u (*N, T, n_u) with the intervals dt (*N, T) as its last column: (*N, T, n_u + 1)."""
    if dt is None:
        return u
    if (
        _is_tracer(u)
        or _is_tracer(dt)
        or any(isinstance(a, jax.Array) and len(a.sharding.device_set) > 1 for a in (u, dt))
    ):  # (traced, or a fleet sharded over devices: kept where it lies)
        return jnp.concatenate([u, jnp.asarray(dt, u.dtype)[..., None]], axis=-1)
    return np.concatenate([np.asarray(u), np.asarray(dt, u.dtype)[..., None]], axis=-1)


def split_intervals(model, u):
    """An augmented record (or its windows) back into the user's u and its `Intervals`;
    `(u, None)` for a model that is not timed."""
    if not model.timed:
        return u, None
    return u[..., :-1], Intervals(u[..., -1])


def head_times(t, T, n):
    """The first n of one record's time stamps `t` (T,) (`estimate_x0` uses the head of a
    record), after checking all of `t` as `predict` does (one stamp per sample of u,
    finite, strictly increasing); None stays None."""
    if t is None:
        return None
    arr = as_times(t, "t")
    _intervals(arr, "t", T)
    return arr[:n]
