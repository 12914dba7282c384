"""Parallel-in-time (DEER Newton + associative scans) against the sequential `lax.scan`.

The model family: a chain of n_x / 2 damped Duffing oscillators, mass i with stiffness
k_i, cubic stiffness eps_i and damping c_i, neighbours coupled by springs kc, a force on
the first mass; RK4 at dt = 0.05 (`Model.from_ode`), theta = {"k", "eps", "c", "kc"},
n_x in {2, 4, 8, 16}. The input is a slow sine plus white noise, the data z the first
position plus noise. Float64 unless `--float32`.

Timed at each (n_x, T), one trajectory:

- `forward`: sequential `oneshot_jax._simulate.rollout` against the parallel rollout
  (`oneshot_jax.ParallelInTime().rollout`, states x_0..x_{T-1}): what `oneshot_jax.simulate`
  runs with `strategy="jacobian"` and `"parallel"`;
- `value_and_grad`: sequential `oneshot_jax._gradient.value_and_grad_impl` (strategy
  "jacobian") against the `ParallelInTime` rollout and reverse sweep (`parallel_value_and_grad`
  below): what
  `oneshot_jax.value_and_grad` runs with `strategy="jacobian"` and `"parallel"`.

Each callable is one `jax.jit` of the library's internals (the public functions add
their input checks, about a millisecond); the time is the median of interleaved samples
after two warm-up calls (`benchmarks/timing.py`). `iters` are the
parallel rollout's Newton (+ damped) iterations and `solve` the stage that produced the
states (newton / damped / sequential fallback); `rel. diff` is the largest of
max|parallel - sequential| / max|sequential| over the states, C and the gradients.
Cells whose stacked Jacobians (T n_x^2 floats) exceed `--max-mib` run with
`chunk_size` set to stay within it (the `chunk` column).

A fit-like loop: `--fit-steps` steps of gradient descent with Adam on
theta, the whole loop in one `jax.jit` (`lax.fori_loop`), with each gradient from the
sequential or the parallel path; `rel. diff` compares the final theta.

`--memory` adds the memory of one call at n_x = 4 as XLA's compiled memory analysis
reports it (temporaries, arguments, outputs; nothing is run): T = 1e6 unchunked and
chunked, and T = 1e7 chunked.

Run: `python benchmarks/parallel.py` (default grid: the ten cells with T n_x^3 <= 1.1e7);
`--quick` (T in {1e3, 1e4}, n_x in {2, 8}); `--full` (T up to 1e6 at every n_x, for an
accelerator); `--nx` / `--horizons` pick the cells; `--json PATH` writes the numbers (after
each cell); `--render JSON...` prints the tables of earlier runs (the GPU table in
`docs/benchmarks.md` is `python benchmarks/parallel.py --render benchmarks/gpu/h100_grid.json
benchmarks/gpu/h100_nx16.json`; the runs on a GPU are `benchmarks/gpu/h100.sh`).
"""

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from timing import conditions, fmt_time, interleaved, runs  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.internal import (  # noqa: E402
    METHOD_NAMES,
    Cost,
    rollout,
    value_and_grad_impl,
    value_and_grad_of_states,
)

NX = (2, 4, 8, 16)
HORIZONS = (1_000, 10_000, 100_000, 1_000_000)
# The default grid skips cells with T n_x^3 above this (the parallel path's work per
# Newton iteration is O(T n_x^3)): on a 2-core CPU the whole run stays at a few minutes.
DEFAULT_WORK = 1.1e7


def chain_rhs(x, u, th):
    """n_x / 2 damped Duffing oscillators in a chain: q_i'' = -k q - eps q^3 - c q' + springs."""
    m = x.shape[0] // 2
    q, v = x[:m], x[m:]
    zero = jnp.zeros(1, x.dtype)
    left, right = jnp.concatenate([zero, q[:-1]]), jnp.concatenate([q[1:], zero])
    f = -th["k"] * q - th["eps"] * q**3 - th["c"] * v + th["kc"] * (left - 2 * q + right)
    return jnp.concatenate([v, f.at[0].add(u[0])])


