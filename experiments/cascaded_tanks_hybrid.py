"""Cascaded tanks benchmark: the overflow model plus a neural residual (a hybrid model).

The physical part is the overflow model of `oneshot_jax.examples.cascaded_tanks`; an
`oneshot_jax.residual.MLP` r adds a correction to both level derivatives:

    x' = f_overflow(x, u; k1, k3, k4, h1, h2, k5) + s r(features; w),
    y = x2 + c + c2 (x2 - 5 V)^2     (the quadratic sensor; y = x2 + c with `sensor` off),

with the features the levels (x1, x2) (by default: the pump flow already enters the
physics, and a network of the levels alone stays closer to a correction of the outflows
and spills) or (x1, x2, u), centred and scaled by their mean and standard deviation on
the physical model's estimation trajectory, and the constant s the RMS of f_overflow
there (so that the network's outputs are of order one). The last layer starts at zero:
the hybrid starts as the physical model. theta = {k1, k3, k4, c, h1, h2, k5, c2, "r":
MLP}.

Training, in stages that each start where the last stopped (all through `oneshot_jax.fit`):

1. physics alone (the residual is zero): the basic model from a rough guess, then the
   overflow model from it and from the rough guess with a multistart over h1, then the
   sensor's c2 from zero (as `experiments/cascaded_tanks.py`, with the configured
   solver);
2. jointly: Adam on the one-shot gradient (cosine-decayed rate, optionally weight decay
   on the network, `sparsity.l2`), with a multistart over the network's initialisation;
3. a refinement by L-BFGS or Levenberg-Marquardt (or none).

With `residual.combine = "mean"` every start of the multistart is kept and refined: a
committee whose output is the mean of its members' outputs, each member simulating from
its own x0 (under the protocol: estimated from the first 5 test outputs with its own
parameters). Averaging models trained from different initialisations reduces the
variance of the prediction; the single start of the lowest final Adam loss is reported
beside it.

The physical bounds hold throughout. Evaluation follows the community protocol
(Champneys et al. 2024): train on the estimation record, simulate the validation record
from an x0 estimated from its first 5 outputs only, and score the RMS error on the rest.

Run: `python experiments/run.py experiment=cascaded_tanks_hybrid`; figures in
`cascaded_tanks_hybrid_plots.py`, the tables in `cascaded_tanks_hybrid_report.py`.
"""

from __future__ import annotations

import functools
import json
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import oneshot_jax as oj
from oneshot_jax import sparsity
from oneshot_jax.examples import cascaded_tanks as example
from oneshot_jax.residual import MLP, count_parameters

from . import cascaded_tanks, common
from .config import as_dict

PHYSICAL = tuple(example.UNITS)  # the physical parameters (the sensor's c2 included)
# The held-out scores of `cascaded_tanks_hybrid_select` (the configuration's choice on the
# estimation record), which the page reports against the physical stage.
SELECTION = Path(__file__).with_name("cascaded_tanks_hybrid_selection.json")
# The network's weights and biases (its activation is a function leaf, not a parameter).
NETWORK = sparsity.mask(lambda theta: theta["r"].layers)


class HybridRHS(eqx.Module):
    """x' = f_overflow(x, u) + theta["r"](features): the overflow model's right-hand side
    plus the network's correction of both level derivatives."""

    physics: example.OverflowRHS
    inputs: str = eqx.field(static=True)

    def features(self, x, u):
        """The network's input: (x1, x2, u) or (x1, x2)."""
        return jnp.concatenate([x, u]) if self.inputs == "states_and_input" else x

    def terms(self, x, u, theta):
        """(physical derivative, residual), each (2,), at one state and input."""
        return self.physics(x, u, theta), theta["r"](self.features(x, u))

    def __call__(self, x, u, theta):
        f, r = self.terms(x, u, theta)
        return f + r


def hybrid_model(data, ex) -> tuple[oj.Model, HybridRHS]:
    """The hybrid `Model` (RK4, `ex.substeps` steps per sample) and its right-hand side."""
    rhs = HybridRHS(example.OverflowRHS(ex.gate_width, ex.relu_width), ex.residual.inputs)
    model = oj.Model.from_ode(
        rhs, data.Ts, method="rk4", substeps=ex.substeps, observe=example.observe
    )
    return model, rhs


