"""Coverage of the 95 % intervals on the CSTR case study, aggregated outputs against
point samples at the shifts' middles.

The record (`oneshot_jax.examples.cstr.design`): four days of a CSTR sampled at irregular
times (intervals of 1 to 10 minutes), the reactor temperature measured at the samples
with gaps, the concentration of A only as 8-hour time means. The design (times, coolant,
gaps) is fixed; each draw adds new noise (`cstr.measure`). Each draw is fitted twice by
Levenberg-Marquardt from a perturbed start (no multistart), with `t=` the time stamps and
`missing="mask"`:

- (a) `aggregated`: the averages as what they are, `aggregate=cstr.aggregate(...)`
  (`oneshot_jax.Aggregate`, kind `"time_mean"`);
- (b) `midpoint`: the same numbers written as point samples of C_A at each shift's middle
  sample (`cstr.point_samples`), the alternative without aggregated outputs.

Per parameter: the mean estimate, its bias, the bias in units of the empirical standard
error, the empirical SE (the spread of the estimates over the draws), the mean reported
SE (`result.std`) and the coverage of the 95 % intervals (`result.ci95`). A fit that does
not report success counts as a miss. Every draw has the same shapes, so `fit` compiles
once per variant and the later draws reuse it.

Run: `python benchmarks/cstr_coverage.py` (`--draws N`, default 50; `--seed S`: the
design; `--quick`: 5 draws on two days).
"""

import argparse
import sys
import time
import warnings

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from timing import conditions  # noqa: E402

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.examples import cstr  # noqa: E402

NAMES = ("ln_k0", "UA")
VARIANTS = {
    "aggregated": "(a) C_A as 8-hour time means (aggregate=, kind 'time_mean')",
    "midpoint": "(b) the same averages as point samples of C_A at the shifts' middles",
}


def start(rng, z, averages):
    """A perturbed start: ln k0 off by up to 0.25 (k0 by up to 28 %), UA by up to 15 %;
    x0 from the first average and the first temperature sample."""
    true = cstr.THETA_TRUE
    theta0 = {
        "ln_k0": true["ln_k0"] + rng.uniform(-0.25, 0.25),
        "UA": true["UA"] * rng.uniform(0.85, 1.15),
    }
    first = z[np.flatnonzero(~np.isnan(z[:, 1]))[0], 1]
    return theta0, np.array([averages[0], first])


def fit(variant, design, model, z, averages, theta0, x0):
    common = dict(t=design.t, weight=cstr.weight(), missing="mask")
    if variant == "aggregated":
        agg = cstr.aggregate(design, averages)
        return oj.fit(model, theta0, x0, design.u, z, aggregate=agg, **common)
    return oj.fit(model, theta0, x0, design.u, cstr.point_samples(design, z, averages), **common)


def study(design, draws, seed):
    """Estimates, standard errors and interval hits per variant over `draws` draws."""
    model = cstr.model()
    rng = np.random.default_rng(seed)
    out = {
        v: {"theta": [], "std": [], "hit": [], "success": [], "warned": [], "time": 0.0}
        for v in VARIANTS
    }
    for i in range(draws):
        z, averages = cstr.measure(design, seed * 100_000 + i)
        theta0, x0 = start(rng, z, averages)
        for variant, rec in out.items():
            tic = time.perf_counter()
            with warnings.catch_warnings():  # (counted in the table: `result.warnings`)
                warnings.simplefilter("ignore")
                result = fit(variant, design, model, z, averages, theta0, x0)
            rec["time"] += time.perf_counter() - tic
            rec["warned"].append(result.warnings[0] if result.warnings else "")
            lo, hi = result.ci95
            est = [float(result.theta[n]) for n in NAMES]
            rec["theta"].append(est)
            rec["std"].append([float(result.std[n]) for n in NAMES])
            rec["success"].append(bool(result.success))
            rec["hit"].append(
                [
                    bool(result.success) and float(lo[n]) <= cstr.THETA_TRUE[n] <= float(hi[n])
                    for n in NAMES
                ]
            )
    return {
        v: {k: a if k == "warned" else np.asarray(a) for k, a in rec.items()}
        for v, rec in out.items()
    }


def warned(rec):
    """How many fits warned, with the start of the first warning."""
    said = [w for w in rec["warned"] if w]
    if not said:
        return "none warned"
    head = said[0].split(":")[0]
    return f'{len(said)} warned (first: "{head}: ...")'


def table(rec):
    rows = [
        f"  {'parameter':<10}{'true':>10}{'mean est.':>12}{'bias':>11}{'bias/SE':>9}"
        f"{'emp. SE':>10}{'mean rep. SE':>14}{'coverage':>10}"
    ]
    for j, name in enumerate(NAMES):
        est, std = rec["theta"][:, j], rec["std"][:, j]
        bias = est.mean() - cstr.THETA_TRUE[name]
        emp = est.std(ddof=1) if est.size > 1 else float("nan")
        rows.append(
            f"  {name:<10}{cstr.THETA_TRUE[name]:>10.4f}{est.mean():>12.4f}{bias:>+11.2e}"
            f"{bias / emp:>+9.2f}{emp:>10.2e}{std.mean():>14.2e}"
            f"{100 * rec['hit'][:, j].mean():>9.0f}%"
        )
    return "\n".join(rows)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=50, help="noise draws (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="the design's seed (default 0)")
    parser.add_argument("--quick", action="store_true", help="5 draws on a two-day record")
    args = parser.parse_args(argv)
    days, draws = (2.0, 5) if args.quick else (4.0, args.draws)
    design = cstr.design(args.seed, days=days)
    gaps = 100 * (1 - design.observed.mean())
    print(
        f"CSTR coverage study: {days:g} days, {design.t.size} samples (intervals "
        f"{np.diff(design.t).min():.2f} to {np.diff(design.t).max():.2f} min), temperature "
        f"sigma {cstr.SIGMA_T} K with {gaps:.0f} % of samples missing, "
        f"{len(design.intervals)} shift averages of C_A (sigma {cstr.SIGMA_C} mol/L); "
        f"{draws} noise draws, design seed {args.seed}; Levenberg-Marquardt from a "
        "perturbed start (ln_k0 +- 0.25, UA +- 15 %), x0 estimated."
    )
    print(conditions())
    results = study(design, draws, args.seed)
    for variant, title in VARIANTS.items():
        rec = results[variant]
        print(
            f"\n{title}: {rec['success'].sum()}/{draws} fits succeeded, {warned(rec)}, "
            f"{rec['time']:.1f} s in all"
        )
        print(table(rec))
    cover = 100 * results["aggregated"]["hit"].mean(0)
    verdict = "within" if np.all((cover >= 90) & (cover <= 99)) else "OUTSIDE"
    verdict = f"{verdict} 90..99 %"
    if draws < 20:  # (5 draws cover 0, 20, ..., 100 %: none of them inside the band)
        verdict = f"{draws} draws are too few to judge a 95 % coverage"
    print(
        f"\nCoverage of (a): {', '.join(f'{n} {c:.0f} %' for n, c in zip(NAMES, cover))}: "
        f"{verdict}."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
