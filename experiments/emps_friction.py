"""EMPS trained for the open-loop protocol, with richer physical friction models.

The benchmark's model M q'' = tau - Fv q' - Fc sign(q') - offset (`oneshot_jax.examples.emps`)
is extended by physical friction effects, each a parameter that starts at zero:

- **asymmetric viscous friction**: Fv q' + dFv |q'|, i.e. a viscous coefficient Fv + dFv
  for q' > 0 and Fv - dFv for q' < 0;
- **load-dependent Coulomb friction**: (Fc + mu |tau|) sign(q'), the friction of a
  screw drive growing with the force it transmits (mu is dimensionless);
- **Stribeck friction**: Fs exp(-(q'/vs)^2) sign(q'), an extra friction at low speed
  (vs fixed, `stribeck_velocity`);
- **position-dependent Coulomb friction and force**: Fc and offset become functions of
  the position q, piecewise linear between `position_knots` knots spread evenly over the
  travel (`TRAVEL`): the vectors Fcq and Fq of their values at the knots (a screw
  drive's friction varies along the screw; a cable carrier pulls with a force that
  depends on where the carriage is). They replace Fc and offset (the knots' hat
  functions sum to one, so a constant Fc or offset beside them would be the same
  direction twice).

sign(q') is tanh(q'/eps) and |q'| is q' tanh(q'/eps), |tau| is sqrt(tau^2 + 1 N^2) (smooth
stand-ins, so that the closed-form Jacobians exist). The structures compared are named in
`STRUCTURES`.

Unlike `experiment=emps` and `experiment=emps_hybrid`, which fit short windows (a few
tens of ms, each with its own initial state), every structure here is fitted for the
protocol that scores it: the open-loop simulation of a whole record from one initial
state. The simulation error of a double integrator over 20 s has bad minima from a far
start, so the fit is `oneshot_jax.fit_continuation`: windows of 50 samples first, then
longer ones, each stage warm-started, up to the whole training record (input tau = gtau
vir, output qm in mm, Levenberg-Marquardt).

The structure is selected on the estimation record (DATA_EMPS.mat) alone, by rolling-origin
cross-validation: for each fold (`cv_holdouts`), the first part of the record trains and
the last fraction is scored like the test record (x0 from its first 20 outputs, open-loop
simulation of the rest); the least mean held-out RMSE selects. Every structure is also
fitted on the whole estimation record (the final model). The test record
(DATA_EMPS_PULSES.mat) is scored with the community's protocol only
(`oneshot_jax.examples.emps.protocol_prediction`), for every fit.

Run: `python experiments/run.py experiment=emps_friction`; tables in `markdown`.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj
from oneshot_jax.examples import emps as example

from . import common
from .config import as_dict

STRUCTURES = {
    "coulomb_viscous": (),
    "asymmetric": ("dFv",),
    "load": ("dFv", "mu"),
    "stribeck": ("dFv", "Fs"),
    "load_stribeck": ("dFv", "mu", "Fs"),
    "position": ("dFv", "Fcq", "Fq"),
    "position_stribeck": ("dFv", "Fs", "Fcq", "Fq"),
    "position_load_stribeck": ("dFv", "mu", "Fs", "Fcq", "Fq"),
}
"""Each structure's parameters beyond M, Fv, Fc, offset (each starts at zero); Fcq and Fq
replace Fc and offset (they start at them, at every knot)."""
POSITION = {"Fcq": "Fc", "Fq": "offset"}
"""The position-dependent parameters and the constant ones each replaces."""
UNITS = {**example.UNITS, "dFv": "N/(m/s)", "mu": "-", "Fs": "N", "Fcq": "N", "Fq": "N"}
LABELS = {
    "coulomb_viscous": "Coulomb + viscous (the benchmark's model)",
    "asymmetric": "+ asymmetric viscous",
    "load": "+ asymmetric viscous + load-dependent Coulomb",
    "stribeck": "+ asymmetric viscous + Stribeck",
    "load_stribeck": "+ asymmetric viscous + load-dependent Coulomb + Stribeck",
    "position": "+ asymmetric viscous + position-dependent Coulomb and force",
    "position_stribeck": "+ asymmetric viscous + Stribeck + position-dependent Coulomb and force",
    "position_load_stribeck": (
        "+ asymmetric viscous + load-dependent Coulomb + Stribeck + position-dependent "
        "Coulomb and force"
    ),
}
LOWER = {**example.LOWER, "mu": 0.0, "Fs": 0.0, "Fcq": example.LOWER["Fc"]}
"""M, Fv, Fc > 0 (Fcq > 0 at every knot, as Fc) and mu, Fs >= 0
(`oneshot_jax.constraints.box`)."""
TRAVEL = (0.0, 0.25)
"""m: the span of the position knots (the axis moves within 0 and 0.247 m in both records)."""
TAU_SMOOTH = 1.0
"""N: |tau| is sqrt(tau^2 + TAU_SMOOTH^2)."""
STRIBECK_VELOCITY = 0.01
"""m/s: the default Stribeck velocity vs (the extra friction at rest decays as exp(-(v/vs)^2))."""


def knot_weights(q, n_knots):
    """The hat functions of `n_knots` knots spread evenly over `TRAVEL` at position q
    (m): piecewise linear, one at their own knot, zero at the others, summing to one
    (constant beyond the end knots)."""
    knots = jnp.linspace(*TRAVEL, n_knots)
    q = jnp.clip(q, *TRAVEL)
    return jnp.clip(1.0 - jnp.abs(q - knots) / (knots[1] - knots[0]), 0.0, 1.0)


def friction(v, tau, theta, eps=example.EPS, vs=STRIBECK_VELOCITY, q=None):
    """The friction force (N) at velocity v (m/s), motor force tau (N) and position q (m):
    Fv v + dFv |v| + (Fc + mu |tau| + Fs exp(-(v/vs)^2)) sign(v) + offset, the terms of
    theta only; with Fcq and Fq, Fc and offset are their values interpolated at q
    (`knot_weights`)."""
    s = jnp.tanh(v / eps)
    if q is None and any(k in theta for k in POSITION):
        raise ValueError("`q` is needed for the position-dependent terms Fcq and Fq.")
    # Fc and offset, or their position-dependent replacements at q (POSITION's order)
    fc, off = (
        knot_weights(q, theta[k].shape[0]) @ theta[k] if k in theta else theta[constant]
        for k, constant in POSITION.items()
    )
    f = theta["Fv"] * v + fc * s + off
    if "dFv" in theta:
        f = f + theta["dFv"] * v * s
    if "mu" in theta:
        f = f + theta["mu"] * jnp.sqrt(tau**2 + TAU_SMOOTH**2) * s
    if "Fs" in theta:
        f = f + theta["Fs"] * jnp.exp(-((v / vs) ** 2)) * s
    return f


class FrictionPlant(eqx.Module):
    """d(q, q')/dt = (q', (tau - friction(q', tau)) / M); input u = (tau,) (N)."""

    eps: float = eqx.field(static=True, default=example.EPS)
    vs: float = eqx.field(static=True, default=STRIBECK_VELOCITY)

    def __call__(self, x, u, theta):
        f = friction(x[1], u[0], theta, self.eps, self.vs, q=x[0])
        return jnp.stack([x[1], (u[0] - f) / theta["M"]])


def _position(x, u, theta):
    del u, theta
    return x[:1]


def friction_model(Ts, eps=example.EPS, substeps=1, vs=STRIBECK_VELOCITY) -> oj.Model:
    """State (q, q'), input tau (N), output q: RK4 of `FrictionPlant` (the structure is
    the set of keys of theta)."""
    return oj.Model.from_ode(
        FrictionPlant(float(eps), float(vs)), Ts, substeps=int(substeps), observe=_position
    )


def theta_start(ex, structure) -> dict:
    """The configured start of M, Fv, Fc, offset, and zero for the structure's extras;
    Fcq and Fq (`ex.position_knots` values each) start at Fc and offset, which they
    replace."""
    theta = {**dict(ex.theta0), **{k: 0.0 for k in STRUCTURES[structure]}}
    for k, constant in POSITION.items():
        if k in theta:
            theta[k] = np.full(int(ex.position_knots), float(theta.pop(constant)))
    return theta


def as_arrays(theta) -> dict:
    """theta with its vector parameters (Fcq, Fq) as arrays (a row's theta holds lists)."""
    return {k: np.asarray(v, dtype=float) if np.ndim(v) else float(v) for k, v in theta.items()}


def as_plain(theta) -> dict:
    """theta as JSON-ready numbers: floats, and lists for the vector parameters."""
    return {k: np.asarray(v, dtype=float).tolist() for k, v in theta.items()}


def mean_theta(thetas) -> dict:
    """The mean of several thetas of one structure, parameter by parameter."""
    return {k: np.mean([np.asarray(t[k], dtype=float) for t in thetas], axis=0) for k in thetas[0]}


def fmt(v) -> str:
    """A parameter's value for tables and logs: a scalar to 4 digits, a vector (values at
    the knots) as [a, b, ...] to 3."""
    if np.ndim(v):
        return "[" + ", ".join(f"{x:.3g}" for x in np.asarray(v)) + "]"
    return f"{v:.4g}"


def split(record, holdout):
    """The estimation record as (training part, held-out last `holdout` fraction)."""
    n = len(record)
    n_train = n - int(round(holdout * n))
    fields = ("t", "qm", "qg", "vir", "pulses")
    return example.trim(record, n_train), dataclasses.replace(
        record, **{f: getattr(record, f)[n_train:] for f in fields}
    )


def record_rmse_mm(model, theta, record, gtau, Ts, n=20, half=5):
    """A record scored as the protocol scores the test record: x0 from its first n
    outputs (`oneshot_jax.predict`), RMSE of q in mm over the rest."""
    u = gtau * np.asarray(record.vir).reshape(-1, 1)
    y = np.asarray(record.qm).reshape(-1, 1)
    v0 = example.velocity_estimate(y[: max(n, 2 * half + 1), 0], Ts, half)[0]
    pred = oj.predict(model, as_arrays(theta), u, y, n, x0=np.array([y[0, 0], v0]))
    return float(1e3 * np.sqrt(np.mean((np.asarray(pred.z)[n:, 0] - y[n:, 0]) ** 2)))


def fit_structure(data, record, structure, ex, solver, progress=False):
    """`fit_continuation` of one structure on one record from `theta_start`. Returns the
    `Continuation` and its wall time (s)."""
    model = friction_model(data.Ts, ex.eps, ex.substeps, ex.stribeck_velocity)
    u, z, x0 = example.open_loop_data(record, data.gtau, data.Ts, None, ex.velocity_halfwidth)
    windows = [w for w in ex.windows if w < u.shape[1]]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # The extras start at zero, where some directions are flat: fit warns about them.
        warnings.simplefilter("ignore", UserWarning)
        theta = theta_start(ex, structure)
        cont = oj.fit_continuation(
            model,
            theta,
            x0[0],
            u[0],
            z[0],
            windows=windows,
            solver=solver,
            constraints=oj.constraints.box(lower={k: LOWER[k] for k in theta if k in LOWER}),
            weight=np.array([1e6]),  # q in mm in the loss
            progress=progress,
        )
    return cont, time.perf_counter() - t0


EDGE_SPAN = (5, 150)
"""Samples before and after a pulse edge over which `edge_drift_mm` takes the error's change."""


def edge_drift_mm(pred, record, Ts, half=5):
    """The mean change of the simulation error q_sim - qm (mm) across the test record's
    pulse edges (from `EDGE_SPAN[0]` samples before each edge to `EDGE_SPAN[1]` after),
    signed by the direction of motion at the edge: > 0 where the model runs ahead of the
    axis after the pulses switch."""
    on = np.asarray(record.pulses) != 0
    edges = np.flatnonzero(np.diff(on.astype(int))) + 1
    before, after = EDGE_SPAN
    edges = edges[(edges >= before) & (edges + after < len(on))]
    err = 1e3 * (np.asarray(pred.z)[:, 0] - np.asarray(record.qm))
    v = example.velocity_estimate(record.qm, Ts, half)
    return float(np.mean(np.sign(v[edges]) * (err[edges + after] - err[edges - before])))


def fit_span(data, record, structure, holdout, ex, solver, progress=False) -> dict:
    """One structure fitted (`fit_structure`, from the far start) on the training span of
    the estimation record that holds out its last `holdout` fraction (0: the whole
    record), scored on that held-out part (`record_rmse_mm`) and on the test record
    (`oneshot_jax.examples.emps.protocol_prediction`)."""
    train, held_out = split(record, holdout) if holdout > 0 else (record, None)
    if len(train) <= ex.windows[0]:
        raise ValueError(
            f"the training span of holdout {holdout:g} ({len(train)} samples) must be longer "
            f"than the first window ({ex.windows[0]}): raise experiment.n_samples or lower "
            "experiment.windows."
        )
    cont, wall = fit_structure(data, train, structure, ex, solver, progress)
    model = friction_model(data.Ts, ex.eps, ex.substeps, ex.stribeck_velocity)
    res = cont.result
    theta = as_arrays(res.theta)
    pred, sc = example.protocol_prediction(
        data, theta, ex.eps, ex.substeps, half=ex.velocity_halfwidth, model=model
    )
    return {
        "structure": structure,
        "holdout": float(holdout),
        "n_train": len(train),
        "theta": as_plain(theta),
        "std": as_plain(res.std),
        "stages": [
            {"window": s.window, "loss": s.loss, "steps": s.num_steps, "status": s.status}
            for s in cont.stages
        ],
        "status": res.status,
        "time_s": float(wall),
        "rmse_train_mm": float(1e3 * np.atleast_1d(res.metrics["rmse"])[0]),
        "rmse_heldout_mm": (
            record_rmse_mm(model, theta, held_out, data.gtau, data.Ts, half=ex.velocity_halfwidth)
            if held_out is not None
            else None
        ),
        "protocol": common.protocol_scores(sc, pred, "mm"),
        "edge_drift_mm": edge_drift_mm(pred, data.validation, data.Ts, ex.velocity_halfwidth),
    }


def cross_validation_mm(fits, holdouts) -> float:
    """Rolling-origin cross-validation score of one structure: the mean, over the folds
    `holdouts`, of the held-out RMSE (mm) of the fit on the span before each fold's
    held-out part. `fits` maps a holdout to its `fit_span` row."""
    return float(np.mean([fits[float(h)]["rmse_heldout_mm"] for h in holdouts]))


def averaged_model(data, fits, ex) -> dict:
    """The model whose parameters are the mean of one structure's span fits (an
    aggregate over training spans: each fit's span-dependent error partly cancels),
    scored on the test record; and, for its spread, the models that leave one of the fits
    out of the mean."""
    model = friction_model(data.Ts, ex.eps, ex.substeps, ex.stribeck_velocity)

    def scored(group):
        theta = mean_theta([f["theta"] for f in group])
        pred, sc = example.protocol_prediction(
            data, theta, ex.eps, ex.substeps, half=ex.velocity_halfwidth, model=model
        )
        return theta, common.protocol_scores(sc, pred, "mm")

    theta, protocol = scored(fits)
    loo = [scored(fits[:i] + fits[i + 1 :])[1]["rmse_mm"] for i in range(len(fits))]
    return {
        "theta": as_plain(theta),
        "protocol": protocol,
        "leave_one_out_mm": loo if len(fits) > 1 else [],
    }


def aggregation_check(data, record, fits, holdouts, ex) -> dict:
    """Whether averaging parameters over training spans helps out of sample, on the
    estimation record only: for each fold but the one that holds out most, the held-out
    RMSE (mm) of the fold's own fit and of the model with the mean parameters of the fits
    that did not see that held-out part (those of this fold and of the folds holding out
    more). `fits` maps a holdout to its `fit_span` row."""
    model = friction_model(data.Ts, ex.eps, ex.substeps, ex.stribeck_velocity)
    folds = sorted(float(h) for h in set(holdouts))
    single, mean = [], []
    for h in folds[:-1]:
        _, held_out = split(record, h)
        group = [fits[g]["theta"] for g in folds if g >= h]
        theta = mean_theta(group)
        single.append(fits[h]["rmse_heldout_mm"])
        mean.append(
            record_rmse_mm(model, theta, held_out, data.gtau, data.Ts, half=ex.velocity_halfwidth)
        )
    return {"holdouts": folds[:-1], "single_mm": single, "mean_mm": mean}


def final_model(check) -> str:
    """The procedure's model, decided on the estimation record: "mean" (the parameters
    averaged over the whole-record and fold fits) where `aggregation_check` found the
    averaged parameters better on the held-out parts on average, else "whole" (the fit on
    the whole estimation record)."""
    if check["holdouts"] and np.mean(check["mean_mm"]) < np.mean(check["single_mm"]):
        return "mean"
    return "whole"


def run(cfg, outdir, command="python experiments/run.py experiment=emps_friction") -> dict:
    """Fit every configured structure on the whole estimation record and on the training
    span of each rolling-origin fold, select the structure by the folds' mean held-out
    RMSE (the estimation record only), score every fit on the test record, write
    results.md into `outdir`; `cfg` is the validated `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "EMPS friction")
    data = oj.datasets.load_emps(ex.data_path)
    record = example.trim(data.estimation, ex.n_samples)
    spans = [0.0] + sorted(float(h) for h in set(ex.cv_holdouts))
    print(
        f"EMPS friction: {len(record)} estimation samples; spans holding out "
        f"{', '.join(f'{h:g}' for h in spans)}; continuation windows {list(ex.windows)} then "
        f"the whole span; {cfg.solver.title}",
        flush=True,
    )
    rows = []
    for structure in ex.structures:
        for h in spans:
            row = fit_span(data, record, structure, h, ex, solver, cfg.progress)
            rows.append(row)
            # Every span compiles programs of its own shapes, and XLA keeps each compiled
            # program's machine code mapped: some hundred of them exhaust Linux's limit
            # of memory maps per process (vm.max_map_count). Drop them between spans.
            jax.clear_caches()
            ho = row["rmse_heldout_mm"]
            print(
                f"  {structure:<16} holdout {h:<4g} {row['time_s']:6.1f} s {row['status']:<17} | "
                + " ".join(f"{k} {fmt(v)}" for k, v in row["theta"].items())
                + f" | RMSE (mm) train {row['rmse_train_mm']:.3f} held-out "
                + ("-" if ho is None else f"{ho:.3f}")
                + f" test {row['protocol']['rmse_mm']:.3f}",
                flush=True,
            )
    summary = {}
    for structure in ex.structures:
        fits = {r["holdout"]: r for r in rows if r["structure"] == structure}
        tests = [r["protocol"]["rmse_mm"] for r in fits.values()]
        summary[structure] = {
            "cv_mm": cross_validation_mm(fits, ex.cv_holdouts),
            "test_whole_mm": fits[0.0]["protocol"]["rmse_mm"],
            "test_mean_mm": float(np.mean(tests)),
            "test_min_mm": float(np.min(tests)),
            "test_max_mm": float(np.max(tests)),
            "averaged": averaged_model(data, list(fits.values()), ex),
            "aggregation_check": aggregation_check(data, record, fits, ex.cv_holdouts, ex),
        }
    selected = min(ex.structures, key=lambda s: summary[s]["cv_mm"])
    final = final_model(summary[selected]["aggregation_check"])
    ref_pred, ref_sc = example.protocol_prediction(
        data, example.REFERENCE, ex.eps, ex.substeps, half=ex.velocity_halfwidth
    )
    out = {
        "benchmark": "EMPS",
        "command": command,
        "solver": as_dict(cfg.solver),
        "config": as_dict(ex),
        "n_estimation": len(record),
        "spans": spans,
        "Ts_s": data.Ts,
        "gtau_N_per_V": float(data.gtau),
        "units": UNITS,
        "rows": rows,
        "summary": summary,
        "selected": selected,
        "final": final,
        "max_force_N": {
            "estimation": float(np.max(np.abs(data.gtau * data.estimation.vir))),
            "test": float(np.max(np.abs(data.gtau * data.validation.vir))),
        },
        "pulse_V": float(np.max(np.abs(data.validation.pulses))),
        "reference": {
            "theta": example.REFERENCE,
            "protocol": common.protocol_scores(ref_sc, ref_pred, "mm"),
        },
        "figures": [],
        "total_time_s": time.perf_counter() - t_start,
    }
    out = common.to_jsonable(out)
    md = markdown(out)
    (outdir / "results.md").write_text(md)
    print(md)
    return out


PUBLISHED = (
    ("LTI state space", "5.53"),
    ("pNARX", "5.17"),
    ("CT-SUBNET", "4.61"),
    ("dynoNet", "about 2.6"),
)
"""Published protocol RMSEs (mm) on DATA_EMPS_PULSES (Champneys et al. 2024, Tables 3-4)."""


def _spread(summary) -> str:
    """'mean (min-max)' of the leave-one-out mean-parameter models' test RMSEs (mm)."""
    loo = summary["averaged"]["leave_one_out_mm"]
    if not loo:
        return ""
    return f"{np.mean(loo):.2f} ({np.min(loo):.2f}-{np.max(loo):.2f})"


def markdown(res) -> str:
    """results.md of a run: every number from its results dict."""
    cfg = res["config"]
    rows, summary = res["rows"], res["summary"]
    structures = list(summary)
    folds = [h for h in res["spans"] if h > 0]

    def fit(structure, h):
        return next(r for r in rows if r["structure"] == structure and r["holdout"] == h)

    def short(structure):
        return LABELS[structure].split(" (")[0].lstrip("+ ")

    sel = res["selected"]
    L = [
        "# EMPS: friction models trained for the open-loop protocol",
        "",
        f"Command: `{res['command']}`.",
        "",
        "The benchmark's model M q'' = tau - Fv q' - Fc sign(q') - offset (tau = gtau vir), "
        "and physical extensions of its friction, each a parameter that starts at zero: "
        "a viscous coefficient that differs with the direction of motion (Fv q' + dFv |q'|), "
        "a Coulomb friction that grows with the force the drive transmits "
        "((Fc + mu |tau|) sign(q'), as in a screw drive), and a Stribeck friction, an extra "
        "friction at low speed (Fs exp(-(q'/vs)^2) sign(q'), "
        f"vs = {cfg['stribeck_velocity']:g} m/s), and a Coulomb friction and a force "
        "that vary along the travel (Fcq and Fq: their values at "
        f"{cfg['position_knots']} knots spread evenly over {TRAVEL[0]:g} to {TRAVEL[1]:g} m, "
        "linear between them; they replace Fc and offset, from which they start; as in a "
        "screw whose friction varies along it, or a cable carrier whose pull depends on "
        "where the carriage is). sign(q') is tanh(q'/eps), "
        f"eps = {cfg['eps']:g} m/s.",
        "",
        "Every structure is fitted for the protocol that scores it, the open-loop "
        f"simulation of a whole record: `oneshot_jax.fit_continuation` from M, Fv, Fc, "
        f"offset = {', '.join(f'{v:g}' for v in cfg['theta0'].values())} (far from the "
        f"reference), windows of {', '.join(str(w) for w in cfg['windows'])} samples "
        "(each with its own initial state), each stage warm-started, then the whole "
        "training span from one initial state; loss: the simulation error of q in mm.",
        "",
        "## Selection on the estimation record",
        "",
        "The structure is chosen on DATA_EMPS.mat alone, by rolling-origin "
        "cross-validation: for each fold, the structure is fitted on the first part of "
        "the record and the rest is scored like the test record (x0 from its first 20 "
        "outputs, open-loop simulation of the rest); the score is the mean held-out RMSE "
        "over the folds. Held-out RMSE (mm) by the fraction of the "
        f"{res['n_estimation']} samples held out:",
        "",
        "| model | " + " | ".join(f"{h:g}" for h in folds) + " | mean |",
        "|---|" + "---|" * (len(folds) + 1),
    ]
    for s in structures:
        L.append(
            f"| {LABELS[s]} | "
            + " | ".join(f"{fit(s, h)['rmse_heldout_mm']:.3f}" for h in folds)
            + f" | {summary[s]['cv_mm']:.3f} |"
        )
    L += [
        "",
        f"Selected: {LABELS[sel]}.",
        "",
    ]
    checks = {s: summary[s]["aggregation_check"] for s in structures}
    check_folds = checks[structures[0]]["holdouts"]
    if check_folds:
        L += [
            "Averaging parameters over training spans, checked on the estimation record "
            "alone: for each fold, the held-out RMSE (mm) of the fold's own fit, then of "
            "the model whose parameters are the mean of the fits that did not see that "
            "held-out part (the fold's and those of the folds holding out more):",
            "",
            "| model | " + " | ".join(f"{h:g}" for h in check_folds) + " | mean |",
            "|---|" + "---|" * (len(check_folds) + 1),
        ]
        for s in structures:
            c = checks[s]
            L.append(
                f"| {LABELS[s]} | "
                + " | ".join(f"{a:.3f} / {b:.3f}" for a, b in zip(c["single_mm"], c["mean_mm"]))
                + f" | {np.mean(c['single_mm']):.3f} / {np.mean(c['mean_mm']):.3f} |"
            )
        L.append("")
    L += [
        "Each structure is also fitted on the whole estimation record, from the same far "
        "start. The procedure's model is the selected structure fitted on the whole "
        "record, or, where the check above finds the mean parameters better on the "
        "held-out parts, the selected structure with the mean of its parameters over "
        "its fits (the whole record and the folds' training spans). Here: "
        + (
            "the mean parameters."
            if res["final"] == "mean"
            else "the whole-record fit (the mean parameters are not better on the held-out parts)."
        ),
        "",
        "## Test scores",
        "",
        "Test: the community's protocol on DATA_EMPS_PULSES.mat (open-loop simulation "
        "with u = vir and y = qm, x0 = (q, q') estimated from the first "
        f"{rows[0]['protocol']['n']} test outputs only, RMSE of q in mm on the "
        "rest). The test record is used for these scores only. Each structure's fit on "
        "the whole estimation record, each of its fold fits, the model whose "
        "parameters are the mean of these fits, and the models that leave one fit out "
        "of that mean:",
        "",
        "| model | whole record | "
        + " | ".join(f"held out {h:g}" for h in folds)
        + " | mean (min-max) | mean parameters | leaving one fit out: mean (min-max) "
        "| whole-record fit time (s) |",
        "|---|---|" + "---|" * (len(folds) + 4),
    ]
    for s in structures:
        m = summary[s]
        L.append(
            f"| {LABELS[s]} | {m['test_whole_mm']:.3f} | "
            + " | ".join(f"{fit(s, h)['protocol']['rmse_mm']:.3f}" for h in folds)
            + f" | {m['test_mean_mm']:.2f} ({m['test_min_mm']:.2f}-{m['test_max_mm']:.2f}) "
            f"| {m['averaged']['protocol']['rmse_mm']:.3f} | {_spread(m)} "
            f"| {fit(s, 0.0)['time_s']:.0f} |"
        )
    ref = res["reference"]["protocol"]
    L += [
        "",
        f"IDIM-LS reference parameters: test RMSE {ref['rmse_mm']:.3f} mm (FIT "
        f"{ref['fit_percent']:.2f} %). Published on the same protocol (Champneys et al. "
        "2024): " + ", ".join(f"{name} {rmse} mm" for name, rmse in PUBLISHED) + ".",
        "",
        "Parameters fitted on the whole estimation record:",
        "",
        "| parameter | " + " | ".join(LABELS[s] for s in structures) + " | IDIM-LS reference |",
        "|---|" + "---|" * (len(structures) + 1),
    ]
    names = []
    for s in structures:
        names += [k for k in fit(s, 0.0)["theta"] if k not in names]
    for k in names:
        cells = [
            fmt(fit(s, 0.0)["theta"][k]) if k in fit(s, 0.0)["theta"] else "" for s in structures
        ]
        refv = res["reference"]["theta"].get(k)
        L.append(
            f"| {k} ({res['units'][k]}) | "
            + " | ".join(cells)
            + f" | {'' if refv is None else f'{refv:.4g}'} |"
        )
    force = res["max_force_N"]
    pulse_N = res["pulse_V"] * res["gtau_N_per_V"]
    m = summary[sel]
    drift = {s: fit(s, 0.0)["edge_drift_mm"] for s in structures}
    with_mu = [s for s in structures if "mu" in fit(s, 0.0)["theta"]]
    without_mu = [s for s in structures if s not in with_mu]
    load_text = ""
    if with_mu and without_mu:
        d_with = float(np.mean([drift[s] for s in with_mu]))
        d_without = float(np.mean([drift[s] for s in without_mu]))
        load_text = (
            " A friction that grows with the transmitted force would slow the axis there; "
            f"the structures with the load term drift {d_with:+.3f} mm per edge on average, "
            f"those without it {d_without:+.3f} mm."
        )
        if sel not in with_mu:
            load_text += (
                " The folds do not select a structure with the load term: choosing one "
                "for the test record would take "
                "knowledge that the estimation record does not hold (where the models "
                "drift on the test record, or a prior on the drive's friction), so the "
                "test scores of the structures with it are not a blind result."
            )
    L += [
        "",
        "## What the estimation record can and cannot tell",
        "",
        f"The procedure's model, {short(sel)} "
        + (
            f"with the mean parameters of its {len(folds) + 1} fits, scores "
            f"{m['averaged']['protocol']['rmse_mm']:.3f} mm"
            if res["final"] == "mean"
            else f"fitted on the whole estimation record, scores {m['test_whole_mm']:.3f} mm"
        )
        + " on the test record; its selection and training use the estimation record "
        f"only. The selected structure's {len(folds) + 1} fits score "
        f"{m['test_mean_mm']:.2f} mm on average, from {m['test_min_mm']:.2f} to "
        f"{m['test_max_mm']:.2f} mm; the model with their mean parameters "
        f"{m['averaged']['protocol']['rmse_mm']:.3f} mm (leaving one fit out of the "
        f"mean: {_spread(m)} mm)"
        + (
            ", a gain on the test record that the estimation record does not show."
            if res["final"] == "whole"
            else "."
        ),
        "",
    ]

    def n_params(structure):
        return sum(np.size(v) for v in fit(structure, 0.0)["theta"].values())

    richest = max(structures, key=n_params)
    if richest != sel:
        r = summary[richest]
        rank = sorted(structures, key=lambda s: summary[s]["cv_mm"]).index(richest) + 1
        train_richest = fit(richest, 0.0)["rmse_train_mm"]
        train_sel = fit(sel, 0.0)["rmse_train_mm"]
        L += [
            f"The structure with the most parameters, {short(richest)}, fits the whole estimation "
            f"record {'better' if train_richest < train_sel else 'no better'} than the "
            f"selected one ({train_richest:.3f} mm against {train_sel:.3f} mm) and ranks "
            f"{rank} of {len(structures)} on the folds ({r['cv_mm']:.3f} mm). Fitted on "
            f"the whole record it scores {r['test_whole_mm']:.3f} mm on the test record, "
            f"and its {len(folds) + 1} fits {r['test_mean_mm']:.2f} mm on average (from "
            f"{r['test_min_mm']:.2f} to {r['test_max_mm']:.2f} mm)"
            + (
                ": better on the test record, a choice that the estimation record's "
                "held-out parts do not make."
                if r["test_whole_mm"] < summary[sel]["test_whole_mm"]
                else ", no better on the test record than the selected structure."
            ),
            "",
        ]
    L += [
        "The estimation record has no force pulses: its motor force stays within "
        f"{force['estimation']:.0f} N, while the test record adds pulses of "
        f"{res['pulse_V']:g} V (about {pulse_N:.0f} N) every second that the controller "
        f"compensates (its force reaches {force['test']:.0f} N). Across each pulse edge "
        f"(from {EDGE_SPAN[0]} samples before to {EDGE_SPAN[1]} after), the simulation "
        "error of the whole-record fits changes on average by "
        + ", ".join(f"{drift[s]:+.3f} mm ({short(s)})" for s in structures)
        + " in the direction of motion (> 0: the model runs ahead of the axis after the "
        "pulses switch)." + load_text,
        "",
        "The open-loop simulation integrates force errors: a constant error of 0.1 N "
        f"makes the simulated axis drift by {1e2 / fit(sel, 0.0)['theta']['Fv']:.2f} mm/s "
        "(0.1 N / Fv of the selected fit), so a test RMSE of a few mm needs the friction "
        "right to a few hundredths of a newton on average over the record. Refitting on "
        "a slightly different span moves the test score by millimetres, far more than "
        "the parameters' standard errors suggest (the residuals are a model error, not "
        "white noise). Reaching the about 2.6 mm of dynoNet with a physical model would "
        "need the force-dependent friction identified on an estimation record that "
        "exercises the test's force range (or a friction "
        f"law that predicts it), rather than extrapolated from {force['estimation']:.0f} N.",
        "",
        f"The run took {res['total_time_s']:.0f} s.",
    ]
    return "\n".join(L) + "\n"
