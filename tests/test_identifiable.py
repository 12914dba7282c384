"""Hybrid fits whose physics stays identifiable: `fit_physics_first` (the physical
estimates are those of the physics alone) and `fit_orthogonal` (the network's output
contribution orthogonal to the physical sensitivities).

The case: a pendulum with a nonlinear damping, 0.1 q' + 0.3 tanh(4 q'), modelled as
-w0sq sin q - b q' + r(q, q') + g u with an MLP r fed the WHOLE state (the trap of
docs/guides/minima.md): a plain joint fit lets r absorb part of the restoring force and
ends with w0sq 9 % off the truth 9; the physics first keeps it within 1 %, equal to a fit
of the physical model written without any network, while the network lowers the loss; the
orthogonal fit keeps it within 1 % too. The orthogonal penalty and its one-shot gradient
are checked against an independent autodiff formula.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import observe_angle, pendulum_nonlinear_damping

import oneshot_jax as oj
from oneshot_jax import internal
from oneshot_jax.residual import MLP

DT, T, W0SQ = 0.05, 300, 9.0


def _hybrid(x, u, p):
    q, v = x
    r = p["r"](x)[0]  # the whole state
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - p["b"] * v + r + p["g"] * u[0]])


def _physics(x, u, p):
    q, v = x
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - p["b"] * v + p["g"] * u[0]])


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(0)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.0, 2.0, 4.5, 6.0))[:, None]
    truth = oj.Model.from_ode(pendulum_nonlinear_damping, DT, observe=observe_angle)
    x, z = oj.simulate(truth, {"w0sq": W0SQ, "g": 1.0}, np.zeros(2), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))
    x = np.asarray(x)
    net = MLP(2, 1, (8,), key=jax.random.PRNGKey(0), input_offset=x.mean(0), input_scale=x.std(0))
    model = oj.Model.from_ode(_hybrid, DT, observe=observe_angle)
    return model, {"w0sq": 8.0, "b": 0.2, "g": 1.0, "r": net}, u, z


def test_plain_joint_fit_lets_the_network_absorb_the_restoring_force(case):
    model, theta0, u, z = case
    joint = oj.fit(model, theta0, np.zeros(2), u, z)
    # It fits the data to the noise level, with w0sq far off: the bias the option removes.
    assert np.sqrt(joint.loss) < 0.0105
    assert abs(float(joint.theta["w0sq"]) / W0SQ - 1) > 0.05


def test_physics_first_keeps_the_physics_only_estimates(case):
    model, theta0, u, z = case
    r = oj.fit_physics_first(model, theta0, np.zeros(2), u, z, learned="r")
    # The physical estimates equal those of the physical model written without a network.
    alone = oj.fit(
        oj.Model.from_ode(_physics, DT, observe=observe_angle),
        {k: theta0[k] for k in ("w0sq", "b", "g")},
        np.zeros(2),
        u,
        z,
    )
    for k in ("w0sq", "b", "g"):
        assert float(r.physics.theta[k]) == float(r.result.theta[k])  # held in stage 2
        np.testing.assert_allclose(float(r.physics.theta[k]), float(alone.theta[k]), rtol=1e-8)
    np.testing.assert_allclose(r.physics.loss, alone.loss, rtol=1e-10)
    assert abs(float(r.result.theta["w0sq"]) / W0SQ - 1) < 0.015
    # Stage 1 switched the network off; stage 2 started from theta0's and lowered the loss
    # to the noise level (0.01 rad), from the physics' 0.015.
    leaves = jax.tree_util.tree_leaves(eqx.filter(r.physics.theta["r"], eqx.is_inexact_array))
    assert leaves and all(np.all(np.asarray(a) == 0) for a in leaves)
    assert np.sqrt(r.result.loss) < 0.0101 < 0.014 < np.sqrt(r.physics.loss)
    assert r.physics.success
    assert "Physics first" in str(r)
    # The printout points to the physics stage's standard errors: the hybrid stage, which
    # it shows, holds the physical parameters (std 0 there)
    assert float(r.result.std["w0sq"]) == 0.0 < float(r.physics.std["w0sq"]) < np.inf
    assert "their standard errors are those of the physics stage (the field `physics`)" in str(r)


def test_physics_first_with_starts_on_every_physical_leaf(case):
    """`multistart=True` as documented: a leading axis of starts on every physical leaf
    (the network has none). It was refused: the network's leaves had no starts axis."""
    model, theta0, u, z = case
    starts = {**theta0, "w0sq": np.array([2.0, 8.0]), "b": np.array([0.2, 0.2])}
    starts["g"] = np.array([1.0, 1.0])
    r = oj.fit_physics_first(
        model,
        starts,
        np.zeros(2),
        u,
        z,
        learned="r",
        multistart=True,
        network_solver=oj.LevenbergMarquardt(max_steps=2),
    )
    assert r.physics.starts is not None and len(r.physics.starts.loss) == 2
    one = oj.fit_physics_first(
        model,
        {**theta0, "w0sq": 8.0},
        np.zeros(2),
        u,
        z,
        learned="r",
        network_solver=oj.LevenbergMarquardt(max_steps=2),
    )
    assert float(r.physics.loss) <= float(one.physics.loss) * (1 + 1e-9)


