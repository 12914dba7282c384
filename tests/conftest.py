import os
import subprocess
import sys

# XLA's elemental emitter compiles a CPU kernel in about 40 % less time than its default
# fusion emitters, for the same kernels (`oneshot_jax._jit` passes it to the library's
# top-level compiled calls); the suite is dominated by compilation, so the tests (and the
# experiment runs they start) use it for every compiled call. Set before JAX starts, and
# only where this XLA knows the flag: an XLA without it (jaxlib 0.11) aborts the process
# on an unknown flag in XLA_FLAGS. One probe in a child process; the answer is kept in the
# environment for the pytest-xdist workers and the runs the tests start. (LLVM's
# optimisation level 0, `--xla_backend_optimization_level=0`, halves the suite's time
# too, but it changes the last bits of some results, and the tests that check two paths
# to the bit, or the docs' printed outputs, then fail.)
FUSION_FLAG = "--xla_cpu_use_fusion_emitters=false"
PROBED = "ONESHOT_JAX_TESTS_XLA_PROBED"


def _xla_takes(flag):
    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip())
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    try:
        done = subprocess.run(
            [sys.executable, "-c", probe], env=env, capture_output=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


if PROBED not in os.environ:
    os.environ[PROBED] = "1"
    for flag in (FUSION_FLAG,):
        name = flag.split("=")[0].lstrip("-")
        if name not in os.environ.get("XLA_FLAGS", "") and _xla_takes(flag):
            os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {flag}".strip()

import jax  # noqa: E402

# Identification runs in float64; the library itself never flips this on import.
jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402

from oneshot_jax import datasets  # noqa: E402
from oneshot_jax.internal import data_hidden  # noqa: E402

# ONESHOT_JAX_HIDE_DATA=1 runs the tests as on a checkout without the benchmark files:
# the loaders stop looking in ../shared/data and the user cache, and the folders a
# developer's shell may name are dropped too, so the tests that need the files skip.
if data_hidden():
    for name in (datasets.ENV_VAR, datasets.CACHE_ENV_VAR):
        os.environ.pop(name, None)


def pytest_report_header(config):
    if data_hidden():
        return f"benchmark data: hidden by ${datasets.HIDE_ENV_VAR}; the tests that need it skip"
    roots = ", ".join(map(str, datasets.default_data_dirs()))
    return f"benchmark data: {roots or 'no folder found; the tests that need it skip'}"


@pytest.fixture(autouse=True, scope="module")
def _fresh_compilation_caches():
    """Each test module starts from empty compilation caches, so that the executables
    of a long session do not pile up in one process."""
    yield
    jax.clear_caches()
