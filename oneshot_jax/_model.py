"""The grey-box model of eq. (1): a discrete step f and an observation g."""

import math
import numbers
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._counts import integral

_INPUTS = ("zoh", "foh")


def _identity_observe(x, u, theta):
    del u, theta
    return x


def _check_input(input):
    if input not in _INPUTS:
        raise ValueError(f"`input` must be 'zoh' or 'foh', got {input!r}.")
    return input


def _check_names(names, name):
    """`Model`'s `states` or `outputs`: None, one string (one name), or a sequence of
    strings, as a tuple."""
    if names is None:
        return None
    if isinstance(names, str):
        return (names,)
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise TypeError(
            f"`{name}` must be a string or a list of strings (one name per entry, e.g. "
            f"['q (m)', 'v (m/s)']), got {names!r}."
        )
    return tuple(names)


def model_labels(names, n):
    """The names a `Model` gives n entries (its `states` or `outputs`), or None where it
    gives none of that count (no names, or a result loaded with another model)."""
    return names if names is not None and len(names) == n else None


def _check_integrator(rhs, method, substeps) -> int:
    """The checks of `ode_step`'s and `Model.from_ode`'s static arguments; the number of
    substeps as an int."""
    if not callable(rhs):
        raise ValueError(f"`rhs` must be callable (x, u, theta) -> dx/dt, got {rhs!r}.")
    if method not in ("rk4", "euler"):
        raise ValueError(f"`method` must be 'rk4' or 'euler', got {method!r}.")
    substeps = integral(substeps)  # (a 0-d array: the count it holds)
    if (
        isinstance(substeps, bool)
        or not isinstance(substeps, numbers.Real)
        or not math.isfinite(substeps)
        or int(substeps) != substeps
        or substeps < 1
    ):
        raise ValueError(f"`substeps` must be an integer >= 1, got {substeps!r}.")
    return int(substeps)


def _input_at(u, dt, input):
    """u(t_k + s) over one sample interval of length dt: u[k] held ("zoh"), or the linear
    interpolant of the pair (u[k], u[k+1]) ("foh")."""
    if _check_input(input) == "foh" and u is not None:
        u0, du = u[0], (u[1] - u[0]) / dt
        return lambda s: u0 + s * du
    return lambda s: u


def _derivative(rhs, x, u, theta):
    """rhs(x, u, theta), which must be dx/dt of the state's shape and dtype: the stages'
    sums would broadcast another shape into a state of the right shape and a wrong model,
    and promote another dtype silently."""
    dx = rhs(x, u, theta)
    shape, dtype = getattr(dx, "shape", None), getattr(dx, "dtype", None)
    if shape != jnp.shape(x) or dtype != x.dtype:
        got = f"shape {shape} and dtype {dtype}" if shape is not None else type(dx).__name__
        raise ValueError(
            f"`rhs` must return dx/dt as an array of the state's shape {jnp.shape(x)} and "
            f"dtype {x.dtype}, got {got}."
        )
    return dx


