"""Cascaded tanks benchmark: Torricelli grey-box models with and without overflow.

The models (basic and overflow, and the quadratic sensor), their bounds and the
published results are `oneshot_jax.examples.cascaded_tanks`. Both records start from the
same unknown state (benchmark description, Sec. 3): x0 is estimated on the estimation
record and reused, unchanged, to simulate the validation record. The figure of merit is
the RMS simulation error on validation (eq. 4). The basic model is fitted from a rough
physical guess; the overflow model starts from the basic estimate and from the rough
guess, with a multistart over the overflow level h1 from each; with `sensor`, the
overflow model with the quadratic sensor (c2) starts from the overflow estimate and
c2 = 0. The solver is the configured one (Levenberg-Marquardt by default).

Run: `python experiments/run.py experiment=cascaded_tanks`; figures in
`cascaded_tanks_plots.py`, the tables in `cascaded_tanks_report.py`.
"""

from __future__ import annotations

import time
import warnings

import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj
from oneshot_jax.examples import cascaded_tanks as example

from . import common
from .config import as_dict


def make_model(kind, data, ex, substeps=None):
    """The example model of `kind` with the experiment's substeps and smoothing."""
    substeps = getattr(ex, kind).substeps if substeps is None else substeps
    return example.model(kind, data.Ts, substeps, ex.gate_width, ex.relu_width)


