"""Learned residuals (`oneshot_jax.residual`): the MLP and the sparse Dictionary, alone and
inside a hybrid Duffing model whose one-shot gradient is checked against `jax.grad` of an
independent rollout (a `lax.scan` of our own RK4 written here)."""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_tree_rel_close

import oneshot_jax as oj
from oneshot_jax.residual import MLP, Dictionary, Features, count_parameters

#
# The hybrid Duffing oscillator: q'' + c q' + k q + eps q^3 = u, with the cubic term left
# out of the physics and a residual r(x, u) in its place.
#

DT, T = 0.05, 120
TRUE = {"c": 0.3, "k": 1.0, "eps": 0.8}


def duffing_true_rhs(x, u, p):
    q, v = x
    return jnp.stack([v, u[0] - p["c"] * v - p["k"] * q - p["eps"] * q**3])


def hybrid_rhs(x, u, theta):
    """The physics without the cubic term, plus the residual (an MLP or a Dictionary)."""
    q, v = x
    res = theta["r"]
    r = res(jnp.concatenate([x, u])) if isinstance(res, MLP) else res(x, u)
    return jnp.stack([v, u[0] - theta["c"] * v - theta["k"] * q + r[0]])


def observe_q(x, u, theta):
    del u, theta
    return x[:1]


def rk4(rhs, x, u, theta, h):
    k1 = rhs(x, u, theta)
    k2 = rhs(x + (h / 2) * k1, u, theta)
    k3 = rhs(x + (h / 2) * k2, u, theta)
    k4 = rhs(x + h * k3, u, theta)
    return x + h * (k1 + 2 * k2 + 2 * k3 + k4) / 6


def scan_rollout(rhs, theta, x0, u):
    def body(x, u_k):
        x_next = rk4(rhs, x, u_k, theta, DT)
        return x_next, x_next

    _, xs = jax.lax.scan(body, x0, u[:-1])
    return jnp.concatenate([x0[None], xs])


@functools.cache
def duffing_data():
    t = DT * np.arange(T)
    u = jnp.asarray((0.8 * np.sin(0.9 * t) + 0.4 * np.sin(2.3 * t))[:, None])
    x0 = jnp.array([1.2, 0.0])
    xs = scan_rollout(duffing_true_rhs, TRUE, x0, u)
    z = xs[:, :1] + 0.01 * jnp.asarray(np.random.default_rng(0).standard_normal((T, 1)))
    return x0, u, z


def hybrid_model(static):
    rhs = lambda x, u, p: hybrid_rhs(x, u, eqx.combine(p, static))  # noqa: E731
    return oj.Model.from_ode(rhs, DT, observe=observe_q)


def oracle_value_and_grad(params, static, x0, u, z):
    def cost(params, x0):
        theta = eqx.combine(params, static)
        xs = scan_rollout(hybrid_rhs, theta, x0, u)
        return jnp.mean(jnp.sum((xs[:, :1] - z) ** 2, axis=1))

    return jax.jit(jax.value_and_grad(cost, argnums=(0, 1)))(params, x0)


def mlp_theta(key=0, perturb=True):
    mlp = MLP(3, 1, widths=(8, 8), key=jax.random.PRNGKey(key))
    if perturb:  # move the zero last layer so that every layer's gradient is non-zero
        last = mlp.layers[-1]
        w = 0.1 * jax.random.normal(jax.random.PRNGKey(key + 1), last.weight.shape)
        mlp = eqx.tree_at(lambda m: m.layers[-1].weight, mlp, w)
    return {"c": jnp.asarray(0.25), "k": jnp.asarray(0.9), "r": mlp}


def dictionary_theta():
    feats = Features(2, 1, degree=3, exclude=("q", "v", "u0"), x_names=("q", "v"))
    coef = 0.05 * jax.random.normal(jax.random.PRNGKey(3), (len(feats), 1))
    d = Dictionary(feats, 1, out_names=("dv",), coef=coef)
    return {"c": jnp.asarray(0.25), "k": jnp.asarray(0.9), "r": d}


