"""`Adam(scale="theta0")`: steps relative to the starting magnitude of the named
parameters (a network's weights keep the absolute rate).

It is Adam on theta_i / |theta0_i| (up to eps): checked against plain Adam on a
reparameterised model, iterate for iterate; a network's weights keep the absolute rate.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.residual import MLP

DT, T = 0.05, 200


def _rhs(x, u, th):
    return jnp.array([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])


def _data():
    rng = np.random.default_rng(3)
    u = np.repeat(rng.normal(0.0, 1.0, T // 10), 10)[:, None]
    model = oj.Model.from_ode(_rhs, DT, observe=lambda x, u, th: x[:1])
    x0 = np.array([0.2, 0.0])
    _, z = oj.simulate(model, {"k": 15.0, "c": 0.05}, x0, u)
    return model, u, np.asarray(z), x0


def test_relative_steps_are_adam_on_rescaled_parameters():
    model, u, z, x0 = _data()
    theta0 = {"k": 12.0, "c": -0.2}  # a negative start: the factor is |theta0|
    factor = {k: abs(v) for k, v in theta0.items()}
    adam = dict(lr_theta=1e-2, lr_x0=1e-3, eps=1e-30, max_steps=40, gtol=0.0)
    res = oj.fit(model, theta0, x0, u, z, solver=oj.Adam(scale="theta0", **adam))

    def rhs_scaled(x, u, th):
        return _rhs(x, u, {k: th[k] * factor[k] for k in th})

    scaled = oj.Model.from_ode(rhs_scaled, DT, observe=lambda x, u, th: x[:1])
    start = {k: v / factor[k] for k, v in theta0.items()}
    ref = oj.fit(scaled, start, x0, u, z, solver=oj.Adam(**adam))
    for k in theta0:
        np.testing.assert_allclose(res.theta[k], ref.theta[k] * factor[k], rtol=1e-9)
    np.testing.assert_allclose(res.x0, ref.x0, rtol=1e-9)
    # (Plain Adam on theta moves k and c by the same absolute steps, not these.)


def test_network_weights_keep_the_absolute_rate():
    # A weight with a large start moves at the absolute rate; a named parameter of the
    # same start moves relative to it: after one step the named one moved |theta0| times
    # farther (Adam's first step is lr sign(g) per entry).
    def rhs(x, u, th):
        return jnp.array([x[1], -th["k"] * x[0] - th["net"](x[1:])[0] + u[0]])

    model = oj.Model.from_ode(rhs, DT, observe=lambda x, u, th: x[:1])
    _, u, z, x0 = _data()
    net = MLP(1, 1, widths=(), key=jax.random.PRNGKey(0), zero_last=False)
    theta0 = {"k": 12.0, "net": net}
    res = oj.fit(
        model,
        theta0,
        x0,
        u,
        z,
        solver=oj.Adam(scale="theta0", lr_theta=1e-3, max_steps=1, gtol=0.0),
    )
    dk = abs(res.theta["k"] - 12.0)
    dw = np.abs(np.asarray(res.theta["net"].layers[0].weight) - np.asarray(net.layers[0].weight))
    np.testing.assert_allclose(dk, 12.0 * 1e-3, rtol=1e-6)
    np.testing.assert_allclose(dw, 1e-3, rtol=1e-6)


def test_scale_checks():
    with pytest.raises(ValueError, match="scale"):
        oj.Adam(scale="relative")
    model, u, z, x0 = _data()
    from oneshot_jax import sparsity

    with pytest.raises(ValueError, match="regulariser"):
        oj.fit(
            model,
            {"k": 12.0, "c": 0.2},
            x0,
            u,
            z,
            solver=oj.Adam(scale="theta0"),
            regulariser=sparsity.l1(1e-3),
        )


def test_each_start_of_a_multistart_takes_its_own_magnitude():
    """With starts over k, every start steps relative to its own |k|: each start ends
    where a single fit from it ends (all of them took the first start's magnitude)."""
    model, u, z, x0 = _data()
    solver = oj.Adam(scale="theta0", lr_theta=1e-2, max_steps=30)
    ks = np.array([2.0, 12.0, 30.0])
    multi = oj.fit(model, {"k": 12.0, "c": 0.1}, x0, u, z, solver=solver, multistart={"k": ks})
    for i, k in enumerate(ks):
        single = oj.fit(model, {"k": k, "c": 0.1}, x0, u, z, solver=solver)
        np.testing.assert_allclose(multi.starts.theta["k"][i], single.theta["k"], rtol=1e-9)
        np.testing.assert_allclose(multi.starts.loss[i], single.loss, rtol=1e-9)


def test_a_gradient_far_below_eps_is_named_at_max_steps():
    """Outputs of scale 1e-6: the gradient (about 1e-13) is far below Adam's eps (1e-8),
    so each step is lr |g| / eps: 200 steps barely move theta, and the stop said only
    "raise max_steps (or the learning rates)". It now names eps; outputs of scale 1 do not
    get the note."""
    model, u, z, x0 = _data()
    theta0 = {"k": 12.0, "c": 0.1}

    def scaled(s):
        m = oj.Model.from_ode(_rhs, DT, observe=lambda x, u, th: s * x[:1])
        solver = oj.Adam(lr_theta=1e-2, lr_x0=1e-3, scale="theta0", max_steps=200)
        return oj.fit(m, theta0, x0, u, s * z, solver=solver)

    small, plain = scaled(1e-6), scaled(1.0)
    assert small.status == plain.status == "max_steps_reached"
    assert "far below Adam's eps 1e-08" in small.message and "Adam(eps=" in small.message
    assert small.stop_info["grad_norm"] < 1e-10
    assert "Adam's eps" not in plain.message and "below_eps" not in plain.stop_info
