"""Operating points: `find_equilibrium` (MATLAB's `findop(sys, 'steady', u)`) and
`linearise` (MATLAB's `linearize`). References written here: the pendulum's equilibria
in closed form (sin q = u / w0^2), its Jacobians by hand, the RK4 step's Jacobian at an
equilibrium as RK4's stability polynomial of Ac h, and the nonlinear simulation of small
deviations."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

DT = 0.05
THETA = {"w0sq": 9.0, "b": 0.6}


def pendulum(x, u, th):
    return jnp.stack([x[1], -th["w0sq"] * jnp.sin(x[0]) - th["b"] * x[1] + u[0]])


def angle_and_torque(x, u, th):  # (an output that reads the input: D != 0)
    return jnp.stack([x[0], 0.5 * u[0] + 0.1 * x[1]])


def _model(**kwargs):
    return oj.Model.from_ode(pendulum, DT, observe=angle_and_torque, **kwargs)


def _rk4_step_jacobians(Ac, Bc, h, substeps):
    """A and B of `substeps` RK4 steps of h at an equilibrium under a held input: the
    stability polynomial P(M) = I + M + M^2/2 + M^3/6 + M^4/24 of M = Ac h per step, and
    B = sum_j A_h^j h (I + M/2 + M^2/6 + M^3/24) Bc."""
    eye = np.eye(len(Ac))
    M = Ac * h
    P = eye + M + M @ M / 2 + M @ M @ M / 6 + M @ M @ M @ M / 24
    G = h * (eye + M / 2 + M @ M / 6 + M @ M @ M / 24) @ Bc
    A, B = eye, np.zeros_like(G)
    for _ in range(substeps):
        A, B = P @ A, P @ B + G
    return A, B


@pytest.mark.parametrize("substeps", [1, 3])
def test_the_pendulums_equilibria_and_linear_models(substeps):
    """At the torque u, sin q = u / w0^2: from near 0 the hanging equilibrium, from near
    pi the upturned one (unstable: a pole outside the unit circle). Ac and Bc are the
    Jacobians by hand, A and B those of the model's RK4 steps, C and D of its outputs."""
    model = _model(substeps=substeps)
    u = np.array([3.0])
    for start, q in ((0.0, math.asin(3.0 / 9.0)), (3.0, math.pi - math.asin(3.0 / 9.0))):
        eq = oj.find_equilibrium(model, THETA, u, np.array([start, 0.5]))
        assert eq.success and "equilibrium" in eq.message, eq.message
        np.testing.assert_allclose(eq.x, [q, 0.0], atol=1e-14)
        np.testing.assert_allclose(eq.z, [q, 1.5], atol=1e-14)
        lin = oj.linearise(model, THETA, eq.x, u)
        Ac = np.array([[0.0, 1.0], [-9.0 * math.cos(q), -0.6]])
        Bc = np.array([[0.0], [1.0]])
        np.testing.assert_allclose(lin.Ac, Ac, atol=1e-14)
        np.testing.assert_allclose(lin.Bc, Bc, atol=1e-14)
        A, B = _rk4_step_jacobians(Ac, Bc, DT / substeps, substeps)
        np.testing.assert_allclose(lin.A, A, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(lin.B, B, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(lin.C, [[1.0, 0.0], [0.0, 0.1]])
        np.testing.assert_allclose(lin.D, [[0.0], [0.5]])
        assert lin.dt == DT
        unstable = np.max(np.abs(lin.poles)) > 1
        assert unstable == (start == 3.0)


def test_the_linear_model_predicts_small_deviations_to_second_order():
    """From the equilibrium plus dx0 under u + du (a varying du), the nonlinear simulation
    minus the operating point equals the linear model's response up to O(delta^2): half
    the deviations, a quarter of the difference."""
    model = _model()
    u = np.array([3.0])
    eq = oj.find_equilibrium(model, THETA, u, np.zeros(2))
    lin = oj.linearise(model, THETA, eq.x, u)
    T = 40
    shape_u = np.sin(0.3 * np.arange(T))[:, None]

    def difference(delta):
        dx0, du = delta * np.array([1.0, -0.5]), delta * shape_u
        _, z = oj.simulate(model, THETA, eq.x + dx0, u + du)
        dx, dz = dx0, []
        for k in range(T):
            dz.append(lin.C @ dx + lin.D @ du[k])
            dx = lin.A @ dx + lin.B @ du[k]
        return np.max(np.abs(np.asarray(z) - eq.z - np.array(dz)))

    big, small = difference(2e-3), difference(1e-3)
    assert 3.5 < big / small < 4.5 and small < 1e-5


def test_a_discrete_linear_model_is_its_own_linear_model():
    """A `Model(step)` with x[k+1] = F x + G u, z = H x + K u: A, B, C, D are F, G, H, K,
    no continuous-time part, and the equilibrium is (I - F)^{-1} G u."""
    F = np.array([[0.9, 0.2], [-0.1, 0.7]])
    G, H, K = np.array([[0.5], [1.0]]), np.array([[1.0, -1.0]]), np.array([[0.3]])
    model = oj.Model(lambda x, u, th: th["F"] @ x + G @ u, lambda x, u, th: H @ x + K @ u)
    u = np.array([2.0])
    eq = oj.find_equilibrium(model, {"F": F}, u, np.zeros(2))
    want = np.linalg.solve(np.eye(2) - F, G @ u)
    assert eq.success
    np.testing.assert_allclose(eq.x, want, rtol=1e-14)
    lin = oj.linearise(model, {"F": F}, np.array([0.3, -1.0]), u)
    for got, ref in ((lin.A, F), (lin.B, G), (lin.C, H), (lin.D, K)):
        np.testing.assert_allclose(got, ref, atol=1e-15)
    assert lin.Ac is None and lin.Bc is None and lin.dt is None
    np.testing.assert_allclose(np.sort_complex(lin.poles), np.sort_complex(np.linalg.eigvals(F)))


def _cart(x, u, th):
    return jnp.stack([x[1], -th["c"] * x[1] + u[0]])


def test_a_family_of_equilibria_keeps_the_start_and_none_is_said():
    """A cart: every position is an equilibrium at u = 0 (a rank-deficient Jacobian): the
    search keeps the start's position, or the one held. With c = 0 and a force, it has
    none: `success` False, the residual the force."""
    model = oj.Model.from_ode(_cart, DT)
    eq = oj.find_equilibrium(model, {"c": 0.4}, [0.0], np.array([0.7, 0.3]))
    assert eq.success
    np.testing.assert_allclose(eq.x, [0.7, 0.0], atol=1e-15)
    eq = oj.find_equilibrium(model, {"c": 0.4}, [0.0], np.array([-2.0, 0.3]),
                             hold=np.array([True, False]))  # fmt: skip
    assert eq.success and eq.x[0] == -2.0
    none = oj.find_equilibrium(model, {"c": 0.0}, [1.0], np.array([0.0, 0.3]))
    assert not none.success and "no equilibrium" in none.message
    assert none.residual == pytest.approx(1.0)
    held = oj.find_equilibrium(model, {"c": 0.4}, [0.0], np.array([0.0, 0.3]),
                               hold=np.array([False, True]))  # fmt: skip
    assert not held.success  # (v held at 0.3: the position moves)


def test_other_input_models_and_time_stamped_models():
    """A "foh" model's step reads u[k] and u[k + 1] (B0, B1): its linear model is the
    step's state-space form, B = B0 + A B1, D = D_g + C B1 for the state dx - B1 du,
    whose frequency response is the foh step's own (B was B0 + B1, an input held over
    the interval, whose response lags the foh model's by half a sample: 28.6 degrees at
    10 rad/s with dt = 0.1). A model of time-stamped records needs `dt` for A and B, and
    then gives the fixed-dt model's, and finds the same equilibria without it."""
    u, x = np.array([1.0]), np.array([0.2, 0.1])
    zoh = oj.linearise(_model(), THETA, x, u)
    model = _model(input="foh")
    foh = oj.linearise(model, THETA, x, u)
    np.testing.assert_allclose(foh.A, zoh.A, rtol=1e-13)
    assert zoh.B_next is None and "foh: state xi = dx - B_next du" in str(foh)
    pair = jnp.stack([jnp.asarray(u)] * 2)  # (u[k], u[k + 1])
    steps = np.asarray(jax.jacfwd(model.step, 1)(jnp.asarray(x), pair, THETA))
    B0, B1 = steps[:, 0, :1], steps[:, 1, :1]
    np.testing.assert_allclose(B0 + B1, zoh.B, rtol=1e-13)  # (a held input)
    np.testing.assert_allclose(foh.B_next, B1, rtol=1e-13)
    w = np.array([0.5, 3.0, 10.0, 40.0])
    exact = [
        foh.C @ np.linalg.solve(q * np.eye(2) - foh.A, B0 + q * B1) + zoh.D
        for q in np.exp(1j * w * DT)
    ]
    np.testing.assert_allclose(foh.frequency_response(w), exact, rtol=1e-12, atol=1e-15)
    timed = oj.Model.from_ode(pendulum, None, observe=angle_and_torque)
    lin = oj.linearise(timed, THETA, x, u, dt=DT)
    for a, b in zip(lin, zoh):
        if isinstance(a, np.ndarray):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-16)
    assert lin.dt == DT
    with pytest.raises(ValueError, match="`dt`"):
        oj.linearise(timed, THETA, x, u)
    with pytest.raises(ValueError, match="`dt`"):
        oj.linearise(_model(), THETA, x, u, dt=DT)
    eq = oj.find_equilibrium(timed, THETA, u, np.zeros(2))
    np.testing.assert_allclose(eq.x, [math.asin(1 / 9), 0.0], atol=1e-14)


def test_a_theta_holding_a_network():
    """A hybrid's theta (a physical parameter and an equinox MLP of the rate): the
    continuous-time Jacobians are those of `jax.jacfwd` of the rhs with the whole theta,
    and the equilibrium zeroes the rhs."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] + th["net"](x[1:])[0] + u[0]])

    net = eqx.nn.MLP(1, 1, 8, 1, key=jax.random.PRNGKey(0))
    net = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if eqx.is_array(a) else a, net)
    theta = {"k": 4.0, "net": net}
    model = oj.Model.from_ode(rhs, DT)
    eq = oj.find_equilibrium(model, theta, [0.5], np.zeros(2))
    assert eq.success
    assert np.max(np.abs(np.asarray(rhs(jnp.asarray(eq.x), jnp.array([0.5]), theta)))) < 1e-14
    lin = oj.linearise(model, theta, eq.x, [0.5])
    np.testing.assert_allclose(lin.Ac, jax.jacfwd(rhs)(jnp.asarray(eq.x), jnp.array([0.5]), theta),
                               rtol=1e-14)  # fmt: skip


def test_the_results_methods_use_the_fitted_theta_and_x0():
    rng = np.random.default_rng(0)
    model = _model()
    u = np.sin(0.3 * np.arange(80))[:, None]
    _, z = oj.simulate(model, THETA, np.array([0.3, 0.0]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))
    result = oj.fit(model, {"w0sq": 7.0, "b": 0.3}, np.array([0.3, 0.0]), u, z)
    eq = result.find_equilibrium([2.0])
    same = oj.find_equilibrium(model, result.theta, [2.0], result.x0)
    np.testing.assert_array_equal(eq.x, same.x)
    np.testing.assert_allclose(eq.x[0], math.asin(2.0 / result.theta["w0sq"]), atol=1e-14)
    lin = result.linearise(eq.x, [2.0])
    np.testing.assert_array_equal(lin.A, oj.linearise(model, result.theta, eq.x, [2.0]).A)
    with pytest.raises(ValueError, match="`x` must have the fitted state's n_x = 2"):
        result.linearise(np.zeros(3), [2.0])
    for call in (
        lambda: result.find_equilibrium([2.0, 1.0]),  # (the model reads u[0] alone)
        lambda: result.find_equilibrium(np.linspace(0.0, 2.0, 5)[None, :]),  # (transposed)
        lambda: result.linearise(eq.x, [2.0, 1.0]),
    ):
        with pytest.raises(ValueError, match="`u` must be the operating point's constant input"):
            call()
    # x and u swapped (it gave a record's hint, "(T, 1): u[:, None]"), an Equilibrium
    # where its state is meant (NumPy's inhomogeneous-shape error).
    with pytest.raises(ValueError, match=r"got shape \(2,\) \(are `x` and `u` swapped\?\)"):
        result.linearise([2.0], eq.x)
    with pytest.raises(TypeError, match=r"`x` is an Equilibrium: pass its state, `eq.x`"):
        result.linearise(eq, [2.0])


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda m: oj.find_equilibrium(m, THETA, np.ones((2, 1, 1)), np.zeros(2)), ValueError,
         r"`u` must be the constant input \(n_u,\) or a sweep"),
        (lambda m: oj.linearise(m, THETA, np.zeros(2), np.ones((2, 1))), ValueError,
         r"`u` must be the constant input, shape \(n_u,\)"),
        (lambda m: oj.find_equilibrium(m, THETA, [1.0], np.zeros((1, 2))), ValueError,
         r"`x` must be one state"),
        (lambda m: oj.find_equilibrium(m, THETA, [1.0], np.zeros(2), hold=[1, 0]), ValueError,
         "`hold` must be an"),
        (lambda m: oj.linearise(m, THETA, np.zeros(2), ["a"]), ValueError, "`u`"),
        (lambda m: oj.linearise(m, THETA, np.zeros(3), [1.0]), ValueError, "rhs"),
        # (x and u swapped: the order each takes them in is named)
        (lambda m: oj.linearise(m, THETA, [3.0], np.zeros(2)), ValueError,
         r"`x` \(shape \(1,\)\) and `u` \(shape \(2,\)\) do not fit the model "
         r"\(`linearise\(model, theta, x, u\)`: are they swapped\? they fit it the other "
         r"way round\)"),
        (lambda m: oj.find_equilibrium(m, THETA, np.zeros(2), [3.0]), ValueError,
         r"\(`find_equilibrium\(model, theta, u, x\)`: are they swapped\?"),
        # (a bad value or theta is named as such, not as a swap of x and u that fit)
        (lambda m: oj.find_equilibrium(m, THETA, [1.0], [np.inf, 0.0]), ValueError,
         r"^`x` contains NaN or inf values; the first is `x\[0\]`"),
        (lambda m: oj.linearise(m, THETA, np.zeros(2), [np.nan]), ValueError,
         r"^`u` contains NaN or inf values"),
        (lambda m: oj.linearise(m, {"w0sq": 9.0}, np.zeros(2), [1.0]), ValueError,
         r"do not fit the model; as a record's x0 and u"),
        (lambda m: oj.linearise(m, THETA, oj.find_equilibrium(m, THETA, [1.0], np.zeros(2)),
                                [1.0]), TypeError, "`x` is an Equilibrium"),
        (lambda m: oj.linearise(m, THETA, np.zeros(2), [1.0]).frequency_response(
            [1.0], continuous="no"), TypeError, "`continuous` must be True or False"),
        (lambda m: oj.find_equilibrium(pendulum, THETA, [1.0], np.zeros(2)), TypeError,
         "`model` must be a oneshot_jax.Model, got function"),
        (lambda m: oj.linearise(None, THETA, np.zeros(2), [1.0]), TypeError,
         "`model` must be a oneshot_jax.Model"),
        (lambda m: oj.find_equilibrium(m, THETA, [[1.0], [2.0, 3.0]], np.zeros(2)), ValueError,
         "`u` must hold real numbers"),
    ],
)  # fmt: skip
def test_bad_arguments_are_named(call, error, match):
    with pytest.raises(error, match=match):
        call(_model())


def test_frequency_responses():
    """A first-order lag dx/dt = -a x + a u, z = x: continuous H = a / (j w + a); the
    discrete one of its Euler step (A = 1 - a dt, B = a dt) is a dt / (e^{j w dt} - 1 +
    a dt), which tends to the continuous one at low frequency."""
    a, dt = 2.0, 0.01
    model = oj.Model.from_ode(lambda x, u, th: th * (u - x), dt, method="euler")
    lin = oj.linearise(model, a, np.zeros(1), np.zeros(1))
    w = np.array([0.0, 0.5, 2.0, 20.0])
    np.testing.assert_allclose(lin.frequency_response(w, continuous=True)[:, 0, 0],
                               a / (1j * w + a), rtol=1e-14)  # fmt: skip
    discrete = lin.frequency_response(w)[:, 0, 0]
    np.testing.assert_allclose(discrete, a * dt / (np.exp(1j * w * dt) - 1 + a * dt), rtol=1e-12)
    np.testing.assert_allclose(discrete[:3], a / (1j * w[:3] + a), rtol=2e-2)
    assert lin.frequency_response(w).shape == (4, 1, 1)
    with pytest.raises(ValueError, match="`continuous=True` needs"):
        oj.linearise(oj.Model(lambda x, u, th: th * x), 0.5, np.ones(1), np.zeros(0)
                     ).frequency_response(w, continuous=True)  # fmt: skip
    # With input="foh" the sampled model's D holds C B1 besides the observation's own
    # feedthrough; the continuous-time response added it too (a gain of 0.05 at 1e6 rad/s
    # for the angle, which reads no input).
    foh = oj.linearise(_model(input="foh"), THETA, np.array([0.2, 0.0]), np.array([1.0]))
    assert np.any(np.abs(foh.C @ foh.B_next) > 1e-3)  # (the term that was added)
    w = np.array([0.0, 1.0, 3.0, 1e6])
    X = np.linalg.solve(1j * w[:, None, None] * np.eye(2) - foh.Ac, foh.Bc)
    np.testing.assert_allclose(foh.frequency_response(w, continuous=True),
                               foh.C @ X + foh.D_observe, rtol=1e-13, atol=1e-15)  # fmt: skip
    np.testing.assert_array_equal(foh.D_observe, [[0.0], [0.5]])
    assert abs(foh.frequency_response([1e9], continuous=True)[0, 0, 0]) < 1e-8
    # A frequency on a pole (an integrator's w = 0) gives an infinite H (as `freqresp`).
    one, zero = np.ones((1, 1)), np.zeros((1, 1))
    integrator = oj.LinearModel(one, 2 * one, one, zero, None, None, 0.1, np.zeros(1), np.zeros(1))
    H = integrator.frequency_response([0.0, 1.0])[:, 0, 0]
    assert np.isinf(H[0]) and H[1] == pytest.approx(2 / (np.exp(0.1j) - 1), rel=1e-14)
    for bad, error in (([1 + 2j], ValueError), ([True, False], TypeError), ([], ValueError),
                       ("abc", ValueError), ([[1.0]], ValueError)):  # fmt: skip
        with pytest.raises(error, match="`w` must"):
            integrator.frequency_response(bad)


def test_bode_draws_the_gain_and_phase_of_the_frequency_response():
    """`plot.bode` draws 20 log10 |H| and the unwrapped phase of H in degrees against w
    on a log axis, one line per model; the default frequencies run up to pi / dt."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = _model()
    rest = oj.linearise(model, THETA, np.zeros(2), np.zeros(1))
    tilted = oj.linearise(model, THETA, np.array([0.5, 0.0]), np.zeros(1))
    fig = oj.plot.bode(rest, tilted, labels=["rest", "tilted"])
    gain, phase = fig.axes
    assert gain.get_xscale() == "log" and len(gain.lines) == 2 * 2  # (2 outputs, 1 input)
    w, db = gain.lines[0].get_data()
    H = rest.frequency_response(w)[:, 0, 0]
    np.testing.assert_allclose(db, 20 * np.log10(np.abs(H)), rtol=1e-12)
    np.testing.assert_allclose(phase.lines[0].get_ydata(), np.degrees(np.unwrap(np.angle(H))))
    assert w[-1] == pytest.approx(np.pi / DT)
    assert gain.lines[2].get_label() == "tilted z[0] <- u[0]"
    plt.close(fig)
    fig = oj.plot.bode([rest, tilted])  # (a list, as MATLAB's bode(sys1, sys2) users pass)
    assert len(fig.axes[0].lines) == 4
    plt.close(fig)
    fig = oj.plot.bode(rest, w=np.array([1.0, 2.0]), continuous=True)
    np.testing.assert_allclose(
        fig.axes[0].lines[0].get_ydata(),
        20 * np.log10(np.abs(rest.frequency_response([1.0, 2.0], continuous=True)[:, 0, 0])),
    )
    plt.close(fig)
    with pytest.raises(TypeError, match=r"`models\[0\]` must be a `LinearModel`"):
        oj.plot.bode(rest.A)
    with pytest.raises(ValueError, match="positive angular frequencies"):
        oj.plot.bode(rest, w=[0.0, 1.0])
    # A model of its own step (no dt: radians per sample) beside an ODE model's (radians
    # per time unit): one axis cannot carry both (its curve was drawn per time unit on
    # an axis labelled per sample).
    one, zero = np.ones((1, 1)), np.zeros((1, 1))
    per_second = oj.LinearModel(one, one, one, zero, None, None, 0.1, np.zeros(1), np.zeros(1))
    per_sample = oj.LinearModel(one, one, one, zero, None, None, None, np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match="`models` mix frequency units"):
        oj.plot.bode(per_second, per_sample)
    # A pair without a path from input to output (x[0] is driven by u[0] alone; z = x)
    # is left out, and the legend says so.
    two = oj.LinearModel(np.array([[0.9, 0.0], [0.3, 0.5]]), np.eye(2), np.eye(2),
                         np.zeros((2, 2)), None, None, 0.1, np.zeros(2), np.zeros(2))  # fmt: skip
    fig = oj.plot.bode(two)
    labels = [line.get_label() for line in fig.axes[0].lines]
    assert labels == ["model z[0] <- u[0]", "model z[0] <- u[1]: no response (zero)",
                      "model z[1] <- u[0]", "model z[1] <- u[1]"]  # fmt: skip
    assert len(fig.axes[1].lines) == 3
    plt.close(fig)
    step_only = two._replace(Ac=None)
    with pytest.raises(ValueError, match="`continuous=True` needs models built from an ODE"):
        oj.plot.bode(step_only, continuous=True)


def test_a_sweep_of_inputs_follows_one_branch():
    """u from 0 to 8.5 (below w0^2 = 9): each equilibrium continued from the one before
    stays on the hanging branch, asin(u / 9); beyond u = 9 there is none, and the next
    row starts again from `x`."""
    model = _model()
    sweep = np.linspace(0.0, 8.5, 12)[:, None]
    eqs = oj.find_equilibrium(model, THETA, sweep, np.array([0.2, 0.0]))
    assert all(e.success for e in eqs)
    np.testing.assert_allclose([e.x[0] for e in eqs], np.arcsin(sweep[:, 0] / 9.0), atol=1e-13)
    np.testing.assert_array_equal(eqs[5].x, oj.find_equilibrium(model, THETA, sweep[5], eqs[4].x).x)
    past = oj.find_equilibrium(model, THETA, np.array([[8.0], [9.5], [3.0]]), np.zeros(2))
    assert [e.success for e in past] == [True, False, True]
    np.testing.assert_allclose(past[2].x, [math.asin(3.0 / 9.0), 0.0], atol=1e-14)


def test_a_far_start_neither_passes_a_non_equilibrium_nor_stops_short():
    """The success threshold was sqrt(eps) times the residual at the start plus |J| |x|:
    just past the pendulum's fold (u = 9 + 1e-7, where sin q = u / w0^2 has no solution)
    the least-squares point, residual 1e-7, read success from a start of residual 9; and
    dx/dt = u - (x - 1000)^2 at u = -1e-3 (no equilibrium) read success from x = 0 and
    failure from x = 999, at the same point. The search also stopped short of the
    equilibrium from a far start (dx/dt = 1 - exp(x) from x = 35: x = 0.108, success)."""
    past = oj.find_equilibrium(_model(), THETA, np.array([9.0 + 1e-7]), np.zeros(2))
    assert not past.success and past.residual == pytest.approx(1e-7, rel=1e-3)
    quadratic = oj.Model.from_ode(lambda x, u, th: u - (x - 1000.0) ** 2, DT)
    for start in (999.0, 0.0):
        eq = oj.find_equilibrium(quadratic, {}, np.array([-1e-3]), np.array([start]))
        assert not eq.success and eq.residual == pytest.approx(1e-3, rel=1e-6)
        assert eq.message.startswith("no equilibrium reached")
    exponential = oj.Model.from_ode(lambda x, u, th: u - jnp.exp(x), DT)
    eq = oj.find_equilibrium(exponential, {}, np.array([1.0]), np.array([35.0]))
    assert eq.success and abs(float(eq.x[0])) < 1e-14


def test_each_equation_is_at_round_off_on_its_own_scale():
    """A level h in m that integrates inflow minus outflow, next to a pressure p in Pa that
    lags 1e5 + rho g h: with the inflow above the outflow there is no equilibrium (h
    rises for ever), but one scale for both equations (the largest row sum of |J| times
    the largest |x|, 1e4 x 1e5) passed a residual dh/dt of 1 m/s as round-off. Each
    equation is now held to its own scale; with the flows balanced it is an equilibrium."""

    def tank(x, u, th):
        return jnp.stack([u[0] - u[1], (1e5 + 1000.0 * 9.81 * x[0] - x[1]) / th["tau"]])

    model = oj.Model.from_ode(tank, 1.0)
    for imbalance in (1e-2, 1.0):
        eq = oj.find_equilibrium(model, {"tau": 1.0}, [0.1 + imbalance, 0.1], [1.0, 1.1e5])
        assert not eq.success and eq.residual == pytest.approx(imbalance, rel=1e-9)
    eq = oj.find_equilibrium(model, {"tau": 1.0}, [0.1, 0.1], [1.0, 1.0e5], hold=[True, False])
    assert eq.success and eq.x[1] == pytest.approx(1e5 + 9810.0, rel=1e-14)
    # An equation of held entries alone is held to the scale of its terms too (with the
    # held columns left out of the scale, a residual at round-off, 1e-16 here, read as
    # no equilibrium).
    torricelli = oj.Model.from_ode(
        lambda x, u, th: jnp.stack(
            [u[0] - th["k"] * jnp.sqrt(x[0]), (1e5 + 1000.0 * 9.81 * x[0] - x[1]) / th["tau"]]
        ),
        1.0,
    )
    theta, u = {"k": 0.1, "tau": 1.0}, [0.1 * np.sqrt(2.0) * (1.0 + 4e-16)]
    eq = oj.find_equilibrium(torricelli, theta, u, [2.0, 1e5], hold=[True, False])
    assert eq.success and 1e-17 < eq.residual < 1e-15


def test_a_timed_step_of_ones_own_needs_the_interval_of_its_fixed_points():
    """x+ = e^{-h} x + u, h the interval a `Model(step, timed=True)` sees: its fixed point
    u / (1 - e^{-h}) depends on h, and `find_equilibrium` took h = 1 without a word. It
    now takes `dt` (needed there); an ODE's zeros of rhs need none."""
    dose = oj.Model(lambda x, u, th: jnp.exp(-u[-1]) * x + u[0], timed=True)
    with pytest.raises(ValueError, match="`dt` .* is needed for a model of time-stamped"):
        oj.find_equilibrium(dose, {}, [1.0], np.zeros(1))
    for h in (0.1, 1.0):
        eq = oj.find_equilibrium(dose, {}, [1.0], np.zeros(1), dt=h)
        assert eq.success and eq.x[0] == pytest.approx(1.0 / (1.0 - np.exp(-h)), rel=1e-12)
    ode = oj.Model.from_ode(lambda x, u, th: u[:1] - x, None)
    assert oj.find_equilibrium(ode, {}, [2.0], np.zeros(1)).x[0] == pytest.approx(2.0)


@pytest.mark.parametrize("input", ["zoh", "foh"])
def test_the_step_response_and_dc_gain(input):
    """`step_response` is the sampled model's response to a unit step from rest: the
    nonlinear model's response to a small step from an equilibrium, divided by it, to
    first order (1e-6 of a 1e-4 step); for zoh, SciPy's `dstep` of (A, B, C, D)
    exactly. `dcgain` is the response's limit, the equilibrium output's slope in u, and
    the continuous-time model's within RK4's error."""
    from scipy import signal

    model = _model(input=input)
    eq = oj.find_equilibrium(model, THETA, [1.0], np.zeros(2))
    lin = oj.linearise(model, THETA, eq.x, [1.0])
    T, d = 400, 1e-4
    _, z0 = oj.simulate(model, THETA, eq.x, np.ones((T, 1)))
    _, z1 = oj.simulate(model, THETA, eq.x, np.full((T, 1), 1.0 + d))
    step = lin.step_response(T)
    assert step.shape == (T, 2, 1)
    np.testing.assert_allclose(step[:, :, 0], (np.asarray(z1) - np.asarray(z0)) / d, atol=1e-6)
    np.testing.assert_array_equal(step[0], lin.D if input == "zoh" else lin.D_observe)
    if input == "zoh":
        _, (y,) = signal.dstep(signal.dlti(lin.A, lin.B, lin.C, lin.D, dt=DT), n=T)
        np.testing.assert_allclose(step[:, :, 0], y, rtol=1e-13, atol=1e-15)
    slope = (oj.find_equilibrium(model, THETA, [1.0 + d], eq.x).z - eq.z) / d
    np.testing.assert_allclose(lin.dcgain()[:, 0], slope, rtol=1e-3)
    np.testing.assert_allclose(step[-1], lin.dcgain(), atol=2e-3)  # (settled, b = 0.6)
    np.testing.assert_allclose(lin.dcgain(continuous=True), lin.dcgain(), rtol=1e-4)
    with pytest.raises(ValueError, match="`n` .* must be an integer >= 1"):
        lin.step_response(0)
