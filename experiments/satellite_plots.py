"""Figures 2-6 of the satellite study (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

import textwrap

import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

THETA_TEX = (
    r"$\hat\theta_1 = \hat I_x$",
    r"$\hat\theta_2 = \hat I_y$",
    r"$\hat\theta_3 = \hat I_z$",
)
INERTIA_UNIT = r"kg m$^2$"
DPI = 120


def _save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def fig2(path, model, ex, main, u, z, loss_grid):
    """C over (theta_a, theta_b), theta_c and x0 at the estimate, with the path."""
    a, b = (int(i) for i in ex.fig2.pair)
    c = ({0, 1, 2} - {a, b}).pop()
    G = int(ex.fig2.grid)
    margin = float(ex.fig2.margin)
    theta_true = np.asarray(ex.theta_true, dtype=np.float64)
    P = main.path
    pts = np.concatenate([P[:, [a, b]], theta_true[None, [a, b]], main.theta_flat[None, [a, b]]])
    lo, hi = pts.min(0), pts.max(0)
    pad = margin * (hi - lo) + 0.02 * np.abs(hi)
    lo = np.maximum(lo - pad, 0.25 * lo)
    hi = hi + pad
    ga, gb = np.linspace(lo[0], hi[0], G), np.linspace(lo[1], hi[1], G)
    A, B = np.meshgrid(ga, gb)
    grid = np.empty((G * G, 3))
    grid[:, a], grid[:, b], grid[:, c] = A.ravel(), B.ravel(), main.theta_flat[c]
    C = np.asarray(
        loss_grid(model, jnp.asarray(grid), jnp.asarray(main.x0), jnp.asarray(u), jnp.asarray(z))
    ).reshape(G, G)
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    logC = np.log10(np.where(np.isfinite(C) & (C > 0), C, np.nan))
    cs = ax.contourf(A, B, logC, levels=30, cmap="viridis")
    ax.contour(A, B, logC, levels=12, colors="k", linewidths=0.3, alpha=0.5)
    fig.colorbar(cs, ax=ax, label=r"$\log_{10} C$  [(rad/s)$^2$]")
    ax.plot(
        P[:, a],
        P[:, b],
        "-" if len(P) > 50 else ".-",
        color="white",
        lw=1.6,
        label=f"optimisation path ({main.iterations} steps)",
    )
    ax.plot(P[0, a], P[0, b], "o", color="white", mec="k", ms=8, label="initial value")
    ax.plot(
        main.theta_flat[a],
        main.theta_flat[b],
        "X",
        color="orange",
        mec="k",
        ms=10,
        label="estimate",
    )
    ax.plot(theta_true[a], theta_true[b], "*", color="red", mec="k", ms=14, label="true value")
    ax.set_xlabel(f"{THETA_TEX[a]}  [{INERTIA_UNIT}]")
    ax.set_ylabel(f"{THETA_TEX[b]}  [{INERTIA_UNIT}]")
    ax.set_title(
        f"Fig. 2: loss $C$ over $(\\theta_{a + 1}, \\theta_{b + 1})$, "
        f"$\\theta_{c + 1}$ and $x_0$ at the estimate",
        fontsize=10,
    )
    ax.legend(loc="best", fontsize=8, framealpha=0.8)
    return _save(fig, path)


def fig3(path, runs, theta_true, label):
    """theta-hat_i against the solver's step for several initial conditions (the
    recorded path of each fit, `FitResult.history`)."""
    fig, axes = plt.subplots(3, 1, figsize=(6.4, 7.2), sharex=True)
    colors = plt.cm.tab10(np.arange(len(runs)) % 10)
    for i, ax in enumerate(axes):
        for j, r in enumerate(runs):
            ax.plot(r.path_steps, r.path[:, i], color=colors[j], lw=1.3, label=f"start {j + 1}")
        ax.axhline(theta_true[i], ls="--", color="k", lw=1.2, label=r"true $\theta_i$")
        ax.set_ylabel(f"{THETA_TEX[i]}\n[{INERTIA_UNIT}]")
        ax.set_xscale("symlog", linthresh=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=3, loc="best")
    axes[0].set_title(f"Fig. 3: estimates against the step ({label})", fontsize=9)
    axes[-1].set_xlabel(r"step $\ell$")
    return _save(fig, path)


def fig4(path, t, x_true, sims, labels, t_train, z_train):
    """w-hat_i(t) over the long horizon for each method, and the true trajectory."""
    fig, axes = plt.subplots(3, 1, figsize=(7.2, 8.0), sharex=True)
    styles = {"proposed": ("tab:red", "-", 2.0)}
    palette = iter(
        [
            ("tab:green", "--", 1.4),
            ("tab:orange", "-.", 1.4),
            ("tab:purple", ":", 1.8),
            ("tab:blue", "--", 1.2),
            ("tab:brown", "-.", 1.2),
            ("tab:olive", ":", 1.2),
        ]
    )
    order = [k for k in sims if k != "proposed"] + (["proposed"] if "proposed" in sims else [])
    for i, ax in enumerate(axes):
        span = np.ptp(x_true[:, i])
        lo, hi = x_true[:, i].min() - 0.5 * span, x_true[:, i].max() + 0.5 * span
        ax.axvspan(0.0, t_train, color="0.85", label="training window")
        ax.plot(t[: len(z_train)], z_train[:, i], ".", color="0.4", ms=2.5, label="measurements")
        ax.plot(t, x_true[:, i], "-", color="k", lw=2.4, label="true")
        for key in order:  # the proposed method last, on top
            if key not in styles:
                styles[key] = next(palette)
            color, ls, lw = styles[key]
            ax.plot(t, sims[key][:, i], ls, color=color, lw=lw, label=labels[key])
        ax.set_ylim(lo, hi)
        ax.set_ylabel(rf"$\hat\omega_{'xyz'[i]}$ [rad/s]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    axes[0].set_title(
        "Fig. 4: simulated angular velocity with the estimated parameters", fontsize=10
    )
    axes[-1].set_xlabel("time t [s]")
    return _save(fig, path)


def fig5(path, summary, keys, crb, T):
    """Box plots of ||theta-hat - theta||_2 over the noise seeds."""
    fig, ax = plt.subplots(figsize=(max(6.4, 0.95 * len(keys) + 2.0), 5.2))
    data = [np.asarray(summary[k]["errors"], dtype=np.float64) for k in keys]
    pos = np.arange(1, len(keys) + 1)
    ax.boxplot(data, positions=pos, widths=0.55, showfliers=False)
    rng = np.random.default_rng(0)
    for p, d in zip(pos, data):
        ax.plot(p + rng.uniform(-0.15, 0.15, d.size), d, ".", color="tab:blue", alpha=0.6, ms=4)
        ax.plot(p, np.sqrt(np.mean(d**2)), "D", color="tab:red", ms=6)
    ax.plot([], [], "D", color="tab:red", label="RMS over seeds")
    ax.axhline(crb, ls="--", color="k", label=f"Cramer-Rao bound on the RMS ({crb:.2e})")
    ax.set_yscale("log")
    ax.set_xticks(pos)
    ax.set_xticklabels(
        [textwrap.fill(summary[k]["label"], 18) for k in keys], fontsize=7, rotation=0
    )
    ax.set_ylabel(r"$\|\hat\theta - \theta\|_2$  [" + INERTIA_UNIT + "]")
    n = len(data[0]) if data else 0
    ax.set_title(f"Fig. 5: estimation error over {n} noise seeds, T = {T}", fontsize=10)
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3, axis="y")
    return _save(fig, path)


def fig6(path, hs, theta_true, label):
    """Estimates, error (with the CRB) and time against the horizon T."""
    Ts = np.array(sorted(hs, key=int), dtype=int)
    keys = [k for k in sorted(hs, key=int)]
    fig, axes = plt.subplots(1, 3, figsize=(13.0, 4.2))
    ax = axes[0]
    for i in range(3):
        th = np.stack([np.asarray(hs[k]["theta_hat"])[:, i] for k in keys]) / theta_true[i]
        med = np.median(th, axis=1)
        q1, q3 = np.percentile(th, [25, 75], axis=1)
        ax.plot(Ts, med, "o-", label=rf"$\hat\theta_{i + 1}/\theta_{i + 1}$ (median)")
        ax.fill_between(Ts, q1, q3, alpha=0.2)
    ax.axhline(1.0, ls="--", color="k", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel("horizon T [samples]")
    ax.set_ylabel(r"$\hat\theta_i / \theta_i$ [-] (median, IQR over seeds)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax = axes[1]
    for T, k in zip(Ts, keys):
        e = np.asarray(hs[k]["errors"], dtype=np.float64)
        ax.plot(np.full(e.size, T), e, ".", color="tab:blue", alpha=0.4, ms=4)
    ax.plot([], [], ".", color="tab:blue", label="per seed")
    ax.plot(Ts, [hs[k]["rmse"] for k in keys], "o-", color="tab:red", label="RMS over seeds")
    ax.plot(Ts, [hs[k]["crb_rmse"] for k in keys], "k--", label="Cramer-Rao bound (RMS)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("horizon T [samples]")
    ax.set_ylabel(r"$\|\hat\theta - \theta\|_2$  [" + INERTIA_UNIT + "]")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    ax = axes[2]
    ax.plot(
        Ts,
        [hs[k]["median_time_s"] for k in keys],
        "o-",
        color="tab:blue",
        label="median time per fit (compiled)",
    )
    first = [hs[k].get("first_call_s") for k in keys]
    if any(f is not None for f in first):
        ax.plot(
            Ts,
            [np.nan if f is None else f for f in first],
            "s:",
            color="tab:gray",
            label="first call (with compilation)",
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("horizon T [samples]")
    ax.set_ylabel("computation time [s]")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"Fig. 6: estimates, error and time against the horizon ({label})", fontsize=10)
    return _save(fig, path)
