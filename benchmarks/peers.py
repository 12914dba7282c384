"""Side-by-side benchmark of oneshot_jax against the tools a user would otherwise pick.

Problems (`peers_problems.py`): (a) the satellite of Section 4 at T = 50 and T = 5000,
(b) the EMPS benchmark as a windowed fit (248 windows of 100 samples, each with its own
initial state), (c) a chain of 20 masses with 40 unknown stiffness and damping values.

Tools (`peers_tools.py`): oneshot_jax `fit` (Levenberg-Marquardt and Gauss-Newton on the
closed-form Jacobian), scipy `least_squares` ('lm', and 'trf' with bounds and, for the
windowed problem, the documented `jac_sparsity` + `lsmr` route), scipy SLSQP, CasADi +
IPOPT (exact derivatives, Gauss-Newton Hessian, as in CasADi's sysid example),
jax-sysid (L-BFGS-B, regularisation off) and optimistix Levenberg-Marquardt with a
forward-mode autodiff Jacobian (the "plain JAX" baseline). Every tool minimises the same
multi-step loss C with the same RK4 discretisation from the same start; C is recomputed
for every answer by one common evaluator.

Each (problem, tool) pair runs in its own Python process. The first call of each tool
is timed in a fresh process, one tool at a time (a true cold start: JIT compilation or
graph building included), and stopped if it exceeds `--timeout` seconds. Then up to
`--repeats` rounds of further calls (the time without compilation) are run, interleaved
across the tools of the problem so that a change of machine load hits every tool alike;
the median is reported. oneshot_jax is reported twice per solver: the whole `fit()` call
(what a user waits for) and its one compiled call alone (`FitResult.wall_time`:
start projection, solve, covariance and metrics).

Run:  python benchmarks/peers.py                  # everything, writes benchmarks/results.md
      python benchmarks/peers.py --quick          # a small smoke run (does not write results.md)
      python benchmarks/peers.py --problems emps --tools oneshot_lm,scipy_trf
Needs the peers: pip install -e .[bench]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

DEFAULT_TOOLS = (
    "oneshot_lm",
    "oneshot_gn",
    "scipy_lm",
    "scipy_trf",
    "scipy_slsqp",
    "casadi_ipopt",
    "jax_sysid",
    "optimistix_lm",
)
MARK = "@@PEERS-RESULT@@"


# ------------------------------------------------------------------------------ worker


def worker(problem, tool):
    """Runs in its own process: the cold call, then one warm call per "run" line read on
    stdin until "quit" (or the end of stdin). After every call it prints one JSON line with
    everything measured so far."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import peers_problems
    import peers_tools

    pb = peers_problems.build(problem)
    runner = peers_tools.TOOLS[tool](pb)
    loss = peers_tools.make_loss(pb)
    out = {
        "problem": problem,
        "tool": tool,
        "label": runner.label,
        "method": runner.method,
        "n_var": pb.n_var,
        "n_res": pb.N * pb.T * pb.n_z,
        "title": pb.title,
        "notes": pb.notes,
        "truth_label": pb.truth_label,
        "warm_s": [],
        "solver_warm_s": [],
    }

    def report(res):
        p = np.asarray(res["p"], float)
        th, _ = pb.split(p)
        out.update(
            loss=loss(p),
            iterations=res.get("iterations"),
            fevals=res.get("fevals"),
            stop=res.get("stop"),
            param_error=pb.param_error(th),
            theta=th.tolist(),
            tool_t_solve_s=res.get("tool_t_solve_s"),
            loss_reported=res.get("loss_reported"),
        )
        print(MARK + json.dumps(out), flush=True)

    out["loss_start"] = loss(pb.p0())
    t0 = time.perf_counter()
    res = runner.run()
    out["cold_s"] = time.perf_counter() - t0
    for k, v in (("solver_cold_s", "solver_s"), ("build_s", "build_s")):
        if v in res:
            out[k] = res[v]
    report(res)
    for line in sys.stdin:
        if line.strip() != "run":
            break
        t0 = time.perf_counter()
        res = runner.run()
        out["warm_s"].append(time.perf_counter() - t0)
        if "solver_s" in res:
            out["solver_warm_s"].append(res["solver_s"])
        report(res)