def fit_model(kind, data, ex, theta0, x0, solver, n=None, multistart=False, progress=False):
    """Fit one model on the first n estimation samples; with `multistart` the theta0
    leaves carry a leading axis of starts. Returns the `FitResult` and the model."""
    model = make_model(kind, data, ex)
    n = len(data.u_est) if n is None else int(n)
    u, y = data.u_est[:n, None], data.y_est[:n, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        res = oj.fit(
            model,
            theta0,
            np.asarray(list(x0), float),
            u,
            y,
            solver=solver,
            constraints=example.constraints(kind),
            multistart=bool(multistart),
            progress=progress,
            history=ex.history,
        )
    return res, model


def fit_overflow(data, ex, basic_theta, basic_x0, solver, n=None, progress=False):
    """The overflow model from `ex.overflow.theta0` (h2, k5), multistart over the overflow
    level h1 (`ex.overflow.h1_starts`) from two origins: the basic estimate (basic_theta,
    basic_x0) and the rough guess (`ex.basic.theta0`, `ex.x0`); the start of the least
    loss is kept (`fit_model`). The basic model has no overflow: on a record where the
    tanks overflow often, its estimate can lie far from the overflow model's basin (on
    the first 768 samples, an upper-tank level above 30 V at the start)."""
    h1s = [float(h) for h in ex.overflow.h1_starts]
    origins = [
        ({k: float(v) for k, v in basic_theta.items()}, [float(v) for v in basic_x0]),
        ({k: float(v) for k, v in ex.basic.theta0.items()}, [float(v) for v in ex.x0]),
    ]
    thetas = [{**t, **dict(ex.overflow.theta0), "h1": h} for t, _ in origins for h in h1s]
    starts = {k: jnp.asarray([t[k] for t in thetas]) for k in thetas[0]}
    x0s = np.asarray([x for _, x in origins for _ in h1s])
    return fit_model("overflow", data, ex, starts, x0s, solver, n, True, progress)


def fit_sensor(data, ex, theta, x0, solver, n=None, progress=False):
    """The overflow model with the quadratic sensor, fitted from an overflow estimate
    (theta, x0) and c2 = 0 (`fit_model`)."""
    start = {**{k: float(v) for k, v in theta.items()}, "c2": 0.0}
    return fit_model("overflow", data, ex, start, x0, solver, n, progress=progress)


def simulate(model, theta, x0, u):
    """The model output (T,) for a pump-voltage record u (T,)."""
    _, z = oj.simulate(model, theta, np.asarray(x0), np.asarray(u)[:, None])
    return np.asarray(z)[:, 0]


def protocol_prediction(model, theta, data, x0_guess):
    """The community's protocol (Champneys et al. 2024) on the validation record: x0 from
    its first n = 5 outputs only (`oneshot_jax.predict`, Gauss-Newton on x0), simulated
    over the whole record, scored on samples n: (`benchmark_scores`). Returns the
    `Prediction` and the scores."""
    test = data.test
    pred = oj.predict(
        model,
        theta,
        np.asarray(test.u)[:, None],
        np.asarray(test.y)[:, None],
        test.n,
        x0=np.asarray(x0_guess, float),
    )
    sc = oj.metrics.benchmark_scores(np.asarray(test.y)[:, None], np.asarray(pred.z), test.n)
    return pred, common.protocol_scores(sc, pred, "V")


def protocol(model, theta, data, x0_guess):
    """The protocol scores of `protocol_prediction`."""
    return protocol_prediction(model, theta, data, x0_guess)[1]


def _summary(res, model, data, kind, wall):
    y_est_sim = simulate(model, res.theta, res.x0, data.u_est)
    y_val_sim = simulate(model, res.theta, res.x0, data.u_val)  # the same initial state
    return {
        "model": kind,
        "theta": {k: float(v) for k, v in res.theta.items()},
        "std": {k: float(v) for k, v in res.std.items()},
        "x0": [float(v) for v in np.asarray(res.x0)],
        "x0_std": [float(v) for v in np.asarray(res.x0_std)],
        "rmse_estimation_V": float(oj.metrics.rmse(data.y_est, y_est_sim)[0]),
        "rmse_validation_V": float(oj.metrics.rmse(data.y_val, y_val_sim)[0]),
        "fit_percent_validation": float(oj.metrics.fit_percent(data.y_val, y_val_sim)[0]),
        "protocol": protocol(model, res.theta, data, res.x0),
        "stop_reason": common.from_fit(res).stop_reason,
        "iterations": int(res.num_steps),
        "wall_time_s": float(wall),
        "starts": None
        if res.starts is None
        else {"loss": [float(v) for v in np.asarray(res.starts.loss)], "best": int(res.best)},
        "_sim": (y_est_sim, y_val_sim),
    }


def run(cfg, outdir, command="python experiments/run.py experiment=cascaded_tanks") -> dict:
    """Fit the basic and the overflow model (and, with `ex.sensor`, the overflow model
    with the quadratic sensor), score them on validation, write figures and results.md
    into `outdir`; `cfg` is the validated `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "cascaded-tanks")
    data = oj.datasets.load_cascaded_tanks(ex.data_path)
    n = ex.n_samples
    print(
        f"Cascaded tanks: {len(data.u_est) if n is None else n} estimation samples, "
        f"Ts = {data.Ts} s, validation on {len(data.u_val)} samples; solver {cfg.solver.title}",
        flush=True,
    )

    rows = {}
    # 1. the basic model from a rough physical guess.
    t0 = time.perf_counter()
    res, model = fit_model(
        "basic", data, ex, dict(ex.basic.theta0), ex.x0, solver, n, progress=cfg.progress
    )
    rows["basic"] = _summary(res, model, data, "basic", time.perf_counter() - t0)

    # 2. the overflow model, multistart over the overflow level h1 from the basic estimate
    # and from the rough guess.
    t0 = time.perf_counter()
    res, model = fit_overflow(
        data, ex, rows["basic"]["theta"], rows["basic"]["x0"], solver, n, cfg.progress
    )
    rows["overflow"] = _summary(res, model, data, "overflow", time.perf_counter() - t0)
    rows["overflow"]["h1_starts"] = [float(h) for h in ex.overflow.h1_starts]

    # 3. the overflow model with the quadratic sensor, c2 from zero beside its estimate.
    if ex.sensor:
        t0 = time.perf_counter()
        res_s, model_s = fit_sensor(
            data, ex, rows["overflow"]["theta"], rows["overflow"]["x0"], solver, n, cfg.progress
        )
        rows["sensor"] = _summary(res_s, model_s, data, "sensor", time.perf_counter() - t0)

    # Integration check: the same parameters with twice the RK4 substeps.
    fine = make_model("overflow", data, ex, 2 * ex.overflow.substeps)
    y_fine = simulate(fine, res.theta, res.x0, data.u_val)
    rows["overflow"]["integration_check_max_abs_V"] = float(
        np.max(np.abs(y_fine - rows["overflow"]["_sim"][1]))
    )

    figures = []
    if ex.figures:
        from . import cascaded_tanks_plots

        figures = cascaded_tanks_plots.figures(data, rows, outdir)
    for r in rows.values():
        r.pop("_sim")
    out = {
        "benchmark": "cascaded_tanks",
        "command": command,
        "solver": as_dict(cfg.solver),
        "Ts_s": data.Ts,
        "n_estimation_samples": len(data.u_est) if n is None else int(n),
        "units": example.UNITS,
        "models": rows,
        "published_validation_rmse_V": example.PUBLISHED,
        "figures": figures,
        "total_time_s": time.perf_counter() - t_start,
    }
    out = common.to_jsonable(out)
    from . import cascaded_tanks_report

    md = cascaded_tanks_report.markdown(out)
    (outdir / "results.md").write_text(md)
    print(md.split("![")[0])
    return out
