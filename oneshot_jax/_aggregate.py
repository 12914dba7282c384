"""Aggregated observations: an output measured as a sum, mean or integral over an interval
of samples (a meter read once a day, a lab assay averaged over a shift) instead of at an
instant, entering the loss of eq. (4)/(5) through the aggregated prediction.

The aggregation is made exact and local by accumulator states. A reading i of channel c
is a row of an aggregation matrix, r_i = sum_k A_ik y_c[k] with y = g(x, u, theta) (eq. 1),
nonzero on the samples [start_i, stop_i). The readings of one channel are split into groups
whose spans do not overlap; each group gets an accumulator state s_j, driven by two input
columns, a reset rho_jk (1 at the first sample of a span) and a weight a_jk (A_ik on the
span, 0 elsewhere):

    s_j[k+1] = (1 - rho_jk) s_j[k] + a_jk y_c(x_k, u_k),

and an extra output, (1 - rho_jk) s_j[k] + a_jk y_c(x_k, u_k), which at the span's last
sample stop_i - 1 equals r_i. The reading is placed there in the extra column of z (NaN,
masked, elsewhere). The augmented model is a `Model` like any other, so the rollout, the
one-shot recursion of eq. (17)/(20) (the error at a reading flows back through s_j to every
sample it covers), the forward sensitivities and every solver apply unchanged and exactly.
The accumulators' initial states are 0 and never estimated.

A reading's weight w_i enters as sqrt(w_i) on its row of A and on its value, with weight 1
on the extra output, so the loss is

    C = (1/T) [ sum_k e_k^T Q e_k + sum_i w_i (r_i - v_i)^2 ]

with T the number of time points (as without readings: the readings add terms, not time
points) and the point samples' e_k masked where missing.
"""

import dataclasses
import math
from typing import Any, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import metrics as _metrics
from ._checks import as_float, x0_mask
from ._model import ODE_STEPS, Model
from ._timing import _intervals, _is_tracer

KINDS = ("sum", "mean", "integral", "time_mean")


def _is_int(v):
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


