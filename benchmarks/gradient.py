"""Cost of the one-shot closed-form gradient against the forward simulation and autodiff.

The paper's satellite (Section 4, `oneshot_jax.examples.satellite`): Euler's equations
I w' = M - w x (I w) with a diagonal inertia theta = {"I": (3,)}, RK4 at dt = 0.1 s, the
paper's w0, its torque and noise statistics, float64. Gradients are taken at the paper's
tentative values (theta and w0 off by 20-30 %), as during identification.

Timed at each horizon T, in one run:

- `forward`: the simulation, `oneshot_jax.simulate`;
- `jacobian`, `vjp`: the closed-form `oneshot_jax.value_and_grad` with that `strategy`
  (eq. 17/20 by the reverse recursion, both gradients in theta and x0);
- `autodiff`: `jax.value_and_grad` (in theta and x0) of `oneshot_jax.loss`, i.e.
  reverse-mode differentiation through the same `lax.scan` rollout;
- `public ...`: `oneshot_jax.simulate` / `oneshot_jax.value_and_grad` (strategy "auto")
  called directly, i.e. including input validation and equinox's dispatch.

The first four columns are each wrapped in one `jax.jit` (model closed over, arrays as
arguments), so they share the same dispatch path and only the compiled computation
differs; the ratios use these. Every time is the median of interleaved samples after two
warm-up calls (`timing.interleaved`: compilation excluded, each call blocked, the methods
alternating so that a change of machine load hits all of them alike). `rel. diff` is
max|closed - autodiff| / max|autodiff| over C and the gradients in theta and x0, the larger
of the two strategies.

XLA:CPU runs a while loop as one compiled kernel only when one iteration touches less than
1 KiB (`xla_cpu_small_while_loop_byte_threshold`); the forward rollout and the jacobian
strategy's reverse scan qualify, the backward loop of autodiff and the vjp strategy's scan
do not, and then every operation of every iteration is a separate call. Much of the
autodiff gap on CPU comes from there (see `--xla-context`).

The second table is the peak memory of one `value_and_grad` call (strategy "vjp",
n_x = 1000, T = 1000, a tanh-coupled model with a dense 1000 x 1000 coupling in theta)
next to autodiff and the forward simulation, measured two ways in a fresh subprocess
each: XLA's `compiled.memory_analysis()` (argument + output + temporary buffers) and the
growth of the process's peak resident set over a second call (`VmHWM` in /proc/self/status,
reset through /proc/self/clear_refs after compilation and a first call; glibc's mmap
threshold is pinned and the heap trimmed so that freed buffers do not hide the peak).

Run: `python benchmarks/gradient.py` (`--quick`: T in {50, 500} only; `--json PATH`: the
numbers; `--pin-cpu N`: timings on one core, steadier on a shared machine;
`--xla-context`: one more timing table with that XLA threshold raised, in a subprocess;
`--no-memory`: skip the memory table).
"""

import argparse
import ctypes
import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from timing import block, conditions, fmt_time, interleaved  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.examples import satellite  # noqa: E402
from oneshot_jax.internal import flat_host  # noqa: E402

HORIZONS = (50, 500, 5000, 50000)
QUICK_HORIZONS = (50, 500)
HOIST_FLAG = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000000"


