"""Coverage of the confidence bands of a fitted model's outputs (`FitResult.output_std`,
the estimate's covariance carried to the simulated outputs to first order), over noise
draws.

The system: a damped pendulum q'' = -w0sq sin q - b q' + u (w0sq = 9, b = 0.6, RK4 over
dt = 0.05), its angle measured with white noise of std 0.05. Each draw fits theta and x0
(the truth x0 = (0.6, -0.4)) to a training record of T = 100 samples by Levenberg-Marquardt
from w0sq = 7, b = 0.3, x0 = (0.5, 0), and scores three bands against the noise-free
output:

- the fitted record, x0 from all of it (`output_std(u, z_head=z)`: the joint covariance
  of theta and x0);
- a new record of T = 100 samples (x0 = (-0.3, 0.5), another input), x0 estimated from
  its first 10 noisy outputs (`output_std(u2, z_head=z2[:10])`: theta's covariance
  through the prediction and through that estimate, and the head's noise);
- the same new record from its true x0 (`output_std(u2, x0=...)`: theta's alone).

Per band: the coverage of the 95 % intervals (zhat +- 1.96 std holds the noise-free
output) over all samples and draws, its lowest and highest over the samples (each over
the draws), and the RMS reported std against the spread of zhat's error, per sample
(median, lowest, highest over the samples). The known x0's band leaves out the first
sample, z_0 = g(x0), which has neither error nor std.

Run: `python benchmarks/output_std.py` (`--draws N`, default 1000; `--quick`: 10 draws).
"""

import argparse
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from sandwich_x0 import monte_carlo_note  # noqa: E402
from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402

TRUTH, DT, T, SIGMA, HEAD = {"w0sq": 9.0, "b": 0.6}, 0.05, 100, 0.05, 10
X0, X0_NEW = np.array([0.6, -0.4]), np.array([-0.3, 0.5])


def rhs(x, u, th):
    return jnp.stack([x[1], -th["w0sq"] * jnp.sin(x[0]) - th["b"] * x[1] + u[0]])


def angle(x, u, th):
    del u, th
    return x[:1]


MODEL = oj.Model.from_ode(rhs, DT, observe=angle)


def inputs(phase):
    return 0.8 * np.sin(0.4 * np.arange(T) + phase)[:, None]


def study(draws):
    """Per band, the errors zhat - z_true (draws, T) and the reported std (draws, T)."""
    u, u2 = inputs(0.0), inputs(2.0)
    z_true = np.asarray(oj.simulate(MODEL, TRUTH, X0, u)[1])[:, 0]
    z2_true = np.asarray(oj.simulate(MODEL, TRUTH, X0_NEW, u2)[1])[:, 0]
    out = {"fitted": ([], []), "head": ([], []), "known": ([], [])}
    for seed in range(draws):
        rng = np.random.default_rng(seed)
        z = (z_true + SIGMA * rng.standard_normal(T))[:, None]
        head = (z2_true[:HEAD] + SIGMA * rng.standard_normal(HEAD))[:, None]
        r = oj.fit(MODEL, {"w0sq": 7.0, "b": 0.3}, np.array([0.5, 0.0]), u, z)
        zhat = np.asarray(r.simulate(u)[1])[:, 0]
        bands = {
            "fitted": (zhat - z_true, r.output_std(u, z_head=z)[:, 0]),
            "head": (r.predict(u2, head).z[:, 0] - z2_true, r.output_std(u2, z_head=head)[:, 0]),
            "known": (
                np.asarray(r.simulate(u2, X0_NEW)[1])[:, 0] - z2_true,
                r.output_std(u2, x0=X0_NEW)[:, 0],
            ),
        }
        for name, (e, s) in bands.items():
            out[name][0].append(e)
            out[name][1].append(s)
    return {k: (np.asarray(e), np.asarray(s)) for k, (e, s) in out.items()}


LABELS = {
    "fitted": "fitted record, x0 from all of it",
    "head": f"new record, x0 from {HEAD} samples",
    "known": "new record, x0 known",
}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=1000, help="noise draws (default 1000)")
    parser.add_argument("--quick", action="store_true", help="10 draws")
    args = parser.parse_args(argv)
    draws = 10 if args.quick else args.draws
    warnings.simplefilter("ignore")
    print(
        f"Confidence bands of the outputs (FitResult.output_std): a pendulum, w0sq = "
        f"{TRUTH['w0sq']:g}, b = {TRUTH['b']:g}, angle measured with noise std {SIGMA:g}, "
        f"T = {T}; {draws} draws; Levenberg-Marquardt from w0sq = 7, b = 0.3."
    )
    print(conditions())
    print(
        f"\n  {'band':<36}{'coverage':>9}{'per sample':>14}{'RMS std / spread (median, range)':>36}"
    )
    for name, (e, s) in study(draws).items():
        if name == "known":  # (the first sample, z_0 = g(x0), has no error and no std)
            e, s = e[:, 1:], s[:, 1:]
        inside = np.abs(e) <= 1.96 * s
        per_sample = 100 * inside.mean(axis=0)
        spread = np.sqrt(np.mean(e**2, axis=0))  # (about the truth: zhat's bias counts)
        rms = np.sqrt(np.mean(s**2, axis=0))
        keep = (spread > 0) & (rms > 0)
        ratio = rms[keep] / spread[keep]
        print(
            f"  {LABELS[name]:<36}{100 * inside.mean():>8.1f}%"
            f"{f'{per_sample.min():.0f}-{per_sample.max():.0f}%':>14}"
            f"{f'{np.median(ratio):.2f} ({ratio.min():.2f}-{ratio.max():.2f})':>36}"
        )
    print(monte_carlo_note(draws))
    return 0


if __name__ == "__main__":
    sys.exit(main())