@pytest.mark.parametrize("strategy", ["jacobian", "vjp"])
@pytest.mark.parametrize("residual", ["mlp", "dictionary"])
def test_hybrid_one_shot_gradient_matches_autodiff(residual, strategy):
    theta = mlp_theta() if residual == "mlp" else dictionary_theta()
    params, static = eqx.partition(theta, eqx.is_inexact_array)
    x0, u, z = duffing_data()
    C, (g_theta, g_x0) = oj.value_and_grad(
        hybrid_model(static), params, x0, u, z, strategy=strategy
    )
    C_ref, (g_theta_ref, g_x0_ref) = oracle_value_and_grad(params, static, x0, u, z)
    assert_tree_rel_close(C, C_ref, rtol=1e-12)
    assert_tree_rel_close(g_theta, g_theta_ref, rtol=1e-12)
    assert_tree_rel_close(g_x0, g_x0_ref, rtol=1e-12)
    # Not vacuous: every trained leaf has a non-zero gradient.
    assert all(float(jnp.linalg.norm(g)) > 0 for g in jax.tree_util.tree_leaves(g_theta))
    assert jax.tree_util.tree_structure(g_theta) == jax.tree_util.tree_structure(params)


def test_mlp_starts_as_the_physical_model():
    theta = mlp_theta(perturb=False)
    feats = jax.random.normal(jax.random.PRNGKey(5), (50, 3))
    assert np.all(np.asarray(jax.vmap(theta["r"])(feats)) == 0.0)
    params, static = eqx.partition(theta, eqx.is_inexact_array)
    x0, u, z = duffing_data()
    xs_hybrid, _ = oj.simulate(hybrid_model(static), params, x0, u)
    physical = lambda x, u, p: hybrid_rhs(x, u, {**p, "r": lambda x, u: jnp.zeros(1)})  # noqa: E731
    phys = {"c": theta["c"], "k": theta["k"]}
    xs_phys, _ = oj.simulate(oj.Model.from_ode(physical, DT, observe=observe_q), phys, x0, u)
    np.testing.assert_array_equal(xs_hybrid, xs_phys)  # bit for bit
    # The last layer gets a gradient at the start; the hidden layers' gradient is exactly 0.
    _, (g, _) = oj.value_and_grad(hybrid_model(static), params, x0, u, z)
    layers = g["r"].layers
    assert float(jnp.linalg.norm(layers[-1].weight)) > 0
    assert all(float(jnp.linalg.norm(layer.weight)) == 0 for layer in layers[:-1])


def test_mlp_options_and_parameter_count():
    key = jax.random.PRNGKey(0)
    mlp = MLP(3, 2, widths=(5, 4), key=key)
    assert count_parameters(mlp) == (3 * 5 + 5) + (5 * 4 + 4) + (4 * 2 + 2)
    assert count_parameters(mlp_theta()) == 2 + count_parameters(mlp_theta()["r"])
    # A bound caps the output, with slope 1 at zero.
    big = MLP(3, 2, widths=(5,), key=key, zero_last=False, scale=100.0, bound=0.5)
    out = jax.vmap(big)(3.0 * jax.random.normal(key, (200, 3)))
    assert float(jnp.max(jnp.abs(out))) <= 0.5 and float(jnp.max(jnp.abs(out))) > 0.45
    raw = MLP(3, 2, widths=(5,), key=key, zero_last=False, scale=1e-6)
    bounded = MLP(3, 2, widths=(5,), key=key, zero_last=False, scale=1e-6, bound=0.5)
    v = jnp.ones(3)
    np.testing.assert_allclose(bounded(v), raw(v), rtol=1e-10)
    # Input normalisation: (v - offset) / scale before the first layer.
    norm = MLP(
        3, 1, widths=(4,), key=key, zero_last=False, input_offset=1.0, input_scale=[2.0, 4.0, 8.0]
    )
    plain = MLP(3, 1, widths=(4,), key=key, zero_last=False)
    np.testing.assert_allclose(norm(jnp.array([3.0, 5.0, 9.0])), plain(jnp.ones(3)), rtol=1e-14)
    # Static parts are not parameters; an affine map has no hidden layer.
    assert count_parameters(MLP(3, 1, widths=(), key=key)) == 4
    assert eqx.partition(mlp, eqx.is_inexact_array)[1].activation is jax.nn.tanh


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(in_size=0, out_size=1), "`in_size`"),
        (dict(in_size=2, out_size=1.5), "`out_size`"),
        (dict(in_size=2, out_size=1, widths=(4, -1)), "`widths`"),
        (dict(in_size=2, out_size=1, widths=4), "`widths`"),
        (dict(in_size=2, out_size=1, bound=0.0), "`bound`"),
        (dict(in_size=2, out_size=1, scale=math.inf), "`scale`"),
        (dict(in_size=2, out_size=1, scale=jnp.array([1.0, 2.0])), "`scale` must be one finite"),
        (dict(in_size=2, out_size=1, scale=True), "`scale` must be a finite real"),
        (dict(in_size=2, out_size=1, activation="tanh"), "`activation`"),
        (dict(in_size=2, out_size=1, input_scale=[1.0, 0.0]), "`input_scale`"),
        (dict(in_size=2, out_size=1, input_offset=[1.0, 2.0, 3.0]), "`input_offset`"),
    ],
)
def test_mlp_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MLP(**kwargs, key=jax.random.PRNGKey(0))


