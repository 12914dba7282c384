"""The first `fit()` and `predict()` in a fresh process, with and without JAX's persistent
compilation cache (`oneshot_jax.enable_compilation_cache`), and the per-call overhead of
a compiled `fit()`.

Three problems:

- `pendulum`: a damped pendulum driven by a motor torque, dx/dt = (x1, -w0sq sin(x0) -
  c x1 + b u0), RK4 at dt = 0.02 s, the angle measured (1 % noise), T = 1500 samples of
  a multisine input (data made in NumPy, so that nothing is compiled before the timed
  calls); `fit` from theta0 = {w0sq: 5, c: 1, b: 1}, x0 = (0.2, 0) with the default
  solver (Levenberg-Marquardt), then `result.predict(u, z[:20])` (x0 of the record from
  its first 20 outputs, then the whole record simulated);
- `satellite`: the paper's satellite (`oneshot_jax.examples.satellite`), T = 50,
  Gauss-Newton with `constraints=positive()`, and `result.predict(u, z[:10])`.
- `hybrid`: a Duffing oscillator (q'' = u - c q' - k q - eps q^3, RK4 at dt = 0.05 s, the
  position measured with 1 % noise, T = 600 samples of a multisine) fitted as a hybrid
  whose cubic spring is an MLP r(q, q') (`oneshot_jax.residual.MLP`, one hidden layer of
  8, 33 weights): `fit` with 300 steps of `Adam(1e-2)` from c = 0.2, k = 0.8 and the
  network at its start, then `result.predict(u, z[:20])`.

Each problem runs in three fresh processes that share one empty cache folder:

- `no cache`: the cache is off (what a fresh process costs by default);
- `cache, cold`: `enable_compilation_cache(folder)` on the empty folder: this process
  compiles and writes;
- `cache, warm`: a later process that loads the compiled code from the folder.

Each process reports: the import of `oneshot_jax`; the first `fit()` and the first
`predict()` (compilation included), with the time JAX spent tracing the Python code
(jaxpr), lowering it (MLIR) and in XLA's compiler, and the number of programs XLA
compiled (from `jax.monitoring`; with the cache warm, the programs loaded; on a CPU the
first fit's count includes the one-element program by which the library asks, once per
process, whether XLA takes its compiler options); then, over
`--repeats` later calls with the same shapes, the median of a `fit()` call, of its
`FitResult.wall_time` (the compiled solve, covariance and metrics, and the checks of its
result) and of the overhead
(a call's wall time minus its `wall_time`: the input checks, the setup and the assembly
of the `FitResult`), and the median of a later `predict()`.

Run: `python benchmarks/first_call.py` (`--repeats N`, `--problems pendulum satellite
hybrid`)
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from timing import conditions

HERE = Path(__file__).resolve().parent

WORKER = r"""
import json, statistics, sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import oneshot_jax as oj
t_import = time.perf_counter() - t0
sys.path.insert(0, sys.argv[3])
from first_call import problem

cache, name, repeats = sys.argv[1], sys.argv[2], int(sys.argv[4])
if cache != "off":
    if hasattr(oj, "enable_compilation_cache"):
        oj.enable_compilation_cache(cache)
    else:  # an older checkout, for comparison: the same settings by hand
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

phases = {}
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}
def listen(event, seconds, **kwargs):
    if event in EVENTS:
        phases[EVENTS[event]] = phases.get(EVENTS[event], 0.0) + seconds
    if event == "/jax/core/compile/backend_compile_duration":
        phases["programs"] = phases.get("programs", 0) + 1
jax.monitoring.register_event_duration_secs_listener(listen)
hits = []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None
)

fit, predict = problem(name)

def first(fn):
    phases.clear()
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t, dict(phases)

r, t_fit, ph_fit = first(fit)
p, t_pred, ph_pred = first(lambda: predict(r))
calls, walls, over = [], [], []
for _ in range(repeats):
    t = time.perf_counter()
    s = fit()
    dt = time.perf_counter() - t
    calls.append(dt); walls.append(s.wall_time); over.append(dt - s.wall_time)