def diagnose_worker(problem):
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    import peers_problems
    import peers_tools

    out = peers_tools.jacobian_timings(peers_problems.build(problem))
    out["problem"] = problem
    print(MARK + json.dumps(out), flush=True)


def run_diagnose(problem, timeout=180):
    cmd = [sys.executable, str(Path(__file__).resolve()), "--diagnose", problem]
    try:
        cp = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None
    for line in cp.stdout.splitlines():
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    print(f"diagnostics for {problem} failed: {cp.stderr.strip().splitlines()[-1:]}")
    return None


class Pair:
    """One (problem, tool) worker process, driven call by call."""

    def __init__(self, problem, tool):
        import queue
        import tempfile
        import threading

        self.problem, self.tool = problem, tool
        self.result = None
        self.status = "ok"
        self.warm_total = 0.0
        self.err = tempfile.TemporaryFile(mode="w+")  # a file: a chatty tool cannot block
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", problem, tool]
        self.proc = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.err,
            text=True,
            bufsize=1,
        )
        self.lines = queue.Queue()

        def pump():
            for line in self.proc.stdout:
                if line.startswith(MARK):
                    self.lines.put(json.loads(line[len(MARK) :]))
            self.lines.put(None)

        threading.Thread(target=pump, daemon=True).start()

    @property
    def alive(self):
        return self.status == "ok" and self.proc.poll() is None

    def _wait(self, timeout):
        import queue

        try:
            r = self.lines.get(timeout=timeout)
        except queue.Empty:
            r = "timeout"
        if isinstance(r, dict):
            self.result = r
            return True
        if r == "timeout":
            self.proc.kill()
            self.status = "timeout" if self.result is None else self.status
        else:  # the process ended without a result
            self.proc.wait()
            if self.result is None:
                self.err.seek(0)
                tail = self.err.read().strip().splitlines()[-3:]
                self.status, self.error = "error", " | ".join(tail)
        return False

    def cold(self, timeout):
        self.timeout = timeout
        return self._wait(timeout)

    def warm(self, timeout):
        t0 = time.perf_counter()
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        ok = self._wait(timeout)
        self.warm_total += time.perf_counter() - t0
        return ok

    def close(self):
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=20)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
        self.err.close()

    def record(self):
        if self.result is None:
            r = {"problem": self.problem, "tool": self.tool, "status": self.status}
            if self.status == "timeout":
                r["timeout_s"] = self.timeout
            else:
                r["error"] = getattr(self, "error", "")
            return r
        return {**self.result, "status": "ok"}


def run_problem(problem, tools, repeats, timeout, budget, log=print):
    """Cold calls one tool at a time (each in a fresh process, the others idle), then
    `repeats` rounds of warm calls, interleaved across the tools (the order rotates each
    round), so that a change of machine load affects every tool alike. A tool gets no
    further warm call once its warm calls have used `budget` seconds (or when its last
    call says the next one would overrun it); a call that does not finish within
    `timeout` s is stopped (a cold call: "timeout"; a warm call: the runs so far are kept)."""
    pairs = []
    for tool in tools:
        pair = Pair(problem, tool)
        pair.cold(timeout)
        pairs.append(pair)
        r = pair.record()
        if r["status"] == "ok":
            log(
                f"{problem:16s} {tool:14s} cold {_t(r['cold_s']):>9s}  C = {r['loss']:.6e}  "
                f"it {r['iterations']}  {r['stop']}"
            )
        else:
            log(f"{problem:16s} {tool:14s} {r['status']} {r.get('error', '')}")
        # an idle JAX process holds no CPU; a finished tool needs no process
        if not pair.alive:
            pair.close()
    for rnd in range(repeats):
        order = pairs[rnd % len(pairs) :] + pairs[: rnd % len(pairs)]
        for pair in order:
            if not pair.alive:
                continue
            last = (pair.result.get("warm_s") or [pair.result["cold_s"]])[-1]
            if pair.warm_total + last > budget:
                continue
            pair.warm(max(timeout, 3 * last))
    out = []
    for pair in pairs:
        pair.close()
        r = pair.record()
        out.append(r)
        if r["status"] == "ok":
            log(f"{problem:16s} {pair.tool:14s} warm {_t(warm_time(r)):>9s} (n={len(r['warm_s'])})")
    return out


