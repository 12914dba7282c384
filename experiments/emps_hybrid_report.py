"""results.md of the EMPS hybrid study: the tables of a run (every number from its
results dict)."""

from __future__ import annotations

from oneshot_jax.examples.emps import PARAMS, UNITS


def markdown(res) -> str:
    cfg, net, solver = res["config"], res["network"], res["solver"]
    phys, hyb, ref = res["physical"], res["hybrid"], res["reference"]
    settings = ", ".join(f"{k} = {v}" for k, v in (solver.get("kwargs") or {}).items())
    adam = cfg["adam"]
    r_of = ", ".join(net["inputs"])
    decay = ""
    if adam["weight_decay"]:
        decay = f", weight decay {adam['weight_decay']:g} on the network"
    L = [
        "# EMPS: physics plus a neural friction term",
        "",
        f"Command: `{res['command']}`.",
        "",
        "The physical model M q'' = tau - Fv q' - Fc tanh(q'/eps) - offset (tau = gtau vir) "
        f"gets a learned friction force r({r_of}) added to its friction: a tanh MLP with "
        f"hidden layers {net['widths']} ({net['parameters']} parameters), inputs normalised "
        "by the estimation record's standard deviations, output scaled by "
        f"{net['output_scale_N']:g} N and zero at the start. Training on "
        f"{res['n_estimation_samples']} samples of the estimation record (DATA_EMPS.mat) "
        f"cut into {res['n_windows']} open-loop windows of {cfg['window']} samples, each "
        "with its own estimated initial state (q, q'); loss: the multi-step simulation "
        "error of q in mm. Stages, each starting where the last stopped:",
        "",
        f"1. physics: M, Fv, Fc, offset alone, the network held by `fixed=`; "
        f"{solver.get('label') or solver['name']} ({settings}); M, Fv, Fc >= 1e-6;",
        f"2. joint: Adam, {adam['steps']} steps, rate {adam['lr']:g} with cosine decay"
        + f"{decay};",
        f"3. joint: Levenberg-Marquardt, at most {cfg['lm_steps']} steps.",
        "",
        "| stage | iterations | stop | time (s) | M | Fv | Fc | offset | estimation RMSE (mm) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["stages"]:
        t = r["theta"]
        L.append(
            f"| {r['stage']} | {r['iterations']} | {r['stop_reason']} | {r['time_s']:.1f} | "
            f"{t['M']:.3f} | {t['Fv']:.2f} | {t['Fc']:.3f} | {t['offset']:.3f} | "
            f"{r['rmse_fit_mm']:.5f} |"
        )
    L += [
        "",
        "Estimation RMSE: over the training windows, each from its estimated initial state. "
        "Time: the whole `fit` call, compilation included.",
        "",
        "## Validation",
        "",
        "The community's protocol on the validation record (DATA_EMPS_PULSES.mat), as in "
        "the [EMPS case study](emps.md): open-loop simulation with u = vir and y = qm, "
        f"x0 = (q, q') estimated from the first {phys['protocol']['n']} test outputs only, "
        "scored on the rest (position in mm):",
        "",
        "| model | RMSE (mm) | NRMSE | R^2 | FIT % |",
        "|---|---|---|---|---|",
    ]
    for label, r in (
        ("IDIM-LS reference parameters (physical)", ref["protocol"]),
        ("physical model (stage 1)", phys["protocol"]),
        (f"physics + NN friction r({r_of}) (stage 3)", hyb["protocol"]),
    ):
        L.append(
            f"| {label} | {r['rmse_mm']:.3f} | {r['nrmse']:.4f} | {r['r2']:.4f} | "
            f"{r['fit_percent']:.2f} |"
        )
    lf = hyb["learned_force_N"]
    change = res["improvement_pct"]
    L += [
        "",
        f"The hybrid model's validation RMSE is {abs(change):.1f} % "
        f"{'lower' if change > 0 else 'higher'} than the physical model's. "
        f"Largest learned force over |q'| <= {lf['v_max_m_per_s']:.3f} m/s"
        + (
            f" (at mid-travel, q = {lf['q_m']:.3f} m)"
            if res["config"].get("inputs") == "qv"  # (r of the velocity alone: no q)
            else ""
        )
        + f": {lf['max_abs']:.2f} N; at q' = 0: "
        f"{lf['at_zero_velocity']:+.2f} N. The network has seen the velocities of the "
        f"estimation record, |q'| <= {lf['v_max_m_per_s']:.3f} m/s (central differences of "
        f"qm); the validation record reaches {lf['v_max_validation_m_per_s']:.3f} m/s, where "
        "it extrapolates.",
        "",
        "| parameter | physical model | hybrid model | IDIM-LS reference |",
        "|---|---|---|---|",
    ]
    for k in PARAMS:
        L.append(
            f"| {k} ({UNITS[k]}) | {phys['theta'][k]:.4f} | {hyb['theta'][k]:.4f} | "
            f"{ref['theta'][k]:.4f} |"
        )
    L += [
        "",
        "In the hybrid model Fc, Fv and offset share the friction with the network, so they "
        "are no longer the physical friction coefficients alone: compare the total "
        "friction curves below.",
        "",
        "The joint Levenberg-Marquardt stage ends at its step budget on a network whose "
        "Jacobian is ill-conditioned, so where it ends, and the test RMSE, depend on "
        "round-off (the machine, the versions of JAX and XLA). The [friction models fitted "
        "for the open-loop protocol](emps_friction.md) are physical models; the one that "
        "page's procedure selects scores better than this hybrid.",
        "",
        f"The run took {res['total_time_s']:.0f} s.",
        "",
    ]
    L += [f"![{f}]({f})" for f in res["figures"]]
    return "\n".join(L) + "\n"
