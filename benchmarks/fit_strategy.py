"""`oneshot_jax.fit` end to end, by strategy: sequential scans against parallel in time.

The problem is `parallel.py`'s chain of damped Duffing oscillators (RK4, dt = 0.05, the
data the first position plus noise; theta and x0 estimated from theta * 1.1 and x0 * 0.9;
at n_x = 2 the coupling kc, which then acts as k does, is held). Each cell fits it with
`LevenbergMarquardt(max_steps=--steps)`, once with `strategy="jacobian"` (sequential
`lax.scan`s: the rollout and the sensitivities, the forward twin of eq. (17) and (20))
and once with `strategy="parallel"` (`ParallelInTime`: the DEER rollout and the
sensitivities as associative scans), and says which of the two `strategy="auto"` (the
default) takes on this backend.

Timed: the whole `fit` call as a user makes it (input checks, the compiled solve, the
result's assembly), the first call (compilation included) and the median of `--repeats`
further calls. `steps` and `stop` are the parallel fit's (the sequential one's where
they differ: `a / b`); `rel. diff` is max|theta_par - theta_seq| / max|theta_seq|.

Run: `python benchmarks/fit_strategy.py` (default cells: n_x = 2 at T = 1e3 and 1e4);
`--nx` / `--horizons` pick the cells; `--json PATH` writes the numbers after each cell;
`--render JSON...` prints the table of earlier runs.
"""

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from parallel import chain_problem, fmt_T, rel_diff  # noqa: E402
from timing import conditions, fmt_time, runs, timed  # noqa: E402

import oneshot_jax as oj  # noqa: E402

STRATEGIES = ("jacobian", "parallel")


def time_cell(n_x, T, steps, repeats):
    """One (n_x, T) cell: each strategy's fit, timed, and what they found."""
    model, guess, x0, u, z = chain_problem(n_x, T, jnp.float64, seed=2)
    x0_guess = x0 * 0.9
    # With one oscillator the coupling spring acts on the wall as k does: hold it.
    fixed = {"k": False, "eps": False, "c": False, "kc": n_x == 2}
    row = {"n_x": n_x, "T": T, "steps_cap": steps}
    results = {}
    t0 = time.perf_counter()
    for s in STRATEGIES:
        solver = oj.LevenbergMarquardt(strategy=s, max_steps=steps)
        res, first, warm = timed(
            lambda: oj.fit(model, guess, x0_guess, u, z, solver=solver, fixed=fixed), repeats
        )
        results[s] = res
        row[s] = {
            "first": first,
            "warm": warm,
            "steps": int(res.num_steps),
            "stop": res.status,
            "loss": float(res.loss),
        }
    row["auto"] = oj.Auto().resolve(n_x, T, 8).name
    row["rel_diff"] = rel_diff(results["parallel"].theta, results["jacobian"].theta)
    row["wall"] = time.perf_counter() - t0
    return row


def table(rows):
    head = (
        "| n_x | T | auto takes | steps | stop | sequential: first | warm | "
        "parallel: first | warm | par/seq (warm) | rel. diff |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        seq, par = r["jacobian"], r["parallel"]

        def both(key):
            a, b = par[key], seq[key]
            return str(a) if a == b else f"{a} / {b}"

        ratio = par["warm"] / seq["warm"] if seq["warm"] and par["warm"] else None
        lines.append(
            f"| {r['n_x']} | {fmt_T(r['T'])} | {r['auto']} | {both('steps')} | {both('stop')} "
            f"| {fmt_time(seq['first'])} | {fmt_time(seq['warm'])} | {fmt_time(par['first'])} "
            f"| {fmt_time(par['warm'])} | {'—' if ratio is None else f'{ratio:.3g}'} "
            f"| {r['rel_diff']:.1e} |"
        )
    return "\n".join(lines)


def render(paths):
    """The table of earlier `--json` runs, after each run's conditions."""
    rows = []
    for d in runs(paths, lambda d: f"backend {d['backend']}, median of {d['repeats']} warm calls"):
        rows += d["cells"]
    print()
    print(table(sorted(rows, key=lambda r: (r["n_x"], r["T"]))))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nx", type=int, nargs="+", default=[2], help="state sizes")
    ap.add_argument(
        "--horizons", type=float, nargs="+", default=[1_000, 10_000], help="record lengths T"
    )
    ap.add_argument("--steps", type=int, default=20, help="max_steps of the fits")
    ap.add_argument("--repeats", type=int, default=3, help="warm calls per median")
    ap.add_argument("--json", metavar="PATH", help="write the numbers to PATH (after each cell)")
    ap.add_argument("--render", metavar="JSON", nargs="+", help="print earlier --json runs")
    args = ap.parse_args()
    if args.render:
        render(args.render)
        return

    rows = []
    t_start = time.perf_counter()
    for n in args.nx:
        for T in (int(T) for T in args.horizons):
            rows.append(time_cell(n, T, args.steps, args.repeats))
            print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
            if args.json:
                with open(args.json, "w") as f:
                    json.dump(
                        {
                            "backend": jax.default_backend(),
                            "conditions": conditions(),
                            "repeats": args.repeats,
                            "cells": rows,
                        },
                        f,
                        indent=2,
                    )
    print(
        f"Levenberg-Marquardt fits of the chain of damped Duffing oscillators, float64, backend "
        f"{jax.default_backend()}; the whole `fit` call, median of {args.repeats} warm calls; "
        f"{time.perf_counter() - t_start:.0f} s in all. {conditions()}\n"
    )
    print(table(rows))


if __name__ == "__main__":
    main()
