"""EMPS with a hybrid friction model: the physical model plus a neural friction term.

The physical model of `oneshot_jax.examples.emps` (M q'' = tau - Fv q' - Fc sign(q') -
offset, sign(q') ~ tanh(q'/eps)) gets a learned friction force r added to its physical
friction,

    M q'' = tau - (Fv q' + Fc tanh(q'/eps) + offset) - r(q', q),

with r an `oneshot_jax.residual.MLP` of the velocity (`inputs: v`) or of the velocity and
the position (`inputs: qv`), its inputs normalised by the estimation record's standard
deviations and its output in newtons (`output_scale`). The network starts at zero, so the
hybrid starts as the physical model. Both are fitted on open-loop windows of the
estimation record (input tau = gtau vir, output qm, each window's (q, q') estimated), in
stages that each start where the last stopped, all through `oneshot_jax.fit`:

1. **physics**: M, Fv, Fc, offset alone (`fixed=` holds the network), with the configured
   solver (Levenberg-Marquardt by default) and M, Fv, Fc >= 1e-6 by a box constraint. This
   is the physical model the hybrid is compared with;
2. **joint, Adam**: everything, Adam with a cosine-decayed rate, weight decay on the
   network (`sparsity.l2`) when `adam.weight_decay > 0`;
3. **joint, Levenberg-Marquardt**: everything, from where Adam stopped.

Both models are then scored on the validation record (DATA_EMPS_PULSES.mat) with the
community's protocol, as `experiment=emps` scores its physical fits
(`oneshot_jax.examples.emps.protocol_prediction`): open-loop simulation with u = vir and
y = qm, x0 = (q, q') estimated from the first 20 test outputs only, RMSE in mm on the rest.

Run: `python experiments/run.py experiment=emps_hybrid`; tables in `emps_hybrid_report.py`,
figures in `emps_hybrid_plots.py`.
"""

from __future__ import annotations

import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import oneshot_jax as oj
from oneshot_jax import sparsity
from oneshot_jax.examples import emps as example
from oneshot_jax.residual import MLP, count_parameters

from . import common
from .config import as_dict

PARAMS = example.PARAMS
NETWORK = sparsity.mask(lambda theta: theta["r"].layers)
INPUTS = {"v": ("q'",), "qv": ("q", "q'")}
"""The network's inputs for each `inputs` option."""


class HybridPlant(eqx.Module):
    """d(q, q')/dt = (q', q'') with the physical friction of `example.acceleration` plus
    the learned force theta["r"] (N) of (q') or (q, q'); input u = (tau,) (N)."""

    eps: float = eqx.field(static=True, default=example.EPS)
    position: bool = eqx.field(static=True, default=False)

    def __call__(self, x, u, theta):
        features = x if self.position else x[1:]
        tau = u[0] - theta["r"](features)[0]
        return jnp.stack([x[1], example.acceleration(x[1], tau, theta, self.eps)])


def _position(x, u, theta):
    del u, theta
    return x[:1]


def hybrid_model(Ts, eps=example.EPS, substeps=1, inputs="v") -> oj.Model:
    """State (q, q'), input tau (N), output q: RK4 of `HybridPlant` (`inputs`: "v" for
    r(q'), "qv" for r(q, q'))."""
    plant = HybridPlant(float(eps), inputs == "qv")
    return oj.Model.from_ode(plant, Ts, substeps=int(substeps), observe=_position)


def friction_network(record, Ts, ex, key) -> MLP:
    """The friction MLP, zero at the start, its inputs centred and scaled by the record's
    position and velocity (central difference of qm), its output scaled to newtons."""
    v = example.velocity_estimate(record.qm, Ts, ex.velocity_halfwidth)
    offset, scale = [0.0], [float(np.std(v))]
    if ex.inputs == "qv":
        offset, scale = [float(np.mean(record.qm)), 0.0], [float(np.std(record.qm)), scale[0]]
    return MLP(
        len(offset),
        1,
        tuple(ex.widths),
        key=jax.random.PRNGKey(ex.seed),
        scale=float(ex.output_scale),
        input_offset=offset,
        input_scale=scale,
    )


