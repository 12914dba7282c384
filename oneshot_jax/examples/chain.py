"""A chain of n masses with a spring and a damper per link: many parameters, few states
each, a known initial state.

Mass i (unit mass) sits between link i and link i + 1; link 1 ties mass 1 to a wall, the
last mass is free and driven by a force u (N). With positions q (n,) and velocities v (n,),

    f_i = k_i (q_i - q_{i-1}) + c_i (v_i - v_{i-1})     (q_0 = v_0 = 0: the wall),
    q_i'' = f_{i+1} - f_i          (f_{n+1} = 0),        plus u on the last mass,

with the stiffness k (n,) and the damping c (n,) unknown (2 n parameters). Every position
is measured. The chain starts at rest (x0 = 0, known).

A standard mechanical test system for identification (a linear multi-body chain); here it
is the many-parameter problem of `benchmarks/peers.py`.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj

from ._arguments import count

DT = 0.05
"""Sampling time, s."""
NOISE_STD = 1e-3
"""Position noise, m."""


def _forces(q, v, k, c, xp):
    zero = xp.zeros(1, q.dtype)
    return k * (q - xp.concatenate([zero, q[:-1]])) + c * (v - xp.concatenate([zero, v[:-1]]))


class ChainRHS(eqx.Module):
    """d(q, v)/dt of a chain of `n` masses; theta = {"k": (n,), "c": (n,)}, u = (force,)."""

    n: int = eqx.field(static=True)

    def __call__(self, x, u, theta):
        n = self.n
        q, v = x[:n], x[n:]
        f = _forces(q, v, theta["k"], theta["c"], jnp)
        a = jnp.concatenate([f[1:], jnp.zeros(1, x.dtype)]) - f
        a = a.at[-1].add(u[0])
        return jnp.concatenate([v, a])


class Positions(eqx.Module):
    """z = q, the n positions."""

    n: int = eqx.field(static=True)

    def __call__(self, x, u, theta):
        del u, theta
        return x[: self.n]


def model(n, dt=DT) -> oj.Model:
    """The chain of `n` masses by RK4 (one step per sample, the force held), observing
    the positions; theta = {"k": (n,), "c": (n,)}."""
    n = count(n, "n")
    return oj.Model.from_ode(ChainRHS(n), dt, observe=Positions(n))


def _rhs_np(x, u, k, c, n):
    q, v = x[:n], x[n:]
    f = _forces(q, v, k, c, np)
    a = np.append(f[1:], 0.0) - f
    a[-1] += u[0]
    return np.concatenate([v, a])


def generate(n=20, T=1000, dt=DT, seed=1, noise_std=NOISE_STD) -> dict:
    """A record of the chain: random stiffness in [1, 2), damping in [0.1, 0.3), a white
    standard-normal force, RK4 in NumPy (independent of the library's integrator), one
    step per sample, from rest.

    **Returns:**

    A dict: `theta` (the true {"k", "c"}), `u` (T, 1), `x` (T, 2n), `z` (T, n) the
    positions plus noise.
    """
    rng = np.random.default_rng(seed)
    k = 1.0 + rng.random(n)
    c = 0.1 + 0.2 * rng.random(n)
    u = rng.standard_normal((T, 1))
    x = np.zeros((T, 2 * n))
    h = dt
    for i in range(T - 1):
        xi, ui = x[i], u[i]
        k1 = _rhs_np(xi, ui, k, c, n)
        k2 = _rhs_np(xi + 0.5 * h * k1, ui, k, c, n)
        k3 = _rhs_np(xi + 0.5 * h * k2, ui, k, c, n)
        k4 = _rhs_np(xi + h * k3, ui, k, c, n)
        x[i + 1] = xi + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    z = x[:, :n] + noise_std * rng.standard_normal((T, n))
    return {"theta": {"k": k, "c": c}, "u": u, "x": x, "z": z}
