import jax.numpy as jnp
import pytest

import oneshot_jax as oj


def test_ode_step_is_the_from_ode_discretisation():
    rhs = lambda x, u, th: jnp.stack([x[1], -th * x[0] + u[0]])  # noqa: E731
    x, u = jnp.array([0.3, -0.1]), jnp.array([0.2])
    for method, substeps in (("rk4", 1), ("rk4", 3), ("euler", 12)):
        model = oj.Model.from_ode(rhs, 0.1, method=method, substeps=substeps)
        direct = oj.ode_step(rhs, x, u, 2.0, 0.1, method=method, substeps=substeps)
        assert jnp.array_equal(model.step(x, u, 2.0), direct)


def test_ode_step_of_an_autonomous_rhs_takes_u_none_without_a_deprecation():
    # (jnp.ndim(None) is deprecated by JAX, to become an error: u=None was checked with it)
    import warnings

    rhs = lambda x, u, th: jnp.stack([x[1], -th * x[0]])  # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        x = oj.ode_step(rhs, jnp.array([0.3, -0.1]), None, 2.0, 0.1)
    assert jnp.array_equal(x, oj.ode_step(rhs, jnp.array([0.3, -0.1]), jnp.zeros(1), 2.0, 0.1))
    # and for input="foh" (refused before: "got shape ()")
    foh = oj.ode_step(rhs, jnp.array([0.3, -0.1]), None, 2.0, 0.1, input="foh")
    assert jnp.array_equal(foh, x)


def test_ode_step_refuses_a_zoh_input_of_several_rows():
    # (a slice u[k:k+3] ran: the rows broadcast against the state, a wrong model)
    rhs = lambda x, u, th: -x + u[0]  # noqa: E731
    with pytest.raises(ValueError, match=r"`u` must be u\[k\] of shape \(n_u,\) .*\(3, 2\)"):
        oj.ode_step(rhs, jnp.array([1.0, 2.0]), jnp.ones((3, 2)), None, 0.1)
