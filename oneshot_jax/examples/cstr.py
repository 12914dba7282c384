"""A continuous stirred-tank reactor (CSTR) with an exothermic first-order reaction
A -> B, observed as plants report it: temperature samples at irregular times with gaps,
the concentration only as 8-hour averages.

States: the concentration of A, C_A (mol/L), and the reactor temperature T (K); input:
the coolant temperature T_c (K). The classical mass and energy balances (Seborg, Edgar,
Mellichamp & Doyle, *Process Dynamics and Control*; Henson & Seborg, *Nonlinear Process
Control*, 1997), with time in minutes:

    r     = k0 exp(-E/(R T)) C_A                                   (mol/(L min))
    C_A'  = q/V (C_Af - C_A) - r
    T'    = q/V (T_f - T) + (-dH)/(rho c_p) r + UA/(V rho c_p) (T_c - T).

Two parameters are estimated: `ln_k0`, the natural logarithm of the pre-exponential
factor k0 (1/min; its log, because k0 ~ 1e9 enters through a product with
exp(-E/(R T)) ~ 1e-11, and a relative change of k0 is what the data see), and `UA`, the
heat-transfer coefficient times area in kJ/(min K) (so that both are of order 1 to 20
with sensitivities of order 1: Levenberg-Marquardt's steps are well scaled). The other
constants are known (`FLOW`, `VOLUME`, `C_AF`, `T_F`, `RHO_CP`, `DH`, `E_OVER_R`).

The constants are Henson and Seborg's with the flow, the rate constant and the heat
transfer slowed down 50 times (a residence time of 50 min instead of 1 min: a larger
vessel) and a larger heat-transfer area (UA = 3 kJ/(min K)), so that the reactor has one
stable steady state for every coolant temperature between 310 and 340 K (between 0.93
and 0.32 mol/L of A). Its linearised modes there decay with time constants of about 8 to
120 minutes: up to about 320 K two real modes, of 36 to 46 minutes and of 8 to 12 minutes
(as long as the longest sample intervals); from about 325 K an oscillatory pair whose
decay time grows from about 23 minutes to 120 minutes at 340 K (periods of 6 hours down
to 90 minutes).

The data (`design`, `measure`): sample times with random intervals between about 1 and
10 minutes over a few days, an instant at every 8-hour shift boundary; the coolant
temperature a random walk of levels (moves of up to 6 K) held for 40 to 240 minutes, with small
filtered-noise moves at the samples, held between samples (`input="zoh"`: it is a set
point the controller changes at the sample instants); the temperature measured at the
samples with noise, a few samples and a few outages of hours missing; the concentration
measured only as the time mean over each shift (a composite sample assayed in the lab)
with noise. The averages of the data are exact time means of the continuous state
(integrated with the state as a third state), not the model's quadrature of them.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj

from ._arguments import count, positive

FLOW = 2.0
"""q, feed flow (L/min)."""
VOLUME = 100.0
"""V, reactor volume (L)."""
C_AF = 1.0
"""C_Af, feed concentration of A (mol/L)."""
T_F = 350.0
"""T_f, feed temperature (K)."""
RHO_CP = 239.0
"""rho c_p, volumetric heat capacity (J/(L K))."""
DH = -5.0e4
"""dH, heat of reaction (J/mol; exothermic)."""
E_OVER_R = 8750.0
"""E/R, activation temperature (K)."""
THETA_TRUE = {"ln_k0": math.log(1.44e9), "UA": 3.0}
"""The true parameters: ln k0 (k0 in 1/min) and UA (kJ/(min K))."""
UNITS = {"ln_k0": "ln(1/min)", "UA": "kJ/(min K)"}
SHIFT = 480.0
"""Minutes per averaged concentration sample (an 8-hour shift)."""
MAX_STEP = 2.0
"""Minutes: the longest RK4 substep of the model."""
T_C_RANGE = (315.0, 335.0)
"""K: the range of the coolant temperature's levels."""
SIGMA_T = 0.5
"""K: the noise of the temperature samples."""
SIGMA_C = 0.01
"""mol/L: the noise of the averaged concentration."""


def rhs(x, u, theta):
    """d(C_A, T)/dt of the CSTR (module docstring); u = (T_c,), theta = {"ln_k0", "UA"}."""
    c, temp = x[0], x[1]
    rate = jnp.exp(theta["ln_k0"] - E_OVER_R / temp) * c
    dilution = FLOW / VOLUME
    dc = dilution * (C_AF - c) - rate
    dtemp = (
        dilution * (T_F - temp)
        + (-DH / RHO_CP) * rate
        + 1e3 * theta["UA"] / (VOLUME * RHO_CP) * (u[0] - temp)
    )
    return jnp.stack([dc, dtemp])


