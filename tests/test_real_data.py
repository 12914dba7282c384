"""Reduced fits on the real benchmarks: a short stretch of each estimation record, fitted
with the experiments' own code, lands near the full-run parameters; the experiments run
the configured solver.

The full runs (`python experiments/run.py experiment=emps|cascaded_tanks`) use the whole
records; the numbers they print are in docs/case-studies/emps.md and
docs/case-studies/cascaded_tanks.md. These tests skip, naming the files, when the
benchmark files are not found (they are not in the repository).
"""

import functools
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import benchmark_or_skip

import oneshot_jax as oj
from oneshot_jax import datasets as ds

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments import cascaded_tanks, config, emps  # noqa: E402

# Full-run estimates (docs/case-studies/emps.md, docs/case-studies/cascaded_tanks.md).
EMPS_FULL = {"M": 95.1070, "Fv": 203.8237, "Fc": 20.4664, "offset": -3.1684}
TANKS_FULL = {
    "k1": 0.04589,
    "k3": 0.05407,
    "k4": 0.05244,
    "c": -1.84978,
    "h1": 14.91295,
    "h2": 11.73456,
    "k5": 0.93745,
}


def _load(loader):
    return benchmark_or_skip(loader)


def test_emps_closed_loop_on_six_seconds():
    """Closed-loop output-error fit on the first 6 s (of 24.8 s): M, Fv, Fc within 3 %
    and the offset within 8 % of the full run; the validation error in the closed-loop
    simulator stays at the full run's level."""
    data = _load(ds.load_emps)
    ex = config.EMPSConfig(n_samples=6000)
    row = emps.fit_closed_loop(data, None, ex, oj.LevenbergMarquardt(max_steps=200))
    th = row["theta"]
    for k in ("M", "Fv", "Fc"):
        assert th[k] > 0
        assert th[k] == pytest.approx(EMPS_FULL[k], rel=0.03), (k, th)
    assert th["offset"] == pytest.approx(EMPS_FULL["offset"], rel=0.08), th
    assert all(np.isfinite(v) and v > 0 for v in row["std"].values())
    sc = emps.score(data, th, ex)
    assert sc["validation"]["relerr_position_pct"] < 0.0016


def test_emps_experiment_runs_the_configured_solver(tmp_path):
    """`experiment=emps solver=gauss_newton` runs Gauss-Newton (the solver is honoured,
    not replaced by the experiment's default), on a reduced sweep; the closed-loop window,
    longer than the samples used, is left out and named."""
    _load(ds.load_emps)
    from hydra import compose, initialize_config_dir

    config.register()
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=[
                "experiment=emps",
                "solver=gauss_newton",
                "experiment.n_samples=3000",
                "experiment.open_loop.windows=[500]",
                "experiment.closed_loop.windows=[5000]",  # (longer than the 3000 used)
                "experiment.figures=false",
                "experiment.check_unconstrained=false",
                "progress=false",
            ],
        )
    res = emps.run(config.load(cfg), tmp_path, command="test")
    assert res["solver"]["name"] == "gauss_newton"
    (row,) = res["sweeps"]["open_loop"]
    assert row["n_windows"] == 6 and row["stop_reason"] == "converged" and row["success"]
    assert row["theta"]["M"] == pytest.approx(EMPS_FULL["M"], rel=0.05)
    assert "Gauss-Newton" in (tmp_path / "results.md").read_text()
    # A window longer than the samples used is left out, and said so (it was silent).
    assert res["windows_left_out"] == {"closed_loop": [5000]} and not res["sweeps"].get(
        "closed_loop"
    )
    assert "left out: closed loop [5000]" in (tmp_path / "results.md").read_text()


@functools.cache
def _overflow_on_768():
    """The overflow model on the first 768 of 1024 estimation samples (both overflow
    episodes start before sample 600) from the full-run parameters perturbed by +-10 %,
    the signs alternating, and by the opposite signs: two starts in one multistart, the
    call `cascaded_tanks.fit_overflow` makes in
    `test_tanks_overflow_starts_from_the_rough_guess_too` (the same model, solver and
    shapes: the module compiles that fit once)."""
    data = _load(ds.load_cascaded_tanks)
    ex = config.TanksConfig()
    signs = [(1.1 if i % 2 else 0.9) for i in range(len(TANKS_FULL))]
    starts = {
        k: jnp.asarray([v * s, v * (2.0 - s)]) for (k, v), s in zip(TANKS_FULL.items(), signs)
    }
    solver = oj.LevenbergMarquardt(max_steps=300)
    x0 = [[9.0, 7.0], [9.0, 7.0]]
    return cascaded_tanks.fit_model("overflow", data, ex, starts, x0, solver, 768, True)


def test_tanks_overflow_on_first_768_samples():
    """Overflow model on the first 768 of 1024 estimation samples (both overflow episodes
    start before sample 600), from the full-run parameters perturbed by +-10 % in two
    directions (`_overflow_on_768`): both starts land within 20 % of them, and the
    validation RMSE stays below 0.40 V."""
    data = _load(ds.load_cascaded_tanks)
    res, model = _overflow_on_768()
    for start in range(2):
        th = {k: float(v[start]) for k, v in res.starts.theta.items()}
        for k, v in TANKS_FULL.items():
            assert th[k] == pytest.approx(v, rel=0.2), (start, k, th)
        assert 0.0 <= th["k5"] <= 1.0
    y_val = cascaded_tanks.simulate(model, res.theta, res.x0, data.u_val)
    assert float(oj.metrics.rmse(data.y_val, y_val)[0]) < 0.40


