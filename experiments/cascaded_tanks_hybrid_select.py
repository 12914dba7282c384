"""Choosing the hybrid cascaded-tanks configuration on the estimation record alone.

Each candidate (Hydra overrides of `experiment=cascaded_tanks_hybrid`) is trained as the
experiment trains it (`cascaded_tanks_hybrid.fit_physics`, then `train_hybrid`), but on
the first T - tail samples of the estimation record only, and scored on the held-out
tail as the protocol scores the test record: x0 from the tail's first 5 outputs
(`oneshot_jax.predict`, Gauss-Newton from the state the model reaches there), simulated
over the rest of the tail, the RMS error on it. Both the single model (the start of the
lowest final Adam loss) and the committee of all starts are scored. The validation
(test) record is not used.

Run: `python experiments/cascaded_tanks_hybrid_select.py [--tail 256] [--seeds 0 1 2]
[--publish]`; `--publish` writes docs/case-studies/cascaded_tanks_hybrid_selection.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import oneshot_jax as oj  # noqa: E402
from experiments import cascaded_tanks_hybrid as hybrid  # noqa: E402
from experiments import common, config  # noqa: E402

# name: Hydra overrides of experiment=cascaded_tanks_hybrid
CANDIDATES = {
    "widths 16 x 16, weight decay 1e-4": [],
    "widths 8 x 8, weight decay 1e-4": ["experiment.residual.widths=[8,8]"],
    "widths 16 x 16, weight decay 3e-4": ["experiment.joint.weight_decay=3e-4"],
}
PAGE = REPO / "docs" / "case-studies" / "cascaded_tanks_hybrid_selection.md"


def load(overrides):
    """The validated configuration of `experiment=cascaded_tanks_hybrid` with overrides."""
    from hydra import compose, initialize_config_dir

    config.register()
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("config", ["experiment=cascaded_tanks_hybrid", *overrides])
    return config.load(cfg)


def tail_prediction(model, theta, x0, data, m, n):
    """The output (T - m,) on the estimation record's tail from sample m: x0 estimated
    from its first n outputs (Gauss-Newton from the state the model reaches at m when
    simulated from x0), then simulated."""
    xs, _ = oj.simulate(model, theta, np.asarray(x0), data.u_est[: m + 1, None])
    guess = np.asarray(xs)[m]  # x[k] is the state at sample k
    pred = oj.predict(model, theta, data.u_est[m:, None], data.y_est[m:, None], n, x0=guess)
    return np.asarray(pred.z)[:, 0]


def tail_rmse(z, data, m, n):
    """RMS error of z (T - m,) against the tail's outputs from sample m + n on."""
    return float(np.sqrt(np.mean((z[n:] - data.y_est[m + n :]) ** 2)))


def select(tail, seeds, progress=False):
    """The held-out scores {candidate: {"single": [per seed], "committee": [per seed]}}."""
    data = oj.datasets.load_cascaded_tanks()
    T = len(data.u_est)
    m, n = T - tail, data.test.n
    out, phys = {}, None
    for name, overrides in CANDIDATES.items():
        conf = load([*overrides, f"experiment.n_samples={m}", "experiment.residual.combine=mean"])
        ex = conf.experiment
        if phys is None:  # the physical stage does not depend on the candidates
            solver = common.make_solver(conf.solver.name, conf.solver.kwargs)
            phys, _ = hybrid.fit_physics(data, ex, solver, progress)
            theta_phys = {k: float(v) for k, v in phys.theta.items()}
        row = {"single": [], "committee": []}
        for seed in seeds:
            t0 = time.perf_counter()
            res, model, _, _, _, members = hybrid.train_hybrid(
                data, ex, theta_phys, phys.x0, seed, progress
            )
            z_single = tail_prediction(model, res.theta, res.x0, data, m, n)
            zs = [tail_prediction(model, t, x, data, m, n) for t, x, _ in members]
            row["single"].append(tail_rmse(z_single, data, m, n))
            row["committee"].append(tail_rmse(np.mean(zs, 0), data, m, n))
            print(
                f"{name}, seed {seed}: held-out RMSE single {row['single'][-1]:.4f} V, "
                f"committee {row['committee'][-1]:.4f} V ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
        out[name] = row
    return out, m, n


def markdown(scores, m, n, tail, seeds, command, wall) -> str:
    """The selection page: the held-out scores of every candidate and the choice."""
    means = {
        (name, kind): float(np.mean(v)) for name, row in scores.items() for kind, v in row.items()
    }
    best = min(means, key=means.get)
    L = [
        "# Cascaded tanks hybrid: choosing the configuration on the estimation record",
        "",
        f"Command: `{command}` (seeds {', '.join(map(str, seeds))}).",
        "",
        "The [hybrid cascaded-tanks model](cascaded_tanks_hybrid.md) is trained, for each "
        f"candidate below, on the first {m} samples of the estimation record only (the "
        "physical stage and the joint stages as the experiment runs them) and scored on "
        f"the held-out last {tail} samples as the benchmark's protocol scores the test "
        f"record: x0 estimated from their first {n} outputs, then simulated, the RMS error "
        f"on the remaining {tail - n}. The test record is not used. 'single' is the start "
        "of the lowest final Adam loss, 'committee' the mean output of all starts (each "
        "from its own x0).",
        "",
        "| candidate | combine | " + " | ".join(f"seed {s} (V)" for s in seeds) + " | mean (V) |",
        "|---|---|" + "---|" * (len(seeds) + 1),
    ]
    for name, row in scores.items():
        for kind, v in row.items():
            mean = means[(name, kind)]
            cell = f"**{mean:.4f}**" if (name, kind) == best else f"{mean:.4f}"
            L.append(f"| {name} | {kind} | " + " | ".join(f"{x:.4f}" for x in v) + f" | {cell} |")
    L += [
        "",
        f"Lowest mean held-out RMSE: {best[0]}, {best[1]} ({means[best]:.4f} V). The run "
        f"took {wall:.0f} s.",
        "",
    ]
    return "\n".join(L)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tail", type=int, default=256, help="held-out samples (the tail)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--publish", action="store_true", help=f"write {PAGE.name}")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.tail < 6:
        parser.error(f"--tail must be an integer >= 6, got {args.tail}")
    t0 = time.perf_counter()
    scores, m, n = select(args.tail, args.seeds)
    command = "python experiments/cascaded_tanks_hybrid_select.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    md = markdown(scores, m, n, args.tail, args.seeds, command.strip(), time.perf_counter() - t0)
    print(md)
    if args.publish:
        PAGE.write_text(md)
        print(f"published {PAGE.relative_to(REPO)}")


if __name__ == "__main__":
    main()
