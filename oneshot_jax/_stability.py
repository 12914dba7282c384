"""How close a `Model.from_ode` model runs to its explicit integrator's stability limit.

An explicit integrator (`ode_step`: RK4 or Euler, h = dt / substeps) is stable on a mode
of the right-hand side's Jacobian only while lambda h lies in its stability region. A fit
knows nothing of that region: it can move a stiff mode (a friction, a fast pole) out to
where the discrete step f of eq. (1) is no longer the ODE's flow, and the estimates then
depend on `substeps`. `check_stability` bounds |lambda| h at every state of the fitted
trajectory (eq. 7) by the row sums of the right-hand side's Jacobian, takes the
eigenvalues at the states of the largest bounds and at a few evenly spaced ones, and
compares max |lambda| h with the integrator's limit, and for RK4 with the range where
its step follows the ODE's flow (`ACCURATE`: past 1.5, near RK4's fold at 1.596, a
faster mode steps like a slower one); `fit` calls it after every fit of such a model. A
model of time-stamped records (`Model.from_ode(rhs, dt=None)`) takes each step's own h,
its interval over its number of integrator steps, and is checked also before its
longest interval.
"""

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._caller_warnings import warn
from ._checks import check_data
from ._jit import jit
from ._model import Model, _ODEStep, _TimedODEStep, _WithoutInterval, interval_count
from ._simulate import simulate_impl

# The largest |lambda| h taken as safe. RK4's stability region reaches 2.785 on the
# negative real axis and 2.828 on the imaginary axis, and is narrower in between (about
# 2.62 near 120 degrees, 2.70 at 135): 2.5 leaves a margin in every direction. Explicit
# Euler's region is the disc |1 + lambda h| <= 1, which reaches 2 on the negative real
# axis (and contains no point of the imaginary axis: an undamped mode grows under Euler
# at any h).
LIMITS = {"rk4": 2.5, "euler": 2.0}

# The largest |lambda| h at which RK4's step still follows the ODE's flow. Its step factor
# R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24 decreases along the negative real axis only down
# to z = -1.596, where R' = 0 (the other zeros of R', -0.70 +- 1.81j, lie farther out); past
# it a faster mode steps like a slower one: R(-2.456) = R(-0.5) = e^-0.5, so a fitted lag
# converged to a = 24.6 with a = 5's loss (h = 0.1), inside the stability margin and
# without a warning. An undamped mode loses 8 % of its amplitude a step at 1.6 too. The
# warning starts short of the fold: a fit that the data pull past it stops at the fold
# itself (a lag's estimate sat at |lambda| h = 1.596, 'stalled', unwarned by a limit of
# 1.6), and R' has fallen to a quarter of the ODE's e^z by 1.5 (R'(-1.5) = 0.0625,
# e^-1.5 = 0.223): the step barely tells the mode's speed there. Below it the step still
# errs (R(-1.2) = 0.318 against e^-1.2 = 0.301, 6 % a step), which biases estimates by
# the record's information: `check_discretisation` measures that bias on a fit's data.
# Euler's factor 1 + z is one-to-one: its measure is judged against its disc alone.
ACCURATE = {"rk4": 1.5, "euler": 2.0}


def scaled_eigenvalues(eig, h, method):
    """Each eigenvalue's measure against `LIMITS[method]`, linear in h: |lambda| h for
    RK4; for Euler h |lambda|^2 / (-Re lambda) where Re lambda < 0, which is <= 2 exactly
    inside the disc |1 + lambda h| <= 1 (|1 + lambda h|^2 = 1 + 2 h Re lambda +
    h^2 |lambda|^2); inf for an undamped mode (Re lambda = 0 up to round-off, lambda != 0:
    Euler grows it at any h, by sqrt(1 + |lambda h|^2) a step); and |lambda| h where
    Re lambda > 0 (the ODE's own mode grows: its growth is not the discretisation's)."""
    size = np.abs(eig) * h
    if method != "euler":
        return size
    damped = _decays(eig)
    with np.errstate(divide="ignore"):
        disc = np.abs(eig) ** 2 * h / np.where(damped, np.maximum(-eig.real, 0.0), 1.0)
    return np.where(damped, disc, size)


def _decays(eig):
    """The modes that decay, or do not grow (Re lambda <= 1e-12 |lambda|, lambda != 0):
    Euler's measure applies to them."""
    return (eig.real <= 1e-12 * np.abs(eig)) & (np.abs(eig) > 0)


