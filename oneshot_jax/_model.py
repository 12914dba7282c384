"""The grey-box model of eq. (1): a discrete step f and an observation g."""

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

_INPUTS = ("zoh", "foh")


def _identity_observe(x, u, theta):
    del u, theta
    return x


def _check_input(input):
    if input not in _INPUTS:
        raise ValueError(f"`input` must be 'zoh' or 'foh', got {input!r}.")
    return input


def ode_step(rhs, x, u, theta, dt, *, method="rk4", substeps=1, input="zoh"):
    """Advance `dx/dt = rhs(x, u, theta)` by one sample interval `dt`.

    `input` says what u does between the samples t_k and t_{k+1} = t_k + dt:

    - `"zoh"` (zero-order hold): `u` has shape (n_u,) and every stage of every substep
        sees the same u[k]. Right for a piecewise-constant input (a digital controller's
        output through a DAC).
    - `"foh"` (first-order hold): `u` has shape (2, n_u), the pair (u[k], u[k+1]), and a
        stage at time t_k + s sees u[k] + (s / dt) (u[k+1] - u[k]). Right for measured
        inputs sampled from a continuous, band-limited signal: there the hold itself is
        an error of order dt against which a higher-order integrator gains nothing.

    `method="rk4"` is classical RK4 (tableau 0; 1/2 1/2; 1/2 0 1/2; 1 0 0 1; weights 1/6
    1/3 1/3 1/6), global error O(h^4) with h = dt / substeps against the ODE driven by the
    held input ("zoh") or by the linear interpolant of the samples ("foh");
    `method="euler"` is explicit Euler, O(h). Against a smooth input u(t) that the samples
    come from, the hold adds an error of O(dt) under "zoh" and O(dt^2) under "foh" (the
    interpolant is off by dt^2 u''/8 mid-interval). This is the discretisation behind
    `Model.from_ode`; call it directly inside a hand-written `step` whose state holds more
    than the ODE (a controller's delay line, say).

    **Arguments:**

    - `rhs`: `rhs(x, u, theta) -> dx/dt`, with u of shape (n_u,).
    - `x`: the state at t_k.
    - `u`: u[k] (n_u,) for "zoh", or (u[k], u[k+1]) stacked to (2, n_u) for "foh".
    - `theta`: the parameters, passed on to `rhs`.
    - `dt`: the sample interval.
    - `method`, `substeps`, `input`: as above.

    **Returns:**

    The state at t_{k+1}.
    """
    h = dt / substeps
    if _check_input(input) == "foh":
        u0, du = u[0], (u[1] - u[0]) / dt

        def u_at(s):
            return u0 + s * du

    else:

        def u_at(s):
            del s
            return u

    def substep(j, x):
        s = j * h
        if method == "euler":
            return x + h * rhs(x, u_at(s), theta)
        u_mid = u_at(s + 0.5 * h)
        k1 = rhs(x, u_at(s), theta)
        k2 = rhs(x + 0.5 * h * k1, u_mid, theta)
        k3 = rhs(x + 0.5 * h * k2, u_mid, theta)
        k4 = rhs(x + h * k3, u_at(s + h), theta)
        return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    if substeps <= 8:  # unrolled: cheaper to differentiate than a loop for a few substeps
        for j in range(substeps):
            x = substep(j, x)
        return x
    return jax.lax.fori_loop(0, substeps, substep, x)


class _ODEStep(eqx.Module):
    """`ode_step` of `rhs` as a step function (hashable, so jit caches hit)."""

    rhs: Callable
    dt: float = eqx.field(static=True)
    method: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    input: str = eqx.field(static=True)

    def __call__(self, x, u, theta):
        return ode_step(
            self.rhs,
            x,
            u,
            theta,
            self.dt,
            method=self.method,
            substeps=self.substeps,
            input=self.input,
        )


class FloatObserve(eqx.Module):
    """`observe` with its outputs promoted to a floating dtype. Outputs are measurements:
    an observation that returns integers or booleans (a quantised sensor, a threshold) is
    compared with z as real numbers, and z is never cast to its integer dtype."""

    fn: Callable
    dtype: Any = eqx.field(static=True)

    def __call__(self, x, u, theta):
        return jnp.asarray(self.fn(x, u, theta), self.dtype)


