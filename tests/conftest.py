import gc
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# The suite is dominated by XLA's compilation of CPU kernels, so the tests (and the
# experiment runs they start) compile with four options that shorten it, set before JAX
# starts, and only where this XLA knows them (an XLA without one, jaxlib 0.11 for the
# first, aborts the process on an unknown flag in XLA_FLAGS): one probe in a child process;
# the answer is kept in the environment for the pytest-xdist workers and the runs the
# tests start.
# - XLA's elemental emitter compiles a kernel in about 40 % less time than its default
#   fusion emitters, for the same kernels and numbers (`oneshot_jax._jit` passes it to the
#   library's top-level compiled calls for users too).
# - LLVM's optimisation level 0 takes about 40 % off the whole suite's time (slower
#   kernels, much faster compilation). It changes the last bits of some results: the few
#   tests that check two compiled paths to the bit, or the docs' printed outputs
#   (generated with XLA's defaults), are marked `default_optimisation` and run in a child
#   process with the level XLA uses by default (`pytest_runtest_call` below).
# - XLA splits a program's machine code into parts compiled on threads of their own; with
#   a pytest-xdist worker per core the threads only contend: one part per program took
#   6-9 % off the time of two sets of test files run as CI runs them (two workers on two
#   cores), for the same kernels (the split changes where code goes, not what it does).
# - XLA's HLO simplification pipeline runs its passes again until none changes the
#   program: on a fit's nested while loops (solver, line search, rollouts) it went 14
#   rounds, most of its time in loop-invariant code motion and the while-loop simplifier,
#   which move and drop code without changing what is computed (slower loops, at O0
#   already). Without those two, a 2-state fit's HLO passes took about 35 % less time and
#   tests/test_honest_solvers.py 8 % less in one process (473 -> 434 s).
FUSION_FLAG = "--xla_cpu_use_fusion_emitters=false"
OPT_FLAG = "--xla_backend_optimization_level=0"
SPLIT_FLAG = "--xla_cpu_parallel_codegen_split_count=1"
PASSES_FLAG = "--xla_disable_hlo_passes=while-loop-invariant-code-motion,simplify-while-loops"
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
    for flag in (FUSION_FLAG, OPT_FLAG, SPLIT_FLAG, PASSES_FLAG):
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


# Tracing and compiling make many short-lived Python objects: the collector's default
# first threshold (700 allocations) ran it some thousand times per minute, its full passes
# over every object of the imported modules as well. A higher threshold, and the objects
# alive after the imports frozen out of those passes, took 5-12 % off the CPU time of
# sets of three and four test files in one process (no gain from disabling the collector
# or from a full collection per test file on top), and 5 % off the whole suite's time.
gc.collect()
gc.freeze()
gc.set_threshold(50_000, 50, 100)


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


# The outcomes of the `default_optimisation` tests, per test file: one child process runs
# all of a file's marked tests the first time one of them is reached, in the first
# pytest-xdist worker to reach one; it leaves them in a folder of this test run (`SHARED`,
# made by the process that starts the workers) for the other worker.
_CHILD_OUTCOMES = {}
SHARED = "ONESHOT_JAX_TESTS_CHILD_OUTCOMES"
_MADE = []


def pytest_configure(config):
    if SHARED not in os.environ:
        _MADE.append(tempfile.mkdtemp(prefix="oneshot_jax_tests_"))
        os.environ[SHARED] = _MADE[0]


def pytest_unconfigure(config):
    for folder in _MADE:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(SHARED, None)


def _run_in_child(item):
    """{test name: (outcome, text)} of every `default_optimisation` test in `item`'s file,
    run in one child pytest process without `OPT_FLAG` and `PASSES_FLAG`."""
    import xml.etree.ElementTree as ET

    marked = [
        i.nodeid
        for i in item.session.items
        if i.path == item.path and i.get_closest_marker("default_optimisation") is not None
    ]
    flags = os.environ.get("XLA_FLAGS", "").replace(OPT_FLAG, "").replace(PASSES_FLAG, "")
    flags = " ".join(flags.split())
    env = dict(os.environ, XLA_FLAGS=flags)
    env.pop("PYTEST_XDIST_WORKER", None)
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "child.xml"
        done = subprocess.run(
            [
                *(sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"),
                *("-p", "no:xdist", "-o", "addopts=", f"--junitxml={report}", *marked),
            ],
            cwd=item.config.rootpath,
            env=env,
            capture_output=True,
            text=True,
        )
        output = f"{done.stdout[-6000:]}\n{done.stderr[-3000:]}"
        outcomes = {}
        if report.exists():
            for case in ET.parse(report).iter("testcase"):
                kind, text = "passed", ""
                for child in case:
                    if child.tag in ("failure", "error", "skipped"):
                        kind = child.tag
                        text = child.get("message", "") + "\n" + (child.text or "")
                outcomes[case.get("name")] = (kind, text or output)
    return outcomes, output


def _shared_child_outcomes(item, wait=3600.0):
    """`_run_in_child(item)`, run by the first process of this test run to ask for
    `item`'s file: the others wait for its outcomes in the `SHARED` folder (and run their
    own child if none come within `wait` seconds)."""
    if SHARED not in os.environ:
        return _run_in_child(item)
    folder = Path(os.environ[SHARED])
    key = hashlib.sha256(str(item.path).encode()).hexdigest()[:16]
    done = folder / f"{key}.json"
    try:
        os.close(os.open(folder / f"{key}.lock", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        deadline = time.monotonic() + wait
        while not done.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        if done.exists():
            outcomes, output = json.loads(done.read_text())
            return {name: tuple(kind) for name, kind in outcomes.items()}, output
        return _run_in_child(item)
    outcomes, output = _run_in_child(item)
    partial = folder / f"{key}.part"
    partial.write_text(json.dumps([outcomes, output]))
    os.replace(partial, done)
    return outcomes, output


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_call(item):
    """A test marked `default_optimisation` runs in a child pytest process whose XLA
    compiles at its default optimisation level (without `OPT_FLAG`, and with every HLO
    pass), where this process
    has the flag (one child per test file); its failure or skip is this test's."""
    if item.get_closest_marker("default_optimisation") is None:
        return
    if OPT_FLAG not in os.environ.get("XLA_FLAGS", ""):
        return  # (the child itself, or an XLA without the flag: run here)
    if item.path not in _CHILD_OUTCOMES:
        _CHILD_OUTCOMES[item.path] = _shared_child_outcomes(item)
    outcomes, output = _CHILD_OUTCOMES[item.path]
    kind, text = outcomes.get(item.name, ("missing", output))
    where = f"{item.nodeid} at XLA's default optimisation level (a child process)"
    if kind == "skipped":
        pytest.skip(f"{where}: {text.strip()}")
    if kind != "passed":
        pytest.fail(f"{where}: {kind}\n{text}", pytrace=False)
    item.runtest = lambda: None  # (passed in the child)
