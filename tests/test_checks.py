"""Bad input is a ValueError that names the argument, before any tracing error, and never
a silent broadcast."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import oneshot_jax as oj
from oneshot_jax import constraints as oc
from oneshot_jax.internal import fixed_mask

N_X, N_U, N_Z, T = 3, 2, 2, 6


def step(x, u, theta):
    return theta["a"] * jnp.tanh(x) + theta["B"] @ u


def observe(x, u, theta):
    del u, theta
    return x[:N_Z]


MODEL = oj.Model(step, observe)
THETA = {"a": jnp.asarray(0.9), "B": jnp.ones((N_X, N_U))}
_rng = np.random.default_rng(0)
X0 = jnp.asarray(_rng.standard_normal(N_X))
U = jnp.asarray(_rng.standard_normal((T, N_U)))
Z = jnp.asarray(_rng.standard_normal((T, N_Z)))
X0_B = jnp.stack([X0, -X0])
U_B = jnp.stack([U, 2 * U])
Z_B = jnp.stack([Z, -Z])


def penalty(x, theta):
    return jnp.sum(x**2)


ENTRY_POINTS = ["simulate", "loss", "value_and_grad", "literal_value_and_grad"]
WITH_Z = ENTRY_POINTS[1:]


def call(entry, model=MODEL, theta=THETA, x0=X0, u=U, z=Z, **kwargs):
    if entry == "simulate":
        assert not kwargs
        return oj.simulate(model, theta, x0, u)
    fn = {
        "loss": oj.loss,
        "value_and_grad": oj.value_and_grad,
        "literal_value_and_grad": oj.literal_value_and_grad,
    }[entry]
    return fn(model, theta, x0, u, z, **kwargs)


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_good_input_is_accepted(entry):
    # The baseline that every case below perturbs in one argument only.
    call(entry)
    call(entry, x0=X0_B, u=U_B, z=Z_B)
    if entry != "simulate":
        call(entry, weight=jnp.array([1.0, 2.0]), penalty=penalty, penalty_weight=0.5)
        call(entry, weight=jnp.array([[1.0, 1.0], [1.0, 1.0]]))  # PSD, singular


# (overrides, regex the message must match). Each case changes one argument of `call`.
SHAPE_CASES = {
    "x0 scalar": (dict(x0=jnp.asarray(1.0)), r"`x0` must have shape \(n_x,\)"),
    "x0 3-D": (dict(x0=jnp.ones((2, 1, N_X))), r"`x0` must have shape .* got shape \(2, 1, 3\)"),
    "x0 wrong n_x": (dict(x0=jnp.ones(N_X + 1)), r"`x0` of shape \(4,\)"),
    "x0 too short, broadcasts": (
        dict(x0=jnp.ones(1)),
        r"`model.step` must return a state "
        r"of shape \(1,\)",
    ),
    "u 1-D": (dict(u=jnp.ones(T)), r"`u` must have shape \(T, n_u\)"),
    "u 3-D for one trajectory": (dict(u=U[None]), r"`u` must have shape \(T, n_u\)"),
    "u wrong n_u": (dict(u=jnp.ones((T, N_U + 1))), r"`u` of shape \(6, 3\)"),
    "u empty horizon": (
        dict(u=jnp.ones((0, N_U)), z=jnp.ones((0, N_Z))),
        r"`u` must hold "
        r"at least one sample",
    ),
    "u not batched like x0": (dict(x0=X0_B, z=Z_B), r"`u` must have shape \(2, T, n_u\)"),
    "u wrong N": (
        dict(x0=X0_B, u=jnp.stack([U, U, U]), z=Z_B),
        r"`u` must have shape \(2, T, n_u\)",
    ),
    "no trajectories": (
        dict(x0=jnp.ones((0, N_X)), u=jnp.ones((0, T, N_U)), z=jnp.ones((0, T, N_Z))),
        r"`x0` must hold at least one trajectory",
    ),
}

Z_SHAPE_CASES = {
    "z wrong T": (dict(z=Z[:-1]), r"`z` must have shape \(6, 2\)"),
    "z wrong n_z": (dict(z=jnp.ones((T, N_Z + 1))), r"`z` must have shape \(6, 2\)"),
    "z broadcastable n_z": (dict(z=jnp.ones((T, 1))), r"`z` must have shape \(6, 2\)"),
    "z broadcastable T": (dict(z=jnp.ones((1, N_Z))), r"`z` must have shape \(6, 2\)"),
    "z 1-D": (dict(z=jnp.ones(T)), r"`z` must have shape \(6, 2\)"),
    "z batched, one trajectory": (dict(z=Z_B), r"`z` must have shape \(6, 2\)"),
    "z not batched": (dict(x0=X0_B, u=U_B), r"`z` must have shape \(2, 6, 2\)"),
    "z wrong N": (dict(x0=X0_B, u=U_B, z=Z_B[:1]), r"`z` must have shape \(2, 6, 2\)"),
    "weight wrong length": (dict(weight=jnp.ones(N_Z + 1)), r"`weight` must have shape \(2,\)"),
    "weight scalar": (
        dict(weight=jnp.asarray(2.0)),
        r"`weight` is a scalar, which is taken for one output only: .*n_z = 2 .*shape \(2,\)",
    ),
    "weight non-square": (dict(weight=jnp.ones((N_Z, N_Z + 1))), r"`weight` must have shape"),
    "weight 3-D": (dict(weight=jnp.ones((N_Z, N_Z, 1))), r"`weight` must have shape"),
    "weight sized for x": (dict(weight=jnp.eye(N_X)), r"`weight` must have shape .*\(2, 2\)"),
}


@pytest.mark.parametrize("entry", ENTRY_POINTS)
@pytest.mark.parametrize("case", list(SHAPE_CASES))
def test_shape_mismatch(case, entry):
    overrides, match = SHAPE_CASES[case]
    with pytest.raises(ValueError, match=match):
        call(entry, **overrides)


@pytest.mark.parametrize("entry", WITH_Z)
@pytest.mark.parametrize("case", list(Z_SHAPE_CASES))
def test_z_and_weight_shape_mismatch(case, entry):
    overrides, match = Z_SHAPE_CASES[case]
    with pytest.raises(ValueError, match=match):
        call(entry, **overrides)


def _with(a, index, value):
    return jnp.asarray(a).at[index].set(value)


VALUE_CASES = {
    "u NaN": ("u", dict(u=_with(U, (2, 1), jnp.nan))),
    "u inf": ("u", dict(u=_with(U, (0, 0), jnp.inf))),
    "u -inf batched": ("u", dict(x0=X0_B, u=_with(U_B, (1, 5, 1), -jnp.inf), z=Z_B)),
    "z NaN": ("z", dict(z=_with(Z, (3, 0), jnp.nan))),
    "z inf": ("z", dict(z=_with(Z, (5, 1), jnp.inf))),
    "z NaN batched": ("z", dict(x0=X0_B, u=U_B, z=_with(Z_B, (1, 0, 0), jnp.nan))),
    "x0 NaN": ("x0", dict(x0=_with(X0, 1, jnp.nan))),
    "theta inf": ("theta", dict(theta={"a": jnp.asarray(jnp.inf), "B": THETA["B"]})),
    "weight NaN": ("weight", dict(weight=jnp.array([1.0, jnp.nan]))),
}


@pytest.mark.parametrize("entry", ENTRY_POINTS)
@pytest.mark.parametrize("case", list(VALUE_CASES))
def test_nan_or_inf(case, entry):
    name, overrides = VALUE_CASES[case]
    if entry == "simulate" and name in ("z", "weight"):
        pytest.skip("simulate takes no z or weight")
    hint = (
        r" values \(`fit`, `loss`, `value_and_grad`, `estimate_x0` and `predict` take"
        if name == "z"
        else ""
    )
    with pytest.raises(ValueError, match=rf"`{name}` contains NaN or inf{hint}"):
        call(entry, **overrides)


def test_nan_or_inf_names_its_first_entry():
    """The error names the first entry that is not finite: a record of a ragged list
    and its sample (the padded stack's index would point past a short record), a leaf of
    a dict theta by its key."""
    model = oj.Model(lambda x, u, th: th["a"][0] * x + u[:1])
    short, long = np.ones((5, 1)), np.ones((8, 1))
    long[3] = np.nan
    with pytest.raises(
        ValueError, match=r"^`u` contains NaN or inf values; the first is `u\[1\]\[3, 0\]`\.$"
    ):
        oj.simulate(model, {"a": np.ones(2)}, np.zeros((2, 1)), [short, long])
    with pytest.raises(
        ValueError,
        match=r"^`theta` contains NaN or inf values; the first is `theta\['a'\]\[1\]`\.$",
    ):
        oj.simulate(model, {"a": np.array([1.0, np.inf])}, np.zeros(1), short)


NOT_REAL = {
    "x0 complex": (dict(x0=X0.astype(jnp.complex128)), "x0"),
    "x0 bool": (dict(x0=X0 > 0), "x0"),  # (the mask of `estimate_x0`, misplaced: it ran)
    "u string": (dict(u=np.array([["a", "b"]] * T)), "u"),
    "z complex": (dict(z=Z + 1j), "z"),
    "z bool": (dict(z=Z > 0), "z"),  # (a comparison passed for the measured outputs)
    "z bool records": (
        dict(x0=np.stack([X0, X0]), u=[U, U[:-3]], z=[Z > 0, Z[:-3] > 0]),
        r"z\[0\]",
    ),
    "theta string": (dict(theta={"a": "0.9", "B": THETA["B"]}), "theta"),
}


@pytest.mark.parametrize("entry", WITH_Z)
@pytest.mark.parametrize("case", list(NOT_REAL))
def test_not_real_numbers(case, entry):
    overrides, name = NOT_REAL[case]
    with pytest.raises(ValueError, match=rf"`{name}` must hold real numbers"):
        call(entry, **overrides)


def test_a_theta_without_parameters_is_a_known_model():
    """A model whose functions read no parameter takes theta = {} or None: it simulates,
    its x0 is estimated (MATLAB's findstates of a known model), and `fit` estimates x0
    alone, as a fit with a parameter that the model ignores, held fixed, does; the
    printout says there is none. A model that reads a parameter theta lacks names it."""

    def step(x, u, th):
        return jnp.array([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - 2.0 * x[0] - 0.5 * x[1])])

    known = oj.Model(step, lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1))
    _, z = oj.simulate(known, {}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    ignored = oj.fit(known, {"unused": 1.0}, np.zeros(2), u, z, fixed={"unused": True})
    for theta in ({}, None):
        r = oj.fit(known, theta, np.zeros(2), u, z)
        assert r.success, r.message
        np.testing.assert_allclose(r.x0, ignored.x0, rtol=1e-12)
        np.testing.assert_allclose(r.x0_std, ignored.x0_std, rtol=1e-10)
        assert "(none: the model has no parameters" in str(r)
        est = oj.estimate_x0(known, theta, u[:20], z[:20], x0=np.zeros(2))
        np.testing.assert_allclose(est.x0, ignored.x0, atol=0.05)
    starts = np.array([[0.0, 0.0], [3.0, 1.0]])
    assert oj.fit(known, {}, starts, u, z, multistart=True).success
    with pytest.raises(ValueError, match=r"the starts are the rows of `x0`"):
        oj.fit(known, {}, np.zeros(2), u, z, multistart=True)
    for theta in ({}, None, []):
        with pytest.raises(ValueError, match=r"calling the model's `step`.*failed: \w+Error"):
            call("loss", theta=theta)


BAD_MODELS = {
    "step grows the state": (
        oj.Model(lambda x, u, th: jnp.concatenate([x, u]), observe),
        r"`model.step` must return a state of shape \(3,\)",
    ),
    "step returns a scalar": (
        oj.Model(lambda x, u, th: jnp.sum(x), observe),
        r"`model.step` must return a state of shape \(3,\)",
    ),
    "step returns a row": (
        oj.Model(lambda x, u, th: x[None, :], observe),
        r"`model.step` must return a state of shape \(3,\)",
    ),
    "step returns a tuple": (
        oj.Model(lambda x, u, th: (x, x), observe),
        r"`model.step` must return a state of shape \(3,\)",
    ),
    "step changes dtype": (
        oj.Model(lambda x, u, th: step(x, u, th).astype(jnp.float32), observe),
        r"`model.step` must keep the state's dtype float64",
    ),
    "step promotes float32 state": (
        oj.Model(lambda x, u, th: x + jnp.ones(N_X, dtype=jnp.float64), observe),
        r"`model.step` must keep the state's dtype float32",
    ),
    "step fails": (
        oj.Model(lambda x, u, th: th["missing"] * x, observe),
        r"calling the model's `step` on a state of shape \(3,\) \(from `x0`.* and the parameters "
        r"`theta0?` \(a dict, leaf shapes \{'B': \(3, 2\), 'a': \(\)\}\) failed: KeyError",
    ),
    "step returns a list": (
        oj.Model(lambda x, u, th: [x[0], x[1], x[2]], observe),
        r"`model.step` must return a state of shape \(3,\) .*got list \(build the state with",
    ),
    # RK4 broadcasts dx/dt against x: these gave a state of the right shape (a wrong
    # model, fitted to "converged"), a deep error, or one about the step.
    "rhs returns one entry": (
        oj.Model.from_ode(lambda x, u, th: th["a"] * x[:1] + u[0], 0.1, observe=observe),
        r"the model's `rhs` \(`Model.from_ode`\) must return dx/dt as an array of shape "
        r"\(3,\) \(the shape of x0\), got \(1,\)",
    ),
    "rhs of more states than x0": (  # (an unmeasured state left out of x0 = z[0])
        oj.Model.from_ode(
            lambda x, u, th: th["a"] * jnp.concatenate([x, x[:1]]), 0.1, observe=observe
        ),
        r"got \(4,\): `rhs` and `x0` .* must agree on the number of states \(if the model "
        r"has 4 states, x0 needs all 4, the unmeasured ones too",
    ),
    "rhs returns a scalar": (
        oj.Model.from_ode(lambda x, u, th: th["a"] * x[0], 0.1, observe=observe),
        r"`rhs` \(`Model.from_ode`\) must return dx/dt as an array of shape \(3,\).*got \(\)",
    ),
    "rhs returns a column": (
        oj.Model.from_ode(lambda x, u, th: th["a"] * x[:, None], 0.1, observe=observe),
        r"`rhs` \(`Model.from_ode`\) must return dx/dt .*got \(3, 1\)",
    ),
    "rhs returns a list": (
        oj.Model.from_ode(lambda x, u, th: [x[1], x[2], -x[0]], 0.1, observe=observe),
        r"`rhs` \(`Model.from_ode`\) must return dx/dt .*got a list \(build dx/dt with jnp.stack",
    ),
    "rhs fails": (
        oj.Model.from_ode(lambda x, u, th: th["missing"] * x, 0.1, observe=observe),
        r"calling the model's `rhs` \(`Model.from_ode`\) on a state of shape \(3,\)",
    ),
    "observe returns a scalar": (
        oj.Model(step, lambda x, u, th: x[0]),
        r"`model.observe` must return a 1-D output",
    ),
    "observe returns a list": (
        oj.Model(step, lambda x, u, th: [x[0], x[1]]),
        r"`model.observe` must return a 1-D output .*got list \(build z with jnp.stack",
    ),
    "observe returns a matrix": (
        oj.Model(step, lambda x, u, th: jnp.outer(x, x)),
        r"`model.observe` must return a 1-D output",
    ),
}


@pytest.mark.parametrize("entry", ENTRY_POINTS)
@pytest.mark.parametrize("case", list(BAD_MODELS))
def test_bad_model(case, entry):
    model, match = BAD_MODELS[case]
    kwargs = {}
    if case == "step promotes float32 state":
        kwargs = dict(
            theta={"a": jnp.float32(0.9), "B": THETA["B"].astype(jnp.float32)},
            x0=X0.astype(jnp.float32),
            u=U.astype(jnp.float32),
            z=Z.astype(jnp.float32),
        )
    with pytest.raises(ValueError, match=match):
        call(entry, model=model, **kwargs)


def test_a_failing_model_call_describes_the_held_leaves_of_theta():
    """The shapes in the message were None for theta's integer leaves (held as data)."""
    model = oj.Model(lambda x, u, th: th["missing"] * x, observe)
    theta = {**THETA, "n": np.int64(3), "k": np.arange(4)}
    with pytest.raises(
        ValueError, match=r"leaf shapes \{'B': \(3, 2\), 'a': \(\), 'k': \(4,\), 'n': \(\)\}"
    ):
        oj.simulate(model, theta, X0, U)


def test_a_failing_model_call_describes_a_network_in_theta_by_its_size():
    """A network inside theta was described by its repr, cut after 200 characters and
    spread over several lines; now by its class and its count of numbers."""
    import equinox as eqx

    net = eqx.nn.MLP(3, 3, 8, 1, key=jax.random.PRNGKey(0))
    model = oj.Model(lambda x, u, th: th["missing"] * x + th["r"](x), observe)
    with pytest.raises(
        ValueError, match=r"leaf shapes \{'B': \(3, 2\), 'a': \(\), 'r': 'MLP of 59 numbers'\}\) "
    ):
        oj.simulate(model, {**THETA, "r": net}, X0, U)


def test_a_transposed_input_is_named():
    with pytest.raises(
        ValueError, match=r"`u` of shape \(2, 6\) holds T = 2 samples of 6 inputs: "
    ):
        model = oj.Model(lambda x, u, th: th["a"] * x + u[0], observe)  # any number of inputs
        oj.loss(model, THETA, X0, U.T, jnp.ones((6, N_Z)))


def test_a_one_sample_input_whose_other_columns_the_model_ignores_warns():
    """A one-input record given as (1, T) simulated one sample without a word when the
    model reads only u[0] (`simulate` has no z to compare it with). It warns at the
    caller's line; a model that reads both inputs of a one-sample record does not."""
    one = oj.Model(lambda x, u, th: th["a"] * x + u[0], lambda x, u, th: x)
    u = np.linspace(0.0, 1.0, 50)[None]
    with pytest.warns(UserWarning, match=r"`u` has shape \(1, 50\).*Is it transposed") as w:
        oj.simulate(one, {"a": 0.5}, np.zeros(1), u)
    assert w[0].filename == __file__
    with pytest.warns(UserWarning, match="Is it transposed"):
        oj.check_stability(one, {"a": 0.5}, np.zeros(1), u)
    two = oj.Model(lambda x, u, th: th["a"] * x + u[0] - u[1], lambda x, u, th: x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.simulate(two, {"a": 0.5}, np.zeros(1), np.ones((1, 2)))
        oj.simulate(one, {"a": 0.5}, np.zeros(1), u.T)


def test_the_rhs_of_a_timed_model_is_checked():
    model = oj.Model.from_ode(lambda x, u, th: th["a"] * x[:1], observe=observe)
    t = 0.1 * jnp.arange(T)
    with pytest.raises(ValueError, match=r"`rhs` \(`Model.from_ode`\) must return .*got \(1,\)"):
        oj.simulate(model, THETA, X0, U, t=t)
    with pytest.raises(ValueError, match=r"`rhs` \(`Model.from_ode`\) must return .*got \(1,\)"):
        oj.fit(model, THETA, X0, U, Z, t=t)


def test_an_rhs_shaped_by_a_too_wide_u_names_u():
    """dx/dt = -a x + u with x0 of 1 state and u of 2 columns: the error blamed `rhs`
    and `x0` (both right) and did not name `u`."""
    model = oj.Model.from_ode(lambda x, u, th: -th["a"] * x + u, 0.1)
    with pytest.raises(ValueError, match=r"got \(2,\).*shape of an input u\[k\], \(2,\), from `u`"):
        oj.simulate(model, {"a": 1.0}, np.zeros(1), np.ones((10, 2)))


WEIGHT_VALUES = {
    "negative diagonal": (
        jnp.array([1.0, -0.1]),
        r"`weight` \(diagonal of Q\) must be "
        r"non-negative",
    ),
    "not symmetric": (jnp.array([[1.0, 0.5], [0.0, 1.0]]), r"`weight` must be a symmetric"),
    "not PSD": (jnp.array([[1.0, 2.0], [2.0, 1.0]]), r"`weight` must be positive semi-definite"),
    "negative definite": (-jnp.eye(N_Z), r"`weight` must be positive semi-definite"),
}


@pytest.mark.parametrize("entry", WITH_Z)
@pytest.mark.parametrize("case", list(WEIGHT_VALUES))
def test_bad_weight_values(case, entry):
    weight, match = WEIGHT_VALUES[case]
    with pytest.raises(ValueError, match=match):
        call(entry, weight=weight)


def test_a_scalar_weight_is_the_weight_of_one_output():
    # (weight=-1.0 on one output was refused for its shape (), which hid its sign.)
    model = oj.Model(lambda x, u, th: th["a"] * jnp.tanh(x) + u[:1], lambda x, u, th: x)
    theta, x0, z = {"a": 0.9}, X0[:1], Z[:, :1]
    C = oj.loss(model, theta, x0, U, z, weight=jnp.array([2.0]))
    assert oj.loss(model, theta, x0, U, z, weight=2.0) == C
    assert oj.value_and_grad(model, theta, x0, U, z, weight=np.float64(2.0))[0] == C
    for entry in WITH_Z:
        with pytest.raises(
            ValueError, match=r"`weight` \(Q of eq. 4\) must be non-negative, got -1\."
        ):
            call(entry, model=model, theta=theta, x0=x0, z=z, weight=-1.0)
        # Its sign first where the shape is wrong too (two outputs)
        with pytest.raises(ValueError, match=r"must be non-negative, got -1\."):
            call(entry, weight=-1.0)
    with pytest.raises(ValueError, match=r"must be non-negative, got weight\[1\] = -0\.1\."):
        call("loss", weight=jnp.array([1.0, -0.1]))
    r = oj.fit(model, theta, x0, U, z, weight=4.0)
    np.testing.assert_array_equal(r.weight, [4.0])
    # (the fit's weight, read by predict's smoother as sigma^2 Q^-1)
    assert r.predict(U, z[:3], method="smoother").z.shape == z.shape


PENALTIES = {
    "vector": (lambda x, th: x, r"`penalty` must return a scalar"),
    "length-1 vector": (
        lambda x, th: jnp.sum(x, keepdims=True),
        r"`penalty` must return a "
        r"scalar",
    ),
    "not callable": (1.0, r"`penalty` must be callable"),
}


@pytest.mark.parametrize("entry", ["loss", "value_and_grad", "literal_value_and_grad"])
@pytest.mark.parametrize("case", ["vector", "length-1 vector"])
def test_penalty_not_scalar(case, entry):
    pen, match = PENALTIES[case]
    with pytest.raises(ValueError, match=match):
        call(entry, penalty=pen)


@pytest.mark.parametrize("entry", WITH_Z)
def test_penalty_not_callable(entry):
    pen, match = PENALTIES["not callable"]
    with pytest.raises(ValueError, match=match):
        call(entry, penalty=pen)


@pytest.mark.parametrize("entry", WITH_Z)
@pytest.mark.parametrize(
    "penalty_weight", [jnp.ones(2), float("nan"), float("inf"), "heavy", 1j, None, True, np.True_]
)
def test_bad_penalty_weight(penalty_weight, entry):
    with pytest.raises(ValueError, match=r"`penalty_weight` must be a finite real scalar"):
        call(entry, penalty=penalty, penalty_weight=penalty_weight)


@pytest.mark.parametrize("strategy", ["adjoint", "Jacobian", None, "", "literal"])
def test_bad_strategy(strategy):
    with pytest.raises(
        ValueError, match=r"`strategy` must be 'auto', 'jacobian', 'vjp' or 'parallel'"
    ):
        call("value_and_grad", strategy=strategy)


def test_bad_model_construction():
    with pytest.raises(ValueError, match=r"`step` must be callable"):
        oj.Model(3.0)
    with pytest.raises(ValueError, match=r"`observe` must be callable"):
        oj.Model(step, observe="x")
    rhs = lambda x, u, th: -x  # noqa: E731
    with pytest.raises(ValueError, match=r"`rhs` must be callable"):
        oj.Model.from_ode(None, 0.1)
    for dt in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"`dt` must be a finite positive number"):
            oj.Model.from_ode(rhs, dt)
    for method in ("rk45", "RK4", "tsit5"):
        with pytest.raises(ValueError, match=r"`method` must be 'rk4' or 'euler'"):
            oj.Model.from_ode(rhs, 0.1, method=method)
    for substeps in (0, -1, 1.5):
        with pytest.raises(ValueError, match=r"`substeps` must be an integer >= 1"):
            oj.Model.from_ode(rhs, 0.1, substeps=substeps)
    with pytest.raises(ValueError, match=r"`observe` must be callable"):
        oj.Model.from_ode(rhs, 0.1, observe=1)


def _spring_step(x, u, th):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] - 0.1 * th["k"] * x[0] + 0.1 * u[0]])


