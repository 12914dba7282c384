"""The CSTR case study (`oneshot_jax.examples.cstr`): the model, its data generator and a
fit on time-stamped data with the concentration measured only as shift averages."""

import jax
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.examples import cstr


@pytest.fixture(scope="module")
def short():
    """One day: three shifts, about 260 samples, one outage."""
    return cstr.design(3, days=1.0, outages=1)


def test_steady_state_is_a_rest_point_and_physical():
    """At the steady state of a coolant temperature the model stays put; the reactor is
    hotter than its coolant (the reaction heats it), and more A reacts when it is hotter."""
    cold, hot = cstr.steady_state(315.0), cstr.steady_state(335.0)
    assert 0.0 < hot[0] < cold[0] < cstr.C_AF
    assert cold[1] > 315.0 and hot[1] > 335.0 and hot[1] > cold[1]
    np.testing.assert_allclose(
        cstr.rhs(cold, np.array([315.0]), cstr.THETA_TRUE), [0.0, 0.0], atol=1e-9
    )
    u = np.full((50, 1), 335.0)
    x, z = oj.simulate(cstr.model(5.0), cstr.THETA_TRUE, hot, u)
    assert x.shape == (50, 2) and z.shape == (50, 2)
    np.testing.assert_allclose(np.asarray(x), np.broadcast_to(hot, (50, 2)), rtol=1e-9)


def test_design_times_shifts_and_gaps(short):
    d = short
    dt = np.diff(d.t)
    assert d.t[0] == 0.0 and np.all(dt > 0.9) and np.all(dt < 10.5)
    assert len(d.intervals) == 3
    for j, (a, b) in enumerate(d.intervals):  # every boundary is a sample time
        assert d.t[a] == j * cstr.SHIFT and d.t[b - 1] == (j + 1) * cstr.SHIFT
        c = d.x[a:b, 0]  # the time mean lies within the samples' range, near their mean
        assert c.min() < d.averages[j] < c.max()
        np.testing.assert_allclose(d.averages[j], np.trapezoid(c, d.t[a:b]) / 480, rtol=1e-3)
    assert b == d.t.size
    assert 0.8 < d.observed.mean() < 0.99
    again = cstr.design(3, days=1.0, outages=1)
    np.testing.assert_array_equal(again.x, d.x)
    z, avg = cstr.measure(d, 0)
    assert np.all(np.isnan(z[:, 0])) and np.array_equal(np.isnan(z[:, 1]), ~d.observed)
    e = z[d.observed, 1] - d.x[d.observed, 1]
    assert 0.4 < e.std() < 0.6 and avg.shape == d.averages.shape


def test_point_samples_at_the_shift_middles(short):
    z, avg = cstr.measure(short, 0)
    zp = cstr.point_samples(short, z, avg)
    mid = cstr.midpoints(short)
    np.testing.assert_array_equal(np.flatnonzero(~np.isnan(zp[:, 0])), mid)
    np.testing.assert_array_equal(zp[mid, 0], avg)
    for (a, b), m in zip(short.intervals, mid):
        assert abs(short.t[m] - (short.t[a] + short.t[b - 1]) / 2) < 10.0


def test_timed_model_matches_the_generator(short):
    """The model (RK4, substeps of at most 2 min, each interval its own) against the
    generator (RK4, 40 substeps per interval): the same equations, a finer integrator."""
    x, _ = oj.simulate(cstr.model(), cstr.THETA_TRUE, short.x0, short.u, t=short.t)
    np.testing.assert_allclose(np.asarray(x), short.x, rtol=1e-6)
    assert np.abs(np.asarray(x) - short.x).max() > 1e-12  # two integrators, not one


def test_fit_recovers_the_parameters_from_averages_and_gappy_samples(short):
    """Noise-free temperature samples with gaps and the exact shift averages of C_A (no
    point sample of it): LM from a perturbed start recovers ln k0, UA and x0 (up to the
    model's RK4 error: substeps of up to 5 min, coarser than the default to compile
    faster)."""
    z = np.where(short.observed, short.x[:, 1], np.nan)
    z = np.stack([np.full(short.t.size, np.nan), z], 1)
    theta0 = {"ln_k0": cstr.THETA_TRUE["ln_k0"] + 0.2, "UA": 3.4}
    result = oj.fit(
        cstr.model(max_step=5.0, substeps=3),
        theta0,
        short.x0 + np.array([0.05, 2.0]),
        short.u,
        z,
        t=short.t,
        aggregate=cstr.aggregate(short, short.averages),
        weight=cstr.weight(),
        missing="mask",
    )
    assert result.success
    np.testing.assert_allclose(result.theta["ln_k0"], cstr.THETA_TRUE["ln_k0"], atol=1e-4)
    np.testing.assert_allclose(result.theta["UA"], cstr.THETA_TRUE["UA"], rtol=1e-4)
    np.testing.assert_allclose(result.x0, short.x0, rtol=1e-4)


def test_the_data_need_float64_and_say_so():
    """Under float32 `design` returned float32 states behind JAX's "dtype float64 ...
    truncated" warnings; its docstring says it needs float64."""
    with jax.enable_x64(False), pytest.raises(RuntimeError, match="need float64"):
        cstr.design(0, days=1.0)