class Model(eqx.Module):
    """A discrete-time grey-box model, eq. (1)-(2) of the paper:

    x[k+1] = step(x[k], u_step[k], theta),    z[k] = observe(x[k], u[k], theta).

    `theta` is any pytree (a dict of named physical parameters is the normal case; it may
    hold equinox modules such as a neural-network residual, see `oneshot_jax.residual`);
    `x` is a 1-D state array, `u[k]` a 1-D input array. Both functions must be pure and
    traceable by JAX. The model is immutable and hashable: pass it to a function under
    `eqx.filter_jit` (as the library does), as a static argument of `jax.jit`, or close
    over it; plain `jax.jit` cannot take it as a traced argument because it holds
    functions.

    **Arguments:**

    - `step`: `step(x, u_step, theta) -> x_next`, the map f of eq. (1). Must return an
        array of the same shape and dtype as `x`.
    - `observe`: `observe(x, u, theta) -> z`, the map g of eq. (1), with u = u[k] of
        shape (n_u,). Defaults to `z = x`. Integer or boolean outputs are promoted to the
        data's floating dtype.
    - `input`: what the step sees of the input record u (T, n_u). `"zoh"` (default):
        `u_step[k] = u[k]`, shape (n_u,). `"foh"`: the pair `(u[k], u[k+1])`, shape
        (2, n_u), for a step that interpolates between the samples (see `ode_step`).
    """

    step: Callable[[Any, Any, Any], Any]
    observe: Callable[[Any, Any, Any], Any]
    input: str = eqx.field(static=True)

    def __init__(self, step, observe=None, *, input="zoh"):
        if not callable(step):
            raise ValueError(f"`step` must be callable (x, u, theta) -> x_next, got {step!r}.")
        if observe is not None and not callable(observe):
            raise ValueError(f"`observe` must be callable (x, u, theta) -> z, got {observe!r}.")
        self.step = step
        self.observe = _identity_observe if observe is None else observe
        self.input = _check_input(input)

    @property
    def observes_state(self) -> bool:
        """Whether `observe` is the default z = x (the whole state is measured)."""
        return self.observe is _identity_observe

    def step_inputs(self, u):
        """The inputs of the steps x[k] -> x[k+1], k = 0..T-2, from a record u (T, n_u):
        u[:-1] (T-1, n_u) for "zoh", the pairs (u[k], u[k+1]) (T-1, 2, n_u) for "foh"."""
        if self.input == "foh":
            return jnp.stack([u[:-1], u[1:]], axis=1)
        return u[:-1]

    @classmethod
    def from_ode(cls, rhs, dt, *, method="rk4", substeps=1, observe=None, input="zoh"):
        """Build a `Model` from a continuous-time right-hand side `dx/dt = rhs(x, u, theta)`.

        Each sample interval is split into `substeps` equal steps of classical RK4
        (`method="rk4"`, global error O(h^4)) or explicit Euler (`method="euler"`), see
        `ode_step`.

        **Arguments:**

        - `rhs`: `rhs(x, u, theta) -> dx/dt`, u of shape (n_u,).
        - `dt`: the sample interval (> 0).
        - `method`: `"rk4"` or `"euler"`.
        - `substeps`: number of integrator steps per sample interval (>= 1).
        - `observe`: as for `Model`.
        - `input`: `"zoh"` (default) holds u[k] over [k dt, (k+1) dt); `"foh"`
            interpolates linearly between u[k] and u[k+1], which is what a measured,
            band-limited input needs.

        **Returns:**

        A `Model` whose `step` advances the state by one sample interval.
        """
        if not callable(rhs):
            raise ValueError(f"`rhs` must be callable (x, u, theta) -> dx/dt, got {rhs!r}.")
        if method not in ("rk4", "euler"):
            raise ValueError(f"`method` must be 'rk4' or 'euler', got {method!r}.")
        try:
            if isinstance(dt, (str, bytes, bool)):
                raise TypeError
            dt = float(dt)
        except (TypeError, ValueError):
            raise TypeError(
                f"`dt` must be a number, the sample interval (> 0), got {dt!r}."
            ) from None
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"`dt` must be a finite positive number, got {dt}.")
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"`substeps` must be an integer >= 1, got {substeps!r}.")
        input = _check_input(input)
        return cls(_ODEStep(rhs, dt, method, int(substeps), input), observe, input=input)