# one model for the precision tests below: their simulations (and the float32 fits of the two
# half precisions, widened alike) share their compiled programs
_SPRING = oj.Model(_spring_step)


def test_float64_host_data_run_in_float32_without_x64():
    """JAX's default (x64 off) with NumPy float64 data, as a user who did not enable x64
    would call it: the data are canonicalised to float32 once, and `simulate`, `fit` and
    `value_and_grad` run and return float32, with the fit recovering the parameters."""
    import jax

    model = _SPRING
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1))  # float64
    x0 = np.array([1.0, 0.0])
    with jax.enable_x64(False):
        _, z = oj.simulate(model, {"k": np.array(2.0)}, x0, u)
        assert z.dtype == jnp.float32
        z = np.asarray(z, np.float64)
        r = oj.fit(model, {"k": np.array(1.5)}, x0, u, z, solver="gauss_newton")
        assert r.theta["k"].dtype == np.float32
        assert r.success, r.stop_reason
        assert abs(float(r.theta["k"]) - 2.0) < 1e-4
        C, (g, gx) = oj.value_and_grad(model, {"k": np.array(2.0)}, x0, u, z)
        assert C.dtype == jnp.float32 and g["k"].dtype == jnp.float32
        assert float(C) < 1e-10
        # An ODE model's step called with NumPy float64 arrays (the uncertainty guide's
        # process-noise example): JAX's float32, not "`rhs` must return ... dtype float64"
        rhs = lambda x, u, th: -th["k"] * x + u[0]  # noqa: E731
        ode = oj.Model.from_ode(rhs, 0.1)
        for step in (ode.step, lambda x, u, th: oj.ode_step(rhs, x, u, th, 0.1)):
            assert step(x0, u[0], {"k": np.array(2.0)}).dtype == jnp.float32


