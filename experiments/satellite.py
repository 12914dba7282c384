"""The satellite case study of Section 4 (Figs. 2-6 and the numbers behind them).

The system, its constants and its data generator are `oneshot_jax.examples.satellite`:
Euler's equations I w' = M - w x (I w) with I = diag(theta), z_k = w(k dt) + e_k, a known
random torque held over each sample. theta and x0 = w(0) are estimated from tentative
values by minimising the multi-step cost C (eq. 5) with theta_i > 0 by projection. Data
are generated in numpy (classical RK4 with `data_substeps` steps per sample, independent
of the library's integrator); the identification model is `examples.satellite.model`
(RK4, `model_substeps` per sample). Each seed draws its own torque and noise.

`run(cfg, outdir)` does, for the proposed method (the `solver` config) and the baselines
listed in `experiment.methods`:

- Fig. 2: C over two components of theta (the third and x0 at the estimate), with the
  recorded path of the main fit drawn on it.
- Fig. 3: theta-hat_i against the solver's step for `fig3.n_starts` initial conditions.
- Fig. 4: w-hat(t) over [0, `simulate_time`] for the proposed method, the one-step
  prediction-error grey-box fit, the multi-step and single-step SLSQP fits with
  finite-difference gradients, and the true trajectory.
- Fig. 5: ||theta-hat - theta||_2 over `n_seeds` noise draws (box plots) per method.
- Fig. 6: estimation error and time against the horizon T, with the Cramer-Rao bound.
- `results.md`: the tables (`satellite_report.py`).
- `fit.npz`: the main fit's `FitResult` where the proposed method is one of the library's
  solvers (`oneshot_jax.load_result(path, model=examples.satellite.model(dt))`).
"""

from __future__ import annotations

import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import oneshot_jax as oj
from oneshot_jax.examples import satellite as example

from . import common
from .config import as_dict

PAPER_THETA_HAT_T50 = (0.0398, 0.0389, 0.0076)
FIT_FILE = "fit.npz"  # the main fit's FitResult (`FitResult.save`)

FIGURES = {
    "fig2": "fig2_loss_landscape.png",
    "fig3": "fig3_parameter_evolution.png",
    "fig4": "fig4_trajectories.png",
    "fig5": "fig5_estimation_error.png",
    "fig6": "fig6_horizon.png",
}


def generate(ex, seeds, n) -> dict:
    """Records of n samples for each seed (see `oneshot_jax.examples.satellite.generate`)
    with the experiment's constants."""
    return example.generate(
        seeds,
        n,
        theta=ex.theta_true,
        w0=ex.w0,
        dt=ex.dt,
        torque_mean=ex.torque_mean,
        torque_std=ex.torque_std,
        noise_std=ex.noise_std,
        substeps=ex.data_substeps,
    )


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
    xs = example.simulate_np(B[:, :3], B[:, 3:], U, float(ex.dt), int(ex.data_substeps))
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
def loss_grid(model, grid, x0, u, z):
    """C at each row of `grid` (G, 3) of inertia diagonals (Fig. 2)."""
    return jax.vmap(lambda inertia: oj.loss(model, {"I": inertia}, x0, u, z))(grid)


# ------------------------------------------------------------------------------- driver


def _methods(cfg):
    """The proposed method and the configured baselines: id -> spec (label, cost, solver).
    A baseline that is the proposed method with the same settings is an alias of it."""
    ex = cfg.experiment
    methods = {
        "proposed": {
            "label": f"proposed: {cfg.solver.title}",
            "cost": "multi_step",
            "solver": cfg.solver,
        }
    }
    aliases = {}
    for key, m in ex.methods.items():
        if ex.run_methods is not None and key not in ex.run_methods:
            continue
        if m.cost == "multi_step" and common.same_solver(m.solver, cfg.solver):
            aliases[key] = "proposed"
            continue
        methods[key] = {"label": m.solver.described(m.label), "cost": m.cost, "solver": m.solver}
    return methods, aliases


def _init(ex, z_first):
    theta0 = np.asarray(ex.init.theta0, dtype=np.float64)
    x0 = ex.init.x0
    x0 = z_first if isinstance(x0, str) else x0
    return theta0, np.asarray(x0, dtype=np.float64)


