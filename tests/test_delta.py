"""`FitResult.delta_method`: standard errors of quantities derived from theta. References
here: the derivatives by hand carried through `result.covariance`, and the spread of
`sample_theta`'s draws pushed through the function."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EULER_PENDULUM

import oneshot_jax as oj

X0 = np.array([0.6, -0.4])


def record():
    rng = np.random.default_rng(0)
    u = 0.8 * np.sin(0.4 * np.arange(60))[:, None]
    _, z = oj.simulate(EULER_PENDULUM, {"w0sq": 9.0, "b": 0.6}, X0, u)
    return u, np.asarray(z) + 0.02 * rng.standard_normal(np.shape(z))


@pytest.fixture(scope="module")
def fitted():
    return oj.fit(EULER_PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0, *record())


def test_a_function_of_the_parameters_carries_their_covariance(fitted):
    """sqrt(w0sq): std / (2 sqrt(w0sq)); (w0sq b, b): J Sigma J^T with J by hand, in the
    order of `result.names`."""
    r = fitted
    w, b = float(r.theta["w0sq"]), float(r.theta["b"])
    f0 = r.delta_method(lambda th: jnp.sqrt(th["w0sq"]))
    assert f0.value.shape == f0.std.shape == ()
    np.testing.assert_allclose(f0.value, np.sqrt(w), rtol=1e-15)
    np.testing.assert_allclose(f0.std, r.std["w0sq"] / (2 * np.sqrt(w)), rtol=1e-12)
    both = r.delta_method(lambda th: jnp.stack([th["w0sq"] * th["b"], th["b"]]))
    d = {"w0sq": np.array([b, 0.0]), "b": np.array([w, 1.0])}
    J = np.stack([d[name] for name in r.names], axis=1)
    np.testing.assert_allclose(both.covariance, J @ r.covariance @ J.T, rtol=1e-12)
    np.testing.assert_allclose(both.std, np.sqrt(np.diag(J @ r.covariance @ J.T)), rtol=1e-12)
    lo, hi = both.ci95
    np.testing.assert_allclose(hi - lo, 2 * 1.96 * both.std)


def test_the_first_order_spread_is_that_of_the_draws(fitted):
    """Over 20000 draws of `sample_theta`, the spread of w0sq / b (nonlinear in both)
    is the delta method's std within 3 %."""
    r = fitted
    q = r.delta_method(lambda th: th["w0sq"] / th["b"])
    draws = r.sample_theta(20000, seed=1)
    spread = np.std(np.asarray(draws["w0sq"]) / np.asarray(draws["b"]))
    assert abs(spread / q.std - 1) < 0.03


def test_the_poles_of_the_linear_model(fitted):
    """|pole| of Ac at rest is sqrt(w0sq) for an underdamped pendulum: the same standard
    error as sqrt(w0sq)'s (the pole written with `jnp.linalg.eigvals`)."""
    r = fitted

    def pole_magnitude(th):
        Ac = jnp.array([[0.0, 1.0], [-th["w0sq"], -th["b"]]])
        return jnp.abs(jnp.linalg.eigvals(Ac))

    poles = r.delta_method(pole_magnitude)
    f0 = r.delta_method(lambda th: jnp.sqrt(th["w0sq"]))
    np.testing.assert_allclose(poles.value, [f0.value] * 2, rtol=1e-12)
    np.testing.assert_allclose(poles.std, [f0.std] * 2, rtol=1e-9)


@pytest.mark.parametrize(
    "fn, error, match",
    [
        (lambda th: {"a": th["b"]}, TypeError, "must return real floating values"),
        (lambda th: (th["b"], jnp.stack([th["b"], th["b"]])), TypeError, "jnp.stack"),
        (lambda th: np.sqrt(th["w0sq"]), TypeError, "written in jax.numpy"),
        (lambda th: float(th["w0sq"]), TypeError, "written in jax.numpy"),
        (lambda th: th["nope"], ValueError, r"calling `fn\(theta\)` failed: KeyError"),
        (lambda th: jnp.log(-th["b"]), ValueError, "not finite at the estimate"),
        (3.0, TypeError, "`fn` must be a function of theta"),
        (lambda th: jnp.linalg.eigvals(jnp.eye(2) * th["b"]), TypeError, "jnp.real"),
        # (an integer is no complex number: the hint was the complex one)
        (lambda th: 3, TypeError, "dtype int.*: integers and booleans have no derivative"),
        (lambda th: th["b"] > 0, TypeError, "dtype bool: integers and booleans"),
    ],
)  # fmt: skip
def test_bad_functions_are_named(fitted, fn, error, match):
    with pytest.raises(error, match=match):
        fitted.delta_method(fn)


def test_a_function_takes_only_the_covariances_it_moves(fitted):
    """w0sq and b with their variances, their covariance unknown (as a hybrid's physical
    parameters with the network's weights): a function of w0sq alone takes its variance
    (the whole column held an inf, and its std was inf), one of both is inf."""
    S = np.array(fitted.covariance)
    S[0, 1] = S[1, 0] = np.inf
    r = dataclasses.replace(fitted, covariance=S)
    alone = r.delta_method(lambda th: jnp.stack([jnp.sqrt(th["w0sq"]), th["b"]]))
    np.testing.assert_allclose(
        alone.std,
        [fitted.std["w0sq"] / (2 * np.sqrt(fitted.theta["w0sq"])), fitted.std["b"]],
        rtol=1e-12,
    )
    assert np.isinf(alone.covariance[0, 1]) and np.isfinite(alone.covariance[1, 1])
    both = r.delta_method(lambda th: jnp.stack([th["w0sq"] * th["b"], th["b"]]))
    assert np.isinf(both.std[0]) and np.isfinite(both.std[1])


def test_fixed_and_unknown_parameters():
    """A fixed parameter adds no uncertainty (std 0 of a function of it alone); without a
    covariance every std that depends on a parameter is inf, one that depends on none 0."""
    u, z = record()
    r = oj.fit(EULER_PENDULUM, {"w0sq": 7.0, "b": 0.6}, X0, u, z, fixed={"b": True})
    assert r.delta_method(lambda th: 2 * th["b"]).std == 0.0
    np.testing.assert_allclose(
        r.delta_method(lambda th: 2 * th["w0sq"]).std, 2 * r.std["w0sq"], rtol=1e-12
    )
    r = oj.fit(EULER_PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0, u, z, covariance=None)
    mixed = r.delta_method(lambda th: jnp.stack([th["b"], jnp.float64(1.0)]))
    assert np.isinf(mixed.std[0]) and mixed.std[1] == 0.0
    assert np.isinf(mixed.covariance[0]).all() and mixed.covariance[1, 1] == 0.0