def test_physics_first_rejects_bad_arguments(case):
    model, theta0, u, z = case
    x0 = np.zeros(2)
    with pytest.raises(TypeError, match="`theta0` must be a dict"):
        oj.fit_physics_first(model, [1.0, 2.0], x0, u, z)
    with pytest.raises(TypeError, match="`learned` must be a key"):
        oj.fit_physics_first(model, theta0, x0, u, z, learned=3)
    with pytest.raises(TypeError, match="`learned` must be a key"):
        oj.fit_physics_first(model, theta0, x0, u, z, learned=())
    with pytest.raises(ValueError, match="`learned` names 'net'"):
        oj.fit_physics_first(model, theta0, x0, u, z, learned="net")
    with pytest.raises(ValueError, match="`learned` names a key twice"):
        oj.fit_physics_first(model, theta0, x0, u, z, learned=("r", "r"))
    # (an integer array is data to `fit`, not a parameter; a Python number is one)
    with pytest.raises(ValueError, match="`learned` names 'b', which holds no floating"):
        oj.fit_physics_first(model, {**theta0, "b": np.array(2)}, x0, u, z, learned=("r", "b"))
    for fn in (oj.fit_physics_first, oj.fit_orthogonal):  # (a physical parameter switched off)
        with pytest.raises(ValueError, match="`learned` names only single numbers \\('w0sq'\\)"):
            fn(model, theta0, x0, u, z, learned="w0sq")
    with pytest.raises(ValueError, match="`learned` names every parameter"):
        oj.fit_physics_first(model, {"r": theta0["r"]}, x0, u, z, learned="r")
    with pytest.raises(TypeError, match="`fixed` must be None or a dict"):
        oj.fit_physics_first(model, theta0, x0, u, z, fixed=[True])
    # (refused before stage 1 runs: it was refused after, as "unknown `solver`")
    with pytest.raises(ValueError, match="`network_solver`: unknown `solver` 'foo'"):
        oj.fit_physics_first(model, theta0, x0, u, z, network_solver="foo", fixed={"w0sq": [1]})
    for fn in (oj.fit_physics_first, oj.fit_orthogonal):  # (they said `fit()` got it)
        with pytest.raises(TypeError, match=rf"`{fn.__name__}` got unexpected keyword .*bogus"):
            fn(model, theta0, x0, u, z, bogus=1)
    with pytest.raises(ValueError, match="`fixed` has keys that theta0 does not have"):
        oj.fit_physics_first(model, theta0, x0, u, z, fixed={"k": True})
    with pytest.raises(ValueError, match="`multistart` has starts of the learned terms"):
        oj.fit_physics_first(model, theta0, x0, u, z, multistart={"r": np.zeros(3)})


