"""The cascaded-tanks benchmark: two water tanks in series, with overflow.

States in volts of the lower-tank level sensor: x1 the upper tank, x2 the lower tank;
input u the pump voltage (V, held over Ts = 4 s); output y the sensor (V).

**basic** (benchmark description, eq. 1-3, with an output offset c; Torricelli's law):

    x1' = k4 u - k1 sqrt(x1),     x2' = k1 sqrt(x1) - k3 sqrt(x2),     y = x2 + c.

**overflow**: the upper tank is full at x1 = h1; the inflow it cannot hold spills, a
fraction k5 of it into the lower tank (the rest to the reservoir); the lower tank is full
at x2 = h2:

    q_in = k4 u,  q12 = k1 sqrt(x1),
    s1 = sigma((x1 - h1)/w) relu(q_in - q12)                 (upper-tank spill)
    x1' = q_in - q12 - s1
    n2 = q12 + k5 s1 - k3 sqrt(x2),  s2 = sigma((x2 - h2)/w) relu(n2)
    x2' = n2 - s2,                    y = x2 + c,

with the logistic gate sigma and the relu smoothed (gate width w = 0.05 V, relu by a
softplus of width 1e-3 V/s) so that the closed-form Jacobians exist. The smoothed gate
does not hold a level at h: while the inflow exceeds the outflow, the level goes on
rising past h, slowly (by several gate widths over minutes, like w ln t), so a fitted h
sits somewhat below the physical overflow height.

The models are for levels above empty: Torricelli's sqrt is taken of max(x, 1e-6) (a
finite derivative at an empty tank), so an empty tank goes on draining at k1 1e-3 V/s and
its level drifts below zero. The benchmark's records stay well above empty.

**sensor**: the level sensors are not calibrated and "can introduce an extra source of
nonlinear behavior" (benchmark description, Sec. 3). With the parameter c2 in theta
(either model), the output is quadratic in the level:

    y = x2 + c + c2 (x2 - SENSOR_LEVEL)^2,

with slope one at x2 = SENSOR_LEVEL, so that x2 keeps the sensor's volts there (c2 in
1/V; without c2, y = x2 + c).

Units and scaling: the sensor is not calibrated, so levels are in sensor volts. x1 is the
upper tank's water volume divided by the lower tank's cross-section, so the flow that
leaves the upper tank enters the lower one with the same coefficient (k2 = k1: this
removes the one unidentifiable scale) and k5 is a volume fraction in [0, 1]. k1, k3 are
in V^0.5/s, k4 in 1/s, h1, h2 and c in V. Both records start from the same unknown state
(benchmark description, Sec. 3).

Reference: M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, "Cascaded tanks benchmark
combining soft and hard nonlinearities", Workshop on Nonlinear System Identification
Benchmarks, 2016 (the records are read by `oneshot_jax.datasets.load_cascaded_tanks`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

import oneshot_jax as oj

from ._arguments import count, positive

KINDS = ("basic", "overflow")
UNITS = {
    "k1": "V^0.5/s",
    "k3": "V^0.5/s",
    "k4": "1/s",
    "c": "V",
    "h1": "V",
    "h2": "V",
    "k5": "-",
    "c2": "1/V",
}
GATE_WIDTH = 0.05
"""V: width of the logistic "tank is full" gates."""
RELU_WIDTH = 1e-3
"""V/s: softplus width of the smoothed relu of the spilled flow."""
SENSOR_LEVEL = 5.0
"""V: the level at which the quadratic sensor's slope is one (mid-range of the records)."""
PUBLISHED = {
    "BLA (best linear approximation)": 0.7574,
    "Volterra, 3rd degree, transient removal": 0.54,
    "PNLSS-I (polynomial nonlinear state space)": 0.4498,
    "NLSS2 (nonlinear state space)": 0.3433,
}
"""Published simulation RMSEs (V) on the validation record, as compiled in Table 2 of
"Hammerstein Box-Jenkins System Identification of the Cascaded Tanks Benchmark System",
Mathematical Problems in Engineering, 2021, article 6613425 (the benchmark description
itself reports no results)."""


def _sqrt(x):
    # Torricelli's sqrt, kept differentiable at an empty tank.
    return jnp.sqrt(jnp.maximum(x, 1e-6))


def _relu(a, width):
    return width * jax.nn.softplus(a / width)


def basic_rhs(x, u, theta):
    """The basic model's right-hand side (eq. 1-3 of the benchmark description)."""
    q12 = theta["k1"] * _sqrt(x[0])
    return jnp.stack([theta["k4"] * u[0] - q12, q12 - theta["k3"] * _sqrt(x[1])])


class OverflowRHS(eqx.Module):
    """The overflow model's right-hand side (module docstring), with smoothed gates."""

    gate_width: float = eqx.field(static=True, default=GATE_WIDTH)
    relu_width: float = eqx.field(static=True, default=RELU_WIDTH)

    def __call__(self, x, u, theta):
        q_in = theta["k4"] * u[0]
        q12 = theta["k1"] * _sqrt(x[0])
        gate1 = jax.nn.sigmoid((x[0] - theta["h1"]) / self.gate_width)
        s1 = gate1 * _relu(q_in - q12, self.relu_width)
        n2 = q12 + theta["k5"] * s1 - theta["k3"] * _sqrt(x[1])
        s2 = jax.nn.sigmoid((x[1] - theta["h2"]) / self.gate_width) * _relu(n2, self.relu_width)
        return jnp.stack([q_in - q12 - s1, n2 - s2])


def observe(x, u, theta):
    """y = x2 + c, plus c2 (x2 - SENSOR_LEVEL)^2 where theta has c2 (the sensor's
    curvature)."""
    del u
    y = x[1:2] + theta["c"]
    if "c2" in theta:
        y = y + theta["c2"] * (x[1:2] - SENSOR_LEVEL) ** 2
    return y


def model(kind, Ts, substeps=1, gate_width=GATE_WIDTH, relu_width=RELU_WIDTH) -> oj.Model:
    """The `oneshot_jax.Model` of the basic or the overflow model (RK4, `substeps` steps
    per sample, the pump voltage held over each sample).

    **Arguments:**

    - `kind`: `"basic"` or `"overflow"`.
    - `Ts`: the sampling time (s).
    - `substeps`: RK4 steps per sample.
    - `gate_width`, `relu_width`: the smoothing of the overflow model.

    **Returns:**

    An `oneshot_jax.Model` with theta = {k1, k3, k4, c} (basic) or {k1, k3, k4, c, h1,
    h2, k5} (overflow), each optionally with c2 (the quadratic sensor, `observe`).
    """
    if kind not in KINDS:
        raise ValueError(f"`kind` must be one of {KINDS}, got {kind!r}.")
    widths = (positive(gate_width, "gate_width"), positive(relu_width, "relu_width"))
    rhs = basic_rhs if kind == "basic" else OverflowRHS(*widths)
    substeps = count(substeps, "substeps")
    return oj.Model.from_ode(rhs, Ts, method="rk4", substeps=substeps, observe=observe)


def constraints(kind):
    """Physical bounds: k1, k3, k4 > 0; for the overflow model h1, h2 >= 0, 0 <= k5 <= 1."""
    if kind not in KINDS:
        raise ValueError(f"`kind` must be one of {KINDS}, got {kind!r}.")
    lower = {"k1": 1e-6, "k3": 1e-6, "k4": 1e-6}
    upper = None
    if kind == "overflow":
        lower.update({"k5": 0.0, "h1": 0.0, "h2": 0.0})
        upper = {"k5": 1.0}
    return oj.constraints.box(lower, upper)
