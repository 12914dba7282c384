"""What the checks for bad minima and integrator stability cost next to a fit.

The pendulum of docs/guides/minima.md (RK4, dt = 0.05, angle measured), T samples, fitted
from the truth (a converged fit in few steps: the cheapest fit, so the ratios are the
largest they get). Timed with `timing.timed` (the first call, compilation included, in a
fresh process for this model; the median of further calls):

- `fit`: `oneshot_jax.fit`, which runs the stability check after the solve;
- `check_stability`: the check alone (one compiled simulation with the Jacobian of the
  right-hand side at 32 states, eigenvalues on the host): what every fit of a
  `Model.from_ode` model pays;
- `check_basin`: the opt-in bad-basin check (a windowed fit, windows of 50);
- `fit_continuation`: windows of 50, then the whole record.

Run: `python benchmarks/checks.py` (`--T 400 1500`, `--repeats N`).
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from timing import conditions, fmt_time, timed

import oneshot_jax as oj

jax.config.update("jax_enable_x64", True)
DT = 0.05
TRUTH = {"w0sq": 9.0, "b": 0.3}


def pendulum(x, u, p):
    return jnp.stack([x[1], -p["w0sq"] * jnp.sin(x[0]) - p["b"] * x[1] + u[0]])


def row(T, repeats):
    model = oj.Model.from_ode(pendulum, DT, observe=lambda x, u, p: x[:1])
    rng = np.random.default_rng(0)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.5, 3.0, 6.0))[:, None]
    _, z = oj.simulate(model, TRUTH, np.zeros(2), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal((T, 1))
    x0 = np.zeros(2)
    # The check first, so that its first call compiles it (fit runs it too).
    _, st_first, st_warm = timed(lambda: oj.check_stability(model, TRUTH, x0, u), repeats)
    result, fit_first, fit_warm = timed(lambda: oj.fit(model, TRUTH, x0, u, z), repeats)
    _, cb_first, cb_warm = timed(lambda: oj.check_basin(result, u, z, window=50), repeats)
    _, fc_first, fc_warm = timed(
        lambda: oj.fit_continuation(model, TRUTH, x0, u, z, windows=(50,)), repeats
    )
    return (T, fit_first, fit_warm, st_first, st_warm, cb_first, cb_warm, fc_first, fc_warm)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--T", type=int, nargs="+", default=[400, 1500])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(conditions())
    print()
    print("first call (compilation included) / later calls (median)")
    print("| T | fit | check_stability | check_basin | fit_continuation |")
    print("|---|---|---|---|---|")
    for T in args.T:
        r = row(T, args.repeats)
        cells = [f"{fmt_time(a)} / {fmt_time(b)}" for a, b in zip(r[1::2], r[2::2])]
        print(f"| {T} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
