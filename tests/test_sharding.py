"""Fleets sharded over devices (`oneshot_jax.sharding`) give the unsharded results.

The check runs in a subprocess with `XLA_FLAGS=--xla_force_host_platform_device_count=4`:
the flag only takes effect before JAX initialises its CPU backend, which this test
process has already done. There, with 8 trajectories split over 4 CPU devices:

- `oneshot_jax.value_and_grad` (batched, strategy "jacobian" and "vjp") on sharded
  inputs equals the call on unsharded ones, and its compiled form reduces over devices
  (an all-reduce in the HLO), with grad_x0 left sharded;
- the Gauss-Newton normal equations (`_linalg.normal_blocks`, einsums over the
  trajectory axis) of the closed-form residual Jacobians equal the unsharded ones;
- the parallel-in-time gradient over the sharded fleet equals the sequential one;
- `fit` on the sharded fleet equals `fit` on the unsharded one, also with missing samples
  (whose masked z stays sharded);
- N = 6 on 4 devices is refused with a ValueError.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from oneshot_jax import sharding

SCRIPT = textwrap.dedent(
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)

    import oneshot_jax as oj
    from oneshot_jax.internal import Cost, normal_blocks, trajectory_jacobian, value_and_grad_impl
    from oneshot_jax.sharding import AXIS, fleet_mesh, replicate, shard_fleet

    assert len(jax.devices()) == 4, jax.devices()

    def rhs(w, M, theta):
        inertia = theta["I"]
        return (M - jnp.cross(w, inertia * w)) / inertia

    model = oj.Model.from_ode(rhs, 0.1)
    rng = np.random.default_rng(0)
    N, T = 8, 60
    theta = {"I": jnp.array([0.05, 0.03, 0.01])}
    x0 = jnp.asarray(rng.normal(0.0, 1e-3, (N, 3)))
    u = jnp.asarray(rng.normal(1e-5, 1e-7, (N, T, 3)))
    z = jnp.asarray(rng.normal(0.0, 1e-3, (N, T, 3)))

    mesh = fleet_mesh()
    xs, us, zs = shard_fleet(x0, u, z, mesh=mesh)
    th = replicate(theta, mesh)
    assert len(xs.sharding.device_set) == 4 and xs.sharding.spec[0] == AXIS
    assert len(us.addressable_shards) == 4 and us.addressable_shards[0].data.shape[0] == 2

    def rel(a, b):
        a, b = np.asarray(a), np.asarray(b)
        return float(np.linalg.norm(a - b) / np.linalg.norm(b))

    def check(got, want, what):
        for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            assert g.shape == w.shape, (what, g.shape, w.shape)
            assert rel(g, w) <= 1e-13, (what, rel(g, w))

    # 1. The library's batched value_and_grad.
    for strategy in ("jacobian", "vjp"):
        want = oj.value_and_grad(model, theta, x0, u, z, strategy=strategy)
        got = oj.value_and_grad(model, th, xs, us, zs, strategy=strategy)
        check(got, want, "value_and_grad " + strategy)
        assert got[1][1].sharding.spec[0] == AXIS  # grad_x0 stays sharded
    cost = Cost(None, None, jnp.asarray(0.0))
    fn = jax.jit(lambda th, x0, u, z: value_and_grad_impl(
        model, cost, th, x0, u, z, True, "jacobian"))
    hlo = fn.lower(th, xs, us, zs).compile().as_text()
    assert "all-reduce" in hlo

    # 2. Gauss-Newton normal equations from the closed-form Jacobians.
    def normal_equations(theta, x0, u, z):
        flat = theta["I"]
        def one(x0, u, z):
            return trajectory_jacobian(
                model, cost, lambda p: {"I": p}, flat, lambda p: p, x0, u, z,
                scale=1.0 / np.sqrt(N * T), strategy="jacobian")
        lin = jax.vmap(one)(x0, u, z)
        return normal_blocks(lin.Jt, lin.Jx, lin.r.reshape(N, -1))

    normal_equations = jax.jit(normal_equations)
    want = normal_equations(theta, x0, u, z)
    got = normal_equations(th, xs, us, zs)
    check(got, want, "normal equations")
    hlo = normal_equations.lower(th, xs, us, zs).compile().as_text()
    assert "all-reduce" in hlo

    # 3. The parallel-in-time gradient over the sharded fleet.
    want = oj.value_and_grad(model, theta, x0, u, z, strategy="jacobian")
    check(oj.value_and_grad(model, th, xs, us, zs, strategy="parallel"), want, "parallel fleet")

    # 4. fit on the sharded fleet (the data stay sharded in its compiled call).
    _, zt = oj.simulate(model, theta, x0, u)
    zt = zt + 1e-4 * jnp.asarray(rng.standard_normal(zt.shape))
    xs, us, zts = shard_fleet(x0, u, zt, mesh=mesh)
    theta0 = {"I": theta["I"] * 1.05}
    want = oj.fit(model, theta0, x0, u, zt, solver=oj.GaussNewton())
    got = oj.fit(model, theta0, xs, us, zts, solver=oj.GaussNewton())
    assert got.num_steps == want.num_steps, (got.num_steps, want.num_steps)
    assert rel(got.theta["I"], want.theta["I"]) <= 1e-10, rel(got.theta["I"], want.theta["I"])
    assert rel(got.x0, want.x0) <= 1e-10

    # 5. A fleet with missing samples stays sharded (z was copied to the host for its
    #    mask) and fits as the unsharded one.
    from oneshot_jax.internal import check_data

    zn = np.asarray(zt).copy()
    zn[1, 5:9, 0] = np.nan
    _, _, zns = shard_fleet(x0, u, zn, mesh=mesh)
    assert len(check_data(model, theta, xs, us, zns, None, "mask").z.sharding.device_set) == 4
    want = oj.fit(model, theta0, x0, u, zn, missing="mask", solver=oj.GaussNewton())
    got = oj.fit(model, theta0, xs, us, zns, missing="mask", solver=oj.GaussNewton())
    assert rel(got.theta["I"], want.theta["I"]) <= 1e-10, rel(got.theta["I"], want.theta["I"])

    # 6. Uneven fleets are refused.
    try:
        shard_fleet(x0[:6], u[:6], z[:6], mesh=mesh)
    except ValueError as err:
        assert "multiple of the number of devices" in str(err)
    else:
        raise AssertionError("N = 6 on 4 devices was accepted")
    print("SHARDING OK")
    """
)