def model(dt=None, *, max_step=MAX_STEP, substeps=8) -> oj.Model:
    """The CSTR's `oneshot_jax.Model`: classical RK4 over each sample interval in equal
    substeps of at most `max_step` minutes, the coolant temperature held over the
    interval (`input="zoh"`); z = (C_A, T), the whole state.

    **Arguments:**

    - `dt`: None (default) for time-stamped records (pass the sample times as `t=`), or
        the sample interval in minutes of evenly sampled records.
    - `max_step`: the longest RK4 substep (minutes).
    - `substeps`: with `dt=None`, the most substeps an interval may need (8: intervals
        up to 8 `max_step`, 16 minutes).

    **Returns:**

    An `oneshot_jax.Model` with theta = {"ln_k0", "UA"}.
    """
    if dt is None:
        return oj.Model.from_ode(
            rhs,
            None,
            method="rk4",
            substeps=count(substeps, "substeps"),
            max_step=positive(max_step, "max_step"),
        )
    return oj.Model.from_ode(rhs, dt, method="rk4", substeps=max(1, math.ceil(dt / max_step)))


def steady_state(t_c, theta=THETA_TRUE):
    """The steady state (C_A, T) for a coolant temperature `t_c` (K): C_A from the mass
    balance as a function of T, T by bisection on the energy balance (the state is
    unique for the constants of this module and t_c in 300..345 K)."""
    theta = {k: float(v) for k, v in theta.items()}

    def conc(temp):
        k = math.exp(theta["ln_k0"] - E_OVER_R / temp)
        return (FLOW / VOLUME) * C_AF / (FLOW / VOLUME + k)

    def energy(temp):
        return float(rhs(np.array([conc(temp), temp]), np.array([t_c]), theta)[1])

    lo, hi = 250.0, 500.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if energy(mid) > 0 else (lo, mid)
    temp = 0.5 * (lo + hi)
    return np.array([conc(temp), temp])


class Design(NamedTuple):
    """A noise-free record of the CSTR (`design`).

    - `t`: (T,) sample times (minutes), t[0] = 0, an instant at every shift boundary.
    - `u`: (T, 1) coolant temperature (K), held from each sample to the next.
    - `x`: (T, 2) the true states (C_A, T).
    - `intervals`: the shifts as half-open ranges of sample indices (start, stop), as
        `oneshot_jax.Aggregate` takes them: t[start] = j SHIFT and t[stop - 1] = (j + 1)
        SHIFT (a boundary sample ends one shift and starts the next).
    - `averages`: (S,) the true time mean of C_A over each shift, (1/SHIFT) times the
        integral of C_A from t[start] to t[stop - 1].
    - `observed`: (T,) whether the temperature sample exists (False in the gaps).
    - `theta`, `x0`: the true parameters and initial state.
    """

    t: np.ndarray
    u: np.ndarray
    x: np.ndarray
    intervals: tuple
    averages: np.ndarray
    observed: np.ndarray
    theta: dict
    x0: np.ndarray


def sample_times(rng, days, min_interval=1.0, max_interval=10.0):
    """Sample times (minutes) over `days` days: intervals uniform in [min_interval,
    max_interval], each shift's rescaled to end exactly at its boundary (so every
    boundary j SHIFT is a sample time). Returns t (T,) and the index of each boundary."""
    t, bounds = [0.0], [0]
    for j in range(int(round(days * 1440.0 / SHIFT))):
        steps = []
        while sum(steps) < SHIFT:
            steps.append(rng.uniform(min_interval, max_interval))
        steps = np.asarray(steps) * (SHIFT / sum(steps))
        t.extend(j * SHIFT + np.cumsum(steps))
        t[-1] = (j + 1) * SHIFT
        bounds.append(len(t) - 1)
    return np.asarray(t), np.asarray(bounds)


def coolant(rng, t, levels=T_C_RANGE, move=6.0, hold=(40.0, 240.0), noise=0.5, corr=30.0):
    """The coolant temperature at the samples t: levels held for a random duration
    uniform in `hold` (minutes), each a move uniform in [-move, move] K from the last,
    kept in `levels` (larger steps at a high concentration ignite a runaway), plus
    first-order filtered noise (std `noise` K, correlation time `corr` minutes).
    Returns (T, 1)."""
    level = np.empty(t.shape)
    value = rng.uniform(*levels)
    end = rng.uniform(*hold)
    for k, tk in enumerate(t):
        while tk >= end:
            value = float(np.clip(value + rng.uniform(-move, move), *levels))
            end += rng.uniform(*hold)
        level[k] = value
    moves = np.zeros(t.shape)
    for k in range(1, t.size):
        a = math.exp(-(t[k] - t[k - 1]) / corr)
        moves[k] = a * moves[k - 1] + noise * math.sqrt(1.0 - a * a) * rng.standard_normal()
    return (level + moves)[:, None]


def _augmented(x, u, theta):
    # (C_A, T, integral of C_A): the shift averages come from the third state.
    return jnp.concatenate([rhs(x[:2], u, theta), x[:1]])


