"""Write docs/figures/cstr_data.png, the data of the CSTR case study in
docs/guides/non-uniform.md: the coolant temperature, the temperature samples with their
gaps, and the concentration with its 8-hour averages and the shifts' middle samples.

Run: `python docs/figures/make_cstr_figure.py` (needs matplotlib). The record is the
guide's (`cstr.design(0)`, noise draw 1).
"""

from pathlib import Path

import jax

HERE = Path(__file__).resolve().parent


def main():
    jax.config.update("jax_enable_x64", True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from oneshot_jax.examples import cstr

    design = cstr.design(0)
    z, averages = cstr.measure(design, seed=1)
    hours = design.t / 60.0
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    axes[0].step(hours, design.u[:, 0], where="post", color="tab:blue", lw=1)
    axes[0].set_ylabel("coolant T_c (K)")
    axes[1].plot(hours, design.x[:, 1], color="0.6", lw=1, label="true T")
    axes[1].plot(hours, z[:, 1], ".", ms=2, color="tab:red", label="samples (gaps: NaN)")
    axes[1].set_ylabel("reactor T (K)")
    axes[1].legend(loc="upper right", fontsize=8)
    axes[2].plot(hours, design.x[:, 0], color="0.6", lw=1, label="true C_A")
    for j, (a, b) in enumerate(design.intervals):
        label = "8-hour averages (measured)" if j == 0 else None
        axes[2].hlines(averages[j], hours[a], hours[b - 1], color="tab:green", lw=2, label=label)
    mid = cstr.midpoints(design)
    axes[2].plot(
        hours[mid], averages, "x", color="k", label="as point samples at the middles (biased)"
    )
    axes[2].set_ylabel("C_A (mol/L)")
    axes[2].set_xlabel("time (h)")
    axes[2].legend(loc="lower right", fontsize=8)
    for ax in axes:
        for j in range(len(design.intervals) + 1):
            ax.axvline(j * cstr.SHIFT / 60.0, color="0.85", lw=0.8, zorder=0)
    fig.tight_layout()
    path = HERE / "cstr_data.png"
    fig.savefig(path, dpi=110)
    print(path)


if __name__ == "__main__":
    main()
