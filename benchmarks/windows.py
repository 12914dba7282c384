"""Structured vs dense least squares for many windows, each with its own initial state.

A mass with viscous and (smoothed) Coulomb friction and an offset, n_x = 2, 4 parameters
(the EMPS structure), simulated with noise and cut into N windows of 100 samples. Each
window has its own x0, so the unknowns are 4 + 2N. Compared, in one run:

- `structured`: `fit(solver="levenberg_marquardt", window=100)`: the Schur complement
  eliminates each window's x0 block (cost linear in N);
- `dense`: `fit(solver=optimistix.LevenbergMarquardt(...), window=100)`: the same
  closed-form Jacobian, but optimistix solves the dense (N T) x (4 + 2N) system by QR.

Run: `python benchmarks/windows.py` (add `--quick` for N <= 50, `--figure PATH` to save
the plot, `--json PATH` for the numbers). Times are medians of repeated solves after a
warm-up call (compilation excluded; the compile time is its own column).
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

jax.config.update("jax_enable_x64", True)

import oneshot_jax as oj  # noqa: E402

TRUE = {"M": 95.0, "Fv": 200.0, "Fc": 20.0, "offset": -3.0}


def rhs(x, u, theta):
    q, v = x
    friction = theta["Fv"] * v + theta["Fc"] * jnp.tanh(v / 1e-3) + theta["offset"]
    return jnp.stack([v, (u[0] - friction) / theta["M"]])


MODEL = oj.Model.from_ode(rhs, 1e-3, observe=lambda x, u, th: x[:1])


def make_data(N, T_w, seed=0):
    key = jax.random.PRNGKey(seed)
    t = np.arange(N * T_w) * 1e-3
    force = 300.0 * np.sin(2 * np.pi * 0.7 * t) + 150.0 * np.sin(2 * np.pi * 3.1 * t + 1.0)
    u = jnp.asarray(force)[:, None]
    x0 = jnp.array([0.0, 0.0])
    theta = {k: jnp.asarray(v) for k, v in TRUE.items()}
    _, z = oj.simulate(MODEL, theta, x0, u)
    z = z + 1e-5 * jax.random.normal(key, z.shape)
    return u, z, x0


def timed(fn, repeats):
    t0 = time.perf_counter()
    res = fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t0)
    return res, first, float(np.median(times))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N in {10, 50} only")
    parser.add_argument("--figure", default=None, help="save a PNG of time against N")
    parser.add_argument("--json", default=None, help="write the numbers as JSON")
    parser.add_argument(
        "--dense-max", type=int, default=100, help="largest N for the dense solve (it grows fast)"
    )
    args = parser.parse_args()

    Ns = [10, 50] if args.quick else [10, 50, 100, 250]
    T_w = 100
    theta0 = {"M": 80.0, "Fv": 150.0, "Fc": 10.0, "offset": 0.0}
    # x0 of each window is free (q from z, v by simulation from the initial guess).
    positive = oj.constraints.box(lower={"M": 1e-6, "Fv": 0.0, "Fc": 0.0})
    common = dict(window=T_w, constraints=positive, rtol=1e-8, max_epochs=100)
    rows = []
    for N in Ns:
        u, z, x0 = make_data(N, T_w)
        row = {"N": N, "unknowns": 4 + 2 * N}
        solvers = {"structured": "levenberg_marquardt"}
        if N <= args.dense_max:
            solvers["dense"] = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-12)
        for label, solver in solvers.items():
            repeats = 3 if label == "structured" else 1
            res, first, med = timed(
                lambda s=solver: oj.fit(MODEL, u, z, theta0, x0, solver=s, **common), repeats
            )
            err = max(abs(float(res.theta[k]) / TRUE[k] - 1) for k in TRUE)
            row[label] = {
                "time_s": med,
                "first_call_s": first,
                "loss": res.loss,
                "iterations": res.epochs,
                "max_rel_param_err": err,
                "stop": res.stop_reason.name,
            }
        rows.append(row)

    print(
        f"Windowed fit, n_x = 2, 4 parameters, windows of {T_w} samples, float64, CPU "
        f"({jax.devices()[0].device_kind}, {jax.device_count()} device)"
    )
    print()
    print(
        "| N windows | unknowns | structured LM (s) | iters | dense LM (s) | iters | "
        "dense / structured | loss structured | loss dense | max rel. param. error |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        s = r["structured"]
        d = r.get("dense")
        dense_t = f"{d['time_s']:.3g}" if d else "-"
        dense_i = f"{d['iterations']}" if d else "-"
        ratio = f"{d['time_s'] / s['time_s']:.0f}x" if d else "-"
        dense_l = f"{d['loss']:.6e}" if d else "-"
        print(
            f"| {r['N']} | {r['unknowns']} | {s['time_s']:.3g} | {s['iterations']} | {dense_t} | "
            f"{dense_i} | {ratio} | {s['loss']:.6e} | {dense_l} | {s['max_rel_param_err']:.2e} |"
        )
    print()
    print(
        "Times are medians after a warm-up call; first-call (compile + solve) times: "
        + ", ".join(
            f"N={r['N']}: {r['structured']['first_call_s']:.2f} s structured"
            + (f", {r['dense']['first_call_s']:.2f} s dense" if "dense" in r else "")
            for r in rows
        )
    )

    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 3.8))
        ax.loglog(
            [r["N"] for r in rows],
            [r["structured"]["time_s"] for r in rows],
            "o-",
            label="structured LM (Schur complement)",
        )
        dense = [r for r in rows if "dense" in r]
        ax.loglog(
            [r["N"] for r in dense],
            [r["dense"]["time_s"] for r in dense],
            "s--",
            label="dense LM (optimistix, QR)",
        )
        ax.set_xlabel("number of windows N (100 samples each)")
        ax.set_ylabel("time to solution (s)")
        ax.set_title("Windowed fit: n_x = 2, 4 parameters + 2N initial states")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.figure, dpi=120)


if __name__ == "__main__":
    main()
