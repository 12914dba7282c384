"""First `fit()` in a fresh process, with and without JAX's persistent compilation cache.

The satellite of Section 4 (T = 50, Gauss-Newton, positivity constraint) is fitted in
three fresh Python processes that share one empty cache folder:

- `no cache`: the cache is off (what a fresh process costs by default);
- `cache, cold`: the cache is on and empty, so this process compiles and writes it;
- `cache, warm`: a later process that finds the compiled solver in the cache.

Each process reports the wall time of its first `fit()` call (compilation included)
and of a second call with the same shapes (compilation excluded).

Run: `python benchmarks/first_call.py`
"""

import json
import subprocess
import sys
import tempfile

WORKER = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
if sys.argv[1] != "off":
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
import numpy as np, jax.numpy as jnp
import oneshot_jax as oj

def rhs(w, M, inertia):
    return (M - jnp.cross(w, inertia * w)) / inertia

model = oj.Model.from_ode(rhs, 0.1)
rng = np.random.default_rng(0)
M = 1e-5 + 1e-7 * rng.standard_normal((50, 3))
theta = np.array([0.0403, 0.0404, 0.0080])
w0 = np.array([9.915e-6, -1.102e-3, 1.3179e-5])
_, z = oj.simulate(model, theta, w0, M)
z = np.asarray(z) + 1e-4 * rng.standard_normal((50, 3))
times = []
for _ in range(2):
    t0 = time.perf_counter()
    r = oj.fit(model, M, z, theta * 1.2, w0, solver="gauss_newton",
               constraints=oj.constraints.positive())
    times.append(time.perf_counter() - t0)
print(json.dumps({"first": times[0], "second": times[1], "loss": r.loss}))
"""


def run(cache):
    out = subprocess.run(
        [sys.executable, "-c", WORKER, cache], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    with tempfile.TemporaryDirectory() as cache:
        rows = [
            ("no cache", run("off")),
            ("cache, cold", run(cache)),
            ("cache, warm", run(cache)),
        ]
    print("First fit() in a fresh process: satellite T = 50, Gauss-Newton, float64, CPU")
    print()
    print("| process | first fit() (s), compilation included | second fit() (ms) | loss |")
    print("|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['first']:.2f} | {1e3 * r['second']:.2f} | {r['loss']:.6e} |")


if __name__ == "__main__":
    main()