class Aggregate:
    """Aggregated readings of one output channel: each reading is a sum, mean or integral
    of the channel's prediction over an interval of samples, not a sample at an instant.

    Give either `intervals` with a `kind`, or a general aggregation `matrix`:

    - `intervals`: (start, stop) sample indices, half-open [start, stop) as Python slices
        (the samples start, ..., stop - 1); intervals may overlap. The reading is
        `kind` of y_c over those samples: `"sum"` (sum_k y_c[k]), `"mean"` (the sum over
        stop - start), `"integral"` (the trapezoid rule over the samples' time stamps
        t[start], ..., t[stop - 1] of a time-stamped record, over t_k = k dt for a
        `Model.from_ode` with a fixed dt, over unit spacing for a discrete-time model)
        or `"time_mean"` (the integral over its duration t[stop - 1] - t[start]). The two
        last need at least two samples per interval.
    - `matrix`: an (m, T) array whose row i holds the weights A_ik of reading i,
        r_i = sum_k A_ik y_c[k] (T the record's length; each row with a nonzero entry).

    Pass it to `loss`, `value_and_grad` or `fit` as `aggregate=`, with z's column
    `channel` holding the channel's point samples where there are any and NaN elsewhere
    (`missing="mask"`; an all-NaN column for a channel measured only in aggregate).

    **Arguments:**

    - `channel`: the index of the aggregated output of z (of the model's `observe`).
    - `intervals`: a list of (start, stop) pairs, or None with `matrix`.
    - `values`: the measured aggregates, one per interval (per row of `matrix`); NaN
        marks a missing reading (with `missing="mask"`).
    - `kind`: `"sum"`, `"mean"` (default), `"integral"` or `"time_mean"`.
    - `matrix`: the (m, T) aggregation matrix, instead of `intervals` and `kind`.
    - `weight`: the readings' weight w_i in the loss, a scalar or one per reading
        (>= 0); by default the channel's diagonal entry of Q (`weight=` of the function,
        1 without one).
    """

    def __init__(
        self, channel, intervals=None, values=None, *, kind="mean", matrix=None, weight=None
    ):
        if not _is_int(channel) or channel < 0:
            raise ValueError(
                f"`channel` must be a non-negative integer, an output index of z, got {channel!r}."
            )
        if (intervals is None) == (matrix is None):
            raise ValueError("give exactly one of `intervals` (with `kind`) and `matrix`.")
        if not isinstance(kind, str) or kind not in KINDS:
            raise ValueError(f"`kind` must be one of {KINDS}, got {kind!r}.")
        if values is None:
            raise ValueError("`values` must hold the measured aggregates, one per reading.")
        vals = np.asarray(as_float(values, "values"), float)
        if vals.ndim != 1:
            raise ValueError(
                f"`values` must be a 1-D sequence of readings, got shape {vals.shape}."
            )
        if np.any(np.isinf(vals)):
            raise ValueError("`values` must be finite (NaN marks a missing reading).")
        if matrix is not None:
            A = np.asarray(as_float(matrix, "matrix"), float)
            if A.ndim != 2:
                raise ValueError(f"`matrix` must be a 2-D (m, T) array, got shape {A.shape}.")
            if not np.all(np.isfinite(A)):
                raise ValueError("`matrix` must be finite.")
            if A.shape[0] != vals.shape[0]:
                raise ValueError(
                    f"`values` must hold one reading per row of `matrix` ({A.shape[0]}), "
                    f"got {vals.shape[0]}."
                )
            empty = np.flatnonzero(~np.any(A != 0, axis=1))
            if empty.size:
                raise ValueError(f"row {int(empty[0])} of `matrix` has no nonzero entry.")
            kind, pairs = None, None
        else:
            try:
                pairs = [tuple(p) for p in intervals]
            except TypeError:
                raise ValueError(
                    f"`intervals` must be a list of (start, stop) pairs, got {intervals!r}."
                ) from None
            for i, p in enumerate(pairs):
                if len(p) != 2 or not all(_is_int(v) for v in p):
                    raise ValueError(
                        f"`intervals[{i}]` must be a (start, stop) pair of integers, got {p!r}."
                    )
                start, stop = p = pairs[i] = (int(p[0]), int(p[1]))  # (plain ints: repr)
                if start < 0 or stop <= start:
                    raise ValueError(
                        f"`intervals[{i}]` = {p}: need 0 <= start < stop (half-open "
                        "[start, stop), like a slice)."
                    )
                if kind in ("integral", "time_mean") and stop - start < 2:
                    raise ValueError(
                        f"`intervals[{i}]` = {p}: kind {kind!r} needs at least two samples."
                    )
            if len(pairs) != vals.shape[0]:
                raise ValueError(
                    f"`values` must hold one reading per interval ({len(pairs)}), got "
                    f"{vals.shape[0]}."
                )
            A = None
        if vals.shape[0] == 0:
            raise ValueError("an `Aggregate` needs at least one reading.")
        if weight is not None:
            if isinstance(weight, (bool, np.bool_)) or np.asarray(weight).dtype == np.bool_:
                raise TypeError(
                    f"`weight` must be a number or one number per reading, got {weight!r}."
                )
            w = np.asarray(as_float(weight, "weight"), float)
            if w.shape not in ((), vals.shape):
                raise ValueError(
                    f"`weight` must be a scalar or one per reading ({vals.shape[0]},), got "
                    f"shape {w.shape}."
                )
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError("`weight` must be finite and non-negative.")
            weight = np.broadcast_to(w, vals.shape).copy()
        self.channel = int(channel)
        self.intervals = pairs
        self.values = vals
        self.kind = kind
        self.matrix = A
        self.weight = weight

    def __repr__(self):
        form = f"intervals={self.intervals}, kind={self.kind!r}"
        if self.matrix is not None:
            form = f"matrix of shape {self.matrix.shape}"
        return f"Aggregate(channel={self.channel}, {form}, {len(self.values)} readings)"

    def operator(self, T, t=None):
        """The (m, T) aggregation matrix A of the readings over a record of T samples.

        **Arguments:**

        - `T`: the record's number of samples.
        - `t`: its sample times (T,), needed for `"integral"` and `"time_mean"` (as `fit`
            integrates them: the record's time stamps, `dt * np.arange(T)` for a
            `Model.from_ode` with a fixed dt, `np.arange(T)` for a discrete-time model).

        **Returns:**

        A NumPy array: reading i predicts sum_k A[i, k] y_c[k].
        """
        if not _is_int(T) or T < 1:
            raise ValueError(f"`T` must be a positive integer, got {T!r}.")
        if self.matrix is not None:
            if self.matrix.shape[1] != T:
                raise ValueError(
                    f"`matrix` must have one column per sample: shape "
                    f"({self.matrix.shape[0]}, {T}), got {self.matrix.shape}."
                )
            return self.matrix.copy()
        if t is None and self.kind in ("integral", "time_mean"):
            raise ValueError(
                f"`t` is needed for kind={self.kind!r}: the sample times (T,) the fit "
                "integrates over (the record's time stamps, dt * np.arange(T) for a "
                "Model.from_ode with a fixed dt, np.arange(T) for a discrete-time model)."
            )
        if t is None:
            ts = np.arange(T, dtype=float)
        else:
            _intervals(t, "t", T, of="the record")  # (T,), finite and strictly increasing
            ts = np.asarray(t, dtype=float)
        A = np.zeros((len(self.intervals), T))
        for i, (start, stop) in enumerate(self.intervals):
            if stop > T:
                raise ValueError(
                    f"interval {i} = ({start}, {stop}) of the aggregate of channel "
                    f"{self.channel} ends past the record's {T} samples (stop <= {T})."
                )
            if self.kind == "sum":
                A[i, start:stop] = 1.0
            elif self.kind == "mean":
                A[i, start:stop] = 1.0 / (stop - start)
            else:
                dt = np.diff(ts[start:stop])
                row = np.zeros(stop - start)
                row[:-1] += dt / 2
                row[1:] += dt / 2
                if self.kind == "time_mean":
                    row /= ts[stop - 1] - ts[start]
                A[i, start:stop] = row
        return A

    def predict(self, z, t=None):
        """The readings predicted from outputs `z` (T, n_z): A @ z[:, channel], with the
        sample times `t` (T,) for `"integral"` and `"time_mean"` (see `operator`).

        **Returns:**

        An (m,) array.
        """
        z = jnp.asarray(z)
        if z.ndim != 2:
            raise ValueError(f"`z` must have shape (T, n_z), the outputs, got shape {z.shape}.")
        if self.channel >= z.shape[1]:
            raise ValueError(
                f"`Aggregate.channel` = {self.channel} is out of range: `z` has {z.shape[1]} "
                f"outputs (channel < {z.shape[1]})."
            )
        if t is not None and np.shape(t) != (z.shape[0],):
            raise ValueError(
                f"`t` must have shape ({z.shape[0]},): one time stamp per row of `z` "
                f"(T = {z.shape[0]}), got shape {np.shape(t)}."
            )
        return jnp.asarray(self.operator(z.shape[0], t), z.dtype) @ z[:, self.channel]


