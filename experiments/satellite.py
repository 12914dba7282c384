"""The satellite case study of Section 4 (Figs. 2-6 and the numbers behind them).

Euler's equations for a rigid body with diagonal inertia I = diag(theta),

    I w' = M - w x (I w),        z_k = w(k dt) + e_k,   e_k ~ N(0, sigma_w^2 I_3),

sampled every dt = 0.1 s, with the torque M_k ~ N(1e-5, (1e-7)^2) per axis and sample a
known input (zero-order hold). theta and x0 = w(0) are estimated from tentative values by
minimising the multi-step cost C (eq. 5) with theta_i > 0 by projection.

Data are generated in numpy (classical RK4 with `data_substeps` steps per sample,
independent of the library's integrator); the identification model is
`oneshot_jax.Model.from_ode` (RK4, `model_substeps` per sample). Each seed draws its own
torque and noise sequences (two independent streams spawned from the seed), so a record
of n samples is a prefix of any longer record of the same seed.

`run(cfg, outdir)` does, for the proposed method (the `solver` config) and the baselines
listed in `experiment.methods`:

- Fig. 2: C over two components of theta (the third and x0 at the estimate), with the
  optimisation path of the main fit drawn on it.
- Fig. 3: theta-hat_i against epoch for `fig3.n_starts` initial conditions.
- Fig. 4: w-hat(t) over [0, `simulate_time`] for the proposed method, the one-step
  prediction-error grey-box fit, the multi-step and single-step SLSQP fits with
  finite-difference gradients, and the true trajectory.
- Fig. 5: ||theta-hat - theta||_2 over `n_seeds` noise draws (box plots) per method.
- Fig. 6: estimation error and time against the horizon T, with the Cramer-Rao bound.
- `results.md`: the tables and a discussion computed from the measurements.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj

from . import common

AXES = ("x", "y", "z")
PAPER_THETA_HAT_T50 = (0.0398, 0.0389, 0.0076)
FIGURES = {
    "fig2": "fig2_loss_landscape.png",
    "fig3": "fig3_parameter_evolution.png",
    "fig4": "fig4_trajectories.png",
    "fig5": "fig5_estimation_error.png",
    "fig6": "fig6_horizon.png",
}


# ------------------------------------------------------------------------------ physics


def euler_rhs(w, M, theta):
    """w' = I^{-1} (M - w x (I w)), I = diag(theta["I"])."""
    inertia = theta["I"]
    return (M - jnp.cross(w, inertia * w)) / inertia


def _rhs_np(w, M, inertia):
    return (M - np.cross(w, inertia * w)) / inertia


def make_model(ex) -> oj.Model:
    return oj.Model.from_ode(euler_rhs, float(ex.dt), method="rk4",
                             substeps=int(ex.model_substeps))


def simulate_np(inertia, w0, M, dt, substeps):
    """Batched RK4 with a zero-order-hold input: inertia, w0 (B, 3), M (B, n, 3) ->
    w (B, n, 3) with w[:, 0] = w0."""
    inertia = np.asarray(inertia, dtype=np.float64)
    w = np.array(w0, dtype=np.float64)
    M = np.asarray(M, dtype=np.float64)
    n = M.shape[1]
    h = dt / substeps
    out = np.empty(M.shape)
    out[:, 0] = w
    for k in range(n - 1):
        m = M[:, k]
        for _ in range(substeps):
            k1 = _rhs_np(w, m, inertia)
            k2 = _rhs_np(w + 0.5 * h * k1, m, inertia)
            k3 = _rhs_np(w + 0.5 * h * k2, m, inertia)
            k4 = _rhs_np(w + h * k3, m, inertia)
            w = w + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out[:, k + 1] = w
    return out