# (Its rounds converge where the inner fits of the augmented model succeed. At gtol 1e-8
# they stopped on their statistical test on one machine and on their step budget on
# another (the first-order measure levels off near 1e-3 on the network's weights, whose
# steps the statistical test then weighs): whether the rounds settle within 10 turned on
# the last bits of the machine's code. gtol 1e-3, a largest cosine of 1e-3 between the
# residual and a Jacobian column, is a test the inner fits pass, and the rounds settle.)
@pytest.mark.default_optimisation
def test_fit_orthogonal_keeps_the_restoring_force_in_the_physics(case):
    model, theta0, u, z = case
    solver = oj.LevenbergMarquardt(gtol=1e-3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = oj.fit_orthogonal(model, theta0, np.zeros(2), u, z, learned="r", solver=solver)
    # (the penalty's rows, measured at one sample, have FIT -inf: a round that succeeded
    # warned of a bad minimum, "worse than that output's mean")
    assert not [w for w in caught if "worse than that output's mean" in str(w.message)]
    # The plain joint fit of the same case is 9 % off (the test above); here w0sq is
    # within 1 %, the network still brings the fit to the noise level (0.01 rad), and
    # its output contribution is orthogonal to the physical sensitivities.
    assert abs(float(r.theta["w0sq"]) / W0SQ - 1) < 0.015
    assert np.sqrt(r.loss) < 0.0105
    assert r.rounds[-1].projection < 0.01
    assert r.converged and len(r.rounds) > 1
    assert r.rounds[-1].moved <= 0.1
    assert r.x0.shape == (2,)
    assert "Orthogonal augmentation" in str(r)
    last = r.rounds[-1]  # (a round prints its fields by name; the table has its header)
    numbers = [f"{last.loss:.5g}", f"{last.projection:.3g}", f"{last.change:.3g}"]
    numbers += [f"{last.moved:.3g}", f"{last.absorbed:.3g}", last.status]
    assert str(r).splitlines()[-1].split() == [str(len(r.rounds) - 1), *numbers]
    assert str(last) == (
        "Round: loss {}, projection {}, change {}, moved {} SE, absorbed {} SE, stop {}"
    ).format(*numbers)
    # The projection and the physics the network carries, at the returned estimate with
    # its own sensitivities (the projection was the round's, against the basis it held
    # from its start: a pendulum "converged" with 0.38 at its end, 3 standard errors of
    # w0sq carried by the network).
    names = ["w0sq", "b", "g"]

    def outputs(phys, net):
        return oj.simulate(model, {**r.theta, **phys, "r": net}, r.x0, u)[1][:, 0]

    phys = {k: jnp.asarray(r.theta[k]) for k in names}
    off = jax.tree_util.tree_map(
        lambda a: jnp.zeros_like(a) if eqx.is_inexact_array(a) else a, r.theta["r"]
    )
    d = np.asarray(outputs(phys, r.theta["r"]) - outputs(phys, off))
    sens = jax.jacfwd(outputs)(phys, r.theta["r"])
    S = np.stack([np.asarray(sens[k]) for k in names], axis=1)
    q = np.linalg.qr(S)[0]
    assert last.projection == pytest.approx(np.linalg.norm(q.T @ d) / np.linalg.norm(d), rel=1e-6)
    carried = np.linalg.lstsq(S, d, rcond=None)[0] / np.array([r.result.std[k] for k in names])
    assert last.absorbed == pytest.approx(np.max(np.abs(carried)), rel=1e-6)
    assert last.absorbed <= 0.1


def test_fit_orthogonal_does_not_count_an_entry_held_by_fixed_as_unresolved(case):
    """A physical leaf held in part (k = [w0sq, b], b fixed): its std is 0, which `moved`
    read as "not finite", inf in every round, so the rounds could converge only by
    `rtol`. The held entry does not move and does not count, in `moved` and in
    `absorbed` (whose least squares is over the free entries)."""
    _, theta0, u, z = case

    def rhs(x, u, p):
        q, v = x
        return jnp.stack(
            [v, -p["k"][0] * jnp.sin(q) - p["k"][1] * v + p["r"](x)[0] + p["g"] * u[0]]
        )

    model = oj.Model.from_ode(rhs, DT, observe=observe_angle)
    start = {"k": np.array([8.0, 0.2]), "g": 1.0, "r": theta0["r"]}
    r = oj.fit_orthogonal(
        model, start, np.zeros(2), u, z, learned="r", rounds=1,
        fixed={"k": np.array([False, True])}, solver=oj.LevenbergMarquardt(max_steps=5),
    )  # fmt: skip
    assert float(r.theta["k"][1]) == 0.2 and r.result.std["k"][1] == 0.0
    assert np.isfinite(r.rounds[0].moved) and np.isfinite(r.rounds[0].absorbed)


# Two rounds, each fit stopped by its step budget of one step, a loose `rtol`. (Each call
# of `fit_orthogonal` compiles its own augmented model: the tests below share this one.)
SHORT_ROUNDS = dict(learned="r", rounds=2, rtol=1e3, solver=oj.LevenbergMarquardt(max_steps=1))


@pytest.fixture(scope="module")
def short_rounds(case):
    model, theta0, u, z = case
    return oj.fit_orthogonal(model, theta0, np.zeros(2), u, z, **SHORT_ROUNDS)


def test_fit_orthogonal_counts_no_round_whose_fit_failed_as_converged(short_rounds, tmp_path):
    """A round whose fit stopped short (here its step budget of one step) moves the
    physics by whatever that fit did: within the tolerances (a loose `rtol` here) it
    ended the rounds as "converged". A round converges only where its fit succeeded; the
    rounds then run to their number, and say that they did not converge."""
    r = short_rounds
    assert [round.status for round in r.rounds] == ["max_steps_reached"] * 2
    assert all(round.change <= 1e3 for round in r.rounds)  # (the tolerance held)
    assert not r.converged and not r.success
    assert "2 rounds (not converged)" in str(r)
    # `save_result` of an `Orthogonal` said to save its `.result`, which is the last
    # round's fit of the augmented model: it loads with that model only, not the user's.
    with pytest.raises(TypeError, match=r"An Orthogonal is not saved whole, and its `.result` is"):
        oj.save_result(r, tmp_path / "o.npz")
    assert np.shape(r.result.x0) != np.shape(r.x0)  # (why: the augmented model's x0)


def test_physics_first_learns_a_term_written_as_a_python_float(case):
    """A learned term written as a Python float (b = 0.2), which `fit` estimates, was
    refused as holding "no floating array to fit": stage 1 holds it, stage 2 fits it."""
    model, theta0, u, z = case
    short = oj.LevenbergMarquardt(max_steps=2)
    r = oj.fit_physics_first(
        model, theta0, np.zeros(2), u, z, learned=("r", "b"), solver=short, network_solver=short
    )
    assert float(r.physics.theta["b"]) == 0.2 != float(r.result.theta["b"])


def test_fit_orthogonal_estimates_a_python_int_as_fit_does(case, short_rounds):
    """A physical start written as an int (g = 1): round 2 crashed reshaping the basis,
    which round 1 had built without g. (The same fit from g = 1.0: `short_rounds`.)"""
    model, theta0, u, z = case
    assert theta0["g"] == 1.0 and isinstance(theta0["g"], float)
    with warnings.catch_warnings():
        # (one output: fit's advice to weigh the outputs by their noise was given each
        # round, about the penalty's rows, which the user cannot weigh)
        warnings.filterwarnings("error", "the weighted residuals of the outputs differ")
        as_int = oj.fit_orthogonal(model, {**theta0, "g": 1}, np.zeros(2), u, z, **SHORT_ROUNDS)
    as_float = short_rounds
    assert len(as_int.rounds) == 2
    assert float(as_int.theta["g"]) == float(as_float.theta["g"]) != 1.0


def test_orthogonal_penalty_and_its_gradient():
    """The augmented model's cost is C + strength / T ||Q^T W^{1/2} d||^2 with Q an
    orthonormal basis of the weighted sensitivities, and its one-shot gradient equals
    reverse-mode autodiff of that formula written independently (a whole-state output
    with a full weight, a network with a nonzero output)."""
    T, strength = 40, 7.0
    model = oj.Model.from_ode(_hybrid, DT)  # z = x: n_z = 2
    net = MLP(2, 1, (4,), key=jax.random.PRNGKey(1), zero_last=False)
    theta = {"w0sq": jnp.asarray(8.5), "b": jnp.asarray(0.3), "g": jnp.asarray(1.1), "r": net}
    rng = np.random.default_rng(3)
    u = rng.standard_normal((T, 1))
    x0 = np.array([0.3, -0.2])
    z = np.asarray(oj.simulate(model, theta, x0, u)[1]) + 0.05 * rng.standard_normal((T, 2))
    W = np.array([[2.0, 0.5], [0.5, 1.0]])
    vals, vecs = np.linalg.eigh(W)
    root = vecs @ np.diag(np.sqrt(vals)) @ vecs.T
    names = ["w0sq", "b", "g"]
    m = internal.orthogonal_basis(model, theta, x0, u, names, root)
    assert m.shape == (T, 2, 3)
    # Q = W^{-1/2} M is orthonormal and spans the weighted sensitivities.
    q = np.einsum("ij,tjp->tip", np.linalg.inv(root), m).reshape(2 * T, 3)
    np.testing.assert_allclose(q.T @ q, np.eye(3), atol=1e-12)

    def outputs(phys):
        return oj.simulate(model, {**theta, **phys}, x0, u)[1]

    sens = jax.jacfwd(outputs)({k: theta[k] for k in names})
    s_w = np.stack([np.asarray(sens[k]) @ root for k in names], axis=-1).reshape(2 * T, 3)
    np.testing.assert_allclose(q @ (q.T @ s_w), s_w, rtol=1e-10, atol=1e-12)
    # Sensitivities of rank 2, a zero column first and a dependent one (a gain written
    # as a product, ga * gb): the basis spans them all, with one zero column (a QR's Q,
    # zeroed where R's diagonal was small, missed part of the later columns).
    deficient = np.stack([np.zeros(2 * T), s_w[:, 0], 2.0 * s_w[:, 0], s_w[:, 2]], axis=1)
    q2 = np.einsum(
        "ij,tjp->tip", np.linalg.inv(root), internal.orthonormal_basis(deficient, root)
    ).reshape(2 * T, 4)
    assert np.sum(np.linalg.norm(q2, axis=0) > 0.5) == 2
    np.testing.assert_allclose(q2 @ (q2.T @ deficient), deficient, rtol=1e-10, atol=1e-12)

    aug = internal.orthogonal_model(model, ("r",), 2, 1, 2, 3)
    u_aug = np.concatenate([u, m.reshape(T, 6)], axis=1)
    x0_aug = np.concatenate([x0, np.zeros(5)])
    z_aug = np.concatenate([z, np.full((T, 3), np.nan)], axis=1)
    z_aug[-1, 2:] = 0.0
    w_aug = np.zeros((5, 5))
    w_aug[:2, :2], w_aug[2:, 2:] = W, strength * np.eye(3)

    def independent(theta):
        zero = lambda a: jnp.zeros_like(a) if eqx.is_inexact_array(a) else a  # noqa: E731
        off = {**theta, "r": jax.tree_util.tree_map(zero, theta["r"])}
        y = oj.simulate(model, theta, x0, u)[1]
        d = y - oj.simulate(model, off, x0, u)[1]
        e = y - z
        along = jnp.einsum("tj,tjp->p", d, jnp.asarray(m))
        return jnp.einsum("ti,ij,tj->", e, W, e) / T + strength / T * jnp.sum(along**2)

    net_theta = eqx.filter(theta, eqx.is_inexact_array)
    static = eqx.filter(theta, eqx.is_inexact_array, inverse=True)
    want, want_grad = jax.value_and_grad(lambda p: independent(eqx.combine(p, static)))(net_theta)
    data = oj.loss(model, theta, x0, u, z, weight=W)
    assert want - data > 0.01 * want  # the penalty is a real part of the cost here
    got = oj.loss(aug, theta, x0_aug, u_aug, z_aug, weight=w_aug, missing="mask")
    np.testing.assert_allclose(got, want, rtol=1e-12)
    value, (grad, _) = oj.value_and_grad(
        aug, theta, x0_aug, u_aug, z_aug, weight=w_aug, missing="mask"
    )
    np.testing.assert_allclose(value, want, rtol=1e-12)
    for a, b in zip(
        jax.tree_util.tree_leaves(eqx.filter(grad, eqx.is_inexact_array)),
        jax.tree_util.tree_leaves(want_grad),
        strict=True,
    ):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_fit_orthogonal_rejects_bad_arguments(case):
    model, theta0, u, z = case
    x0 = np.zeros(2)
    with pytest.raises(TypeError, match="`theta0` must be a dict"):
        oj.fit_orthogonal(model, [1.0], x0, u, z)
    with pytest.raises(ValueError, match="`learned` names 'net'"):
        oj.fit_orthogonal(model, theta0, x0, u, z, learned="net")
    for bad in (0.0, -1.0, float("inf"), "1", True):
        with pytest.raises(ValueError, match="`strength` must be a finite number > 0"):
            oj.fit_orthogonal(model, theta0, x0, u, z, strength=bad)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="`rounds` must be an integer >= 1"):
            oj.fit_orthogonal(model, theta0, x0, u, z, rounds=bad)
    # `weight="noise"` is `fit`'s alone (named here); `rounds=2.0`, an integral float, passes
    # its check to reach it.
    with pytest.raises(ValueError, match="`fit_orthogonal` does not estimate it"):
        oj.fit_orthogonal(model, theta0, x0, u, z, rounds=2.0, weight="noise")
    with pytest.raises(TypeError, match="`weight` must hold numbers"):
        oj.fit_orthogonal(model, theta0, x0, u, z, weight=True)
    with pytest.raises(ValueError, match="`stol` must be a finite number > 0"):
        oj.fit_orthogonal(model, theta0, x0, u, z, stol=0.0)
    with pytest.raises(ValueError, match="`rtol` must be a finite number > 0"):
        oj.fit_orthogonal(model, theta0, x0, u, z, rtol=-1e-3)
    with pytest.raises(ValueError, match=r"does not take \['window'\]"):
        oj.fit_orthogonal(model, theta0, x0, u, z, window=50)
    with pytest.raises(TypeError, match="`model` must be a `Model`"):
        oj.fit_orthogonal(_hybrid, theta0, x0, u, z)
    timed = oj.Model.from_ode(_hybrid, None, observe=observe_angle)
    with pytest.raises(ValueError, match="`model` is timed"):
        oj.fit_orthogonal(timed, theta0, x0, u, z)
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_x,\)"):
        oj.fit_orthogonal(model, theta0, np.zeros((2, 2)), u, z)
    with pytest.raises(ValueError, match="`u` and `z` must have shapes"):
        oj.fit_orthogonal(model, theta0, x0, u[None], z[None])
    with pytest.raises(ValueError, match=r"`z` has missing \(NaN\)"):
        oj.fit_orthogonal(model, theta0, x0, u, np.where(np.arange(T)[:, None] == 3, np.nan, z))
    with pytest.raises(ValueError, match=r"`weight` must have shape \(1,\)"):
        oj.fit_orthogonal(model, theta0, x0, u, z, weight=np.ones(3))
    with pytest.raises(ValueError, match="`estimate_x0` must be a boolean"):
        oj.fit_orthogonal(model, theta0, x0, u, z, estimate_x0=np.ones(3, bool))
    with pytest.raises(ValueError, match="`fixed` holds every physical parameter"):
        oj.fit_orthogonal(model, theta0, x0, u, z, fixed={"w0sq": True, "b": True, "g": True})