# ------------------------------------------------------------------------------ report


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return None if not n else (xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2]))


def _t(x):
    if x is None:
        return "—"
    return f"{x * 1e3:.3g} ms" if x < 1 else f"{x:.3g} s"


def _ratio(a, b):
    if a is None or b is None or b <= 0:
        return "—"
    r = a / b
    return f"{r:.3g}x"


def warm_time(r):
    """Median of the warm calls; the first call's time where no warm call fitted the budget."""
    if r.get("status") != "ok":
        return None
    return _median(r.get("warm_s") or []) or r.get("cold_s")


def _runs(r):
    n = len(r.get("warm_s") or [])
    return str(n) if n else "1st call only"


def summarise(results):
    """Per problem: the oneshot reference (best warm fit() total of LM/GN) and the best peer."""
    by_problem = {}
    for r in results:
        by_problem.setdefault(r["problem"], []).append(r)
    summary = {}
    for prob, rows in by_problem.items():
        ok = [r for r in rows if r["status"] == "ok"]
        best_loss = min((r["loss"] for r in ok), default=None)
        one = [r for r in ok if r["tool"].startswith("oneshot") and warm_time(r) is not None]
        ref = min(one, key=warm_time) if one else None
        peers = [r for r in ok if not r["tool"].startswith("oneshot") and warm_time(r) is not None]
        # A peer counts as "solving" the problem when its loss is within 1e-6 of the best.
        solved = [r for r in peers if r["loss"] <= best_loss * (1 + 1e-6)]
        best_peer = min(solved, key=warm_time) if solved else None
        fastest_any = min(peers, key=warm_time) if peers else None
        summary[prob] = {
            "rows": rows,
            "best_loss": best_loss,
            "ref": ref,
            "best_peer": best_peer,
            "fastest_peer_any_loss": fastest_any,
        }
    return summary


