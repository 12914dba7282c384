"""Coverage of the prediction bands of K-step-ahead predictions (`predict_ahead`'s `std`,
the extended Kalman filter's covariance run K steps on, plus the measurement noise), over
noise draws of records made with process noise.

Two systems, each record with a random initial state, process noise w_k added to the
state at every step and white measurement noise:

- a linear two-state model, x[k+1] = A x[k] + B u[k] + w_k, z = x_0 + v_k (w_k of std 0.05
  per entry, v_k of std 0.02, x0 ~ N(0, I), T = 80), predicted with the true A and the
  true noise covariances and prior (where the extended Kalman filter is the Kalman
  filter: the bands are exact);
- a damped pendulum q'' = -w0sq sin q - b q' + u (w0sq = 9, b = 0.6, RK4 over dt = 0.05),
  w_k of std 0.01 on the rate, its angle measured with noise of std 0.02, x0 ~ N((0.5,
  0), 0.1^2 I), T = 150: theta (and x0) fitted to the record by Levenberg-Marquardt from
  w0sq = 7, b = 0.3 (the output-error fit), then `result.predict_ahead` with the true
  process noise (the measurement noise the fit's, the prior mean its x0 from the record):
  the filter's linearisation and theta's error are not in the band.

Per system and horizon K: the share of the measurements z[k], k >= K + 10 (predicted from
a state filtered over at least 10 samples), that lie within zhat +- 1.96 std, over all
draws, and the RMS std against the RMS prediction error; and the share for the first
K + 10 samples, where the prior on x0 decides the band (the linear model's is the
distribution its x0 were drawn from; the pendulum's is `result.predict_ahead`'s default,
the covariance of the x0 estimated from the record).

Run: `python benchmarks/ahead_coverage.py` (`--draws N`, default 300; `--quick`: 5 draws).
"""

import argparse
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402

HORIZONS = (1, 3, 10, 30)
SKIP = 10  # (the samples filtered before a prediction counts: before, the prior decides)

A = np.array([[0.95, 0.1], [-0.2, 0.9]])
B = np.array([[0.0], [0.1]])
LINEAR = oj.Model(lambda x, u, th: th["A"] @ x + B @ u, lambda x, u, th: x[:1])

TRUTH, DT = {"w0sq": 9.0, "b": 0.6}, 0.05


def rhs(x, u, th):
    return jnp.stack([x[1], -th["w0sq"] * jnp.sin(x[0]) - th["b"] * x[1] + u[0]])


PENDULUM = oj.Model.from_ode(rhs, DT, observe=lambda x, u, th: x[:1])
PENDULUM_NOISE = 0.02  # (the std of its measurement noise)
FITTED_SIGMA = []  # (the fits' sigma, the measurement noise their predictions take)


def linear_draw(rng):
    T, w, v = 80, 0.05, 0.02
    u = rng.standard_normal((T, 1))
    x, zs = rng.standard_normal(2), []
    for k in range(T):
        zs.append(x[:1] + v * rng.standard_normal(1))
        x = A @ x + B @ u[k] + w * rng.standard_normal(2)
    z = np.array(zs)
    preds = [
        oj.predict_ahead(
            LINEAR,
            {"A": A},
            u,
            z,
            K,
            x0=np.zeros(2),
            process_noise=w**2,
            measurement_noise=v**2,
            prior_covariance=1.0,
        )  # fmt: skip
        for K in HORIZONS
    ]
    return z, preds


def pendulum_draw(rng):
    T, w, v = 150, 0.01, PENDULUM_NOISE
    u = 0.8 * np.sin(0.4 * np.arange(T) + rng.uniform(0, 6))[:, None]
    x = np.array([0.5, 0.0]) + 0.1 * rng.standard_normal(2)
    step = jax.jit(lambda x, u: PENDULUM.step(x, u, TRUTH))
    zs = []
    for k in range(T):
        zs.append(x[:1] + v * rng.standard_normal(1))
        x = np.asarray(step(x, u[k])) + np.array([0.0, w * rng.standard_normal()])
    z = np.array(zs)
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, np.array([0.5, 0.0]), u, z)
    e = np.asarray(result.residuals)  # (sigma^2 = SSE / (T - 4): 2 parameters, 2 of x0)
    FITTED_SIGMA.append(float(np.sqrt(np.sum(e**2) / (e.size - 4))))
    noise = np.diag([1e-12, w**2])  # (the angle's: nearly none, a positive covariance)
    return z, [result.predict_ahead(u, z, K, process_noise=noise) for K in HORIZONS]


def study(draw, draws):
    """Per horizon K: the errors z - zhat and the stds of the samples from K + SKIP on,
    and the share of the first K + SKIP samples' errors within 1.96 std."""
    e, s = {K: [] for K in HORIZONS}, {K: [] for K in HORIZONS}
    early = {K: [] for K in HORIZONS}
    for seed in range(draws):
        z, preds = draw(np.random.default_rng(seed))
        for K, p in zip(HORIZONS, preds, strict=True):
            e[K].append((z - p.z)[K + SKIP :, 0])
            s[K].append(p.std[K + SKIP :, 0])
            first = slice(0, K + SKIP)
            early[K].append(np.abs(z - p.z)[first, 0] <= 1.96 * p.std[first, 0])
    return {K: (e[K], s[K], np.mean(np.concatenate(early[K]))) for K in HORIZONS}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=300, help="noise draws (default 300)")
    parser.add_argument("--quick", action="store_true", help="5 draws")
    args = parser.parse_args(argv)
    draws = 5 if args.quick else args.draws
    warnings.simplefilter("ignore")
    print(
        "Prediction bands of K-step-ahead predictions (predict_ahead's std): a linear "
        "two-state model with the true parameters and noise (T = 80), and a pendulum "
        f"with process noise fitted by Levenberg-Marquardt (T = 150); {draws} draws each; "
        f"the measurements from sample K + {SKIP} on."
    )
    print(conditions())
    print(
        f"\n  {'system':<34}{'K':>4}{'coverage':>10}{'(s.e.)':>8}{'RMS std / RMS error':>22}"
        f"{'first K + ' + str(SKIP):>16}"
    )
    for name, draw in (
        ("linear model, true parameters", linear_draw),
        ("pendulum, fitted theta", pendulum_draw),
    ):
        for K, (es, ss, early) in study(draw, draws).items():
            shares = [np.mean(np.abs(e) <= 1.96 * s) for e, s in zip(es, ss, strict=True)]
            e, s = np.concatenate(es), np.concatenate(ss)
            inside = np.mean(np.abs(e) <= 1.96 * s)
            se = np.std(shares) / np.sqrt(draws)  # (over the draws: samples of a record
            ratio = np.sqrt(np.mean(s**2)) / np.sqrt(np.mean(e**2))  # are correlated)
            print(
                f"  {name:<34}{K:>4}{100 * inside:>9.1f}%{100 * se:>7.1f}%{ratio:>22.2f}"
                f"{100 * early:>15.1f}%"
            )
    print(
        f"\nThe pendulum fits' sigma (the measurement noise of their predictions): median "
        f"{np.median(FITTED_SIGMA):.4f}, against the {PENDULUM_NOISE} the records were made "
        "with."
    )
    print(
        "\n(s.e.): the standard error of the coverage, from the spread of the draws' own "
        "coverages (the samples of one record are correlated)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
