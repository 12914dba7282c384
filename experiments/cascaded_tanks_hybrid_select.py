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
[--only NAME ...] [--physical] [--publish]`. `--only` trains the named candidates alone;
`--physical` scores the physical stage alone (the candidates' baseline); `--publish`
merges this run's rows into experiments/cascaded_tanks_hybrid_selection.json (each row
with the command and wall time of the run that produced it; rows of other candidates are
kept) and writes docs/case-studies/cascaded_tanks_hybrid_selection.md from it.
"""

from __future__ import annotations

import argparse
import json
import os
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

# The settings the candidates vary, pinned to the first candidate's values, so that a
# candidate stays what its name says when the experiment's defaults change.
BASE = {
    "experiment.residual.widths": "[16,16]",
    "experiment.residual.inputs": "states",
    "experiment.joint.weight_decay": "1e-4",
    "experiment.joint.refine_steps": "30",
}
# name: Hydra overrides of experiment=cascaded_tanks_hybrid (over BASE)
CANDIDATES = {
    "widths 16 x 16, weight decay 1e-4": [],
    "widths 8 x 8, weight decay 1e-4": ["experiment.residual.widths=[8,8]"],
    "widths 16 x 16, weight decay 3e-4": ["experiment.joint.weight_decay=3e-4"],
    "refine to convergence (LM up to 300 steps)": ["experiment.joint.refine_steps=300"],
    "features (x1, x2, u)": ["experiment.residual.inputs=states_and_input"],
    "features (x1, x2, u), LM up to 300 steps": [
        "experiment.residual.inputs=states_and_input",
        "experiment.joint.refine_steps=300",
    ],
}
PAGE = REPO / "docs" / "case-studies" / "cascaded_tanks_hybrid_selection.md"
STORE = hybrid.SELECTION


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


def fit_physics(data, conf, progress=False):
    """The physical stage (`cascaded_tanks_hybrid.fit_physics`) of the configuration
    `conf` with its solver: (FitResult, Model)."""
    solver = common.make_solver(conf.solver.name, conf.solver.kwargs)
    return hybrid.fit_physics(data, conf.experiment, solver, progress)


def physical_score(tail, progress=False):
    """The held-out RMSE of the physical stage alone (`cascaded_tanks_hybrid.fit_physics`
    on the first T - tail samples), scored as the candidates are: the hybrids' baseline."""
    data = oj.datasets.load_cascaded_tanks()
    m, n = len(data.u_est) - tail, data.test.n
    phys, model = fit_physics(data, load([f"experiment.n_samples={m}"]), progress)
    z = tail_prediction(model, phys.theta, phys.x0, data, m, n)
    return tail_rmse(z, data, m, n), m, n


def select(tail, seeds, names=None, progress=False):
    """The held-out scores {candidate: {"single": [per seed], "committee": [per seed],
    "refine": [per seed: the kept start's refinement stop reason and step count]}} of
    the candidates `names` (None: all)."""
    data = oj.datasets.load_cascaded_tanks()
    T = len(data.u_est)
    m, n = T - tail, data.test.n
    out, phys = {}, None
    for name, overrides in CANDIDATES.items():
        if names is not None and name not in names:
            continue
        settings = {**BASE, **dict(o.split("=", 1) for o in overrides)}
        conf = load(
            [
                *(f"{k}={v}" for k, v in settings.items()),
                f"experiment.n_samples={m}",
                "experiment.residual.combine=mean",
            ]
        )
        ex = conf.experiment
        if phys is None:  # the physical stage does not depend on the candidates
            phys, _ = fit_physics(data, conf, progress)
            theta_phys = {k: float(v) for k, v in phys.theta.items()}
        row = {"single": [], "committee": [], "refine": []}
        for seed in seeds:
            t0 = time.perf_counter()
            res, model, _, stages, _, members = hybrid.train_hybrid(
                data, ex, theta_phys, phys.x0, seed, progress
            )
            stage = stages.get(ex.joint.refine)
            z_single = tail_prediction(model, res.theta, res.x0, data, m, n)
            zs = [tail_prediction(model, t, x, data, m, n) for t, x, *_ in members]
            row["single"].append(tail_rmse(z_single, data, m, n))
            row["committee"].append(tail_rmse(np.mean(zs, 0), data, m, n))
            row["refine"].append(
                None if stage is None else f"{stage['stop_reason']} ({stage['iterations']})"
            )
            print(
                f"{name}, seed {seed}: held-out RMSE single {row['single'][-1]:.4f} V, "
                f"committee {row['committee'][-1]:.4f} V, refinement of the kept start "
                f"{row['refine'][-1]} ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
        out[name] = row
    return out, m, n


def _empty(m, n, tail, seeds):
    """A store with no rows yet."""
    return {"m": m, "n": n, "tail": tail, "seeds": list(seeds), "runs": [], "scores": {}}


def run_conditions() -> str:
    """The run's conditions: the machine and versions (`experiments.run.conditions`) and
    the CPU cores this process may use (a run pinned to one core by `taskset` says so)."""
    from experiments import run

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{run.conditions()[:-1]}; the run may use {cores} of them."


def merge(store, scores, m, n, tail, seeds, command, wall, conditions=None):
    """The store (dict, or None for none yet) with this run's rows put in: a candidate's
    earlier row is replaced, the others are kept. Rows of different tails or seeds are
    not comparable: a ValueError then."""
    store = _empty(m, n, tail, seeds) if store is None else store
    if (store["m"], store["n"], store["tail"], store["seeds"]) != (m, n, tail, list(seeds)):
        raise ValueError(
            f"{STORE.name} holds rows of tail {store['tail']} and seeds {store['seeds']}; "
            f"this run has tail {tail} and seeds {list(seeds)}: rerun every candidate"
        )
    store["runs"].append(
        {
            "command": command,
            "wall_s": round(wall),
            "candidates": list(scores),
            "conditions": conditions,
        }
    )
    for name, row in scores.items():
        store["scores"][name] = {**row, "run": len(store["runs"])}
    return prune(store)


def merge_physical(store, row, m, n, tail, seeds):
    """The store (dict, or None for none yet) with the physical stage's row
    {"rmse", "command", "wall_s"} put in, replacing an earlier one; a store of another
    tail: a ValueError."""
    store = _empty(m, n, tail, seeds) if store is None else store
    if (store["m"], store["n"], store["tail"]) != (m, n, tail):
        raise ValueError(
            f"{STORE.name} holds rows of tail {store['tail']}; this run has tail {tail}"
        )
    return {**store, "physical": row}


def prune(store):
    """The store without the runs whose rows were all replaced, the runs renumbered."""
    used = sorted({row["run"] for row in store["scores"].values()})
    new = {old: i for i, old in enumerate(used, 1)}
    store["runs"] = [store["runs"][old - 1] for old in used]
    for row in store["scores"].values():
        row["run"] = new[row["run"]]
    return store


def candidate_means(store) -> dict:
    """{(candidate, combine): its mean held-out RMSE over the seeds}, in the order of
    `CANDIDATES` (single before committee)."""
    order = list(CANDIDATES)
    names = sorted(store["scores"], key=lambda k: order.index(k) if k in order else len(order))
    return {
        (name, kind): float(np.mean(store["scores"][name][kind]))
        for name in names
        for kind in ("single", "committee")
        if kind in store["scores"][name]
    }


def markdown(store) -> str:
    """The selection page: the held-out scores of every stored candidate and the choice."""
    m, n, tail, seeds = store["m"], store["n"], store["tail"], store["seeds"]
    means = candidate_means(store)
    scores = {name: store["scores"][name] for name, _ in means}  # in the order of CANDIDATES
    kinds = [k for k in ("single", "committee") if any(k in row for row in scores.values())]
    best = min(means, key=means.get) if means else None
    L = [
        "# Cascaded tanks hybrid: choosing the configuration on the estimation record",
        "",
        "The [hybrid cascaded-tanks model](cascaded_tanks_hybrid.md) is trained, for each "
        f"candidate below, on the first {m} samples of the estimation record only (the "
        "physical stage, the overflow model with the quadratic sensor, and the joint "
        "stages as the experiment runs them) and scored on "
        f"the held-out last {tail} samples as the benchmark's protocol scores the test "
        f"record: x0 estimated from their first {n} outputs, then simulated, the RMS error "
        f"on the remaining {tail - n}. The test record is not used. 'single' is the start "
        "of the lowest final Adam loss, 'committee' the mean output of all starts (each "
        "from its own x0). Each candidate changes the "
        "[experiment's configuration](cascaded_tanks_hybrid.md) as its name says "
        "(`CANDIDATES` in `experiments/cascaded_tanks_hybrid_select.py`).",
        "",
        "| candidate | combine | "
        + " | ".join(f"seed {s} (V)" for s in seeds)
        + " | mean (V) | run |",
        "|---|---|" + "---|" * (len(seeds) + 2),
    ]
    for name, row in scores.items():
        for kind in [k for k in kinds if k in row]:
            mean = means[(name, kind)]
            cell = f"**{mean:.4f}**" if (name, kind) == best else f"{mean:.4f}"
            L.append(
                f"| {name} | {kind} | "
                + " | ".join(f"{x:.4f}" for x in row[kind])
                + f" | {cell} | {row['run']} |"
            )
    L.append("")
    if best is not None:
        L += [f"Lowest mean held-out RMSE: {best[0]}, {best[1]} ({means[best]:.4f} V).", ""]
    phys = store.get("physical")
    if phys is not None:
        below = [k for k, v in means.items() if v < phys["rmse"]]
        verdict = (
            f"; {len(below)} of the {len(means)} rows score lower"
            if below
            else "; no row scores lower: on this held-out tail the network does not "
            "improve on the physics"
        )
        L += [
            "The physical stage alone (the overflow model with the quadratic sensor, no "
            f"network), trained and scored the same way: {phys['rmse']:.4f} V"
            f"{verdict if means else ''} (`{phys['command']}`, {phys['wall_s']} s"
            + (f"; {phys['conditions'].rstrip('.')}" if phys.get("conditions") else "")
            + ").",
            "",
        ]
    L += [
        "The refinement of the kept start (stop reason and steps; for the committee's other "
        "members it is not recorded):",
        "",
        "| candidate | " + " | ".join(f"seed {s}" for s in seeds) + " |",
        "|---|" + "---|" * len(seeds),
    ]
    for name, row in scores.items():
        refine = row.get("refine") or [None] * len(seeds)
        L.append(f"| {name} | " + " | ".join(r or "not recorded" for r in refine) + " |")
    L += ["", "The runs (seeds " + ", ".join(map(str, seeds)) + "):", ""]
    for i, run in enumerate(store["runs"], 1):
        where = f" Conditions: {run['conditions']}" if run.get("conditions") else ""
        L.append(
            f"{i}. `{run['command']}` ({run['wall_s']} s): "
            + "; ".join(f"'{c}'" for c in run["candidates"])
            + "."
            + where
        )
    L.append("")
    return "\n".join(L)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tail", type=int, default=256, help="held-out samples (the tail)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--only", action="append", metavar="NAME", help="train this candidate (repeatable)"
    )
    parser.add_argument(
        "--physical",
        action="store_true",
        help="score the physical stage alone (the candidates' baseline), no candidate",
    )
    parser.add_argument("--publish", action="store_true", help=f"write {PAGE.name}")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.tail < 6:
        parser.error(f"--tail must be an integer >= 6, got {args.tail}")
    for name in args.only or []:
        if name not in CANDIDATES:
            parser.error(f"--only must name a candidate of {list(CANDIDATES)}, got {name!r}")
    if args.physical and args.only:
        parser.error("--physical scores the physical stage alone: drop --only")
    t0 = time.perf_counter()
    command = "python experiments/cascaded_tanks_hybrid_select.py " + " ".join(
        repr(a) if " " in a else a for a in (argv if argv is not None else sys.argv[1:])
    )
    if args.physical:
        rmse, m, n = physical_score(args.tail)
        wall = time.perf_counter() - t0
        print(f"physical stage alone: held-out RMSE {rmse:.4f} V ({wall:.0f} s)")
        row = {
            "rmse": rmse,
            "command": command.strip(),
            "wall_s": round(wall),
            "conditions": run_conditions(),
        }
        update = lambda store: merge_physical(store, row, m, n, args.tail, args.seeds)  # noqa: E731
    else:
        scores, m, n = select(args.tail, args.seeds, args.only)
        wall = time.perf_counter() - t0
        print(json.dumps(scores, indent=1))
        where = run_conditions()
        this = merge(None, scores, m, n, args.tail, args.seeds, command.strip(), wall, where)
        print(markdown(this))
        update = lambda store: merge(  # noqa: E731
            store, scores, m, n, args.tail, args.seeds, command.strip(), wall, where
        )
    if args.publish:
        store = update(json.loads(STORE.read_text()) if STORE.exists() else None)
        STORE.write_text(json.dumps(store, indent=1) + "\n")
        PAGE.write_text(markdown(store))
        print(f"published {PAGE.relative_to(REPO)} and {STORE.relative_to(REPO)}")


if __name__ == "__main__":
    main()
