"""`oneshot_jax.enable_compilation_cache`: it sets JAX's persistent cache (and nothing
does on import), and a second fresh process loads what the first one compiled.

Each process is a subprocess, so that the test process's own JAX configuration is never
changed."""

import json
import os
import subprocess
import sys

import pytest

import oneshot_jax as oj

WORKER = r"""
import json, sys
import jax
before = jax.config.jax_compilation_cache_dir
import numpy as np
import oneshot_jax as oj
after_import = jax.config.jax_compilation_cache_dir
hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name == "/jax/compilation_cache/cache_hits" else None
)
if sys.argv[1] == "default":
    path = oj.enable_compilation_cache()
else:
    path = oj.enable_compilation_cache(sys.argv[1])
model = oj.Model(lambda x, u, th: x * th["a"] + u, lambda x, u, th: x[:1])
x, z = oj.simulate(model, {"a": 0.9}, np.array([1.0, 2.0]), np.ones((7, 2)))
print(json.dumps({
    "before": before,
    "after_import": after_import,
    "path": str(path),
    "dir": jax.config.jax_compilation_cache_dir,
    "min_time": jax.config.jax_persistent_cache_min_compile_time_secs,
    "min_size": jax.config.jax_persistent_cache_min_entry_size_bytes,
    "hits": len(hits),
    "z": np.asarray(z).tolist(),
}))
"""


def _run(arg, env=None):
    out = subprocess.run(
        [sys.executable, "-c", WORKER, arg],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, **(env or {})},
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_second_process_loads_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _run(str(cache))
    # Importing the library changes nothing; the call sets the folder and the thresholds.
    assert first["before"] is None and first["after_import"] is None
    assert first["path"] == str(cache.resolve()) == first["dir"]
    assert first["min_time"] == 0.0 and first["min_size"] == 0
    assert first["hits"] == 0
    assert any(cache.iterdir())  # what it compiled was written
    second = _run(str(cache))
    assert second["hits"] >= 1  # ... and loaded by a fresh process
    assert second["z"] == first["z"]


def test_default_folder_is_under_the_user_cache(tmp_path):
    out = _run("default", env={"ONESHOT_JAX_CACHE": str(tmp_path)})
    assert out["path"] == str((tmp_path / "jax").resolve()) == out["dir"]


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "soon"])
def test_bad_threshold(tmp_path, bad):
    with pytest.raises(ValueError, match="min_compile_time_secs"):
        oj.enable_compilation_cache(tmp_path, min_compile_time_secs=bad)


def test_path_that_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ValueError, match="must be a folder"):
        oj.enable_compilation_cache(f)