def learned_force(theta, q, v):
    """The learned friction force r (N) at positions q and velocities v (arrays of one
    shape)."""
    net = theta["r"]
    q, v = np.broadcast_arrays(np.asarray(q, float), np.asarray(v, float))
    feats = np.stack([q, v], -1) if net.in_size == 2 else v[..., None]
    flat = jax.vmap(net)(jnp.asarray(feats.reshape(-1, net.in_size)))
    return np.asarray(flat)[:, 0].reshape(v.shape)


def physical_friction(theta, v, eps=example.EPS):
    """Fv q' + Fc tanh(q'/eps) + offset (N)."""
    v = np.asarray(v, float)
    return theta["Fv"] * v + theta["Fc"] * np.tanh(v / eps) + theta["offset"]


# --------------------------------------------------------------------------- stages


def _stage(name, res, t0):
    """The JSON-friendly summary of one stage."""
    return {
        "stage": name,
        "theta": {k: float(res.theta[k]) for k in PARAMS},
        "loss": float(res.loss),
        "rmse_fit_mm": float(1e3 * np.atleast_1d(res.metrics["rmse"])[0]),
        "iterations": int(res.num_steps),
        "stop_reason": res.status,
        "time_s": float(time.perf_counter() - t0),
    }


def train(data, ex, solver, progress=False):
    """The three stages on open-loop windows of the estimation record. Returns
    `(physics, joint, rows)`: the `FitResult`s of the physical stage and of the last
    joint stage, and the stages' summaries."""
    rec = example.trim(data.estimation, ex.n_samples)
    model = hybrid_model(data.Ts, ex.eps, ex.substeps, ex.inputs)
    u, z, x0 = example.open_loop_data(rec, data.gtau, data.Ts, ex.window, ex.velocity_halfwidth)
    # Position in mm in the loss: O(1) values, and a weight-decay strength in mm^2.
    weight = np.array([1e6])
    box = oj.constraints.box(lower=example.LOWER)
    theta0 = {**dict(ex.theta0), "r": friction_network(data.estimation, data.Ts, ex, ex.seed)}
    common_kw = dict(weight=weight, progress=progress, history=ex.history)
    rows = []
    with warnings.catch_warnings():
        # The network's directions are flat at the start (it is zero) and its parameters
        # are not identifiable one by one: fit warns about both.
        warnings.simplefilter("ignore", UserWarning)
        t0 = time.perf_counter()
        physics = oj.fit(
            model,
            theta0,
            x0,
            u,
            z,
            solver=solver,
            constraints=box,
            fixed={**{k: False for k in PARAMS}, "r": True},
            **common_kw,
        )
        rows.append(_stage("physics", physics, t0))
        res = physics
        if ex.adam.steps > 0:
            lr = optax.cosine_decay_schedule(ex.adam.lr, ex.adam.steps, alpha=1e-2)
            decay = None
            if ex.adam.weight_decay > 0:
                decay = sparsity.l2(ex.adam.weight_decay, where=NETWORK)
            t0 = time.perf_counter()
            res = oj.fit(
                model,
                res.theta,
                res.x0,
                u,
                z,
                solver=oj.Adam(lr, ex.adam.lr_x0, max_steps=ex.adam.steps),
                constraints=box,
                regulariser=decay,
                **common_kw,
            )
            rows.append(_stage("joint, Adam", res, t0))
        if ex.lm_steps > 0:
            t0 = time.perf_counter()
            res = oj.fit(
                model,
                res.theta,
                res.x0,
                u,
                z,
                solver=oj.LevenbergMarquardt(max_steps=ex.lm_steps),
                constraints=box,
                **common_kw,
            )
            rows.append(_stage("joint, Levenberg-Marquardt", res, t0))
    return physics, res, rows


def _protocol(data, theta, ex, model=None):
    """The protocol prediction and scores of one parameter set (position in mm)."""
    pred, sc = example.protocol_prediction(
        data, theta, ex.eps, ex.substeps, half=ex.velocity_halfwidth, model=model
    )
    return pred, common.protocol_scores(sc, pred, "mm")


