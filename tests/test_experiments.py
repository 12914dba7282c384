"""The Hydra experiments: every config composes and validates, a bad value is refused
before anything runs, results.json says whether the run succeeded, and the entry points
run end to end."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import benchmark_or_skip
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

import oneshot_jax as oj

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "configs"
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import common, config, run, satellite  # noqa: E402

config.register()


def _groups():
    """{group: [options]} discovered from configs/ (new experiments are picked up)."""
    return {
        d.name: sorted(p.stem for p in d.glob("*.yaml"))
        for d in sorted(CONFIGS.iterdir())
        if d.is_dir() and any(d.glob("*.yaml"))
    }


def _compose(overrides=()):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _load(overrides=()):
    return config.load(_compose(overrides))


GROUPS = _groups()
PAIRS = [(e, s) for e in GROUPS.get("experiment", []) for s in GROUPS.get("solver", [])]
OPTIONS = [(g, o) for g, opts in GROUPS.items() for o in opts]


def test_groups_discovered():
    assert {"satellite", "emps", "cascaded_tanks"} <= set(GROUPS["experiment"])
    assert {
        "adam",
        "lbfgs",
        "gauss_newton",
        "levenberg_marquardt",
        "slsqp",
        "trust_constr",
    } <= set(GROUPS["solver"])


def test_default_config():
    cfg = _load()
    assert isinstance(cfg.experiment, config.SatelliteConfig)
    assert cfg.experiment.name == "satellite"
    assert cfg.solver.name == "adam"
    assert cfg.seed == 0
    # the tuned Adam settings of the satellite experiment reach the solver config
    assert cfg.solver.kwargs["lr_theta"] == cfg.experiment.solver_defaults["adam"]["lr_theta"]
    # the physical constants default to the example module, their one home
    from oneshot_jax.examples import satellite as example

    assert cfg.experiment.theta_true == list(example.THETA_TRUE)


@pytest.mark.parametrize("experiment", GROUPS["experiment"])
def test_a_key_added_with_plus_that_the_schema_lacks_is_refused(experiment):
    """`+experiment.foo=1` composes (Hydra adds the key); it was then ignored silently."""
    cfg = _compose([f"experiment={experiment}", "+experiment.foo=1"])
    with pytest.raises(config.ConfigError, match=r"unknown key\(s\) experiment.foo: "):
        config.load(cfg)
    with pytest.raises(config.ConfigError, match=r"unknown key\(s\) bar: Config has "):
        config.load(_compose(["+bar=2"]))


@pytest.mark.parametrize("group,option", OPTIONS)
def test_every_option_composes(group, option):
    cfg = _compose([f"{group}={option}"])
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved[group] is not None


@pytest.mark.parametrize("experiment,solver", PAIRS)
def test_experiment_solver_pairs(experiment, solver):
    """Every pair either validates (and the solver builds), or is refused with a message
    that names the experiment and the solvers it runs."""
    cfg = _compose([f"experiment={experiment}", f"solver={solver}"])
    assert (REPO / "experiments" / f"{cfg.experiment.name}.py").is_file()
    if cfg.solver.name in config.LIBRARY_SOLVERS or experiment == "satellite":
        conf = config.load(cfg)
        assert conf.solver.name in type(conf.experiment).SOLVERS
        if conf.solver.name != "scipy":
            common.make_solver(conf.solver.name, conf.solver.kwargs)
    else:
        with pytest.raises(config.ConfigError, match=f"experiment={experiment} runs the library"):
            config.load(cfg)


def test_real_data_experiments_choose_their_solver_and_honour_another():
    emps = _load(["experiment=emps"])
    assert emps.solver.name == "levenberg_marquardt"
    assert emps.solver.kwargs["max_steps"] == 200  # the experiment's solver_defaults
    gn = _load(["experiment=emps", "solver=gauss_newton"])
    assert gn.solver.name == "gauss_newton" and gn.solver.kwargs["max_steps"] == 200
    tanks = _load(["experiment=cascaded_tanks", "solver=adam"])
    assert tanks.solver.name == "adam"


def test_command_line_overrides_compose():
    cfg = _load(["solver=gauss_newton", "experiment.T=100", "seed=3", "solver.kwargs.max_steps=7"])
    assert (cfg.solver.name, cfg.experiment.T, cfg.seed) == ("gauss_newton", 100, 3)
    assert common.make_solver(cfg.solver.name, cfg.solver.kwargs) == common.make_solver(
        "gauss_newton", {"max_steps": 7, "rtol": 1e-10}
    )


def test_satellite_methods_are_valid_specs():
    cfg = _load()
    methods = cfg.experiment.methods
    for m in methods.values():
        assert m.cost in ("multi_step", "single_step")
    for key in cfg.experiment.fig4_methods + cfg.experiment.fig5_methods:
        assert key in methods
    # the Adam baseline is the default solver: it is deduplicated into the proposed method
    assert common.same_solver(methods["adam"].solver, cfg.solver)


BAD = [
    (["experiment.T=-5"], "`experiment.T` must be an integer >= 2, got -5"),
    (["experiment.T=0"], "`experiment.T` must be an integer >= 2, got 0"),
    (["experiment.noise_std=-1"], "`experiment.noise_std` must be a finite number > 0"),
    (["seed=-1"], "`seed` must be an integer >= 0"),
    (["experiment.theta_true=[0.04,0.04]"], "`experiment.theta_true` must be a list of 3"),
    (["experiment.init.x0=zero"], "`experiment.init.x0` must be 'first_sample'"),
    (["experiment.fig2.pair=[0,0]"], "`experiment.fig2.pair` must be two different"),
    (["experiment.run_methods=[nope]"], "`experiment.run_methods` must be one of"),
    (["solver.kwargs.max_steps=-3"], r"Adam\(max_steps=...\)"),
    # (a study of no step reported the start as its fit)
    (["solver.kwargs.max_steps=0"], r"`solver.kwargs.max_steps` must be an integer >= 1"),
    (["+solver.kwargs.foo=1"], r"unknown kwargs \['foo'\]"),
    (["solver=slsqp", "solver.kwargs.method=NOPE"], r"`solver.kwargs.method` must be a scipy"),
    (["solver=slsqp", "solver.kwargs.fd_scheme=7-point"], r"`solver.kwargs.fd_scheme` must be"),
    (["solver=slsqp", "solver.kwargs.scale=maybe"], r"`solver.kwargs.scale` must be true or"),
    (["solver=slsqp", "solver.kwargs.tol=abc"], r"`solver.kwargs.tol` must be a finite"),
    (
        ["experiment.methods.gb_one_step.solver.kwargs.max_steps=-1"],
        r"experiment.methods.gb_one_step.solver.kwargs of 'levenberg_marquardt'",
    ),
    (
        ["experiment.methods.slsqp_fd.solver.name=foo"],
        r"`experiment.methods.slsqp_fd.solver.name` must be one of",
    ),
    (
        ["+experiment.solver_defaults.adam.max_stepz=5"],
        r"unknown key\(s\) experiment.solver_defaults.adam.max_stepz",
    ),
    (["experiment=emps", "solver=slsqp"], "experiment=emps runs the library's solvers only"),
    (["experiment=emps", "experiment.eps=0"], "`experiment.eps` must be a finite number > 0"),
    (
        ["experiment.horizon_seeds=50"],
        r"`experiment.horizon_seeds` must be an integer >= 0 and <= 20 \(experiment.n_seeds\)",
    ),
    (["experiment=emps", "experiment.open_loop.windows=[1]"], r"open_loop.windows\[0\]"),
    (["experiment=emps_hybrid", "experiment.inputs=x"], "`experiment.inputs` must be one of"),
    (["experiment=emps_hybrid", "experiment.window=1"], "`experiment.window` must be an int"),
    (["experiment=cascaded_tanks", "experiment.overflow.theta0.k5=2"], "k5` must be"),
    (["experiment=cascaded_tanks", "experiment.x0=[1]"], "`experiment.x0` must be a list"),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.joint.refine=newton"],
        "`experiment.joint.refine` must be one of",
    ),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.residual.widths=[0]"],
        r"`experiment.residual.widths\[0\]` must be an integer >= 1",
    ),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.joint.patience=10"],
        "`experiment.joint.patience` must be null unless joint.holdout > 0",
    ),
    (
        [
            "experiment=cascaded_tanks_hybrid",
            "experiment.joint.scale=theta0",
            "experiment.joint.weight_decay=0.1",
        ],
        "`experiment.joint.scale` must be null with joint.weight_decay > 0",
    ),
    # (a bound above the truth pinned every estimate on it, "converged 2/2")
    (["experiment.theta_lower=0.1"], "`experiment.theta_lower` must be below every entry"),
    # (not a list: it said "'NoneType' object is not iterable", naming no key)
    (["experiment.init.x0=null"], "`experiment.init.x0` must be 'first_sample' or a list"),
    (["experiment.init.x0=5"], "`experiment.init.x0` must be 'first_sample' or a list"),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.joint.holdout=0.9"],
        "`experiment.joint.holdout` must be a finite number >= 0",
    ),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.residual.combine=median"],
        "`experiment.residual.combine` must be one of best, mean",
    ),
    (
        ["experiment=cascaded_tanks_hybrid", "experiment.residual.n_starts=1"],
        "`experiment.residual.combine` must be best with residual.n_starts = 1",
    ),
]


@pytest.mark.parametrize("overrides,message", BAD, ids=[" ".join(b[0]) for b in BAD])
def test_bad_values_are_refused(overrides, message):
    with pytest.raises(config.ConfigError, match=message):
        _load(overrides)


def test_wrong_types_are_refused_when_composing():
    with pytest.raises(ConfigCompositionException) as info:
        _compose(["seed=abc"])
    assert "seed" in str(info.value.__cause__ or info.value)


def _cli(args, cwd, module=False, timeout=300):
    cmd = (
        [sys.executable, "-m", "experiments"]
        if module
        else [
            sys.executable,
            str(REPO / "experiments" / "run.py"),
        ]
    )
    return subprocess.run(cmd + args, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def test_cli_refuses_a_bad_value_before_running(tmp_path):
    """`experiment.T=-5` stops with exit status 2 and a message naming the key; nothing
    runs (no resolved config, no figures), and results.json records the failure."""
    out = tmp_path / "run"
    proc = _cli([f"hydra.run.dir={out}", "experiment.T=-5"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "invalid configuration: `experiment.T` must be an integer >= 2" in proc.stderr
    assert "Traceback" not in proc.stderr
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "failed" and "experiment.T" in res["error"]
    assert not (out / "resolved_config.yaml").exists()
    assert not list(out.glob("*.png"))
    # Hydra's job log is written only when something is logged (it was an empty run.log)
    assert not list(out.glob("*.log"))


def test_a_sweeps_job_folders_name_their_overrides(tmp_path):
    """A sweep's job folders were `0_satellite_adam`, `1_satellite_adam`: which seed or
    horizon a folder held was in its `.hydra/` files only. The name now ends with the job's
    other overrides, in a form a folder name holds (a bad value stops the sweep at its
    first job, after Hydra made the folder)."""
    out = tmp_path / "sweep"
    args = ["-m", "seed=1,2", "experiment.T=1", "experiment.horizons=[10,20]"]
    proc = _cli([*args, f"hydra.sweep.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    folders = [p.name for p in out.iterdir() if p.is_dir()]
    assert folders == ["0_satellite_adam_experiment.T=1,experiment.horizons=-10,20-,seed=1"]
    assert config.swept("") == "" and config.swept("a=x/y z") == "_a=x-y-z"
    assert len(config.swept("seed=" + "1" * 300)) == 1 + config.SWEPT_LENGTH


def test_cli_names_a_cache_folder_it_cannot_make(tmp_path):
    """`jax_cache_dir` under a regular file ended in a Python traceback (exit 1)."""
    (tmp_path / "file").write_text("")
    cache = tmp_path / "file" / "cache"
    proc = _cli([f"hydra.run.dir={tmp_path / 'run'}", f"jax_cache_dir={cache}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "invalid configuration: `jax_cache_dir`: `path`: cannot create" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_refuses_a_group_set_to_null(tmp_path):
    """`experiment=null` (or `solver=~`) stops with exit status 2 and the options of the
    group, not Hydra's traceback ("Config group override must be a string"). The message
    is `run.check_groups`'s, checked here for both groups; the command line, which
    `experiments/run.py` and `python -m experiments` both reach through `run.cli`, runs
    once (`python -m experiments solver=~`)."""
    for arg, option in (("experiment=null", "satellite"), ("solver=~", "levenberg_marquardt")):
        message = run.check_groups([f"hydra.run.dir={tmp_path / 'run'}", arg])
        group = arg.split("=")[0]
        assert message.startswith(f"`{group}` must name one of ") and option in message
    proc = _cli([f"hydra.run.dir={tmp_path / 'run'}", "solver=~"], cwd=REPO, module=True)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "invalid configuration: `solver` must name one of " in proc.stderr
    assert "levenberg_marquardt" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_says_where_a_method_is_added():
    """A method added with `+` (Hydra: "Invalid type assigned: dict is not a subclass of
    Method") is answered with where methods are written."""
    arg = "+experiment.methods.mine={label:mine,cost:multi_step,solver:{name:gauss_newton}}"
    message = run.check_added_methods(["experiment.T=20", arg])
    assert (
        message.startswith(repr(arg)) and "add it under `methods:` in configs/experiment" in message
    )
    assert run.check_added_methods(["experiment.methods.slsqp_fd.solver.kwargs.maxiter=50"]) is None


def test_cli_names_experiment_data_path_when_the_benchmark_files_are_missing(tmp_path):
    """A real-data run without its files stops with exit status 2 and says how a run is
    given them (`experiment.data_path`), not only the loader's own `path=`."""
    out = tmp_path / "run"
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = _cli(
        [f"hydra.run.dir={out}", "experiment=emps", f"experiment.data_path={empty}"], cwd=tmp_path
    )
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "missing data: EMPS benchmark: could not find DATA_EMPS.mat" in proc.stderr
    assert "experiment.data_path=<folder>" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert json.loads((out / "results.json").read_text())["status"] == "failed"


def test_cli_reports_a_malformed_benchmark_file_in_one_line(tmp_path):
    """A benchmark file that loads as malformed (NaN in a column) stops with exit status 2
    and the loader's message, not a traceback (a missing file did; this did not)."""
    data = tmp_path / "data"
    data.mkdir()
    rows = "".join(
        f"{k},{k},{'nan' if k == 3 else k},{k},{4 if k == 0 else ''}\n" for k in range(20)
    )
    (data / "dataBenchmark.csv").write_text("uEst,uVal,yEst,yVal,Ts\n" + rows)
    out = tmp_path / "run"
    proc = _cli(
        [f"hydra.run.dir={out}", "experiment=cascaded_tanks", f"experiment.data_path={data}"],
        cwd=tmp_path,
    )
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "malformed data:" in proc.stderr and "yEst" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_python_m_experiments_composes(tmp_path):
    proc = _cli(["--cfg", "job", "solver=gauss_newton", "experiment.T=100", "seed=3"], REPO, True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = OmegaConf.create(proc.stdout)
    assert (cfg.solver.name, cfg.experiment.T, cfg.seed) == ("gauss_newton", 100, 3)


def test_a_run_sent_sigterm_is_recorded_as_failed_and_gives_its_folder_back(tmp_path):
    """SIGTERM (`kill`, `timeout`, a scheduler's time limit) ends a run as Ctrl-C does:
    results.json says it failed and why, `.running` is removed, and the exit status is
    143; the handler before the run is restored. (Python's default ended the process with
    neither.)"""
    import signal

    def killed(cfg, outdir, command):
        signal.raise_signal(signal.SIGTERM)
        raise AssertionError("not reached: the handler raises")

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stopped:
        run.execute(_compose(), tmp_path, command="cmd", runner=killed)
    assert stopped.value.code == 143 and signal.getsignal(signal.SIGTERM) is before
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["status"] == "failed" and "SIGTERM" in res["error"]
    assert not (tmp_path / run.RUNNING).exists()


def test_failed_run_replaces_stale_results(tmp_path):
    """An earlier run's results.json and results.md are removed at the start; a run that
    fails leaves results.json with status "failed", its error and its conditions."""
    (tmp_path / "results.json").write_text(json.dumps({"status": "ok", "figures": ["a.png"]}))
    (tmp_path / "results.md").write_text("old")
    (tmp_path / "a.png").write_bytes(b"old")

    def boom(cfg, outdir, command):
        assert not (outdir / "results.json").exists()
        assert not (outdir / "results.md").exists() and not (outdir / "a.png").exists()
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        run.execute(_compose(), tmp_path, command="cmd", runner=boom)
    res = json.loads((tmp_path / "results.json").read_text())
    assert res == {
        "status": "failed",
        "error": "RuntimeError: boom",
        "experiment": "satellite",
        "command": "cmd",
        "wall_time_s": res["wall_time_s"],
        "conditions": run.conditions(),  # (a failure states its conditions too)
    }
    assert not (tmp_path / "results.md").exists()
    assert not list(tmp_path.glob(".results.json.*"))  # no temporary file left

    out = run.execute(_compose(), tmp_path, command="cmd", runner=lambda c, o, command: {"x": 1})
    assert json.loads((tmp_path / "results.json").read_text()) == out
    assert out["status"] == "ok" and out["x"] == 1
    # A runner's own "status" (its fit's stop, say) does not stand for the run's.
    out = run.execute(
        _compose(), tmp_path, command="cmd", runner=lambda c, o, command: {"status": "stalled"}
    )
    assert out["status"] == "ok" and out["runner_status"] == "stalled"

    # A file the runner wrote is listed, and removed when the next run starts: a failed
    # rerun leaves no result of the earlier run beside its own "failed".
    def saves(c, o, command):
        (o / "fit.npz").write_bytes(b"fit")
        return {}

    out = run.execute(_compose(), tmp_path, command="cmd", runner=saves)
    assert out["files"] == ["fit.npz"] and (tmp_path / "fit.npz").exists()
    with pytest.raises(RuntimeError, match="boom"):
        run.execute(_compose(), tmp_path, command="cmd", runner=boom)
    assert not (tmp_path / "fit.npz").exists()


def test_a_folder_another_running_process_holds_is_refused(tmp_path):
    """Two runs started in the same second wrote into one folder: the second run's
    results beside the first run's configuration. A run holds its folder while it runs
    (`.running`, this process's id); another live process's folder is refused before
    anything is written there, a dead one's is taken over, and the file is gone after
    the run, a failed one's too."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / run.RUNNING).write_text(str(other.pid))
        (tmp_path / "results.json").write_text('{"status": "ok", "mine": 1}')
        with pytest.raises(
            config.ConfigError, match=rf"in use by another run \(process {other.pid}\)"
        ):
            run.execute(_compose(), tmp_path, command="cmd", runner=lambda c, o, command: {})
        assert json.loads((tmp_path / "results.json").read_text()) == {"status": "ok", "mine": 1}
    finally:
        other.kill()
        other.wait()
    out = run.execute(_compose(), tmp_path, command="cmd", runner=lambda c, o, command: {})
    assert out["status"] == "ok" and not (tmp_path / run.RUNNING).exists()
    assert "files" not in out  # (the claim is not among the run's files)

    def boom(c, o, command):
        assert (o / run.RUNNING).read_text() == str(os.getpid())
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        run.execute(_compose(), tmp_path, command="cmd", runner=boom)
    assert not (tmp_path / run.RUNNING).exists()


def test_every_job_of_a_sweep_compiles_its_own_first_calls(tmp_path, monkeypatch):
    """A sweep runs its jobs in one process: a job after the first reused the programs an
    earlier one compiled, while its report said its first calls included compilation.
    Each job starts with JAX's caches cleared; a persistent cache, where one is set, is
    named in the conditions."""
    traced = []
    f = jax.jit(lambda x: traced.append(1) or x + 1.0)  # (counts its traces)

    def runner(c, o, command):
        f(1.0)
        f(2.0)  # (the same program, within a job)
        return {}

    run.execute(_compose(), tmp_path / "job0", command="cmd", runner=runner)
    out = run.execute(_compose(), tmp_path / "job1", command="cmd", runner=runner)
    assert len(traced) == 2 and "persistent compilation cache" not in out["conditions"]
    # (JAX's configuration is global: the cache a job would set up, pretended)
    monkeypatch.setattr(run, "_cache_dir", lambda: str(tmp_path / "xla"))
    out = run.execute(_compose(), tmp_path / "job2", command="cmd", runner=runner)
    assert f"persistent compilation cache in {tmp_path / 'xla'}" in out["conditions"]


def test_an_emps_window_longer_than_the_record_is_refused_before_a_fit(tmp_path):
    """With no window that fits the estimation record the run stops with a configuration
    error before any fit (exit status 2; it was a traceback after the data were loaded).
    A window that does not fit, next to some that do, is left out and said so
    (`windows_left_out`: it was left out in silence)."""
    import scipy.io

    t = np.arange(60)[:, None] * 1e-3
    est = dict(t=t, qm=np.sin(t), qg=np.sin(t), vir=np.cos(t), kp=160.18, kv=243.45, gtau=35.15)
    folder = tmp_path / "data"
    folder.mkdir()
    scipy.io.savemat(folder / "DATA_EMPS.mat", est)
    scipy.io.savemat(folder / "DATA_EMPS_PULSES.mat", {**est, "pulses_N": np.zeros((60, 1))})
    cfg = _compose(
        [
            "experiment=emps",
            f"experiment.data_path={folder}",
            "experiment.open_loop.windows=[100]",
            "experiment.closed_loop.windows=[200]",
        ]
    )
    with pytest.warns(UserWarning, match="not the official record"):
        with pytest.raises(config.ConfigError, match=r"must hold a window of at most the 60"):
            run.execute(cfg, tmp_path / "out", command="cmd")


def test_results_tables_show_a_huge_or_infinite_standard_error_in_significant_digits():
    # (an unidentifiable tank level's 5.6e16 printed as 56317653543639608.00000)
    assert common.plus_minus(14.716, 5.6317653543639608e16, 5) == "14.71600 ± 5.63e+16"
    assert common.plus_minus(1.2, float("inf"), 4, 3) == "1.2000 ± inf"
    assert common.plus_minus(0.05809, 0.00111, 5) == "0.05809 ± 0.00111"
    assert common.plus_minus(2.0, 0.0123, 4, 3) == "2.0000 ± 0.012"
    # A NaN standard error (a diverged fit's) is None once `to_jsonable` has made the
    # results strict JSON: the tanks report of a Gauss-Newton run crashed on it.
    std = common.to_jsonable({"k": float("nan")})["k"]
    assert std is None and common.plus_minus(1.0, std, 5) == "1.00000 ± nan"
    assert common.plus_minus(None, None, 2) == "nan ± nan"


def test_an_experiment_without_a_schema_is_refused_with_what_to_add():
    """A user's YAML that does not start from a registered schema: a ConfigError naming
    the schema line, not an AttributeError of the solver check."""
    from omegaconf import open_dict

    cfg = _compose()
    with open_dict(cfg):
        cfg.experiment = {"name": "lag", "T": 200}
    with pytest.raises(config.ConfigError, match="/schema/experiment/<name>@experiment"):
        config.load(cfg)


SMALL = [
    "experiment.T=20",
    "experiment.n_seeds=2",
    "experiment.horizon_seeds=2",
    "experiment.horizons=[10,20]",
    "experiment.fig3.n_starts=2",
    "experiment.fig2.grid=12",
    "experiment.solver_defaults.adam.max_steps=300",
    "experiment.simulate_time=5",
    "experiment.run_methods=[slsqp_fd,slsqp_fd_one_step,trust_constr_fd_raw]",
]


def test_run_end_to_end(tmp_path):
    out = tmp_path / "run"
    proc = _cli([f"hydra.run.dir={out}", *SMALL], cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "ok"
    assert (out / "resolved_config.yaml").is_file()
    assert (out / ".hydra" / "config.yaml").is_file()
    md = (out / "results.md").read_text()
    assert md.startswith("# Satellite")
    # the run's output holds no INFO line of JAX's backend probing (configs/config.yaml)
    assert "Unable to initialize backend" not in proc.stdout + proc.stderr
    # the raw trust-constr baseline fails on purpose, and its rows say so
    assert "trust-constr + finite differences (raw, default tol) †" in md
    assert "† Shown failing on purpose" in md
    assert set(res["figures"]) == set(satellite.FIGURES.values())
    for fig in res["figures"]:
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", fig
    assert set(res["monte_carlo"]) == {
        "proposed",
        "slsqp_fd",
        "slsqp_fd_one_step",
        "trust_constr_fd_raw",
    }
    assert res["monte_carlo"]["proposed"]["n"] == 2
    assert set(res["horizons"]) == {"10", "20"}
    main = res["main_fit"]
    assert len(main["theta"]["I"]) == 3 and main["path_length"] >= 2
    assert main["stop_reason"] and main["time_s"] > 0
    assert all(np.isfinite(res["crb_rmse"][k]) for k in res["crb_rmse"])
    # the recorded path (Figs. 2, 3: FitResult.history) ends at the estimate
    np.testing.assert_allclose(main["path_end"], main["theta"]["I"], rtol=1e-12)
    # the main fit is saved, and loads with the example's model to the reported estimate
    from oneshot_jax.examples import satellite as example

    assert res["fit_file"] == "fit.npz" and "fit.npz" in res["files"]
    fit = oj.load_result(out / "fit.npz", model=example.model(res["dt"], 1))
    np.testing.assert_array_equal(fit.theta["I"], main["theta"]["I"])
    assert fit.status == main["stop_reason"]
    # A fit that did not converge (Adam at lr 1e-2 diverged at step 1) is not shown as an
    # estimate: no bold row with standard errors, and a sentence that names its stop.
    from experiments import satellite_report

    assert main["success"] and f"| **{main['label']}** | **" in md
    failed = {**main, "success": False, "stop_reason": "diverged", "message": "the loss became"
              " non-finite at step 1; the simulation diverged"}  # fmt: skip
    text = satellite_report.markdown({**res, "main_fit": failed})
    assert f"| {main['label']} (diverged: not an estimate) | " in text
    assert f"| **{main['label']}** | **" not in text and "at the returned point" in text
    assert "did not converge**: it stopped with `diverged` (the loss became non-finite" in text


def test_emps_hybrid_end_to_end(tmp_path):
    """`experiment=emps_hybrid` on a tiny budget: the three stages run, both models are
    scored with the protocol (finite numbers) and the figures are written."""
    from oneshot_jax import datasets

    benchmark_or_skip(datasets.load_emps)
    out = tmp_path / "run"
    args = [
        f"hydra.run.dir={out}",
        "experiment=emps_hybrid",
        "experiment.n_samples=400",
        "experiment.window=20",
        "experiment.widths=[4]",
        "experiment.adam.steps=3",
        "experiment.adam.weight_decay=1e-3",
        "experiment.lm_steps=1",
        "experiment.solver_defaults.levenberg_marquardt.max_steps=3",
        "progress=false",
    ]
    proc = _cli(args, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "ok"
    assert (out / "results.md").read_text().startswith("# EMPS: physics plus a neural friction")
    assert [s["stage"] for s in res["stages"]] == [
        "physics",
        "joint, Adam",
        "joint, Levenberg-Marquardt",
    ]
    assert res["n_windows"] == 20 and res["network"]["parameters"] == 13
    for model in ("physical", "hybrid", "reference"):
        scores = res[model]["protocol"]
        assert scores["n"] == 20
        assert all(np.isfinite(scores[k]) for k in ("rmse_mm", "nrmse", "r2", "fit_percent"))
    assert np.isfinite(res["hybrid"]["learned_force_N"]["max_abs"])
    # r of the velocity alone: the page names no position for its largest force
    md = (out / "results.md").read_text()
    assert "Largest learned force over" in md and "(at mid-travel" not in md
    from experiments import emps_hybrid_report

    res_qv = {**res, "config": {**res["config"], "inputs": "qv"}}
    assert "Largest learned force over" in emps_hybrid_report.markdown(res_qv)
    assert "(at mid-travel, q = " in emps_hybrid_report.markdown(res_qv)
    assert set(res["figures"]) == {"compare.png", "friction.png"}
    for fig in res["figures"]:
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", fig


TANKS_HYBRID_SMALL = [
    "experiment=cascaded_tanks_hybrid",
    "experiment.n_samples=40",
    "experiment.basic.substeps=1",
    "experiment.overflow.substeps=1",
    "experiment.overflow.h1_starts=[10]",
    "experiment.substeps=1",
    "experiment.residual.widths=[3]",
    "experiment.residual.n_starts=2",
    "experiment.joint.adam_steps=3",
    "experiment.joint.weight_decay=1e-4",
    "experiment.joint.refine=none",
    "experiment.extra_seeds=[1]",
    "solver.kwargs.max_steps=3",
    "progress=false",
]


def test_cascaded_tanks_hybrid_end_to_end(tmp_path):
    """The hybrid tanks experiment on a tiny budget through the Hydra entry point: the
    run succeeds, writes its tables and figures, and every score is finite."""
    from oneshot_jax import datasets

    benchmark_or_skip(datasets.load_cascaded_tanks)
    out = tmp_path / "run"
    proc = _cli([f"hydra.run.dir={out}", *TANKS_HYBRID_SMALL], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert res["status"] == "ok"
    assert (out / "results.md").read_text().startswith("# Cascaded tanks: a hybrid model")
    assert res["figures"] == ["compare.png", "learned_terms.png"]
    for fig in res["figures"]:
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", fig
    # the physics ends with the quadratic sensor (experiment.sensor, on by default)
    assert "c2" in res["physical"]["theta"] and "c2" in res["hybrid"]["theta"]
    for row in (res["physical"], res["hybrid"]):
        scores = [row["rmse_estimation_V"], row["rmse_validation_V"], row["protocol"]["rmse_V"]]
        assert all(v is not None and np.isfinite(v) for v in scores)
        assert all(v is not None and np.isfinite(v) for v in row["theta"].values())
    # features (x1, x2) -> 3 hidden -> 2 outputs
    assert res["hybrid"]["n_network_parameters"] == 2 * 3 + 3 + 3 * 2 + 2
    assert set(res["hybrid"]["stages"]) == {"adam"}
    # the seed table: the run's seed, then the extra one, from different initialisations
    assert [r["seed"] for r in res["seeds"]] == [0, 1]
    assert res["seeds"][0]["rmse_test_V"] == res["hybrid"]["protocol"]["rmse_V"]
    assert res["seeds"][0]["rmse_estimation_V"] != res["seeds"][1]["rmse_estimation_V"]
    assert "| mean |" in (out / "results.md").read_text()
    # the committee of both starts (residual.combine = mean, the default)
    committee = res["committee"]
    assert len(committee["member_losses"]) == 2
    assert len(committee["protocol"]["members_rmse_V"]) == 2
    assert res["hybrid"]["protocol"]["rmse_V"] in committee["protocol"]["members_rmse_V"]
    assert np.isfinite(committee["protocol"]["rmse_V"])
    assert res["seeds"][0]["committee_rmse_test_V"] == committee["protocol"]["rmse_V"]
    assert all(np.isfinite(r["committee_rmse_test_V"]) for r in res["seeds"])
    assert "committee of 2 (mean output)" in (out / "results.md").read_text()


def test_a_scipy_baselines_label_names_the_options_that_run():
    """`solver=slsqp solver.kwargs.jac=fd solver.kwargs.scale=false` was labelled "SLSQP +
    closed-form gradient (scaled)" (the YAML's label), and a gradient-free method kept
    the gradient; a label that names the options stays (the study's methods keep theirs)."""
    cfg = _compose(["solver=slsqp", "solver.kwargs.jac=fd", "solver.kwargs.scale=false"])
    assert config.load(cfg).solver.title == "SLSQP + finite differences (raw)"
    cfg = _compose(["solver=slsqp", "solver.kwargs.method=Nelder-Mead"])
    assert config.load(cfg).solver.title == "Nelder-Mead + no gradient (scaled)"
    from experiments import satellite_report

    assert satellite_report._kind({"name": "scipy", "kwargs": {"method": "Nelder-Mead"}})[0] == (
        "none"
    )
    assert config.load(_compose(["solver=slsqp"])).solver.title == (
        "SLSQP + closed-form gradient (scaled)"
    )
    for m in config.load(_compose()).experiment.methods.values():
        assert m.solver.described(m.label) == m.label
