"""The EMPS friction study (`experiments/emps_friction.py`): its friction terms, its
configuration checks, and an end-to-end run on a tiny slice of the records."""

import json
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import benchmark_or_skip
from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from experiments import config, emps_friction, run  # noqa: E402
from oneshot_jax.examples import emps as example  # noqa: E402

config.register()


def _compose(overrides=()):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return compose(config_name="config", overrides=["experiment=emps_friction", *overrides])


def test_friction_terms():
    """The benchmark's structure is the example's model; dFv and mu add v |v|-type and
    load terms that differ by direction and grow with |tau|."""
    base = {"M": 95.0, "Fv": 200.0, "Fc": 20.0, "offset": -3.0}
    plant = emps_friction.FrictionPlant()
    x, u = jnp.array([0.1, 0.05]), jnp.array([40.0])
    np.testing.assert_allclose(plant(x, u, base), example.Plant()(x, u, base), rtol=1e-14)
    for v in (0.05, -0.05):
        for tau in (0.0, 150.0):
            th = {**base, "dFv": 30.0, "mu": 0.1, "Fs": 5.0}
            got = emps_friction.friction(v, tau, th, vs=0.02)
            s = np.tanh(v / example.EPS)
            stribeck = 5.0 * np.exp(-((v / 0.02) ** 2))
            want = 200.0 * v + 30.0 * abs(v) + (20.0 + 0.1 * np.hypot(tau, 1.0) + stribeck) * s
            want -= 3.0
            np.testing.assert_allclose(got, want, rtol=1e-13)


def test_position_dependent_terms():
    """Fcq and Fq interpolate Fc and offset linearly between knots spread over the
    travel: equal knot values give the constant model; between two knots the value is
    their linear blend; the hat functions sum to one, also beyond the travel."""
    K = 6
    knots = np.linspace(*emps_friction.TRAVEL, K)
    for q in (-0.01, 0.0, 0.013, knots[2], 0.2, 0.3):
        w = np.asarray(emps_friction.knot_weights(q, K))
        np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-14)
        assert np.all(w >= 0)
    base = {"M": 95.0, "Fv": 200.0, "Fc": 20.0, "offset": -3.0, "dFv": 30.0}
    const = {**base, "Fcq": np.full(K, 20.0), "Fq": np.full(K, -3.0)}
    del const["Fc"], const["offset"]
    for v, q in ((0.05, 0.07), (-0.02, 0.21)):
        np.testing.assert_allclose(
            emps_friction.friction(v, 10.0, const, q=q),
            emps_friction.friction(v, 10.0, base),
            rtol=1e-13,
        )
    fcq, fq = np.arange(K) + 10.0, 2.0 * np.arange(K) - 4.0
    th = {**const, "Fcq": fcq, "Fq": fq}
    q = 0.25 * knots[1] + 0.75 * knots[2]  # 3/4 of the way from knot 1 to knot 2
    v = 0.05
    s = np.tanh(v / example.EPS)
    want = 200.0 * v + 30.0 * v * s + (0.25 * fcq[1] + 0.75 * fcq[2]) * s
    want += 0.25 * fq[1] + 0.75 * fq[2]
    np.testing.assert_allclose(emps_friction.friction(v, 0.0, th, q=q), want, rtol=1e-13)
    with pytest.raises(ValueError, match="`q` is needed"):
        emps_friction.friction(v, 0.0, th)


def test_position_start_and_rows():
    """A position structure starts Fcq and Fq at Fc and offset at every knot (and has no
    Fc or offset); its rows keep them as lists, turned back into arrays for the model,
    and the mean of several fits is taken knot by knot."""
    from types import SimpleNamespace

    ex = SimpleNamespace(theta0={"M": 50.0, "Fv": 100.0, "Fc": 10.0, "offset": -1.0})
    ex.position_knots = 5
    th = emps_friction.theta_start(ex, "position_stribeck")
    assert set(th) == {"M", "Fv", "dFv", "Fs", "Fcq", "Fq"}
    np.testing.assert_array_equal(th["Fcq"], np.full(5, 10.0))
    np.testing.assert_array_equal(th["Fq"], np.full(5, -1.0))
    plain = emps_friction.as_plain(th)
    assert plain["Fcq"] == [10.0] * 5 and plain["M"] == 50.0
    back = emps_friction.as_arrays(plain)
    assert back["Fq"].shape == (5,) and isinstance(back["M"], float)
    other = {**plain, "Fcq": [12.0] * 5, "M": 60.0}
    mean = emps_friction.mean_theta([plain, other])
    np.testing.assert_allclose(mean["Fcq"], np.full(5, 11.0))
    assert float(mean["M"]) == 55.0
    assert emps_friction.fmt([1.0, 2.5]) == "[1, 2.5]" and emps_friction.fmt(95.1089) == "95.11"