@pytest.mark.parametrize("half", ["float16", "bfloat16"])
def test_half_precision_data_are_widened_to_float32(half):
    """theta0, x0, u and z all in float16 (or bfloat16): the fit's linear algebra has no
    half-precision routine (LAPACK's eigh failed with "Unsupported dtype float16" deep
    inside), so the data are widened to float32, and the fit runs and recovers k."""

    model = _SPRING
    dt = jnp.dtype(half)
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1))
    _, z = oj.simulate(model, {"k": np.array(2.0)}, np.array([1.0, 0.0]), u)
    h = lambda a: jnp.asarray(a, dt)  # noqa: E731
    r = oj.fit(model, {"k": h(1.5)}, h([1.0, 0.0]), h(u), h(z), solver="gauss_newton")
    assert r.theta["k"].dtype == np.float32 and np.asarray(r.x0).dtype == np.float32
    assert abs(float(r.theta["k"]) - 2.0) < 0.05  # (the data carry half precision's error)


def test_optimistix_trust_region_on_float32_with_x64_is_refused_by_name():
    """optimistix's trust-region solvers (LevenbergMarquardt, IndirectLevenbergMarquardt,
    Dogleg) fail deep inside lineax or `lax.cond` on float32 data with x64 on (optimistix
    0.1.0): `fit` names `solver` and the ways out instead. The same float32 data fit with
    those solvers with x64 off, and with optimistix's GaussNewton and BFGS with x64 on
    (the refusal is no broader than the failure)."""
    import jax

    model = _SPRING
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1)).astype(np.float32)
    x0 = np.array([1.0, 0.0], np.float32)
    _, z = oj.simulate(model, {"k": np.float32(2.0)}, x0, u)
    args = (model, {"k": np.float32(1.5)}, x0, u, np.asarray(z))
    kw = {"rtol": 1e-5, "atol": 1e-7}
    trust = [optx.LevenbergMarquardt(**kw), optx.IndirectLevenbergMarquardt(**kw)]
    trust.append(optx.Dogleg(**kw))
    for solver in trust:
        name = type(solver).__name__
        with pytest.raises(ValueError, match=rf"`solver`: .*Optimistix\({name}\).*float32"):
            oj.fit(*args, solver=oj.Optimistix(solver))
    with jax.enable_x64(False):
        r = oj.fit(*args, solver=oj.Optimistix(optx.LevenbergMarquardt(**kw)))
        assert r.theta["k"].dtype == np.float32 and abs(float(r.theta["k"]) - 2.0) < 1e-3
    for solver in (optx.GaussNewton(**kw), optx.BFGS(**kw)):
        r = oj.fit(*args, solver=oj.Optimistix(solver))
        assert r.theta["k"].dtype == np.float32 and abs(float(r.theta["k"]) - 2.0) < 1e-3


def _osc(x, u, p):
    return jnp.stack([x[1], -p["k"] * x[0] - p["c"] * x[1]])


OSC = {"k": 2.0, "c": 0.3}


def test_a_right_hand_side_or_observation_in_another_dtype_is_refused():
    """float32 from `rhs` with float64 data used to pass (RK4 promoted the stages back) and
    float32 from `observe` rounded the measurements to float32, silently."""
    u = np.zeros((20, 1), np.float64)
    rhs32 = oj.Model.from_ode(lambda x, u, p: _osc(x, u, p).astype(jnp.float32), 0.1)
    with pytest.raises(ValueError, match=r"`rhs`.*dtype float64.*got float32"):
        oj.simulate(rhs32, OSC, np.array([1.0, 0.0]), u)
    obs32 = oj.Model.from_ode(_osc, 0.1, observe=lambda x, u, p: x[:1].astype(jnp.float32))
    with pytest.raises(ValueError, match=r"`model.observe`.*dtype float64, got float32"):
        oj.loss(obs32, OSC, np.array([1.0, 0.0]), u, np.zeros((20, 1)))


def test_ode_step_in_a_handwritten_step_refuses_a_wrong_shaped_rhs():
    """`ode_step` broadcast dx/dt of shape () against a state of 2: a wrong model."""

    def step(x, u, p):
        return oj.ode_step(lambda x, u, p: -p["a"] * x[0], x, u, p, 0.1)

    with pytest.raises(ValueError, match=r"`rhs` must return dx/dt.*shape \(2,\).*got shape \(\)"):
        oj.simulate(oj.Model(step), {"a": 1.0}, np.array([1.0, 0.0]), np.zeros((10, 1)))


def test_a_model_without_inputs_fits_on_u_with_no_columns():
    """n_u = 0: `fit` (whose stability check reshaped u with -1) works as `simulate` does;
    u=None names what to give."""
    model = oj.Model.from_ode(_osc, 0.1, observe=lambda x, u, p: x[:1])
    u = np.zeros((200, 0))
    _, z = oj.simulate(model, OSC, np.array([1.0, 0.0]), u)
    noisy = np.asarray(z) + 1e-3 * np.random.default_rng(0).standard_normal(z.shape)
    r = oj.fit(model, {"k": 1.5, "c": 0.2}, np.array([1.0, 0.0]), u, noisy)
    assert r.success and abs(float(r.theta["k"]) - 2.0) < 3 * float(r.std["k"]) + 1e-3
    with pytest.raises(ValueError, match=r"`u` is required.*np.zeros\(\(T, 0\)\)"):
        oj.fit(model, {"k": 1.5, "c": 0.2}, np.array([1.0, 0.0]), None, noisy)
    # (the residual test and `predict` take that u too: they divided by its 0 columns,
    # and said "got shape ()" for None)
    rc = oj.metrics.residual_correlations(r.residuals, u)
    alone = oj.metrics.residual_correlations(r.residuals)
    assert rc.cross is None and rc.independent is None
    np.testing.assert_array_equal(rc.auto, alone.auto)
    with pytest.raises(ValueError, match=r"`u` is required.*np.zeros\(\(T, 0\)\)"):
        r.predict(None, noisy[:20])