def test_sharded_fleet_equals_unsharded():
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "SHARDING OK" in out.stdout


@pytest.mark.parametrize(
    "call, error, match",
    [
        # An AttributeError, a pybind TypeError, and a sharding of a 0-d array accepted.
        (
            lambda: sharding.shard_fleet(np.zeros((1, 2)), np.zeros((1, 5, 1)), mesh="cpu"),
            TypeError,
            "`mesh` must be a 1-D jax.sharding.Mesh",
        ),
        (lambda: sharding.replicate({"k": 1.0}, None), TypeError, "`mesh` must be a"),
        (lambda: sharding.fleet_sharding(None, 2), TypeError, "`mesh` must be a 1-D"),
        (lambda: sharding.fleet_sharding(sharding.fleet_mesh(), 0), ValueError, "`ndim`"),
        (lambda: sharding.fleet_sharding(sharding.fleet_mesh(), 1.0), TypeError, "`ndim`"),
        # NumPy's "inhomogeneous shape", and "the same N as `x0`" said of x0 itself.
        (
            lambda: sharding.shard_fleet(np.zeros((2, 1)), [np.zeros((5, 1)), np.zeros((3, 1))]),
            ValueError,
            "`u` must be one array .* different lengths .* cannot be sharded",
        ),
        (
            lambda: sharding.shard_fleet(np.zeros(2), np.zeros((2, 5, 1))),
            ValueError,
            r"`x0` must have shape \(N, n_x\), got shape \(2,\)\.",
        ),
    ],
)
def test_bad_mesh_and_ndim_are_named(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_a_fleet_given_as_lists_or_on_one_device():
    """A list of x0 rows passed the shape check and failed inside `device_put`; one
    `Device` for `fleet_mesh` was "'Device' object is not iterable"."""
    import jax

    mesh = sharding.fleet_mesh(jax.devices()[0])
    assert mesh.devices.size == 1
    x0, u = sharding.shard_fleet(list(np.zeros((2, 2))), np.zeros((2, 5, 1)), mesh=mesh)
    assert x0.shape == (2, 2) and u.shape == (2, 5, 1)


@pytest.mark.parametrize(
    "devices, error, match",
    [
        # A mesh of characters, then "'str' object has no attribute 'id'".
        ("cpu", TypeError, "`devices` must be a sequence of jax.Device objects .* the string"),
        # "'numpy.int64' object has no attribute 'platform'" in `shard_fleet`.
        ([1, 2], TypeError, "`devices` must be a sequence of jax.Device objects .* int 1"),
        # "'int' object is not iterable".
        (0, TypeError, "`devices` must be a sequence of jax.Device objects"),
        # A mesh of one device twice, then a `safe_zip` error in `shard_fleet`.
        (
            lambda: [jax.devices()[0]] * 2,
            ValueError,
            "`devices` must be distinct devices: .* appears more than once",
        ),
        ([], ValueError, "`devices` must hold at least one device"),
    ],
)
def test_fleet_mesh_refuses_what_is_not_distinct_devices(devices, error, match):
    devices = devices() if callable(devices) else devices
    with pytest.raises(error, match=match):
        sharding.fleet_mesh(devices)
    assert sharding.fleet_mesh(tuple(jax.devices())).devices.size == len(jax.devices())


def test_replicate_names_a_leaf_that_is_not_an_array():
    # (JAX's "Argument 'x' of type <class 'str'> is not a valid JAX type", naming neither.)
    mesh = sharding.fleet_mesh()
    with pytest.raises(TypeError, match=r"`tree` must hold arrays .* leaf \['a'\] is str 'x'"):
        sharding.replicate({"a": "x"}, mesh)
    with pytest.raises(TypeError, match=r"leaf \['b'\]\[0\] is an array of shape \(1,\)"):
        sharding.replicate({"b": [np.array(["s"])]}, mesh)


def test_replicate_carries_the_functions_of_a_residual():
    # (An MLP in theta failed: its activation function is a leaf that JAX cannot place.)
    from oneshot_jax.residual import MLP

    theta = {"k": 1.0, "r": MLP(2, 1, (3,), key=jax.random.PRNGKey(0))}
    out = sharding.replicate(theta, sharding.fleet_mesh())
    assert out["r"].activation is theta["r"].activation
    assert out["r"].layers[0].weight.sharding.is_fully_replicated
    np.testing.assert_array_equal(out["r"].layers[0].weight, theta["r"].layers[0].weight)


@pytest.mark.parametrize(
    "shapes, match",
    [
        # N = 0 was sharded (fit refused it later).
        (((0, 2), (0, 5, 1), (0, 5, 1)), r"`x0` must hold at least one trajectory .*\(0, 2\)"),
        # u and z of different T were sharded (fit refused them later).
        (((2, 2), (2, 5, 1), (2, 4, 1)), r"`z` must have the same number of time steps T as `u`"),
    ],
)
def test_shard_fleet_refuses_no_trajectories_and_a_z_of_another_length(shapes, match):
    with pytest.raises(ValueError, match=match):
        sharding.shard_fleet(*(np.zeros(s) for s in shapes))
