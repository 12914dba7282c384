"""Figures of the hybrid cascaded-tanks study (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .cascaded_tanks_hybrid_report import physical_label  # noqa: E402

DPI = 130
COLORS = {"physical": "C1", "hybrid": "C0", "committee": "C2"}
LABELS = {
    "hybrid": "hybrid model",
    "committee": "hybrid committee (mean output)",
}


def figures(data, physical, hybrid, f, r, outdir, committee=None) -> list[str]:
    """The protocol comparison on the validation record (measured, physical, hybrid and,
    given, the hybrid committee) and the learned term against the physical one along the
    hybrid's validation trajectory (`f`, `r`: (T, 2) physical derivative and residual,
    V/s); returns the file names written into `outdir`."""
    outdir = Path(outdir)
    t = data.t
    n = physical["protocol"]["n"]
    fig, (a0, a1) = plt.subplots(
        2, 1, figsize=(9, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]}
    )
    a0.plot(t, data.y_val, "k", lw=1.3, label="measured")
    rows = [("physical", physical), ("hybrid", hybrid)]
    rows += [] if committee is None else [("committee", committee)]
    for name, row in rows:
        z = row["_pred"]["z"]
        label = f"{physical_label(row['theta'])} model" if name == "physical" else LABELS[name]
        a0.plot(
            t,
            z,
            color=COLORS[name],
            lw=1.0,
            ls="--" if name == "physical" else "-",
            label=f"{label} (RMSE {row['protocol']['rmse_V']:.3f} V)",
        )
        a1.plot(t[n:], z[n:] - data.y_val[n:], color=COLORS[name], lw=0.9, label=name)
    a0.axvspan(t[0], t[n - 1], color="0.85", lw=0, label=f"first {n} samples: x0")
    a0.set_ylabel("lower-tank level y (V)")
    a0.set_title("Cascaded tanks, validation record: x0 from the first samples, then simulated")
    a0.legend(fontsize=8, loc="lower right")
    a1.axhline(0.0, color="k", lw=0.5)
    a1.set_ylabel("error (V)")
    a1.set_xlabel("time (s)")
    a1.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(outdir / "compare.png", dpi=DPI)
    plt.close(fig)

    T = len(f)
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, ax in enumerate(axes[:2]):
        ax.plot(t[:T], f[:, i], color="C1", lw=1.0, label=f"physical f{i + 1}(x, u)")
        ax.plot(t[:T], r[:, i], color="C0", lw=1.0, label=f"learned r{i + 1}")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"dx{i + 1}/dt (V/s)")
        rms = np.sqrt(np.mean(r[:, i] ** 2)) / np.sqrt(np.mean(f[:, i] ** 2))
        ax.set_title(
            f"{'upper' if i == 0 else 'lower'} tank: RMS(r{i + 1}) / RMS(f{i + 1}) = {rms:.2f}",
            fontsize=9,
        )
        ax.legend(fontsize=8, loc="upper right")
    axes[2].plot(t[:T], data.u_val[:T], "k", lw=0.8)
    axes[2].set_ylabel("pump u (V)")
    axes[2].set_xlabel("time (s)")
    fig.suptitle("Hybrid model along its validation trajectory: physical and learned terms")
    fig.tight_layout()
    fig.savefig(outdir / "learned_terms.png", dpi=DPI)
    plt.close(fig)
    return ["compare.png", "learned_terms.png"]
