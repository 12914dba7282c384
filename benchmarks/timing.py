"""The timing helper every benchmark script uses, and the conditions each table states.

- `timed(fn, repeats)`: the first call (compilation included) and the median of further
  calls (compilation excluded), each blocked until its result is ready.
- `interleaved(calls, repeats)`: medians of several callables timed round by round, the
  order rotating each round, so that a change of machine load hits all of them alike.
- `conditions()`: the hardware, the software versions and the command, for the header of
  every table.
- `runs(paths, describe)`: the runs that scripts wrote with `--json`, each announced by
  its file's name and conditions (the `--render` of a script).
"""

from __future__ import annotations

import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version

import jax


def block(out):
    """`out` with every array ready (JAX dispatches asynchronously)."""
    return jax.block_until_ready(out)


def timed(fn, repeats=3):
    """Time `fn()`: `(result, first_s, median_s)`, the first call (compilation included)
    and the median over `repeats` further calls (None when `repeats` is 0)."""
    t0 = time.perf_counter()
    out = block(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = block(fn())
        times.append(time.perf_counter() - t0)
    return out, first, (statistics.median(times) if times else None)


def interleaved(calls, repeats=15, min_sample_s=2e-3, warmup=2):
    """Median seconds per call of each callable in `calls` (a dict name -> fn).

    After `warmup` calls of each (compilation), every round times each callable once, the
    order rotating from round to round. A sample is the mean of n back-to-back calls, with
    n chosen so that a sample lasts about `min_sample_s` (0: one call per sample).
    """
    names = list(calls)
    for name in names:
        for _ in range(warmup):
            block(calls[name]())
    inner = {}
    for name in names:
        t0 = time.perf_counter()
        block(calls[name]())
        one = time.perf_counter() - t0
        inner[name] = int(min(200, max(1, min_sample_s / max(one, 1e-7))))
    samples = {name: [] for name in names}
    for r in range(repeats):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            fn, n = calls[name], inner[name]
            t0 = time.perf_counter()
            for _ in range(n):
                block(fn())
            samples[name].append((time.perf_counter() - t0) / n)
    return {name: statistics.median(s) for name, s in samples.items()}


def fmt_time(s):
    """Seconds as µs, ms or s with three significant digits ('—' for None)."""
    if s is None:
        return "—"
    if s < 1e-3:
        return f"{s * 1e6:.3g} µs"
    return f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s"


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def versions(extra=()) -> dict:
    """Installed versions of oneshot_jax, JAX and the numerical stack (and `extra`)."""
    out = {}
    for name in (
        "oneshot_jax",
        "jax",
        "jaxlib",
        "numpy",
        "scipy",
        "optax",
        "optimistix",
        "equinox",
        *extra,
    ):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    if out["oneshot_jax"] == "not installed" and "oneshot_jax" in sys.modules:
        out["oneshot_jax"] = f"{sys.modules['oneshot_jax'].__version__} (source tree)"
    return out


def commit() -> str:
    """The checkout's commit (short hash, "+changes" where the library's or the benchmarks'
    Python files differ from it, tracked or not; their outputs, JSON files and figures,
    do not count). Outside a git checkout (a copy of a clean tree on another machine), the
    environment variable `ONESHOT_JAX_COMMIT` if set, marked as given; else ""."""
    given = os.environ.get("ONESHOT_JAX_COMMIT", "")
    given = f"{given}, given by ONESHOT_JAX_COMMIT" if given else ""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "oneshot_jax", "benchmarks/*.py"],
            cwd=root,
            capture_output=True,
            text=True,
        )
    except OSError:
        return given
    if head.returncode:
        return given
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def _shown(cmd: str) -> str:
    """The command as the docs show it: without `--json PATH` (a file of the run)."""
    return re.sub(r"\s--json\s+[^\s`]+", "", cmd)


def conditions(extra_versions=(), argv=None) -> str:
    """One paragraph: hardware, float64, software versions with the commit, and the
    command line (without its `--json` output path)."""
    argv = sys.argv if argv is None else argv
    script = os.path.relpath(os.path.abspath(argv[0]), os.getcwd()) if argv else "?"
    cmd = _shown(" ".join(["python", script, *argv[1:]]))
    dev = jax.devices()[0]
    hw = f"{cpu_name()}, {os.cpu_count()} CPU cores" if dev.platform == "cpu" else dev.device_kind
    vers = ", ".join(f"{k} {v}" for k, v in versions(extra_versions).items())
    at = commit()
    at = f" (commit {at})" if at else ""
    return f"Hardware: {hw} ({dev.platform}), float64. Versions: {vers}{at}. Command: `{cmd}`."


def runs(paths, describe):
    """The `--json` runs in `paths` (dicts with a "conditions" entry), in order, each after
    a printed line: its file's name, `describe(run)` and its conditions."""
    for path in paths:
        with open(path) as f:
            run = json.load(f)
        shown = _shown(run["conditions"]).replace(
            "oneshot_jax not installed", "oneshot_jax from its source tree (version not recorded)"
        )
        print(f"- `{os.path.basename(path)}`: {describe(run)}. {shown}")
        yield run
