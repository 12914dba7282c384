"""The Hydra experiments: every config composes, run.py runs end to end, data are seeded."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "configs"
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import common, satellite  # noqa: E402


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


GROUPS = _groups()
PAIRS = [(e, s) for e in GROUPS.get("experiment", []) for s in GROUPS.get("solver", [])]
OPTIONS = [(g, o) for g, opts in GROUPS.items() for o in opts]


def test_groups_discovered():
    assert "satellite" in GROUPS["experiment"]
    assert {"adam", "gauss_newton", "levenberg_marquardt", "slsqp", "trust_constr"} <= set(
        GROUPS["solver"]
    )


def test_default_config():
    cfg = _compose()
    assert cfg.experiment.name == "satellite"
    assert cfg.solver.name == "adam"
    assert cfg.seed == 0
    # the tuned Adam settings of the satellite experiment reach the solver config
    assert cfg.solver.kwargs.lr_theta == cfg.experiment.solver_defaults.adam.lr_theta


@pytest.mark.parametrize("group,option", OPTIONS)
def test_every_option_composes(group, option):
    cfg = _compose([f"{group}={option}"])
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved[group] is not None
    if group == "solver":
        common.solver_spec(cfg.solver)


@pytest.mark.parametrize("experiment,solver", PAIRS)
def test_experiment_solver_pairs_compose(experiment, solver):
    cfg = _compose([f"experiment={experiment}", f"solver={solver}"])
    OmegaConf.to_container(cfg, resolve=True)
    assert cfg.experiment.name == experiment
    assert (REPO / "experiments" / f"{cfg.experiment.name}.py").is_file()
    name, kwargs = common.solver_spec(cfg.solver)
    assert name in common.SOLVER_NAMES


def test_command_line_overrides_compose():
    cfg = _compose(
        ["solver=gauss_newton", "experiment.T=100", "seed=3", "solver.kwargs.max_epochs=7"]
    )
    assert (cfg.solver.name, cfg.experiment.T, cfg.seed) == ("gauss_newton", 100, 3)
    assert cfg.solver.kwargs.max_epochs == 7


def test_satellite_methods_are_valid_specs():
    cfg = _compose()
    methods = OmegaConf.to_container(cfg.experiment.methods, resolve=True)
    for key, spec in methods.items():
        assert spec["cost"] in ("multi_step", "single_step"), key
        common.solver_spec(spec["solver"])
    for key in list(cfg.experiment.fig4_methods) + list(cfg.experiment.fig5_methods):
        assert key in methods
    # the Adam baseline is the default solver: it is deduplicated into the proposed method
    assert common.same_solver(methods["adam"]["solver"], cfg.solver)


def test_satellite_data_deterministic():
    ex = _compose().experiment
    a = satellite.generate(ex, [3, 4], 30)
    b = satellite.generate(ex, [3, 4], 30)
    for key in ("u", "x", "z"):
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.allclose(a["z"][0], a["z"][1])  # seeds differ
    short = satellite.generate(ex, [4], 10)  # a shorter record is a prefix of a longer one
    np.testing.assert_array_equal(short["z"][0], a["z"][1, :10])
    np.testing.assert_allclose(a["x"][0, 0], np.asarray(ex.w0))
    # noise and torque have the configured statistics (loosely)
    big = satellite.generate(ex, [0], 600)
    assert abs(np.std(big["z"][0] - big["x"][0]) / ex.noise_std - 1) < 0.1
    assert abs(np.mean(big["u"][0]) / ex.torque_mean - 1) < 1e-3


def test_cli_locates_the_checkout(tmp_path):
    from oneshot_jax import _cli

    assert _cli._repo_root() == REPO
    # the console script's entry point composes the same configs from any folder
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "oneshot_jax._cli",
            "--cfg",
            "job",
            "solver=gauss_newton",
            "experiment.T=100",
            "seed=3",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = OmegaConf.create(proc.stdout)
    assert (cfg.solver.name, cfg.experiment.T, cfg.seed) == ("gauss_newton", 100, 3)


SMALL = [
    "experiment.T=20",
    "experiment.n_seeds=2",
    "experiment.horizon_seeds=2",
    "experiment.horizons=[10,20]",
    "experiment.fig3.n_starts=2",
    "experiment.fig2.grid=12",
    "experiment.solver_defaults.adam.max_epochs=300",
    "experiment.simulate_time=5",
    "experiment.run_methods=[slsqp_fd,slsqp_fd_one_step]",
]


def test_run_end_to_end(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, str(REPO / "experiments" / "run.py"), f"hydra.run.dir={out}", *SMALL],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert (out / "resolved_config.yaml").is_file()
    assert (out / ".hydra" / "config.yaml").is_file()
    assert (out / "results.md").read_text().startswith("## Satellite")
    assert set(res["figures"]) == set(satellite.FIGURES.values())
    for fig in res["figures"]:
        assert (out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", fig
    assert set(res["monte_carlo"]) == {"proposed", "slsqp_fd", "slsqp_fd_one_step"}
    assert res["monte_carlo"]["proposed"]["n"] == 2
    assert set(res["horizons"]) == {"10", "20"}
    main = res["main_fit"]
    assert len(main["theta"]["I"]) == 3 and main["path_length"] >= 2
    assert main["stop_reason"] and main["time_s"] > 0
    assert all(np.isfinite(res["crb_rmse"][k]) for k in res["crb_rmse"])
    # the recorded path (Figs. 2, 3) ends at the estimate, and recording does not change it
    np.testing.assert_allclose(main["path_end"], main["theta"]["I"], rtol=1e-12)
    np.testing.assert_allclose(
        res["seed0_estimates"]["proposed"]["theta"]["I"], main["theta"]["I"], rtol=1e-9
    )
