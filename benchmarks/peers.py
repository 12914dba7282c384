"""Side-by-side benchmark of oneshot_jax against the tools a user would otherwise pick.

Problems (`peers_problems.py`): (a) the satellite of Section 4 at T = 50 and T = 5000,
(b) the EMPS benchmark as a windowed fit (248 windows of 100 samples, each with its own
initial state), (c) a chain of 20 masses with 40 unknown stiffness and damping values,
(d) `tanks_hybrid`: the cascaded tanks with an MLP residual (`peers_hybrid.py`), against
jax-sysid only: the cost of one gradient, and Adam + L-BFGS fits with the same budget.

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

One run measures every part, (a) to (d), and prints its report; `--json PATH` keeps the
whole run (numbers, command, date, duration, load average, hardware, versions, commit),
and `--render PATH` prints the report of a kept run again, as it stands in the section
"Against other tools" of docs/benchmarks.md (whose run is `benchmarks/cpu/peers.json`).

Run:  python benchmarks/peers.py --pin-cpu 1 --json benchmarks/cpu/peers.json   # the page's run
      python benchmarks/peers.py --render benchmarks/cpu/peers.json   # its report, printed
      python benchmarks/peers.py                  # everything, also writes benchmarks/results.md
      python benchmarks/peers.py --quick          # a small smoke run (does not write results.md)
      python benchmarks/peers.py --problems emps --tools oneshot_lm,scipy_trf
      python benchmarks/peers.py --problems tanks_hybrid --pin-cpu 1   # (d) only, printed
Needs the peers: pip install -e .[bench]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from timing import commit, cpu_name, fmt_time  # noqa: E402

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
HYBRID = "tanks_hybrid"  # (d): its own protocol (`peers_hybrid.py`), not a `peers_problems` one


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


def hybrid_worker(adam, lbfgs, repeats):
    """Runs in its own process: the hybrid-tanks comparison (`peers_hybrid.measure`)."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    import peers_hybrid

    out = peers_hybrid.measure(
        adam=adam, lbfgs=lbfgs, repeats=repeats, log=lambda m: print(m, file=sys.stderr, flush=True)
    )
    print(MARK + json.dumps(out), flush=True)