class _Step(eqx.Module):
    """The augmented model's step f (`observe=False`) or observation g (`observe=True`) of
    eq. (1) on the state [x, s]: the model's own step of x or its outputs, with the
    accumulators' update (1 - rho_k) s_k + a_k y_c(x_k, u_k) (the module's docstring)."""

    model: Model
    n_x: int = eqx.field(static=True)
    n_u: int = eqx.field(static=True)
    channels: tuple = eqx.field(static=True)
    observe: bool = eqx.field(static=True)

    def __call__(self, x, u, theta):
        x_in, s = x[: self.n_x], x[self.n_x :]
        if self.observe:
            u_now, u_step = u, u[: self.n_u]
        elif self.model.input == "foh":
            u_now, u_step = u[0], u[:, : self.n_u]
        else:
            u_now, u_step = u, u[: self.n_u]
        y = jnp.asarray(self.model.observe(x_in, u_now[: self.n_u], theta))
        drive = u_now[self.n_u :]
        rho, a = drive[0::2], drive[1::2]
        acc = (1 - rho) * s + a * y[jnp.asarray(self.channels)].astype(s.dtype)
        if self.observe:
            return jnp.concatenate([y.astype(acc.dtype), acc])
        return jnp.concatenate([self.model.step(x_in, u_step, theta), acc])


class _OnStates(eqx.Module):
    """A penalty h(x, theta) of eq. (21) on the model's own states of the augmented x."""

    penalty: Any
    n_x: int = eqx.field(static=True)

    def __call__(self, x, theta):
        return self.penalty(x[: self.n_x], theta)


_MODELS: dict = {}


def _augmented_model(model, n_x, n_u, channels):
    """The augmented `Model`, one object per (model, sizes, channels), so that the checks'
    and the compiled calls' caches hit on repeated calls."""
    key = (id(model), n_x, n_u, channels)
    hit = _MODELS.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    aug = Model(
        _Step(model, n_x, n_u, channels, False),
        _Step(model, n_x, n_u, channels, True),
        input=model.input,
    )
    if len(_MODELS) >= 64:
        _MODELS.pop(next(iter(_MODELS)))
    _MODELS[key] = (model, aug)
    return aug