def _integrator_step(rhs, x, u_at, theta, s, h, method):
    """One step of size h from t_k + s of classical RK4 (or explicit Euler) for
    dx/dt = rhs(x, u(t), theta), the discretisation of eq. (1) for an ODE."""
    k1 = _derivative(rhs, x, u_at(s), theta)
    if method == "euler":
        return x + h * k1
    u_mid = u_at(s + 0.5 * h)
    k2 = rhs(x + 0.5 * h * k1, u_mid, theta)
    k3 = rhs(x + 0.5 * h * k2, u_mid, theta)
    k4 = rhs(x + h * k3, u_at(s + h), theta)
    return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


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
    - `u`: u[k] (n_u,) for "zoh", or (u[k], u[k+1]) stacked to (2, n_u) for "foh";
        None for an autonomous `rhs` (which then gets None as its u).
    - `theta`: the parameters, passed on to `rhs`.
    - `dt`: the sample interval, > 0 (checked where it is concrete; a traced one, under
        `jax.jit` or `jax.vmap`, is not).
    - `method`, `substeps`, `input`: as above.

    **Returns:**

    The state at t_{k+1}.
    """
    substeps = _check_integrator(rhs, method, substeps)
    if not isinstance(x, jax.Array):
        # (a list, a tuple, a Python number, or a NumPy array, in JAX's dtype: float64
        # data with x64 off are float32, as `rhs` computes them)
        x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        # (`rhs` was blamed for returning floats to an integer state)
        raise TypeError(
            f"`x` must be a floating-point state, got dtype {x.dtype}: the integrator "
            "carries the state in its own dtype (write [1.0, 0.0], or x.astype(float))."
        )
    if isinstance(u, (list, tuple)):
        u = jnp.asarray(u)
    # (np.ndim and np.shape: a model without inputs passes u=None, which jnp.ndim
    # deprecates; a tracer's own shape either way)
    if _check_input(input) == "foh" and u is not None and (np.ndim(u) != 2 or np.shape(u)[0] != 2):
        raise ValueError(
            f'`u` must be the pair (u[k], u[k+1]) of shape (2, n_u) for input="foh", got '
            f"shape {jnp.shape(u)}."
        )
    if input == "zoh" and np.ndim(u) == 2 and np.shape(u)[0] == 2:
        # (a step of `Model(step, input="foh")` gets the pair: its `ode_step` needs to know)
        raise ValueError(
            f'`u` must be u[k] of shape (n_u,) for input="zoh", got the shape {jnp.shape(u)} '
            'of a pair (u[k], u[k+1]): pass input="foh" to interpolate between them (a '
            'step of `Model(step, input="foh")` gets that pair).'
        )
    if input == "zoh" and np.ndim(u) > 1:
        raise ValueError(f'`u` must be u[k] of shape (n_u,) for input="zoh", got {np.shape(u)}.')
    if not isinstance(dt, jax.core.Tracer):  # (a traced dt is not checked: jit, vmap)
        dt = _positive_number(dt, "dt", "the sample interval")
    h = dt / substeps
    u_at = _input_at(u, dt, input)

    def substep(j, x):
        return _integrator_step(rhs, x, u_at, theta, j * h, h, method)

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


def timed_ode_step(
    rhs, x, u, theta, dt, *, method="rk4", substeps=1, max_step=None, input="zoh", refine=1
):
    """Advance `dx/dt = rhs(x, u, theta)` over one interval `dt` of a time-stamped record,
    t[k+1] - t[k], with `dt` a traced value (data, not a parameter): the step f of eq. (1)
    of a model built by `Model.from_ode(rhs, dt=None)`.

    The integrator, its stages and the input between the samples are those of `ode_step`
    (classical RK4 or explicit Euler; "zoh" holds u[k], "foh" interpolates linearly to
    u[k+1]). Without `max_step` the interval is split into `substeps` equal steps. With
    `max_step`, it is split into n = ceil(dt / max_step) equal steps of h = dt / n <=
    max_step (`interval_count`): the loop (a `fori_loop`, which compiles much faster than
    the unrolled masked steps) runs to the static bound `substeps` and the steps j >= n
    leave the state as it is (a `jnp.where`, so the map stays differentiable
    in x and theta; the caller checks n <= substeps). A zero interval (the padding after
    a record's last sample) leaves the state unchanged. An interval the caller could not
    check (traced time stamps) that is negative, not finite, or needs n > substeps + 1
    gives a NaN state.

    **Arguments:**

    - `rhs`, `x`, `u`, `theta`, `method`, `input`: as for `ode_step`.
    - `dt`: the interval t[k+1] - t[k] (>= 0), a scalar array.
    - `substeps`: the number of steps (without `max_step`), or their upper bound.
    - `max_step`: the largest integrator step, or None.
    - `refine`: with `max_step`, each interval's steps split into this many equal ones
        (`refine` times ceil(dt / max_step) steps, the loop's bound `substeps * refine`):
        the same model with steps `refine` times shorter everywhere, which `max_step /
        refine` is not (an interval shorter than it still takes one step).

    **Returns:**

    The state at t[k+1].
    """
    x = x if isinstance(x, jax.Array) else jnp.asarray(x)  # (JAX's dtype, as `ode_step`)
    dt = jnp.asarray(dt, x.dtype)
    if max_step is None:
        n = substeps
        h = dt / substeps
    else:
        # (at most `substeps`: the host's check counts in NumPy, and the compiled count
        # can round one higher next to a multiple of max_step (XLA folds 1 / max_step and
        # the tolerance into one constant); a count above the loop's bound would leave the
        # rest of the interval unintegrated)
        count = interval_count(dt, max_step, jnp)
        n = jnp.minimum(count, substeps) * refine
        h = dt / jnp.maximum(n, 1.0)
        # An interval the host did not check (a traced `t`) that needs more than one step
        # beyond the bound, or that is negative or not finite, gives NaN states: steps
        # longer than `max_step`, or a frozen state, would be a silently wrong answer.
        bad = ~(jnp.isfinite(dt) & (dt >= 0) & (count <= substeps + 1))
    u_at = _input_at(u, jnp.where(dt > 0, dt, 1.0), input)  # (dt = 0: no step is taken)

    def substep(j, x):
        if max_step is None:
            return _integrator_step(rhs, x, u_at, theta, j * h, h, method)
        # A step j >= n is masked. It is taken with h = 0 and evaluated at the start of the
        # interval, so its stages see only the state x, where the steps before it evaluated
        # rhs too. A full step of h would evaluate rhs beyond the interval (the stages of
        # RK4 after the last state), and a non-finite derivative there (sqrt of a stage
        # below 0) would reach the gradient through the zero cotangent of the `where`
        # (0 * nan) in reverse mode.
        live = j < n
        h_j = jnp.where(live, h, 0.0)
        x_new = _integrator_step(rhs, x, u_at, theta, jnp.where(live, j * h, 0.0), h_j, method)
        return jnp.where(live, x_new, x)

    if substeps <= 8 and max_step is None:  # unrolled as in `ode_step`; masked: a loop
        for j in range(substeps):
            x = substep(j, x)
        return x
    x = jax.lax.fori_loop(0, substeps * (1 if max_step is None else refine), substep, x)
    return x if max_step is None else jnp.where(bad, jnp.nan, x)


def interval_count(dt, max_step, xp=np):
    """The number of integrator steps n = ceil(dt / max_step) an interval `dt` is split
    into, with a relative tolerance of 1e-6 so that the rounding of time stamps
    (t = cumsum(intervals), say) does not add a step: h = dt / n exceeds `max_step` by at
    most that much. `xp` is NumPy (the host's check) or `jax.numpy` (the step)."""
    dt = xp.asarray(dt)
    return xp.ceil(dt / xp.asarray(max_step, dt.dtype) * (1.0 - 1e-6))


class _TimedODEStep(eqx.Module):
    """`timed_ode_step` of `rhs` as a step function whose input carries the interval
    t[k+1] - t[k] as its last entry (`oneshot_jax._timing` appends it): u_step[-1] for
    "zoh", u_step[0, -1] for "foh"."""

    rhs: Callable
    method: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    max_step: float | None = eqx.field(static=True)
    input: str = eqx.field(static=True)
    # (`check_discretisation`'s finer model: each interval's steps split `refine` times)
    refine: int = eqx.field(static=True, default=1)

    def __call__(self, x, u, theta):
        if self.input == "foh":
            dt, u = u[0, -1], u[:, :-1]
        else:
            dt, u = u[-1], u[:-1]
        return timed_ode_step(
            self.rhs,
            x,
            u,
            theta,
            dt,
            method=self.method,
            substeps=self.substeps,
            max_step=self.max_step,
            refine=self.refine,
            input=self.input,
        )

    def check_intervals(self, dt):
        """Raise where an interval of `dt` (concrete, host) needs more steps of `max_step`
        than the bound `substeps`."""
        if self.max_step is None or np.size(dt) == 0:
            return
        worst = float(np.max(dt))
        need = int(np.max(interval_count(dt, self.max_step)))
        if need > self.substeps:
            raise ValueError(
                f"`t`: the longest interval, {worst!r}, needs {need} integrator steps of "
                f"`max_step` = {self.max_step!r}, more than `substeps` = {self.substeps} "
                f"(the bound of the loop): build the model with `substeps={need}` or more, "
                "or a larger `max_step`."
            )


class _WithoutInterval(eqx.Module):
    """The user's `observe` of a timed model: it sees u[k] without the appended interval."""

    fn: Callable

    def __call__(self, x, u, theta):
        return self.fn(x, u[:-1], theta)


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
    `x` is a 1-D state array, `u[k]` a 1-D input array (a model without inputs takes u of
    shape (T, 0), which gives a record its length). JAX clamps an index beyond an array's
    end instead of raising (`u[1]` with n_u = 1 reads u[0]), so the checks cannot see
    such a slip: index the state and the input within their sizes. Both functions must be
    pure and traceable by JAX: a value they read from a global or a closure is frozen into
    each compiled function at its first call (a later `simulate` keeps the old value, a
    `fit` compiled after the change takes the new one); pass a value that changes as an
    entry of theta (held by `fit(fixed=...)`). The same holds of a function edited in
    place (IPython's `%autoreload` gives the function object a new body): the compiled
    programs of a model built from it keep the old body, a rebuilt model's too (it
    equals the old one); call `jax.clear_caches()` after such an edit. They are
    differentiated in forward mode (`jax.jvp`) as well as in reverse mode: a function with
    a custom derivative inside them needs `jax.custom_jvp` (a `jax.custom_vjp` works only with
    `value_and_grad(strategy="vjp")`). The model is immutable and hashable: pass
    it to a function under `eqx.filter_jit` (as the library does), as a static argument
    of `jax.jit`, or close over it; plain `jax.jit` cannot take it as a traced argument
    because it holds functions. `step` and `observe` (or `rhs`) may be an
    `equinox.Module` with a `__call__`: its array fields are data, traced with the model
    and never estimated (a network to be fitted belongs in theta).

    **Arguments:**

    - `step`: `step(x, u_step, theta) -> x_next`, the map f of eq. (1). Must return an
        array of the same shape and dtype as `x`.
    - `observe`: `observe(x, u, theta) -> z`, the map g of eq. (1), with u = u[k] of
        shape (n_u,). Defaults to `z = x`. Integer or boolean outputs are promoted to the
        data's floating dtype; floating outputs must be in it (a float32 z of float64
        data would round the measurements, and is refused).
    - `input`: what the step sees of the input record u (T, n_u). `"zoh"` (default):
        `u_step[k] = u[k]`, shape (n_u,). `"foh"`: the pair `(u[k], u[k+1])`, shape
        (2, n_u), for a step that interpolates between the samples (see `ode_step`).
    - `timed`: False (default) for a fixed sample interval. True for a model of
        time-stamped records (what `Model.from_ode(rhs, dt=None)` builds): every function
        that takes data then needs the time stamps `t=`, and the library appends the
        interval t[k+1] - t[k] to each input sample as its last entry (0 after a record's
        last sample), so `step` and `observe` see u[k] of shape (n_u + 1,) (for "foh"
        the interval of step k is `u_step[0, -1]`).
    - `states`, `outputs`: optional names of the state's entries (n_x) and of the
        outputs (n_z), with their units if you like (`["q (m)", "v (m/s)"]`; MATLAB's
        `InitialStates.Name` and `OutputName`): `print(result)` labels the initial
        states and the FIT and RMSE per output with them, and `plot.compare` its axes.
        The data's sizes are checked against them.
    """

    step: Callable[[Any, Any, Any], Any]
    observe: Callable[[Any, Any, Any], Any]
    input: str = eqx.field(static=True)
    timed: bool = eqx.field(static=True)
    states: tuple | None = eqx.field(static=True)
    outputs: tuple | None = eqx.field(static=True)

    def __init__(self, step, observe=None, *, input="zoh", timed=False, states=None, outputs=None):
        if not callable(step):
            raise ValueError(f"`step` must be callable (x, u, theta) -> x_next, got {step!r}.")
        if observe is not None and not callable(observe):
            hint = ""
            if isinstance(observe, (int, float)) and not isinstance(observe, bool):
                hint = (
                    " (for a continuous-time right-hand side and its sample interval, "
                    f"use Model.from_ode(rhs, dt={observe!r}))"
                )
            raise ValueError(
                f"`observe` must be callable (x, u, theta) -> z, got {observe!r}{hint}."
            )
        if not isinstance(timed, bool):
            raise TypeError(f"`timed` must be a bool, got {timed!r}.")
        _check_hashable(step, "step")
        if observe is not None:
            _check_hashable(observe, "observe")
        self.step = step
        self.observe = _identity_observe if observe is None else observe
        self.input = _check_input(input)
        self.timed = timed
        self.states = _check_names(states, "states")
        self.outputs = _check_names(outputs, "outputs")

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
    def from_ode(
        cls,
        rhs,
        dt=None,
        *,
        method="rk4",
        substeps=1,
        max_step=None,
        observe=None,
        input="zoh",
        states=None,
        outputs=None,
    ):
        """Build a `Model` from a continuous-time right-hand side `dx/dt = rhs(x, u, theta)`.

        Each sample interval is split into `substeps` equal steps of classical RK4
        (`method="rk4"`, global error O(h^4)) or explicit Euler (`method="euler"`), see
        `ode_step`.

        With `dt=None` the model is for time-stamped records (`Model.timed`): every
        function that takes data (`simulate`, `loss`, `value_and_grad`, `fit`,
        `estimate_x0`, `predict`, ...) then needs the sample times `t=`, and step k
        integrates over its own interval t[k+1] - t[k] (`timed_ode_step`). The interval
        enters the step as data, so the one-shot gradient (eq. 17, 20) and the residual
        Jacobian stay exact.

        **Arguments:**

        - `rhs`: `rhs(x, u, theta) -> dx/dt`, u of shape (n_u,); dx/dt of the state's
            shape and dtype.
        - `dt`: the sample interval (> 0), or None for records with time stamps `t`.
        - `method`: `"rk4"` or `"euler"`.
        - `substeps`: number of integrator steps per sample interval (>= 1); with
            `max_step`, their upper bound.
        - `max_step`: only with `dt=None`: the largest integrator step (> 0). Interval k
            is then split into n_k = ceil((t[k+1] - t[k]) / max_step) equal steps, at
            most `substeps` (a record whose longest interval needs more is refused,
            naming the `substeps` it needs). Without it every interval is split into
            `substeps` equal steps.
        - `observe`: as for `Model` (it sees u[k] of shape (n_u,), without the interval).
        - `input`: `"zoh"` (default) holds u[k] over [t_k, t_{k+1}); `"foh"`
            interpolates linearly between u[k] and u[k+1], which is what a measured,
            band-limited input needs.
        - `states`, `outputs`: names of the state's entries and of the outputs, as for
            `Model`.

        **Returns:**

        A `Model` whose `step` advances the state by one sample interval.

        **Example:**

        ```python
        model = oj.Model.from_ode(rhs, dt=None, max_step=0.05, substeps=20)
        x, z = oj.simulate(model, theta, x0, u, t=t)  # t: (T,) increasing time stamps
        ```
        """
        substeps = _check_integrator(rhs, method, substeps)
        _check_hashable(rhs, "rhs")
        input = _check_input(input)
        if dt is None:
            if max_step is not None:
                max_step = _positive_number(max_step, "max_step", "the largest integrator step")
            if observe is not None and not callable(observe):
                raise ValueError(f"`observe` must be callable (x, u, theta) -> z, got {observe!r}.")
            observe = None if observe is None else _WithoutInterval(observe)
            step = _TimedODEStep(rhs, method, substeps, max_step, input)
            return cls(step, observe, input=input, timed=True, states=states, outputs=outputs)
        if max_step is not None:
            raise ValueError(
                "`max_step` applies to records with time stamps (`dt=None`); with a fixed "
                "`dt`, set `substeps` instead."
            )
        dt = _positive_number(dt, "dt", "the sample interval")
        return cls(
            _ODEStep(rhs, dt, method, substeps, input),
            observe,
            input=input,
            states=states,
            outputs=outputs,
        )


ODE_STEPS = (_ODEStep, _TimedODEStep)
"""The step classes of `Model.from_ode` (their `rhs` is checked with the data)."""


def _check_hashable(fn, name):
    """Every compiled call takes the model's functions as static (hashed) arguments: a
    callable object that cannot be hashed (a `@dataclass`, whose eq=True sets __hash__ to
    None) would fail there with JAX's "Non-hashable static arguments" error. Arrays
    inside an equinox module are the model's leaves (traced), not hashed."""
    for leaf in jax.tree_util.tree_leaves(fn):
        if isinstance(leaf, (jax.Array, np.ndarray, np.generic)):
            continue
        try:
            hash(leaf)
        except TypeError:
            raise TypeError(
                f"`{name}` must be hashable (the compiled functions take it as a static "
                f"argument), got an unhashable {type(leaf).__name__}: use a function, "
                "functools.partial, an equinox.Module, or @dataclass(frozen=True) (a "
                "plain @dataclass sets __hash__ to None)."
            ) from None


def _positive_number(value, name, what):
    try:
        if isinstance(value, (str, bytes, bool, np.bool_)):
            raise TypeError
        value = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"`{name}` must be a number, {what} (> 0), got {value!r}.") from None
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"`{name}` must be a finite positive number, got {value}.")
    return value
