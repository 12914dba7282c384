"""Coverage of the Newey-West sandwich on a two-parameter oscillator: where strongly
correlated noise and a short record leave its intervals short at every lag.

The system: a damped oscillator stepped by Euler (dt = 0.1), x = (position, rate),
rate' = -k position - c rate + u (k = 2, c = 0.5, x0 = (1, 0)), the position observed,
T = 400 samples of a piecewise-constant random input (a new level every 5 samples, one
record per draw). Output noise: white, or AR(1) with coefficient 0.8, standard deviation
0.05 either way. Each draw is fitted from k = 2.3, c = 0.4 and x0 = 0 by
Levenberg-Marquardt, once per covariance (same path, same estimate): classical
sigma^2 (J^T J)^+, `covariance="newey_west"` (Newey and West's lag rule) and
`NeweyWest(L)` for each L of `--lags`.

Per covariance and noise: the coverage of the 95 % intervals (estimate +- 1.96 SE holds
the truth) of k, c and x0[0], and the RMS of the reported standard errors of k and c
against the spread of their estimates over the draws. `sandwich_x0.py` is the
one-parameter counterpart (x[k+1] = a x + b u).

Run: `python benchmarks/sandwich_oscillator.py` (`--draws N`, default 1000; `--quick`: 10
draws; `--lags L ...`: the sandwich's lags besides the rule's, default 10 20 40).
"""

import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from hybrid_sandwich import ar1  # noqa: E402
from sandwich_x0 import arguments, monte_carlo_note  # noqa: E402
from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402

DT, T, SIGMA, PHI = 0.1, 400, 0.05, 0.8
TRUTH, START = {"k": 2.0, "c": 0.5}, {"k": 2.3, "c": 0.4}
X0 = np.array([1.0, 0.0])


def step(x, u, th):
    return jnp.stack([x[0] + DT * x[1], x[1] + DT * (-th["k"] * x[0] - th["c"] * x[1] + u[0])])


def position(x, u, th):
    return x[:1]


MODEL = oj.Model(step, position)


def study(draws, phi, covariances):
    """Per covariance, each draw's (k, SE k, c, SE c, x0[0], SE x0[0])."""
    out = {name: [] for name in covariances}
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        u = np.repeat(rng.standard_normal(T // 5 + 1), 5)[:T, None]
        _, z = oj.simulate(MODEL, TRUTH, X0, u)
        # (stationary standard deviation SIGMA whatever phi)
        z = np.asarray(z) + ar1(rng, T, phi, SIGMA * np.sqrt(1 - phi**2))
        for name, cov in covariances.items():
            r = oj.fit(MODEL, START, np.zeros(2), u, z, covariance=cov)
            out[name].append(
                (
                    *(float(v) for k in ("k", "c") for v in (r.theta[k], r.std[k])),
                    float(r.x0[0]),
                    float(r.x0_std[0]),
                )
            )
    return {k: np.asarray(v) for k, v in out.items()}


def main(argv=None):
    args = arguments(__doc__, [10, 20, 40], argv)
    draws = 10 if args.quick else args.draws
    warnings.simplefilter("ignore")
    print(
        f"Standard errors of a damped oscillator (Euler, dt = {DT:g}; k = {TRUTH['k']:g}, "
        f"c = {TRUTH['c']:g}, x0 = (1, 0)), position observed, T = {T}, output noise of "
        f"standard deviation {SIGMA:g}; {draws} draws; Levenberg-Marquardt from "
        f"k = {START['k']:g}, c = {START['c']:g}, x0 = 0."
    )
    print(conditions())
    print(
        f"\n  {'noise':<14}{'covariance':<26}{'k: coverage':>13}{'c: coverage':>13}"
        f"{'x0[0]: coverage':>17}{'k: RMS SE / spread':>20}{'c: RMS SE / spread':>20}"
    )
    rule_lags = int(np.floor(4 * (T / 100) ** (2 / 9)))  # (`covariance="newey_west"`)
    rule = {"classical": "classical", f"Newey-West ({rule_lags}, the rule)": "newey_west"}
    lagged = {f"Newey-West ({L})": oj.NeweyWest(lags=L) for L in args.lags}
    for phi, covariances in ((0.0, {"classical": "classical"}), (PHI, {**rule, **lagged})):
        res = study(draws, phi, covariances)
        noise = "white" if phi == 0 else f"AR(1) {phi:g}"
        for name, r in res.items():
            k, sk, c, sc, x0, sx = r.T
            cover = [
                100 * np.mean(np.abs(v - truth) <= 1.96 * s)
                for v, s, truth in ((k, sk, TRUTH["k"]), (c, sc, TRUTH["c"]), (x0, sx, X0[0]))
            ]
            ratio = [np.sqrt(np.mean(s**2)) / v.std(ddof=1) for v, s in ((k, sk), (c, sc))]
            print(
                f"  {noise:<14}{name:<26}{cover[0]:>12.0f}%{cover[1]:>12.0f}%"
                f"{cover[2]:>16.0f}%{ratio[0]:>20.2f}{ratio[1]:>20.2f}"
            )
    print(monte_carlo_note(draws))
    return 0


if __name__ == "__main__":
    sys.exit(main())