class _Fitter:
    """Runs a method on one record; the first call of each (method, T) is repeated so
    that the reported time excludes compilation (the first time is kept as well)."""

    def __init__(self, model, constraints, history):
        self.model = model
        self.constraints = constraints
        self.history = history
        self.first_call = {}

    def __call__(self, key, spec, u, z, theta0, x0):
        if spec["cost"] == "single_step":
            U, Z, X0 = one_step_windows(u, z)
            args = ({"I": theta0}, X0, U, Z)
            kw = dict(estimate_x0=False)
        else:
            args = ({"I": theta0}, x0, u, z)
            kw = {}
        kw.update(constraints=self.constraints, history=self.history)
        tag = (key, u.shape[0])
        if tag not in self.first_call:
            t0 = time.perf_counter()
            common.solve(self.model, *args, spec["solver"], **kw)
            self.first_call[tag] = time.perf_counter() - t0
        return common.solve(self.model, *args, spec["solver"], **kw)


def _summaries(mc, methods, fitter, T, err):
    summary = {}
    for key, ests in mc.items():
        e = np.array([err(s) for s in ests])
        reasons = {}
        for s in ests:
            reasons[s.stop_reason] = reasons.get(s.stop_reason, 0) + 1
        summary[key] = {
            "label": methods[key]["label"],
            "cost": methods[key]["cost"],
            "solver": as_dict(methods[key]["solver"]),
            "errors": e,
            "rmse": float(np.sqrt(np.mean(e**2))),
            "median_error": float(np.median(e)),
            "median_time_s": float(np.median([s.time_s for s in ests])),
            "times_s": np.array([s.time_s for s in ests]),
            "first_call_s": fitter.first_call.get((key, T)),
            "median_iterations": float(np.median([s.iterations for s in ests])),
            "iterations": np.array([s.iterations for s in ests]),
            "n_success": int(sum(s.success for s in ests)),
            "n": len(ests),
            "stop_reasons": reasons,
            "theta_hat": np.stack([s.theta_flat for s in ests]),
        }
    return summary