def test_edge_drift():
    """The error's change across the pulse edges, signed by the direction of motion: a
    1 mm jump after the first of two edges averages to 0.5 mm, and changes sign with the
    motion."""
    from types import SimpleNamespace

    pulses = np.r_[np.zeros(200), 5.0 * np.ones(400), np.zeros(400)]
    t = np.arange(pulses.size) * 1e-3
    for v, want in ((0.05, 0.5), (-0.05, -0.5)):
        qm = 0.1 + v * t
        z = qm + 1e-3 * (np.arange(pulses.size) >= 200)
        rec = SimpleNamespace(pulses=pulses, qm=qm)
        got = emps_friction.edge_drift_mm(SimpleNamespace(z=z[:, None]), rec, 1e-3)
        np.testing.assert_allclose(got, want, rtol=1e-9)


@pytest.mark.parametrize(
    "overrides,message",
    [
        (["experiment.windows=[500,50]"], "`experiment.windows` must be increasing"),
        (["experiment.structures=[lugre]"], r"`experiment.structures\[0\]` must be one of"),
        (["experiment.cv_holdouts=[]"], "`experiment.cv_holdouts` must be a non-empty list"),
        (
            ["experiment.cv_holdouts=[0.2,0]"],
            r"`experiment.cv_holdouts\[1\]` must be a finite number > 0",
        ),
    ],
)
def test_bad_config(overrides, message):
    with pytest.raises(config.ConfigError, match=message):
        config.load(_compose(overrides))


def test_cross_validation_score():
    """The selection score is the mean held-out RMSE over the configured folds only (the
    whole-record fit, which holds nothing out, is not one of them)."""
    fits = {0.0: {"rmse_heldout_mm": None}, 0.1: {"rmse_heldout_mm": 1.0}}
    fits[0.3] = {"rmse_heldout_mm": 4.0}
    assert emps_friction.cross_validation_mm(fits, [0.1, 0.3]) == 2.5
    assert emps_friction.cross_validation_mm(fits, [0.3]) == 4.0


def test_final_model():
    """The mean parameters become the model only where they score better on the held-out
    parts on average; with no check (one fold) the whole-record fit stays."""
    check = {"holdouts": [0.1, 0.2], "single_mm": [1.0, 3.0], "mean_mm": [1.5, 2.0]}
    assert emps_friction.final_model(check) == "mean"
    assert emps_friction.final_model({**check, "mean_mm": [1.5, 2.6]}) == "whole"
    assert emps_friction.final_model({"holdouts": [], "single_mm": [], "mean_mm": []}) == "whole"


