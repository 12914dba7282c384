"""The EMPS benchmark: a prismatic axis driven by a DC motor under a PD controller.

Physics (benchmark description, eq. 1-7): the load position q (m) obeys

    M q'' = tau - Fv q' - Fc sign(q') - offset,        tau = gtau * vir  (N),

with the mass M (kg), the viscous and Coulomb friction Fv (N/(m/s)) and Fc (N), and an
offset (N); vir (V) is the controller's force command and gtau (N/V) the drive gain.
sign(q') is replaced by tanh(q' / eps) (eps = 1e-3 m/s by default), a smooth stand-in so
that the closed-form Jacobians exist. The system runs in closed loop at Ts = 1 ms under
the discrete PD law of the benchmark,

    nu[k] = kp kv (qg[k] - q[k]) - kv (q[k] - q[k-2]) / (2 Ts),   |nu| <= 10 V,

with the reference position qg (m); the recorded vir is this law applied to the recorded
position qm (plus the force pulses of the validation record).

Two model structures:

- `open_loop_model`: input tau (N), state (q, q'), output q. The plant is a double
  integrator, so a record is cut into windows (`open_loop_data`), each with its own
  initial state.
- `closed_loop_model`: input (qg, pulse voltage), the PD law in the loop, state
  (q, q', q[k-1], q[k-2]), outputs (q, vir).

The figure of merit is the benchmark's relative error (eq. 11), `relative_error`.

Reference: A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS",
Workshop on Nonlinear System Identification Benchmarks, 2019 (the records are read by
`oneshot_jax.datasets.load_emps`).
"""

import dataclasses
import numbers

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj
from oneshot_jax.datasets import EMPS_IDIM_LS_REFERENCE

from ._arguments import count, positive

PARAMS = ("M", "Fv", "Fc", "offset")
"""The estimated parameters, in order."""
UNITS = {"M": "kg", "Fv": "N/(m/s)", "Fc": "N", "offset": "N"}
REFERENCE = dict(EMPS_IDIM_LS_REFERENCE)
"""The IDIM-LS reference parameters of the benchmark description (Section 3.4)."""
THETA0 = {"M": 50.0, "Fv": 100.0, "Fc": 10.0, "offset": 0.0}
"""A starting point deliberately far from the reference."""
LOWER = {"M": 1e-6, "Fv": 1e-6, "Fc": 1e-6}
"""Lower bounds that keep M, Fv and Fc positive (`oneshot_jax.constraints.box`)."""
EPS = 1e-3
"""m/s: sign(q') is replaced by tanh(q' / EPS)."""
NU_MAX = 10.0
"""V: the saturation of the controller output."""


def acceleration(v, tau, theta, eps=EPS):
    """q'' of eq. (3), (tau - Fv q' - Fc tanh(q'/eps) - offset) / M.

    **Arguments:**

    - `v`: the velocity q' (m/s).
    - `tau`: the motor force (N).
    - `theta`: `{"M", "Fv", "Fc", "offset"}`.
    - `eps`: the width of the smoothed sign (m/s).

    **Returns:**

    The acceleration (m/s^2).
    """
    friction = theta["Fv"] * v + theta["Fc"] * jnp.tanh(v / eps) + theta["offset"]
    return (tau - friction) / theta["M"]


class Plant(eqx.Module):
    """The right-hand side d(q, q')/dt = (q', q'') with input u = (tau,) (N)."""

    eps: float = eqx.field(static=True, default=EPS)

    def __call__(self, x, u, theta):
        return jnp.stack([x[1], acceleration(x[1], u[0], theta, self.eps)])


def _position(x, u, theta):
    del u, theta
    return x[:1]


def open_loop_model(Ts, eps=EPS, substeps=1) -> oj.Model:
    """State (q, q'), input tau (N) held over each sample, output q: RK4 of `Plant`.

    **Arguments:**

    - `Ts`: the sampling time (s).
    - `eps`: the width of the smoothed sign (m/s).
    - `substeps`: RK4 steps per sample.

    **Returns:**

    An `oneshot_jax.Model`; models built with the same arguments compare equal, so
    repeated fits reuse their compilation.
    """
    plant, substeps = Plant(positive(eps, "eps")), count(substeps, "substeps")
    return oj.Model.from_ode(plant, Ts, substeps=substeps, observe=_position)


def controller(x, u, kp, kv, Ts, nu_max=NU_MAX):
    """The benchmark's PD law on the simulated position, plus the pulse (V): eq. (6)-(7),
    with the velocity as the difference (q[k] - q[k-2]) / (2 Ts) of the delay line."""
    nu = kp * kv * (u[0] - x[0]) - kv * (x[0] - x[3]) / (2.0 * Ts)
    return jnp.clip(nu, -nu_max, nu_max) + u[1]