def test_features_of_integer_data_are_not_truncated():
    """Integer states gave sin(1) = 0: the user functions' values were cast to the data's
    integer dtype (in `Dictionary` and `Features.rms` too)."""
    f = Features(1, 0, 2, functions={"sin(x0)": lambda x, u: jnp.sin(x[0])})
    np.testing.assert_array_equal(f(np.array([1]), np.zeros(0)), f(np.array([1.0]), np.zeros(0)))
    assert float(f(np.array([1]), np.zeros(0))[-1]) == pytest.approx(np.sin(1.0), rel=1e-15)
    d = Dictionary(f, 1, coef=np.ones((3, 1)))
    np.testing.assert_array_equal(d(np.array([1]), np.zeros(0)), d(np.array([1.0]), np.zeros(0)))
    ints, floats = np.array([[1], [2]]), np.array([[1.0], [2.0]])
    np.testing.assert_array_equal(f.rms(ints, np.zeros((2, 0))), f.rms(floats, np.zeros((2, 0))))


def test_mlp_takes_a_scale_given_as_a_0d_array():
    # A scale from data (jnp.std(...) or np.float64) is a 0-d array: a constant like 2.0.
    key = jax.random.PRNGKey(0)
    for scale in (jnp.array(2.0), np.array(2.0), np.float64(2.0)):
        mlp = MLP(2, 1, (4,), key=key, zero_last=False, scale=scale, bound=jnp.array(3.0))
        assert (mlp.scale, mlp.bound) == (2.0, 3.0)
        assert type(mlp.scale) is float


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        # A scale of 0 gave a residual identically zero with a zero gradient.
        (dict(scale=0.0), ValueError, "`scale` must be > 0"),
        (dict(scale=jnp.array(-1.0)), ValueError, "`scale` must be > 0"),
        # A non-bool zero_last was taken for its truth value ("no" as True).
        (dict(zero_last="no"), TypeError, "`zero_last` must be True or False, got 'no'"),
        (dict(zero_last=None), TypeError, "`zero_last` must be True or False"),
        (dict(zero_last=1), TypeError, "`zero_last` must be True or False"),
    ],
)
def test_mlp_scale_must_be_positive_and_zero_last_a_bool(kwargs, error, match):
    with pytest.raises(error, match=match):
        MLP(2, 1, (4,), key=jax.random.PRNGKey(0), **kwargs)
    assert MLP(2, 1, (4,), key=jax.random.PRNGKey(0), zero_last=np.bool_(False)).scale == 1.0


@pytest.mark.parametrize(
    "key, dtype, error, match",
    [
        # JAX's "invalid PRNG key data" (an int) and "split accepts a single key".
        (0, None, TypeError, "`key` must be a JAX PRNG key"),
        (jax.random.split(jax.random.PRNGKey(0), 3), None, TypeError, "`key` must be a JAX"),
        # JAX's "dtype argument to `uniform` must be a float dtype".
        (jax.random.PRNGKey(0), jnp.int32, ValueError, "`dtype` must be a floating dtype"),
    ],
)
def test_mlp_names_a_bad_key_or_dtype(key, dtype, error, match):
    with pytest.raises(error, match=match):
        MLP(2, 1, (4,), key=key, dtype=dtype)


def test_mlp_wrong_feature_shape():
    mlp = MLP(3, 1, widths=(4,), key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="`features`"):
        mlp(jnp.ones(4))