def run(cfg, outdir, command="python experiments/run.py") -> dict:
    """Run the satellite study; figures and results.md go to `outdir`. `cfg` is the
    validated `config.Config`. Returns the results dict (written to results.json by
    experiments/run.py)."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    ex = cfg.experiment
    t_start = time.perf_counter()
    stages = {}
    seed = int(cfg.seed)
    T = int(ex.T)
    dt = float(ex.dt)
    theta_true = np.asarray(ex.theta_true, dtype=np.float64)
    n_seeds = int(ex.n_seeds)
    horizons = sorted({int(h) for h in ex.horizons})
    n_h_seeds = min(int(ex.horizon_seeds), n_seeds) if horizons else 0
    seeds = [seed + i for i in range(n_seeds)]
    n_sim = int(round(float(ex.simulate_time) / dt)) + 1
    n_total = max([T, n_sim, *horizons])

    model = example.model(dt, int(ex.model_substeps))
    constraints = oj.constraints.positive(float(ex.theta_lower))
    methods, aliases = _methods(cfg)
    fitter = _Fitter(model, constraints, int(ex.history))

    t0 = time.perf_counter()
    data = generate(ex, seeds, n_total)
    crb, crb_std = crb_rmse(ex, data["u"], [T, *horizons])
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

    # --- the main fit (seed `seed`, T) is the first Monte-Carlo run; its recorded path
    # and those of the other starts of Fig. 3.
    t0 = time.perf_counter()
    u, z = data["u"][0, :T], data["z"][0, :T]
    theta0, x0 = _init(ex, z[0])
    main = mc["proposed"][0]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
    starts = [(theta0, x0)]
    spread = float(ex.fig3.spread)
    for _ in range(int(ex.fig3.n_starts) - 1):
        th = theta_true * (1.0 + spread * rng.uniform(-1.0, 1.0, 3))
        starts.append((th, z[0] + float(ex.noise_std) * rng.standard_normal(3)))
    runs = [main] + [fitter("proposed", methods["proposed"], u, z, th, xx) for th, xx in starts[1:]]
    stages["starts_s"] = time.perf_counter() - t0

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
    fig4_keys = ["proposed"] + [
        aliases.get(k, k) for k in ex.fig4_methods if aliases.get(k, k) in methods
    ]
    sims = {}
    for key in dict.fromkeys(fig4_keys):
        est = mc[key][0]
        start = z[0] if methods[key]["cost"] == "single_step" else est.x0
        xs, _ = oj.simulate(model, {"I": est.theta_flat}, start, u_long)
        sims[key] = np.asarray(xs)
    stages["simulations_s"] = time.perf_counter() - t0

    # --- summaries
    def err(est):
        return float(np.linalg.norm(est.theta_flat - theta_true))

    summary = _summaries(mc, methods, fitter, T, err)
    horizon_summary = {}
    for Th, ests in hor.items():
        if not ests:
            continue
        e = np.array([err(s) for s in ests])
        horizon_summary[Th] = {
            "errors": e,
            "rmse": float(np.sqrt(np.mean(e**2))),
            "crb_rmse": crb[Th],
            "median_time_s": float(np.median([s.time_s for s in ests])),
            "first_call_s": fitter.first_call.get(("proposed", Th)),
            "median_iterations": float(np.median([s.iterations for s in ests])),
            "theta_hat": np.stack([s.theta_flat for s in ests]),
            "n_success": int(sum(s.success for s in ests)),
        }

    def rmse(a, b):  # one RMS over every sample and axis
        return float(oj.metrics.rmse(np.ravel(a), np.ravel(b))[0])

    sim_rmse = {k: rmse(x_true, v) for k, v in sims.items()}
    train_rmse = {k: rmse(x_true[:T], v[:T]) for k, v in sims.items()}

    # --- figures
    t0 = time.perf_counter()
    from . import satellite_plots as plots

    figs = []
    if ex.figures:
        figs.append(plots.fig2(outdir / FIGURES["fig2"], model, ex, main, u, z, loss_grid))
        figs.append(
            plots.fig3(outdir / FIGURES["fig3"], runs, theta_true, methods["proposed"]["label"])
        )
        figs.append(
            plots.fig4(
                outdir / FIGURES["fig4"],
                data["t"][:n_sim],
                x_true,
                sims,
                {k: methods[k]["label"] for k in sims},
                T * dt,
                data["z"][0, :T],
            )
        )
        fig5_keys = ["proposed"] + [aliases.get(k, k) for k in ex.fig5_methods]
        fig5_keys = [k for k in dict.fromkeys(fig5_keys) if k in summary]
        figs.append(plots.fig5(outdir / FIGURES["fig5"], summary, fig5_keys, crb[T], T))
        if horizon_summary:
            figs.append(
                plots.fig6(
                    outdir / FIGURES["fig6"],
                    horizon_summary,
                    theta_true,
                    methods["proposed"]["label"],
                )
            )
    stages["figures_s"] = time.perf_counter() - t0
    stages["total_s"] = time.perf_counter() - t_start

    results = {
        "experiment": "satellite",
        "command": command,
        "solver": {**as_dict(cfg.solver), "label": cfg.solver.title},
        "seed": seed,
        "T": T,
        "dt": dt,
        "seeds": seeds,
        "theta_true": theta_true,
        "w0_true": np.asarray(ex.w0),
        "noise_std": float(ex.noise_std),
        "init_theta0": np.asarray(ex.init.theta0, dtype=np.float64),
        "init_x0": ex.init.x0,
        "theta_lower": float(ex.theta_lower),
        "paper_theta_hat_T50": PAPER_THETA_HAT_T50,
        "main_fit": {
            **main.summary(),
            "error_l2": err(main),
            "label": methods["proposed"]["label"],
            "path_length": len(main.path),
            "path_end": main.path[-1],
        },
        "fig3_starts": [
            {
                "theta0": s[0],
                "x0": s[1],
                "theta_hat": r.theta_flat,
                "iterations": r.iterations,
                "stop_reason": r.stop_reason,
            }
            for s, r in zip(starts, runs)
        ],
        "crb_rmse": {str(k): v for k, v in crb.items()},
        "crb_std": {str(k): v for k, v in crb_std.items()},
        "initial_loss": float(oj.loss(model, {"I": theta0}, x0, u, z)),
        "monte_carlo": summary,
        "aliases": aliases,
        "seed0_estimates": {k: {**mc[k][0].summary(), "error_l2": err(mc[k][0])} for k in mc},
        "simulation": {
            "t_end_s": float(data["t"][n_sim - 1]),
            "rmse_vs_true": sim_rmse,
            "rmse_vs_true_training_window": train_rmse,
        },
        "horizons": {str(k): v for k, v in horizon_summary.items()},
        "stages_s": stages,
        "figures": [Path(f).name for f in figs],
    }
    if main.result is not None:  # (`oj.load_result(path, model=example.model(dt))`)
        main.result.save(outdir / FIT_FILE)
        results["fit_file"] = FIT_FILE
    results = common.to_jsonable(results)
    from . import satellite_report

    md = satellite_report.markdown(results)
    (outdir / "results.md").write_text(md)
    print(md.split("### Figures")[0])
    return results