def make_network(rhs, ex, theta_phys, x0, u, Ts, key) -> MLP:
    """An MLP that starts at zero, its features normalised on the physical model's
    trajectory under the inputs u (T,) and its output scaled by the RMS of the physical
    derivative there."""
    phys = example.model("overflow", Ts, ex.overflow.substeps, ex.gate_width, ex.relu_width)
    xs, _ = oj.simulate(phys, theta_phys, np.asarray(x0), np.asarray(u)[:, None])
    xs = jnp.asarray(xs)
    uu = jnp.asarray(u)[:, None]
    feats = np.asarray(jax.vmap(rhs.features)(xs, uu))
    f = np.asarray(jax.vmap(lambda x, v: rhs.physics(x, v, theta_phys))(xs, uu))
    return MLP(
        feats.shape[1],
        2,
        tuple(ex.residual.widths),
        key=key,
        scale=float(np.sqrt(np.mean(f**2))),
        input_offset=feats.mean(0),
        input_scale=np.maximum(feats.std(0), 1e-6),
    )


def evaluate(model, theta, x0, data):
    """Estimation RMSE, validation RMSE from the estimation x0, and the protocol scores
    (x0 from the first 5 validation outputs), with the simulated and predicted signals."""
    z_est = cascaded_tanks.simulate(model, theta, x0, data.u_est)
    z_val = cascaded_tanks.simulate(model, theta, x0, data.u_val)
    pred, scores = cascaded_tanks.protocol_prediction(model, theta, data, x0)
    return {
        "rmse_estimation_V": float(oj.metrics.rmse(data.y_est, z_est)[0]),
        "rmse_validation_V": float(oj.metrics.rmse(data.y_val, z_val)[0]),
        "protocol": scores,
        "_pred": {"z": np.asarray(pred.z)[:, 0], "x": np.asarray(pred.x)},
    }


def evaluate_committee(model, members, data):
    """The scores of `evaluate` for a committee: the mean of the members' outputs, each
    member (theta, x0) simulated from its own estimation x0, and under the protocol from
    its own x0 estimated from the first 5 validation outputs only."""
    z_est = np.mean([cascaded_tanks.simulate(model, t, x, data.u_est) for t, x in members], 0)
    z_val = np.mean([cascaded_tanks.simulate(model, t, x, data.u_val) for t, x in members], 0)
    preds = [cascaded_tanks.protocol_prediction(model, t, data, x) for t, x in members]
    test = data.test
    z = np.mean([np.asarray(p.z) for p, _ in preds], 0)
    sc = oj.metrics.benchmark_scores(np.asarray(test.y)[:, None], z, test.n)
    return {
        "rmse_estimation_V": float(oj.metrics.rmse(data.y_est, z_est)[0]),
        "rmse_validation_V": float(oj.metrics.rmse(data.y_val, z_val)[0]),
        "protocol": {
            "n": int(sc.n),
            "rmse_V": float(sc.rmse[0]),
            "nrmse": float(sc.nrmse[0]),
            "r2": float(sc.r2[0]),
            "fit_percent": float(sc.fit_percent[0]),
            "members_rmse_V": [q["rmse_V"] for _, q in preds],
        },
        "_pred": {"z": z[:, 0]},
    }


def member(starts, like, k):
    """Start k of a multistart's parameters `starts` (`Starts.theta`: every array leaf
    with a leading axis of starts), its other parts (the activation) from `like`."""
    arrays = jax.tree_util.tree_map(lambda a: a[k], eqx.filter(starts, eqx.is_array))
    return eqx.combine(arrays, eqx.filter(like, eqx.is_array, inverse=True))


def _stack(trees):
    """One pytree whose array leaves carry a leading axis of starts (other parts shared)."""
    params = [eqx.filter(t, eqx.is_array) for t in trees]
    static = eqx.filter(trees[0], eqx.is_array, inverse=True)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *params)
    return eqx.combine(stacked, static)