def test_mlp_takes_integer_and_list_features_as_floats():
    """Integer features with an input offset and scale: the constants were cast to the
    features' integer dtype (0.5 -> 0, 0.25 -> 0), a wrong output without an error; a
    list failed inside the matrix product."""
    mlp = MLP(
        1, 1, (4,), key=jax.random.PRNGKey(0), zero_last=False, input_offset=0.5, input_scale=0.25
    )
    want = np.asarray(mlp(jnp.array([1.0])))
    np.testing.assert_array_equal(np.asarray(mlp(jnp.array([1]))), want)
    np.testing.assert_array_equal(np.asarray(mlp([1.0])), want)


#
# Dictionary
#


def test_feature_names_and_count():
    f = Features(2, 1, degree=3)
    assert len(f) == math.comb(3 + 3, 3) - 1 == 19
    assert f.names[:9] == ("x0", "x1", "u0", "x0^2", "x0*x1", "x0*u0", "x1^2", "x1*u0", "u0^2")
    assert f.names[9] == "x0^3" and "x0^2*u0" in f.names and f.names[-1] == "u0^3"
    assert len(set(f.names)) == 19
    fc = Features(2, 1, degree=3, constant=True)
    assert len(fc) == 20 and fc.names[0] == "1"
    for n_var, degree in [(1, 5), (3, 2), (4, 4)]:
        assert len(Features(n_var, 0, degree=degree)) == math.comb(n_var + degree, degree) - 1
    named = Features(2, 1, degree=2, x_names=("q", "v"), u_names=("F",), exclude=("q", "v"))
    assert named.names == ("F", "q^2", "q*v", "q*F", "v^2", "v*F", "F^2")
    fn = Features(1, 1, degree=1, functions={"sin(x0)": lambda x, u: jnp.sin(x[0])})
    assert fn.names == ("x0", "u0", "sin(x0)")


def test_feature_values():
    f = Features(
        2, 1, degree=3, constant=True, functions=[("tanh(u0)", lambda x, u: jnp.tanh(u[0]))]
    )
    x, u = jnp.array([0.7, -1.3]), jnp.array([2.0])
    vals = dict(zip(f.names, np.asarray(f(x, u))))
    v = {"x0": 0.7, "x1": -1.3, "u0": 2.0}
    for name, got in vals.items():
        if name == "1":
            expected = 1.0
        elif name == "tanh(u0)":
            expected = np.tanh(2.0)
        else:
            expected = 1.0
            for part in name.split("*"):
                base, _, power = part.partition("^")
                expected *= v[base] ** int(power or 1)
        assert got == pytest.approx(expected, rel=1e-15), name
    # Derivatives at zero are exact (products, not powers).
    g = jax.jacfwd(lambda x: f(x, u))(jnp.zeros(2))
    assert np.all(np.isfinite(np.asarray(g)))
    # lists, as arrays
    np.testing.assert_array_equal(np.asarray(f([0.7, -1.3], [2.0])), np.asarray(f(x, u)))
    # the columns' rms of an autonomous system's features (n_u = 0: it failed in reshape)
    auto = Features(2, 0, degree=2)
    np.testing.assert_allclose(auto.rms(np.ones((5, 2)), np.ones((5, 0))), np.ones(5))


