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

Run: `python benchmarks/sandwich_x0.py` (`--draws N`, default 1000; `--quick`: 10 draws;
`--lags L ...`: the sandwich's lags under the AR(1) noise, default 20).
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
WHITE_LAGS, PHI = 3, 0.8  # the sandwich's lags under white noise; the AR(1) coefficient


def step(x, u, th):
    return th["a"] * x + th["b"] * u


def study(draws, phi, lags):
    """Per covariance ("classical", and "L" for each of `lags`), each draw's (a, SE of a,
    x0, SE of x0)."""
    model = oj.Model(step)
    covs = {"classical": "classical", **{str(L): oj.NeweyWest(lags=L) for L in lags}}
    out = {name: [] for name in covs}
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        u = rng.standard_normal((T, 1))
        _, x = oj.simulate(model, TRUTH, np.array([X0]), u)
        z = np.asarray(x) + ar1(rng, T, phi, SIGMA)
        for name, cov in covs.items():
            r = oj.fit(model, {"a": 0.7, "b": 0.4}, np.array([X0]), u, z, covariance=cov)
            out[name].append(
                (float(r.theta["a"]), float(r.std["a"]), float(r.x0[0]), float(r.x0_std[0]))
            )
    return {k: np.asarray(v) for k, v in out.items()}


def arguments(doc, lags, argv):
    """The command line of a sandwich study: `--draws`, `--quick` (10 draws), `--lags`."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=1000, help="noise draws (default 1000)")
    parser.add_argument("--quick", action="store_true", help="10 draws")
    parser.add_argument("--lags", type=int, nargs="+", default=lags, help="the sandwich's lags")
    return parser.parse_args(argv)


def main(argv=None):
    args = arguments(__doc__, [20], argv)
    draws = 10 if args.quick else args.draws
    warnings.simplefilter("ignore")
    print(
        f"Standard errors of a and x0: x[k+1] = a x + b u, a = {TRUTH['a']:g}, "
        f"b = {TRUTH['b']:g}, x0 = {X0:g}, T = {T}, AR(1) output noise of innovation std "
        f"{SIGMA:g}; {draws} draws; Levenberg-Marquardt from a = 0.7, b = 0.4."
    )
    print(conditions())
    print(
        f"\n  {'noise':<14}{'covariance':<22}{'a: coverage':>12}{'a: RMS SE / spread':>20}"
        f"{'x0: coverage':>14}{'x0: RMS SE / spread':>21}"
    )
    for phi, lags in ((0.0, [WHITE_LAGS]), (PHI, args.lags)):
        res = study(draws, phi, lags)
        noise = "white" if phi == 0 else f"AR(1) {phi:g}"
        for name, r in res.items():
            a, sa, x0, sx = r.T
            cover_a = 100 * np.mean(np.abs(a - TRUTH["a"]) <= 1.96 * sa)
            cover_x = 100 * np.mean(np.abs(x0 - X0) <= 1.96 * sx)
            ratio_a = np.sqrt(np.mean(sa**2)) / a.std(ddof=1)
            ratio_x = np.sqrt(np.mean(sx**2)) / x0.std(ddof=1)
            label = name if name == "classical" else f"Newey-West ({name})"
            print(
                f"  {noise:<14}{label:<22}{cover_a:>11.0f}%{ratio_a:>20.2f}"
                f"{cover_x:>13.0f}%{ratio_x:>21.2f}"
            )
    print(monte_carlo_note(draws))
    return 0


def monte_carlo_note(draws):
    """A line on the Monte Carlo standard error of a coverage over `draws` draws."""
    se90, se95 = (100 * np.sqrt(p * (1 - p) / draws) for p in (0.9, 0.95))
    return (
        f"\nA coverage near 90 % over {draws} draws has a Monte Carlo standard error of "
        f"{se90:.1f} points (near 95 %: {se95:.1f})."
    )


if __name__ == "__main__":
    sys.exit(main())