def _fit(
    model, theta0, x0, u, y, solver, constraints, multistart, progress, history, reg=None, val=None
):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return oj.fit(
            model,
            theta0,
            np.asarray(x0, float),
            u,
            y,
            solver=solver,
            constraints=constraints,
            regulariser=reg,
            multistart=multistart,
            progress=progress,
            history=history,
            validation=val,
        )


def _stage(res, wall):
    return {
        "loss": float(res.loss),
        "iterations": int(res.num_steps),
        "stop_reason": res.status,
        "wall_time_s": float(wall),
    }


@functools.lru_cache
def _cosine(lr, steps):
    """Adam's rate, lr cosine-decayed to 1 % over `steps`: one schedule object per setting,
    so that another seed's fit reuses the compiled program (a schedule created anew is a
    new function, and `fit` compiles again)."""
    return optax.cosine_decay_schedule(lr, steps, alpha=1e-2)


@functools.lru_cache
def _decay(weight):
    """The network's weight decay: one object per weight, as `_cosine`."""
    return sparsity.l2(weight, where=NETWORK)


def split(data, ex) -> tuple[int, int]:
    """(n, m): the joint stages use the first n estimation samples, train on the first m
    and validate on the last n - m (`joint.holdout` of them)."""
    n = len(data.u_est) if ex.n_samples is None else int(ex.n_samples)
    return n, n - int(round(ex.joint.holdout * n))


def train_hybrid(data, ex, theta_phys, x0, seed, progress=False):
    """Stages 2 and 3 from the physical estimate (theta_phys, x0). Returns (FitResult of
    the start of the lowest final Adam loss, model, rhs, stage summaries, the
    multistart's final Adam losses, the committee): the committee (`residual.combine =
    "mean"`) is a list of every start's (theta, x0, final loss, stop reason of its last
    stage), each refined as the kept one, a start other than the kept one from its own
    x0 (Gauss-Newton on the training record with its parameters fixed,
    `oneshot_jax.predict`); None for "best"."""
    n, m = split(data, ex)
    jt = ex.joint
    u, y = data.u_est[:m, None], data.y_est[:m, None]
    val = None
    if m < n:
        val = oj.Validation(
            data.u_est[m:n, None],
            data.y_est[m:n, None],
            n=data.test.n,
            x0=np.asarray(x0, float),
            patience=jt.patience,
        )
    model, rhs = hybrid_model(data, ex)
    S = ex.residual.n_starts
    nets = [
        make_network(rhs, ex, theta_phys, x0, data.u_est[:n], data.Ts, k)
        for k in jax.random.split(jax.random.PRNGKey(seed), S)
    ]
    box = example.constraints("overflow")
    decay = _decay(float(jt.weight_decay)) if jt.weight_decay > 0 else None
    lr = _cosine(float(jt.lr), int(jt.adam_steps))
    adam = oj.Adam(lr, jt.lr_x0, max_steps=jt.adam_steps, scale=jt.scale)
    if S > 1:
        theta0 = {**{k: jnp.full((S,), v) for k, v in theta_phys.items()}, "r": _stack(nets)}
    else:
        theta0 = {**theta_phys, "r": nets[0]}
    t0 = time.perf_counter()
    res = _fit(model, theta0, x0, u, y, adam, box, S > 1, progress, ex.history, decay, val)
    stages = {"adam": _stage(res, time.perf_counter() - t0)}
    starts = None if res.starts is None else [float(v) for v in np.asarray(res.starts.loss)]
    adam_res = res
    if jt.refine != "none":
        cls = {"lbfgs": oj.LBFGS, "levenberg_marquardt": oj.LevenbergMarquardt}[jt.refine]

        def refine(theta, x0_k):
            return _fit(
                model,
                theta,
                x0_k,
                u,
                y,
                cls(max_steps=jt.refine_steps),
                box,
                False,
                progress,
                ex.history,
                val=val,
            )

        t0 = time.perf_counter()
        res = refine(res.theta, res.x0)
        stages[jt.refine] = _stage(res, time.perf_counter() - t0)
    committee = None
    if ex.residual.combine == "mean":
        committee = []
        for k in range(S):
            if k == adam_res.best:
                committee.append((res.theta, res.x0, float(res.loss), res.status))
                continue
            theta_k = member(adam_res.starts.theta, adam_res.theta, k)
            x0_k = oj.predict(model, theta_k, u, y, m, x0=np.asarray(adam_res.x0)).x0
            loss_k, stop_k = float(adam_res.starts.loss[k]), adam_res.status
            if jt.refine != "none":
                fit_k = refine(theta_k, x0_k)
                theta_k, x0_k, loss_k, stop_k = (
                    fit_k.theta,
                    fit_k.x0,
                    float(fit_k.loss),
                    fit_k.status,
                )
            committee.append((theta_k, x0_k, loss_k, stop_k))
    return res, model, rhs, stages, starts, committee