def run_hybrid(adam, lbfgs, repeats, timeout=900):
    """The hybrid-tanks comparison in a fresh process: its numbers, or a dict with "status"
    "timeout" or "error" (and a message) where it gave none."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--hybrid-worker"]
    cmd += [str(adam), str(lbfgs), str(repeats)]
    try:
        cp = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        print(f"tanks_hybrid: timeout at {timeout} s")
        return {"status": "timeout", "timeout_s": timeout}
    sys.stderr.write(cp.stderr)
    for line in cp.stdout.splitlines():
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    print("tanks_hybrid failed (its messages are above)")
    lines = cp.stderr.strip().splitlines()
    # the exception's line (JAX may print a note on its traceback after it)
    error = next((x for x in reversed(lines) if re.match(r"\w+(Error|Exception)\b", x)), None)
    return {"status": "error", "error": error or " | ".join(lines[-3:])}


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
    return statistics.median(xs) if xs else None


_t = fmt_time


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


def fmt_problem(prob, s, level=4):
    """The table of one problem, under a heading of `level` (the number of #)."""
    import peers_tools

    rows, ref, best = s["rows"], s["ref"], s["best_loss"]
    any_ok = next((r for r in rows if r["status"] == "ok"), None)
    title = any_ok["title"] if any_ok else prob
    lines = [f"{'#' * level} {title}", ""]
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
            label = r.get("label", label)
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


def fmt_where(summary, problems, diags, level=3):
    """Two tables: oneshot_jax's `fit()` against its compiled call alone, and the cost of
    one trajectory Jacobian against one simulation (under a heading of `level`)."""
    L = [
        "",
        f"{'#' * level} Where the time goes",
        "",
        "oneshot_jax's `fit()` against its compiled call alone (the faster of LM / GN per "
        "problem; `FitResult.wall_time`: projection, solve, covariance, metrics); the "
        "difference is Python-side work around it (input checks, setup, `FitResult`):",
        "",
        "| problem | fit() no JIT | solver no JIT | overhead | fit() 1st call | solver 1st call |",
        "|---|---|---|---|---|---|",
    ]
    for prob in problems:
        ref = summary.get(prob, {}).get("ref")
        if not ref:
            continue
        f, sv = warm_time(ref), _median(ref.get("solver_warm_s") or [])
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
            "per Jacobian, forward-mode autodiff (`jax.jacfwd`) pushes all columns through "
            "the rollout. oneshot_jax's closed form evaluates the sensitivity recursion "
            "S <- A S + [B, 0] in one of two ways (`strategy`): *formed* builds A = df/dx and "
            "B = df/dtheta at every step at once after the forward pass (vmapped jacfwd, the "
            "paper's Remark 1); *matrix-free* pushes the columns of S through the step as JVPs "
            "inside the scan. `fit` picks formed Jacobians for n_x <= 16 and small batches "
            "(`strategy='auto'`).",
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
    return L


def fmt_faster(summary, problems):
    """Sentences computed from the numbers: per problem where oneshot_jax gave no result or
    stopped above the best loss, and where a peer reached the optimum faster than
    oneshot_jax (time without compilation), or one sentence saying that on every problem
    oneshot_jax reached the best loss and no peer was faster; then one per problem where a
    peer's first call (compilation included, in a fresh process) reached the optimum
    faster than oneshot_jax's first call."""
    faster, first = [], []
    for prob in problems:
        s = summary.get(prob)
        if not s:
            continue
        ref, best = s["ref"], s["best_loss"]
        if ref is None:
            faster.append(f"On {prob}, oneshot_jax gave no result.")
            continue
        if ref["loss"] > best * (1 + 1e-6):
            faster.append(
                f"On {prob}, oneshot_jax stopped at C = {ref['loss']:.6e}, above the best loss "
                f"{best:.6e}."
            )
        if s["best_peer"] is None:
            continue
        rt, bt = warm_time(ref), warm_time(s["best_peer"])
        if bt < rt:
            faster.append(
                f"On {prob}, {s['best_peer']['label']} reached the optimum faster than "
                f"oneshot_jax: {_t(bt)} against {_t(rt)} ({rt / bt:.3g}x)."
            )
        solved = [
            r
            for r in s["rows"]
            if r["status"] == "ok"
            and not r["tool"].startswith("oneshot")
            and r["loss"] <= best * (1 + 1e-6)
            and r.get("cold_s") is not None
        ]
        one = [
            r
            for r in s["rows"]
            if r["status"] == "ok" and r["tool"].startswith("oneshot") and r.get("cold_s")
        ]
        if solved and one:
            peer = min(solved, key=lambda r: r["cold_s"])
            ours = min(one, key=lambda r: r["cold_s"])
            if peer["cold_s"] < ours["cold_s"]:
                first.append(
                    f"On {prob}, the first call of {peer['label']} (compilation included) "
                    f"reached the optimum faster than oneshot_jax's first call: "
                    f"{_t(peer['cold_s'])} against {_t(ours['cold_s'])} "
                    f"({ours['cold_s'] / peer['cold_s']:.3g}x)."
                )
    if not faster:
        faster = [
            "On every problem here oneshot_jax reached the best loss, and no peer reached it "
            "faster (time without compilation)."
        ]
    return faster + first


def fmt_conditions(m):
    """The two paragraphs of a run's conditions: the command, date, duration and load
    average; the hardware, the versions and the commit."""
    load = m.get("load_average")
    load = f", load average {load[0]:.1f} -> {load[1]:.1f}" if load else ""
    at = ""
    if m.get("commit"):
        at = f"; oneshot_jax at commit {m['commit']}"
        if m.get("changed"):
            at += " (the files that differed from it: " + ", ".join(m["changed"]) + ")"
    return [
        f"Generated by `{m['command']}` on {m['date']} in {m['wall_s'] / 60:.1f} min{load} "
        "(install the peers with `pip install -e .[bench]`).",
        "",
        f"Hardware: {m['hardware']}, {m['cores']} CPU cores, CPU only, float64. Versions: "
        + ", ".join(f"{k} {val}" for k, val in m["versions"].items())
        + at
        + ".",
        "",
    ]


def fmt_tanks(hybrid, level):
    """Part (d), under a heading of `level`: its tables, or why the run has none."""
    title = "(d) hybrid cascaded tanks: oneshot_jax against jax-sysid"
    if "grad_s" in hybrid:
        import peers_hybrid

        head, *rest = peers_hybrid.fmt_hybrid(hybrid)
        assert head.lstrip("#").strip() == title, head
        return [f"{'#' * level} {title}", *rest]
    what = (
        f"stopped at the time cap of {hybrid['timeout_s']:.0f} s"
        if hybrid.get("status") == "timeout"
        else f"it failed: {hybrid.get('error', '')[:200]}"
    )
    return [f"{'#' * level} {title}", "", f"No result in this run ({what}).", ""]


def report(data, level=3):
    """A run (the dict that `--json` writes) as Markdown lines: its conditions, then the
    sections under headings of `level` (3 on the benchmarks page, whose section "Against
    other tools" holds them; 2 in results.md), each problem one level below."""
    m = data["meta"]
    results, problems, tools = data["results"], m["problems"], m["tools"]
    diags, hybrid = data.get("diagnostics") or [], data.get("hybrid")
    summary = summarise(results)
    sec = "#" * level
    L = fmt_conditions(m)
    if problems:
        L += [
            f"{sec} Summary",
            "",
            "Time to solution without compilation (median of warm calls, each a fresh solve "
            "from the same start); oneshot_jax is its `fit()` call, the faster of LM and GN. "
            '"Best peer" is the fastest peer whose loss is within 1e-6 (relative) of the best '
            "loss any tool reached.",
            "",
        ]
        L += fmt_summary(summary, problems)
        L += ["", *fmt_faster(summary, problems)]
        L += [
            "",
            f"{sec} Ratios to oneshot_jax",
            "",
            "Each cell: time without compilation / oneshot_jax's (reference row of that "
            "problem), and the loss reached relative to the best (C / C_best - 1).",
            "",
        ]
        L += fmt_ratio_table(summary, problems, tools)
        L += [""]
    if problems or hybrid is not None:
        L += [f"{sec} Per problem", ""]
    for prob in problems:
        if prob in summary:
            L += fmt_problem(prob, summary[prob], level + 1)
    if hybrid is not None:
        L += fmt_tanks(hybrid, level + 1)
    if problems:
        L += [f"{sec} How each tool is used", ""]
        seen = {}
        for r in results:
            if r["status"] == "ok" and r["tool"] not in seen:
                seen[r["tool"]] = (r["label"], r["method"])
        for tool in tools:
            if tool in seen:
                L.append(f"- **{seen[tool][0]}**: {seen[tool][1]}.")
        L += fmt_where(summary, problems, diags, level)
        L += ["", f"{sec} Notes on the method", "", NOTES]
    return L


def render(path):
    """The report of a run written by `--json`, as it stands on the benchmarks page."""
    print("\n".join(report(json.loads(Path(path).read_text()), 3)).rstrip())


def write_report(data, path):
    """results.md: a title and the report with its sections at level 2."""
    Path(path).write_text("# oneshot_jax against its peers\n\n" + "\n".join(report(data, 2)))


NOTES = """- Same cost, same model, same start for every tool: C = mean over records and samples of
  ||zhat - z||^2 (eq. 5), classical RK4 with one step per sample and the input held over
  it; sign(q') of the EMPS friction is tanh(q'/1e-3) for every tool. The loss column is
  recomputed for every tool by one common JAX evaluator at the parameters it returned.
- "No JIT" is the median over repeated calls in the same process after the first one (each
  call a full solve from the start point; a JAX function is compiled once, a CasADi
  solver object is built once). "With JIT/build" is the first call in a fresh process.
  jax-sysid builds new jitted closures inside every `fit()`, so its later calls compile
  again: for it the two columns differ little, which is how the tool behaves.
- Bounds: theta >= 0 (>= 1e-12 for the inertia, >= 1e-6 for M, Fv, Fc) wherever a tool takes
  bounds (oneshot_jax, scipy 'trf', SLSQP, IPOPT, jax-sysid); MINPACK 'lm' and optimistix
  have none.
- Tolerances are each tool's defaults except: optimistix rtol = atol = 1e-8 (it has no
  default), oneshot_jax max_steps = 200, jax-sysid lbfgs_epochs = 1000 (its default).
  SLSQP's default ftol = 1e-6 is an absolute tolerance on a loss of order 1e-8 .. 1e-5 here,
  so it can stop "successfully" far from the optimum (the effect of the paper's Fig. 5); it
  is listed as a user would meet it, and the loss column shows where it stopped.
- jax-sysid takes several records as a list of experiments and sums their losses in a
  Python loop inside one jitted function, so the EMPS windows become one unrolled scan each
  in one XLA program, whose compilation grows with the number of windows. jax-sysid 1.0.1
  also fails with bounds and a list of experiments (it builds the default x0 bounds with
  `jnp.ones_like` on a list); the runner passes explicit, unbounded x0 bounds.
- CasADi generates and compiles C for the NLP functions when a compiler is found, as its
  example does; that time is in the first call.
- A run that does not finish within the time cap (`--timeout`) is stopped and reported as
  a timeout; a tool whose calls are slow gets fewer warm runs (the "runs" column, capped by
  `--budget` seconds per tool).
"""


# -------------------------------------------------------------------------------- main


def changed_files():
    """The library's and the benchmarks' Python files that differ from the commit, tracked
    or not (what `timing.commit`'s "+changes" stands for)."""
    try:
        cp = subprocess.run(
            ["git", "status", "--porcelain", "--", "oneshot_jax", "benchmarks/*.py"],
            cwd=HERE.parent,
            capture_output=True,
            text=True,
        )
    except OSError:
        return []
    if cp.returncode:
        return []
    return sorted(line[3:].strip() for line in cp.stdout.splitlines() if line.strip())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--problems",
        default=None,
        help="comma-separated subset of: satellite_T50, satellite_T5000, emps, chain20, "
        "tanks_hybrid",
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
    ap.add_argument(
        "--hybrid-budget",
        default="200,100",
        metavar="ADAM,LBFGS",
        help="tanks_hybrid: Adam epochs and L-BFGS iterations of each fit (default 200,100)",
    )
    ap.add_argument(
        "--hybrid-repeats",
        type=int,
        default=2,
        help="tanks_hybrid: fits of each tool after the first call (default 2)",
    )
    ap.add_argument(
        "--pin-cpu",
        type=int,
        metavar="N",
        help="run every worker process on CPU N only (XLA's threads included): steadier on a "
        "busy machine",
    )
    ap.add_argument("--quick", action="store_true", help="small problems, 2 repeats; no results.md")
    ap.add_argument("--out", default=str(HERE / "results.md"))
    ap.add_argument(
        "--json", default=None, metavar="PATH", help="also write the whole run as JSON to PATH"
    )
    ap.add_argument(
        "--render",
        default=None,
        metavar="JSON",
        help="print the report of a run written by --json (as on the benchmarks page), "
        "without running anything",
    )
    ap.add_argument(
        "--report-only",
        default=None,
        metavar="JSON",
        help="rewrite results.md (--out) from a run written by --json, without running anything",
    )
    ap.add_argument("--worker", nargs=2, metavar=("PROBLEM", "TOOL"), help=argparse.SUPPRESS)
    ap.add_argument("--diagnose", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--hybrid-worker", nargs=3, type=int, help=argparse.SUPPRESS)
    ap.add_argument(
        "--no-diagnostics",
        action="store_true",
        help="skip the Jacobian-cost diagnostics (one process per problem, ~10 s each)",
    )
    args = ap.parse_args()
    if args.render:
        render(args.render)
        return
    if args.report_only:
        write_report(json.loads(Path(args.report_only).read_text()), args.out)
        print(f"wrote {args.out}")
        return
    if args.worker:
        worker(args.worker[0], args.worker[1])
        return
    if args.diagnose:
        diagnose_worker(args.diagnose)
        return
    if args.hybrid_worker:
        hybrid_worker(*args.hybrid_worker)
        return
    if args.pin_cpu is not None:  # inherited by every worker process
        os.sched_setaffinity(0, {args.pin_cpu})
    # the command shown in the report: without the output paths
    argv, shown = sys.argv[1:], []
    while argv:
        a = argv.pop(0)
        if a in ("--json", "--out"):
            argv = argv[1:]
        elif not a.startswith(("--json=", "--out=")):
            shown.append(a)
    import peers_problems
    import peers_tools

    if args.quick:
        problems = ["satellite_T50", "chain5_quick"]
        args.repeats, args.timeout = 2, 60.0
    else:
        problems = [*peers_problems.PROBLEMS, HYBRID]
    if args.problems:
        problems = args.problems.split(",")
    run_tanks = HYBRID in problems
    problems = [p for p in problems if p != HYBRID]
    tools = args.tools.split(",") if args.tools else list(DEFAULT_TOOLS)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    meta = {
        "command": " ".join(["python benchmarks/peers.py", *shown]),
        "date": datetime.date.today().isoformat(),
        "hardware": cpu_name(),
        "cores": os.cpu_count(),
        "versions": peers_tools.versions(),
        "commit": commit() or None,
        "changed": changed_files(),
        "problems": problems,
        "tools": tools,
        "repeats": args.repeats,
        "timeout_s": args.timeout,
        "budget_s": args.budget,
    }
    results = []
    for prob in problems:
        results += run_problem(
            prob, tools, args.repeats, args.timeout, args.budget, log=lambda m: print(m, flush=True)
        )
    hybrid = None
    if run_tanks:
        adam, lbfgs = (int(n) for n in args.hybrid_budget.split(","))
        hybrid = run_hybrid(adam, lbfgs, args.hybrid_repeats)
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
    meta["wall_s"] = time.perf_counter() - t0
    meta["load_average"] = [load0, os.getloadavg()[0]]
    data = {"results": results, "diagnostics": diags, "hybrid": hybrid, "meta": meta}
    if args.json:
        Path(args.json).write_text(json.dumps(data, indent=1) + "\n")
    out = None if args.quick or not problems else args.out  # (d) alone: printed only
    if out:
        write_report(data, out)
    print()
    print("\n".join(report(data, 3)).rstrip())
    if out:
        print(f"\nwrote {out} ({meta['wall_s'] / 60:.1f} min)")


if __name__ == "__main__":
    main()
