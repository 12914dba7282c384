"""A multistart fit: its starts in turn, side by side, and a loop of single fits.

A Duffing oscillator (q'' = u - c q' - k q - eps q^3, `Model.from_ode`, RK4, dt = 0.05,
the position measured with 1 % noise) under a multisine, T samples; theta = (c, k, eps)
and x0 estimated from S starts spread over k (0.3 to 3 times the truth, the others at
a rough guess), which need different numbers of steps. For each solver (Levenberg-
Marquardt, Gauss-Newton, 300 steps of Adam), the time of:

- `one start`: `fit` from one start (the first);
- `loop`: a Python loop of S `fit` calls, one per start (one compiled program for all);
- `in turn`: `fit(multistart=...)` with the starts in turn (`lax.scan` over the starts
  inside the one compiled call, each start stopping on its own tests), the default on a
  CPU;
- `side by side`: the same with the starts side by side (vmapped: every start steps
  until the last one stops), the default on an accelerator.

Times are medians of interleaved rounds after warm-up (`timing.interleaved`; compilation
excluded). The best loss of each path is printed too: the paths reach the same optimum.

`--same` puts every start at the rough guess (k = 1.15): the starts then take the same
steps, so that side by side against in turn measures what batching costs or saves by
itself, without the wait for the slowest start.

Run: `python benchmarks/multistart.py` (`--T`, `--starts S`, `--repeats`, `--solvers`,
`--same`; `--quick`: T = 500 only, 3 rounds).
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from timing import conditions, fmt_time, interleaved  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.internal import iterate_module  # noqa: E402

DT = 0.05
TRUTH = {"c": 0.3, "k": 1.0, "eps": 0.8}
THETA0 = {"c": 0.25, "k": 1.15, "eps": 0.7}


def duffing(x, u, p):
    q, v = x
    return jnp.stack([v, u[0] - p["c"] * v - p["k"] * q - p["eps"] * q**3])


MODEL = oj.Model.from_ode(duffing, DT, observe=lambda x, u, p: x[:1])


def make_data(T, seed=0):
    """A multisine of 12 tones (0.05 to 0.6 Hz) from x0 = (0.5, 0), position with 1 %
    noise."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    w = 2 * np.pi * np.linspace(0.05, 0.6, 12)
    u = np.sum(np.sin(np.outer(t, w) + rng.uniform(0, 2 * np.pi, 12)), axis=1)[:, None]
    u = 1.5 * u / u.std()
    x0 = np.array([0.5, 0.0])
    _, q = oj.simulate(MODEL, TRUTH, x0, u)
    q = np.asarray(q)
    z = q + 0.01 * np.sqrt(np.mean(q**2)) * rng.standard_normal(q.shape)
    return u, z, np.array([0.45, 0.05])


SOLVERS = {
    "LevenbergMarquardt": ("LevenbergMarquardt", oj.LevenbergMarquardt),
    "GaussNewton": ("GaussNewton", oj.GaussNewton),
    "Adam": ("Adam, 300 steps", lambda: oj.Adam(1e-2, max_steps=300, gtol=0.0)),
}


def calls(T, S, solver, same=False):
    u, z, x0 = make_data(T)
    ks = np.full(S, THETA0["k"]) if same else np.geomspace(0.3, 3.0, S)
    theta0 = {**THETA0, "k": ks[0]}

    def one():
        return oj.fit(MODEL, theta0, x0, u, z, solver=solver)

    def loop():
        return min(
            (oj.fit(MODEL, {**THETA0, "k": k}, x0, u, z, solver=solver) for k in ks),
            key=lambda r: r.loss,
        )

    def multistart(in_turn):
        def call():
            iterate_module.STARTS_IN_TURN = in_turn
            try:
                return oj.fit(MODEL, theta0, x0, u, z, solver=solver, multistart={"k": ks})
            finally:
                iterate_module.STARTS_IN_TURN = None

        return call

    return {
        "one start": one,
        "loop": loop,
        "in turn": multistart(True),
        "side by side": multistart(False),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--T", type=int, nargs="+", default=[500, 2000])
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="T = 500, 3 rounds")
    parser.add_argument(
        "--same", action="store_true", help="every start at the rough guess (k = 1.15)"
    )
    parser.add_argument(
        "--solvers", nargs="+", choices=SOLVERS, default=list(SOLVERS), help="(default: all)"
    )
    args = parser.parse_args()
    if args.quick:
        args.T, args.repeats = [500], 3
    solvers = {SOLVERS[name][0]: SOLVERS[name][1]() for name in args.solvers}
    S = args.starts
    # The conditions first: a run stopped by a time limit keeps them with its rows.
    print(conditions(), "\n")
    starts = "all at k = 1.15" if args.same else "k from 0.3 to 3"
    print(f"Multistart over k, S = {S} starts ({starts}); median time per fit (best loss).\n")
    print(
        "| T | solver | one start | loop of S fits | in turn | side by side | "
        "side by side / in turn |"
    )
    print("|---|---|---|---|---|---|---|")
    for T in args.T:
        for name, solver in solvers.items():
            fns = calls(T, S, solver, args.same)
            loss = {k: float(fn().loss) for k, fn in fns.items()}
            t = interleaved(fns, repeats=args.repeats, min_sample_s=0.0, warmup=1)
            cells = [f"{fmt_time(t[k])} ({loss[k]:.4g})" for k in fns]
            ratio = t["side by side"] / t["in turn"]
            print(f"| {T} | {name} | " + " | ".join(cells) + f" | {ratio:.2f} |", flush=True)


if __name__ == "__main__":
    main()