def fit_physics(data, ex, solver, progress=False):
    """Stage 1 on the first `ex.n_samples` estimation samples: the basic model from
    `ex.basic.theta0`, then the overflow model from it and from the rough guess,
    multistart over h1 (`cascaded_tanks.fit_overflow`), then (with `ex.sensor`) the
    quadratic sensor's c2 from zero beside the overflow model's estimate. Returns the
    last model's (FitResult, Model)."""
    n = ex.n_samples
    res, _ = cascaded_tanks.fit_model(
        "basic", data, ex, dict(ex.basic.theta0), ex.x0, solver, n, progress=progress
    )
    res, model = cascaded_tanks.fit_overflow(data, ex, res.theta, res.x0, solver, n, progress)
    if not ex.sensor:
        return res, model
    return cascaded_tanks.fit_sensor(data, ex, res.theta, res.x0, solver, n, progress)


def _seed_row(scores, stages, committee=None) -> dict:
    """One seed's scores (from `evaluate`, and `evaluate_committee` for a committee) and
    the iterations of its stages."""
    row = {
        "rmse_estimation_V": scores["rmse_estimation_V"],
        "rmse_test_V": scores["protocol"]["rmse_V"],
        "iterations": {k: v["iterations"] for k, v in stages.items()},
    }
    if committee is not None:
        row["committee_rmse_estimation_V"] = committee["rmse_estimation_V"]
        row["committee_rmse_test_V"] = committee["protocol"]["rmse_V"]
    return row


def _committee(model, members, data):
    """`evaluate_committee` of `train_hybrid`'s committee (None for none), with the
    members' final losses and stop reasons."""
    if members is None:
        return None
    out = evaluate_committee(model, [(t, x) for t, x, *_ in members], data)
    return {
        **out,
        "member_losses": [loss for _, _, loss, _ in members],
        "member_stops": [stop for *_, stop in members],
    }


def learned_terms(rhs, theta, x, u):
    """The physical derivative and the residual (each (T, 2), V/s) along states x (T, 2)
    under inputs u (T,)."""
    f, r = jax.vmap(lambda a, b: rhs.terms(a, b, theta))(jnp.asarray(x), jnp.asarray(u)[:, None])
    return np.asarray(f), np.asarray(r)


