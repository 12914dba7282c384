"""First `fit()` in a fresh process, with and without JAX's persistent compilation cache.

The satellite of Section 4 (`oneshot_jax.examples.satellite`, T = 50, Gauss-Newton,
positivity constraint) is fitted in three fresh Python processes that share one empty
cache folder:

- `no cache`: the cache is off (what a fresh process costs by default);
- `cache, cold`: the cache is on and empty, so this process compiles and writes it;
- `cache, warm`: a later process that finds the compiled solver in the cache.

Each process reports the wall time of its first `fit()` call (compilation included) and
the median of three further calls with the same shapes (compilation excluded), both from
`timing.timed`.

Run: `python benchmarks/first_call.py`
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from timing import conditions

HERE = Path(__file__).resolve().parent

WORKER = r"""
import json, sys
sys.path.insert(0, sys.argv[2])
import jax
jax.config.update("jax_enable_x64", True)
if sys.argv[1] != "off":
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
import numpy as np
import oneshot_jax as oj
from oneshot_jax.examples import satellite
from timing import timed

model = satellite.model()
data = satellite.generate([0], 50)
M, z = data["u"][0], data["z"][0]
theta0 = {"I": np.asarray(satellite.THETA0)}
w0 = np.asarray(satellite.W0)
fit = lambda: oj.fit(model, theta0, w0, M, z, solver="gauss_newton",
                     constraints=oj.constraints.positive())
r, first, second = timed(fit, repeats=3)
print(json.dumps({"first": first, "second": second, "loss": float(r.loss)}))
"""


def run(cache):
    out = subprocess.run(
        [sys.executable, "-c", WORKER, cache, str(HERE)], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    with tempfile.TemporaryDirectory() as cache:
        rows = [
            ("no cache", run("off")),
            ("cache, cold", run(cache)),
            ("cache, warm", run(cache)),
        ]
    print("First fit() in a fresh process: satellite T = 50, Gauss-Newton.")
    print(conditions())
    print()
    print("| process | first fit() (s), compilation included | later fit() (ms), median | loss |")
    print("|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['first']:.2f} | {1e3 * r['second']:.2f} | {r['loss']:.6e} |")


if __name__ == "__main__":
    main()
