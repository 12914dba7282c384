r"""Barrier penalties h(x, theta) on the simulated states, for eq. (21) of the paper.

Section 3.3 of the paper adds a penalty to the multi-step cost,

    C = (1/T) sum_k [ e_k^T Q e_k + lambda h(x_k, theta) ],   (eq. 21)

here with the 1/T of the error: the paper's eq. (21) adds lambda h without it, so its
lambda is `penalty_weight / T`.

and names an exponential barrier on the states as one use. For hybrid models the barrier
guards stability: a learned residual can make the simulated trajectory leave the region
where the real system lives and then diverge, and the multi-step cost and its gradient
overflow long before the data could pull the parameters back. A barrier that grows as soon
as a simulated state leaves a safe region (known from physics or from the data's range)
keeps the iterates stable while leaving the fit untouched inside that region.

The barriers here are one-sided powers of the violation v >= 0 of the safe set,

    h = sum_i (v_i / width_i)^p,   p >= 2,

so that h >= 0 everywhere, h = 0 exactly inside the safe set (no bias where the model is
well behaved), h is p - 1 times continuously differentiable, and it grows polynomially
outside (finite for any state, unlike a log barrier, so a start outside the set is
allowed). Least-squares solvers use it as the residual sqrt(lambda h): with p = 2 that is
sqrt(lambda) times the norm of the scaled violations, zero inside and Lipschitz.

Each factory returns an equinox module (hashable, with static constants), to pass as
`penalty=` to `oneshot_jax.loss`, `value_and_grad` or `fit`, with `penalty_weight` = lambda.
"""

import math
import numbers

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._counts import real

__all__ = ["state_box", "state_ball", "StateBox", "StateBall"]