def run(cfg, outdir, command="python experiments/run.py experiment=cascaded_tanks_hybrid") -> dict:
    """Fit the physical model, then the hybrid; score both on validation under the
    protocol, write figures and results.md into `outdir`; `cfg` is the validated
    `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "cascaded-tanks hybrid")
    data = oj.datasets.load_cascaded_tanks(ex.data_path)
    n = ex.n_samples
    print(
        f"Cascaded tanks, hybrid: {len(data.u_est) if n is None else n} estimation samples, "
        f"Ts = {data.Ts} s; validation on {len(data.u_val)} samples, x0 from its first "
        f"{data.test.n}; physics stage: {cfg.solver.title}",
        flush=True,
    )

    # 1. physics alone: basic, then overflow (multistart over h1); the residual is zero.
    t0 = time.perf_counter()
    phys, phys_model = fit_physics(data, ex, solver, cfg.progress)
    theta_phys = {k: float(v) for k, v in phys.theta.items()}
    physical = {
        "theta": theta_phys,
        "x0": [float(v) for v in np.asarray(phys.x0)],
        "stage": _stage(phys, time.perf_counter() - t0),
        **evaluate(phys_model, phys.theta, phys.x0, data),
    }
    print(
        f"physical model: protocol RMSE {physical['protocol']['rmse_V']:.4f} V",
        flush=True,
    )

    # 2, 3. jointly: Adam (multistart over the network's initialisation), then refined.
    hyb, model, rhs, stages, adam_starts, members = train_hybrid(
        data, ex, theta_phys, phys.x0, cfg.seed, cfg.progress
    )
    hybrid = {
        "theta": {k: float(v) for k, v in hyb.theta.items() if k in PHYSICAL},
        "x0": [float(v) for v in np.asarray(hyb.x0)],
        "n_network_parameters": count_parameters(hyb.theta["r"]),
        "network_scale_V_per_s": float(hyb.theta["r"].scale),
        "stages": stages,
        "adam_start_losses": adam_starts,
        **evaluate(model, hyb.theta, hyb.x0, data),
    }
    # Integration check: the same parameters with twice the RK4 substeps.
    fine = oj.Model.from_ode(
        rhs, data.Ts, method="rk4", substeps=2 * ex.substeps, observe=example.observe
    )
    _, z_fine = oj.simulate(fine, hyb.theta, np.asarray(hyb.x0), data.u_val[:, None])
    _, z_val = oj.simulate(model, hyb.theta, np.asarray(hyb.x0), data.u_val[:, None])
    hybrid["integration_check_max_abs_V"] = float(np.max(np.abs(np.asarray(z_fine - z_val))))
    committee = _committee(model, members, data)
    print(
        f"hybrid model: estimation RMSE {hybrid['rmse_estimation_V']:.4f} V, protocol RMSE "
        f"{hybrid['protocol']['rmse_V']:.4f} V"
        + ("" if committee is None else f"; committee {committee['protocol']['rmse_V']:.4f} V"),
        flush=True,
    )

    # The same training from other seeds (network initialisations), the physics shared.
    seeds = [{"seed": cfg.seed, **_seed_row(hybrid, stages, committee)}]
    for seed in ex.extra_seeds:
        res_s, _, _, stages_s, _, members_s = train_hybrid(
            data, ex, theta_phys, phys.x0, seed, cfg.progress
        )
        row = _seed_row(
            evaluate(model, res_s.theta, res_s.x0, data),
            stages_s,
            _committee(model, members_s, data),
        )
        seeds.append({"seed": int(seed), **row})
        print(
            f"seed {seed}: protocol RMSE {row['rmse_test_V']:.4f} V"
            + (f"; committee {row['committee_rmse_test_V']:.4f} V" if members_s else ""),
            flush=True,
        )

    figures = []
    if ex.figures:
        from . import cascaded_tanks_hybrid_plots

        x = hybrid["_pred"]["x"][: len(data.u_val)]
        f, r = learned_terms(rhs, hyb.theta, x, data.u_val[: len(x)])
        figures = cascaded_tanks_hybrid_plots.figures(
            data, physical, hybrid, f, r, outdir, committee
        )
    for row in (physical, hybrid, committee or {}):
        row.pop("_pred", None)
    out = {
        "benchmark": "cascaded_tanks",
        "command": command,
        "solver": as_dict(cfg.solver),
        "config": as_dict(ex),
        "seed": cfg.seed,
        "Ts_s": data.Ts,
        "n_estimation_samples": len(data.u_est) if n is None else int(n),
        "n_train_samples": split(data, ex)[1],
        "units": example.UNITS,
        "physical": physical,
        "hybrid": hybrid,
        "committee": committee,
        "seeds": seeds,
        "figures": figures,
        "selection": json.loads(SELECTION.read_text()) if SELECTION.exists() else None,
        "total_time_s": time.perf_counter() - t_start,
    }
    out = common.to_jsonable(out)
    from . import cascaded_tanks_hybrid_report

    md = cascaded_tanks_hybrid_report.markdown(out)
    (outdir / "results.md").write_text(md)
    print(md.split("![")[0])
    return out
