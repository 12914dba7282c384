"""Structured vs dense least squares for many windows, each with its own initial state.

The EMPS plant (`oneshot_jax.examples.emps.open_loop_model`: a mass with viscous and
smoothed Coulomb friction and an offset, n_x = 2, 4 parameters) at Ts = 1 ms, simulated at
the benchmark's IDIM-LS reference parameters under a two-sine force with output noise, and
cut into N windows of 100 samples. Each window has its own x0, so the unknowns are 4 + 2N.
Compared, in one run:

- `structured`: `fit(solver=LevenbergMarquardt(rtol=1e-8), window=100)`: the Schur
  complement eliminates each window's x0 block (cost linear in N);
- `dense`: `fit(solver=Optimistix(optimistix.LevenbergMarquardt(...)), window=100)`: the
  same closed-form Jacobian, but optimistix solves the dense (N T) x (4 + 2N) system by QR.

Times come from `timing.timed`: the first call (compilation included) and the median of
further calls (compilation excluded).

Run: `python benchmarks/windows.py` (`--quick`: N in {10, 50}; `--figure PATH`: save the
plot; `--json PATH`: the numbers; `--dense-max N`: the largest N for the dense solve).
"""

import argparse
import json
import sys

import jax
import numpy as np
import optimistix as optx

jax.config.update("jax_enable_x64", True)

from timing import conditions, fmt_time, timed  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.examples import emps  # noqa: E402

TS = 1e-3
MODEL = emps.open_loop_model(TS)
TRUE = emps.REFERENCE
THETA0 = {"M": 80.0, "Fv": 150.0, "Fc": 10.0, "offset": 0.0}


def make_data(N, T_w, seed=0):
    """A record of N T_w samples at the reference parameters, from rest, with 10 µm noise."""
    t = np.arange(N * T_w) * TS
    force = 300.0 * np.sin(2 * np.pi * 0.7 * t) + 150.0 * np.sin(2 * np.pi * 3.1 * t + 1.0)
    u = force[:, None]
    x0 = np.zeros(2)
    _, z = oj.simulate(MODEL, TRUE, x0, u)
    z = np.asarray(z) + 1e-5 * np.random.default_rng(seed).standard_normal(z.shape)
    return u, z, x0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="N in {10, 50} only")
    parser.add_argument("--figure", default=None, help="save a PNG of time against N")
    parser.add_argument("--json", default=None, help="write the numbers as JSON")
    parser.add_argument(
        "--dense-max", type=int, default=100, help="largest N for the dense solve (it grows fast)"
    )
    args = parser.parse_args()

    Ns = [10, 50] if args.quick else [10, 50, 100, 250]
    T_w = 100
    positive = oj.constraints.box(lower={"M": 1e-6, "Fv": 0.0, "Fc": 0.0})
    rows = []
    for N in Ns:
        u, z, x0 = make_data(N, T_w)
        row = {"N": N, "unknowns": 4 + 2 * N}
        solvers = {"structured": oj.LevenbergMarquardt(rtol=1e-8, max_steps=100)}
        if N <= args.dense_max:
            dense = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-12)
            solvers["dense"] = oj.Optimistix(dense, max_steps=100)
        for label, solver in solvers.items():
            res, first, med = timed(
                lambda s=solver: oj.fit(
                    MODEL, THETA0, x0, u, z, solver=s, window=T_w, constraints=positive
                ),
                repeats=3 if label == "structured" else 1,
            )
            err = max(abs(float(res.theta[k]) / TRUE[k] - 1) for k in TRUE)
            row[label] = {
                "time_s": med,
                "first_call_s": first,
                "loss": float(res.loss),
                "iterations": int(res.num_steps),
                "max_rel_param_err": err,
                "stop": res.status,
            }
        rows.append(row)
        print(f"  N = {N} done", file=sys.stderr, flush=True)  # progress, not the table

    print(f"Windowed fit, n_x = 2, 4 parameters, windows of {T_w} samples.")
    print(conditions())
    print()
    print(
        "| N windows | unknowns | structured LM | steps | dense LM | steps | "
        "dense / structured | loss structured | loss dense | max rel. param. error | "
        "first call structured | first call dense |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        s, d = r["structured"], r.get("dense")
        ratio = f"{d['time_s'] / s['time_s']:.0f}x" if d else "—"
        dense_loss = f"{d['loss']:.6e}" if d else "—"
        print(
            f"| {r['N']} | {r['unknowns']} | {fmt_time(s['time_s'])} | {s['iterations']} | "
            f"{fmt_time(d['time_s']) if d else '—'} | {d['iterations'] if d else '—'} | "
            f"{ratio} | {s['loss']:.6e} | {dense_loss} | {s['max_rel_param_err']:.2e} | "
            f"{fmt_time(s['first_call_s'])} | {fmt_time(d['first_call_s']) if d else '—'} |"
        )
    print()
    print(
        "Times: median of later calls (compilation excluded); first call: compilation "
        "included. Parameter error: max_i |theta_i / theta_i,true - 1| (structured fit)."
    )

    if args.json:
        with open(args.json, "w") as f:
            json.dump({"conditions": conditions(), "rows": rows}, f, indent=2)
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
