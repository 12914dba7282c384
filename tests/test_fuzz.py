"""Property tests of the public entry points on random input (hypothesis, fixed seeds).

The property: every call either returns a correct result (the right shapes, finite where
the input is finite, the loss equal to the value of `value_and_grad`) or raises a
`ValueError`/`TypeError` whose message names the offending argument in backticks. Nothing
else: no tracing error, no NaN reported as a result, no silent broadcast."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oneshot_jax as oj

NAMES = re.compile(
    r"`(x0|u|z|theta|theta0|weight|penalty|penalty_weight|model\.step|model\.observe|"
    r"model|missing|strategy|u\[\d+\]|z\[\d+\]|fixed|estimate_x0|window|solver|"
    r"constraints|history|path|like)`|calling the model"
)

FUZZ = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _total(theta):
    leaves = [jnp.sum(jnp.asarray(a)) for a in jax.tree_util.tree_leaves(theta)]
    return sum(leaves) if leaves else 0.0


def step(x, u, theta):
    return 0.8 * x + 0.05 * jnp.tanh(_total(theta)) * jnp.sum(u)


MODELS = {
    "full": oj.Model(step),
    "first": oj.Model(step, lambda x, u, th: x[:1] + 0.0 * jnp.sum(u)),
}

DTYPES = ["float64", "float32", "int32", "bool", "complex128", "str"]


@st.composite
def arrays(draw, shape, *, allow_bad_dtype=True, allow_nonfinite=True):
    """An array of roughly `shape`, sometimes with the wrong rank, size, dtype or values."""
    shape = list(shape)
    kind = draw(st.sampled_from(["ok"] * 12 + ["rank", "size", "scalar"]))
    if kind == "rank" and shape:
        shape = shape[:-1] if draw(st.booleans()) else [*shape, 1]
    elif kind == "size" and shape:
        i = draw(st.integers(0, len(shape) - 1))
        shape[i] = draw(st.integers(0, 4))
    elif kind == "scalar":
        shape = []
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    a = rng.standard_normal(shape)
    bad = draw(st.sampled_from([None] * 12 + [np.nan, np.inf, -np.inf]))
    if allow_nonfinite and a.size and bad is not None:
        a.flat[draw(st.integers(0, a.size - 1))] = bad
    dtype = draw(st.sampled_from(["float64"] * 10 + (DTYPES if allow_bad_dtype else DTYPES[:2])))
    if dtype == "str":
        return a.astype(str)
    with np.errstate(invalid="ignore"):
        return a.astype(dtype)


@st.composite
def thetas(draw):
    leaf = st.builds(
        lambda seed, n: np.random.default_rng(seed).standard_normal(n) * 0.1,
        st.integers(0, 100),
        st.sampled_from([(), (1,), (2,), (2, 2)]),
    )
    kind = draw(
        st.sampled_from(["dict"] * 4 + ["list", "tuple", "nested", "array", "empty", "bad"])
    )
    if kind == "dict":
        return {
            k: draw(leaf)
            for k in draw(st.lists(st.sampled_from("abc"), min_size=1, max_size=3, unique=True))
        }
    if kind == "list":
        return [draw(leaf) for _ in range(draw(st.integers(1, 3)))]
    if kind == "tuple":
        return tuple(draw(leaf) for _ in range(draw(st.integers(1, 3))))
    if kind == "nested":
        return {"a": [draw(leaf), {"b": draw(leaf)}], "c": (draw(leaf),)}
    if kind == "array":
        return draw(leaf)
    if kind == "empty":
        return draw(st.sampled_from([{}, [], None]))
    return {"a": draw(st.sampled_from(["x", 1j, np.array(["s"])]))}


@st.composite
def problems(draw):
    n_x = draw(st.integers(1, 3))
    n_u = draw(st.integers(1, 2))
    T = draw(st.integers(1, 6))
    N = draw(st.sampled_from([None, 1, 2]))
    lead = () if N is None else (N,)
    model_name = draw(st.sampled_from(list(MODELS)))
    n_z = n_x if model_name == "full" else 1
    return dict(
        model=MODELS[model_name],
        theta=draw(thetas()),
        x0=draw(arrays((*lead, n_x))),
        u=draw(arrays((*lead, T, n_u))),
        z=draw(arrays((*lead, T, n_z))),
        weight=draw(
            st.one_of(st.none(), arrays((n_z,), allow_nonfinite=False), arrays((n_z, n_z)))
        ),
    )


def _finite(*arrays):
    return all(
        np.all(np.isfinite(np.asarray(a, dtype=float)))
        for a in jax.tree_util.tree_leaves(arrays)
        if np.asarray(a).dtype.kind in "fiub"
    )


def _check_error(err):
    assert isinstance(err, (ValueError, TypeError)), repr(err)
    assert NAMES.search(str(err)), f"the message names no argument: {err}"


@FUZZ
@given(problems())
def test_simulate_loss_and_gradient_either_work_or_name_the_argument(p):
    model, theta, x0, u, z, w = p["model"], p["theta"], p["x0"], p["u"], p["z"], p["weight"]
    try:
        x, zhat = oj.simulate(model, theta, x0, u)
    except Exception as err:  # noqa: BLE001 - the property is about the exception's kind
        _check_error(err)
    else:
        assert x.shape == (*np.shape(u)[:-1], np.shape(x0)[-1])
        assert zhat.shape[:-1] == np.shape(u)[:-1]
    try:
        C = oj.loss(model, theta, x0, u, z, weight=w)
        C2, (g, gx) = oj.value_and_grad(model, theta, x0, u, z, weight=w)
    except Exception as err:  # noqa: BLE001
        _check_error(err)
    else:
        assert C.shape == () and gx.shape == np.shape(x0)
        assert float(C) == pytest.approx(float(C2), rel=1e-5, abs=1e-12)
        assert _finite(C, g, gx)  # every input was finite, or it would have been refused
        assert float(C) >= 0


@st.composite
def fit_calls(draw):
    p = draw(problems())
    kwargs = {}
    extra = draw(st.sampled_from(["none", "fixed", "estimate_x0", "window", "solver", "history"]))
    if extra == "fixed":
        kwargs["fixed"] = draw(st.sampled_from([True, False, {"a": True}, [True], "yes"]))
    elif extra == "estimate_x0":
        kwargs["estimate_x0"] = draw(
            st.sampled_from([False, np.array([True]), np.array([True, False, True]), 1])
        )
    elif extra == "window":
        kwargs["window"] = draw(st.sampled_from([0, 1, 2, 100, 2.5]))
    elif extra == "solver":
        kwargs["solver"] = draw(st.sampled_from(["gauss_newton", "newton", 3, []]))
    elif extra == "history":
        kwargs["history"] = draw(st.sampled_from([0, 3, 4, -2]))
    return p, kwargs


@settings(FUZZ, max_examples=20)
@given(fit_calls())
def test_fit_either_works_or_names_the_argument(call):
    p, kwargs = call
    kwargs.setdefault("solver", oj.GaussNewton(max_steps=3))
    try:
        r = oj.fit(p["model"], p["theta"], p["x0"], p["u"], p["z"], weight=p["weight"], **kwargs)
    except Exception as err:  # noqa: BLE001
        _check_error(err)
    else:
        assert np.isfinite(float(r.loss))
        if r.success:
            for leaf in jax.tree_util.tree_leaves((r.std, r.x0_std)):
                assert not np.any(np.isnan(leaf))


@st.composite
def plain_thetas(draw):
    leaf = st.builds(
        lambda seed, n: 0.3 + 0.1 * np.random.default_rng(seed).standard_normal(n),
        st.integers(0, 100),
        st.sampled_from([(), (2,)]),
    )
    keys = draw(st.lists(st.sampled_from("abc"), min_size=1, max_size=2, unique=True))
    theta = {k: draw(leaf) for k in keys}
    if draw(st.booleans()):
        theta = {"outer": [theta, (draw(leaf),)]}
    return theta


@settings(FUZZ, max_examples=4)
@given(plain_thetas(), st.booleans())
def test_save_and_load_round_trip(tmp_path_factory, theta, multistart):
    import equinox as eqx

    rng = np.random.default_rng(0)
    u = rng.standard_normal((8, 1))
    z = rng.standard_normal((8, 2))
    if multistart:
        theta = jax.tree_util.tree_map(lambda a: np.stack([a, 1.1 * a]), theta)
    r = oj.fit(
        MODELS["full"],
        theta,
        np.zeros(2),
        u,
        z,
        multistart=multistart,
        solver=oj.GaussNewton(max_steps=2),
    )
    path = r.save(tmp_path_factory.mktemp("fuzz") / "r")
    loaded = oj.load_result(path, model=MODELS["full"])
    assert eqx.tree_equal(loaded, r) is True