def chain_problem(n_x, T, dtype, seed=0):
    m = n_x // 2
    rng = np.random.default_rng(seed)
    model = oj.Model.from_ode(chain_rhs, 0.05, observe=lambda x, u, th: x[:1])
    theta = {
        "k": jnp.linspace(1.0, 2.0, m, dtype=dtype),
        "eps": jnp.full((m,), 0.5, dtype),
        "c": jnp.full((m,), 0.3, dtype),
        "kc": jnp.asarray(0.5, dtype),
    }
    u = 0.5 * np.sin(0.01 * np.arange(T)) + 0.1 * rng.standard_normal(T)
    u = jnp.asarray(u[:, None], dtype)
    x0 = jnp.zeros(n_x, dtype).at[0].set(1.0)
    _, z = oj.simulate(model, theta, x0, u)
    z = z + jnp.asarray(0.01 * rng.standard_normal(z.shape), dtype)
    guess = jax.tree_util.tree_map(lambda a: a * 1.1, theta)
    return model, guess, x0, u, z


def rel_diff(a, b):
    a = np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree_util.tree_leaves(a)])
    b = np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree_util.tree_leaves(b)])
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def parallel_rollout(model, theta, x0, u, chunk_size):
    """The states and `RolloutInfo` of the parallel rollout."""
    return oj.ParallelInTime(chunk_size=chunk_size).rollout(model, theta, x0, u)


def parallel_value_and_grad(model, cost, theta, x0, u, z, chunk_size, with_info=False):
    """C and its gradient parallel in time (`ParallelInTime`: the rollout, then the
    reverse recursion by associative scans), and the rollout's info with `with_info`."""
    strategy = oj.ParallelInTime(chunk_size=chunk_size)
    xs, info = strategy.rollout(model, theta, x0, u)
    out = value_and_grad_of_states(model, cost, theta, xs, u, z, strategy)
    return (out, info) if with_info else out