class _Reading(NamedTuple):
    channel: int
    start: int
    stop: int
    row: np.ndarray  # A[i, start:stop] times sqrt(w_i)
    value: float  # v_i times sqrt(w_i)


def _readings(aggregates, T, n_z, Q, t, where):
    """The readings of one record, each scaled by the square root of its weight."""
    out = []
    for agg in aggregates:
        if not isinstance(agg, Aggregate):
            raise TypeError(
                f"`aggregate`{where} must hold `oneshot_jax.Aggregate` objects, got "
                f"{type(agg).__name__}."
            )
        if agg.channel >= n_z:
            raise ValueError(
                f"`Aggregate.channel` = {agg.channel} is out of range: the model has {n_z} "
                f"outputs (channel < {n_z})."
            )
        try:
            A = agg.operator(T, t)
        except ValueError as err:
            if not where:
                raise
            raise ValueError(f"`aggregate`{where} (trajectory {where[1:-1]}): {err}") from None
        if agg.weight is not None:
            w = agg.weight
        else:
            q = (
                1.0
                if Q is None
                else float(Q[agg.channel] if Q.ndim == 1 else Q[agg.channel, agg.channel])
            )
            w = np.full(len(agg.values), q)
        for i in range(A.shape[0]):
            nz = np.flatnonzero(A[i])
            start, stop = int(nz[0]), int(nz[-1]) + 1
            sw = math.sqrt(w[i])
            out.append(
                _Reading(agg.channel, start, stop, A[i, start:stop] * sw, agg.values[i] * sw)
            )
    return out


def _groups(readings):
    """Per channel, the readings split into groups of non-overlapping spans (greedy by
    start: each reading goes to the first group whose last span has ended)."""
    by_channel: dict = {}
    for r in sorted(readings, key=lambda r: (r.channel, r.start, r.stop)):
        groups = by_channel.setdefault(r.channel, [])
        for g in groups:
            if g[-1].stop <= r.start:
                g.append(r)
                break
        else:
            groups.append([r])
    return by_channel


class Augmented(NamedTuple):
    """The aggregated problem as an ordinary one, and what maps its results back."""

    model: Any
    x0: Any
    u: Any
    z: Any
    weight: Any
    n_x: int
    n_z: int
    n_acc: int

    def penalty(self, penalty):
        """`penalty=` of the function, applied to the model's own states."""
        return None if penalty is None else _OnStates(penalty, self.n_x)

    def x0_mask(self, estimate_x0):
        """`estimate_x0` of `fit` for the augmented state (accumulators never estimated)."""
        if estimate_x0 is False:
            return False
        mask = x0_mask(estimate_x0, self.n_x)
        return np.concatenate([mask, np.zeros(self.n_acc, bool)])

    def reading_mean_squares(self, result):
        """Per output with aggregated readings, the mean over its readings of the squared
        weighted residual w_i (r_i - v_i)^2 of a `FitResult` of the augmented problem (before
        `restore`): comparable with the point samples' weighted residuals, whose noise
        level sigma^2 the covariance pools with the readings'."""
        e = np.asarray(result.residuals, dtype=np.float64)[..., self.n_z :]
        layout = self.model.step.channels  # (the output of each accumulator's readings)
        out = {}
        for c in sorted(set(layout)):
            v = e[..., [j for j, ch in enumerate(layout) if ch == c]]
            v = v[np.isfinite(v)]
            if v.size:
                out[c] = float(np.mean(v * v))
        return out

    def restore(self, result):
        """A `FitResult` of the augmented problem as one of the user's model: x0 with its
        n_x entries, residuals and per-output metrics of z's n_z outputs, the criteria
        (AIC, AICc, BIC, FPE) on the point samples of the outputs that have any (the
        covariance, from all residuals, counts the readings as observations)."""
        n_x, n_z = self.n_x, self.n_z

        def per_output(v):
            v = np.asarray(v)
            return v[..., :n_z] if v.ndim and v.shape[-1] == n_z + self.n_acc else v

        e = np.asarray(result.residuals)[..., :n_z]
        metrics = {k: per_output(v) for k, v in result.metrics.items()}
        seen = np.isfinite(e)
        sampled = np.any(seen.reshape(-1, n_z), axis=0)  # outputs with point samples
        if "aic" in metrics and sampled.any():  # on those outputs' point samples
            n_traj = 1 if e.ndim == 2 else e.shape[0]
            n_free = int(np.count_nonzero(~np.asarray(result.fixed)))
            n_free += int(np.count_nonzero(np.asarray(result.x0_estimated)[:n_x])) * n_traj
            es, ms = np.where(seen, e, 0.0)[..., sampled], seen[..., sampled]
            # (unchecked: NaN where no sample measures every such output, as in a fit
            # without aggregates; the checking `metrics.aic` refuses that)
            zero = np.zeros_like(es)
            for name in _metrics._CRITERIA:
                metrics[name] = float(getattr(_metrics, f"_{name}")(zero, es, n_free, ms))
        elif "aic" in metrics:  # (readings only: no point sample to judge by)
            metrics.update({name: float("nan") for name in _metrics._CRITERIA})
        starts = result.starts
        if starts is not None and starts.x0 is not None:
            starts = dataclasses.replace(starts, x0=np.asarray(starts.x0)[..., :n_x])
        return dataclasses.replace(
            result,
            starts=starts,
            x0=np.asarray(result.x0)[..., :n_x],
            x0_std=np.asarray(result.x0_std)[..., :n_x],
            x0_estimated=np.asarray(result.x0_estimated)[:n_x],
            residuals=e,
            metrics=metrics,
            model=self.model.step.model,
            diagnostics={**(result.diagnostics or {}), "aggregated": True},
        )


