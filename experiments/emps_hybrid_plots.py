"""Figures of the EMPS hybrid study (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from oneshot_jax.examples import emps as example  # noqa: E402

DPI = 130


def friction_samples(record, gtau, Ts, M, half=5):
    """The friction force seen in a record, tau - M q'' (N), against the velocity q' (m/s),
    both from central differences of qm over +-`half` samples."""
    q = np.asarray(record.qm, float)
    h = half
    v = example.velocity_estimate(q, Ts, h)
    a = np.zeros_like(q)
    a[h:-h] = (q[2 * h :] - 2 * q[h:-h] + q[: -2 * h]) / (h * Ts) ** 2
    # A centred window average of tau over the same span as the difference.
    tau = np.convolve(gtau * record.vir, np.ones(2 * h + 1) / (2 * h + 1), mode="same")
    keep = slice(2 * h, -2 * h)
    return v[keep], tau[keep] - M * a[keep]


def binned(x, y, edges):
    """Median of y in the bins of x (NaN where a bin has fewer than 10 samples)."""
    idx = np.digitize(x, edges) - 1
    out = np.full(len(edges) - 1, np.nan)
    for i in range(len(out)):
        sel = idx == i
        if np.count_nonzero(sel) >= 10:
            out[i] = np.median(y[sel])
    return 0.5 * (edges[1:] + edges[:-1]), out


def figures(data, ex, outdir, preds, scores, theta_phys, theta_hybrid) -> list[str]:
    """The validation comparison (measured, physical, hybrid) and the learned friction;
    returns the file names written into `outdir`."""
    from .emps_hybrid import INPUTS, learned_force, physical_friction

    outdir = Path(outdir)
    files = []
    test = data.test
    y = 1e3 * np.asarray(test.y).reshape(-1)
    t = data.Ts * np.arange(len(y))
    z_p = 1e3 * np.asarray(preds["physical"].z).reshape(-1)
    z_h = 1e3 * np.asarray(preds["hybrid"].z).reshape(-1)
    r_of = ", ".join(INPUTS[ex.inputs])
    lab_p = f"physical: RMSE {scores['physical']['rmse_mm']:.3f} mm"
    lab_h = f"physics + NN friction r({r_of}): RMSE {scores['hybrid']['rmse_mm']:.3f} mm"

    fig, (a0, a1) = plt.subplots(
        2, 1, figsize=(9, 5.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]}
    )
    a0.plot(t, y, "k", lw=1.2, label="measured qm")
    a0.plot(t, z_p, "C3--", lw=0.9, label=lab_p)
    a0.plot(t, z_h, "C0--", lw=0.9, label=lab_h)
    a0.set_ylabel("position (mm)")
    a0.legend(loc="upper right", fontsize=8)
    a0.set_title(
        "EMPS validation record (DATA_EMPS_PULSES.mat): open-loop simulation, "
        f"x0 from {scores['physical']['n']} samples",
        fontsize=10,
    )
    a1.plot(t, z_p - y, "C3", lw=0.8, label="physical")
    a1.plot(t, z_h - y, "C0", lw=0.8, label=f"physics + NN friction r({r_of})")
    a1.axhline(0.0, color="k", lw=0.5)
    a1.set_ylabel("error (mm)")
    a1.set_xlabel("time (s)")
    a1.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "compare.png", dpi=DPI)
    plt.close(fig)
    files.append("compare.png")

    rec = data.estimation
    v_data = example.velocity_estimate(rec.qm, data.Ts, ex.velocity_halfwidth)
    vmax = float(np.max(np.abs(v_data)))
    v = np.linspace(-vmax, vmax, 801)
    q_mid = float(np.mean(rec.qm))
    r_mid = learned_force(theta_hybrid, q_mid, v)
    f_phys = physical_friction(theta_phys, v, ex.eps)
    f_hyb = physical_friction(theta_hybrid, v, ex.eps) + r_mid
    vs, fs = friction_samples(
        rec, data.gtau, data.Ts, float(theta_hybrid["M"]), ex.velocity_halfwidth
    )
    centres, med = binned(vs, fs, np.linspace(-vmax, vmax, 81))

    fig, (b0, b1) = plt.subplots(1, 2, figsize=(11, 4))
    b0.plot(centres, med, ".", color="0.5", ms=4, label="tau - M q'' of the estimation record")
    b0.plot(v, f_phys, "C3", lw=1.2, label="physical: Fv q' + Fc tanh(q'/eps) + offset")
    at = f" (q = {q_mid:.3f} m)" if ex.inputs == "qv" else ""
    hyb_label = "hybrid: its physical part + r" + at
    b0.plot(v, f_hyb, "C0", lw=1.2, label=hyb_label)
    b0.set_xlabel("velocity q' (m/s)")
    b0.set_ylabel("friction force (N)")
    b0.set_title("Total friction")
    b0.legend(fontsize=7)
    if ex.inputs == "qv":
        for qq, style in zip(np.percentile(rec.qm, [10, 50, 90]), ("--", "-", ":")):
            b1.plot(v, learned_force(theta_hybrid, qq, v), "C0" + style, label=f"q = {qq:.3f} m")
        b1.legend(fontsize=7)
    else:
        b1.plot(v, r_mid, "C0")
    b1.axhline(0.0, color="k", lw=0.5)
    b1.set_xlabel("velocity q' (m/s)")
    b1.set_ylabel("learned force r (N)")
    b1.set_title(f"The learned term r({r_of})")
    fig.tight_layout()
    fig.savefig(outdir / "friction.png", dpi=DPI)
    plt.close(fig)
    files.append("friction.png")
    return files