def fmt_problem(prob, s):
    import peers_tools

    rows, ref, best = s["rows"], s["ref"], s["best_loss"]
    any_ok = next((r for r in rows if r["status"] == "ok"), None)
    title = any_ok["title"] if any_ok else prob
    lines = [f"### {title}", ""]
    if any_ok:
        lines.append(
            f"{any_ok['n_var']} unknowns, {any_ok['n_res']} residuals; parameter error "
            f"= max_i |theta_i / ref_i - 1| against the {any_ok['truth_label']}; loss at the "
            f"start C0 = {any_ok['loss_start']:.4e}."
        )
        if any_ok.get("notes"):
            lines.append(any_ok["notes"])
        lines.append("")
    ref_t = warm_time(ref) if ref else None
    ref_cold = ref["cold_s"] if ref else None
    lines.append(
        "| tool | time, no JIT (median) | runs | time with JIT/build (1st call) | "
        "ratio tool / oneshot_jax (no JIT) | ratio (with JIT) | loss C | C / C_best - 1 "
        "| param. error | iterations | f-evals | stop |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r["status"] != "ok":
            what = (
                f"timeout at {r['timeout_s']:.0f} s"
                if r["status"] == "timeout"
                else f"error: {r.get('error', '')[:120]}"
            )
            label = peers_tools.LABELS.get(r["tool"], r["tool"])
            lines.append(f"| {label} | {what} | | | | | | | | | | |")
            continue
        wt = warm_time(r)
        name = r["label"] + (" **[reference]**" if r is ref else "")
        excess = (r["loss"] / best - 1) if best else None
        pe = "—" if r["param_error"] is None else f"{100 * r['param_error']:.3g} %"
        lines.append(
            f"| {name} | {_t(wt)} | {_runs(r)} | {_t(r['cold_s'])} | {_ratio(wt, ref_t)} | "
            f"{_ratio(r['cold_s'], ref_cold)} | {r['loss']:.6e} | {excess:.1e} | {pe} | "
            f"{r['iterations'] if r['iterations'] is not None else '—'} | "
            f"{r['fevals'] if r['fevals'] is not None else '—'} | {r['stop']} |"
        )
        if r["tool"].startswith("oneshot"):
            sw = _median(r.get("solver_warm_s") or [])
            lines.append(
                f"| &nbsp;&nbsp;↳ solver only (`FitResult.wall_time`) | {_t(sw)} | "
                f"{len(r.get('solver_warm_s') or [])} | {_t(r.get('solver_cold_s'))} | "
                f"{_ratio(sw, ref_t)} | {_ratio(r.get('solver_cold_s'), ref_cold)} | | | | | | |"
            )
    lines.append("")
    return lines


def fmt_summary(summary, problems):
    lines = [
        "| problem | oneshot_jax (no JIT) | best peer at the optimum | its time | "
        "ratio peer / oneshot_jax | oneshot_jax loss | best peer loss | fastest peer at any loss |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for prob in problems:
        s = summary.get(prob)
        if not s:
            continue
        ref, bp, fa = s["ref"], s["best_peer"], s["fastest_peer_any_loss"]
        if ref is None:
            lines.append(f"| {prob} | — | | | | | | |")
            continue
        rt = warm_time(ref)
        fa_txt = "—" if fa is None else f"{fa['label']}: {_t(warm_time(fa))}, C = {fa['loss']:.4e}"
        if bp is None:
            lines.append(
                f"| {prob} | {_t(rt)} ({ref['tool']}) | none reached the optimum | | | "
                f"{ref['loss']:.6e} | | {fa_txt} |"
            )
            continue
        bt = warm_time(bp)
        lines.append(
            f"| {prob} | {_t(rt)} ({ref['tool']}) | {bp['label']} | {_t(bt)} | "
            f"**{_ratio(bt, rt)}** | {ref['loss']:.6e} | {bp['loss']:.6e} | {fa_txt} |"
        )
    return lines


def fmt_ratio_table(summary, problems, tools):
    head = "| tool | " + " | ".join(problems) + " |"
    lines = [head, "|---|" + "---|" * len(problems)]
    import peers_tools

    for tool in tools:
        cells = []
        label = peers_tools.LABELS.get(tool, tool)
        for prob in problems:
            s = summary.get(prob)
            r = next((x for x in (s["rows"] if s else []) if x["tool"] == tool), None)
            if r is None:
                cells.append("")
                continue
            label = r.get("label", tool)
            if r["status"] == "timeout":
                cells.append(f"timeout at {r['timeout_s']:.0f} s")
                continue
            if r["status"] != "ok":
                cells.append("error")
                continue
            ref = s["ref"]
            best = s["best_loss"]
            ratio = _ratio(warm_time(r), warm_time(ref) if ref else None)
            cells.append(f"{ratio} (C {r['loss'] / best - 1:+.1e})" if best else ratio)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


_STRATEGY_NAMES = {"jacobian": "formed", "vjp": "matrix-free"}


def targets(summary, problems):
    out = []
    for prob in problems:
        s = summary.get(prob)
        if not s or s["ref"] is None:
            continue
        ref, bp = s["ref"], s["best_peer"]
        rt = warm_time(ref)
        need = 3.0 if prob in ("emps", "chain20") else 1.0
        if bp is None:
            out.append(
                (prob, True, f"no peer reached the optimum (best loss {s['best_loss']:.4e})")
            )
            continue
        ratio = warm_time(bp) / rt
        loss_ok = ref["loss"] <= bp["loss"] * (1 + 1e-6)
        fastest = all(
            warm_time(r) >= rt
            for r in s["rows"]
            if r["status"] == "ok"
            and not r["tool"].startswith("oneshot")
            and warm_time(r) is not None
            and r["loss"] <= s["best_loss"] * (1 + 1e-6)
        )
        met = ratio >= need and loss_ok and fastest
        out.append(
            (
                prob,
                met,
                f"best peer {bp['label']} / oneshot_jax = {ratio:.3g}x "
                f"(target >= {need:g}x), loss {'<=' if loss_ok else '>'} best peer's",
            )
        )
    return out


def fmt_analysis(summary, problems, diags):
    L = [
        "",
        "## Where the time goes",
        "",
        "oneshot_jax's `fit()` against its compiled call alone (the faster of LM / GN per "
        "problem; `FitResult.wall_time`: projection, solve, covariance, metrics); the "
        "difference is Python-side work around it (input checks, setup, `FitResult`):",
        "",
        "| problem | fit() no JIT | solver no JIT | overhead | fit() 1st call | solver 1st call |",
        "|---|---|---|---|---|---|",
    ]
    over = {}
    for prob in problems:
        ref = summary.get(prob, {}).get("ref")
        if not ref:
            continue
        f, sv = warm_time(ref), _median(ref.get("solver_warm_s") or [])
        over[prob] = (f, sv)
        L.append(
            f"| {prob} ({ref['tool']}) | {_t(f)} | {_t(sv)} | "
            f"{_t(f - sv) if sv is not None else '—'} | {_t(ref['cold_s'])} | "
            f"{_t(ref.get('solver_cold_s'))} |"
        )
    diag = {d["problem"]: d for d in diags}
    if diag:
        L += [
            "",
            "One trajectory Jacobian against one simulation (first record, jitted, median "
            "of 20 interleaved rounds): finite differences need (columns + 1) simulations "
            "per Jacobian, "
            "forward-mode autodiff (`jax.jacfwd`) pushes all columns through the rollout. "
            "oneshot_jax's closed form evaluates the sensitivity recursion "
            "S <- A S + [B, 0] in one of two ways (`strategy`): *formed* builds A = df/dx and "
            "B = df/dtheta at every step at once after the forward pass (vmapped jacfwd, the "
            "paper's Remark 1) and leaves the scan only small products; *matrix-free* pushes "
            "the columns of S through the step as JVPs inside the scan. `fit` picks formed "
            "Jacobians for n_x <= 16 and small batches (`strategy='auto'`).",
            "",
            "| problem | T | n_x | columns | one simulation | jacfwd | closed form, formed | "
            "closed form, matrix-free | fit's choice | its cost / simulation | "
            "its cost / jacfwd |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for prob in problems:
            d = diag.get(prob)
            if d:
                c = d["closed_" + d["auto"]]
                L.append(
                    f"| {prob} | {d['T']} | {d['n_x']} | {d['n_columns']} | "
                    f"{_t(d['simulate'])} | {_t(d['jacfwd'])} | {_t(d['closed_jacobian'])} | "
                    f"{_t(d['closed_vjp'])} | {_STRATEGY_NAMES[d['auto']]} | "
                    f"{c / d['simulate']:.3g} | {c / d['jacfwd']:.3g} |"
                )
    L += ["", "## Targets not met: the reasons found", ""]
    missed = [(prob, why) for prob, met, why in targets(summary, problems) if not met]
    if not missed:
        L.append("Every target is met in this run.")
    for prob, why in missed:
        L.append(f"**{prob}** ({why}).")
        L.append("")
        s = summary[prob]
        f, sv = over.get(prob, (None, None))
        bp = s["best_peer"]
        bt = warm_time(bp) if bp else None
        d = diag.get(prob)
        peer = bp["label"] if bp else "the best peer"
        its = sorted(
            {
                r["iterations"]
                for r in s["rows"]
                if r.get("status") == "ok"
                and r["tool"] in ("scipy_trf", "casadi_ipopt", "optimistix_lm")
                and r.get("iterations")
                and r["loss"] <= s["best_loss"] * (1 + 1e-6)
            }
        )
        its_txt = f"{its[0]}-{its[-1]}" if len(its) > 1 else (str(its[0]) if its else "—")
        one_it = s["ref"]["iterations"]
        if sv is not None and bt is not None:
            L.append(
                f"The solver alone (one compiled call: projection, solve, covariance) takes "
                f"{_t(sv)}, {_ratio(bt, sv)} faster than {peer}; `fit()` adds {_t(f - sv)} of "
                "Python-side work around it (input checks, building the `Problem`, "
                "`FitResult`)."
            )
        else:
            L.append("See the per-problem table above.")
        if d:
            c = d["closed_" + d["auto"]]
            # One linearisation at the start and one per accepted step but the last
            # (a converged step is not linearised again): at most one per iteration.
            lin = one_it
            floor = lin * c
            L[-1] += (
                f" One Jacobian ({_STRATEGY_NAMES[d['auto']]}) costs {c / d['simulate']:.3g} "
                f"simulations and {c / d['jacfwd']:.3g}x forward-mode autodiff of the "
                f"rollout, against {d['n_columns'] + 1} simulations for finite differences; "
                f"oneshot_jax linearises at most {lin} times ({one_it} iterations; "
                f"{its_txt} for the Gauss-Newton-type peers). The Jacobians alone take "
                f"{_t(floor)}, so even with nothing else in an iteration it would be "
                f"{_ratio(bt, floor)} faster than {peer}"
            )
            need = 3.0 if prob in ("emps", "chain20") else 1.0
            if bt is not None and bt / floor < need:
                L[-1] += (
                    f": the {need:g}x target needs a Jacobian cheaper than forward-mode "
                    "autodiff, or fewer iterations. Forward sensitivities cost one tangent "
                    "rollout per free parameter whatever the implementation; where every "
                    "parameter reaches every output and there is no initial state to "
                    "eliminate (the chain: x0 known, one record), the structure leaves "
                    "nothing else to exploit."
                )
            else:
                L[-1] += (
                    ": the rest of each iteration (normal-equation products over the stored "
                    "J, trial evaluations) is what is left to cut."
                )
        L.append("")
    first = [prob for prob in problems if summary.get(prob, {}).get("ref")]
    if first:
        L += [
            "**With JIT (first call in a fresh process)** oneshot_jax is slower than most "
            "peers on every problem: its first `fit()` compiles the whole solver loop (a "
            "`while_loop` around the sensitivity scan, the structured solve and the step "
            "logic) and the post-processing (covariance, metrics) with XLA, several seconds "
            "even for the satellite, where scipy's only compilation is the jitted residual "
            "and CasADi generates and compiles C. JAX's persistent compilation cache "
            "(`jax.config.update('jax_compilation_cache_dir', ...)`) takes most of it away "
            "for later processes: `python benchmarks/first_call.py` measures it (README). "
            "What would compile less: the runner is vmapped over starts even for one start.",
            "",
        ]
    return L


def write_report(results, problems, tools, args, path, wall, diags=()):
    import peers_tools

    summary = summarise(results)
    v = peers_tools.versions()
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    load = getattr(args, "load_end", None)
    load0 = getattr(args, "load_start", None)
    cmd = "python benchmarks/peers.py" + (
        " " + " ".join(args.passthrough) if args.passthrough else ""
    )
    L = [
        "# oneshot_jax against its peers",
        "",
        f"Generated by `{cmd}` on {datetime.date.today().isoformat()} in {wall / 60:.1f} min "
        f"(install the peers with `pip install -e .[bench]`).",
        "",
        f"Machine: {cpu}, {os.cpu_count()} CPU cores, float64, CPU only"
        + (
            f"; load average (1/5/15 min) {load0[0]:.1f} / {load0[1]:.1f} / {load0[2]:.1f} at the "
            "start"
            if load0
            else ""
        )
        + (f", {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} at the end" if load else "")
        + ". Other work on the machine slows every tool; the warm calls are interleaved "
        "across tools, so ratios suffer less than absolute times.",
        "No GPU was available to this benchmark: the accelerator part is not measured here.",
        "",
        "Versions: "
        + ", ".join(f"{k} {val}" for k, val in v.items())
        + (f"; oneshot_jax at commit {args.commit}" if getattr(args, "commit", None) else "")
        + ".",
        "",
        "## Summary",
        "",
        "Time to solution without compilation (median of warm calls, each a fresh solve from the "
        'same start); oneshot_jax is its `fit()` call, the faster of LM and GN. "Best peer" is '
        "the fastest peer whose loss is within 1e-6 (relative) of the best loss any tool reached.",
        "",
    ]
    L += fmt_summary(summary, problems)
    L += [
        "",
        "Targets (fastest on every problem with a loss no worse than the best peer's; "
        ">= 3x faster than the best peer on (b) and (c)):",
        "",
    ]
    for prob, met, why in targets(summary, problems):
        L.append(f"- {prob}: **{'met' if met else 'NOT met'}** — {why}")
    L += [
        "",
        "## Ratios to oneshot_jax",
        "",
        "Each cell: time without compilation / oneshot_jax's (reference row of that problem), "
        "and the loss reached relative to the best (C / C_best - 1).",
        "",
    ]
    L += fmt_ratio_table(summary, problems, tools)
    L += ["", "## Per problem", ""]
    for prob in problems:
        if prob in summary:
            L += fmt_problem(prob, summary[prob])
    L += ["## How each tool is used", ""]
    seen = {}
    for r in results:
        if r["status"] == "ok" and r["tool"] not in seen:
            seen[r["tool"]] = (r["label"], r["method"])
    for tool in tools:
        if tool in seen:
            L.append(f"- **{seen[tool][0]}**: {seen[tool][1]}.")
    L += fmt_analysis(summary, problems, diags)
    L += ["", NOTES]
    Path(path).write_text("\n".join(L) + "\n")
    return summary


NOTES = """## Notes on the method

- Same cost, same model, same start for every tool: C = mean over records and samples of
  ||zhat - z||^2 (eq. 5), classical RK4 with one step per sample and the input held over
  it; sign(q') of the EMPS friction is tanh(q'/1e-3) for every tool. The loss column is
  recomputed for every tool by one common JAX evaluator at the parameters it returned.
- "No JIT" is the median over repeated calls in the same process after the first one (each
  call a full solve from the start point; a JAX function is compiled once, a CasADi
  solver object is built once). "With JIT/build" is the first call in a fresh process.
  jax-sysid builds new jitted closures inside every `fit()`, so its later calls compile
  again: for it the two columns differ little, which is how the tool behaves.
- Bounds: theta >= 0 (>= 1e-12 for the inertia, >= 1e-6 for M, Fv, Fc) wherever a tool takes
  bounds (oneshot_jax, scipy 'trf', SLSQP, IPOPT, jax-sysid); MINPACK 'lm' and optimistix have
  none. No bound is active at any optimum reported here.
- Tolerances are each tool's defaults except: optimistix rtol = atol = 1e-8 (it has no
  default), oneshot_jax max_epochs = 200, jax-sysid lbfgs_epochs = 1000 (its default).
  SLSQP's default ftol = 1e-6 is an absolute tolerance on a loss of order 1e-8 .. 1e-5 here:
  it stops "successfully" far from the optimum (the effect of the paper's Fig. 5); it is
  listed as a user would meet it.
- jax-sysid takes several records as a list of experiments and sums their losses in a
  Python loop inside one jitted function, so the 248 EMPS windows become 248 unrolled
  scans in one XLA program; in development 10 windows took 27 s (683 L-BFGS-B
  iterations) and 40 windows 92 s, hence the timeout on (b). jax-sysid 1.0.1 also fails
  with bounds and a list of experiments (it builds the default x0 bounds with
  `jnp.ones_like` on a list); the runner passes explicit, unbounded x0 bounds.
- CasADi generates and compiles C for the NLP functions when a compiler is found, as its
  example does (here `gcc` through the 'shell' plugin); that time is in the first call.
- A run that does not finish within the time cap is stopped and reported as a timeout; a
  tool whose first call is slow gets fewer warm runs (the "runs" column) so that the whole
  benchmark stays within about ten minutes.
"""


# -------------------------------------------------------------------------------- main


def _commit():
    """The repository's commit (with '+changes' when the working tree differs from it)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=HERE,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=HERE,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout
        return (head + ("+changes" if dirty.strip() else "")) or None
    except (OSError, subprocess.SubprocessError):
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--problems",
        default=None,
        help="comma-separated subset of: satellite_T50, satellite_T5000, emps, chain20",
    )
    ap.add_argument(
        "--tools", default=None, help="comma-separated subset of: " + ", ".join(DEFAULT_TOOLS)
    )
    ap.add_argument("--repeats", type=int, default=5, help="warm runs per pair (median reported)")
    ap.add_argument(
        "--timeout",
        type=float,
        default=60.0,
        help="seconds the first call of a pair may take before it is stopped",
    )
    ap.add_argument(
        "--budget",
        type=float,
        default=20.0,
        help="seconds per pair after which no further warm run is started",
    )
    ap.add_argument("--quick", action="store_true", help="small problems, 2 repeats; no results.md")
    ap.add_argument("--out", default=str(HERE / "results.md"))
    ap.add_argument("--json", default=None, help="also write the raw results as JSON")
    ap.add_argument("--worker", nargs=2, metavar=("PROBLEM", "TOOL"), help=argparse.SUPPRESS)
    ap.add_argument("--diagnose", default=None, help=argparse.SUPPRESS)
    ap.add_argument(
        "--no-diagnostics",
        action="store_true",
        help="skip the Jacobian-cost diagnostics (one process per problem, ~10 s each)",
    )
    ap.add_argument(
        "--report-only",
        default=None,
        metavar="JSON",
        help="rewrite the report from a JSON file written by --json, without running anything",
    )
    args = ap.parse_args()
    if args.report_only:
        saved = json.loads(Path(args.report_only).read_text())
        m = saved["meta"]
        args.passthrough, args.load_start, args.load_end = (
            m["passthrough"],
            m["load_start"],
            m["load_end"],
        )
        args.commit = m.get("commit")
        write_report(
            saved["results"],
            m["problems"],
            m["tools"],
            args,
            args.out,
            m["wall_s"],
            saved["diagnostics"],
        )
        print(f"wrote {args.out}")
        return
    if args.worker:
        worker(args.worker[0], args.worker[1])
        return
    if args.diagnose:
        diagnose_worker(args.diagnose)
        return
    # the command shown in results.md: without the output paths
    argv, args.passthrough = sys.argv[1:], []
    while argv:
        a = argv.pop(0)
        if a in ("--json", "--out", "--report-only"):
            argv = argv[1:]
        elif not a.startswith(("--json=", "--out=", "--report-only=")):
            args.passthrough.append(a)
    import peers_problems

    if args.quick:
        problems = ["satellite_T50", "chain5_quick"]
        args.repeats, args.timeout = 2, 60.0
    else:
        problems = list(peers_problems.PROBLEMS)
    if args.problems:
        problems = args.problems.split(",")
    tools = args.tools.split(",") if args.tools else list(DEFAULT_TOOLS)
    t0 = time.perf_counter()
    try:
        args.load_start = os.getloadavg()
    except OSError:
        args.load_start = None
    args.commit = _commit()
    results = []
    for prob in problems:
        results += run_problem(
            prob, tools, args.repeats, args.timeout, args.budget, log=lambda m: print(m, flush=True)
        )
    diags = []
    if not args.no_diagnostics:
        for prob in problems:
            if prob.startswith("emps"):
                continue  # its target is about the per-window structure, not the Jacobian
            d = run_diagnose(prob)
            if d:
                diags.append(d)
                print(
                    f"{prob:16s} one simulation {_t(d['simulate'])}, Jacobian: jacfwd "
                    f"{_t(d['jacfwd'])}, closed form formed {_t(d['closed_jacobian'])}, "
                    f"matrix-free {_t(d['closed_vjp'])} (fit uses {d['auto']})",
                    flush=True,
                )
    wall = time.perf_counter() - t0
    try:
        args.load_end = os.getloadavg()
    except OSError:
        args.load_end = None
    if args.json:
        meta = {
            "problems": problems,
            "tools": tools,
            "wall_s": wall,
            "passthrough": args.passthrough,
            "load_start": args.load_start,
            "load_end": args.load_end,
            "commit": args.commit,
        }
        Path(args.json).write_text(
            json.dumps({"results": results, "diagnostics": diags, "meta": meta}, indent=1)
        )
    out = None if args.quick else args.out
    if out:
        write_report(results, problems, tools, args, out, wall, diags)
        print(f"\nwrote {out} ({wall / 60:.1f} min)")
    else:
        summary = summarise(results)
        print()
        print("\n".join(fmt_ratio_table(summary, problems, tools)))


if __name__ == "__main__":
    main()