def _per_record(aggregate, batched, N):
    """`aggregate` as one list of `Aggregate`s per record."""

    def as_list(a):
        if a is None:
            return []
        if isinstance(a, Aggregate):
            return [a]
        if isinstance(a, (list, tuple)):
            return list(a)
        raise TypeError(
            f"`aggregate` must be an `Aggregate` or a list of them, got {type(a).__name__}."
        )

    if not batched:
        one = as_list(aggregate)
        if any(a is None for a in one):
            raise TypeError(
                "`aggregate` holds None, which stands for a record without readings in a "
                "list with one entry per record (several records); for one record, pass "
                "its `Aggregate`s alone (an `Aggregate` or a list of them)."
            )
        return [one]
    if isinstance(aggregate, Aggregate) or not isinstance(aggregate, (list, tuple)):
        raise ValueError(
            f"with {N} trajectories, `aggregate` must be a list of {N} entries, one per "
            "trajectory (an `Aggregate`, a list of them, or None)."
        )
    if len(aggregate) != N:
        raise ValueError(
            f"`aggregate` must have one entry per trajectory ({N}), got {len(aggregate)}."
        )
    return [as_list(a) for a in aggregate]


def record_times(model, t, batched, lengths):
    """The sample times of each record over which `"integral"` and `"time_mean"` readings
    integrate: `t` (one record's, one row per record, or one axis they share), or for
    t None k dt for a `Model.from_ode` with a fixed dt and the sample index for a
    discrete-time model; a list of one per record."""
    if t is not None and (not batched or (not isinstance(t, (list, tuple)) and np.ndim(t) == 1)):
        return [t] * len(lengths)  # one record, or N records sharing one (T,) time axis
    if t is None:
        dt = getattr(model.step, "dt", None) if isinstance(model.step, ODE_STEPS) else None
        return [(dt or 1.0) * np.arange(n) for n in lengths]
    return t


def check_window(aggregate, window):
    """`fit`'s `window` is refused with aggregates (checked before the windows are cut)."""
    if aggregate is not None and window is not None:
        raise ValueError(
            "`window` cannot be combined with `aggregate`: an aggregate may span windows. "
            "Fit the whole record, or several records as a list."
        )