class ClosedLoopStep(eqx.Module):
    """One sample of the closed loop: nu from `controller`, tau = gtau nu held over Ts,
    `substeps` RK4 steps of `Plant`, then the delay line shifts."""

    Ts: float = eqx.field(static=True)
    kp: float = eqx.field(static=True)
    kv: float = eqx.field(static=True)
    gtau: float = eqx.field(static=True)
    eps: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    nu_max: float = eqx.field(static=True)

    def __call__(self, x, u, theta):
        tau = self.gtau * controller(x, u, self.kp, self.kv, self.Ts, self.nu_max)
        y = oj.ode_step(Plant(self.eps), x[:2], tau[None], theta, self.Ts, substeps=self.substeps)
        return jnp.stack([y[0], y[1], x[0], x[2]])


class ClosedLoopOutput(eqx.Module):
    """The outputs (q (m), vir (V)) of the closed loop."""

    Ts: float = eqx.field(static=True)
    kp: float = eqx.field(static=True)
    kv: float = eqx.field(static=True)
    nu_max: float = eqx.field(static=True)

    def __call__(self, x, u, theta):
        del theta
        return jnp.stack([x[0], controller(x, u, self.kp, self.kv, self.Ts, self.nu_max)])


def closed_loop_model(Ts, kp, kv, gtau, eps=EPS, substeps=1, nu_max=NU_MAX) -> oj.Model:
    """State (q, q', q[k-1], q[k-2]), input (qg (m), pulse (V)), outputs (q (m), vir (V)).

    **Arguments:**

    - `Ts`, `kp`, `kv`, `gtau`: the sampling time and the controller constants of the
        benchmark (`oneshot_jax.datasets.EMPS` holds them).
    - `eps`, `substeps`: as for `open_loop_model`.
    - `nu_max`: the controller's saturation (V).

    **Returns:**

    An `oneshot_jax.Model`.
    """
    Ts, kp, kv = float(Ts), float(kp), float(kv)
    eps, substeps = positive(eps, "eps"), count(substeps, "substeps")
    step = ClosedLoopStep(Ts, kp, kv, float(gtau), eps, substeps, float(nu_max))
    return oj.Model(step, ClosedLoopOutput(Ts, kp, kv, float(nu_max)))


# --------------------------------------------------------------------------- data


def velocity_estimate(qm, Ts, half=5):
    """Central difference (qm[k+h] - qm[k-h]) / (2 h Ts), held constant at the ends (m/s).

    **Arguments:**

    - `qm`: the measured positions (n,), m.
    - `Ts`: the sampling time, s.
    - `half`: h, the half-width of the difference in samples.

    **Returns:**

    The velocity estimate (n,), m/s.
    """
    qm = np.asarray(qm, dtype=np.float64)
    if isinstance(half, bool) or not isinstance(half, numbers.Integral) or half < 1:
        raise ValueError(f"`half` must be an integer >= 1 (samples), got {half!r}.")
    if qm.ndim != 1 or qm.shape[0] <= 2 * half:
        raise ValueError(
            f"`qm` must be a 1-d record longer than 2 half = {2 * half} samples, got shape "
            f"{qm.shape}."
        )
    v = np.empty_like(qm)
    v[half:-half] = (qm[2 * half :] - qm[: -2 * half]) / (2 * half * Ts)
    v[:half] = v[half]
    v[-half:] = v[-half - 1]
    return v


