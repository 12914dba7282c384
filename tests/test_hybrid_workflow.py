"""A hybrid model from a far start to identified physics, and the stopping test that lets a
fit of an over-parameterised model succeed (`RESULTS.statistically_converged`).

The workflow: a pendulum whose damping is an MLP of the rate. Its physics alone (the
network held) from a far start stops in a bad minimum of the simulation error; multistart
over the physical parameters only (the network shared) finds the basin; the joint fit
reaches the noise level and succeeds by the statistical test (the first-order test is
not reached on a network's rank-deficient Jacobian), with the physical parameters within
1 % of the truth and 95 % intervals from the marginal covariance that contain it.

The stopping test: it never fires on a regular Jacobian (the first-order test decides
there, as before), never far from the optimum although the step alone is small (a huge
damping), and holds with bounds.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import observe_angle, pendulum_nonlinear_damping

import oneshot_jax as oj
from oneshot_jax.residual import MLP

DT = 0.05
W0SQ, GAIN = 9.0, 1.0


def _hybrid(x, u, th):
    q, v = x
    damping = th["r"](x[1:])[0]  # the rate only: the restoring force stays physics
    return jnp.stack([v, -th["w0sq"] * jnp.sin(q) + damping + th["g"] * u[0]])


def _record(T, seed=0, noise=0.01):
    """A multisine record away from the resonance (3 rad/s) of the true pendulum, its
    angle measured with `noise` rad."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.0, 2.0, 4.5, 6.0))[:, None]
    model = oj.Model.from_ode(pendulum_nonlinear_damping, DT, observe=observe_angle)
    x, z = oj.simulate(model, {"w0sq": W0SQ, "g": GAIN}, np.zeros(2), u)
    z = np.asarray(z) + noise * rng.standard_normal(np.shape(z))
    return u, z, float(np.std(np.asarray(x)[:, 1]))


def test_hybrid_pendulum_from_a_far_start_to_identified_physics():
    # Seed 0 of the data and PRNGKey(0) of the network (a fixed case; the asserts are
    # on what the fits reach, not on pinned values).
    u, z, rate_std = _record(400)
    model = oj.Model.from_ode(_hybrid, DT, observe=observe_angle)
    net = MLP(1, 1, (8,), key=jax.random.PRNGKey(0), input_scale=rate_std)
    held = {"w0sq": False, "g": False, "r": True}  # stage 1: the physics, network held
    start = {"w0sq": 4.0, "g": 0.5, "r": net}
    x0 = np.zeros(2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        plain = oj.fit(model, start, x0, u, z, fixed=held)
    # A bad minimum: the plain fit explains a quarter of the angle at most.
    assert plain.metrics["fit_percent"][0] < 30.0
    assert abs(float(plain.theta["w0sq"]) - W0SQ) > 0.3 * W0SQ

    # Multistart over the physical frequency alone; the network shared (and held).
    starts = {"w0sq": np.array([2.0, 4.0, 8.0, 16.0])}
    physics = oj.fit(model, start, x0, u, z, fixed=held, multistart=starts)
    assert physics.success
    assert physics.metrics["fit_percent"][0] > 60.0  # the basin (the damping is missing)
    assert abs(float(physics.theta["w0sq"]) - W0SQ) < 0.02 * W0SQ

    # The joint fit: physics and network.
    joint = oj.fit(model, physics.theta, physics.x0, u, z)
    assert joint.status == "statistically_converged" and joint.success, joint.message
    assert joint.stop_info["standard_errors"] <= joint.stop_info["stol"]
    # At the noise level (0.01 rad; with 29 free variables of 400 samples the residual
    # may fall a little below it).
    assert 0.0095 < float(joint.metrics["rmse"][0]) < 0.0105
    for name, truth in (("w0sq", W0SQ), ("g", GAIN)):
        value, std = float(joint.theta[name]), float(joint.std[name])
        assert abs(value - truth) < 0.01 * truth, (name, value)
        assert np.isfinite(std) and std > 0, (name, std)
        assert value - 1.96 * std < truth < value + 1.96 * std, (name, value, std)


# A pendulum with its stiffness split in two (a + b): the Jacobian always has a null space,
# the rank-deficient case the statistical test is for, with a physical model small
# enough to be fast.


def _split(x, u, p):
    q, v = x
    return jnp.stack([v, -(p["a"] + p["b"]) * jnp.sin(q) - p["c"] * v + u[0]])


def _regular(x, u, p):
    q, v = x
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - p["c"] * v + u[0]])


def _pendulum_data(T=200, seed=1):
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.0, 2.5, 5.0))[:, None]
    model = oj.Model.from_ode(_regular, DT, observe=observe_angle)
    _, z = oj.simulate(model, {"w0sq": W0SQ, "c": 0.5}, np.zeros(2), u)
    return u, np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))