@pytest.fixture(scope="module")
def small():
    """A hybrid oscillator on T = 120 samples, for the argument checks."""

    def hybrid(x, u, p):
        return jnp.stack([x[1], -p["k"] * x[0] - p["c"] * x[1] + p["r"](x)[0] + u[0]])

    model = oj.Model.from_ode(hybrid, DT, observe=lambda x, u, p: x[:1])
    u = np.sin(np.arange(120) * DT)[:, None]
    theta0 = {"k": 3.0, "c": 0.2, "r": MLP(2, 1, (4,), key=jax.random.PRNGKey(0))}
    return model, theta0, u, np.zeros((120, 1))


@pytest.mark.parametrize(
    "change, match",
    [
        # z with more columns than the model's outputs: it was a NumPy reshape error.
        ({"z": np.zeros((120, 2))}, r"`z` must have shape \(120, 1\)"),
        # A NaN weight: it was reported as NaN in `u` (the augmented inputs).
        ({"weight": np.array([np.nan])}, "`weight` contains NaN"),
        # Strings: it was NumPy's "could not convert string to float".
        ({"u": np.full((120, 1), "a")}, "`u` must hold real numbers"),
    ],
)
def test_fit_orthogonal_checks_the_data_as_fit_does(small, change, match):
    model, theta0, u, z = small
    args = {"u": u, "z": z, **change}
    weight = args.pop("weight", None)
    with pytest.raises(ValueError, match=match):
        oj.fit_orthogonal(model, theta0, np.zeros(2), args["u"], args["z"], weight=weight)


def test_physics_first_multistart_true_names_a_scalar_physical_leaf(small):
    """It was an IndexError (a scalar indexed for its first start)."""
    model, theta0, u, z = small
    starts = {**theta0, "k": np.array([2.0, 3.0])}
    with pytest.raises(ValueError, match=r"leading axis of starts.*theta0\['c'\] is a scalar"):
        oj.fit_physics_first(model, starts, np.zeros(2), u, z, multistart=True)


def test_fit_orthogonal_names_a_start_where_the_model_does_not_simulate(small):
    """sqrt(k) at k = -1: the sensitivity basis is NaN, and the error blamed the user's `u`
    (the basis travels as extra input columns)."""

    def hybrid(x, u, p):
        k = jnp.sqrt(p["k"]) ** 2
        return jnp.stack([x[1], -k * x[0] - p["c"] * x[1] + p["r"](x)[0] + u[0]])

    _, theta0, u, z = small
    model = oj.Model.from_ode(hybrid, DT, observe=lambda x, u, p: x[:1])
    with pytest.raises(ValueError, match=r"not finite at theta0 and x0: start where the model"):
        oj.fit_orthogonal(model, {**theta0, "k": -1.0}, np.zeros(2), u, z, rounds=1)