# An undamped mode that explicit Euler grows by at most this fraction over a record's
# steps is not reported (Euler grows one at any h, by sqrt(1 + |lambda h|^2) a step).
SMALL_GROWTH = 0.01

# The states the Jacobian's eigenvalues are taken at: this many, evenly spaced over all
# samples of all trajectories, and as many where its row bound on |lambda| h is largest
# (`stiffest`: a mode that an input or a contact switches on at a few samples falls
# between evenly spaced ones; a gated lag fitted 13 standard errors off unwarned).
POINTS = 32


class Stability(NamedTuple):
    """The largest scaled eigenvalue of a `Model.from_ode` model along a trajectory.

    **Fields:**

    - `value`: max |lambda| h over the states checked, lambda an eigenvalue of the
        Jacobian d rhs / d x, h = dt / substeps; for Euler, max h |lambda|^2 /
        (-Re lambda) over the decaying modes (<= 2 exactly inside Euler's stability
        disc |1 + lambda h| <= 1), inf for an undamped mode that Euler grows by more
        than 1 % over a record (see `growth`), |lambda| h over the others.
    - `limit`: the integrator's limit (2.5 for RK4, 2 for Euler).
    - `eigenvalue`: the lambda of `value`.
    - `sample`: where it was found: the index of its state in the trajectories
        flattened (trajectory i, sample k: i T + k).
    - `method`, `substeps`, `dt`: the model's integrator: `dt` the interval of the step
        at `sample` (a time-stamped model's t[k+1] - t[k]) and `substeps` the number of
        integrator steps it is split into there.
    - `max_step`: a time-stamped model's largest integrator step, or None.
    - `accurate_limit`: the largest `value` at which the integrator's step still follows
        the ODE's flow: 1.5 for RK4 (its step factor R(lambda h) stops decreasing along
        the negative real axis at 1.596, so a faster mode steps like a slower one and a
        fit cannot tell them apart; the warning starts short of it, where R' is a
        quarter of the ODE's e^z); `limit` for Euler.
    - `growth`: for Euler and an undamped mode (`value` inf), the factor by which the
        integrator grows that mode's amplitude over a record's steps, (1 + |lambda
        h|^2)^(N/2); None otherwise.

    **Properties:**

    - `inaccurate`: whether `value` exceeds min(`accurate_limit`, `limit`) (1.5 for
        RK4, 2 for Euler): the condition on which `check_stability` and `fit` warn.
    - `near_limit`: whether `value` exceeds `limit` (2.5 for RK4, 2 for Euler), past
        the integrator's stability margin. For RK4 a `value` between 1.5 and 2.5 is
        `inaccurate` (it warns) but not `near_limit`; for Euler the two agree.
    """

    value: float
    limit: float
    eigenvalue: complex
    sample: int
    method: str
    substeps: int
    dt: float
    max_step: float | None = None
    accurate_limit: float = math.inf
    growth: float | None = None

    @property
    def near_limit(self) -> bool:
        """Whether `value` exceeds `limit`."""
        return bool(self.value > self.limit)

    @property
    def inaccurate(self) -> bool:
        """Whether `value` exceeds `accurate_limit` (or `limit`): `check_stability` and
        `fit` warn."""
        return bool(self.value > min(self.accurate_limit, self.limit))

    def __str__(self) -> str:
        """One line for `print`: the measure against the integrator's limits, and where."""
        lam = complex(self.eigenvalue)
        verdict = (
            "past its stability margin"
            if self.near_limit
            else "past its accurate range"
            if self.inaccurate
            else "inside its accurate range"
        )
        accurate = (
            f", accurate to {self.accurate_limit:g}" if math.isfinite(self.accurate_limit) else ""
        )
        return (
            f"{self.method.upper()} with h = dt / substeps = {self.dt:g} / {self.substeps}: "
            f"largest |lambda| h {self.value:.3g} (lambda = {lam.real:.4g}{lam.imag:+.4g}j at "
            f"sample {self.sample}), {verdict} (limit {self.limit:g}{accurate})"
        )

    __repr__ = __str__


def is_ode(step) -> bool:
    """Whether `step` is an explicit integrator of `Model.from_ode` (a fixed `dt`, or a
    time-stamped model's own intervals)."""
    return isinstance(step, (_ODEStep, _TimedODEStep))


