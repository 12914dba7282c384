"""Cost of training a hybrid model (physics plus an MLP residual) as n_theta grows.

The model is the Duffing hybrid of `experiments/duffing_hybrid.py` (RK4, dt = 0.05 s, one
trajectory of T samples, 40 dB output noise) with a restoring force `residual.MLP(2, 1,
widths)` on the state in theta; the widths set n_theta. Three tables:

1. **Gradient.** Seconds per call of the compiled `oneshot_jax.loss` (one simulation) and
   `oneshot_jax.value_and_grad` (strategy "auto": for n_theta > 8 its theta term is one
   reverse-mode VJP after the scan), and their ratio. A ratio that does not grow with
   n_theta means the gradient costs a fixed number of model evaluations, whatever the
   number of parameters.
2. **One least-squares iteration.** Seconds of one linearisation plus one damped
   normal-equation solve of `LevenbergMarquardt`, dense (the Jacobian formed, one
   forward-sensitivity column per parameter, a p x p solve) and matrix-free (`"cg"`:
   conjugate gradients on J v and J^T w, at most `cg_max_steps` iterations), with the
   dense Jacobian's size in memory.
3. **Fits.** `LevenbergMarquardt(max_steps=K)` with `linear_solver="dense"` and `"cg"` from
   the same start (the physical fit, then 200 Adam steps): final loss and wall time
   (compilation excluded: each configuration is run twice and the second run timed).
4. **The sensitivities' strategy** (only with `--tables 4`). Seconds per dense residual
   Jacobian (the forward sensitivities of one least-squares iteration) with the
   "jacobian" strategy (per-step Jacobians formed after the forward pass) and the "vjp"
   one (column tangents pushed through the scan), for one-layer residuals of growing
   width, and the strategy "auto" takes for that size (`Auto.resolve`).

Every time is the median of `--repeats` calls after a warm-up call (compilation
excluded), blocked with `block_until_ready`. Run:

    python benchmarks/hybrid.py                 # all three tables
    python benchmarks/hybrid.py --quick         # small sizes only
    python benchmarks/hybrid.py --tables 4      # the sensitivities' strategy
"""

import argparse
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from timing import interleaved  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from experiments import duffing_hybrid as duffing  # noqa: E402
from oneshot_jax.internal import FitProblem, check_cost, check_data  # noqa: E402
from oneshot_jax.residual import MLP, count_parameters  # noqa: E402

WIDTHS = ((4,), (16, 16), (32, 32), (64, 64), (128, 128))
QUICK_WIDTHS = ((4,), (16, 16))
STRATEGY_WIDTHS = ((1,), (3,), (6,), (12,), (24,), (48,))


def median_time(fn, repeats):
    jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def theta_for(widths, key=0):
    """Physical start plus a (perturbed, so that every layer matters) MLP residual."""
    net = MLP(2, 1, widths, key=jax.random.PRNGKey(key), zero_last=False, scale=0.05)
    return {**duffing.PHYSICAL_START, "r": net}


def gradient_table(u, z, x0, widths, repeats):
    rows = []
    for w in widths:
        theta = theta_for(w)
        model = duffing.MODEL
        loss = eqx.filter_jit(lambda th: oj.loss(model, th, x0, u, z))
        vg = eqx.filter_jit(lambda th: oj.value_and_grad(model, th, x0, u, z))
        t_loss = median_time(lambda: loss(theta), repeats)
        t_grad = median_time(lambda: vg(theta), repeats)
        rows.append((count_parameters(theta), t_loss, t_grad, t_grad / t_loss))
    print(f"\n1. gradient cost (T = {u.shape[0]})")
    print(f"  {'n_theta':>8} {'loss [ms]':>10} {'value_and_grad [ms]':>20} {'ratio':>7}")
    for n, a, b, r in rows:
        print(f"  {n:>8d} {1e3 * a:>10.2f} {1e3 * b:>20.2f} {r:>7.2f}")


def lsq_problem(theta, x0, u, z):
    """The `FitProblem` that `fit` builds for one trajectory (every entry free)."""
    data = check_data(duffing.MODEL, theta, x0, u, z)
    flat, unravel = jax.flatten_util.ravel_pytree(data.theta)
    return FitProblem(
        model=data.model,
        cost=check_cost(data, None, 1.0),
        u=np.asarray(data.u)[None],
        z=np.asarray(data.z)[None],
        theta_base=flat,
        theta_free=tuple(range(flat.size)),
        unravel=unravel,
        x0_base=np.asarray(data.x0)[None],
        x0_free=(0, 1),
        project=None,
        lower=None,
        upper=None,
    )