def chunk_for(T, n_x, itemsize, max_mib):
    per_step = n_x * n_x * itemsize
    return None if T * per_step <= max_mib * 2**20 else max(1, int(max_mib * 2**20 // per_step))


def time_cell(n_x, T, dtype, repeats, max_mib):
    model, theta, x0, u, z = chain_problem(n_x, T, dtype)
    chunk = chunk_for(T, n_x, jnp.dtype(dtype).itemsize, max_mib)
    cost = Cost(None, None, jnp.asarray(0.0, dtype))
    seq_fwd = jax.jit(lambda th, x0, u: rollout(model, th, x0, u))
    par_fwd = jax.jit(lambda th, x0, u: parallel_rollout(model, th, x0, u, chunk))
    seq_vg = jax.jit(
        lambda th, x0, u, z: value_and_grad_impl(model, cost, th, x0, u, z, False, "jacobian")
    )
    par_vg = jax.jit(
        lambda th, x0, u, z: parallel_value_and_grad(
            model, cost, th, x0, u, z, chunk, with_info=True
        )
    )
    calls = {
        "seq_forward": lambda: seq_fwd(theta, x0, u),
        "par_forward": lambda: par_fwd(theta, x0, u),
        "seq_vg": lambda: seq_vg(theta, x0, u, z),
        "par_vg": lambda: par_vg(theta, x0, u, z),
    }
    t0 = time.perf_counter()
    med = interleaved(calls, repeats)
    xs, info = par_fwd(theta, x0, u)
    vg, info_vg = par_vg(theta, x0, u, z)
    med.update(
        n_x=n_x,
        T=T,
        chunk=chunk,
        method=METHOD_NAMES[max(int(info.method), int(info_vg.method))],
        newton_iterations=int(info.newton_iterations),
        damped_iterations=int(info.damped_iterations),
        rel_diff=max(rel_diff(xs, seq_fwd(theta, x0, u)), rel_diff(vg, seq_vg(theta, x0, u, z))),
        wall=time.perf_counter() - t0,
    )
    return med


def time_fit(n_x, T, steps, dtype, repeats, max_mib):
    model, theta, x0, u, z = chain_problem(n_x, T, dtype, seed=1)
    chunk = chunk_for(T, n_x, jnp.dtype(dtype).itemsize, max_mib)
    cost = Cost(None, None, jnp.asarray(0.0, dtype))
    opt = optax.adam(1e-2)

    def grads(kind, th):
        if kind == "sequential":
            return value_and_grad_impl(model, cost, th, x0, u, z, False, "jacobian")[1][0]
        return parallel_value_and_grad(model, cost, th, x0, u, z, chunk)[1][0]

    def fit(kind):
        @jax.jit
        def run(th):
            def body(_, carry):
                th, state = carry
                updates, state = opt.update(grads(kind, th), state, th)
                return optax.apply_updates(th, updates), state

            return jax.lax.fori_loop(0, steps, body, (th, opt.init(th)))[0]

        return run

    seq, par = fit("sequential"), fit("parallel")
    med = interleaved({"sequential": lambda: seq(theta), "parallel": lambda: par(theta)}, repeats)
    med.update(n_x=n_x, T=T, steps=steps, rel_diff=rel_diff(par(theta), seq(theta)))
    return med


MEMORY_CASES = (
    (1_000_000, None),
    (1_000_000, 100_000),
    (10_000_000, 100_000),
    (10_000_000, 10_000),
)


def memory_rows(dtype):
    """Compiled memory of the parallel forward and value_and_grad at n_x = 4 (not run)."""
    rows = []
    model, theta, x0, _, _ = chain_problem(4, 10, dtype)
    cost = Cost(None, None, jnp.asarray(0.0, dtype))
    for T, chunk in MEMORY_CASES:
        u = jax.ShapeDtypeStruct((T, 1), dtype)
        fns = {
            "forward": (lambda th, x0, u, z: parallel_rollout(model, th, x0, u, chunk)),
            "value_and_grad": (
                lambda th, x0, u, z: parallel_value_and_grad(model, cost, th, x0, u, z, chunk)
            ),
        }
        row = {"T": T, "chunk": chunk}
        for name, fn in fns.items():
            ma = jax.jit(fn).lower(theta, x0, u, u).compile().memory_analysis()
            row[name] = {
                "temp": ma.temp_size_in_bytes,
                "argument": ma.argument_size_in_bytes,
                "output": ma.output_size_in_bytes,
            }
        rows.append(row)
    return rows


def memory_table(rows):
    def total(m):
        gib = (m["temp"] + m["argument"] + m["output"]) / 2**30
        return f"{gib:.2f} GiB (temp {m['temp'] / 2**30:.2f})"

    lines = ["| T | chunk | forward | value_and_grad |", "|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {fmt_T(r['T'])} | {r['chunk'] or '-'} | {total(r['forward'])} "
            f"| {total(r['value_and_grad'])} |"
        )
    return "\n".join(lines)


def fmt_T(T):
    """1e4 for a power of ten from 1000 on, else the number itself (64, 512, 1500)."""
    T = int(T)
    if T >= 1000 and f"{T:.0e}".startswith("1e"):
        return f"{T:.0e}".replace("e+0", "e")
    return str(T)


def cell_table(rows, samples=None):
    """The cells' table; `samples` (one count per row) adds a column of samples per median."""
    lines = [
        "| n_x | T | forward seq | forward par | par/seq | value_and_grad seq "
        "| value_and_grad par | par/seq | iters | solve | chunk | rel. diff |"
        + (" samples |" if samples else ""),
        "|" + "---|" * (13 if samples else 12),
    ]
    for i, r in enumerate(rows):
        its = f"{r['newton_iterations']}" + (
            f"+{r['damped_iterations']}" if r["damped_iterations"] else ""
        )
        lines.append(
            f"| {r['n_x']} | {fmt_T(r['T'])} | {fmt_time(r['seq_forward'])} "
            f"| {fmt_time(r['par_forward'])} | {r['par_forward'] / r['seq_forward']:.3g} "
            f"| {fmt_time(r['seq_vg'])} | {fmt_time(r['par_vg'])} "
            f"| {r['par_vg'] / r['seq_vg']:.3g} | {its} | {r['method']} "
            f"| {r['chunk'] or '-'} | {r['rel_diff']:.1e} |"
            + (f" {samples[i]} |" if samples else "")
        )
    return "\n".join(lines)


def fit_table(rows):
    lines = [
        "| n_x | T | Adam steps | sequential | parallel | par/seq | rel. diff (theta) |",
        "|" + "---|" * 7,
    ]
    for r in rows:
        lines.append(
            f"| {r['n_x']} | {fmt_T(r['T'])} | {r['steps']} | {fmt_time(r['sequential'])} "
            f"| {fmt_time(r['parallel'])} | {r['parallel'] / r['sequential']:.3g} "
            f"| {r['rel_diff']:.1e} |"
        )
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    grid = ap.add_mutually_exclusive_group()
    grid.add_argument("--quick", action="store_true", help="T in {1e3, 1e4}, n_x in {2, 8}")
    grid.add_argument("--full", action="store_true", help="every T up to 1e6 at every n_x")
    ap.add_argument("--float32", action="store_true", help="float32 instead of float64")
    ap.add_argument("--repeats", type=int, default=3, help="samples per median (default 3)")
    ap.add_argument(
        "--max-mib", type=float, default=256.0, help="stacked-Jacobian budget per chunk (MiB)"
    )
    ap.add_argument("--fit-T", type=int, default=None, help="record length of the fit loop")
    ap.add_argument("--fit-steps", type=int, default=20, help="Adam steps in the fit loop")
    ap.add_argument("--memory", action="store_true", help="add the compiled-memory table")
    ap.add_argument("--json", metavar="PATH", help="write the numbers to PATH (after each cell)")
    ap.add_argument("--nx", type=int, nargs="+", help="state sizes (overrides the grid)")
    ap.add_argument("--horizons", type=float, nargs="+", help="record lengths T (overrides)")
    ap.add_argument("--no-fit", action="store_true", help="skip the fit-like loop")
    ap.add_argument(
        "--render", metavar="JSON", nargs="+", help="print the tables of earlier --json runs"
    )
    args = ap.parse_args()
    if args.render:
        render(args.render)
        return

    dtype = jnp.float32 if args.float32 else jnp.float64
    if args.quick:
        cells = [(n, T) for n in (2, 8) for T in (1_000, 10_000)]
    elif args.full:
        cells = [(n, T) for n in NX for T in HORIZONS]
    else:
        cells = [(n, T) for n in NX for T in HORIZONS if T * n**3 <= DEFAULT_WORK]
    if args.nx or args.horizons:
        nxs = args.nx or sorted({n for n, _ in cells})
        hs = [int(T) for T in args.horizons] if args.horizons else sorted({T for _, T in cells})
        cells = [(n, T) for n in nxs for T in hs]
    fit_T = args.fit_T or (10_000 if args.quick else 100_000)

    load0 = os.getloadavg()
    t_start = time.perf_counter()
    rows, fits, mem = [], [], []
    for n, T in cells:
        rows.append(time_cell(n, T, dtype, args.repeats, args.max_mib))
        print(f"  n_x={n} T={T}: {rows[-1]['wall']:.0f} s", file=sys.stderr, flush=True)
        print(cell_table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
        write_json(args, dtype, (load0, os.getloadavg()), rows, fits, mem)
    if not args.no_fit:
        fits = [time_fit(2, fit_T, args.fit_steps, dtype, min(args.repeats, 3), args.max_mib)]
    mem = memory_rows(dtype) if args.memory else []
    wall = time.perf_counter() - t_start
    load1 = os.getloadavg()

    print(
        f"Chain of damped Duffing oscillators (RK4, dt = 0.05), computed in "
        f"{jnp.dtype(dtype).name}, backend {jax.default_backend()}. Median of "
        f"{args.repeats} interleaved samples; load average {load0[0]:.1f} -> {load1[0]:.1f}; "
        f"{wall:.0f} s in all. {conditions()}\n"
    )
    print(cell_table(rows))
    if fits:
        print("\nFit-like loop (one jitted loop of Adam steps on theta, n_x = 2):\n")
        print(fit_table(fits))
    if mem:
        print(
            "\nMemory of one call at n_x = 4 (XLA's compiled memory analysis: temporaries, "
            "arguments and outputs):\n"
        )
        print(memory_table(mem))
    write_json(args, dtype, (load0, load1), rows, fits, mem)


def render(paths):
    """One table of the cells of several `--json` files (sorted by n_x, T), then their
    fit-like loops and memory rows, after each file's conditions."""
    cells, fits, mem = [], [], []
    for d in runs(
        paths, lambda d: f"backend {d['backend']}, {d['dtype']}, median of {d['repeats']} samples"
    ):
        cells += [(r, d["repeats"]) for r in d["cells"]]
        fits += d["fit"]
        mem += d["memory"]
    # One row per cell: the first file that measured it (list the main run first).
    cells = list({(r["n_x"], r["T"]): (r, k) for r, k in reversed(cells)}.values())
    cells.sort(key=lambda c: (c[0]["n_x"], c[0]["T"]))
    print()
    print(cell_table([r for r, _ in cells], samples=[k for _, k in cells]))
    if fits:
        print("\nFit-like loop (one jitted loop of Adam steps on theta, n_x = 2):\n")
        print(fit_table(fits))
    if mem:
        print("\nMemory of one call at n_x = 4 (XLA's compiled memory analysis):\n")
        print(memory_table(mem))


def write_json(args, dtype, loads, rows, fits, mem):
    """The numbers so far to `args.json` (rewritten after each cell)."""
    if not args.json:
        return
    with open(args.json, "w") as f:
        json.dump(
            {
                "jax": jax.__version__,
                "backend": jax.default_backend(),
                "conditions": conditions(),
                "dtype": jnp.dtype(dtype).name,
                "repeats": args.repeats,
                "load_average": [loads[0][0], loads[1][0]],
                "cells": rows,
                "fit": fits,
                "memory": mem,
            },
            f,
            indent=2,
        )


if __name__ == "__main__":
    main()
