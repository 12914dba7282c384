"""The grey-box model of eq. (1): a discrete step f and an observation g."""

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax


def _identity_observe(x, u, theta):
    del u, theta
    return x


def ode_step(rhs, x, u, theta, dt, *, method="rk4", substeps=1):
    """Advance `dx/dt = rhs(x, u, theta)` by one sample interval `dt` with `u` held constant.

    The zero-order hold: every stage of every substep sees the same `u`. `method="rk4"` is
    classical RK4 (tableau 0; 1/2 1/2; 1/2 0 1/2; 1 0 0 1; weights 1/6 1/3 1/3 1/6), global
    error O(h^4) with h = dt / substeps; `method="euler"` is explicit Euler, O(h). This is
    the discretisation behind `Model.from_ode`; call it directly inside a hand-written
    `step` whose state holds more than the ODE (a controller's delay line, say).
    """
    h = dt / substeps

    def substep(x):
        if method == "euler":
            return x + h * rhs(x, u, theta)
        k1 = rhs(x, u, theta)
        k2 = rhs(x + 0.5 * h * k1, u, theta)
        k3 = rhs(x + 0.5 * h * k2, u, theta)
        k4 = rhs(x + h * k3, u, theta)
        return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    if substeps <= 8:  # unrolled: cheaper to differentiate than a loop for a few substeps
        for _ in range(substeps):
            x = substep(x)
        return x
    return jax.lax.fori_loop(0, substeps, lambda _, x: substep(x), x)


class _ODEStep(eqx.Module):
    """`ode_step` of `rhs` as a step function (hashable, so jit caches hit)."""

    rhs: Callable
    dt: float = eqx.field(static=True)
    method: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)

    def __call__(self, x, u, theta):
        return ode_step(self.rhs, x, u, theta, self.dt, method=self.method, substeps=self.substeps)


class Model(eqx.Module):
    """A discrete-time grey-box model, eq. (1)-(2) of the paper:

    x[k+1] = step(x[k], u[k], theta),    z[k] = observe(x[k], u[k], theta).

    `theta` is any pytree of arrays (a dict of named physical parameters is the normal
    case); `x` is a 1-D state array, `u` a 1-D input array. Both functions must be pure
    and traceable by JAX. The model is immutable and hashable: pass it to a function under
    `eqx.filter_jit` (as the library does), as a static argument of `jax.jit`, or close
    over it; plain `jax.jit` cannot take it as a traced argument because it holds functions.

    **Arguments:**

    - `step`: `step(x, u, theta) -> x_next`, the map f of eq. (1). Must return an array
        of the same shape and dtype as `x`.
    - `observe`: `observe(x, u, theta) -> z`, the map g of eq. (1). Defaults to `z = x`.
    """

    step: Callable[[Any, Any, Any], Any]
    observe: Callable[[Any, Any, Any], Any]

    def __init__(self, step, observe=None):
        if not callable(step):
            raise ValueError(f"`step` must be callable (x, u, theta) -> x_next, got {step!r}.")
        if observe is not None and not callable(observe):
            raise ValueError(f"`observe` must be callable (x, u, theta) -> z, got {observe!r}.")
        self.step = step
        self.observe = _identity_observe if observe is None else observe

    @classmethod
    def from_ode(cls, rhs, dt, *, method="rk4", substeps=1, observe=None):
        """Build a `Model` from a continuous-time right-hand side `dx/dt = rhs(x, u, theta)`.

        The input is a zero-order hold: `u[k]` is held over `[k dt, (k+1) dt)`. Each sample
        interval is split into `substeps` equal steps of classical RK4 (`method="rk4"`,
        global error O(h^4)) or explicit Euler (`method="euler"`).

        **Arguments:**

        - `rhs`: `rhs(x, u, theta) -> dx/dt`.
        - `dt`: the sample interval (> 0).
        - `method`: `"rk4"` or `"euler"`.
        - `substeps`: number of integrator steps per sample interval (>= 1).
        - `observe`: as for `Model`.

        **Returns:**

        A `Model` whose `step` advances the state by one sample interval.
        """
        if not callable(rhs):
            raise ValueError(f"`rhs` must be callable (x, u, theta) -> dx/dt, got {rhs!r}.")
        if method not in ("rk4", "euler"):
            raise ValueError(f"`method` must be 'rk4' or 'euler', got {method!r}.")
        dt = float(dt)
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"`dt` must be a finite positive number, got {dt}.")
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"`substeps` must be an integer >= 1, got {substeps!r}.")
        return cls(_ODEStep(rhs, dt, method, int(substeps)), observe)