def iteration_table(u, z, x0, widths, repeats, dense_max):
    print(f"\n2. one Levenberg-Marquardt iteration (linearise + solve), T = {u.shape[0]}")
    print(
        f"  {'n_theta':>8} {'dense [s]':>10} {'cg [s]':>8} {'dense/cg':>9} "
        f"{'Jacobian [MiB]':>15} {'J^T J [MiB]':>12}"
    )
    for w in widths:
        theta = theta_for(w)
        problem = lsq_problem(theta, x0, u, z)
        params = problem.split(problem.theta_base, problem.x0_base)
        p = params.theta.shape[0]
        times = {}
        for ls in ("dense", "cg"):
            if ls == "dense" and p > dense_max:
                times[ls] = float("nan")
                continue
            solver = oj.LevenbergMarquardt(linear_solver=ls)

            @eqx.filter_jit
            def iteration(problem, params, solver=solver):
                blocks, _ = solver._linearise(problem, params)
                active = np.zeros(params.theta.shape, bool)
                return solver._solve(problem, params, blocks, 1e-3, active)

            times[ls] = median_time(lambda: iteration(problem, params), repeats)
        R = u.shape[0]
        print(
            f"  {p:>8d} {times['dense']:>10.3f} {times['cg']:>8.3f} "
            f"{times['dense'] / times['cg']:>9.1f} {R * p * 8 / 2**20:>15.1f} "
            f"{p * p * 8 / 2**20:>12.1f}"
        )


def strategy_table(u, z, x0, widths, repeats):
    print(f"\n4. the sensitivities' strategy: one dense residual Jacobian, T = {u.shape[0]}")
    print(
        f"  {'n_theta':>8} {'columns':>8} {'jacobian [ms]':>14} {'vjp [ms]':>9} "
        f"{'jacobian/vjp':>13} {'auto takes':>11}"
    )
    for w in widths:
        problem = lsq_problem(theta_for(w), x0, u, z)
        params = problem.split(problem.theta_base, problem.x0_base)
        p, n_x = params.theta.shape[0], problem.x0_base.shape[-1]
        cols = p + params.x0.shape[-1]
        calls = {}
        for name in ("jacobian", "vjp"):
            jac = eqx.filter_jit(lambda problem, params, name=name: problem.jacobian(params, name))
            calls[name] = lambda jac=jac: jac(problem, params).Jt
        t = interleaved(calls, repeats=repeats)
        auto = oj.Auto().resolve(n_x, u.shape[0], 8, 1, cols).name
        print(
            f"  {p:>8d} {cols:>8d} {1e3 * t['jacobian']:>14.2f} {1e3 * t['vjp']:>9.2f} "
            f"{t['jacobian'] / t['vjp']:>13.2f} {auto:>11}"
        )


def fit_table(u, z, x0, widths, steps):
    print(f"\n3. LevenbergMarquardt(max_steps={steps}) from the same start, T = {u.shape[0]}")
    print(f"  {'n_theta':>8} {'solver':>7} {'start loss':>11} {'final loss':>11} {'wall [s]':>9}")
    for w in widths:
        theta0 = {**duffing.PHYSICAL_START, "r": MLP(2, 1, w, key=jax.random.PRNGKey(0))}
        phys = oj.fit(duffing.MODEL, theta0, x0, u, z, fixed={"c": False, "k": False, "r": True})
        start = oj.fit(
            duffing.MODEL, phys.theta, phys.x0, u, z, solver=oj.Adam(1e-2, 1e-3, max_steps=200)
        )
        for ls in ("dense", "cg"):
            solver = oj.LevenbergMarquardt(linear_solver=ls, max_steps=steps)
            for _ in range(2):  # the second run is timed without compilation
                res = oj.fit(duffing.MODEL, start.theta, start.x0, u, z, solver=solver)
            print(
                f"  {count_parameters(theta0):>8d} {ls:>7} {float(start.loss):>11.4g} "
                f"{float(res.loss):>11.4g} {res.wall_time:>9.2f}"
            )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes only")
    parser.add_argument("--T", type=int, default=2000, help="samples (default 2000)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20, help="LM steps in table 3")
    parser.add_argument(
        "--dense-max", type=int, default=5000, help="largest n_theta for the dense solve"
    )
    parser.add_argument(
        "--tables", default="123", help="which tables to print (e.g. 12; 4 only when named)"
    )
    args = parser.parse_args()
    widths = QUICK_WIDTHS if args.quick else WIDTHS
    u, z, x0, _ = duffing.make_data(0, args.T)
    print(f"{jax.devices()[0].platform}, jax {jax.__version__}, float64")
    if "1" in args.tables:
        gradient_table(u, z, x0, widths, args.repeats)
    if "2" in args.tables:
        iteration_table(u, z, x0, widths[:4], args.repeats, args.dense_max)
    if "3" in args.tables:
        fit_table(u, z, x0, widths[:3], args.steps)
    if "4" in args.tables:
        strategy_table(u, z, x0, STRATEGY_WIDTHS, args.repeats)


if __name__ == "__main__":
    main()