def test_natural_mistakes_get_a_hint():
    with pytest.raises(ValueError, match=r"Model.from_ode\(rhs, dt=0.1\)"):
        oj.Model(_osc, 0.1)
    with pytest.raises(ValueError, match="`substeps`"):
        oj.Model.from_ode(_osc, 0.1, substeps=True)
    model = oj.Model.from_ode(_osc, 0.1)
    with pytest.raises(ValueError, match=r"read as 2 trajectories.*shape \(2,\)"):
        oj.simulate(model, OSC, np.array([[1.0], [0.0]]), np.zeros((10, 1)))
    # x0 as a row of the outputs, z[:1], for one record: the state's shape is named.
    with pytest.raises(ValueError, match=r"one trajectory of 2 states.*x0 of shape \(2,\)"):
        oj.fit(model, OSC, np.zeros((1, 2)), np.zeros((10, 1)), np.zeros((10, 1)))
    # A MATLAB user's habits: two records with one x0, u of shape (T,), x0 left out, a
    # mask of the initial states per record.
    with pytest.raises(ValueError, match=r"for 3 records .* x0 of shape \(3, 2\)"):
        oj.simulate(model, OSC, np.zeros(2), np.zeros((3, 10, 1)))
    with pytest.raises(ValueError, match=r"u\[:, None\], shape \(T, 1\)"):
        oj.simulate(model, OSC, np.zeros(2), np.zeros(10))
    with pytest.raises(ValueError, match=r"`x0` is required \(the initial state"):
        oj.fit(model, OSC, None, np.zeros((10, 1)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match=r"one of shape \(N, n_x\) = \(2, 2\), a mask per record"):
        oj.fit(
            model,
            OSC,
            np.zeros((2, 2)),
            np.zeros((2, 10, 1)),
            np.zeros((2, 10, 2)),
            estimate_x0=np.array([[False, False], [True, True], [True, True]]),
        )
    u = np.zeros((10, 1))
    u[3] = np.nan
    with pytest.raises(ValueError, match=r"`u` contains NaN.*`missing='mask'` applies to z"):
        oj.fit(model, OSC, np.zeros(2), u, np.zeros((10, 2)), missing="mask")


def test_a_masked_array_is_refused_where_its_mask_would_be_dropped():
    # (a masked z fitted its masked entries as data: its mask was dropped on conversion)
    model = oj.Model.from_ode(_osc, 0.1)
    z = np.ma.masked_array(np.zeros((10, 2)), mask=np.zeros((10, 2), bool))
    z.mask[3] = True
    with pytest.raises(
        ValueError,
        match=r"`z` is a NumPy masked array with 2 masked .*"
        r"z.filled\(np.nan\)` with `missing=\"mask\"`",
    ):
        oj.fit(model, OSC, np.zeros(2), np.zeros((10, 1)), z, missing="mask")
    u = np.ma.masked_array(np.zeros((10, 1)), mask=np.arange(10)[:, None] == 4)
    with pytest.raises(ValueError, match=r"`u` is a NumPy masked array with 1 masked"):
        oj.simulate(model, OSC, np.zeros(2), u)
    # held-out records take no missing samples: not the advice of `missing="mask"`
    held_out = oj.Validation(np.zeros((10, 1)), z, n=3)
    with pytest.raises(ValueError, match=r"`validation`: .*masked array.*fully measured"):
        oj.fit(model, OSC, np.zeros(2), np.zeros((10, 1)), np.zeros((10, 2)), validation=held_out)
    # nothing masked: the array's data, as a plain array gives
    plain = oj.simulate(model, OSC, np.array([1.0, 0.0]), np.ones((10, 1)))
    masked = oj.simulate(model, OSC, np.ma.masked_array([1.0, 0.0]), np.ma.ones((10, 1)))
    np.testing.assert_array_equal(masked[1], plain[1])


def test_an_integer_scalar_of_numpy_in_theta0_warns_that_it_is_held():
    """{"k": np.int64(1)} is carried as data (as a module's exponent would be): fit says
    so, naming the entry; a Python int is a parameter and is not named."""
    model = oj.Model.from_ode(lambda x, u, p: _osc(x, u, p) + jnp.stack([0.0, u[0]]), 0.1)
    u = np.random.default_rng(1).standard_normal((100, 1))
    _, z = oj.simulate(model, OSC, np.array([1.0, 0.0]), u)
    with pytest.warns(UserWarning, match=r"theta0\['k'\] \(int64\).*held fixed as data"):
        r = oj.fit(model, {"k": np.int64(2), "c": 0.2}, np.array([1.0, 0.0]), u, z)
    assert r.names == ("c",) and float(r.theta["c"]) == pytest.approx(0.3, abs=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.fit(model, {"k": 2, "c": 0.2}, np.array([1.0, 0.0]), u, z)


def test_an_integer_array_of_numpy_in_theta0_warns_that_it_is_held():
    """{"kc": np.array([2, 0])} (integers typed by hand) was held as data in silence: the
    fit returned the start for both entries."""

    def rhs(x, u, p):
        return jnp.stack([x[1], -p["kc"][0] * x[0] - p["kc"][1] * x[1] + p["b"] * u[0]])

    model = oj.Model.from_ode(rhs, 0.1)
    u = np.random.default_rng(1).standard_normal((100, 1))
    _, z = oj.simulate(model, {"kc": np.array([2.0, 0.3]), "b": 1.0}, np.array([1.0, 0.0]), u)
    with pytest.warns(UserWarning, match=r"theta0\['kc'\] \(int64, shape \(2,\)\).*held fixed"):
        r = oj.fit(model, {"kc": np.array([2, 0]), "b": 1.0}, np.array([1.0, 0.0]), u, z)
    assert r.names == ("b",) and np.array_equal(r.theta["kc"], [2, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = oj.fit(model, {"kc": np.array([2.0, 0.0]), "b": 1.0}, np.array([1.0, 0.0]), u, z)
    assert np.allclose(r.theta["kc"], [2.0, 0.3], atol=1e-6)


def test_a_python_int_field_of_a_module_warns_that_it_is_estimated():
    """An equinox module's `power: int = 1` (not static) is a parameter, fitted as a float
    where equinox's convention leaves it alone: fit says so, with the remedies; a static
    field or a NumPy integer is not named."""
    import equinox as eqx

    class Power(eqx.Module):
        w: jax.Array
        power: int

        def __call__(self, x):
            return self.w * x[0] ** self.power

    class StaticPower(eqx.Module):
        w: jax.Array
        power: int = eqx.field(static=True)

        def __call__(self, x):
            return self.w * x[0] ** self.power

    def step(x, u, th):
        return jnp.stack([th["a"] * x[0] + th["r"](x) + u[0]])

    model = oj.Model(step, lambda x, u, th: x)
    with pytest.warns(UserWarning, match=r"theta0\['r'\]\.power: a Python int field .*static"):
        oj.fit(model, {"a": 0.5, "r": Power(jnp.zeros(()), 3)}, np.zeros(1), _U1, _Z1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.fit(model, {"a": 0.5, "r": StaticPower(jnp.zeros(()), 3)}, np.zeros(1), _U1, _Z1)


# ------------------------------------------------------------- fit's rarer arguments
# Each case was a raw NumPy, JAX or Python error, or a silent acceptance, before.

LIN = oj.Model(
    lambda x, u, th: jnp.stack([th["a"] * x[0] + th["b"] * u[0]]),
    lambda x, u, th: x,
)
_U1 = np.random.default_rng(1).standard_normal((30, 1))
_Z1 = np.asarray(oj.simulate(LIN, {"a": 0.8, "b": 1.0}, jnp.zeros(1), _U1)[1])
LIN_THETA = {"a": 0.5, "b": 1.0}

FIT_CASES = {
    "z None": (dict(z=None), ValueError, r"`z` is required"),
    "no starts": (
        dict(theta0={"a": np.zeros(0), "b": np.zeros(0)}, multistart=True),
        ValueError,
        r"`multistart` needs at least one start",
    ),
    "NaN start": (
        dict(theta0={"a": np.array([0.5, np.nan]), "b": np.ones(2)}, multistart=True),
        ValueError,
        r"`theta0\['a'\]` must be finite; the starts \[1\]",
    ),
    "inf start of a dict": (
        dict(multistart={"a": np.array([0.5, np.inf])}),
        ValueError,
        r"`multistart\['a'\]` must be finite; the starts \[1\]",
    ),
    "NaN start of x0": (
        dict(x0=np.array([[0.0], [np.nan]]), multistart={"a": np.array([0.5, 0.6])}),
        ValueError,
        r"`x0` must be finite; the starts \[1\]",
    ),
    "integer penalty": (
        dict(penalty=lambda x, th: jnp.sum(x > 0)),
        ValueError,
        r"`penalty` must return a floating scalar",
    ),
    "empty intersection of boxes": (
        dict(
            constraints=[
                oj.constraints.box(lower={"a": 1.0}),
                oj.constraints.box(upper={"a": 0.5}),
            ]
        ),
        ValueError,
        r"intersection is empty .* theta\['a'\]",
    ),
    "outputs whose squares underflow": (
        dict(z=_Z1 * 1e-170, u=_U1 * 1e-170),
        ValueError,
        r"`z`: its largest magnitude .* rescale",
    ),
    "a list of windows": (
        dict(window=[10, 20]),
        ValueError,
        r"`window` must be a positive integer .*fit_continuation\(windows=",
    ),
    # (it blamed `x0`, whose rows matched `u`)
    "ragged records, fewer outputs than inputs": (
        dict(x0=np.zeros((3, 1)), u=[_U1, _U1[:20], _U1[:10]], z=[_Z1, _Z1[:20]]),
        ValueError,
        r"`u` holds 3 trajectories but `z` holds 2: one output record per input record",
    ),
    "validation of different lengths": (
        dict(validation=oj.Validation([_U1, _U1[:20]], [_Z1, _Z1[:20]], n=2)),
        ValueError,
        r"`validation`: records of different lengths",
    ),
}


@pytest.mark.parametrize("case", FIT_CASES)
def test_fit_refuses_bad_rare_arguments(case):
    overrides, error, match = FIT_CASES[case]
    args = dict(theta0=LIN_THETA, x0=np.zeros(1), u=_U1, z=_Z1) | overrides
    theta0, x0, u, z = (args.pop(k) for k in ("theta0", "x0", "u", "z"))
    with pytest.raises(error, match=match):
        oj.fit(LIN, theta0, x0, u, z, **args)


def test_the_intersection_of_boxes_that_meet_is_kept():
    # (the baseline of the empty intersection above: overlapping boxes fit as before)
    boxes = [oj.constraints.box(lower={"a": 0.1}), oj.constraints.box(upper={"a": 0.7})]
    result = oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, constraints=boxes)
    assert float(result.theta["a"]) == pytest.approx(0.7)


@pytest.mark.parametrize(
    "make,error,match",
    [
        (lambda: oj.Adam(b1=1.0), ValueError, r"`Adam\(b1=...\)` must be a number in \[0, 1\)"),
        (lambda: oj.Adam(b2=1.5), ValueError, r"`Adam\(b2=...\)` must be a number in \[0, 1\)"),
        (lambda: oj.Adam(lr_theta=lambda: 1e-3), TypeError, r"`Adam\(lr_theta=...\)` must be"),
        (lambda: oj.Adam(lr_x0=lambda c: jnp.ones(3)), TypeError, r"`Adam\(lr_x0=...\)`"),
        (lambda: oj.Adam(lr_theta=lambda c: jnp.nan), TypeError, r"returned nan"),
        # (the bound it states is the one it checks: a schedule may start at 0)
        (lambda: oj.Adam(lr_theta=lambda c: -1e-3), TypeError, r">= 0: a warm-up .*returned -0"),
        (lambda: oj.LevenbergMarquardt(gtol=1.0), ValueError, r"`LevenbergMarquardt\(gtol"),
        (lambda: oj.Adam(gtol=2.0), ValueError, r"`Adam\(gtol=...\)` must be a number in"),
        (lambda: oj.Validation(_U1, None, n=2), ValueError, r"`Validation` needs `z`"),
        (lambda: oj.Validation(_U1, _Z1, n="all"), ValueError, r"`Validation\(n=...\)`"),
        (lambda: oj.Validation(_U1, _Z1, n=2, x0_steps="5"), ValueError, r"x0_steps"),
        # (0 steps never estimated the head's x0: every iterate scored from the guess)
        (lambda: oj.Validation(_U1, _Z1, n=2, x0_steps=0), ValueError, r"never estimates"),
    ],
)
def test_options_are_checked_where_they_are_made(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_options_take_numpy_integers_and_schedules_that_start_at_zero():
    import optax

    solver = oj.LevenbergMarquardt(max_steps=np.int64(20))
    assert oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, solver=solver).success
    oj.Adam(lr_theta=optax.linear_schedule(0.0, 1e-2, 100))  # a warm-up starts at 0
    # 0-d arrays (an option computed with jnp) are the numbers they hold; they were
    # refused as "must be a number".
    lm = oj.LevenbergMarquardt(gtol=jnp.array(1e-6), mu0=jnp.array(1e-2), rtol=np.array(0.0))
    assert (lm.gtol, lm.mu0, lm.rtol) == (1e-6, 1e-2, 0.0) and type(lm.gtol) is float
    adam = oj.Adam(lr_theta=jnp.array(0.01), b1=jnp.array(0.8), tol_loss=jnp.array(1e-9))
    assert (adam.lr_theta, adam.b1, adam.tol_loss) == (0.01, 0.8, 1e-9)
    assert oj.LBFGS(tol_grad=jnp.array(1e-9)).tol_grad == 1e-9
    with pytest.raises(ValueError, match=r"`GaussNewton\(gtol=\.\.\.\)` must be a number"):
        oj.GaussNewton(gtol=jnp.array([1e-8, 1e-8]))
    # the strategy's options alike, and a NumPy scalar (equinox warned of "a JAX array
    # being set as static" for jnp.array(1e-8) and np.float64(0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pit = oj.ParallelInTime(rtol=jnp.array(1e-6), damping=np.float64(0.5))
        lm = oj.LevenbergMarquardt(gtol=np.float64(1e-6))
    assert (pit.rtol, pit.damping, lm.gtol) == (1e-6, 0.5, 1e-6) and type(pit.damping) is float


@pytest.mark.parametrize(
    "make,field",
    [
        (lambda v: oj.LevenbergMarquardt(max_steps=v), "max_steps"),
        (lambda v: oj.GaussNewton(cg_max_steps=v), "cg_max_steps"),
        (lambda v: oj.Adam(max_steps=v), "max_steps"),
        (lambda v: oj.LBFGS(memory_size=v), "memory_size"),
        (lambda v: oj.Optimistix(optx.LevenbergMarquardt(1e-8, 1e-8), max_steps=v), "max_steps"),
        (lambda v: oj.Windows(v), "length"),
        (lambda v: oj.Windows(10, every=v), "every"),
        (lambda v: oj.Windows(10, count=v), "count"),
        (lambda v: oj.TqdmProgress(v), "refresh_steps"),
    ],
)
def test_counts_are_integers_or_whole_floats_everywhere(make, field):
    """A count written 20.0 (as a configuration file may) is the integer 20 for every
    option that counts; 20.5 is refused by name."""
    made = make(20.0)
    assert getattr(made, field) == 20 and type(getattr(made, field)) is int
    assert type(getattr(make(np.int32(20)), field)) is int
    # A 0-d JAX array (a count computed with jnp) was refused as "not an integer".
    for v in (jnp.array(20), jnp.array(20.0), np.array(20)):
        assert getattr(make(v), field) == 20 and type(getattr(make(v), field)) is int
    with pytest.raises(ValueError, match=rf"{field}=\.\.\.\)` must be"):
        make(20.5)
    with pytest.raises(ValueError, match=rf"{field}=\.\.\.\)` must be"):
        make(jnp.array(True))
    with warnings.catch_warnings():  # (not "a JAX array is being set as static")
        warnings.simplefilter("error")
        assert type(oj.NeweyWest(jnp.array(3)).lags) is int


def test_numbers_given_as_strings_bools_or_complex_are_refused_by_name():
    """Each was silently taken as a number: box(lower="0.7") clipped to 0.7, lower=True
    bound at 1, a complex bound or record lost its imaginary part; positive("x") failed
    with "'>' not supported"; state_box(upper=-inf) made h infinite everywhere, and the fit
    blamed a diverging simulation."""
    theta = {"k": np.array(1.0)}
    for bad in ("0.7", True, 1 + 2j):
        with pytest.raises(ValueError, match="`lower` must hold real numbers"):
            oc.box(lower=bad).project(theta)
    for bad in ("x", None, True, np.array([1e-3, 1.0]), np.inf):
        with pytest.raises(ValueError, match="`eps` must be a finite number > 0"):
            oc.positive(bad)
    # (refused when made, not at its first use: nothing satisfies it)
    with pytest.raises(ValueError, match=r"`box` needs lower <= upper, got lower 1.0 > upper 0"):
        oc.box(1.0, 0.0)
    with pytest.raises(ValueError, match=r"`upper` holds -inf: no state satisfies it"):
        oj.penalties.state_box(upper=-np.inf)
    with pytest.raises(ValueError, match=r"`lower` holds \+inf"):
        oj.penalties.state_box(lower=[0.0, np.inf])
    with pytest.raises(ValueError, match="`lower` must be a scalar or a 1-D sequence of real"):
        oj.penalties.state_box(lower="1")
    # (NaN was "must be a scalar or a 1-D sequence of numbers", which it is)
    with pytest.raises(ValueError, match=r"`lower` holds NaN at \[0\]: give a number"):
        oj.penalties.state_box(lower=[np.nan, 0.0])
    # (a dataset's record passed whole: "dtype object")
    record = oj.datasets.Record(u=np.ones(10), y=np.ones(10), Ts=0.1)
    with pytest.raises(ValueError, match=r"`u` must hold real numbers, got a Record: pass its"):
        oj.fit(LIN, LIN_THETA, np.zeros(1), record, record.y[:, None])
    with pytest.raises(ValueError, match="`radius`"):
        oj.penalties.state_ball(True)
    with pytest.raises(TypeError, match="`u` must hold real numbers"):
        oj.datasets.Record(u=np.ones(10) * 1j, y=np.ones(10), Ts=0.1)
    with pytest.raises((TypeError, ValueError), match="`dt`"):
        oj.Model.from_ode(lambda x, u, p: -x, np.True_)
    with pytest.raises((TypeError, ValueError), match="`min_compile_time_secs`"):
        oj.enable_compilation_cache("/tmp/unused-cache", min_compile_time_secs="1.5")


def test_records_and_substeps_take_whole_floats_and_0d_arrays():
    rec = oj.datasets.Record(u=np.ones(10), y=np.ones(10), Ts=jnp.array(0.5), n=5.0)
    assert (rec.Ts, rec.n, type(rec.n)) == (0.5, 5, int)
    assert oj.datasets.Record(u=np.ones(10), y=np.ones(10), Ts=0.5, n=jnp.array(3)).n == 3
    with pytest.raises(TypeError, match="`n` must be an integer"):
        oj.datasets.Record(u=np.ones(10), y=np.ones(10), Ts=0.5, n=5.5)
    model = oj.Model.from_ode(lambda x, u, p: -x, 0.1, substeps=jnp.array(3))
    assert model.step.substeps == 3 and type(model.step.substeps) is int


def test_benchmark_scores_take_the_counts_a_record_takes():
    z = np.sin(np.arange(30.0))
    zhat = z + 0.1 * np.cos(np.arange(30.0))
    want = oj.metrics.benchmark_scores(z, zhat, 5).rmse
    for n in (5.0, np.float64(5.0), jnp.array(5), np.array(5)):
        np.testing.assert_array_equal(oj.metrics.benchmark_scores(z, zhat, n).rmse, want)
    for n in (5.5, True, "5"):
        with pytest.raises(TypeError, match="`n` must be an integer"):
            oj.metrics.benchmark_scores(z, zhat, n)


def test_ode_step_takes_a_python_number_state_and_a_list_input():
    """`ode_step(rhs, 1.0, [1.0], ...)` raised AttributeError ('float' has no dtype) and
    TypeError (array + list)."""

    def rhs(x, u, p):
        return -p * x + u[0]

    ref = oj.ode_step(rhs, jnp.array(1.0), jnp.array([1.0]), 0.5, 0.1)
    assert oj.ode_step(rhs, 1.0, [1.0], 0.5, 0.1) == ref
    foh = oj.ode_step(rhs, jnp.array(1.0), jnp.ones((2, 1)), 0.5, 0.1, input="foh")
    assert oj.ode_step(rhs, 1.0, [[1.0], [1.0]], 0.5, 0.1, input="foh") == foh
    # An integer state is the caller's mistake, not `rhs`'s (which was blamed for floats).
    with pytest.raises(TypeError, match=r"`x` must be a floating-point state, got dtype int"):
        oj.ode_step(rhs, [1, 0], [1.0], 0.5, 0.1)
    # The pair of a "foh" step under the default "zoh": the input is named (rhs was blamed
    # for dx/dt of shape (2, 1))
    with pytest.raises(ValueError, match=r'for input="zoh", got the shape \(2, 1\) of a pair'):
        oj.ode_step(rhs, jnp.zeros(1), jnp.ones((2, 1)), 0.5, 0.1)


def test_the_head_length_of_predict_may_be_a_whole_float(lin_result):
    theta, x0 = lin_result.theta, np.zeros(1)
    z = _Z1 + 0.1 * np.random.default_rng(2).standard_normal(_Z1.shape)  # heads differ
    a, b, c = (oj.predict(LIN, theta, _U1, z, n, x0=x0).z for n in (5.0, 5, 1))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(TypeError, match=r"`n` \(the number of head samples\) must be an int"):
        oj.predict(LIN, theta, _U1, z, 4.5, x0=x0)


def test_fit_continuation_refuses_an_infinite_factor():
    with pytest.raises(ValueError, match=r"`factor` must be a finite number > 1, got inf"):
        oj.fit_continuation(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, start=5, factor=np.inf)


# ----------------------------------------------------------------- after a fit


@pytest.fixture(scope="module")
def lin_result():
    return oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1)


def test_a_result_checks_inputs_given_as_lists(lin_result):
    two = np.hstack([_U1, _U1])
    with pytest.raises(ValueError, match=r"`u` must have n_u = 1 input columns"):
        lin_result.simulate(two.tolist())
    with pytest.raises(ValueError, match=r"`u` must have n_u = 1 input columns"):
        lin_result.simulate([two, two[:20]])  # ragged records, each checked
    with pytest.raises(ValueError, match=r"`u` must have n_u = 1 input columns"):
        lin_result.predict(two.tolist(), _Z1[:5])
    with pytest.raises(ValueError, match=r"`u` must have n_u = 1 input columns"):
        oj.check_basin(lin_result, two, _Z1, window=10)
    # (the baseline: lists of the right width run)
    _, z = lin_result.simulate(_U1.tolist())
    assert np.shape(z) == _Z1.shape


def test_an_initial_state_of_another_size_than_the_fitted_one_is_named(lin_result):
    """An x0 of 3 entries for a fitted state of 1 was blamed on the model ("`step` must
    return ... shape (3,)"): the result knows n_x, and so does the fit for `Validation`."""
    match = r"`x0` must have the fitted state's n_x = 1 entries .* got shape \(%s\)"
    with pytest.raises(ValueError, match=match % "3,"):
        lin_result.simulate(_U1, np.zeros(3))
    with pytest.raises(ValueError, match=match % "2, 3"):
        lin_result.simulate(np.stack([_U1, _U1]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=match % "3,"):
        lin_result.predict(_U1, _Z1[:5], x0=np.zeros(3))
    with pytest.raises(ValueError, match="`validation`: " + match % "3,"):
        oj.fit(
            LIN,
            LIN_THETA,
            np.zeros(1),
            _U1,
            _Z1,
            validation=oj.Validation(_U1, _Z1, x0=np.zeros(3)),
        )
    _, z = lin_result.simulate(np.stack([_U1, _U1]), np.zeros((2, 1)))  # (the right size)
    assert np.shape(z) == (2, *_Z1.shape)


@pytest.mark.parametrize("z_head", [None, 0.3, np.ones(5)])
def test_predict_names_z_head(lin_result, z_head):
    with pytest.raises(ValueError, match=r"`z_head` must have shape \(T, n_z\)"):
        lin_result.predict(_U1, z_head)


def test_functions_of_a_model_refuse_a_result(lin_result):
    with pytest.raises(TypeError, match=r"`model` must be a oneshot_jax.Model.*result.model"):
        oj.check_stability(lin_result, lin_result.theta, lin_result.x0, _U1)


def test_check_stability_refuses_bad_arguments_of_a_model_it_does_not_check(lin_result):
    # (a model not built by from_ode returned None, whatever its arguments)
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_x,\)"):
        oj.check_stability(lin_result.model, lin_result.theta, np.zeros((1, 1, 1)), _U1)
    assert oj.check_stability(lin_result.model, lin_result.theta, lin_result.x0, _U1) is None


def test_save_and_load_name_their_arguments(lin_result, tmp_path):
    with pytest.raises(TypeError, match=r"`path` must be a str or os.PathLike"):
        oj.load_result(123)
    with pytest.raises(TypeError, match=r"`path` must be a str or os.PathLike"):
        lin_result.save(None)
    path = lin_result.save(tmp_path / "r")
    with pytest.raises(TypeError, match=r"`model` must be a oneshot_jax.Model \(or None\)"):
        oj.load_result(path, model="abc")
    assert oj.load_result(path, model=LIN).model is LIN  # (the baseline)


def test_ode_step_checks_its_arguments():
    def rhs(x, u, theta):
        return jnp.stack([x[1], -theta * x[0] + u[0]])

    x, u = jnp.array([1.0, 0.0]), jnp.array([0.1])
    cases = [
        (dict(substeps=0), r"`substeps` must be an integer >= 1"),
        (dict(substeps=2.5), r"`substeps` must be an integer >= 1"),
        (dict(substeps=None), r"`substeps` must be an integer >= 1"),
        (dict(method="rk45"), r"`method` must be 'rk4' or 'euler'"),
        (dict(dt=0.0), r"`dt` must be a finite positive number"),
        (dict(input="foh"), r"`u` must be the pair \(u\[k\], u\[k\+1\]\) of shape \(2, n_u\)"),
        (dict(rhs=3), r"`rhs` must be callable"),
    ]
    for overrides, match in cases:
        args = dict(rhs=rhs, dt=0.1) | overrides
        f, dt = args.pop("rhs"), args.pop("dt")
        with pytest.raises(ValueError, match=match):
            oj.ode_step(f, x, u, 2.0, dt, **args)
    with pytest.raises(ValueError, match=r"`substeps` must be an integer >= 1, got None"):
        oj.Model.from_ode(rhs, dt=0.1, substeps=None)
    # a list state is taken as an array (it was an AttributeError)
    np.testing.assert_array_equal(
        oj.ode_step(rhs, [1.0, 0.0], u, 2.0, 0.1), oj.ode_step(rhs, x, u, 2.0, 0.1)
    )


# ------------------------------------------------------- a second round of probes


def test_progress_objects_are_checked():
    with pytest.raises(ValueError, match=r"`TqdmProgress\(refresh_steps=...\)` must be an"):
        oj.TqdmProgress(refresh_steps=0)
    with pytest.raises(ValueError, match=r"refresh_steps"):
        oj.TqdmProgress(refresh_steps="10")
    with pytest.raises(TypeError, match=r"`progress` got the class TqdmProgress"):
        oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, progress=oj.TqdmProgress)

    class NoClose:
        def open(self, total, description="fit"):
            return 0

        def update(self, *args):
            pass

    with pytest.raises(TypeError, match=r"open, update and close"):
        oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, progress=NoClose())

    # The methods the message names are enough: `finish` is optional (it was called, and
    # a meter without it failed with a bare AttributeError).
    class Meter(NoClose):
        closed = []

        def close(self, bar_id):
            self.closed.append(bar_id)

    r = oj.fit(LIN, LIN_THETA, np.zeros(1), _U1, _Z1, progress=Meter())
    assert r.success and Meter.closed == [0]


class LookupTableMissing(Exception):
    """An exception of the user's own."""


def test_an_exception_of_the_users_own_class_comes_through_as_itself():
    """Raised by the model on its first call (the entry check, which re-raises Python's
    and JAX's errors as a ValueError with the arguments' shapes), the user's own exception
    class comes through as itself, the shapes in a note, as it does from a later call."""
    calls = []

    def step(x, u, th):
        calls.append(1)
        if len(calls) == 1:
            raise LookupTableMissing("lookup table not loaded")
        return th["a"] * x + u

    with pytest.raises(LookupTableMissing, match="lookup table") as caught:
        oj.fit(oj.Model(step, lambda x, u, th: x), {"a": 0.3}, np.zeros(1), _U1, _Z1)
    assert any("a state of shape (1,)" in note for note in caught.value.__notes__)

    def step(x, u, th):  # (Python's own errors are still named with the shapes)
        return th["b"] * x + u

    with pytest.raises(ValueError, match=r"a state of shape \(1,\).*KeyError"):
        oj.fit(oj.Model(step, lambda x, u, th: x), {"a": 0.3}, np.zeros(1), _U1, _Z1)


def test_a_fixed_mask_must_have_its_parameters_shape():
    model = oj.Model(
        lambda x, u, th: jnp.stack([th["k"][0] * x[0] + th["k"][1] * u[0]]), lambda x, u, th: x
    )
    theta0 = {"k": np.array([0.5, 1.0])}
    with pytest.raises(ValueError, match=r"`fixed` entry of shape \(1,\) does not fit"):
        oj.fit(model, theta0, np.zeros(1), _U1, _Z1, fixed={"k": np.array([True])})
    r = oj.fit(model, theta0, np.zeros(1), _U1, _Z1, fixed={"k": np.array([False, True])})
    assert float(r.theta["k"][1]) == 1.0  # (the baseline: a mask of the leaf's shape)


def test_a_list_of_booleans_is_the_mask_of_an_array_theta():
    # (MATLAB's habit, a parameter vector and a vector of Fixed flags: a PyTreeDef message)
    model = oj.Model(lambda x, u, th: jnp.stack([th[0] * x[0] + th[1] * u[0]]), lambda x, u, th: x)
    theta0 = np.array([0.5, 1.0])
    r = oj.fit(model, theta0, np.zeros(1), _U1, _Z1, fixed=[False, True])
    assert float(r.theta[1]) == 1.0 and r.names == ("theta[0]",)
    np.testing.assert_array_equal(fixed_mask((True, False), jnp.asarray(theta0)), [True, False])
    np.testing.assert_array_equal(
        fixed_mask({"k": [False, True]}, {"k": theta0, "m": 1.0}), [False, True, False]
    )
    np.testing.assert_array_equal(fixed_mask([True, False], [theta0, 1.0]), [1, 1, 0])
    hint = (
        r"a boolean array of theta0's shape \(2,\) \(True where held\), "
        r"e.g. np.array\(\[True, False\]\)"
    )
    for bad in ([[True], [False, True]], {"a": True}):
        with pytest.raises(ValueError, match=rf"`fixed` must be a boolean, or {hint}; got"):
            fixed_mask(bad, theta0)
    with pytest.raises(ValueError, match=rf"names parameters \(\['k'\]\).*give {hint} instead"):
        fixed_mask("k", theta0)
    with pytest.raises(
        ValueError, match=r"entries must be booleans \(True where held\).*: \[1, 0\]"
    ):
        fixed_mask([1, 0], theta0)
    with pytest.raises(ValueError, match=r"`fixed` entry of shape \(1,\) does not fit"):
        fixed_mask([True], theta0)


def test_newey_west_lags_must_fit_the_shortest_record():
    with pytest.raises(ValueError, match=r"NeweyWest\(lags=15\)` exceeds .* the shortest, T = 10"):
        oj.fit(
            LIN,
            LIN_THETA,
            np.zeros((2, 1)),
            [_U1, _U1[:10]],
            [_Z1, _Z1[:10]],
            covariance=oj.NeweyWest(15),
        )


def test_a_host_solve_inside_a_transformation_says_so():
    import jax

    def inside(a):
        model = oj.Model(lambda x, u, th: th["a"] * a * x + u, lambda x, u, th: x)
        return oj.fit(model, {"a": 0.5}, np.zeros(1), _U1, _Z1).loss

    if not oj.internal.jit_module.compiler_options():
        pytest.skip("the message comes from JAX's refusal of compiler options (CPU)")
    with pytest.raises(ValueError, match=r"called inside a JAX transformation"):
        jax.jit(inside)(1.0)


@pytest.mark.parametrize(
    "path,error",
    [(3, TypeError), ("", ValueError), ("/a\0b", ValueError)],
)
def test_compilation_cache_names_a_bad_path(path, error):
    with pytest.raises(error, match=r"`path`"):
        oj.enable_compilation_cache(path)


def test_compilation_cache_refuses_a_folder_it_cannot_create(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=r"`path`"):
        oj.enable_compilation_cache(tmp_path / "file" / "sub")


def test_scores_and_residual_analysis_name_bad_records():
    z = np.random.default_rng(0).standard_normal((60, 1))
    with pytest.raises(ValueError, match=r"is it transposed"):
        oj.metrics.benchmark_scores(z.T, z.T, n=0)
    with pytest.raises(TypeError, match=r"complex"):
        oj.metrics.benchmark_scores(z + 1j, z, n=5)
    with pytest.raises(ValueError, match=r"`e` must hold real numbers"):
        oj.metrics.residual_correlations(z + 1j, None, 5)
    e = z.copy()
    e[3] = np.inf
    with pytest.raises(ValueError, match=r"`e` contains inf values"):
        oj.metrics.residual_correlations(e, None, 5)
    with pytest.raises(TypeError, match=r"`demean` must be True or False"):
        oj.metrics.residual_correlations(z, None, 5, demean="no")


def test_head_and_noise_arguments_of_a_prediction_are_named(lin_result):
    with pytest.raises(ValueError, match=r"`z_head` must have 1 to 10 rows"):
        lin_result.predict(_U1[:10], _Z1[:20])
    with pytest.raises(ValueError, match=r"`z_head` must have 1 to 30 rows"):
        lin_result.predict(_U1, _Z1[:0])
    with pytest.raises(TypeError, match=r"`measurement_noise` must be a variance"):
        oj.estimate_x0(
            LIN,
            lin_result.theta,
            _U1,
            _Z1[:10],
            x0=np.zeros(1),
            method="smoother",
            measurement_noise=True,
        )


def test_a_record_without_a_measured_sample_is_named():
    z = np.stack([_Z1, np.full_like(_Z1, np.nan)])
    u = np.stack([_U1, _U1])
    with pytest.raises(ValueError, match=r"trajectory \[1\] \(first axis\) has no measured"):
        oj.loss(LIN, LIN_THETA, np.zeros((2, 1)), u, z, missing="mask")


def test_errors_name_the_argument_the_caller_passed():
    """`FitResult.predict(u, z_head)` reported a head of the wrong width or with NaN as
    "`z` ...", and `fit` a NaN in theta0 as "`theta` ...": arguments the caller does not
    have."""
    r = oj.fit(MODEL, THETA, X0, U, Z, solver=oj.GaussNewton(max_steps=2))
    with pytest.raises(ValueError, match=r"^`z_head` must have shape \(3, 2\)"):
        r.predict(U, np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"^`z_head` contains NaN"):
        r.predict(U, np.where(np.arange(3)[:, None] == 1, np.nan, np.asarray(Z)[:3]))
    with pytest.raises(ValueError, match=r"^`theta0` contains NaN"):
        oj.fit(MODEL, {**THETA, "a": np.nan}, X0, U, Z)
    with pytest.raises(ValueError, match=r"^`theta0` contains NaN"):
        oj.fit(MODEL, {**THETA, "a": np.nan}, X0, U, Z, window=3)


def test_a_nested_parameter_takes_its_dotted_name_and_its_nested_dict_alike():
    """`units` took only the dotted name of a nested parameter ("phys.a", as the printout
    shows it), `fixed` and the bounds only the nested dict: each refused the other's."""

    def nested_step(x, u, theta):
        return theta["phys"]["a"] * jnp.tanh(x) + theta["B"] @ u

    model = oj.Model(nested_step, observe)
    theta = {"phys": {"a": jnp.asarray(0.9), "c": jnp.asarray(0.0)}, "B": THETA["B"]}
    solver = oj.GaussNewton(max_steps=3)
    kw = dict(solver=solver, estimate_x0=False)
    fits = [
        oj.fit(
            model,
            theta,
            X0,
            U,
            Z,
            fixed=fixed,
            constraints=oj.constraints.box(upper=upper),
            units=units,
            **kw,
        )
        for fixed, upper, units in (
            ({"phys": {"c": True}}, {"phys": {"a": 0.5}}, {"phys": {"a": "1/s"}}),
            ({"phys.c": True}, {"phys.a": 0.5}, {"phys.a": "1/s"}),
        )
    ]
    for r in fits:
        assert float(r.theta["phys"]["a"]) == 0.5 and float(r.theta["phys"]["c"]) == 0.0
        assert "1/s" in str(r)
    assert np.array_equal(np.asarray(fits[0].fixed), np.asarray(fits[1].fixed))
    assert str(fits[0]).split("\n")[3:] == str(fits[1]).split("\n")[3:]
    with pytest.raises(ValueError, match="`fixed` names a parameter twice"):
        oj.fit(model, theta, X0, U, Z, fixed={"phys.c": True, "phys": {"c": False}}, **kw)
    with pytest.raises(
        ValueError, match=r"`lower` names parameters .*\['x'\]; theta has \['a', 'c'\]"
    ):
        oj.constraints.box(lower={"phys.x": 0.0}).bounds(theta)


def test_a_model_that_indexes_past_the_end_of_an_array_is_refused():
    """A model reading u[1] of a record with one input column ran without an error (JAX
    clamps the index: u[1] read u[0]) and the fit 'converged' on a wrong model. Constant
    indices past the end of u, x or a parameter are refused, in every entry point;
    indices computed from the data, and those in range, are not."""

    def reads(index_u=0, index_x=1, index_b=0):
        def step(x, u, th):
            return jnp.stack([x[index_x], -th["k"] * x[0] + th["b"][index_b] * u[index_u]])

        return oj.Model(step, lambda x, u, th: x[:1])

    theta = {"k": 0.5, "b": jnp.ones(2)}
    x0, u = np.zeros(2), np.ones((5, 1))
    z = np.zeros((5, 1))
    oj.simulate(reads(), theta, x0, u)  # in range
    for model, what in (
        (reads(index_u=1), r"index 1 on axis 0 of an array of shape \(1,\)"),
        (reads(index_u=-2), r"index -1 on axis 0 of an array of shape \(1,\)"),
        (reads(index_x=2), r"index 2 on axis 0 of an array of shape \(2,\)"),
        (reads(index_b=2), r"index 2 on axis 0 of an array of shape \(2,\)"),
    ):
        for call in (
            lambda: oj.simulate(model, theta, x0, u),
            lambda: oj.fit(model, theta, x0, u, z),
            lambda: oj.loss(model, theta, x0, u, z),
        ):
            with pytest.raises(ValueError, match="indexes past the end of an array: " + what):
                call()
    two = reads(index_u=1)
    _, z2 = oj.simulate(two, theta, x0, np.ones((5, 2)))  # two columns: in range
    ode = oj.Model.from_ode(
        lambda x, u, th: jnp.stack([x[1], -th["k"] * x[0] + u[1]]), 0.1, observe=lambda x, u, th: x
    )
    with pytest.raises(ValueError, match="indexes past the end"):
        oj.simulate(ode, {"k": 1.0}, x0, u)

    def by_state(x, u, th):  # an index computed from the state: not a constant
        table = th["table"]
        i = jnp.clip(jnp.floor(x[0]).astype(int), 0, 2)
        return jnp.stack([x[1], table[i] + u[0]])

    oj.simulate(oj.Model(by_state, lambda x, u, th: x), {"table": jnp.ones(3)}, x0, u)


def test_an_observe_that_slices_past_the_state_is_refused():
    """A slice past the state's end (x[2:3] of two states) is empty, not an index error:
    the output had n_z = 0 and the error blamed z's shape, (5, 0)."""
    model = oj.Model(lambda x, u, th: th["a"] * x, lambda x, u, th: x[2:3])
    x0, u, z = np.zeros(2), np.ones((5, 1)), np.zeros((5, 1))
    for call in (
        lambda: oj.simulate(model, {"a": 0.5}, x0, u),
        lambda: oj.fit(model, {"a": 0.5}, x0, u, z),
    ):
        with pytest.raises(ValueError, match=r"`model.observe` returned no output .* x\[2:3\]"):
            call()


def test_a_transposed_siso_record_names_the_array_that_is_transposed():
    """A SISO z given as (1, T) was blamed on u ("`u` ... is it transposed?"); a u given
    as (1, T) to a step that broadcasts b * u was reported as a wrong state shape of
    `model.step`; both transposed had no hint; a head (1, n) asked for shape (1, 1)."""
    model = oj.Model(lambda x, u, th: th["a"] * x[:1] + th["a"] * u, lambda x, u, th: x)
    u, z = np.ones((6, 1)), np.ones((6, 1))
    th, x0 = {"a": 0.5}, np.zeros(1)
    with pytest.raises(ValueError, match=r"is `z` transposed\?"):
        oj.loss(model, th, x0, u, z.T)
    with pytest.raises(ValueError, match=r"`u` of shape \(1, 6\) holds T = 1 samples"):
        oj.loss(model, th, x0, u.T, z)
    with pytest.raises(ValueError, match=r"`u` of shape \(1, 6\) holds T = 1 samples"):
        oj.simulate(model, th, x0, u.T)
    r = oj.fit(model, th, x0, u, z, solver=oj.GaussNewton(max_steps=2))
    with pytest.raises(ValueError, match=r"`z_head` must have shape \(4, 1\).*transposed"):
        r.predict(u, z[:4].T)


def test_missing_mask_under_jit_and_vmap_masks_the_nan():
    # z traced (jit, vmap): its NaN are masked in the trace, as on the host.
    model = oj.Model(lambda x, u, th: jnp.array([th["a"] * x[0] + u[0]]))
    rng = np.random.default_rng(0)
    u, z = rng.standard_normal((30, 1)), rng.standard_normal((30, 1))
    z[3] = np.nan
    th, x0 = {"a": 0.7}, np.ones(1)
    C = oj.loss(model, th, x0, u, z, missing="mask")
    assert np.isfinite(C)
    assert jax.jit(lambda z: oj.loss(model, th, x0, u, z, missing="mask"))(z) == C
    g = oj.value_and_grad(model, th, x0, u, z, missing="mask")[1][0]["a"]
    g_jit = jax.jit(lambda z: oj.value_and_grad(model, th, x0, u, z, missing="mask"))(z)
    assert g_jit[1][0]["a"] == g
    Cs = jax.vmap(lambda z: oj.loss(model, th, x0, u, z, missing="mask"))(np.stack([z, z]))
    np.testing.assert_allclose(Cs, [C, C], rtol=1e-14)  # (a batched sum: round-off)


@pytest.mark.parametrize("name", ["estimate_x0", "predict"])
def test_estimate_x0_and_predict_inside_a_transformation_say_so(name):
    model = oj.Model(lambda x, u, th: th["a"] * x + u)
    call = {
        "estimate_x0": lambda z: oj.estimate_x0(model, {"a": 0.5}, _U1[:5], z[:5]).x0,
        "predict": lambda z: oj.predict(model, {"a": 0.5}, _U1, z, 5).z,
    }[name]
    with pytest.raises(TypeError, match=rf"`{name}` runs outside JAX transformations"):
        jax.jit(call)(_Z1)


def test_a_theta_whose_keys_do_not_sort_is_named():
    """{0: ..., "b": ...}: JAX's "Comparator raised exception while sorting pytree
    dictionary keys" named no argument, in fit, simulate and estimate_x0 alike."""
    model = oj.Model(lambda x, u, th: th[0] * x + th["b"] * u)
    theta = {0: 0.5, "b": 1.0}
    u, z = np.ones((10, 1)), np.ones((10, 1))
    with pytest.raises(ValueError, match=r"`theta0` must be a pytree that JAX can flatten"):
        oj.fit(model, theta, np.zeros(1), u, z)
    with pytest.raises(ValueError, match=r"`theta` must be a pytree that JAX can flatten"):
        oj.simulate(model, theta, np.zeros(1), u)
    with pytest.raises(ValueError, match=r"`theta` must be a pytree that JAX can flatten"):
        oj.estimate_x0(model, theta, u, z)


def test_a_custom_vjp_in_the_model_names_forward_mode():
    """A step with a `jax.custom_vjp` (a straight-through rounding) failed with JAX's bare
    "can't apply forward-mode autodiff (jvp) to a custom_vjp function" from deep inside
    the default fit and the default gradient; now a TypeError says what needs forward
    mode and what to do. The reverse-mode gradient still works."""

    @jax.custom_vjp
    def ste_round(x):
        return jnp.round(x)

    ste_round.defvjp(lambda x: (jnp.round(x), None), lambda _, g: (g,))
    model = oj.Model(lambda x, u, th: 0.5 * x + th["a"] * ste_round(4 * x) / 4 + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((20, 1))
    theta, x0 = {"a": 0.3, "b": 0.7}, np.array([0.1])
    _, z = oj.simulate(model, theta, x0, u)
    advice = r"custom_vjp.*forward mode.*`jax\.custom_jvp`"
    with pytest.raises(TypeError, match=advice):
        oj.fit(model, theta, x0, u, np.asarray(z) + 0.1)
    with pytest.raises(TypeError, match=advice) as raised:
        oj.value_and_grad(model, theta, x0, u, np.asarray(z) + 0.1)
    assert str(raised.value).count("Define that function's derivative") == 1  # (said once)
    C, (g, _) = oj.value_and_grad(model, theta, x0, u, np.asarray(z) + 0.1, strategy="vjp")
    assert np.isfinite(C) and np.isfinite(float(g["a"]))


def test_a_while_loop_in_the_model_names_reverse_mode():
    """A step that solves its implicit equation by Newton iterations in a
    `lax.while_loop` (backward Euler): the gradient failed with JAX's bare
    "Reverse-mode differentiation does not work for lax.while_loop", which names neither
    the model nor a remedy; now a ValueError says what needs reverse mode and what to
    use. The same step with a fixed count of iterations (`fori_loop`) fits."""
    dt = 0.05

    def step_of(loop):
        def step(x, u, th):
            def g(y):
                return y - x - dt * (-th["k"] * y**3 + th["b"] * u[0])

            def newton(y):
                return y - g(y) / (1.0 + 3 * dt * th["k"] * y**2)

            return loop(x, newton, g)

        return step

    def until_small(x, newton, g):
        return jax.lax.while_loop(lambda y: jnp.any(jnp.abs(g(y)) > 1e-13), newton, x)

    def twelve_times(x, newton, g):
        return jax.lax.fori_loop(0, 12, lambda i, y: newton(y), x)

    u = 3 * np.sin(0.05 * np.arange(100))[:, None]
    theta, x0 = {"k": 5.0, "b": 1.0}, np.array([0.5])
    fixed = oj.Model(step_of(twelve_times))
    _, z = oj.simulate(fixed, theta, x0, u)
    start = {"k": 2.0, "b": 0.5}
    with pytest.raises(ValueError, match=r"while_loop.*reverse mode.*`lax\.custom_root`"):
        oj.fit(oj.Model(step_of(until_small)), start, x0, u, z, solver="lbfgs")
    r = oj.fit(fixed, start, x0, u, z, solver="lbfgs")
    assert r.success and float(r.theta["k"]) == pytest.approx(5.0, rel=1e-4)


def test_a_pure_callback_without_a_vmap_method_names_it():
    """A step that calls NumPy through `jax.pure_callback` without a `vmap_method`: `fit`
    failed with JAX's bare "vmap is only supported for the pure_callback primitive when
    vmap_method is one of ..." from 29 frames deep; now the error says where the library
    maps the model and what to pass. `simulate` (no vmap) still works."""

    def cube(a):
        return jax.pure_callback(lambda b: np.asarray(b**3, b.dtype), a, a)

    model = oj.Model(lambda x, u, th: 0.5 * x - th["a"] * cube(x) + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((20, 1))
    theta, x0 = {"a": 0.1, "b": 0.7}, np.array([0.1])
    _, z = oj.simulate(model, theta, x0, u)
    with pytest.raises(NotImplementedError, match=r'pure_callback.*vmap_method="sequential"'):
        oj.fit(model, theta, x0, u, np.asarray(z) + 0.1)


def test_a_probe_s_misuses_name_their_argument(tmp_path):
    """A bool in theta0 was held fixed silently (a Python int is estimated); loss and
    value_and_grad without z failed inside a trace ('BatchTracer' - 'NoneType'); a save
    into a missing folder raised FileNotFoundError."""
    model = oj.Model(lambda x, u, th: th["a"] * 0.5 * x + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((30, 1))
    _, z = oj.simulate(model, {"a": 1.0, "b": 0.5}, np.zeros(1), u)
    with pytest.warns(UserWarning, match=r"theta0\['a'\] \(bool\).*held fixed as data"):
        r = oj.fit(model, {"a": True, "b": 0.4}, np.zeros(1), u, np.asarray(z))
    assert r.names == ("b",)
    for fn in (oj.loss, oj.value_and_grad):
        with pytest.raises(ValueError, match="`z` is required"):
            fn(model, {"a": 1.0, "b": 0.5}, np.zeros(1), u, None)
    with pytest.raises(ValueError, match="`path`: the folder .* does not exist"):
        r.save(tmp_path / "missing" / "r.npz")


def test_keywords_and_a_transposed_head_are_named_where_they_were_given():
    """Unknown keywords of `fit_continuation` and `check_basin` were reported as
    `fit()`'s; a transposed z in `predict` was blamed on `n`."""
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 0.5, "b": 1.0}, np.zeros(1), u)
    z = np.asarray(z)
    with pytest.raises(TypeError, match=r"`fit_continuation` got unexpected .*\['solvr'\]"):
        oj.fit_continuation(model, {"a": 0.4, "b": 0.9}, np.zeros(1), u, z, solvr="lm")
    r = oj.fit(model, {"a": 0.4, "b": 0.9}, np.zeros(1), u, z)
    with pytest.raises(TypeError, match=r"`check_basin` got unexpected .*\['foo'\]"):
        oj.check_basin(r, u, z, window=10, foo=1)
    with pytest.raises(ValueError, match=r"is `z` transposed\? it has shape \(1, 40\)"):
        oj.predict(model, r.theta, u, z.T, 5, x0=np.zeros(1))


def test_a_z_of_the_wrong_size_names_the_argument_it_disagrees_with():
    """A `z` whose samples differ from `u`'s, or whose outputs differ from the state
    observed whole (no `observe`: n_z is x0's size), named only `z`'s expected shape."""
    model = oj.Model(lambda x, u, th: th["a"] * x + u[0])
    u, z = np.ones((20, 1)), np.ones((20, 2))
    with pytest.raises(ValueError, match=r"`u` holds T = 10 samples and `z` 20"):
        oj.loss(model, {"a": 0.5}, np.zeros(2), u[:10], z)
    with pytest.raises(ValueError, match=r"n_z is the size of `x0`, 3; is `x0` of the right"):
        oj.loss(model, {"a": 0.5}, np.zeros(3), u, z)
    with pytest.raises(ValueError, match=r"got shape \(20, 3\)\.$"):  # observe given: no hint
        oj.loss(MODEL, THETA, X0, np.ones((20, N_U)), np.ones((20, 3)))


@pytest.mark.parametrize(
    "update",
    [
        lambda g: {"theta": g["theta"]},  # x0 dropped
        lambda g: jax.tree.map(lambda x: jnp.stack([x, x]), g),  # shapes changed
    ],
    ids=["drops-x0", "changes-shapes"],
)
def test_an_optax_transform_whose_update_does_not_match_the_parameters_is_named(update):
    """Such an update failed deep inside JAX ("pytree structure error", "Sum of sizes 3
    must be equal to dimension 0")."""
    import optax

    bad = optax.GradientTransformation(
        lambda p: optax.EmptyState(), lambda g, s, p=None: (update(g), s)
    )
    with pytest.raises(ValueError, match=r"`Optax\(transform\)`: the transform's update must"):
        oj.fit(MODEL, THETA, X0, U, Z, solver=oj.Optax(bad, max_steps=3))


def test_a_fit_result_given_as_theta_names_its_theta():
    """nlgreyest's habit, `fit(model, estimated, ...)`: the FitResult is named, with its
    `theta` (and for `fit`, its `x0`) to pass; it failed on a string inside the result
    ("`theta0` must hold real numbers, got 'auto'")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = oj.fit(
            MODEL, THETA, jnp.zeros(N_X), U, Z, solver=oj.LevenbergMarquardt(max_steps=2)
        )
    with pytest.raises(
        TypeError, match=r"`theta0` is a FitResult: .*`result.theta` and `result.x0`"
    ):
        oj.fit(MODEL, result, jnp.zeros(N_X), U, Z)
    with pytest.raises(
        TypeError, match=r"`theta` is a FitResult: pass its parameters, `result.theta` \("
    ):
        oj.simulate(MODEL, result, jnp.zeros(N_X), U)


def _lag_with_offset(x, u, th):
    return th["a"] * x + th["b"] * u


def test_outputs_rounded_to_float32_below_their_noise_are_warned_of():
    """x64 off and float64 outputs of offset 300 with noise 1e-6, below float32's
    resolution of them (3e-5): the float32 fit read the rounded outputs exactly (loss 0,
    every std 0, "converged", the estimate 3 standard errors from float64's) without a
    word. It warns, and keeps the warning in the result; the same data given in float32
    (nothing rounded by the fit) and a float64 fit do not."""
    import jax

    model = oj.Model(_lag_with_offset, lambda x, u, th: x + th["c"])
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    with jax.enable_x64(True):
        _, z = oj.simulate(model, {"a": 0.8, "b": 1.0, "c": 300.0}, np.zeros(1), u)
    z = np.asarray(z, np.float64) + 1e-6 * rng.standard_normal((200, 1))
    theta0 = {"a": 0.7, "b": 0.9, "c": 299.0}
    with jax.enable_x64(False), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = oj.fit(model, theta0, np.zeros(1), u, z)
        said = [str(w.message) for w in caught if "rounding them changed" in str(w.message)]
        assert len(said) == 1 and said[0] in r.warnings
        assert said[0].startswith("the outputs were given in float64 and the fit ran in float32")
        mine = oj.fit(model, theta0, np.zeros(1), u.astype(np.float32), z.astype(np.float32))
        assert not [w for w in mine.warnings if "rounding them changed" in w]
    with jax.enable_x64(True):
        wide = oj.fit(model, theta0, np.zeros(1), u, z)
    assert wide.success and not [w for w in wide.warnings if "rounding them changed" in w]


class _Series:
    """An array of another library (a pandas Series, say): NumPy reads it through
    `__array__`; to JAX it is an opaque leaf."""

    def __init__(self, a):
        self._a = np.asarray(a)

    def __array__(self, dtype=None, copy=None):
        return self._a if dtype is None else self._a.astype(dtype)


@pytest.mark.parametrize("entry", ENTRY_POINTS + ["fit"])
def test_a_parameter_of_another_array_library_is_refused_by_name(entry):
    """A theta leaf (or theta itself) that is an array of another library: a TypeError
    naming the leaf and the fix, where it was held with the model and refused as "`step`
    must be hashable ... got an unhashable" object."""
    theta = {"a": _Series(0.9), "B": THETA["B"]}
    where = "theta0" if entry == "fit" else "theta"
    for bad, name in ((theta, rf"`{where}\['a'\]`"), (_Series([0.9]), rf"`{where}`")):
        with pytest.raises(TypeError, match=rf"{name} is a _Series, not a parameter .*to_numpy"):
            if entry == "fit":
                oj.fit(MODEL, bad, X0, U, Z)
            else:
                call(entry, theta=bad)


def test_the_model_check_reads_the_x64_switch_of_each_call():
    """A step with a constant of JAX's default dtype (`jnp.zeros(1)`) on float32 data: with
    x64 on it promotes the state to float64 (refused), with x64 off it keeps float32
    (accepted). The check's cache was keyed without the switch: after a call with x64 on,
    one with it off was refused as well, which a fresh process accepts."""
    model = oj.Model(lambda x, u, th: th["a"] * x + u + jnp.zeros(1))
    theta = {"a": np.float32(0.9)}
    x0, u = np.ones(1, np.float32), np.ones((5, 1), np.float32)
    assert jax.config.jax_enable_x64
    with pytest.raises(ValueError, match="must keep the state's dtype float32"):
        oj.simulate(model, theta, x0, u)
    try:
        jax.config.update("jax_enable_x64", False)
        _, z = oj.simulate(model, theta, x0, u)
        assert z.dtype == np.float32
    finally:
        jax.config.update("jax_enable_x64", True)