def rhs_of(model, data):
    """The right-hand side of a `Model.from_ode` model as the checked data's model sees
    theta (its trainable part, the static part bound in) and u (a time-stamped model's
    without the interval appended to it, `_timing`); None for another model."""
    step = model.step
    if not is_ode(step):
        return None
    bound = data.model.step
    rhs = _pytree.Bound(step.rhs, bound.static) if isinstance(bound, _pytree.Bound) else step.rhs
    return _WithoutInterval(rhs) if isinstance(step, _TimedODEStep) else rhs


def step_sizes(step, u, idx) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The interval, the number of integrator steps and h, the integrator's step, of the
    steps from the flattened states `idx` (host): dt, substeps and dt / substeps for a
    fixed sample interval; for a time-stamped model its intervals, the last column of
    the checked data's `u` (0 after a record's last sample: no step, h = 0), split into
    `substeps` steps or, with `max_step`, into ceil(dt / max_step) (`timed_ode_step`)."""
    idx = np.asarray(idx)
    if isinstance(step, _ODEStep):
        dt = np.full(idx.shape, float(step.dt))
        n = np.full(idx.shape, step.substeps)
    else:
        dt = np.asarray(u)[..., -1].reshape(-1)[idx].astype(float)
        if step.max_step is None:
            n = np.full(idx.shape, step.substeps)
        else:
            n = np.maximum(interval_count(dt, step.max_step), 1).astype(int) * step.refine
    return dt, n, dt / n


def sample_points(data, points: int = POINTS, timed: bool = False) -> np.ndarray | None:
    """The flattened indices (trajectory i, sample k: i T + k) of `points` states evenly
    spaced over the valid samples of the checked data (not the padding of ragged
    trajectories); None where there is none. For a time-stamped model (`timed`), also
    the state before the longest interval (its step has the largest h)."""
    if data.mask is None:
        idx = _evenly(math.prod(np.shape(data.u)[:-1]), points)
    else:
        valid = np.flatnonzero(np.asarray(data.mask.samples).reshape(-1) > 0)
        if valid.size == 0:
            return None
        idx = valid[_evenly(valid.size, points)]
    if timed:
        intervals = np.asarray(data.u)[..., -1].reshape(-1)
        idx = np.union1d(idx, [int(np.argmax(intervals))])
    return idx


@functools.lru_cache(maxsize=64)
def _evenly(n: int, points: int) -> np.ndarray:
    """`points` indices evenly spaced over range(n) (all of them when n <= points)."""
    idx = np.unique(np.linspace(0, n - 1, min(points, n)).astype(int))
    idx.setflags(write=False)
    return idx


def step_weights(data, step) -> np.ndarray:
    """Each flattened state's h, the integrator's step from it (`step_sizes`), 0 at the
    padding of ragged trajectories, in the checked data's dtype (host): the weights of
    the row bounds that `stiffest` ranks."""
    rows = math.prod(np.shape(data.u)[:-1])
    h = step_sizes(step, data.u, np.arange(rows))[2]
    if data.mask is not None:
        h = np.where(np.asarray(data.mask.samples).reshape(-1) > 0, h, 0.0)
    return np.asarray(h, np.asarray(data.u).dtype)


# The states whose row bounds `stiffest` forms at once (memory O(this n_x^2)).
BOUND_BATCH = 4096


def stiffest(rhs, theta, xs, u, h, k):
    """The flattened indices of the `k` states of a trajectory xs (..., T, n_x) (inputs u
    (..., T, n_u)) where the row bound ||J||_inf h on |lambda| h is largest, J = d rhs / d x
    and h (rows,) the step from each state (`step_weights`; 0 where there is none): every
    state's Jacobian is formed, in batches, and only its bound kept. Non-finite states
    rank last (the report leaves them out). Traced."""
    rows = math.prod(xs.shape[:-1])
    X, U = xs.reshape(rows, xs.shape[-1]), u.reshape(rows, u.shape[-1])

    def bound(xu):
        J = jax.jacfwd(rhs)(xu[0], xu[1], theta)
        return jnp.max(jnp.sum(jnp.abs(J), axis=-1), initial=0.0)

    b = jax.lax.map(bound, (X, U), batch_size=min(rows, BOUND_BATCH))
    score = jnp.where(jnp.isfinite(b) & (h > 0), b * h, -jnp.inf)
    return jax.lax.top_k(score, min(k, rows))[1]


def jacobians_at(rhs, theta, xs, u, idx):
    """The states of a trajectory xs (..., T, n_x) at the flattened indices `idx`, and
    d rhs / d x there with their inputs u (..., T, n_u) (forward mode: the state is
    small); traced."""
    rows = math.prod(xs.shape[:-1])  # (not -1: an input of n_u = 0 has no elements)
    xs = xs.reshape(rows, xs.shape[-1])[idx]
    us = u.reshape(rows, u.shape[-1])[idx]
    return xs, jax.vmap(lambda x, u: jax.jacfwd(rhs)(x, u, theta))(xs, us)


def row_bound(xs, J):
    """max over the finite states of ||J||_inf (the largest row sum of |J|, a bound on
    every eigenvalue's modulus); -inf where no state is finite. Traced, so that `fit`
    brings one number to the host (`warn_after_fit`)."""
    finite = jnp.all(jnp.isfinite(xs), axis=1) & jnp.all(jnp.isfinite(J), axis=(1, 2))
    rows = jnp.max(jnp.sum(jnp.abs(J), axis=2), axis=1)
    return jnp.max(jnp.where(finite, rows, -jnp.inf), initial=-jnp.inf)


def checked_states(rhs, theta, xs, u, idx, h):
    """The flattened indices `idx` (evenly spaced, `sample_points`) and as many where the
    row bound is largest (`stiffest`, weights `h`), the states of the trajectory xs there
    and d rhs / d x at them (`jacobians_at`). Traced."""
    idx = jnp.concatenate([jnp.asarray(idx), stiffest(rhs, theta, xs, u, h, len(idx))])
    return (idx, *jacobians_at(rhs, theta, xs, u, idx))


@jit
def _jacobians(model, params, x0, u, batched, rhs, idx, h):
    """The states of eq. (7) checked (`checked_states`) and d rhs / d x there, in one
    compiled call."""
    xs, _ = simulate_impl(model, params, x0, u, batched)
    return checked_states(rhs, params, xs, u, idx, h)


def report(step, idx, xs, J, u) -> Stability | None:
    """The `Stability` of the Jacobians `J` at the states `xs` (flattened indices `idx`,
    their inputs in the checked data's `u`) of a `Model.from_ode` model's `step`, from
    their eigenvalues times each step's h (on the host); None where no state is finite."""
    xs, J = np.asarray(xs), np.asarray(J)
    finite = np.all(np.isfinite(xs), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
    if not np.any(finite):
        return None
    dt, n, h = (a[finite] for a in step_sizes(step, u, idx))
    eig = np.linalg.eigvals(J[finite])
    scaled = scaled_eigenvalues(eig, h[:, None], step.method)
    growth = None
    if np.isinf(scaled).any():  # Euler's undamped modes: their growth over a record
        steps = max(np.shape(u)[-2] - 1, 1) * n[:, None]
        log_growth = 0.5 * steps * np.log1p((np.abs(eig) * h[:, None]) ** 2)
        # (within a 1 % growth over the record the mode is followed: its |lambda| h, which
        # is then below 0.15)
        small = np.isinf(scaled) & (log_growth <= np.log(1.0 + SMALL_GROWTH))
        scaled = np.where(small, np.abs(eig) * h[:, None], scaled)
    i, j = np.unravel_index(np.argmax(scaled), eig.shape)
    if np.isinf(scaled[i, j]):
        with np.errstate(over="ignore"):
            growth = float(np.exp(log_growth[i, j]))
    return Stability(
        value=float(scaled[i, j]),
        limit=LIMITS[step.method],
        eigenvalue=complex(eig[i, j]),
        sample=int(np.asarray(idx)[finite][i]),
        method=step.method,
        substeps=int(n[i]),
        dt=float(dt[i]),
        max_step=None if getattr(step, "max_step", None) is None else step.max_step / step.refine,
        accurate_limit=ACCURATE[step.method],
        growth=growth,
    )


def warn_after_fit(step, idx, xs, J, bound, u, stacklevel: int) -> None:
    """`fit`'s warning from the Jacobians `J` at the fitted states `xs`, flattened
    indices `idx` (`checked_states`), and their `row_bound`, the inputs in the checked
    data's `u`. Where max |lambda| h is within the limit by that bound times the largest
    h, no eigenvalue is computed."""
    h = step_sizes(step, u, idx)[2]
    # (|lambda| <= bound: within the limit, or no finite state: -inf. Euler's measure
    # exceeds |lambda| h for a lightly damped mode: always computed.)
    top = bound * float(np.max(h, initial=0.0))
    if step.method != "euler" and not top > ACCURATE[step.method]:
        return
    warn_if_near_limit(report(step, idx, xs, J, u), stacklevel=stacklevel + 1)


def stability(model, theta, x0, u, *, t=None, points: int = POINTS) -> Stability | None:
    """`check_stability` without its checks of the arguments and without the warning;
    None for a model not built by `Model.from_ode` or without a finite state."""
    if not is_ode(model.step):
        return None
    data = check_data(model, theta, x0, u, t=t)
    idx = sample_points(data, points, timed=isinstance(model.step, _TimedODEStep))
    if idx is None:
        return None
    h = step_weights(data, model.step)
    idx, xs, J = _jacobians(
        data.model, data.theta, data.x0, data.u, data.batched, rhs_of(model, data), idx, h
    )
    return report(model.step, idx, xs, J, data.u)


def step_factor(z: complex, method: str) -> complex:
    """The integrator's step factor R(z), z = lambda h: the amplitude a mode of eigenvalue
    lambda is multiplied by per step (1 + z for Euler; 1 + z + z^2/2 + z^3/6 + z^4/24 for
    RK4), against the ODE's exp(z). In NumPy's complex: a z past 1e77 overflows to inf
    (Python's complex power raises OverflowError)."""
    z = np.complex128(z)
    if method == "euler":
        return complex(1 + z)
    with np.errstate(over="ignore", invalid="ignore"):
        return complex(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)


# The check that refits with finer steps, as the warning names it.
CHECK = (
    "`oneshot_jax.check_discretisation(result, u, z)` refits with finer steps and measures "
    "the moves"
)


def warn_if_near_limit(report: Stability | None, stacklevel: int, what="the fitted model") -> None:
    """The warning of `check_stability`, where `report` exceeds its limit, or the range
    where its integrator follows the ODE (`Stability.inaccurate`)."""
    if report is None or not report.inaccurate:
        return
    lam = report.eigenvalue
    h = report.dt / report.substeps
    target = min(report.accurate_limit, report.limit)  # (the remedies reach it)
    if not np.isfinite(report.value):  # an undamped mode: Euler grows it at any h
        growth = report.growth
        growth = (
            ""
            if growth is None
            else f", here by {growth:.3g} over a record"
            if np.isfinite(growth)
            else ", here by more than 1e308 over a record"
        )
        remedy = (
            'RK4 (`Model.from_ode(..., method="rk4")`): explicit Euler grows an undamped '
            f"mode at any step{growth}"
        )
    elif report.max_step is None and report.value > 1e4 * report.limit:
        # (an eigenvalue this far past the limit comes from a very stiff mode or, far more
        # often, from states that have blown up along the simulation: a 100-digit count of
        # substeps was suggested for one)
        need = report.value * report.substeps / report.limit
        remedy = (
            f"about {need:.3g} substeps for a mode this stiff; but where the simulated "
            "states grow without bound from this theta (see `oneshot_jax.simulate`), the "
            "simulation diverges, and the remedy is a theta (or start) at which it does not"
        )
    elif report.max_step is None:
        need = int(np.ceil(report.value * report.substeps / target))
        remedy = (
            f"more substeps (`Model.from_ode(..., substeps={max(need, 2 * report.substeps)})` "
            "or more)"
        )
    else:
        # (as the substeps above: a step that brings |lambda| h to the limit, and at least
        # half the present one; floored to 3 digits, so the printed value is inside it)
        step = min(h / 2, h * target / report.value)
        digits = 2 - int(np.floor(np.log10(step)))
        step = np.floor(step * 10.0**digits) / 10.0**digits
        remedy = (
            f"a smaller `max_step` (`Model.from_ode(..., max_step={step:.3g})` or less, "
            "with `substeps` enough for the longest interval)"
        )
    measure = (
        "h |lambda|^2 / (-Re lambda)"
        if report.method == "euler" and _decays(np.asarray(lam))
        else "|lambda| h"
    )
    region = (
        "stable inside |1 + lambda h| <= 1, where this measure is <= 2"
        if report.method == "euler"
        else f"stable up to about {report.limit:g}"
    )
    if not report.near_limit:  # (RK4 inside its stability margin, past its accurate range)
        warn(
            f"{what} runs where its integrator no longer follows the ODE: a Jacobian "
            f"eigenvalue of the right-hand side, lambda = {lam.real:.4g}{lam.imag:+.4g}j, "
            f"gives |lambda| h = {report.value:.3g} with h = dt / substeps = {report.dt:g} / "
            f"{report.substeps} (RK4: stable up to about {report.limit:g}, but its step "
            f"factor follows the ODE's flow only up to about {report.accurate_limit:g}; past "
            "it a faster mode steps like a slower one, R(-2.46) = R(-0.5), so the fit "
            "cannot tell them apart). The estimates may describe the discretisation "
            f"rather than the ODE: refit with {remedy}, and compare ({CHECK}).",
            RuntimeWarning,
            stacklevel=stacklevel + 1,
        )
        return
    z = complex(lam) * h
    factor = abs(step_factor(z, report.method))
    # (past the region: the integrator grows a mode that the ODE damps, or grows faster)
    past = np.isfinite(factor) and factor > max(1.0, float(np.exp(z.real))) * (1 + 1e-12)
    where = (
        f"past its integrator's stability limit (each step multiplies that mode by "
        f"|R(lambda h)| = {factor:.4g}, the ODE by exp(Re lambda h) = {np.exp(z.real):.4g}: "
        "the discretised model is unstable where the ODE is not)"
        if past
        else "near its integrator's stability limit"
    )
    warn(
        f"{what} runs {where}: a Jacobian "
        f"eigenvalue of the right-hand side, lambda = {lam.real:.4g}{lam.imag:+.4g}j, gives "
        f"{measure} = {report.value:.3g} with h = dt / substeps = {report.dt:g} / "
        f"{report.substeps} ({report.method.upper()}: {region}). "
        f"The estimates may depend on the discretisation rather than on the ODE: refit with "
        f"{remedy}, and compare ({CHECK}).",
        RuntimeWarning,
        stacklevel=stacklevel + 1,
    )


def check_stability(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    *,
    t: Float[ArrayLike, "*N T"] | None = None,
    points: int = POINTS,
) -> Stability | None:
    """Check that a `Model.from_ode` model runs inside its integrator's stability region.

    Simulates the model (eq. 7), evaluates the Jacobian of the right-hand side d rhs / d x
    at `points` states evenly spaced along the trajectory (with their inputs) and at the
    `points` states where its bound ||J||_inf h on |lambda| h is largest (formed at every
    state: a mode that an input or a contact switches on at a few samples is not missed
    between evenly spaced ones), and returns the largest |lambda| h, h = dt / substeps,
    over their eigenvalues lambda. Above 1.5 for RK4 (near where its step stops
    following the ODE's flow, 1.596: a faster mode then steps like a slower one; its stability
    region reaches 2.785 on the negative real axis, 2.828 on the imaginary one), or
    outside Euler's disc |1 + lambda h| <= 1 (`Stability.value`; an undamped mode, which
    Euler grows at any h, where it grows by more than 1 % over a record), it warns
    (RuntimeWarning), naming the eigenvalue and how many substeps would bring it back
    inside. `fit` runs this check on the
    fitted theta and x0 after every fit of a `Model.from_ode` model.

    **Arguments:**

    - `model`: a `Model` built by `Model.from_ode` (for any other model the check
        returns None once its arguments are checked: its step is not a known integrator).
    - `theta`, `x0`, `u`: as for `oneshot_jax.simulate`.
    - `t`: the sample times, for a model of time-stamped records
        (`Model.from_ode(rhs, dt=None)`): h is then each step's own, its interval over
        the number of integrator steps it takes (`substeps`, or with `max_step`
        ceil(interval / max_step)).
    - `points`: how many states to take the eigenvalues at, evenly spaced (and as many
        of the largest bound).

    **Returns:**

    A `Stability` (`value`, `limit`, `eigenvalue`, ...), or None for a model not built by
    `Model.from_ode` or one whose trajectory has no finite state.
    """
    if not isinstance(model, Model):
        hint = " (a FitResult's is `result.model`)" if hasattr(model, "stop_reason") else ""
        raise TypeError(f"`model` must be a oneshot_jax.Model, got {type(model).__name__}{hint}.")
    if (
        isinstance(points, bool)
        or not isinstance(points, (int, float, np.integer, np.floating))
        or not np.isfinite(points)
        or int(points) != points
        or points < 1
    ):
        raise ValueError(f"`points` must be a positive integer, got {points!r}.")
    if not is_ode(model.step):
        check_data(model, theta, x0, u, t=t)  # (bad arguments are refused all the same)
        return None
    report = stability(model, theta, x0, u, t=t, points=int(points))
    warn_if_near_limit(report, stacklevel=2, what="the model")
    return report