def rel_diff(a, b):
    a, b = flat_host(a), flat_host(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def time_horizon(model, T, repeats):
    data = satellite.generate([0], T)
    u, z = jnp.asarray(data["u"][0]), jnp.asarray(data["z"][0])
    theta = {"I": jnp.asarray(satellite.THETA0)}
    x0 = jnp.asarray(satellite.W0) * 1.2

    fwd = jax.jit(lambda th, x0, u: oj.simulate(model, th, x0, u))
    jac = jax.jit(lambda th, x0, u, z: oj.value_and_grad(model, th, x0, u, z, strategy="jacobian"))
    vjp = jax.jit(lambda th, x0, u, z: oj.value_and_grad(model, th, x0, u, z, strategy="vjp"))
    ad = jax.jit(
        jax.value_and_grad(lambda th, x0, u, z: oj.loss(model, th, x0, u, z), argnums=(0, 1))
    )
    calls = {
        "forward": lambda: fwd(theta, x0, u),
        "jacobian": lambda: jac(theta, x0, u, z),
        "vjp": lambda: vjp(theta, x0, u, z),
        "autodiff": lambda: ad(theta, x0, u, z),
        "public_simulate": lambda: oj.simulate(model, theta, x0, u),
        "public_value_and_grad": lambda: oj.value_and_grad(model, theta, x0, u, z),
    }
    med = interleaved(calls, repeats)
    g_ref = ad(theta, x0, u, z)
    med["rel_diff_jacobian"] = rel_diff(jac(theta, x0, u, z), g_ref)
    med["rel_diff_vjp"] = rel_diff(vjp(theta, x0, u, z), g_ref)
    med["T"] = T
    return med


def timing_table(rows):
    head = (
        "| T | forward | jacobian | vjp | autodiff | autodiff / jacobian | autodiff / vjp "
        "| jacobian / forward | vjp / forward | public simulate | public value_and_grad "
        "| rel. diff vs autodiff |"
    )
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        lines.append(
            f"| {r['T']} | {fmt_time(r['forward'])} | {fmt_time(r['jacobian'])} "
            f"| {fmt_time(r['vjp'])} | {fmt_time(r['autodiff'])} "
            f"| {r['autodiff'] / r['jacobian']:.1f}x | {r['autodiff'] / r['vjp']:.1f}x "
            f"| {r['jacobian'] / r['forward']:.2f}x | {r['vjp'] / r['forward']:.2f}x "
            f"| {fmt_time(r['public_simulate'])} | {fmt_time(r['public_value_and_grad'])} "
            f"| {max(r['rel_diff_jacobian'], r['rel_diff_vjp']):.1e} |"
        )
    return "\n".join(lines)


# --- memory: one call in a fresh process ------------------------------------------------

MEM_NX, MEM_T = 1000, 1000


def coupled_model(n):
    def step(x, u, th):
        return x + 0.05 * (-x / th["tau"] + th["W"] @ jnp.tanh(x) + th["b"] * u[0])

    return oj.Model(step)


def _status_kib(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(field)


def memory_worker(method):
    """Run in a subprocess: compile one call, reset the peak RSS, run it, report."""
    n, T = MEM_NX, MEM_T
    rng = np.random.default_rng(0)
    model = coupled_model(n)
    theta = {
        "W": jnp.asarray(rng.normal(0, 0.5 / np.sqrt(n), (n, n))),
        "tau": jnp.asarray(rng.uniform(0.5, 2.0, n)),
        "b": jnp.asarray(rng.normal(0, 1, n)),
    }
    x0 = jnp.asarray(rng.normal(0, 0.1, n))
    u = jnp.asarray(rng.normal(0, 1, (T, 1)))
    z = jnp.asarray(rng.normal(0, 0.1, (T, n)))
    if method == "forward":
        fn = jax.jit(lambda th, x0, u, z: oj.simulate(model, th, x0, u))
    elif method == "autodiff":
        fn = jax.jit(
            jax.value_and_grad(lambda th, x0, u, z: oj.loss(model, th, x0, u, z), argnums=(0, 1))
        )
    else:
        fn = jax.jit(lambda th, x0, u, z: oj.value_and_grad(model, th, x0, u, z, strategy=method))
    compiled = fn.lower(theta, x0, u, z).compile()
    ma = compiled.memory_analysis()
    xla_bytes = None
    if ma is not None:
        xla_bytes = int(
            ma.argument_size_in_bytes
            + ma.output_size_in_bytes
            + ma.temp_size_in_bytes
            - ma.alias_size_in_bytes
        )
        temp_bytes = int(ma.temp_size_in_bytes)
    block(compiled(theta, x0, u, z))  # first run: allocator warm, pages touched once
    # The parent sets MALLOC_MMAP_THRESHOLD_, so every large buffer is its own mapping and
    # goes back to the OS when freed; trim what is left, then reset VmHWM to the RSS now.
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    rss0 = _status_kib("VmRSS")
    t0 = time.perf_counter()
    block(compiled(theta, x0, u, z))
    dt = time.perf_counter() - t0
    hwm = _status_kib("VmHWM")
    print(
        json.dumps(
            {
                "method": method,
                "xla_bytes": xla_bytes,
                "xla_temp_bytes": temp_bytes if ma is not None else None,
                "rss_peak_delta_bytes": (hwm - rss0) * 1024,
                "seconds": dt,
            }
        )
    )


def memory_rows():
    rows = []
    for method in ("forward", "vjp", "autodiff"):
        env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
        out = subprocess.run(
            [sys.executable, __file__, "--_memory-worker", method],
            capture_output=True,
            text=True,
            check=True,
            env=env,
        )
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return rows


def memory_table(rows):
    mib = lambda b: "n/a" if b is None else f"{b / 2**20:.1f} MiB"  # noqa: E731
    lines = [
        f"| n_x = {MEM_NX}, T = {MEM_T} | XLA buffers (args + outputs + temps) | XLA temps "
        "| peak RSS growth of the call (VmHWM) | time |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {mib(r['xla_bytes'])} | {mib(r['xla_temp_bytes'])} "
            f"| {mib(r['rss_peak_delta_bytes'])} | {fmt_time(r['seconds'])} |"
        )
    stacked = MEM_T * MEM_NX * MEM_NX * 8
    lines.append(
        f"| jacobian (not run) | stacked J^{{x/x}}_k alone: T n_x^2 x 8 B = "
        f"{stacked / 2**30:.1f} GiB | | | |"
    )
    return "\n".join(lines)


# --- driver -----------------------------------------------------------------------------


def run_timings(horizons, repeats):
    # Built here: the backend must start after `--pin-cpu` has taken effect.
    model = satellite.model()
    rows = []
    for T in horizons:
        rows.append(time_horizon(model, T, repeats))
        print(f"  T = {T} done", file=sys.stderr, flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="T in {50, 500} only")
    ap.add_argument("--json", metavar="PATH", help="write the numbers to PATH")
    ap.add_argument("--repeats", type=int, default=15, help="samples per median (default 15)")
    ap.add_argument(
        "--xla-context",
        action="store_true",
        help="also time with XLA's small-while-loop threshold raised (subprocess)",
    )
    ap.add_argument("--no-memory", action="store_true", help="skip the memory table")
    ap.add_argument(
        "--pin-cpu",
        type=int,
        metavar="N",
        help="run the timings on CPU N only (XLA's threads included): steadier on a busy machine",
    )
    ap.add_argument("--_memory-worker", dest="memory_worker", help=argparse.SUPPRESS)
    ap.add_argument("--_timing-worker", dest="timing_worker", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.pin_cpu is not None:  # before the backend starts its threads
        os.sched_setaffinity(0, {args.pin_cpu})
    if args.memory_worker:
        memory_worker(args.memory_worker)
        return
    horizons = QUICK_HORIZONS if args.quick else HORIZONS
    if args.timing_worker:
        rows = run_timings([int(t) for t in args.timing_worker.split(",")], args.repeats)
        print(json.dumps(rows))
        return

    t_start = time.perf_counter()
    rows = run_timings(horizons, args.repeats)
    mem = [] if args.no_memory else memory_rows()
    context = None
    if args.xla_context:
        env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + HOIST_FLAG))
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--_timing-worker",
                ",".join(map(str, horizons)),
                "--repeats",
                str(args.repeats),
            ]
            + ([] if args.pin_cpu is None else ["--pin-cpu", str(args.pin_cpu)]),
            capture_output=True,
            text=True,
            check=True,
            env=env,
        )
        context = json.loads(out.stdout.strip().splitlines()[-1])
    wall = time.perf_counter() - t_start

    print(
        "Satellite (n_x = 3, n_theta = 3): time per call, median of "
        f"{args.repeats} interleaved samples"
        f"{'' if args.pin_cpu is None else f', timings pinned to CPU {args.pin_cpu}'}. "
        "Ratios use the first four columns (each in one jax.jit)."
    )
    print(conditions() + "\n")
    print(timing_table(rows))
    if mem:
        print("\nPeak memory of one call (fresh subprocess per row):\n")
        print(memory_table(mem))
    if context is not None:
        print(
            f"\nSame timings with XLA_FLAGS={HOIST_FLAG} (every small while loop compiled "
            "into one kernel):\n"
        )
        print(timing_table(context))
    print(f"\n(total {wall:.0f} s)")

    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "conditions": conditions(),
                    "repeats": args.repeats,
                    "pinned_cpu": args.pin_cpu,
                    "timing_basis": "each method in one jax.jit; seconds per call",
                    "timings": rows,
                    "memory": mem,
                    "memory_case": {"n_x": MEM_NX, "T": MEM_T, "model": "tanh-coupled, dense W"},
                    "xla_hoisted_timings": context,
                    "xla_hoisted_flag": HOIST_FLAG if context is not None else None,
                },
                f,
                indent=2,
            )


if __name__ == "__main__":
    main()