def test_end_to_end(tmp_path):
    """Two structures on 300 estimation samples, one rolling-origin fold: continuation
    runs (a windowed stage, then the whole span) on the whole record and on the fold's
    training span, the fold's held-out RMSE selects, every score is finite, mu respects
    its bound, and results.md is written."""
    from oneshot_jax import datasets

    benchmark_or_skip(datasets.load_emps)
    cfg = _compose(
        [
            "experiment.n_samples=300",
            "experiment.windows=[50]",
            "experiment.structures=[coulomb_viscous,load]",
            "experiment.cv_holdouts=[0.2]",
            "solver.kwargs.max_steps=3",
            "progress=false",
        ]
    )
    res = run.execute(cfg, tmp_path, command="cmd")
    assert res["status"] == "ok"
    assert res["spans"] == [0.0, 0.2]
    fits = {(r["structure"], r["holdout"]): r for r in res["rows"]}
    assert set(fits) == {(s, h) for s in ("coulomb_viscous", "load") for h in (0.0, 0.2)}
    assert fits["load", 0.0]["n_train"] == 300 and fits["load", 0.2]["n_train"] == 240
    assert fits["load", 0.0]["rmse_heldout_mm"] is None
    assert set(fits["load", 0.0]["theta"]) == {*example.PARAMS, "dFv", "mu"}
    assert fits["load", 0.0]["theta"]["mu"] >= 0.0 and fits["load", 0.2]["theta"]["mu"] >= 0.0
    for r in fits.values():
        assert [s["window"] for s in r["stages"]] == [50, None]
        assert np.isfinite(r["protocol"]["rmse_mm"]) and np.isfinite(r["edge_drift_mm"])
    cv = {s: fits[s, 0.2]["rmse_heldout_mm"] for s in ("coulomb_viscous", "load")}
    assert res["selected"] == min(cv, key=cv.get)
    assert json.loads((tmp_path / "results.json").read_text())["selected"] == res["selected"]
    for s, m in res["summary"].items():
        assert m["cv_mm"] == cv[s]
        assert m["test_whole_mm"] == fits[s, 0.0]["protocol"]["rmse_mm"]
        assert m["test_min_mm"] <= m["test_mean_mm"] <= m["test_max_mm"]
        assert np.isfinite(m["averaged"]["protocol"]["rmse_mm"])
        # leaving one of the two fits out of the mean leaves the other fit itself
        loo = sorted(m["averaged"]["leave_one_out_mm"])
        own = sorted(fits[s, h]["protocol"]["rmse_mm"] for h in (0.0, 0.2))
        np.testing.assert_allclose(loo, own, rtol=1e-6)
        assert m["aggregation_check"]["holdouts"] == []  # one fold: nothing to aggregate
    assert res["final"] == "whole"
    assert res["max_force_N"]["test"] > res["max_force_N"]["estimation"] > 0
    md = (tmp_path / "results.md").read_text()
    assert md.startswith("# EMPS: friction models trained for the open-loop protocol")
    assert "dynoNet" in md and "## Selection on the estimation record" in md


def test_aggregation_check():
    """The held-out part of each fold is scored with the mean parameters of the fits that
    did not see it: with identical fits the mean is that fit, and a fit that saw the
    held-out part (holdout 0.1 for the 0.2 fold) is left out of it."""
    from types import SimpleNamespace

    from oneshot_jax import datasets

    benchmark_or_skip(datasets.load_emps)
    data = datasets.load_emps(None)
    record = example.trim(data.estimation, 400)
    ex = SimpleNamespace(eps=example.EPS, substeps=1, stribeck_velocity=0.01, velocity_halfwidth=5)
    good = dict(example.REFERENCE)
    bad = {**good, "offset": 30.0}
    model = emps_friction.friction_model(data.Ts)

    def row(theta, h):
        _, held = emps_friction.split(record, h)
        return {
            "theta": theta,
            "rmse_heldout_mm": emps_friction.record_rmse_mm(model, theta, held, data.gtau, data.Ts),
        }

    fits = {0.1: row(bad, 0.1), 0.2: row(good, 0.2), 0.3: row(good, 0.3)}
    c = emps_friction.aggregation_check(data, record, fits, [0.3, 0.1, 0.2], ex)
    assert c["holdouts"] == [0.1, 0.2]
    # fold 0.2: the mean of the 0.2 and 0.3 fits (both good) is the good fit itself
    np.testing.assert_allclose(c["mean_mm"][1], fits[0.2]["rmse_heldout_mm"], rtol=1e-9)
    # fold 0.1: the bad fit is averaged with the good ones, a different model
    _, held = emps_friction.split(record, 0.1)
    mean = {k: (bad[k] + 2 * good[k]) / 3 for k in good}
    want = emps_friction.record_rmse_mm(model, mean, held, data.gtau, data.Ts)
    np.testing.assert_allclose(c["mean_mm"][0], want, rtol=1e-9)
    assert c["single_mm"] == [fits[0.1]["rmse_heldout_mm"], fits[0.2]["rmse_heldout_mm"]]