def _constants(value, name, fill, positive=False, none_entries=False):
    """A scalar or a 1-D sequence as a static tuple of floats (None -> the fill value; with
    `none_entries`, also a None entry of a list or tuple)."""
    if value is None:
        return (fill,)
    if none_entries and isinstance(value, (list, tuple)) and any(v is None for v in value):
        value = [fill if v is None else v for v in value]  # (a bound's unbounded entries)
    if isinstance(value, (str, bytes, bool, np.bool_)) or np.asarray(value).dtype.kind not in "iuf":
        raise ValueError(
            f"`{name}` must be a scalar or a 1-D sequence of real numbers, got {value!r}."
        )
    try:
        arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must be a scalar or a 1-D sequence of numbers.") from err
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"`{name}` must be a scalar or a 1-D sequence of numbers, got {value!r}.")
    if np.any(np.isnan(arr)):
        where = np.flatnonzero(np.isnan(arr)).tolist()
        raise ValueError(
            f"`{name}` holds NaN at {where}: give a number"
            + (" (or None for no bound there)" if none_entries else "")
            + f", got {value!r}."
        )
    if positive and not np.all((arr > 0) & np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite and > 0, got {value!r}.")
    return tuple(float(a) for a in arr)


def _check_power(power):
    power = real(power)  # (a concrete 0-d array: the number it holds)
    if isinstance(power, bool) or not isinstance(power, numbers.Integral) or power < 2:
        raise ValueError(
            f"`power` must be an integer >= 2 (h smooth at the boundary), got {power!r}."
        )
    return int(power)


def _per_state(values, n_x, name, dtype):
    if len(values) not in (1, n_x):
        raise ValueError(
            f"`{name}` has {len(values)} entries for a state of size {n_x}; give a scalar or "
            f"one entry per state."
        )
    return jnp.broadcast_to(jnp.asarray(values, dtype), (n_x,))


def _check_state(x):
    if jnp.ndim(x) != 1:
        raise ValueError(f"the penalty takes one state x of shape (n_x,), got {jnp.shape(x)}.")


class StateBox(eqx.Module):
    """h(x) = sum_i (max(x_i - upper_i, 0, lower_i - x_i) / width_i)^power (see `state_box`)."""

    lower: tuple[float, ...] = eqx.field(static=True)
    upper: tuple[float, ...] = eqx.field(static=True)
    width: tuple[float, ...] = eqx.field(static=True)
    power: int = eqx.field(static=True)

    def __call__(self, x, theta=None):
        del theta
        _check_state(x)
        n_x, dtype = jnp.shape(x)[0], jnp.result_type(x)
        lo = _per_state(self.lower, n_x, "lower", dtype)
        hi = _per_state(self.upper, n_x, "upper", dtype)
        w = _per_state(self.width, n_x, "width", dtype)
        # Where a bound is infinite the violation is max(0, -inf) = 0, with a zero gradient.
        v = jnp.maximum(jnp.maximum(x - hi, lo - x), 0) / w
        return jnp.sum(v**self.power)


class StateBall(eqx.Module):
    """h(x) = (max(||(x - center) / scale|| - radius, 0) / width)^power (see `state_ball`)."""

    radius: float = eqx.field(static=True)
    center: tuple[float, ...] = eqx.field(static=True)
    scale: tuple[float, ...] = eqx.field(static=True)
    width: float = eqx.field(static=True)
    power: int = eqx.field(static=True)

    def __call__(self, x, theta=None):
        del theta
        _check_state(x)
        n_x, dtype = jnp.shape(x)[0], jnp.result_type(x)
        c = _per_state(self.center, n_x, "center", dtype)
        s = _per_state(self.scale, n_x, "scale", dtype)
        y = (x - c) / s
        # The norm is not differentiable at y = 0, which lies inside the ball (radius > 0),
        # where h is identically zero: take it of a safe value there.
        sq = jnp.sum(y * y)
        inside = sq <= self.radius**2
        norm = jnp.sqrt(jnp.where(inside, self.radius**2, sq))
        v = jnp.where(inside, 0.0, norm - self.radius) / self.width
        return v**self.power


def state_box(lower=None, upper=None, *, width=1.0, power: int = 2) -> StateBox:
    """A barrier that is zero while lower <= x <= upper and grows as (violation/width)^power.

    h(x, theta) = sum_i (max(x_i - upper_i, lower_i - x_i, 0) / width_i)^power, for
    `penalty=` in eq. (21). E.g. from the data's range with a margin:
    `state_box(lower=z.min(0) - m, upper=z.max(0) + m)` when the states are measured.

    **Arguments:**

    - `lower`, `upper`: a scalar (every state) or one value per state; None or -inf/+inf
        entries leave that side unbounded.
    - `width`: the violation at which a state's term reaches 1 (scalar or per state, > 0).
    - `power`: an integer >= 2: h is power - 1 times continuously differentiable.

    **Returns:**

    A `StateBox`, callable as `h(x, theta)` on one state x of shape (n_x,).
    """
    lo = _constants(lower, "lower", -math.inf, none_entries=True)
    hi = _constants(upper, "upper", math.inf, none_entries=True)
    if all(v == -math.inf for v in lo) and all(v == math.inf for v in hi):
        raise ValueError(
            "`state_box` needs `lower` or `upper` (a finite bound on some state); without "
            f"one h is zero everywhere (got lower={lower!r}, upper={upper!r})."
        )
    if math.inf in lo or -math.inf in hi:
        side = "lower" if math.inf in lo else "upper"
        raise ValueError(
            f"`{side}` holds {'+inf' if side == 'lower' else '-inf'}: no state satisfies it "
            f"(h would be inf everywhere); use None or {'-inf' if side == 'lower' else '+inf'} "
            "to leave that side unbounded."
        )
    if len(lo) == len(hi) or 1 in (len(lo), len(hi)):
        lo_b, hi_b = np.broadcast_arrays(np.asarray(lo), np.asarray(hi))
        crossed = np.flatnonzero(lo_b > hi_b)
        if crossed.size:
            names = ["every state"] if lo_b.size == 1 else [f"x[{i}]" for i in crossed[:8]]
            listed = ", ".join(
                f"{name} (lower {lo_b[i]:g} > upper {hi_b[i]:g})" for name, i in zip(names, crossed)
            )
            more = f" and {crossed.size - 8} more" if crossed.size > 8 else ""
            raise ValueError(
                "`state_box` needs lower <= upper for every state; it is not so for "
                f"{listed}{more}."
            )
    else:
        raise ValueError(f"`lower` ({len(lo)} entries) and `upper` ({len(hi)}) do not match.")
    return StateBox(lo, hi, _constants(width, "width", 1.0, positive=True), _check_power(power))


def state_ball(radius, *, center=None, scale=None, width=1.0, power: int = 2) -> StateBall:
    """A barrier that is zero inside the ellipsoid ||(x - center) / scale|| <= radius.

    h(x, theta) = (max(||(x - center) / scale||_2 - radius, 0) / width)^power, for
    `penalty=` in eq. (21): a bound on the (scaled) size of the state, e.g. an energy-like
    norm that a stable system never exceeds.

    **Arguments:**

    - `radius`: > 0, in the units of the scaled state.
    - `center`: a scalar or one value per state (default 0).
    - `scale`: positive, a scalar or one value per state (default 1): the ellipsoid's axes.
    - `width`: > 0, the distance outside the ellipsoid at which h reaches 1.
    - `power`: an integer >= 2.

    **Returns:**

    A `StateBall`, callable as `h(x, theta)` on one state x of shape (n_x,).
    """
    radius, width = real(radius), real(width)  # (0-d arrays: their numbers)
    if isinstance(radius, bool) or not (isinstance(radius, numbers.Real) and 0 < radius < math.inf):
        raise ValueError(f"`radius` must be a finite number > 0, got {radius!r}.")
    if isinstance(width, bool) or not (isinstance(width, numbers.Real) and 0 < width < math.inf):
        raise ValueError(f"`width` must be a finite number > 0, got {width!r}.")
    center = _constants(center, "center", 0.0)
    if not all(math.isfinite(c) for c in center):
        raise ValueError(f"`center` must be finite, got {center!r}.")
    return StateBall(
        float(radius),
        center,
        _constants(scale, "scale", 1.0, positive=True),
        float(width),
        _check_power(power),
    )