preds = []
for _ in range(max(3, repeats // 5)):
    t = time.perf_counter()
    jax.block_until_ready(predict(r))
    preds.append(time.perf_counter() - t)
med = statistics.median
print(json.dumps({
    "import": t_import, "fit": t_fit, "fit_phases": ph_fit, "predict": t_pred,
    "predict_phases": ph_pred, "call": med(calls), "wall": med(walls), "overhead": med(over),
    "predict_call": med(preds), "loss": float(r.loss), "cache_hits": len(hits),
}))
"""


def _rk4(rhs_np, x0, u, dt):
    """States (T, n) of dx/dt = rhs_np(x, u) from x0 by RK4 in NumPy (nothing compiled),
    the input u (T, n_u) held over each interval."""
    import numpy as np

    x = np.zeros((u.shape[0], len(x0)))
    x[0] = x0
    for k in range(u.shape[0] - 1):
        k1 = rhs_np(x[k], u[k])
        k2 = rhs_np(x[k] + 0.5 * dt * k1, u[k])
        k3 = rhs_np(x[k] + 0.5 * dt * k2, u[k])
        k4 = rhs_np(x[k] + dt * k3, u[k])
        x[k + 1] = x[k] + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def problem(name):
    """`(fit, predict)` for a problem: `fit()` returns a `FitResult`, `predict(result)` a
    `Prediction`. Data are made in NumPy (nothing compiled before the timed calls)."""
    import numpy as np

    import oneshot_jax as oj

    if name == "pendulum":
        import jax.numpy as jnp

        dt, T = 0.02, 1500

        def rhs(x, u, th):
            return jnp.array([x[1], -th["w0sq"] * jnp.sin(x[0]) - th["c"] * x[1] + th["b"] * u[0]])

        def rhs_np(x, u, w0sq=9.0, c=0.5, b=2.0):
            return np.array([x[1], -w0sq * np.sin(x[0]) - c * x[1] + b * u[0]])

        rng = np.random.default_rng(0)
        t = np.arange(T) * dt
        freqs = np.array([0.1, 0.3, 0.7, 1.3, 2.1])
        phase = rng.uniform(0, 2 * np.pi, freqs.size)
        u = np.sum(np.sin(2 * np.pi * freqs * t[:, None] + phase), axis=1)[:, None]
        x = _rk4(rhs_np, (0.2, 0.0), u, dt)
        z = x[:, :1] + 0.01 * np.std(x[:, 0]) * rng.standard_normal((T, 1))
        model = oj.Model.from_ode(rhs, dt, observe=lambda x, u, th: x[:1])
        theta0 = {"w0sq": 5.0, "c": 1.0, "b": 1.0}
        x0 = np.array([0.2, 0.0])
        return (
            lambda: oj.fit(model, theta0, x0, u, z),
            lambda r: r.predict(u, z[:20]),
        )
    if name == "satellite":
        from oneshot_jax.examples import satellite

        model = satellite.model()
        data = satellite.generate([0], 50)
        M, z = data["u"][0], data["z"][0]
        theta0 = {"I": np.asarray(satellite.THETA0)}
        w0 = np.asarray(satellite.W0)
        return (
            lambda: oj.fit(
                model,
                theta0,
                w0,
                M,
                z,
                solver="gauss_newton",
                constraints=oj.constraints.positive(),
            ),
            lambda r: r.predict(M, z[:10]),
        )
    if name == "hybrid":
        import jax
        import jax.numpy as jnp

        from oneshot_jax.residual import MLP

        dt, T = 0.05, 600

        def rhs_np(x, u, c=0.3, k=1.0, eps=0.8):
            return np.array([x[1], u[0] - c * x[1] - k * x[0] - eps * x[0] ** 3])

        def hybrid(x, u, th):
            return jnp.stack([x[1], u[0] - th["c"] * x[1] - th["k"] * x[0] + th["r"](x)[0]])

        rng = np.random.default_rng(0)
        t = dt * np.arange(T)
        w = 2 * np.pi * np.linspace(0.05, 0.6, 12)
        u = np.sum(np.sin(np.outer(t, w) + rng.uniform(0, 2 * np.pi, 12)), axis=1)[:, None]
        u = 1.5 * u / u.std()
        x = _rk4(rhs_np, (0.5, 0.0), u, dt)
        z = x[:, :1] + 0.01 * np.std(x[:, 0]) * rng.standard_normal((T, 1))
        model = oj.Model.from_ode(hybrid, dt, observe=lambda x, u, th: x[:1])
        theta0 = {"c": 0.2, "k": 0.8, "r": MLP(2, 1, (8,), key=jax.random.PRNGKey(0))}
        x0 = np.array([0.5, 0.0])
        return (
            lambda: oj.fit(model, theta0, x0, u, z, solver=oj.Adam(1e-2, max_steps=300)),
            lambda r: r.predict(u, z[:20]),
        )
    raise ValueError(f"unknown problem {name!r}")


def run(cache, name, repeats):
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    out = subprocess.run(
        [sys.executable, "-c", WORKER, cache, name, str(HERE), str(repeats)],
        capture_output=True,
        text=True,
        env=env,
    )
    if out.returncode:
        raise RuntimeError(f"{name} ({cache}) failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _phases(ph):
    return " / ".join(f"{ph.get(k, 0.0):.2f}" for k in ("trace", "lower", "compile"))


def _programs(ph):
    return str(int(ph.get("programs", 0)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--problems", nargs="+", default=["pendulum", "satellite", "hybrid"])
    args = ap.parse_args()
    rows = []
    for name in args.problems:
        with tempfile.TemporaryDirectory() as cache:
            for label, where in (
                ("no cache", "off"),
                ("cache, cold", cache),
                ("cache, warm", cache),
            ):
                rows.append((name, label, run(where, name, args.repeats)))
    print(
        "First fit() and predict() in a fresh process, and the compiled fit() call "
        f"(medians of {args.repeats} later calls)."
    )
    print(conditions())
    print()
    print(
        "| problem | process | import (s) | first fit() (s) | its trace / lower / XLA compile "
        "(s) | programs | first predict() (s) | its trace / lower / XLA compile (s) | programs "
        "| later fit() (ms) | FitResult.wall_time (ms) | overhead (ms) | later predict() (ms) "
        "| loss |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, label, r in rows:
        print(
            f"| {name} | {label} | {r['import']:.2f} | {r['fit']:.2f} | "
            f"{_phases(r['fit_phases'])} | {_programs(r['fit_phases'])} | {r['predict']:.2f} | "
            f"{_phases(r['predict_phases'])} | {_programs(r['predict_phases'])} "
            f"| {1e3 * r['call']:.2f} | {1e3 * r['wall']:.2f} | {1e3 * r['overhead']:.2f} | "
            f"{1e3 * r['predict_call']:.2f} | {r['loss']:.6e} |"
        )
    print()
    print(
        "Overhead: a fit() call's wall time minus its FitResult.wall_time (input checks, "
        "setup, FitResult assembly), median over the later calls. With the cache warm, "
        "XLA's compiler is skipped (the executables are loaded: cache hits "
        + ", ".join(f"{n} {r['cache_hits']}" for n, lab, r in rows if lab == "cache, warm")
        + "); tracing the Python code still runs."
    )


if __name__ == "__main__":
    main()
