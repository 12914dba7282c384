"""EMPS benchmark: grey-box identification of M, Fv, Fc and offset from the real records.

The models, the data preparation and the figure of merit are `oneshot_jax.examples.emps`.
Both structures are fitted with the multi-step (simulation-error) loss, M, Fv, Fc >= 1e-6
by a box constraint, and the configured solver (Levenberg-Marquardt by default):

- **open loop**: input tau = gtau * vir (the recorded force command), state (q, q'),
  observed q. The plant is a double integrator, so the record is cut into windows of T
  samples, each with its own initial state (q, q') estimated (initial guess: qm and a
  central difference of qm). A sweep over T.
- **closed loop**: input the reference qg through the benchmark's known PD controller,
  observed q; windows of T samples with (q, q') per window estimated and the controller's
  delay line (q[k-1], q[k-2]) taken from qm, up to the whole record. A sweep over T.

Every parameter set, and the benchmark's IDIM-LS reference, is then simulated in the same
closed-loop simulator on both records (the validation record `DATA_EMPS_PULSES.mat` with
its force pulses) and scored with the benchmark's relative error (eq. 11). The structure
and window kept are those with the smaller relative position error on the *estimation*
record (the validation record is used for scoring only).

Run: `python experiments/run.py experiment=emps`; figures in `emps_plots.py`, the tables in
`emps_report.py`.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

import oneshot_jax as oj
from oneshot_jax.examples import emps as example

from . import common
from .config import ConfigError, as_dict

PARAMS = example.PARAMS


def _box():
    return oj.constraints.box(lower=example.LOWER)


def _row(res, n_windows, T, total_time):
    """The JSON-friendly summary of one fit."""
    return {
        "theta": {k: float(res.theta[k]) for k in PARAMS},
        "std": {k: float(res.std[k]) for k in PARAMS},
        "loss": float(res.loss),
        "iterations": int(res.num_steps),
        "stop_reason": res.status,
        "success": bool(res.success),
        "wall_time_s": float(res.wall_time),
        "total_time_s": float(total_time),
        "window": int(T),
        "n_windows": int(n_windows),
        "rmse_fit": [float(v) for v in np.atleast_1d(res.metrics["rmse"])],
    }


def fit_open_loop(data, T, ex, solver, progress=False) -> dict:
    """Open-loop windows of T samples (None: the whole record) of the first
    `ex.n_samples` estimation samples, input gtau * vir, each window's (q0, q0')
    estimated. Returns the fit's summary row."""
    rec = example.trim(data.estimation, ex.n_samples)
    model = example.open_loop_model(data.Ts, ex.eps, ex.substeps)
    u, z, x0 = example.open_loop_data(rec, data.gtau, data.Ts, T, ex.velocity_halfwidth)
    t0 = time.perf_counter()
    res = oj.fit(
        model,
        dict(ex.theta0),
        x0,
        u,
        z,
        solver=solver,
        constraints=_box(),
        progress=progress,
        history=ex.history,
    )
    return _row(res, u.shape[0], u.shape[1], time.perf_counter() - t0)


def fit_closed_loop(data, T, ex, solver, constrained=True, progress=False) -> dict:
    """Closed loop driven by qg on windows of T samples (None: the whole record), with
    (q0, q0') estimated per window and the delay line taken from qm. Only the position is
    fitted (the force channel has weight 0; it is simulated for the report)."""
    rec = example.trim(data.estimation, ex.n_samples)
    model = example.closed_loop_model(data.Ts, data.kp, data.kv, data.gtau, ex.eps, ex.substeps)
    u, z, x0 = example.closed_loop_data(rec, data.Ts, T, ex.velocity_halfwidth)
    # The weight normalises q to micrometres, so that the loss is O(1).
    weight = np.array([1e12, 0.0])
    t0 = time.perf_counter()
    res = oj.fit(
        model,
        dict(ex.theta0),
        x0,
        u,
        z,
        solver=solver,
        constraints=_box() if constrained else None,
        weight=weight,
        estimate_x0=np.array([True, True, False, False]),
        progress=progress,
        history=ex.history,
    )
    out = _row(res, u.shape[0], u.shape[1], time.perf_counter() - t0)
    out["rmse_fit"] = out["rmse_fit"][:1]
    return out


def score(data, theta, ex) -> dict:
    """Relative errors (%) of position and force in closed-loop simulation, both records,
    and the position RMSE (m)."""
    out = {}
    for name, rec in (("estimation", data.estimation), ("validation", data.validation)):
        q, vir = example.simulate_closed_loop(data, rec, theta, ex.eps, ex.substeps)
        out[name] = {
            "relerr_position_pct": example.relative_error(q, rec.qm),
            "relerr_force_pct": example.relative_error(vir, rec.vir),
            "rmse_position_m": float(oj.metrics.rmse(rec.qm, q)[0]),
        }
    return out


def _protocol(data, theta, ex) -> dict:
    """The protocol scores of one parameter set (position in mm)."""
    pred, sc = example.protocol_prediction(data, theta, ex.eps, ex.substeps)
    return common.protocol_scores(sc, pred, "mm")