def run(cfg, outdir, command="python experiments/run.py experiment=emps_hybrid") -> dict:
    """Train the physical and the hybrid model, score both with the protocol, write the
    figures and results.md into `outdir`; `cfg` is the validated `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "EMPS hybrid")
    data = oj.datasets.load_emps(ex.data_path)
    n_used = (
        len(data.estimation) if ex.n_samples is None else min(ex.n_samples, len(data.estimation))
    )
    if ex.window > n_used:
        raise ValueError(
            f"experiment.window = {ex.window} is longer than the {n_used} estimation samples "
            "used: lower it or raise experiment.n_samples."
        )
    print(
        f"EMPS hybrid: {n_used} estimation samples in windows of {ex.window}; friction MLP "
        f"r({', '.join(INPUTS[ex.inputs])}) widths {list(ex.widths)}; physics stage: "
        f"{cfg.solver.title}",
        flush=True,
    )
    physics, hybrid, stages = train(data, ex, solver, progress=cfg.progress)
    for row in stages:
        print(
            f"  {row['stage']:<27} {row['iterations']:>5} steps {row['time_s']:7.1f} s | "
            + " ".join(f"{k} {row['theta'][k]:9.4f}" for k in PARAMS)
            + f" | estimation RMSE {row['rmse_fit_mm']:.4f} mm ({row['stop_reason']})",
            flush=True,
        )

    theta_phys = {k: float(physics.theta[k]) for k in PARAMS}
    model = hybrid_model(data.Ts, ex.eps, ex.substeps, ex.inputs)
    pred_ref, prot_ref = _protocol(data, example.REFERENCE, ex)
    pred_phys, prot_phys = _protocol(data, theta_phys, ex)
    pred_hyb, prot_hyb = _protocol(data, hybrid.theta, ex, model=model)
    print(
        f"validation (protocol, RMSE of qm in mm over samples {prot_phys['n']}:): physical "
        f"{prot_phys['rmse_mm']:.4f} mm, physics + NN friction {prot_hyb['rmse_mm']:.4f} mm "
        f"(IDIM-LS reference parameters {prot_ref['rmse_mm']:.4f} mm)",
        flush=True,
    )

    v = example.velocity_estimate(data.estimation.qm, data.Ts, ex.velocity_halfwidth)
    v_val = example.velocity_estimate(data.validation.qm, data.Ts, ex.velocity_halfwidth)
    v_grid = np.linspace(-np.max(np.abs(v)), np.max(np.abs(v)), 401)
    q_mid = float(np.mean(data.estimation.qm))
    r_grid = learned_force(hybrid.theta, q_mid, v_grid)
    figures = []
    if ex.figures:
        from . import emps_hybrid_plots

        figures = emps_hybrid_plots.figures(
            data,
            ex,
            outdir,
            preds={"physical": pred_phys, "hybrid": pred_hyb},
            scores={"physical": prot_phys, "hybrid": prot_hyb},
            theta_phys=theta_phys,
            theta_hybrid=hybrid.theta,
        )
    out = {
        "benchmark": "EMPS",
        "command": command,
        "solver": as_dict(cfg.solver),
        "config": as_dict(ex),
        "n_estimation_samples": int(n_used),
        "n_windows": int(n_used // ex.window),
        "Ts_s": data.Ts,
        "units": example.UNITS,
        "network": {
            "inputs": list(INPUTS[ex.inputs]),
            "widths": list(ex.widths),
            "parameters": count_parameters(hybrid.theta["r"]),
            "output_scale_N": float(ex.output_scale),
        },
        "stages": stages,
        "physical": {"theta": theta_phys, "protocol": prot_phys},
        "hybrid": {
            "theta": {k: float(hybrid.theta[k]) for k in PARAMS},
            "protocol": prot_hyb,
            "learned_force_N": {
                "q_m": q_mid,
                "v_max_m_per_s": float(v_grid[-1]),
                "v_max_validation_m_per_s": float(np.max(np.abs(v_val))),
                "max_abs": float(np.max(np.abs(r_grid))),
                "at_zero_velocity": float(learned_force(hybrid.theta, q_mid, 0.0)),
            },
        },
        "reference": {"theta": example.REFERENCE, "protocol": prot_ref},
        "improvement_pct": 100.0 * (1.0 - prot_hyb["rmse_mm"] / prot_phys["rmse_mm"]),
        "figures": figures,
        "total_time_s": time.perf_counter() - t_start,
    }
    out = common.to_jsonable(out)
    from . import emps_hybrid_report

    md = emps_hybrid_report.markdown(out)
    (outdir / "results.md").write_text(md)
    print(md.split("![")[0])
    return out
