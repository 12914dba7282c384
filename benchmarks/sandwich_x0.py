"""Coverage of the standard errors of a parameter and of the initial state: the classical
sigma^2 (J^T J)^+ against the Newey-West sandwich (`fit(covariance=NeweyWest(lags))`),
over noise draws, with white and with correlated output noise.

The system: x[k+1] = a x[k] + b u[k] (a = 0.8, b = 0.5, x0 = 1), T = 200 samples, one
input record per draw, observed with AR(1) noise of innovation std 0.1 (coefficient 0:
white). Each draw is fitted from a = 0.7, b = 0.4 by Levenberg-Marquardt, once per
covariance (same path, same estimate); x0 is estimated with theta.

Per covariance and noise: the coverage of the 95 % intervals (estimate +- 1.96 SE holds
the truth) of a and of x0, and the RMS of x0's reported standard error against the spread
of its estimates. x0 is determined by the few samples at the head of the record: the
sandwich takes its own part from the residuals' autocovariance pooled over the record
(`oneshot_jax._covariance.sandwich`).

Run: `python benchmarks/sandwich_x0.py` (`--draws N`, default 200; `--quick`: 10 draws).
"""

import argparse
import sys
import warnings

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from hybrid_sandwich import ar1  # noqa: E402
from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402

TRUTH, X0, T, SIGMA = {"a": 0.8, "b": 0.5}, 1.0, 200, 0.1
CASES = ((0.0, 3), (0.8, 20))  # (AR(1) coefficient, the sandwich's lags)


def step(x, u, th):
    return th["a"] * x + th["b"] * u


def study(draws, phi, lags):
    model = oj.Model(step)
    out = {"classical": [], "sandwich": [], "x0": []}
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        u = rng.standard_normal((T, 1))
        _, x = oj.simulate(model, TRUTH, np.array([X0]), u)
        z = np.asarray(x) + ar1(rng, T, phi, SIGMA)
        for name, cov in (("classical", "classical"), ("sandwich", oj.NeweyWest(lags=lags))):
            r = oj.fit(model, {"a": 0.7, "b": 0.4}, np.array([X0]), u, z, covariance=cov)
            out[name].append(
                (float(r.theta["a"]), float(r.std["a"]), float(r.x0[0]), float(r.x0_std[0]))
            )
        out["x0"].append(float(r.x0[0]))
    return {k: np.asarray(v) for k, v in out.items()}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=200, help="noise draws (default 200)")
    parser.add_argument("--quick", action="store_true", help="10 draws")
    args = parser.parse_args(argv)
    draws = 10 if args.quick else args.draws
    warnings.simplefilter("ignore")
    print(
        f"Standard errors of a and x0: x[k+1] = a x + b u, a = {TRUTH['a']:g}, "
        f"b = {TRUTH['b']:g}, x0 = {X0:g}, T = {T}, AR(1) output noise of innovation std "
        f"{SIGMA:g}; {draws} draws; Levenberg-Marquardt from a = 0.7, b = 0.4."
    )
    print(conditions())
    print(
        f"\n  {'noise':<14}{'covariance':<22}{'a: coverage':>12}{'x0: coverage':>14}"
        f"{'x0: RMS SE / spread':>21}"
    )
    for phi, lags in CASES:
        res = study(draws, phi, lags)
        spread = res["x0"].std(ddof=1)
        noise = "white" if phi == 0 else f"AR(1) {phi:g}"
        for name, label in (("classical", "classical"), ("sandwich", f"Newey-West ({lags})")):
            a, sa, x0, sx = res[name].T
            cover_a = 100 * np.mean(np.abs(a - TRUTH["a"]) <= 1.96 * sa)
            cover_x = 100 * np.mean(np.abs(x0 - X0) <= 1.96 * sx)
            ratio = np.sqrt(np.mean(sx**2)) / spread
            print(f"  {noise:<14}{label:<22}{cover_a:>11.0f}%{cover_x:>13.0f}%{ratio:>21.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