def test_dictionary_call_equations_and_scaling():
    f = Features(2, 1, degree=3, x_names=("x0", "x1"))
    coef = np.zeros((len(f), 2))
    coef[f.names.index("x0^3"), 1] = -0.98
    coef[f.names.index("x1*u0"), 1] = 0.1
    coef[f.names.index("x0"), 0] = 1.0
    d = Dictionary(f, 2, out_names=("dx0", "dx1"), coef=coef)
    assert d.equations() == "dx0 = 1 x0\ndx1 = 0.1 x1*u0 - 0.98 x0^3"
    x, u = jnp.array([0.5, 2.0]), jnp.array([-1.0])
    np.testing.assert_allclose(d(x, u), [0.5, -0.98 * 0.125 + 0.1 * 2.0 * -1.0], rtol=1e-15)
    assert Dictionary(f, 2).equations() == "r0 = 0\nr1 = 0"
    assert count_parameters(d) == len(f) * 2
    # Per-feature scaling: the model is Theta / s @ coef; equations print coef / s.
    s = np.linspace(0.5, 3.0, len(f))
    ds = Dictionary(f, 2, out_names=("dx0", "dx1"), scale=s, coef=coef * s[:, None])
    np.testing.assert_allclose(ds(x, u), d(x, u), rtol=1e-14)
    np.testing.assert_allclose(ds.coefficients, coef, rtol=1e-15)
    assert ds.equations() == d.equations()
    rms = f.rms(jnp.ones((10, 2)) * jnp.array([2.0, 1.0]), jnp.ones((10, 1)))
    assert rms[f.names.index("x0^3")] == pytest.approx(8.0)
    # Negative first term and a constant.
    fc = Features(1, 0, degree=1, constant=True)
    assert Dictionary(fc, 1, coef=[[-2.5], [0.5]]).equations(precision=2) == "r0 = -2.5 + 0.5 x0"


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Features(0, 1, degree=2), "`n_x`"),
        (lambda: Features(2, -1, degree=2), "`n_u`"),
        (lambda: Features(2, 1, degree=-1), "`degree`"),
        (lambda: Features(2, 1, degree=2.5), "`degree`"),
        (lambda: Features(2, 1, degree=0), "empty"),
        (lambda: Features(2, 1, degree=2, exclude=("x9",)), "`exclude`"),
        (lambda: Features(2, 1, x_names=("a",)), "`x_names`"),
        (lambda: Features(2, 1, x_names=("a", "u0")), "distinct"),
        (lambda: Features(2, 1, functions={"x0": lambda x, u: x[0]}), "`functions`"),
        (lambda: Features(2, 1, functions={"f": lambda x, u: x}), "`functions`"),
        (lambda: Features(2, 1, functions={"f": lambda x, u: x @ u}), "`functions`"),
        (lambda: Features(2, 1, functions={"f": 3.0}), "`functions`"),
        (lambda: Dictionary("x0 x1", 1), "`features`"),
        (lambda: Dictionary(Features(2, 1), 0), "`n_out`"),
        (lambda: Dictionary(Features(2, 1), 1, coef=np.zeros((2, 1))), "`coef`"),
        (lambda: Dictionary(Features(2, 1), 1, scale=[1.0, 2.0]), "`scale`"),
        (lambda: Dictionary(Features(2, 1), 1, scale=[1.0, -1.0, 1.0]), "`scale`"),
        (lambda: Dictionary(Features(2, 1), 2, out_names=("a",)), "`out_names`"),
    ],
)
def test_dictionary_bad_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize("kwargs", [dict(exclude="x0"), dict(x_names="ab"), dict(u_names="F")])
def test_a_string_for_a_sequence_of_names_is_refused(kwargs):
    """A string is a sequence of its letters: `exclude="x0"` asked for terms 'x' and '0'."""
    name = next(iter(kwargs))
    with pytest.raises(TypeError, match=rf"`{name}` must be a sequence .* got the string"):
        Features(2, 1, degree=2, **kwargs)


def test_count_parameters_counts_what_fit_updates():
    """Python numbers are parameters of theta (`{"k": 2.0}`), integer arrays are data."""
    theta = {"k": 2.0, "n": np.int64(3), "idx": np.arange(4), "w": np.ones((2, 3))}
    assert count_parameters(theta) == 1 + 6


@pytest.mark.parametrize("precision", [-1, 2.5, True])
def test_equations_precision_is_an_integer(precision):
    """A negative precision was a format error of Python's."""
    dictionary = Dictionary(Features(2, 1), 1, coef=np.ones((3, 1)))
    with pytest.raises(ValueError, match="`precision` must be an integer >= 0"):
        dictionary.equations(precision=precision)


def test_dictionary_dtype_is_floating():
    """An integer `dtype` gave integer coefficients, which are no parameters of a fit."""
    with pytest.raises(ValueError, match="`dtype` must be a floating dtype"):
        Dictionary(Features(2, 1), 1, dtype=jnp.int32)


def test_dictionary_wrong_state_shape():
    d = Dictionary(Features(2, 1, degree=2), 1)
    with pytest.raises(ValueError, match="`x`"):
        d(jnp.ones(3), jnp.ones(1))
    with pytest.raises(ValueError, match="`u`"):
        d(jnp.ones(2), jnp.ones(2))


def test_a_library_emptied_by_exclude_says_so():
    """Every term excluded: the message asked for a degree >= 1, which was given."""
    with pytest.raises(ValueError, match="`exclude` removes every term"):
        Features(2, 0, degree=1, exclude=("x0", "x1"))