def _sweep(data, ex, solver, n_used, progress):
    fitters = {"open_loop": fit_open_loop, "closed_loop": fit_closed_loop}
    sweeps = {"open_loop": [], "closed_loop": []}
    for fam in sweeps:
        for T in getattr(ex, fam).windows:
            if T is not None and T > n_used:
                continue  # (left out: `run` says so)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                row = fitters[fam](data, T, ex, solver, progress=progress)
            row["scores"] = score(data, row["theta"], ex)
            sweeps[fam].append(row)
            th, sc = row["theta"], row["scores"]
            print(
                f"  {fam:<11} T = {row['window']:>5} ({row['n_windows']:>4} windows) "
                f"{row['stop_reason']:<17} {row['iterations']:>3} steps "
                f"{row['total_time_s']:6.1f} s | "
                + " ".join(f"{k} {th[k]:9.4f}" for k in PARAMS)
                + f" | position relerr est {sc['estimation']['relerr_position_pct']:.6f} %"
                + f" val {sc['validation']['relerr_position_pct']:.6f} %",
                flush=True,
            )
    return {fam: rows for fam, rows in sweeps.items() if rows}, fitters


def run(cfg, outdir, command="python experiments/run.py experiment=emps") -> dict:
    """Fit both structures over the window sweep, score them, write figures and
    results.md into `outdir`; `cfg` is the validated `config.Config`."""
    ex = cfg.experiment
    solver, outdir, t_start = common.start(cfg, outdir, "EMPS")
    data = oj.datasets.load_emps(ex.data_path)
    n_used = (
        len(data.estimation) if ex.n_samples is None else min(ex.n_samples, len(data.estimation))
    )
    print(
        f"EMPS: {n_used} estimation samples at Ts = {data.Ts} s; kp = {data.kp}, kv = {data.kv}, "
        f"gtau = {data.gtau:.4f}; tanh(q'/eps) with eps = {ex.eps} m/s; solver {cfg.solver.title}",
        flush=True,
    )
    # Windows longer than the record (known only now) are left out, and said so (a quick
    # run on fewer samples keeps the shorter ones); none left is a configuration error
    # before any fit (it was a traceback after the data were loaded).
    skipped = {
        fam: [T for T in getattr(ex, fam).windows if T is not None and T > n_used]
        for fam in ("open_loop", "closed_loop")
    }
    if not any(T is None or T <= n_used for fam in skipped for T in getattr(ex, fam).windows):
        raise ConfigError(
            f"`experiment.open_loop.windows` and `experiment.closed_loop.windows` must hold a "
            f"window of at most the {n_used} estimation samples used (or None, the whole "
            f"record, in closed_loop), got {list(ex.open_loop.windows)} and "
            f"{list(ex.closed_loop.windows)}: lower the windows or raise experiment.n_samples."
        )
    for fam, Ts in skipped.items():
        if Ts:
            print(f"  {fam}: windows {Ts} longer than the {n_used} samples left out", flush=True)
    sweeps, fitters = _sweep(data, ex, solver, n_used, cfg.progress)

    # Within each structure and between them: the smallest closed-loop relative position
    # error on the estimation record (validation is for scoring only).
    def key(r):
        return r["scores"]["estimation"]["relerr_position_pct"]

    best = {fam: min(rows, key=key) for fam, rows in sweeps.items()}
    chosen_fam = min(best, key=lambda f: key(best[f]))
    chosen = dict(best[chosen_fam])
    chosen["structure"] = chosen_fam
    chosen["label"] = f"{chosen_fam.replace('_', ' ')} fit, T = {chosen['window'] * data.Ts:g} s"
    ref_scores = score(data, example.REFERENCE, ex)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        # Compute time of the kept fit once compiled: the same call again.
        T_kept = None if chosen["window"] >= n_used else chosen["window"]
        t0 = time.perf_counter()
        fitters[chosen_fam](data, T_kept, ex, solver, progress=cfg.progress)
        chosen["warm_time_s"] = time.perf_counter() - t0
        # The closed-loop position-only fit without constraints (reported, never kept).
        unconstrained = None
        if ex.check_unconstrained:
            unconstrained = fit_closed_loop(data, None, ex, solver, constrained=False)
            unconstrained["scores"] = score(data, unconstrained["theta"], ex)

    # The community's protocol (Champneys et al. 2024): open loop, u = vir, y = qm in mm,
    # x0 from the first 20 test outputs, scored on the rest.
    protocol = {"reference": _protocol(data, example.REFERENCE, ex)}
    for fam, row in best.items():
        protocol[fam] = _protocol(data, row["theta"], ex)

    rel_dev = {
        k: 100.0 * (chosen["theta"][k] - example.REFERENCE[k]) / abs(example.REFERENCE[k])
        for k in PARAMS
    }
    figures = []
    if ex.figures:
        from . import emps_plots

        figures = emps_plots.figures(data, chosen, ex, outdir, sweeps)
    out = {
        "benchmark": "EMPS",
        "command": command,
        "solver": as_dict(cfg.solver),
        "eps_m_per_s": float(ex.eps),
        "n_estimation_samples": int(n_used),
        "Ts_s": data.Ts,
        "units": example.UNITS,
        "reference": {"theta": example.REFERENCE, "scores": ref_scores},
        "sweeps": sweeps,
        "windows_left_out": {fam: Ts for fam, Ts in skipped.items() if Ts},
        "best": best,
        "chosen": chosen,
        "deviation_from_reference_pct": rel_dev,
        "closed_loop_unconstrained": unconstrained,
        "protocol": protocol,
        "pulse_gain_V_per_unit": example.pulse_voltage(data.validation, data.kp, data.kv, data.Ts)[
            1
        ],
        "figures": figures,
        "total_time_s": time.perf_counter() - t_start,
    }
    out = common.to_jsonable(out)
    from . import emps_report

    md = emps_report.markdown(out)
    (outdir / "results.md").write_text(md)
    print(md.split("![")[0])
    return out