def augment(data, aggregate, model, x0, missing, *, t=None) -> Augmented:
    """The aggregated problem as an ordinary one on augmented arrays: the accumulator
    states appended to x (at 0), their reset and weight columns to u, their readings (NaN
    elsewhere) to z, weight 1 to Q (see the module's docstring).

    **Arguments:**

    - `data`: `check_data`'s output on the user's arguments (checked, one dtype, ragged
        trajectories padded, with their `lengths`).
    - `aggregate`: `aggregate=` of the public function.
    - `model`, `x0`: the user's model and x0 (x0 may hold a leading axis of starts).
    - `missing`: the user's `missing` (NaN readings are refused under "raise").
    - `t`: time stamps (T,), or one row (or array) per trajectory, for `"integral"` and
        `"time_mean"`; None: k dt for a `Model.from_ode` with a fixed dt, else the
        sample index.

    **Returns:**

    An `Augmented` whose `model`, `x0`, `u`, `z`, `weight` go to the function's checks
    again (with `missing="mask"`), and which maps the results back.
    """
    if data.z is None:
        raise ValueError("`aggregate` needs the measured outputs `z`.")
    dtype = np.dtype(data.u.dtype)
    # Traced x0, u or z (under jax.jit, vmap or grad) stay traced: the readings' layout
    # depends only on the intervals, the values and the time stamps, which must be concrete.
    xp = jnp if _is_tracer((data.u, data.z, data.mask, x0)) else np
    if _is_tracer(data.weight):
        raise ValueError(
            "`weight` must be concrete (not traced under jax.jit, vmap or grad) with "
            "`aggregate`: it sets the readings' default weights."
        )
    U, Z = xp.asarray(data.u), xp.asarray(data.z)
    if data.mask is not None:  # the checks zero the missing samples: NaN again
        Z = xp.where(xp.asarray(data.mask.outputs) > 0, Z, np.nan)
    if not data.batched:
        U, Z = U[None], Z[None]
    N, T_max, n_u = U.shape
    n_z = Z.shape[-1]
    n_x = np.shape(data.x0)[-1]
    lengths = [T_max] * N if data.lengths is None else list(data.lengths)
    Q = None if data.weight is None else np.asarray(data.weight)
    records = _per_record(aggregate, data.batched, N)
    t = record_times(model, t, data.batched, lengths)
    per_record = []
    for i, aggs in enumerate(records):
        where = f"[{i}]" if data.batched else ""
        if _is_tracer(t[i]):
            if any(a.kind in ("integral", "time_mean") for a in aggs if isinstance(a, Aggregate)):
                raise ValueError(
                    "`t` must be concrete (not traced under jax.jit, vmap or grad) with an "
                    "`Aggregate` of kind 'integral' or 'time_mean': its weights are the "
                    "trapezoid rule over the time stamps."
                )
            ti = None  # ('sum' and 'mean' do not use the times)
        else:
            ti = None if t is None else np.asarray(t[i], dtype=float)[: lengths[i]]
        readings = _readings(aggs, lengths[i], n_z, Q, ti, where)
        if missing == "raise" and any(np.isnan(r.value) for r in readings):
            raise ValueError(
                "`Aggregate.values` holds NaN (missing readings): pass missing='mask'."
            )
        per_record.append(_groups(readings))
    # The same accumulators in every record: per channel, the most groups any record needs.
    channels = sorted({c for rec in per_record for c in rec})
    layout = [c for c in channels for _ in range(max(len(rec.get(c, [])) for rec in per_record))]
    m = len(layout)
    if m == 0:
        raise ValueError("`aggregate` holds no readings.")
    drive = np.zeros((N, T_max, 2 * m), dtype)
    extra = np.full((N, T_max, m), np.nan, dtype)
    for i, rec in enumerate(per_record):
        j = 0
        for c in channels:
            groups = rec.get(c, [])
            for g in range(layout.count(c)):
                for r in groups[g] if g < len(groups) else []:
                    drive[i, r.start, 2 * j] = 1.0
                    drive[i, r.start : r.stop, 2 * j + 1] = r.row
                    # a reading of weight 0 is no observation (as an output of weight 0)
                    extra[i, r.stop - 1, j] = r.value if np.any(r.row) else np.nan
                j += 1
    U_aug = xp.concatenate([U, drive], axis=-1)
    Z_aug = xp.concatenate([Z, extra], axis=-1)
    if data.lengths is not None:
        u_out = [U_aug[i, :n] for i, n in enumerate(lengths)]
        z_out = [Z_aug[i, :n] for i, n in enumerate(lengths)]
    elif data.batched:
        u_out, z_out = U_aug, Z_aug
    else:
        u_out, z_out = U_aug[0], Z_aug[0]
    x0 = xp.asarray(x0, dtype)
    x0_out = xp.concatenate([x0, np.zeros((*x0.shape[:-1], m), dtype)], axis=-1)
    if Q is None:
        w_out = None
    elif Q.ndim == 1:
        w_out = np.concatenate([Q, np.ones(m, Q.dtype)])
    else:
        w_out = np.zeros((n_z + m, n_z + m), Q.dtype)
        w_out[:n_z, :n_z] = Q
        w_out[n_z:, n_z:] = np.eye(m)
    aug_model = _augmented_model(model, n_x, n_u, tuple(layout))
    return Augmented(aug_model, x0_out, u_out, z_out, w_out, n_x, n_z, m)