def test_a_small_step_far_from_the_optimum_is_not_convergence():
    # A huge damping makes every step tiny, in standard errors too: the step test alone
    # (a careless implementation) would declare convergence at the first step, far from
    # the optimum. The first-order guard (no parameter alone moves by a standard error)
    # holds it back.
    u, z = _pendulum_data()
    model = oj.Model.from_ode(_split, DT, observe=observe_angle)
    solver = oj.LevenbergMarquardt(mu0=1e8, max_steps=3)
    r = oj.fit(model, {"a": 3.0, "b": 3.5, "c": 0.3}, np.zeros(2), u, z, solver=solver)
    assert r.stop_info["standard_errors"] <= r.stop_info["stol"]  # the step is tiny
    assert r.status == "max_steps_reached" and not r.success, r.message
    assert r.stop_info["first_order"] * np.sqrt(u.shape[0]) > 1.0
    # The message names both tests that could have stopped it (it named the first-order
    # test alone): the statistical test's step passed, another of its conditions did not.
    se = r.stop_info["standard_errors"]
    assert f"nor the statistical test of a theta with a null space (the last step {se:.3g} " in (
        r.message
    )
    assert "<= stol 0.01, but not a step whose decrease the loss confirmed" in r.message
    # Undamped, the step is too long in standard errors: that is the condition named.
    r = oj.fit(
        model,
        {"a": 3.0, "b": 3.5, "c": 0.3},
        np.zeros(2),
        u,
        z,
        solver=oj.LevenbergMarquardt(max_steps=2),
    )
    assert r.status == "max_steps_reached" and r.stop_info["standard_errors"] > 0.01
    se = r.stop_info["standard_errors"]
    assert f"(the last step {se:.3g} standard errors > stol 0.01);" in r.message


def test_regular_jacobians_stop_as_before():
    # On a regular model the statistical test is not applied: the fit takes the same
    # steps and stops by the first-order test whether it is on or off. (The last steps
    # of a converging fit are tiny in standard errors: without the rank condition the
    # statistical test could end it a step early, as a different stop: the step counts
    # tell. The two compiled programs differ, and their estimates may differ in the last
    # digit.)
    u, z = _pendulum_data()
    model = oj.Model.from_ode(_regular, DT, observe=observe_angle)
    theta0 = {"w0sq": 8.0, "c": 0.3}
    on = oj.fit(model, theta0, np.zeros(2), u, z, solver=oj.LevenbergMarquardt())
    off = oj.fit(model, theta0, np.zeros(2), u, z, solver=oj.LevenbergMarquardt(stol=0.0))
    assert on.status == off.status == "converged"
    assert on.num_steps == off.num_steps
    # Where it takes its max_steps, its message names the first-order test alone.
    short = oj.fit(model, theta0, np.zeros(2), u, z, solver=oj.LevenbergMarquardt(max_steps=2))
    assert short.status == "max_steps_reached" and "statistical" not in short.message
    assert float(on.theta["w0sq"]) == pytest.approx(float(off.theta["w0sq"]), rel=1e-14)
    assert float(on.theta["c"]) == pytest.approx(float(off.theta["c"]), rel=1e-14)


def test_statistical_convergence_with_active_bounds():
    # Both halves of the stiffness held at their upper bounds (a + b = 6 < 9): the
    # constrained optimum has c at the regular model's optimum with w0sq fixed at 6.
    u, z = _pendulum_data()
    model = oj.Model.from_ode(_split, DT, observe=observe_angle)
    box = oj.constraints.box(upper={"a": 3.0, "b": 3.0, "c": np.inf})
    r = oj.fit(model, {"a": 2.0, "b": 2.5, "c": 0.3}, np.zeros(2), u, z, constraints=box)
    assert r.success, r.message
    assert float(r.theta["a"]) == 3.0 and float(r.theta["b"]) == 3.0
    regular = oj.Model.from_ode(_regular, DT, observe=observe_angle)
    ref = oj.fit(
        regular, {"w0sq": 6.0, "c": 0.3}, np.zeros(2), u, z, fixed={"w0sq": True, "c": False}
    )
    # (statistically converged: within `stol`, 0.01 of c's standard error, of the optimum)
    assert r.status == "statistically_converged", r.message
    assert abs(float(r.theta["c"]) - float(ref.theta["c"])) <= 0.01 * float(r.std["c"])


@pytest.mark.parametrize("stol", [-1.0, float("nan"), True])
def test_stol_is_checked(stol):
    with pytest.raises(ValueError, match="stol"):
        oj.LevenbergMarquardt(stol=stol)
    with pytest.raises(ValueError, match="stol"):
        oj.GaussNewton(stol=stol)