@jax.jit
def _integrate(x0, u, dt, theta):
    def step(x, inputs):
        uk, dtk = inputs
        x = oj.ode_step(_augmented, x, uk, theta, dtk, method="rk4", substeps=40)
        return x, x

    _, xs = jax.lax.scan(step, x0, (u, dt))
    return jnp.concatenate([x0[None], xs])


def _check_x64():
    """Refuse float32: the true states' integral of C_A over days needs float64."""
    if jax.dtypes.canonicalize_dtype(jnp.float64) != jnp.float64:
        raise RuntimeError(
            "the CSTR case study's data need float64: call "
            '`jax.config.update("jax_enable_x64", True)` first.'
        )


def simulate_true(t, u, x0, theta=THETA_TRUE):
    """The true states at the sample times t (T,) and the integral of C_A from t[0],
    by RK4 with 40 substeps per interval (at most 0.26 min, against the model's 2 min),
    the input held. Returns (T, 3): C_A, T and the integral."""
    _check_x64()
    theta = {k: jnp.asarray(v, jnp.float64) for k, v in theta.items()}
    x0 = jnp.asarray([x0[0], x0[1], 0.0], jnp.float64)
    xs = _integrate(x0, jnp.asarray(u[:-1], jnp.float64), jnp.asarray(np.diff(t)), theta)
    return np.asarray(xs)


def design(seed=0, *, days=4.0, missing=0.05, outages=3, theta=THETA_TRUE) -> Design:
    """The noise-free record of the case study: sample times, coolant, true states,
    shifts and the temperature samples that exist.

    Needs float64 (`jax.config.update("jax_enable_x64", True)`).

    **Arguments:**

    - `seed`: seeds the times, the coolant and the gaps.
    - `days`: the record's length (a whole number of shifts).
    - `missing`: the fraction of temperature samples lost at random.
    - `outages`: the number of outages of the temperature sensor, each 1 to 3 hours.
    - `theta`: the true parameters.

    **Returns:**

    A `Design`; the record starts at the steady state of its first coolant temperature.
    """
    rng = np.random.default_rng(seed)
    t, bounds = sample_times(rng, days)
    u = coolant(rng, t)
    x0 = steady_state(u[0, 0], theta)
    xs = simulate_true(t, u, x0, theta)
    observed = rng.uniform(size=t.size) >= missing
    for _ in range(int(outages)):
        begin = rng.uniform(0.0, t[-1])
        observed &= ~((t >= begin) & (t < begin + rng.uniform(60.0, 180.0)))
    intervals = tuple((int(a), int(b) + 1) for a, b in zip(bounds[:-1], bounds[1:]))
    averages = np.array([(xs[b - 1, 2] - xs[a, 2]) / (t[b - 1] - t[a]) for a, b in intervals])
    return Design(t, u, xs[:, :2], intervals, averages, observed, dict(theta), x0)


def measure(design, seed, *, sigma_t=SIGMA_T, sigma_c=SIGMA_C):
    """One noise draw on a `Design`.

    **Returns:**

    `(z, averages)`: z (T, 2) with column 0 (C_A) NaN everywhere (it is not sampled) and
    column 1 the temperature plus N(0, sigma_t^2) noise, NaN where not observed; the
    shift averages of C_A plus N(0, sigma_c^2) noise (S,).
    """
    rng = np.random.default_rng(seed)
    temp = design.x[:, 1] + sigma_t * rng.standard_normal(design.t.size)
    z = np.stack([np.full(design.t.size, np.nan), np.where(design.observed, temp, np.nan)], 1)
    averages = design.averages + sigma_c * rng.standard_normal(design.averages.size)
    return z, averages


def midpoints(design):
    """The sample index nearest to the middle of each shift."""
    t = design.t
    return np.array(
        [a + int(np.argmin(np.abs(t[a:b] - 0.5 * (t[a] + t[b - 1])))) for a, b in design.intervals]
    )


def weight(sigma_t=SIGMA_T, sigma_c=SIGMA_C):
    """Q = diag(1/sigma_c^2, 1/sigma_t^2): each output in units of its noise."""
    return np.diag([1.0 / sigma_c**2, 1.0 / sigma_t**2])


def aggregate(design, averages):
    """The measured shift averages as an `oneshot_jax.Aggregate` of C_A (channel 0): the
    time mean over each shift's samples (`kind="time_mean"`, the trapezoid rule over the
    time stamps)."""
    return oj.Aggregate(0, list(design.intervals), averages, kind="time_mean")


def point_samples(design, z, averages):
    """The biased alternative: z with each shift average written as a point sample of
    C_A at the shift's middle sample (`midpoints`), as if the average were the value
    there."""
    z = np.array(z, dtype=float)
    z[midpoints(design), 0] = averages
    return z
