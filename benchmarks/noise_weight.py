"""Standard errors and coverage of a fit whose outputs have unequal noise: the default
weight (Q = I) against `weight="noise"` (Q estimated with theta) and the true weight.

A damped oscillator x'' = -k x - c x' + u (RK4, dt = 0.05, T = 400 by default) observed in
both states, the position with noise 0.01 and the velocity with noise 0.3 (one input
record; each draw new noise). Each draw is fitted by Levenberg-Marquardt from k, c = 3.5,
0.4 (truth 4, 0.5), x0 estimated, three times:

- `identity`: `weight=None`, one noise level pooled over both outputs;
- `noise`: `weight="noise"`, fits alternating with Q the inverse residual covariance;
- `true`: `weight=1 / sigma^2`, the noise variances known.

Per parameter: the spread of the estimates over the draws (empirical SE), the mean
reported SE (`result.std`), and the coverage of the 95 % intervals (`result.ci95`; a fit
that does not report success counts as a miss); for `noise`, the number of fits it took.

Run: `python benchmarks/noise_weight.py` (`--draws N`, default 200; `--T`; `--quick`: 20
draws).
"""

import argparse
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402

SIGMA = np.array([0.01, 0.3])
TRUE = {"k": 4.0, "c": 0.5}
START = {"k": 3.5, "c": 0.4}
NAMES = ("k", "c")
WEIGHTS = {
    "identity": ("weight=None (Q = I)", None),
    "noise": ('weight="noise" (Q estimated)', "noise"),
    "true": ("weight=1/sigma^2 (Q known)", 1 / SIGMA**2),
}


def _rhs(x, u, p):
    return jnp.stack([x[1], -p["k"] * x[0] - p["c"] * x[1] + u[0]])


MODEL = oj.Model.from_ode(_rhs, 0.05, observe=lambda x, u, p: x)


def study(draws, T, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((T, 1))
    _, clean = oj.simulate(MODEL, TRUE, np.array([1.0, 0.0]), u)
    clean = np.asarray(clean)
    out = {w: {"theta": [], "std": [], "hit": [], "fits": [], "time": 0.0} for w in WEIGHTS}
    for _ in range(draws):
        z = clean + SIGMA * rng.standard_normal(clean.shape)
        for name, (_, weight) in WEIGHTS.items():
            rec = out[name]
            tic = time.perf_counter()
            with warnings.catch_warnings():  # (Q = I: the warning of unequal noise, each draw)
                warnings.simplefilter("ignore", UserWarning)
                r = oj.fit(MODEL, START, np.zeros(2), u, z, weight=weight)
            rec["time"] += time.perf_counter() - tic
            lo, hi = r.ci95
            rec["theta"].append([float(r.theta[n]) for n in NAMES])
            rec["std"].append([float(r.std[n]) for n in NAMES])
            rec["hit"].append(
                [r.success and float(lo[n]) <= TRUE[n] <= float(hi[n]) for n in NAMES]
            )
            rec["fits"].append(r.stop_info.get("noise_weight_rounds", 1))
    return {w: {k: np.asarray(v) for k, v in rec.items()} for w, rec in out.items()}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=200, help="noise draws (default 200)")
    parser.add_argument("--T", type=int, default=400, help="samples per record (default 400)")
    parser.add_argument("--quick", action="store_true", help="20 draws")
    args = parser.parse_args(argv)
    draws = 20 if args.quick else args.draws
    print(
        f"Unequal output noise: damped oscillator (truth k = 4, c = 0.5), both states "
        f"measured with noise {SIGMA[0]:g} and {SIGMA[1]:g}, T = {args.T}, {draws} draws; "
        "Levenberg-Marquardt from k, c = 3.5, 0.4, x0 estimated."
    )
    print(conditions())
    print(
        "\n| weight | parameter | empirical SE | mean reported SE | reported / empirical "
        "| coverage of the 95 % intervals | fits per draw (mean, max) | time (s) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    results = study(draws, args.T)
    for name, (title, _) in WEIGHTS.items():
        rec = results[name]
        for j, p in enumerate(NAMES):
            emp = rec["theta"][:, j].std(ddof=1)
            rep = rec["std"][:, j].mean()
            fits = f"{rec['fits'].mean():.2f}, {rec['fits'].max()}" if j == 0 else ""
            spent = f"{rec['time']:.1f}" if j == 0 else ""
            print(
                f"| {title if j == 0 else ''} | {p} | {emp:.3g} | {rep:.3g} | {rep / emp:.2f} "
                f"| {100 * rec['hit'][:, j].mean():.1f} % | {fits} | {spent} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
