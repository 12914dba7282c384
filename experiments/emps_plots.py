"""Figures of the EMPS study (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from oneshot_jax.examples import emps as example  # noqa: E402

DPI = 130


def figures(data, chosen, ex, outdir, sweeps) -> list[str]:
    """The validation comparison, the error histogram and the window sweep; returns the
    file names written into `outdir`."""
    outdir = Path(outdir)
    rec = data.validation
    q_fit, _ = example.simulate_closed_loop(data, rec, chosen["theta"], ex.eps, ex.substeps)
    q_ref, _ = example.simulate_closed_loop(data, rec, example.REFERENCE, ex.eps, ex.substeps)
    t = rec.t
    files = []

    fig, (a0, a1) = plt.subplots(
        2, 1, figsize=(9, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]}
    )
    a0.plot(t, rec.qm, "k", lw=1.2, label="measured qm")
    a0.plot(t, q_fit, "C0--", lw=1.0, label=f"simulated, {chosen['label']}")
    a0.set_ylabel("position (m)")
    a0.legend(loc="upper right", fontsize=8)
    a0.set_title("EMPS validation record (DATA_EMPS_PULSES.mat), closed-loop simulation")
    err_fit = example.relative_error(q_fit, rec.qm)
    err_ref = example.relative_error(q_ref, rec.qm)
    a1.plot(t, 1e6 * (q_fit - rec.qm), "C0", lw=0.7, label=f"{chosen['label']}: {err_fit:.6f} %")
    a1.plot(
        t,
        1e6 * (q_ref - rec.qm),
        "C3",
        lw=0.7,
        alpha=0.7,
        label=f"IDIM-LS reference: {err_ref:.6f} %",
    )
    a1.set_ylabel("error (µm)")
    a1.set_xlabel("time (s)")
    a1.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "compare.png", dpi=DPI)
    plt.close(fig)
    files.append("compare.png")

    fig, ax = plt.subplots(figsize=(6, 4))
    both = 1e6 * np.r_[q_fit - rec.qm, q_ref - rec.qm]
    bins = np.linspace(*np.percentile(both, [0.5, 99.5]), 60)
    ax.hist(1e6 * (q_fit - rec.qm), bins=bins, alpha=0.6, label=chosen["label"])
    ax.hist(
        1e6 * (q_ref - rec.qm), bins=bins, histtype="step", color="C3", label="IDIM-LS reference"
    )
    ax.set_xlabel("position simulation error on validation (µm)")
    ax.set_ylabel("samples")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "residual_hist.png", dpi=DPI)
    plt.close(fig)
    files.append("residual_hist.png")

    fig, axes = plt.subplots(1, 4, figsize=(13, 3.2))
    for ax, k in zip(axes, example.PARAMS):
        for fam, style in (("open_loop", "o-"), ("closed_loop", "s-")):
            rows = sweeps.get(fam, [])
            if rows:
                ax.errorbar(
                    [r["window"] * data.Ts for r in rows],
                    [r["theta"][k] for r in rows],
                    yerr=[r["std"][k] for r in rows],
                    fmt=style,
                    ms=4,
                    label=fam.replace("_", " "),
                )
        ref = example.REFERENCE[k]
        ax.axhline(ref, color="k", lw=0.8, ls=":", label="IDIM-LS")
        ax.axhspan(ref * 0.95, ref * 1.05, color="0.9", zorder=0)
        ax.set_xscale("log")
        ax.set_title(f"{k} ({example.UNITS[k]})")
        ax.set_xlabel("window length T (s)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(outdir / "window_sweep.png", dpi=DPI)
    plt.close(fig)
    files.append("window_sweep.png")
    return files