def test_tanks_overflow_starts_from_the_rough_guess_too():
    """On the first 768 samples the basic model's estimate lies outside the overflow
    model's basin (its upper tank starts above 30 V): the overflow fit from it ends at
    more than five times the loss of the fit from the rough guess (`basic.theta0`,
    `x0`), which `fit_overflow` also runs and keeps (estimation RMSE below 0.3 V)."""
    data = _load(ds.load_cascaded_tanks)
    ex = config.TanksConfig(n_samples=768)
    ex.overflow.h1_starts = [10.0]
    solver = oj.LevenbergMarquardt(max_steps=300)
    basic, _ = cascaded_tanks.fit_model(
        "basic", data, ex, dict(ex.basic.theta0), ex.x0, solver, 768
    )
    assert float(basic.x0[0]) > 30.0  # the trap this test is about
    res, model = cascaded_tanks.fit_overflow(data, ex, basic.theta, basic.x0, solver, 768)
    losses = np.asarray(res.starts.loss)
    assert losses.shape == (2,) and res.best == 1, losses
    assert losses[1] < 0.2 * losses[0], losses
    y = cascaded_tanks.simulate(model, res.theta, res.x0, data.u_est[:768])
    assert float(oj.metrics.rmse(data.y_est[:768], y)[0]) < 0.3


def test_tanks_quadratic_sensor_lowers_the_estimation_error():
    """The quadratic sensor (c2) beside the overflow model's estimate on the first 768
    samples (`_overflow_on_768`, both starts converged to one optimum), from c2 = 0: the
    fit curves the sensor (c2 > 0) and lowers the estimation RMSE by more than a fifth
    (from about 0.23 V, the overflow model alone, to about 0.14 V). Without the sensor
    term in `observe`, c2 would have no effect and the RMSE could not drop."""
    data = _load(ds.load_cascaded_tanks)
    ex = config.TanksConfig()
    base, _ = _overflow_on_768()
    assert base.starts.stop_reason == ("converged", "converged")
    np.testing.assert_allclose(base.starts.loss[0], base.starts.loss[1], rtol=1e-6)
    rmse0 = float(np.atleast_1d(base.metrics["rmse"])[0])
    start = {**{k: float(v) for k, v in base.theta.items()}, "c2": 0.0}
    solver = oj.LevenbergMarquardt(max_steps=300)
    res, _ = cascaded_tanks.fit_model("overflow", data, ex, start, base.x0, solver, 768)
    rmse = float(np.atleast_1d(res.metrics["rmse"])[0])
    assert rmse0 > 0.2 and rmse < 0.8 * rmse0, (rmse0, rmse)
    assert float(res.theta["c2"]) > 0.05


_EMPS_GN = """
import jax
jax.config.update("jax_enable_x64", True)
import oneshot_jax as oj
from oneshot_jax.examples import emps as ex
data = oj.datasets.load_emps()
U, Z, X0 = ex.open_loop_data(data.estimation, data.gtau, data.Ts, 100, 5)
box = oj.constraints.box(lower=ex.LOWER)
for solver in (oj.GaussNewton, oj.LevenbergMarquardt):
    r = oj.fit(ex.open_loop_model(data.Ts), ex.THETA0, X0, U, Z,
               solver=solver(max_steps=200), constraints=box)
    print(r.status, r.num_steps, repr(float(r.loss)))
"""


def test_gauss_newton_on_emps_windows_converges_where_levenberg_marquardt_does():
    """EMPS in open loop, 248 windows of 100 samples, each with its own x0, from the far
    start with M, Fv, Fc >= 1e-6 (the peers benchmark's problem (b)), on one core with
    XLA's default optimisation (as `benchmarks/peers.py --pin-cpu 1` runs it; XLA's
    threads change the round-off): Gauss-Newton ran its 200 steps at the optimum's loss,
    accepting the search's simulated "decreases" at round-off against the
    linearisation's C, and ended max_steps_reached. It now stops converged there, at the
    loss Levenberg-Marquardt reaches."""
    import os
    import subprocess
    import sys

    _load(ds.load_emps)
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in (  # (the tests' options of conftest.py that change the compiled program)
        "--xla_backend_optimization_level=0",
        "--xla_disable_hlo_passes=while-loop-invariant-code-motion,simplify-while-loops",
    ):
        flags = flags.replace(flag, "")
    core = min(os.sched_getaffinity(0))
    done = subprocess.run(
        [sys.executable, "-c", _EMPS_GN],
        env=dict(os.environ, XLA_FLAGS=flags.strip()),
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=lambda: os.sched_setaffinity(0, {core}),
    )
    assert done.returncode == 0, done.stderr[-2000:]
    (gn, gn_steps, gn_loss), (lm, _, lm_loss) = [
        line.split() for line in done.stdout.strip().splitlines()[-2:]
    ]
    assert gn == "converged" and int(gn_steps) < 50, done.stdout
    assert lm == "converged" and float(gn_loss) == pytest.approx(float(lm_loss), rel=1e-9)
