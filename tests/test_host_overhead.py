"""What `fit` keeps between calls to cut its host-side work (issue 19: first call and
per-call overhead) changes no result and skips no check: the structural results of
`check_data` (kept per model, structure, shapes and dtypes), the compiled call's output
packed into one buffer per dtype, result modules built without `Module.__init__`, and
theta's written order."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax import FitHistory
from oneshot_jax.internal import (
    CHECK_DATA_STRUCTURES,
    build,
    check_data,
    kept_theta_order,
    pack,
    unpack,
)

T = 40


def step(x, u, theta):
    return jnp.array([x[1], -theta["k"] * x[0] - theta["c"] * x[1] + u[0]]) * 0.1 + x


def observe(x, u, theta):
    return x[:1]


MODEL = oj.Model(step, observe)
THETA0 = {"k": 1.5, "c": 0.3}
X0 = np.array([0.5, 0.0])
U = np.random.default_rng(0).standard_normal((T, 1))
_, Z = oj.simulate(MODEL, {"k": 2.0, "c": 0.5}, X0, U)
Z = np.asarray(Z) + 1e-3 * np.random.default_rng(1).standard_normal((T, 1))


def _fresh_data(*args, **kwargs):
    """check_data with its structural results computed anew."""
    kept = dict(CHECK_DATA_STRUCTURES)
    CHECK_DATA_STRUCTURES.clear()
    try:
        return check_data(*args, **kwargs)
    finally:
        CHECK_DATA_STRUCTURES.clear()
        CHECK_DATA_STRUCTURES.update(kept)


def test_kept_structure_gives_the_same_data():
    weight = np.array([2.0])
    fresh = _fresh_data(MODEL, THETA0, X0, U, Z, weight)
    check_data(MODEL, THETA0, X0, U, Z, weight)  # keeps the structure
    kept = check_data(MODEL, THETA0, X0, U, Z, weight)
    assert kept.model == fresh.model and kept.n_z == fresh.n_z and kept.batched == fresh.batched
    assert eqx.tree_equal(kept.theta, fresh.theta, typematch=True)
    for a, b in zip(kept[3:7], fresh[3:7]):
        assert a.dtype == b.dtype and np.array_equal(a, b)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(u=np.where(np.arange(T)[:, None] == 3, np.nan, U)), "`u` contains NaN"),
        (dict(z=np.where(np.arange(T)[:, None] == 3, np.inf, Z)), "`z` contains NaN"),
        (dict(x0=np.array([np.nan, 0.0])), "`x0` contains NaN"),
        (dict(theta={"k": np.nan, "c": 0.3}), "`theta` contains NaN"),
        (dict(weight=np.array([-1.0])), "non-negative"),
        (dict(z=np.zeros((T, 2))), r"`z` must have shape \(40, 1\)"),
        (dict(x0=np.zeros(3)), "calling the model"),
    ],
)
def test_every_check_still_runs_once_the_structure_is_kept(change, match):
    args = dict(theta=THETA0, x0=X0, u=U, z=Z, weight=np.array([1.0]))
    check_data(MODEL, **args)
    check_data(MODEL, **args)  # the structure of these arguments is kept
    with pytest.raises(ValueError, match=match):
        check_data(MODEL, **{**args, **change})


def test_kept_structure_follows_float64():
    data = check_data(MODEL, THETA0, X0, U, Z)
    assert data.x0.dtype == np.float64
    with jax.enable_x64(False):
        data32 = check_data(MODEL, THETA0, X0, U, Z)
    assert data32.x0.dtype == np.float32


def test_repeated_fits_are_identical():
    first = oj.fit(MODEL, THETA0, X0, U, Z)
    again = oj.fit(MODEL, THETA0, X0, U, Z)
    other_model = oj.fit(oj.Model(step, observe), THETA0, X0, U, Z)  # equal, not the same
    for r in (again, other_model):
        for name in ("theta", "x0", "loss", "covariance", "std", "residuals", "metrics"):
            assert eqx.tree_equal(getattr(r, name), getattr(first, name), typematch=True), name
        assert eqx.tree_equal(r.history, first.history, typematch=True)
        assert r.stop_info == first.stop_info and r.solver == first.solver
    assert again.solver is not first.solver  # settings are fresh dicts per result
    assert again.solver[0] is not first.solver[0]


def test_theta_order_follows_the_written_order():
    a = {"k": np.ones(2), "c": np.ones(3)}
    b = {"c": np.ones(3), "k": np.ones(2)}
    assert kept_theta_order(a) == ("k", "c")
    assert kept_theta_order(b) == ("c", "k")
    assert kept_theta_order({"outer": b, "x": 1.0}) == ("outer.c", "outer.k", "x")
    assert kept_theta_order({"outer": a, "x": 1.0}) == ("outer.k", "outer.c", "x")


def test_pack_unpack_round_trip():
    tree = {
        "a": jnp.arange(6.0).reshape(2, 3),
        "b": (jnp.array(True), jnp.array([1, 2], jnp.int32)),
        "c": None,
        "d": jnp.float64(2.5),
    }
    buffers, layout = pack(tree)
    assert len(buffers) == 3  # one per dtype
    out = unpack(buffers, layout)
    assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(tree)
    for x, y in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(tree)):
        assert isinstance(x, np.ndarray) and x.dtype == y.dtype and np.array_equal(x, y)


def test_build_is_the_constructor():
    fields = dict(
        loss=np.ones(3),
        grad_norm=np.zeros(3),
        theta={"k": np.ones(3)},
        step=np.arange(3),
        stage=np.zeros(3, np.int32),
    )
    assert eqx.tree_equal(build(FitHistory, **fields), FitHistory(**fields))
    with pytest.raises(TypeError, match="was not given"):
        build(FitHistory, loss=np.ones(3))
    with pytest.raises(TypeError, match="unknown fields"):
        build(FitHistory, **fields, extra=1)


def test_boxes_named_by_value_are_kept_apart():
    # A box made anew on every call is kept by its bounds' values: equal boxes share what
    # `fit` derives from them, different ones (an upper bound changed) never do.
    loose = [oj.fit(MODEL, THETA0, X0, U, Z, constraints=oj.constraints.box(upper={"k": 5.0}))]
    loose.append(oj.fit(MODEL, THETA0, X0, U, Z, constraints=oj.constraints.box(upper={"k": 5.0})))
    tight = oj.fit(MODEL, THETA0, X0, U, Z, constraints=oj.constraints.box(upper={"k": 1.8}))
    assert eqx.tree_equal(loose[0].theta, loose[1].theta)
    assert float(loose[0].theta["k"]) > 1.9  # the truth is 2.0
    assert float(tight.theta["k"]) == 1.8  # at its own bound, not the other box's
    array = oj.constraints.box(upper={"k": np.array(1.8)})  # not named by value
    assert float(oj.fit(MODEL, THETA0, X0, U, Z, constraints=array).theta["k"]) == 1.8


def test_fixed_and_estimated_masks_are_not_confused():
    free = oj.fit(MODEL, THETA0, X0, U, Z)
    held = oj.fit(MODEL, THETA0, X0, U, Z, fixed={"k": True, "c": False})
    none_x0 = oj.fit(MODEL, THETA0, X0, U, Z, estimate_x0=False)
    assert float(held.theta["k"]) == THETA0["k"] and float(free.theta["k"]) != THETA0["k"]
    assert np.array_equal(none_x0.x0, X0) and not np.array_equal(free.x0, X0)
    again = oj.fit(MODEL, THETA0, X0, U, Z)
    assert eqx.tree_equal(again.theta, free.theta) and again.fixed.flags.writeable
