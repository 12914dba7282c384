"""Figures of the cascaded-tanks study (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .cascaded_tanks_report import LABELS  # noqa: E402

DPI = 130
COLORS = {"basic": "C1", "overflow": "C0", "sensor": "C2"}


def figures(data, rows, outdir) -> list[str]:
    """The validation comparison and the error histogram of each model (`rows[kind]
    ["_sim"]` holds its simulated estimation and validation outputs); returns the file
    names written into `outdir`."""
    outdir = Path(outdir)
    t = data.t
    fig, (a0, a1) = plt.subplots(
        2, 1, figsize=(9, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]}
    )
    a0.plot(t, data.y_val, "k", lw=1.3, label="measured")
    for kind, r in rows.items():
        yv = r["_sim"][1]
        a0.plot(
            t,
            yv,
            color=COLORS[kind],
            lw=1.0,
            ls="--" if kind == "basic" else "-",
            label=f"{LABELS[kind]} model (RMSE {r['rmse_validation_V']:.3f} V)",
        )
        a1.plot(t, yv - data.y_val, color=COLORS[kind], lw=0.9, label=LABELS[kind])
    a0.set_ylabel("lower-tank level y (V)")
    a0.set_title("Cascaded tanks, validation record: simulation from the estimated x0")
    a0.legend(fontsize=8, loc="lower right")
    a1.axhline(0.0, color="k", lw=0.5)
    a1.set_ylabel("error (V)")
    a1.set_xlabel("time (s)")
    a1.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(outdir / "compare.png", dpi=DPI)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    errs = {k: r["_sim"][1] - data.y_val for k, r in rows.items()}
    lo, hi = np.percentile(np.concatenate(list(errs.values())), [0.5, 99.5])
    bins = np.linspace(lo, hi, 50)
    for kind, e in errs.items():
        ax.hist(
            e,
            bins=bins,
            alpha=0.55,
            color=COLORS[kind],
            label=f"{LABELS[kind]} (RMS {rows[kind]['rmse_validation_V']:.3f} V)",
        )
    ax.set_xlabel("simulation error on validation (V)")
    ax.set_ylabel("samples")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "residual_hist.png", dpi=DPI)
    plt.close(fig)
    return ["compare.png", "residual_hist.png"]
