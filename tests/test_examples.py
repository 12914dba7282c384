"""The example systems (`oneshot_jax.examples`): each model agrees with the independent
data generator of its module, and the data preparation does what its docstring says."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax import datasets as ds
from oneshot_jax.examples import cascaded_tanks, chain, cstr, emps, satellite


def test_satellite_model_matches_numpy_generator():
    """The identification model (library RK4) and the numpy RK4 of the data generator
    integrate the same equations: with the same substeps they agree to round-off."""
    rng = np.random.default_rng(0)
    M = satellite.TORQUE_MEAN + satellite.TORQUE_STD * rng.standard_normal((40, 3))
    theta = np.asarray(satellite.THETA_TRUE)
    w0 = np.asarray(satellite.W0)
    x_np = satellite.simulate_np(theta[None], w0[None], M[None], satellite.DT, substeps=3)[0]
    x_oj, z_oj = oj.simulate(satellite.model(substeps=3), {"I": jnp.asarray(theta)}, w0, M)
    np.testing.assert_allclose(np.asarray(x_oj), x_np, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(np.asarray(z_oj), np.asarray(x_oj))  # the state is observed


def test_satellite_generate_seeded_and_prefix():
    a = satellite.generate([3, 4], 30)
    b = satellite.generate([3, 4], 30)
    for key in ("u", "x", "z"):
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.allclose(a["z"][0], a["z"][1])  # seeds differ
    short = satellite.generate([4], 10)  # a shorter record is a prefix of a longer one
    np.testing.assert_array_equal(short["z"][0], a["z"][1, :10])
    np.testing.assert_allclose(a["x"][0, 0], satellite.W0)
    big = satellite.generate([0], 600)  # noise and torque have the configured statistics
    assert abs(np.std(big["z"][0] - big["x"][0]) / satellite.NOISE_STD - 1) < 0.1
    assert abs(np.mean(big["u"][0]) / satellite.TORQUE_MEAN - 1) < 1e-3


def test_chain_model_matches_numpy_generator():
    data = chain.generate(n=5, T=60, seed=2, noise_std=0.0)
    theta = {k: jnp.asarray(v) for k, v in data["theta"].items()}
    x, z = oj.simulate(chain.model(5), theta, np.zeros(10), data["u"])
    np.testing.assert_allclose(np.asarray(x), data["x"], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(z), data["z"], rtol=1e-10, atol=1e-12)
    assert chain.model(5) == chain.model(5)  # equal models share their compilation


def test_emps_plant_is_the_friction_model():
    th = {"M": 95.0, "Fv": 200.0, "Fc": 20.0, "offset": -3.0}
    x, tau = jnp.array([0.1, 0.02]), 150.0
    expected = (tau - 200.0 * 0.02 - 20.0 * np.tanh(0.02 / 1e-3) + 3.0) / 95.0
    np.testing.assert_allclose(emps.Plant()(x, jnp.array([tau]), th), [0.02, expected])
    assert emps.open_loop_model(1e-3) == emps.open_loop_model(1e-3)


def test_emps_velocity_estimate_and_windows():
    Ts, t = 1e-3, np.arange(200) * 1e-3
    qm = 0.3 * t**2 + 0.1 * t  # a central difference is exact on a quadratic
    v = emps.velocity_estimate(qm, Ts, half=5)
    np.testing.assert_allclose(v[5:-5], 0.6 * t[5:-5] + 0.1, rtol=1e-9)
    assert v[0] == v[5] and v[-1] == v[-6]  # held at the ends
    starts, T = emps.window_starts(205, 50)
    np.testing.assert_array_equal(starts, [0, 50, 100, 150])
    assert T == 50
    starts, T = emps.window_starts(205, None)
    np.testing.assert_array_equal(starts, [0])
    assert T == 205


def test_emps_open_loop_data_from_a_record():
    n = 230
    rec = ds.EMPSRecord(
        t=np.arange(n) * 1e-3,
        qm=np.linspace(0.0, 0.2, n),
        qg=np.zeros(n),
        vir=np.sin(np.arange(n) / 9.0),
        pulses=np.zeros(n),
        file=None,
    )
    u, z, x0 = emps.open_loop_data(rec, gtau=35.0, Ts=1e-3, T=100)
    assert u.shape == (2, 100, 1) and z.shape == (2, 100, 1) and x0.shape == (2, 2)
    np.testing.assert_allclose(u[1, :, 0], 35.0 * rec.vir[100:200])
    np.testing.assert_allclose(x0[:, 0], rec.qm[[0, 100]])
    np.testing.assert_allclose(x0[:, 1], 0.2 / (n - 1) / 1e-3, rtol=1e-9)
    u, z, x0 = emps.closed_loop_data(rec, Ts=1e-3, T=100)
    assert u.shape == (2, 100, 2) and z.shape == (2, 100, 2) and x0.shape == (2, 4)
    assert x0[0, 1] == 0.0  # the record starts at rest
    np.testing.assert_allclose(x0[1, 2:], rec.qm[[99, 98]])


def test_emps_controller_reproduces_the_recorded_command():
    """The PD law of `closed_loop_model`, applied to the recorded positions, gives the
    recorded force command (the claim behind the closed-loop structure)."""
    try:
        data = ds.load_emps()
    except ds.DatasetNotFoundError as err:
        pytest.skip(f"benchmark files not available: {err}")
    rec = data.estimation
    law = np.clip(emps.pd_output(rec, data.kp, data.kv, data.Ts), -emps.NU_MAX, emps.NU_MAX)
    rms = float(np.sqrt(np.mean((law[2:] - rec.vir[2:]) ** 2)))
    assert rms < 0.01, rms
    assert emps.relative_error(rec.qm, rec.qm) == 0.0


def test_tanks_models():
    th = {"k1": 0.05, "k3": 0.03, "k4": 0.025, "c": -1.0}
    x, u = jnp.array([4.0, 9.0]), jnp.array([2.0])
    np.testing.assert_allclose(
        cascaded_tanks.basic_rhs(x, u, th), [0.025 * 2 - 0.05 * 2, 0.05 * 2 - 0.03 * 3]
    )
    over = {**th, "h1": 100.0, "h2": 100.0, "k5": 0.5}  # far below overflow: the basic model
    np.testing.assert_allclose(
        cascaded_tanks.OverflowRHS()(x, u, over), cascaded_tanks.basic_rhs(x, u, th), atol=1e-12
    )
    np.testing.assert_allclose(cascaded_tanks.observe(x, u, th), [8.0])
    # The quadratic sensor: + c2 (x2 - 5)^2, slope one at 5 V.
    sensor = {**th, "c2": 0.1}
    np.testing.assert_allclose(cascaded_tanks.observe(x, u, sensor), [8.0 + 0.1 * 16.0])
    slope = jax.grad(lambda v: cascaded_tanks.observe(jnp.array([4.0, v]), u, sensor)[0])
    np.testing.assert_allclose(slope(cascaded_tanks.SENSOR_LEVEL), 1.0)
    with pytest.raises(ValueError, match="kind"):
        cascaded_tanks.model("triple", 4.0)


def test_example_helpers_name_bad_arguments():
    """Raw NumPy errors (broadcast, IndexError, ZeroDivisionError, "need at least one array
    to stack") and, for `cascaded_tanks.constraints("Overflow")`, the basic model's box in
    silence."""
    q = np.linspace(0.0, 1.0, 50)
    with pytest.raises(ValueError, match="`half` must be an integer >= 1"):
        emps.velocity_estimate(q, 0.001, half=0)
    with pytest.raises(ValueError, match="`qm` must be a 1-d record longer than"):
        emps.velocity_estimate(q, 0.001, half=25)
    with pytest.raises(ValueError, match="`T` \\(the window length\\)"):
        emps.window_starts(100, 0)
    with pytest.raises(ValueError, match="`n` \\(samples per record\\)"):
        satellite.generate([0], 0)
    with pytest.raises(ValueError, match="`seeds` must hold at least one"):
        satellite.generate([], 5)
    # (a seed of 0.7 ran as seed 0; a bare int, a 2-entry theta and substeps=0 raised
    # TypeError, NumPy's broadcast error and ZeroDivisionError; a negative noise ran)
    bad = [
        (dict(seeds=[0.7]), "`seeds` must be integers >= 0, got 0.7"),
        (dict(seeds=0), "`seeds` must be a sequence"),
        (dict(seeds=[-1]), "`seeds` must be integers >= 0"),
        (dict(theta=(1.0, 2.0)), "`theta` must hold 3 entries"),
        (dict(substeps=0), "`substeps` must be an integer >= 1"),
        (dict(noise_std=-1.0), "`noise_std` must be a finite number >= 0"),
        (dict(dt=0.0), "`dt` must be positive"),
    ]
    for kw, match in bad:
        with pytest.raises(ValueError, match=match):
            satellite.generate(**{"seeds": [0], "n": 5, **kw})
    with pytest.raises(ValueError, match="`kind` must be one of"):
        cascaded_tanks.constraints("Overflow")
    # The builders converted counts and widths themselves: 2.7 substeps ran as 2, a chain
    # of 2.7 masses as 2, a relu width of 0 simulated NaN, a negative gate width reversed
    # the overflow gate, and a NaN mean torque gave NaN records.
    builders = [
        (lambda: satellite.generate([0], 5, torque_mean=np.nan), "`torque_mean` must be a finite"),
        (lambda: cascaded_tanks.model("basic", 4.0, substeps=2.7), "`substeps` must be an integer"),
        (lambda: cascaded_tanks.model("overflow", 4.0, relu_width=0.0), "`relu_width` must be a"),
        (lambda: cascaded_tanks.model("overflow", 4.0, gate_width=-0.05), "`gate_width` must"),
        (lambda: chain.model(2.7), "`n` must be an integer >= 1"),
        (lambda: emps.open_loop_model(0.001, substeps=True), "`substeps` must be an integer"),
        (lambda: emps.open_loop_model(0.001, eps=0.0), "`eps` must be a finite number > 0"),
        (lambda: emps.closed_loop_model(0.001, 1.0, 1.0, 1.0, substeps=1.5), "`substeps` must"),
        (lambda: cstr.model(substeps=2.5), "`substeps` must be an integer >= 1"),
    ]
    for build, match in builders:
        with pytest.raises(ValueError, match=match):
            build()