def generate(ex, seeds, n) -> dict:
    """Records of n samples for each seed: torque `u`, true state `x`, measurement `z`,
    each (S, n, 3). Deterministic given the seed."""
    us, es = [], []
    for seed in seeds:
        streams = np.random.SeedSequence(int(seed)).spawn(2)
        rng_u, rng_e = (np.random.default_rng(s) for s in streams)
        us.append(float(ex.torque_mean) + float(ex.torque_std) * rng_u.standard_normal((n, 3)))
        es.append(float(ex.noise_std) * rng_e.standard_normal((n, 3)))
    u = np.stack(us)
    S = len(seeds)
    theta = np.broadcast_to(np.asarray(ex.theta_true, dtype=np.float64), (S, 3))
    w0 = np.broadcast_to(np.asarray(ex.w0, dtype=np.float64), (S, 3))
    x = simulate_np(theta, w0, u, float(ex.dt), int(ex.data_substeps))
    return {"u": u, "x": x, "z": x + np.stack(es), "t": float(ex.dt) * np.arange(n)}


def crb_rmse(ex, u, horizons) -> tuple[dict, dict]:
    """Cramer-Rao bound on the RMS of ||theta-hat - theta||_2 for each horizon T.

    Fisher information F_T = J_T^T J_T / sigma^2 with J_T = d(z_0..z_{T-1}) / d(theta, x0)
    at the true values (central differences of the noise-free numpy simulation), so that
    E||theta-hat - theta||^2 >= trace([F_T^{-1}]_theta) for an unbiased estimator with x0
    unknown. Averaged over the torque sequences of the seeds: sqrt(mean_s trace). Returns
    ({T: RMS bound}, {T: per-component standard deviations}).
    """
    horizons = sorted({int(T) for T in horizons})
    n = max(horizons)
    theta = np.asarray(ex.theta_true, dtype=np.float64)
    w0 = np.asarray(ex.w0, dtype=np.float64)
    S = u.shape[0]
    p0 = np.concatenate([theta, w0])
    h = np.concatenate([1e-6 * np.abs(theta), np.full(3, 1e-9)])
    P = p0.size
    plus = np.repeat(p0[None], P, 0) + np.diag(h)
    minus = np.repeat(p0[None], P, 0) - np.diag(h)
    pts = np.concatenate([plus, minus])  # (2P, 6)
    B = np.repeat(pts[None], S, 0).reshape(S * 2 * P, P)
    U = np.repeat(u[:, None, :n], 2 * P, 1).reshape(S * 2 * P, n, 3)
    xs = simulate_np(B[:, :3], B[:, 3:], U, float(ex.dt), int(ex.data_substeps))
    xs = xs.reshape(S, 2, P, n, 3)
    J = (xs[:, 0] - xs[:, 1]) / (2 * h[None, :, None, None])  # (S, P, n, 3)
    J = np.transpose(J, (0, 2, 3, 1))  # (S, n, 3, P)
    per_k = np.einsum("snip,sniq->snpq", J, J) / float(ex.noise_std) ** 2
    F = np.cumsum(per_k, axis=1)  # F[:, T-1] is the information of the first T samples
    rmse, std = {}, {}
    for T in horizons:
        var = np.mean(np.diagonal(np.linalg.inv(F[:, T - 1]), axis1=1, axis2=2), axis=0)
        rmse[T] = float(np.sqrt(np.sum(var[:3])))
        std[T] = np.sqrt(var[:3])
    return rmse, std


def one_step_windows(u, z):
    """The one-step-ahead problem as T-1 two-sample trajectories started at the measured
    state: C = mean_k ||z_{k+1} - f(z_k, u_k, theta)||^2 / 2 (x0 = z_k is not estimated)."""
    U = np.stack([u[:-1], u[1:]], axis=1)
    Z = np.stack([z[:-1], z[1:]], axis=1)
    return U, Z, z[:-1].copy()


@eqx.filter_jit
def _loss_grid(model, grid, x0, u, z):
    return jax.vmap(lambda inertia: oj.loss(model, {"I": inertia}, x0, u, z))(grid)


# ------------------------------------------------------------------------------- driver


