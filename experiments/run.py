"""Hydra entry point for the experiments (configs in ../configs, schema in config.py).

    python experiments/run.py                                   # experiment=satellite solver=adam
    python experiments/run.py solver=gauss_newton experiment.T=100 seed=3
    python experiments/run.py -m solver=adam,gauss_newton seed=0,1
    python experiments/run.py experiment=emps publish=true      # also refresh the published files
    python -m experiments ...                                   # the same, from the checkout

The experiment module `experiments/<experiment.name>.py` exposes
`run(cfg, outdir, command) -> dict`, where `cfg` is the validated `config.Config`. This
script enables float64 and, in the run's output folder: removes the results of an earlier
run there (results.json, results.md and its figures), checks the configuration (a bad value
stops the run before anything is computed, exit status 2), writes `resolved_config.yaml`
(Hydra keeps its own copy under `.hydra/`), calls `run`, and writes `results.json`
atomically with a top-level `"status"`: `"ok"`, or `"failed"` with the error (a
`"status"` of the runner's own dict is kept as `"runner_status"`; `"files"` lists the
files the runner wrote there, which the next run into the folder removes first). With
`publish=true` the run's `results.md` is copied to `docs/case-studies/<name>.md` (figure
links rewritten to `../figures/`) and its figures to `docs/figures/<name>_<figure>`.
Benchmark files that are not found end the run with exit status 2 and a message that names
`experiment.data_path`.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import hydra
import jax
from omegaconf import DictConfig, OmegaConf

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import config  # noqa: E402
from oneshot_jax.internal import replace_atomically  # noqa: E402

# Identification runs in float64; the library never enables it itself.
jax.config.update("jax_enable_x64", True)
config.register()

OUTPUTS = ("results.json", "results.md", "resolved_config.yaml")


def _setup_cache(cache_dir):
    """JAX's persistent compilation cache in `cache_dir` (`jax_cache_dir`), if given; a
    folder that cannot be made is a configuration error (exit 2), not a traceback."""
    if cache_dir:
        from oneshot_jax import enable_compilation_cache

        try:
            enable_compilation_cache(str(cache_dir), min_compile_time_secs=0.2)
        except ValueError as err:
            raise config.ConfigError(f"`jax_cache_dir`: {err}") from None


def _cache_dir():
    """The persistent compilation cache's folder JAX uses, or None (JAX's configuration
    is global: in a sweep, the one an earlier job set up)."""
    return jax.config.jax_compilation_cache_dir


def write_json(path: Path, obj) -> None:
    """Write `obj` as JSON to `path` atomically (a temporary file, then a rename), so a
    reader sees the old file or the new one, never a partial one."""
    with replace_atomically(path, "w") as f:
        json.dump(obj, f, indent=2, allow_nan=False)


def _files(outdir: Path) -> set[str]:
    """The names of the files directly in `outdir` (not Hydra's folder), less OUTPUTS."""
    return {p.name for p in outdir.iterdir() if p.is_file()} - set(OUTPUTS)


def clear_stale(outdir: Path) -> list[Path]:
    """Remove the outputs of an earlier run in `outdir` (results.json, results.md,
    resolved_config.yaml, and the figures and files the old results.json lists)."""
    removed = []
    old = outdir / "results.json"
    names = list(OUTPUTS)
    if old.exists():
        try:
            listed = json.loads(old.read_text())
            names += [str(f) for f in listed.get("figures") or []]
            names += [str(f) for f in listed.get("files") or []]
        except (ValueError, AttributeError):
            pass
    for name in names:
        p = outdir / Path(name).name
        if p.is_file():
            p.unlink()
            removed.append(p)
    return removed


def publish(name: str, outdir: Path, figures) -> list[Path]:
    """Copy a run's results.md and figures into the documentation: the case-study page
    `docs/case-studies/<name>.md` and its figures `docs/figures/<name>_<figure>`."""
    written = []
    fig_dir = REPO / "docs" / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    md = (outdir / "results.md").read_text() if (outdir / "results.md").exists() else None
    for fig in figures or []:
        target = fig_dir / f"{name}_{fig}"
        shutil.copyfile(outdir / fig, target)
        written.append(target)
        if md is not None:
            md = md.replace(f"]({fig})", f"](../figures/{name}_{fig})")
    if md is not None:
        target = REPO / "docs" / "case-studies" / f"{name}.md"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(md)
        written.append(target)
    return written


def conditions() -> str:
    """The machine and the versions a run's numbers come from: the CPU (or the JAX
    device), its cores, and the versions of Python, oneshot_jax, JAX and jaxlib."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    dev = jax.devices()[0]
    if dev.platform == "cpu":
        cpu = platform.processor() or platform.machine()
        try:
            with open("/proc/cpuinfo") as f:
                cpu = next(
                    (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu
                )
        except OSError:
            pass
        hw = f"{cpu}, {os.cpu_count()} CPU cores"
    else:
        hw = dev.device_kind
    vers = []
    for pkg in ("oneshot_jax", "jax", "jaxlib"):
        try:
            vers.append(f"{pkg} {version(pkg)}")
        except PackageNotFoundError:
            vers.append(f"{pkg} (not installed)")
    return f"{hw}; Python {platform.python_version()}, {', '.join(vers)}."


def command_line() -> str:
    """The command line of this run, from Hydra's overrides when run through Hydra."""
    try:
        from hydra.core.hydra_config import HydraConfig

        overrides = [o for o in HydraConfig.get().overrides.task if not o.startswith("hydra.")]
    except ValueError:  # not running under Hydra
        overrides = []
    return " ".join(["python experiments/run.py", *overrides])


RUNNING = ".running"  # the file that holds a run's folder while it runs (`claimed`)


def _alive(pid: int) -> bool:
    """Whether a process `pid` runs (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # (another user's process)
        return True
    return True


@contextlib.contextmanager
def claimed(outdir: Path):
    """Hold `outdir` for this run: the file `.running` with this process's id, created
    exclusively and removed at the end. A folder that another running process holds is
    refused (`config.ConfigError`) before anything is written there: two runs started in
    the same folder mixed their files. A `.running` left by a process that no longer
    runs (killed) is taken over."""
    lock = outdir / RUNNING
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _alive(pid):
                raise config.ConfigError(
                    f"the output folder {outdir} is in use by another run (process {pid}): "
                    "give this run a folder of its own (hydra.run.dir=<folder>)."
                ) from None
            lock.unlink(missing_ok=True)
    else:  # (another process took it over in between)
        raise config.ConfigError(f"the output folder {outdir} is in use by another run.")
    with os.fdopen(fd, "w") as f:
        f.write(str(os.getpid()))
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


def execute(cfg: DictConfig, outdir: Path, command: str | None = None, runner=None) -> dict:
    """Run the configured experiment into `outdir` and write the run's files.

    **Arguments:**

    - `cfg`: the composed configuration (validated here, before anything runs).
    - `outdir`: the run's folder; the outputs of an earlier run there are removed first.
    - `command`: the command line shown in results.md.
    - `runner`: `run(cfg, outdir, command) -> dict` (default: the experiment module's).

    **Returns:**

    The results dict, as written to results.json. A failure writes results.json with
    `"status": "failed"` and the error, then raises. A folder that another running
    process writes into is refused (`claimed`).
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    with claimed(outdir), terminated_as_exit():
        return _execute(cfg, outdir, command, runner)


class Terminated(SystemExit):
    """The run was sent SIGTERM (`kill`, `timeout`, a scheduler's time limit): it ends as
    a failure, with exit status 143 (128 + SIGTERM), as Python's default handling would."""

    def __init__(self):
        super().__init__(128 + signal.SIGTERM)

    def __str__(self):
        return "terminated by SIGTERM (kill, timeout or a scheduler's time limit)"


@contextlib.contextmanager
def terminated_as_exit():
    """SIGTERM raises `Terminated` while the block runs (in the main thread; elsewhere
    signals cannot be handled), so that a run stopped at a time limit writes its
    results.json as failed and gives its folder back, as Ctrl-C does; the handler before
    is restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    before = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def _execute(cfg, outdir, command, runner) -> dict:
    """`execute` in a folder this run holds."""
    clear_stale(outdir)
    command = command or command_line()
    t0 = time.perf_counter()
    name = OmegaConf.select(cfg, "experiment.name", throw_on_missing=False)
    before = None  # (the folder's files when the runner starts)
    try:
        conf = config.load(cfg)
        name = conf.experiment.name
        (outdir / "resolved_config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
        _setup_cache(conf.jax_cache_dir)
        if runner is None:
            runner = importlib.import_module(f"experiments.{name}").run
        before = _files(outdir)
        # A sweep (`-m`) runs its jobs in one process: without this, a job after the
        # first reused the programs an earlier one compiled, and its report called its
        # first calls "compilation included" (0.02 s where the first job's took 2.9 s).
        jax.clear_caches()
        # (a first line at once: the first fits compile before anything else prints)
        print(f"{name}: running into {outdir} (compiling first) ...", flush=True)
        results = dict(runner(conf, outdir, command=command))
    except BaseException as err:
        failed = {
            "status": "failed",
            "error": f"{type(err).__name__}: {err}",
            "experiment": name,
            "command": command,
            "wall_time_s": time.perf_counter() - t0,
            "conditions": conditions(),  # (a failure states its conditions too)
        }
        written = [] if before is None else sorted(_files(outdir) - before)
        write_json(outdir / "results.json", {**failed, **({"files": written} if written else {})})
        raise
    written = _files(outdir) - before
    if written:  # (what the runner wrote, for the next run here to clear: `clear_stale`)
        results["files"] = sorted(written | set(results.get("files") or ()))
    if "status" in results:  # (the run's own key: the runner's is kept beside it)
        results["runner_status"] = results.pop("status")
    results = {"status": "ok", **results}
    results.setdefault("wall_time_s", time.perf_counter() - t0)
    results.setdefault("conditions", conditions())
    cache = _cache_dir()
    if cache:  # (first calls then load compiled programs where it has them)
        results["conditions"] += (
            f" JAX's persistent compilation cache in {cache}: a first call loads the "
            "programs it holds instead of compiling them."
        )
    md = outdir / "results.md"
    if md.exists():  # the results' conditions, under the report
        md.write_text(md.read_text().rstrip("\n") + f"\n\nConditions: {results['conditions']}\n")
    write_json(outdir / "results.json", results)
    if conf.publish:
        for path in publish(name, outdir, results.get("figures")):
            print(f"published {path.relative_to(REPO)}")
    print(f"{name}: results in {outdir} ({results['wall_time_s']:.1f} s)")
    return results


def task(cfg: DictConfig) -> None:
    """The Hydra task: run the configured experiment into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig

    from oneshot_jax.datasets import DatasetFormatError, DatasetNotFoundError

    try:
        execute(cfg, Path(HydraConfig.get().runtime.output_dir))
    except config.ConfigError as err:
        print(f"invalid configuration: {err}", file=sys.stderr)
        sys.exit(2)
    except DatasetNotFoundError as err:
        # The loader's message speaks of its own argument, path=; a run sets it as
        # experiment.data_path.
        print(
            f"missing data: {err}\nIn an experiment, give the folder as "
            f"experiment.data_path=<folder> (or set $ONESHOT_JAX_DATA).",
            file=sys.stderr,
        )
        sys.exit(2)
    except DatasetFormatError as err:
        print(f"malformed data: {err}", file=sys.stderr)
        sys.exit(2)


# An absolute config path, so that the entry point works from any working directory.
main = hydra.main(version_base="1.3", config_path=str(REPO / "configs"), config_name="config")(task)


def check_groups(argv) -> str | None:
    """The message for a config group set to null on the command line (`experiment=null`,
    `solver=~`), which Hydra answers with a traceback of its own; None if there is none."""
    for arg in argv:
        group, sep, value = arg.lstrip("+~").partition("=")
        if sep and group in ("experiment", "solver") and value.strip().lower() in ("null", "~", ""):
            options = sorted(p.stem for p in (REPO / "configs" / group).glob("*.yaml"))
            return f"`{group}` must name one of {', '.join(options)}, got {arg!r}."
    return None


def check_added_methods(argv) -> str | None:
    """The message for a method added on the command line (`+experiment.methods.mine=...`),
    which Hydra refuses with "Invalid type assigned: dict is not a subclass of Method";
    None if there is none."""
    for arg in argv:
        key = arg.partition("=")[0]
        if arg.startswith("+") and key.lstrip("+").startswith("experiment.methods."):
            return (
                f"{arg!r}: a method cannot be added on the command line (Hydra cannot add "
                "an entry to the typed `experiment.methods`): add it under `methods:` in "
                "configs/experiment/<experiment>.yaml, as the others are written, and "
                "select it with experiment.run_methods=[...]; an existing method's fields "
                "can be overridden, e.g. experiment.methods.slsqp_fd.solver.kwargs.maxiter=50."
            )
    return None


def cli() -> None:
    """The command line: Hydra's `main`, after `check_groups` and `check_added_methods`."""
    message = check_groups(sys.argv[1:]) or check_added_methods(sys.argv[1:])
    if message is not None:
        print(f"invalid configuration: {message}", file=sys.stderr)
        sys.exit(2)
    main()


if __name__ == "__main__":
    cli()
