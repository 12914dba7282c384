"""results.md of the EMPS study: the tables of a run (every number from its results dict)."""

from __future__ import annotations

from oneshot_jax.examples.emps import PARAMS, UNITS

from .common import plus_minus

NAMES = {"closed_loop": "closed loop", "open_loop": "open loop"}


def markdown(res) -> str:
    ref, ch, best = res["reference"], res["chosen"], res["best"]
    fams = [f for f in ("closed_loop", "open_loop") if f in best]
    solver = res["solver"]
    settings = ", ".join(f"{k} = {v}" for k, v in (solver.get("kwargs") or {}).items())
    L = [
        "# EMPS: physical parameters from the real records",
        "",
        f"Command: `{res['command']}` ({res['n_estimation_samples']} estimation samples, "
        f"Ts = {res['Ts_s']} s, sign(q') ~ tanh(q'/{res['eps_m_per_s']:g} m/s), "
        f"{solver.get('label') or solver['name']} ({settings}), M, Fv, Fc >= 1e-6 by a box "
        "constraint).",
        "",
    ]
    left_out = res.get("windows_left_out") or {}
    if left_out:
        L += [
            "Windows longer than the estimation samples used, left out: "
            + "; ".join(f"{NAMES[f]} {Ts}" for f, Ts in left_out.items())
            + ".",
            "",
        ]
    L += [
        "| parameter | IDIM-LS reference | "
        + " | ".join(f"{NAMES[f]} (T = {best[f]['window'] * res['Ts_s']:g} s)" for f in fams)
        + " | kept vs reference |",
        "|---|---|" + "---|" * len(fams) + "---|",
    ]
    for k in PARAMS:
        L.append(
            f"| {k} ({UNITS[k]}) | {ref['theta'][k]:.4f} | "
            + " | ".join(plus_minus(best[f]["theta"][k], best[f]["std"][k], 4, 3) for f in fams)
            + f" | {res['deviation_from_reference_pct'][k]:+.2f} % |"
        )
    L += [
        "",
        "± : the standard error of the fit, the square root of the diagonal of "
        "sigma^2 (J^T J)^-1 with white residuals.",
        "",
        "Relative error 100 ||q_sim - qm|| / ||qm|| (benchmark eq. 11) of the closed-loop "
        "simulation from qg (and the pulses), every parameter set in the same simulator:",
        "",
        "| parameters | validation position | validation force | estimation position "
        "| estimation force |",
        "|---|---|---|---|---|",
    ]
    for label, sc in [("IDIM-LS reference", ref["scores"])] + [
        (f"{NAMES[f]} fit", best[f]["scores"]) for f in fams
    ]:
        v, e = sc["validation"], sc["estimation"]
        L.append(
            f"| {label} | {v['relerr_position_pct']:.6f} % | {v['relerr_force_pct']:.3f} % | "
            f"{e['relerr_position_pct']:.6f} % | {e['relerr_force_pct']:.3f} % |"
        )
    L += [
        "",
        f"Kept: **{ch['label']}** (smallest closed-loop position error on the estimation "
        f"record). Fit time {ch['wall_time_s']:.2f} s in `fit` the first call (compilation "
        f"included), {ch['warm_time_s']:.2f} s for the whole call repeated; the run took "
        f"{res['total_time_s']:.0f} s.",
        "",
        "Window sweep (each T: windows of T samples, each with its own estimated initial state):",
        "",
        "| structure | T (samples) | windows | M | Fv | Fc | offset | iterations | stop | time (s) "
        "| est. position relerr | val. position relerr |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for f in ("open_loop", "closed_loop"):
        for r in res["sweeps"].get(f, []):
            t = r["theta"]
            L.append(
                f"| {NAMES[f]} | {r['window']} | {r['n_windows']} | {t['M']:.3f} | "
                f"{t['Fv']:.2f} | {t['Fc']:.3f} | {t['offset']:.3f} | {r['iterations']} | "
                f"{r['stop_reason']} | {r['total_time_s']:.1f} | "
                f"{r['scores']['estimation']['relerr_position_pct']:.6f} % | "
                f"{r['scores']['validation']['relerr_position_pct']:.6f} % |"
            )
    un = res.get("closed_loop_unconstrained")
    if un:
        L += [
            "",
            "Closed loop, whole record, without constraints: "
            + ", ".join(f"{k} = {un['theta'][k]:.4f}" for k in PARAMS)
            + f" ({un['stop_reason']}).",
        ]
    pr = res.get("protocol")
    if pr:
        L += [
            "",
            "The community's protocol (Champneys et al., *Baseline results for selected "
            "nonlinear system identification benchmarks*, 2024): the open-loop model with "
            "u = vir (force = gtau vir) and y = qm, x0 = (q, q') estimated from the first "
            f"{pr['reference']['n']} test outputs of DATA_EMPS_PULSES.mat only, simulated over "
            "the whole test record and scored on the rest (position in mm):",
            "",
            "| parameters | RMSE (mm) | NRMSE | R^2 | FIT % |",
            "|---|---|---|---|---|",
        ]
        for key, label in [("reference", "IDIM-LS reference")] + [
            (f, f"{NAMES[f]} fit") for f in fams
        ]:
            r = pr[key]
            L.append(
                f"| {label} | {r['rmse_mm']:.3f} | {r['nrmse']:.4f} | {r['r2']:.4f} | "
                f"{r['fit_percent']:.2f} |"
            )
        L += [
            "",
            "For comparison, as published for this protocol: dynoNet about 2.6 mm, "
            "CT-SUBNET 4.61 mm (black-box models trained for open-loop simulation; the "
            "physical model here has four parameters and drifts in open loop, which the "
            "closed-loop scores above do not show).",
        ]
    L += ["", "Time (s): the whole `fit` call, compilation included.", ""]
    L += [f"![{f}]({f})" for f in res["figures"]]
    return "\n".join(L) + "\n"