def _methods(cfg):
    """The proposed method and the configured baselines: id -> spec (label, cost, solver).
    A baseline that is the proposed method with the same settings is an alias of it."""
    ex = cfg.experiment
    main_solver = common.plain(cfg.solver)
    label = main_solver.get("label") or main_solver["name"]
    methods = {"proposed": {"label": f"proposed: {label}", "cost": "multi_step",
                            "solver": main_solver}}
    aliases = {}
    wanted = common.plain(ex.get("run_methods"))
    for key, spec in common.plain(ex.methods).items():
        if wanted is not None and key not in wanted:
            continue
        if spec["cost"] not in ("multi_step", "single_step"):
            raise ValueError(f"method {key}: cost must be multi_step or single_step.")
        common.solver_spec(spec["solver"])
        if spec["cost"] == "multi_step" and common.same_solver(spec["solver"], main_solver):
            aliases[key] = "proposed"
            continue
        methods[key] = spec
    return methods, aliases


def _init(ex, z_first):
    theta0 = np.asarray(ex.init.theta0, dtype=np.float64)
    x0 = ex.init.x0
    if isinstance(x0, str):
        if x0 != "first_sample":
            raise ValueError(f"experiment.init.x0 must be 'first_sample' or a list, got {x0!r}.")
        x0 = np.asarray(z_first, dtype=np.float64)
    return theta0, np.asarray(x0, dtype=np.float64)


class _Fitter:
    """Runs a method on one record; the first call of each (method, T) is repeated so
    that the reported time excludes compilation (the first time is kept as well)."""

    def __init__(self, model, constraints):
        self.model = model
        self.constraints = constraints
        self.first_call = {}

    def __call__(self, key, spec, u, z, theta0, x0, *, record=False):
        if spec["cost"] == "single_step":
            U, Z, X0 = one_step_windows(u, z)
            args = (U, Z, {"I": theta0}, X0)
            kw = dict(estimate_x0=False)
        else:
            args = (u, z, {"I": theta0}, x0)
            kw = {}
        tag = (key, u.shape[0], record)
        if tag not in self.first_call:
            t0 = time.perf_counter()
            common.solve(self.model, *args, spec["solver"], constraints=self.constraints,
                         record_path=record, **kw)
            self.first_call[tag] = time.perf_counter() - t0
        return common.solve(self.model, *args, spec["solver"], constraints=self.constraints,
                            record_path=record, **kw)


