"""The satellite of Section 4 of the paper: a rigid body with diagonal inertia.

Euler's equations (eq. 22) for the angular velocity w (rad/s) under a known torque M (N m):

    I w' = M - w x (I w),      I = diag(theta["I"]) (kg m^2),      z_k = w(k dt) + e_k,

sampled every dt = 0.1 s, with e_k ~ N(0, sigma_w^2 I_3). The paper's values are the
constants below: the true inertia, the initial angular velocity, the torque statistics
(M_k ~ N(1e-5, (1e-7)^2) per axis and sample, held over each sample) and the output noise.

Reference: C. Donati, M. Mammarella, F. Dabbene, C. Novara, C. Lagoa, "One-shot
backpropagation for multi-step prediction in physics-based system identification",
Section 4, eq. (22) and the values that follow it.
"""

import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj

from ._arguments import is_count

DT = 0.1
"""Sampling time, s."""
THETA_TRUE = (0.0403, 0.0404, 0.0080)
"""True diagonal of the inertia I, kg m^2."""
THETA0 = (0.05, 0.03, 0.01)
"""A tentative start of theta (+24 %, -26 %, +25 % off the truth), kg m^2. (The paper
starts from tentative values; its text does not give them.)"""
W0 = (9.915e-6, -1.102e-3, 1.3179e-5)
"""True initial angular velocity w(0), rad/s."""
TORQUE_MEAN = 1.0e-5
"""Mean of the torque M per axis and sample, N m."""
TORQUE_STD = 1.0e-7
"""Standard deviation of the torque, N m."""
NOISE_STD = 1.0e-4
"""Output noise sigma_w, rad/s."""


def rhs(w, M, theta):
    """Euler's equations, eq. (22): w' = I^{-1} (M - w x (I w)) with I = diag(theta["I"]).

    **Arguments:**

    - `w`: the angular velocity (3,), rad/s.
    - `M`: the torque (3,), N m.
    - `theta`: `{"I": (3,)}`, the diagonal of the inertia, kg m^2.

    **Returns:**

    dw/dt (3,), rad/s^2.
    """
    inertia = theta["I"]
    return (M - jnp.cross(w, inertia * w)) / inertia


def model(dt=DT, substeps=1) -> oj.Model:
    """The identification model: `rhs` by classical RK4 (`substeps` steps per sample),
    the torque held over each sample (zero-order hold), the whole state observed.

    **Arguments:**

    - `dt`: the sampling time, s.
    - `substeps`: RK4 steps per sample.

    **Returns:**

    An `oneshot_jax.Model` with theta = `{"I": (3,)}`.
    """
    return oj.Model.from_ode(rhs, dt, method="rk4", substeps=substeps)


def _rhs_np(w, M, inertia):
    return (M - np.cross(w, inertia * w)) / inertia


def simulate_np(inertia, w0, M, dt=DT, substeps=5):
    """Batched classical RK4 of eq. (22) in NumPy (independent of the library's
    integrator), the torque held over each sample.

    **Arguments:**

    - `inertia`: (B, 3) diagonals of I.
    - `w0`: (B, 3) initial angular velocities.
    - `M`: (B, n, 3) torques.
    - `dt`, `substeps`: the sampling time and the RK4 steps per sample.

    **Returns:**

    w (B, n, 3) with w[:, 0] = w0.
    """
    inertia = np.asarray(inertia, dtype=np.float64)
    w = np.array(w0, dtype=np.float64)
    M = np.asarray(M, dtype=np.float64)
    n = M.shape[1]
    h = dt / substeps
    out = np.empty(M.shape)
    out[:, 0] = w
    for k in range(n - 1):
        m = M[:, k]
        for _ in range(substeps):
            k1 = _rhs_np(w, m, inertia)
            k2 = _rhs_np(w + 0.5 * h * k1, m, inertia)
            k3 = _rhs_np(w + 0.5 * h * k2, m, inertia)
            k4 = _rhs_np(w + h * k3, m, inertia)
            w = w + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out[:, k + 1] = w
    return out


def generate(
    seeds,
    n,
    *,
    theta=THETA_TRUE,
    w0=W0,
    dt=DT,
    torque_mean=TORQUE_MEAN,
    torque_std=TORQUE_STD,
    noise_std=NOISE_STD,
    substeps=5,
) -> dict:
    """Records of the case study, one per seed: torque, true state and measurement.

    Each seed draws its torque and its noise from two independent streams spawned from
    `numpy.random.SeedSequence(seed)`, so a record of n samples is a prefix of any longer
    record of the same seed. The states come from `simulate_np` (RK4, `substeps` steps
    per sample).

    **Arguments:**

    - `seeds`: a sequence of integer seeds.
    - `n`: samples per record.
    - `theta`, `w0`, `dt`, `torque_mean`, `torque_std`, `noise_std`: the system and the
        signals (defaults: the paper's values, this module's constants).
    - `substeps`: RK4 steps per sample of the data.

    **Returns:**

    A dict of NumPy arrays: `u` (S, n, 3) torque, `x` (S, n, 3) true angular velocity,
    `z` (S, n, 3) measurement, and `t` (n,) the sample times.
    """
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise ValueError(f"`seeds` must be a sequence of integer seeds, got {seeds!r}.")
    seeds = list(seeds)
    if not seeds:
        raise ValueError("`seeds` must hold at least one integer seed, got none.")
    for seed in seeds:
        if not is_count(seed, 0):
            raise ValueError(f"`seeds` must be integers >= 0, got {seed!r}.")
    if not is_count(n, 1):
        raise ValueError(f"`n` (samples per record) must be an integer >= 1, got {n!r}.")
    if not is_count(substeps, 1):
        raise ValueError(f"`substeps` must be an integer >= 1, got {substeps!r}.")
    for name, value in (("theta", theta), ("w0", w0)):
        if np.shape(value) != (3,):
            raise ValueError(
                f"`{name}` must hold 3 entries (one per axis), got shape {np.shape(value)}."
            )
    if np.ndim(torque_mean) != 0 or not np.isfinite(float(torque_mean)):
        raise ValueError(f"`torque_mean` must be a finite number, got {torque_mean!r}.")
    for name, value in (("dt", dt), ("torque_std", torque_std), ("noise_std", noise_std)):
        if np.ndim(value) != 0 or not np.isfinite(float(value)) or float(value) < 0:
            raise ValueError(f"`{name}` must be a finite number >= 0, got {value!r}.")
    if float(dt) == 0:
        raise ValueError("`dt` must be positive, got 0.")
    us, es = [], []
    for seed in seeds:
        streams = np.random.SeedSequence(int(seed)).spawn(2)
        rng_u, rng_e = (np.random.default_rng(s) for s in streams)
        us.append(float(torque_mean) + float(torque_std) * rng_u.standard_normal((n, 3)))
        es.append(float(noise_std) * rng_e.standard_normal((n, 3)))
    u = np.stack(us)
    S = len(us)
    inertia = np.broadcast_to(np.asarray(theta, dtype=np.float64), (S, 3))
    w = np.broadcast_to(np.asarray(w0, dtype=np.float64), (S, 3))
    x = simulate_np(inertia, w, u, float(dt), int(substeps))
    return {"u": u, "x": x, "z": x + np.stack(es), "t": float(dt) * np.arange(n)}
