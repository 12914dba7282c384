"""A network fed the whole state absorbs part of the physics; `fit_physics_first` does not.

A pendulum, q'' = -w0sq sin q - (0.1 q' + 0.3 tanh(4 q')) + g u (w0sq = 9, g = 1), driven
by a multisine away from its resonance, its angle measured with noise 0.01 rad (RK4,
dt = 0.05 s). The hybrid model keeps a linear damping b q' and adds an MLP(8) r(q, q')
fed the WHOLE state: q'' = -w0sq sin q - b q' + r(q, q') + g u. A term of r in q trades
with w0sq sin q, and the data cannot tell them apart. For each network seed it prints
w0sq (truth 9) and the RMSE from three fits, all Levenberg-Marquardt with its defaults:

- `joint`: `oj.fit` of everything from the start (w0sq = 8, b = 0.2, g = 1, the network
  at zero output);
- `physics, then joint`: the physics alone (the network held at zero), then everything
  jointly from there (the recipe of the hybrid guide's neural residual);
- `physics first`: `oj.fit_physics_first(..., learned="r")`, the physics alone, then
  the network with the physics held.

The numbers of the section "A network that sees everything" of docs/guides/minima.md
come from `python benchmarks/hybrid_physics_first.py` (T = 300, seeds 0, 1, 2).
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj
from oneshot_jax.residual import MLP

jax.config.update("jax_enable_x64", True)
DT, W0SQ = 0.05, 9.0


def observe(x, u, p):
    return x[:1]


def truth_rhs(x, u, p):
    q, v = x
    return jnp.stack(
        [v, -p["w0sq"] * jnp.sin(q) - (0.1 * v + 0.3 * jnp.tanh(4 * v)) + p["g"] * u[0]]
    )


def hybrid_rhs(x, u, p):
    q, v = x
    r = p["r"](x)[0]  # the whole state: r can learn a term in q
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - p["b"] * v + r + p["g"] * u[0]])


def record(T, seed=0, noise=0.01):
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.0, 2.0, 4.5, 6.0))[:, None]
    truth = oj.Model.from_ode(truth_rhs, DT, observe=observe)
    x, z = oj.simulate(truth, {"w0sq": W0SQ, "g": 1.0}, np.zeros(2), u)
    return u, np.asarray(z) + noise * rng.standard_normal(np.shape(z)), np.asarray(x)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--T", type=int, default=300)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()

    model = oj.Model.from_ode(hybrid_rhs, DT, observe=observe)
    u, z, x = record(args.T)
    print(f"T = {args.T}, true w0sq = {W0SQ}; w0sq (relative error), RMSE in rad")
    print(f"{'seed':>4}  {'joint':>22}  {'physics, then joint':>22}  {'physics first':>22}")
    for seed in args.seeds:
        net = MLP(
            2, 1, (8,), key=jax.random.PRNGKey(seed), input_offset=x.mean(0), input_scale=x.std(0)
        )
        theta0 = {"w0sq": 8.0, "b": 0.2, "g": 1.0, "r": net}
        joint = oj.fit(model, theta0, np.zeros(2), u, z)
        first = oj.fit_physics_first(model, theta0, np.zeros(2), u, z, learned="r")
        then = oj.fit(model, {**first.physics.theta, "r": net}, first.physics.x0, u, z)

        def cell(r):
            w = float(r.theta["w0sq"])
            return f"{w:7.3f} ({100 * (w / W0SQ - 1):+5.1f} %) {np.sqrt(float(r.loss)):.4f}"

        print(f"{seed:>4}  {cell(joint):>22}  {cell(then):>22}  {cell(first.result):>22}")
    print(
        f"physics alone: w0sq {float(first.physics.theta['w0sq']):.3f}, "
        f"RMSE {np.sqrt(float(first.physics.loss)):.4f}"
    )


if __name__ == "__main__":
    main()