def run(cfg, outdir) -> dict:
    """Run the satellite study; figures and results.md go to `outdir`. Returns the
    results dict (written to results.json by experiments/run.py)."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    ex = cfg.experiment
    t_start = time.perf_counter()
    load_start = os.getloadavg()[0]
    stages = {}
    seed = int(cfg.seed)
    T = int(ex.T)
    dt = float(ex.dt)
    theta_true = np.asarray(ex.theta_true, dtype=np.float64)
    n_seeds = int(ex.n_seeds)
    horizons = sorted({int(h) for h in ex.horizons})
    n_h_seeds = min(int(ex.horizon_seeds), n_seeds) if horizons else 0
    seeds = [seed + i for i in range(max(n_seeds, n_h_seeds, 1))]
    n_sim = int(round(float(ex.simulate_time) / dt)) + 1
    n_total = max([T, n_sim, *horizons])

    model = make_model(ex)
    constraints = oj.constraints.positive(float(ex.theta_lower))
    methods, aliases = _methods(cfg)
    fitter = _Fitter(model, constraints)

    t0 = time.perf_counter()
    data = generate(ex, seeds, n_total)
    crb, crb_std = crb_rmse(ex, data["u"][:n_seeds], [T, *horizons])
    stages["data_and_crb_s"] = time.perf_counter() - t0

    # --- Monte Carlo at T: every method on every seed (Fig. 5, tables; seed 0: Fig. 4)
    t0 = time.perf_counter()
    mc = {key: [] for key in methods}
    for i in range(n_seeds):
        u, z = data["u"][i, :T], data["z"][i, :T]
        theta0, x0 = _init(ex, z[0])
        for key, spec in methods.items():
            mc[key].append(fitter(key, spec, u, z, theta0, x0))
    stages["monte_carlo_s"] = time.perf_counter() - t0

    # --- main fit with its path, and the other starts of Fig. 3 (seed `seed`, T)
    t0 = time.perf_counter()
    u, z = data["u"][0, :T], data["z"][0, :T]
    theta0, x0 = _init(ex, z[0])
    rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
    starts = [(theta0, x0)]
    spread = float(ex.fig3.spread)
    for _ in range(int(ex.fig3.n_starts) - 1):
        th = theta_true * (1.0 + spread * rng.uniform(-1.0, 1.0, 3))
        starts.append((th, z[0] + float(ex.noise_std) * rng.standard_normal(3)))
    runs = [fitter("proposed", methods["proposed"], u, z, th, xx, record=True)
            for th, xx in starts]
    main = runs[0]
    stages["paths_s"] = time.perf_counter() - t0

    # --- horizons (Fig. 6): the proposed method for each T on the first n_h_seeds seeds
    t0 = time.perf_counter()
    hor = {}
    for Th in horizons:
        ests = []
        for i in range(n_h_seeds):
            if Th == T:
                ests.append(mc["proposed"][i])
                continue
            uh, zh = data["u"][i, :Th], data["z"][i, :Th]
            th0, xx0 = _init(ex, zh[0])
            ests.append(fitter("proposed", methods["proposed"], uh, zh, th0, xx0))
        hor[Th] = ests
    stages["horizons_s"] = time.perf_counter() - t0

    # --- long simulations for Fig. 4 (seed `seed`)
    t0 = time.perf_counter()
    u_long = data["u"][0, :n_sim]
    x_true = data["x"][0, :n_sim]
    fig4_keys = ["proposed"] + [aliases.get(k, k) for k in (common.plain(ex.fig4_methods) or [])
                                if aliases.get(k, k) in methods]
    fig4_keys = list(dict.fromkeys(fig4_keys))
    sims = {}
    for key in fig4_keys:
        est = mc[key][0] if n_seeds else main
        start = z[0] if methods[key]["cost"] == "single_step" else est.x0
        xs, _ = oj.simulate(model, {"I": jnp.asarray(est.theta_flat)}, jnp.asarray(start),
                            jnp.asarray(u_long))
        sims[key] = np.asarray(xs)
    stages["simulations_s"] = time.perf_counter() - t0

    # --- summaries
    def err(est):
        return float(np.linalg.norm(est.theta_flat - theta_true))

    summary = {}
    for key, ests in mc.items():
        if not ests:
            continue
        e = np.array([err(s) for s in ests])
        tt = np.array([s.time_s for s in ests])
        it = np.array([s.iterations for s in ests])
        reasons = {}
        for s in ests:
            reasons[s.stop_reason] = reasons.get(s.stop_reason, 0) + 1
        summary[key] = {
            "label": methods[key]["label"], "cost": methods[key]["cost"],
            "solver": methods[key]["solver"],
            "errors": e, "rmse": float(np.sqrt(np.mean(e**2))), "median_error": float(np.median(e)),
            "median_time_s": float(np.median(tt)), "times_s": tt,
            "first_call_s": fitter.first_call.get((key, T, False)),
            "median_iterations": float(np.median(it)), "iterations": it,
            "n_success": int(sum(s.success for s in ests)), "n": len(ests),
            "stop_reasons": reasons, "theta_hat": np.stack([s.theta_flat for s in ests]),
        }
    horizon_summary = {}
    for Th, ests in hor.items():
        e = np.array([err(s) for s in ests])
        horizon_summary[Th] = {
            "errors": e, "rmse": float(np.sqrt(np.mean(e**2))), "crb_rmse": crb[Th],
            "median_time_s": float(np.median([s.time_s for s in ests])),
            "first_call_s": fitter.first_call.get(("proposed", Th, False)),
            "median_iterations": float(np.median([s.iterations for s in ests])),
            "theta_hat": np.stack([s.theta_flat for s in ests]),
            "n_success": int(sum(s.success for s in ests)),
        }
    sim_rmse = {k: float(np.sqrt(np.mean((v - x_true) ** 2))) for k, v in sims.items()}
    train_rmse = {k: float(np.sqrt(np.mean((v[:T] - x_true[:T]) ** 2))) for k, v in sims.items()}

    # --- figures
    t0 = time.perf_counter()
    from . import satellite_plots as plots

    figs = []
    if ex.get("figures", True):
        figs.append(plots.fig2(outdir / FIGURES["fig2"], model, ex, main, u, z, _loss_grid))
        figs.append(plots.fig3(outdir / FIGURES["fig3"], runs, theta_true,
                               methods["proposed"]["label"]))
        figs.append(plots.fig4(outdir / FIGURES["fig4"], data["t"][:n_sim], x_true, sims,
                               {k: methods[k]["label"] for k in sims}, T * dt,
                               data["z"][0, :T]))
        fig5_keys = ["proposed"] + [aliases.get(k, k)
                                    for k in (common.plain(ex.fig5_methods) or [])]
        fig5_keys = [k for k in dict.fromkeys(fig5_keys) if k in summary]
        figs.append(plots.fig5(outdir / FIGURES["fig5"], summary, fig5_keys, crb[T], T))
        if horizon_summary:
            figs.append(plots.fig6(outdir / FIGURES["fig6"], horizon_summary, theta_true,
                                   methods["proposed"]["label"]))
    stages["figures_s"] = time.perf_counter() - t0
    stages["total_s"] = time.perf_counter() - t_start

    results = {
        "experiment": "satellite",
        "seed": seed, "T": T, "dt": dt, "seeds": seeds[:n_seeds],
        "theta_true": theta_true, "w0_true": np.asarray(ex.w0),
        "paper_theta_hat_T50": PAPER_THETA_HAT_T50,
        "main_fit": {**main.summary(), "error_l2": err(main), "label": methods["proposed"]["label"],
                     "path_length": None if main.path is None else len(main.path),
                     "path_end": None if main.path is None else main.path[-1]},
        "fig3_starts": [{"theta0": s[0], "x0": s[1], "theta_hat": r.theta_flat,
                         "iterations": r.iterations, "stop_reason": r.stop_reason}
                        for s, r in zip(starts, runs)],
        "crb_rmse": {str(k): v for k, v in crb.items()},
        "crb_std": {str(k): v for k, v in crb_std.items()},
        "initial_loss": float(oj.loss(model, {"I": jnp.asarray(theta0)}, jnp.asarray(x0),
                                      jnp.asarray(u), jnp.asarray(z))),
        "monte_carlo": summary,
        "aliases": aliases,
        "seed0_estimates": {k: {**mc[k][0].summary(), "error_l2": err(mc[k][0])}
                            for k in mc if mc[k]},
        "simulation": {"t_end_s": float(data["t"][n_sim - 1]), "rmse_vs_true": sim_rmse,
                       "rmse_vs_true_training_window": train_rmse},
        "horizons": {str(k): v for k, v in horizon_summary.items()},
        "gyro_to_torque_training": float(
            np.max(np.abs(np.cross(data["x"][0, :T], theta_true * data["x"][0, :T])))
            / float(ex.torque_mean)),
        "gyro_to_torque_simulation": float(
            np.max(np.abs(np.cross(x_true, theta_true * x_true))) / float(ex.torque_mean)),
        "stages_s": stages,
        "machine": {"cpu_count": os.cpu_count(), "loadavg_start": load_start,
                    "loadavg_end": os.getloadavg()[0]},
        "figures": [Path(f).name for f in figs],
    }
    results = common.to_jsonable(results)
    from . import satellite_report

    md = satellite_report.markdown(results, cfg)
    (outdir / "results.md").write_text(md)
    print(md.split("### Figures")[0])
    return results