def window_starts(n, T=None):
    """Start indices of consecutive windows of T samples in a record of n (the tail that
    does not fill a window is dropped), and T; T None (or >= n) is the whole record."""
    if T is not None and (isinstance(T, bool) or not isinstance(T, numbers.Integral) or T < 1):
        raise ValueError(f"`T` (the window length) must be None or an integer >= 1, got {T!r}.")
    if T is None or T >= n:
        return np.array([0]), int(n)
    return np.arange(n // T) * T, int(T)


def trim(record, n=None):
    """The first n samples of an `oneshot_jax.datasets.EMPSRecord` (all of it for None)."""
    if n is None or n >= len(record):
        return record
    cut = {f: getattr(record, f)[:n] for f in ("t", "qm", "qg", "vir", "pulses")}
    return dataclasses.replace(record, **cut)


def open_loop_data(record, gtau, Ts, T=None, half=5):
    """A record as open-loop windows of T samples: input tau = gtau vir, output qm, and
    each window's initial-state guess (qm, central-difference velocity).

    **Returns:**

    `(u, z, x0)` of shapes (N, T, 1), (N, T, 1), (N, 2).
    """
    starts, T = window_starts(len(record), T)
    idx = starts[:, None] + np.arange(T)[None, :]
    v = velocity_estimate(record.qm, Ts, half)
    u = (gtau * record.vir)[idx][..., None]
    z = record.qm[idx][..., None]
    x0 = np.stack([record.qm[starts], v[starts]], axis=1)
    return u, z, x0


def closed_loop_data(record, Ts, T=None, half=5):
    """A record as closed-loop windows of T samples: input (qg, 0), outputs (qm, vir), and
    each window's initial state (qm, velocity estimate (0 at the record's start), and the
    delay line q[k-1], q[k-2] from qm).

    **Returns:**

    `(u, z, x0)` of shapes (N, T, 2), (N, T, 2), (N, 4).
    """
    starts, T = window_starts(len(record), T)
    idx = starts[:, None] + np.arange(T)[None, :]
    v = velocity_estimate(record.qm, Ts, half)
    u = np.stack([record.qg, np.zeros_like(record.qg)], axis=1)[idx]
    z = np.stack([record.qm, record.vir], axis=1)[idx]
    qm = record.qm

    def previous(k):
        return qm[np.maximum(starts - k, 0)]

    x0 = np.stack([qm[starts], np.where(starts > 0, v[starts], 0.0), previous(1), previous(2)], 1)
    return u, z, x0


def pd_output(record, kp, kv, Ts):
    """The controller law applied to the recorded positions (V), without saturation."""
    qm = record.qm
    qd = np.zeros_like(qm)
    qd[2:] = (qm[2:] - qm[:-2]) / (2 * Ts)
    return kp * kv * (record.qg - qm) - kv * qd


def pulse_voltage(record, kp, kv, Ts):
    """The pulse as it enters the force command (V), and its gain (V per unit of pulses_N).

    The recorded `vir` is the PD law on the recorded positions plus the pulse; the gain is
    the least-squares ratio of (vir - PD law) to `pulses` (1.014 on the benchmark file).
    This describes the experiment, not the plant: it is the same for every parameter set.
    """
    p = record.pulses
    if not np.any(p):
        return np.zeros_like(p), 0.0
    r = record.vir - pd_output(record, kp, kv, Ts)
    gain = float(np.sum(r[2:] * p[2:]) / np.sum(p[2:] ** 2))
    return gain * p, gain


def simulate_closed_loop(data, record, theta, eps=EPS, substeps=1):
    """Closed-loop simulation of a record from its qg and pulses, from rest at qm[0].

    **Arguments:**

    - `data`: the `oneshot_jax.datasets.EMPS` (controller constants, Ts).
    - `record`: the `EMPSRecord` to simulate.
    - `theta`: `{"M", "Fv", "Fc", "offset"}`.
    - `eps`, `substeps`: as for `closed_loop_model`.

    **Returns:**

    `(q, vir)`, the simulated position (m) and force command (V), each (n,).
    """
    model = closed_loop_model(data.Ts, data.kp, data.kv, data.gtau, eps, substeps)
    pv, _ = pulse_voltage(record, data.kp, data.kv, data.Ts)
    u = np.stack([record.qg, pv], axis=1)
    x0 = np.array([record.qm[0], 0.0, record.qm[0], record.qm[0]])
    _, z = oj.simulate(model, {k: float(theta[k]) for k in PARAMS}, x0, u)
    z = np.asarray(z)
    return z[:, 0], z[:, 1]


def relative_error(sim, meas):
    """The benchmark's relative error (eq. 11), 100 ||sim - meas|| / ||meas||, in percent."""
    return float(100.0 * np.linalg.norm(sim - meas) / np.linalg.norm(meas))


def protocol_prediction(data, theta, eps=EPS, substeps=1, n=None, half=5, model=None):
    """The community's protocol on the test record (Champneys et al. 2024): the open-loop
    model, input tau = gtau vir and output qm, with x0 = (q, q') estimated from the first
    n = 20 test outputs only (`oneshot_jax.estimate_x0`, Gauss-Newton), then simulated over
    the whole test record.

    **Arguments:**

    - `data`: the `oneshot_jax.datasets.EMPS` benchmark.
    - `theta`: the parameters (M, Fv, Fc, offset).
    - `eps`, `substeps`: as for `open_loop_model`.
    - `n`: the protocol's number of initial test outputs (default: the record's, 20).
    - `half`: the half-width of the central difference that gives the velocity guess.
    - `model`: another open-loop model with the same state (q, q'), input tau (N) and
        output q, e.g. a hybrid one; `theta` is then its parameters (default:
        `open_loop_model(data.Ts, eps, substeps)`).

    **Returns:**

    `(prediction, scores)`: the `oneshot_jax.Prediction` (q in m) and the
    `oneshot_jax.metrics.benchmark_scores` of q in mm over samples n:.
    """
    test = data.test
    n = test.n if n is None else int(n)
    if model is None:
        model = open_loop_model(data.Ts, eps, substeps)
    u = data.gtau * np.asarray(test.u).reshape(-1, 1)
    y = np.asarray(test.y).reshape(-1, 1)
    v0 = velocity_estimate(y[: max(n, 2 * half + 1), 0], data.Ts, half)[0]
    guess = np.array([y[0, 0], v0])
    pred = oj.predict(model, dict(theta), u, y, n, x0=guess)
    scores = oj.metrics.benchmark_scores(1e3 * y, 1e3 * np.asarray(pred.z), n)
    return pred, scores
