"""`fit(validation=Validation(...))`: held-out records scored at every iterate, the best
iterate kept across solvers, early stopping.

The scores are checked against an independent computation (x0 by least squares on the
head with scipy-free NumPy Gauss-Newton, then the loss after it) at the iterates the
history records; the returned iterate is the recorded one with the lowest score, which
is not the training optimum on an over-fitting problem.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

DT = 0.05


def _rhs(x, u, th):
    return jnp.array([x[1], -th["k"] * x[0] - th["c"] * x[1] + th["g"] * u[0]])


MODEL = oj.Model.from_ode(_rhs, DT, observe=lambda x, u, th: x[:1])
TRUTH = {"k": 4.0, "c": 0.6, "g": 1.0}


def _record(seed, T, noise):
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.normal(0.0, 1.0, T // 8 + 1), 8)[:T, None]
    x0 = rng.normal(0.0, 0.3, 2)
    _, z = oj.simulate(MODEL, TRUTH, x0, u)
    return u, np.asarray(z) + noise * rng.normal(size=(T, 1)), x0


def _reference_score(theta, u, z, n):
    """x0 from the head by many Gauss-Newton steps (autodiff Jacobian, lstsq), then the
    mean squared error after the head."""
    return float(_reference(theta, jnp.asarray(u), jnp.asarray(z), n))


@jax.jit
def _reference_impl(theta, u, z, n_mask):
    def head(x0):
        _, zh = oj.simulate(MODEL, theta, x0, u)
        return ((zh - z) * n_mask[:, None]).ravel()

    def gn(_, x0):
        J = jax.jacfwd(head)(x0)
        return x0 - jnp.linalg.lstsq(J, head(x0))[0]

    x0 = jax.lax.fori_loop(0, 30, gn, jnp.zeros(2))
    _, zh = oj.simulate(MODEL, theta, x0, u)
    e2 = ((zh - z) ** 2)[:, 0] * (1.0 - n_mask)
    return jnp.sum(e2) / jnp.sum(1.0 - n_mask)


def _reference(theta, u, z, n):
    mask = (jnp.arange(u.shape[0]) < n).astype(u.dtype)
    theta = {k: jnp.asarray(v, u.dtype) for k, v in theta.items()}
    return _reference_impl(theta, u, z, mask)


def test_scores_and_best_iterate():
    u, z, x0 = _record(0, 200, 0.05)
    uv, zv, _ = _record(1, 150, 0.05)
    val = oj.Validation(uv, zv, n=20, x0_steps=10)
    res = oj.fit(
        MODEL,
        {"k": 2.0, "c": 0.2, "g": 0.5},
        x0,
        u,
        z,
        solver=oj.Adam(lr_theta=2e-2, lr_x0=1e-2, max_steps=60),
        validation=val,
    )
    h = res.history
    assert h.validation is not None and h.validation.shape == h.loss.shape
    # The recorded scores equal the reference at their iterates (a few rows).
    for i in (0, 10, 40):
        theta = {k: h.theta[k][i] for k in TRUTH}
        np.testing.assert_allclose(h.validation[i], _reference_score(theta, uv, zv, 20), rtol=1e-6)
    # The result is the iterate with the lowest score, and reports it.
    scores = h.validation
    np.testing.assert_allclose(res.validation_loss, np.min(scores), rtol=1e-12)
    i = int(np.argmin(scores))
    for k in TRUTH:
        np.testing.assert_allclose(res.theta[k], h.theta[k][i], rtol=1e-12)


def test_keeps_the_best_across_solvers_and_says_so(tmp_path):
    # Training on a short, very noisy record over-fits x0 and theta; the held-out score
    # is lowest before the end, so the returned iterate is not where the solver stopped.
    u, z, x0 = _record(2, 60, 0.3)
    uv, zv, _ = _record(3, 300, 0.01)
    solver = [oj.Adam(lr_theta=5e-2, lr_x0=1e-2, max_steps=40), oj.LevenbergMarquardt()]
    res = oj.fit(
        MODEL,
        {"k": 3.0, "c": 0.3, "g": 0.8},
        x0,
        u,
        z,
        solver=solver,
        validation=oj.Validation(uv, zv, n=20),
    )
    plain = oj.fit(MODEL, {"k": 3.0, "c": 0.3, "g": 0.8}, x0, u, z, solver=solver)
    assert plain.success
    score_plain = _reference_score(plain.theta, uv, zv, 20)
    assert res.validation_loss < score_plain
    assert res.stop_reason == oj.RESULTS.validation and not res.success
    np.testing.assert_allclose(
        res.validation_loss, _reference_score(res.theta, uv, zv, 20), rtol=1e-6
    )
    # The loss reported is the training loss at the returned iterate.
    np.testing.assert_allclose(res.loss, oj.loss(MODEL, res.theta, res.x0, u, z), rtol=1e-10)
    assert "validation loss" in str(res)
    # Saved and loaded with its scores.
    path = tmp_path / "val.npz"
    res.save(path)
    back = oj.load_result(path)
    assert back.validation_loss == res.validation_loss
    np.testing.assert_array_equal(back.history.validation, res.history.validation)


def test_a_solution_that_is_also_the_best_scored_iterate_keeps_its_status():
    """Validation on the training record itself (x0 known and held): the score is the
    training loss, so the point the solver stops at is the best-scored iterate. A solver
    that stops after a step it rejects (the round-off test: the iterate and its score as
    they were) reports the solution as such, not as a `validation` stop at another
    point (it did, because the rejected step's tie did not count as the best)."""
    u, z, x0 = _record(4, 200, 0.05)
    start = {"k": 3.0, "c": 0.2, "g": 0.8}
    val = oj.Validation(u, z, n=None, x0=x0)
    for solver in (oj.LevenbergMarquardt(gtol=1e-14), oj.GaussNewton(gtol=1e-14)):
        plain = oj.fit(MODEL, start, x0, u, z, estimate_x0=False, solver=solver)
        # (The round-off test, after a rejected step, is the case where they differed.)
        assert plain.status == "converged" and plain.stop_info["first_order"] > 1e-14
        res = oj.fit(MODEL, start, x0, u, z, estimate_x0=False, solver=solver, validation=val)
        assert res.status == "converged" and res.success, res.message
        for k in TRUTH:
            assert res.theta[k] == plain.theta[k]
        np.testing.assert_allclose(res.validation_loss, res.loss, rtol=1e-10)


def _oscillator(x, u, th):
    return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])


def test_a_solver_that_converges_past_the_best_score_by_a_tie_keeps_its_solution():
    """A lightly damped oscillator, sines in, validated on another record: the solvers'
    last steps move the score by 1e-8 to 2e-4 of it, far less than the records resolve.
    The converged point is returned with its status, not an iterate before it as a
    `validation` stop (which it was, GN and LM for 2e-8 of the score, 1e-6 of its
    standard deviation). The history's last row holds that point's score, and that
    point: the returned theta and loss are the last recorded iterate's (the solver's
    own end), not those of the best-scored row before it."""
    model = oj.Model.from_ode(_oscillator, DT, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(4)
    t = DT * np.arange(800)
    u = (np.sin(2.0 * t) + np.sin(3.3 * t + 1))[:, None]
    _, z = oj.simulate(model, {"k": 9.0, "c": 0.1}, np.zeros(2), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    uv = (np.sin(1.7 * t) + np.sin(2.9 * t))[:300, None]
    _, zv = oj.simulate(model, {"k": 9.0, "c": 0.1}, np.array([0.1, 0.0]), uv)
    zv = np.asarray(zv) + 0.01 * rng.standard_normal(zv.shape)
    val = oj.Validation(uv, zv, n=20)
    start = {"k": 8.0, "c": 0.5}
    for solver in (oj.LevenbergMarquardt(), oj.GaussNewton(), oj.LBFGS()):
        res = oj.fit(model, start, np.zeros(2), u, z, solver=solver, validation=val)
        assert res.status == "converged" and res.success, res.message
        h = res.history
        for k in start:
            assert res.theta[k] == h.theta[k][-1]
        np.testing.assert_allclose(res.loss, h.loss[-1], rtol=1e-12)
        if isinstance(solver, oj.LBFGS):
            # the scores leave the solver's path as it was (for LM and GN: the tests of
            # validation on the fit's own record and of the right model)
            plain = oj.fit(model, start, np.zeros(2), u, z, solver=solver)
            np.testing.assert_allclose(res.loss, plain.loss, rtol=1e-9)
        scores = h.validation
        assert np.all(np.isfinite(scores))
        np.testing.assert_allclose(scores[-1], res.validation_loss, rtol=1e-12)
        # (the case: an earlier row scores lower, by less than the tie's margin)
        assert np.argmin(scores) < len(scores) - 1
        # (a tie, here even below 1 % of the score's standard deviation, the earlier rule)
        assert 0 <= res.validation_loss - np.min(scores) <= 0.01 * np.min(scores) * np.sqrt(2 / 280)


def test_patience_stops_early():
    u, z, x0 = _record(2, 60, 0.3)
    uv, zv, _ = _record(3, 300, 0.01)
    res = oj.fit(
        MODEL,
        {"k": 3.0, "c": 0.3, "g": 0.8},
        x0,
        u,
        z,
        solver=oj.Adam(lr_theta=5e-2, lr_x0=1e-2, max_steps=3000),
        validation=oj.Validation(uv, zv, n=20, patience=25),
    )
    assert res.num_steps < 3000
    assert res.stop_reason == oj.RESULTS.validation
    i = int(np.nanargmin(res.history.validation))
    assert res.num_steps == res.history.step[i] + 25  # stopped after 25 without a better score


def test_held_out_data_that_never_score_finite_choose_nothing():
    """A held-out input of 1e300 overflows every iterate's score. The argmin over the
    starts' infinite scores kept start 0, whose training loss was 700 times start 1's,
    and with patience 2 the fit stopped after 2 steps ("lowest validation loss inf"), in
    silence. The training loss now ranks the starts, no patience is spent before a
    finite score, and fit warns that the held-out data chose nothing."""
    u, z, x0 = _record(0, 80, 0.01)
    bad = oj.Validation(np.full((40, 1), 1e300), np.zeros((40, 1)), x0=np.zeros(2), patience=2)
    start = {"k": 2.5, "c": 0.2, "g": 1.0}
    lm = oj.LevenbergMarquardt(max_steps=5)
    starts = {"k": np.array([0.3, 4.0])}
    plain = oj.fit(MODEL, start, x0, u, z, solver=lm, multistart=starts)
    assert plain.best == 1  # the case: the starts' training losses differ
    with pytest.warns(RuntimeWarning, match="no iterate scored a finite validation loss"):
        r = oj.fit(MODEL, start, x0, u, z, solver=lm, validation=bad, multistart=starts)
    # (two compiled programs, with and without the validation scores: equal up to the
    # last bits of the loss)
    assert r.best == plain.best and float(r.loss) == pytest.approx(float(plain.loss), rel=1e-12)
    # (patience 2 spent nothing: the fit ran past step 2)
    assert r.num_steps > 2 and r.status != "validation"


def test_a_divergence_behind_the_best_scored_iterate_is_named(tmp_path):
    """Adam with a learning rate that blows the simulation up: the best-scored iterate is
    returned (`validation`), and the solver's own stop, `diverged`, is named with it
    (nothing said so)."""
    u, z, x0 = _record(2, 60, 0.01)
    uv, zv, _ = _record(3, 60, 0.01)
    solver = oj.Adam(lr_theta=100.0, lr_x0=5.0, max_steps=40)

    def fit(**kwargs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return oj.fit(MODEL, {"k": 3.0, "c": 0.3, "g": 0.8}, x0, u, z, solver=solver, **kwargs)

    res = fit(validation=oj.Validation(uv, zv, n=20))
    assert res.status == "validation" and not res.success
    assert res.stop_info["solver_stop"] == "diverged" and res.stop_info["nonfinite"] == "loss"
    assert "the solver itself stopped with diverged" in res.message
    # Without validation the stop is `diverged`, and its first-order measure is NaN (it
    # read 0, a stationary point's value, from the division by an infinite ||r||).
    res = fit()
    assert res.status == "diverged" and np.isnan(res.stop_info["first_order"])
    # With several starts each start's own stop is kept too (they all read `validation`),
    # printed, and saved.
    starts = {"k": np.array([3.0, 2.5]), "c": np.array([0.3, 0.3]), "g": np.array([0.8, 0.8])}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = oj.fit(
            MODEL, starts, x0, u, z, solver=solver, multistart=True,
            validation=oj.Validation(uv, zv, n=20),
        )  # fmt: skip
    assert res.starts.stop_reason == ("validation", "validation")
    assert res.starts.solver_stop == ("diverged", "diverged")
    assert "stops: validation 2 (the solvers' own stops: diverged 2)" in str(res)
    path = res.save(tmp_path / "r.npz")
    assert oj.load_result(path).starts.solver_stop == ("diverged", "diverged")


def test_each_starts_validation_loss_shows_why_a_start_was_returned(tmp_path):
    """With several starts the returned one has the lowest validation score, which need
    not be the lowest training loss, and the starts' scores were not kept: the choice
    could not be checked from the result. `Starts.validation_loss` keeps them (saved),
    and the printout says the starts were ranked by it."""
    u, z, x0 = _record(0, 80, 0.01)
    # Held-out data of a stiffer system (k = 6): a start at k = 6 scores better there,
    # the start at the training truth (k = 4) has the lower training loss; Adam's tiny
    # steps keep both where they start.
    rng = np.random.default_rng(7)
    uv = np.repeat(rng.normal(0.0, 1.0, 11), 8)[:, None]
    zv = np.asarray(oj.simulate(MODEL, {**TRUTH, "k": 6.0}, np.zeros(2), uv)[1])
    starts = {"k": np.array([4.0, 6.0]), "c": np.full(2, 0.6), "g": np.ones(2)}
    adam = oj.Adam(lr_theta=1e-4, lr_x0=1e-4, max_steps=2)
    val = oj.Validation(uv, zv, n=20)
    r = oj.fit(MODEL, starts, x0, u, z, solver=adam, multistart=True, validation=val)
    scores = r.starts.validation_loss
    assert int(np.argmin(r.starts.loss)) == 0 and r.best == 1
    assert scores.shape == (2,) and int(np.argmin(scores)) == 1
    assert scores[1] == r.validation_loss
    for s in range(2):
        reference = _reference_score(r.start_theta(s), uv, zv, 20)
        assert scores[s] == pytest.approx(reference, rel=1e-6)
    assert "multistart: the best of 2 starts by validation loss (index 1)" in str(r)
    loaded = oj.load_result(r.save(tmp_path / "r.npz"))
    np.testing.assert_array_equal(loaded.starts.validation_loss, scores)


def test_counts_given_as_whole_floats_count():
    """Validation(n=10.0) was accepted and then failed inside JAX ("'float' object cannot
    be interpreted as an integer", naming no argument); x0_steps=2.0 in fori_loop. Whole
    floats are the counts they stand for, and score as the integers do."""
    u, z, x0 = _record(2, 60, 0.3)
    uv, zv, _ = _record(3, 100, 0.01)
    solver = oj.Adam(lr_theta=5e-2, lr_x0=1e-2, max_steps=20)
    scores = []
    for n, steps, patience in ((10, 2, 5), (10.0, 2.0, 5.0)):
        v = oj.Validation(uv, zv, n=n, x0_steps=steps, patience=patience)
        assert (type(v.n), type(v.x0_steps), type(v.patience)) == (int, int, int)
        res = oj.fit(MODEL, {"k": 3.0, "c": 0.3, "g": 0.8}, x0, u, z, solver=solver, validation=v)
        scores.append(res.validation_loss)
    assert scores[0] == scores[1]
    with pytest.raises(ValueError, match=r"Validation\(n=...\)"):
        oj.Validation(uv, zv, n=10.5)


def test_validation_checks():
    u, z, x0 = _record(0, 50, 0.0)
    with pytest.raises(ValueError, match="n"):
        oj.Validation(u, z)
    with pytest.raises(ValueError, match="patience"):
        oj.Validation(u, z, n=5, patience=0)
    with pytest.raises(TypeError, match="validation"):
        oj.fit(MODEL, TRUTH, x0, u, z, validation=(u, z))
    with pytest.raises(ValueError, match="validation"):
        oj.fit(MODEL, TRUTH, x0, u, z, validation=oj.Validation(u, z[:-1], n=5))
    with pytest.raises(ValueError, match="below"):
        oj.fit(MODEL, TRUTH, x0, u, z, validation=oj.Validation(u, z, n=50))
    bad = z.copy()
    bad[3] = np.nan
    # (not fit's hint of missing="mask": that option is for the fitted z; said when the
    # records are given, as the docstring's "no NaN" asks)
    with pytest.raises(ValueError, match="NaN: held-out records must be fully measured"):
        oj.Validation(u, bad, n=5)
    bad[3] = np.inf
    with pytest.raises(ValueError, match="inf.*held-out records must be fully measured.$"):
        oj.fit(MODEL, TRUTH, x0, u, z, validation=oj.Validation(u, bad, n=5))
    # Inputs of another width are named before the model is called on them (u of no
    # columns reached the model: an IndexError inside it).
    with pytest.raises(ValueError, match=r"`validation`: `u` must have n_u = 1 input columns"):
        oj.fit(MODEL, TRUTH, x0, u, z, validation=oj.Validation(np.zeros((50, 0)), z, n=5))
    # A head of one output value for two initial states does not determine them (as
    # `predict` with n = 1 warns); a head of two does.
    solver = oj.LevenbergMarquardt(max_steps=2)
    with pytest.warns(UserWarning, match=r"Validation\(n=1\)`: the head holds 1 output") as rec:
        oj.fit(MODEL, TRUTH, x0, u, z, solver=solver, validation=oj.Validation(u, z, n=1))
    assert rec[0].filename == __file__
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        oj.fit(MODEL, TRUTH, x0, u, z, solver=solver, validation=oj.Validation(u, z, n=2))
    assert not [w for w in caught if "the head holds" in str(w.message)]


def test_known_initial_states_and_time_stamps():
    # A model of time-stamped records: the held-out record has its own irregular times,
    # and with known x0 (n=None) the score is the loss of eq. (5) on it, every sample.
    timed = oj.Model.from_ode(_rhs, dt=None, observe=lambda x, u, th: x[:1])
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.02, 0.08, 120))
    t_val = np.cumsum(rng.uniform(0.02, 0.08, 90))
    u = np.sin(t)[:, None]
    u_val = np.cos(2 * t_val)[:, None]
    x0, x0_val = np.array([0.2, 0.0]), np.array([-0.1, 0.3])
    _, z = oj.simulate(timed, TRUTH, x0, u, t=t)
    _, z_val = oj.simulate(timed, TRUTH, x0_val, u_val, t=t_val)
    z = np.asarray(z) + 0.01 * rng.normal(size=z.shape)
    val = oj.Validation(u_val, z_val, x0=x0_val, t=t_val)
    res = oj.fit(timed, {"k": 3.0, "c": 0.3, "g": 0.8}, x0, u, z, t=t, validation=val)
    expected = oj.loss(timed, res.theta, x0_val, u_val, z_val, t=t_val)
    np.testing.assert_allclose(res.validation_loss, expected, rtol=1e-10)
    with pytest.raises(ValueError, match="`validation`.*t"):
        oj.fit(timed, TRUTH, x0, u, z, t=t, validation=oj.Validation(u_val, z_val, x0=x0_val))


def test_validation_inputs_are_checked_against_the_fitted_data_and_cast():
    """Held-out inputs with another number of columns than the training data were
    scored from the wrong column; float64 held-out data with a float32 fit made JAX warn
    of an unsafe cast in the history."""
    u, z, _ = _record(0, 120, 0.01)
    uv, zv, _ = _record(1, 80, 0.01)
    wide = np.concatenate([uv, uv], axis=1)
    with pytest.raises(ValueError, match=r"`validation`: `u` must have n_u = 1"):
        oj.fit(MODEL, TRUTH, np.zeros(2), u, z, validation=oj.Validation(wide, zv, n=10))
    f32 = {k: np.float32(v) for k, v in TRUTH.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = oj.fit(
            MODEL,
            f32,
            np.zeros(2, np.float32),
            u.astype(np.float32),
            z.astype(np.float32),
            validation=oj.Validation(uv, zv, n=10),
            solver=oj.LevenbergMarquardt(max_steps=3),
        )
    assert np.asarray(res.theta["k"]).dtype == np.float32


def test_the_head_estimate_reaches_the_minimum_of_a_model_nonlinear_in_x0():
    """The head's x0 took a full Gauss-Newton step only where it lowered the error: with
    an output x1^3 + x1, the estimate stopped at a point that is no minimum of the head's
    error (from zeros and warm-started alike), and the score was 0.6 % off the one from
    the head's least-squares x0 (scipy, tight tolerances). Each step is now halved until
    it lowers the error."""
    from scipy.optimize import least_squares

    def step(x, u, p):
        return jnp.stack(
            [p["a"] * x[0] + p["b"] * jnp.tanh(2 * x[1]) + u[0], -0.6 * x[0] + 0.5 * x[1]]
        )

    model = oj.Model(step, observe=lambda x, u, p: jnp.stack([x[0] ** 3 + x[0]]))
    truth, n = {"a": 0.6, "b": 0.8}, 8

    def record(T, seed, x0):
        rng = np.random.default_rng(seed)
        u = 0.5 * rng.standard_normal((T, 1))
        _, z = oj.simulate(model, truth, np.array(x0), u)
        return u, np.asarray(z) + 0.01 * rng.standard_normal((T, 1))

    u, z = record(400, 0, [0.0, 0.0])
    held = [record(200, 1, [0.8, -0.5]), record(200, 2, [-0.6, 0.9])]
    uv, zv = np.stack([a for a, _ in held]), np.stack([b for _, b in held])

    def outputs(theta, x0, u):
        return np.asarray(oj.simulate(model, theta, np.asarray(x0), u)[1])

    def score(theta):
        total = 0.0
        for a, b in zip(uv, zv):
            x0 = least_squares(
                lambda x: (outputs(theta, x, a[:n]) - b[:n]).ravel(),
                np.zeros(2),
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            ).x
            total += np.sum((outputs(theta, x0, a) - b)[n:] ** 2)
        return total / (2 * (200 - n))

    solver = oj.Adam(lr_theta=0.01, lr_x0=0.01, max_steps=60)
    val = oj.Validation(uv, zv, n=n)
    r = oj.fit(model, {"a": 0.2, "b": 0.2}, np.zeros(2), u, z, validation=val, solver=solver)
    h = r.history
    rows = range(0, len(h.validation), 6)
    got = np.asarray(h.validation)[list(rows)]
    want = [score({k: np.asarray(h.theta[k])[i] for k in truth}) for i in rows]
    np.testing.assert_allclose(got, want, rtol=1e-3)  # (0.63 % off before; 4e-5 now)


def test_a_right_model_validated_on_the_same_system_keeps_its_solution():
    """Levenberg-Marquardt on a right model (an oscillator, two outputs weighted 1 and 4),
    validated on two records of the same system: in 4 of these 8 noise draws the score at
    the solution was above the lowest (an iterate one step before) by 0.14 to 0.40 of the
    score's standard deviation, and the fit returned that iterate as a `validation` stop,
    not a success. Such a tie keeps the solution (the one-standard-error rule); the fit
    equals the one without validation."""

    def osc(x, u, p):
        return jnp.stack([x[1], -p["k"] * x[0] - p["c"] * x[1] + u[0]])

    model = oj.Model.from_ode(osc, DT, observe=lambda x, u, p: jnp.stack([x[0], 0.5 * x[1]]))
    truth = {"k": 9.0, "c": 0.4}

    def record(T, seed, x0):
        rng = np.random.default_rng(seed)
        t = DT * np.arange(T)
        u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.3, 3.1, 5.0))[:, None]
        _, z = oj.simulate(model, truth, np.array(x0), u)
        return u, np.asarray(z) + 0.02 * rng.standard_normal((T, 2))

    u, z = record(300, 0, [0.0, 0.0])
    weight, start = np.array([1.0, 4.0]), {"k": 8.0, "c": 0.3}
    plain = oj.fit(model, start, np.zeros(2), u, z, weight=weight)
    assert plain.status == "converged"
    for seed in range(8):
        (u1, z1), (u2, z2) = (
            record(200, 10 + 2 * seed, [0.5, -0.3]),
            record(200, 11 + 2 * seed, [-0.2, 0.4]),
        )
        val = oj.Validation(np.stack([u1, u2]), np.stack([z1, z2]), n=10)
        r = oj.fit(model, start, np.zeros(2), u, z, weight=weight, validation=val)
        assert r.status == "converged" and r.success, (seed, r.message)
        for k in truth:
            assert r.theta[k] == plain.theta[k]
        scores = np.asarray(r.history.validation)
        assert r.validation_loss - scores.min() <= scores.min() * np.sqrt(2 / (2 * 190 * 2))


def test_the_head_estimate_leaves_a_local_minimum_the_warm_start_followed():
    """z = (x^2, c x) of a constant state, fitted from c = -3 to about 0.3: while c < 0
    the head's error has its minimum at negative x, and the estimate warm-started from
    the last iterate's followed it there; once c > 0 that is a local minimum (error 0.36
    against 0 at x near +1), and the scores stayed on it (0.2 to 0.5 where the head's
    least-squares x0 from the guess scores 1e-3 to 2e-2; a hybrid's tank level went
    this way to 1e7). Each iterate now also estimates from the guess `x0` and keeps the
    lower head error."""
    from scipy.optimize import least_squares

    model = oj.Model(lambda x, u, p: x, lambda x, u, p: jnp.stack([x[0] ** 2, p["c"] * x[0]]))
    z = np.tile([1.0, 0.3], (40, 1))
    val = oj.Validation(np.zeros((20, 0)), np.tile([1.0, 0.3], (20, 1)), n=2, x0=np.array([2.0]))
    r = oj.fit(model, {"c": -3.0}, np.array([1.0]), np.zeros((40, 0)), z, estimate_x0=False,
               validation=val, solver=oj.Adam(lr_theta=0.1, max_steps=80))  # fmt: skip
    c, got = np.asarray(r.history.theta["c"]), np.asarray(r.history.validation)

    def score(c):  # x0 from the guess by least squares, then the error after the head
        x = least_squares(lambda x: [x[0] ** 2 - 1, c * x[0] - 0.3], [2.0], xtol=1e-15).x[0]
        return (x**2 - 1) ** 2 + (c * x - 0.3) ** 2

    later = np.flatnonzero(c > 0.1)  # (where the minimum near +1 is the lower one)
    assert len(later) > 20
    np.testing.assert_allclose(got[later], [score(v) for v in c[later]], rtol=1e-3, atol=1e-12)


def test_the_head_estimates_stay_within_the_fits_x0_bounds():
    """With `fit(x0_bounds=...)`, each held-out record's x0 is estimated from its head
    within the same box (as `result.predict` keeps it): the scores at the recorded
    iterates equal those from SciPy's bounded least squares on the head. The held-out
    records start just outside the box (x0[0] = -0.15 and -0.1 below a lower bound 0),
    where the unbounded estimate scores lower: without the box the scores differ."""
    from scipy.optimize import least_squares

    def record(seed, T, x0):  # (`_record`'s inputs, from this x0)
        u = _record(seed, T, 0.0)[0]
        z = np.asarray(oj.simulate(MODEL, TRUTH, np.array(x0), u)[1])
        return u, z + 0.02 * np.random.default_rng(seed).normal(size=z.shape)

    u, z = record(0, 200, [0.3, 0.2])
    held = [record(1, 120, [-0.15, 0.3]), record(2, 120, [-0.1, -0.4])]
    UV, ZV = np.stack([a for a, _ in held]), np.stack([b for _, b in held])
    n, box = 15, ([0.0, -np.inf], None)

    def outputs(theta, x0, u):
        return np.asarray(oj.simulate(MODEL, theta, np.asarray(x0), u)[1])

    def score(theta, bounded):
        lb = np.array([0.0, -np.inf]) if bounded else -np.inf
        total = 0.0
        for a, b in held:
            x0 = least_squares(
                lambda x: (outputs(theta, x, a[:n]) - b[:n]).ravel(),
                np.array([0.0, 0.0]),
                bounds=(lb, np.inf),
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            ).x
            total += np.sum((outputs(theta, x0, a) - b)[n:] ** 2)
        return total / (2 * (120 - n))

    val = oj.Validation(UV, ZV, n=n)
    solver = oj.LevenbergMarquardt(max_steps=8)
    r = oj.fit(MODEL, {"k": 3.0, "c": 0.4, "g": 0.8}, np.array([0.2, 0.0]), u, z,
               solver=solver, validation=val, x0_bounds=box)  # fmt: skip
    h = r.history
    assert r.success and len(h.validation) > 3
    rows = range(len(h.validation))
    thetas = [{k: np.asarray(h.theta[k])[i] for k in TRUTH} for i in rows]
    got = np.asarray(h.validation)
    np.testing.assert_allclose(got, [score(th, True) for th in thetas], rtol=1e-6)
    unbounded = [score(th, False) for th in thetas]
    assert np.all(np.asarray(unbounded) < 0.9 * got)


def _ar(x, u, th):
    return th["a"] * x + th["b"] * u


def test_a_validation_stops_measure_is_that_of_the_returned_point():
    """Adam stopped by patience returns its best-scored iterate; `stop_info["first_order"]`
    held the solver's own estimate at its last iterate (1.56, where a cosine is at most
    1). It is the largest cosine between the residual and a Jacobian column at the
    returned point, computed here from the residuals' Jacobian by forward differentiation."""
    model = oj.Model(_ar)
    rng = np.random.default_rng(0)
    u, u_val = rng.standard_normal((200, 1)), rng.standard_normal((200, 1))
    _, z = oj.simulate(model, {"a": 0.8, "b": 1.0}, np.array([0.5]), u)
    _, z_val = oj.simulate(model, {"a": 0.8, "b": 1.0}, np.array([0.2]), u_val)
    z = np.asarray(z) + 0.01 * rng.standard_normal((200, 1))
    z_val = np.asarray(z_val) + 0.01 * rng.standard_normal((200, 1))
    r = oj.fit(model, {"a": 0.3, "b": 2.0}, np.zeros(1), u, z,
               validation=oj.Validation(u_val, z_val, n=5, patience=20),
               solver=oj.Adam(lr_theta=1e-2, max_steps=500))  # fmt: skip
    assert r.status == "validation"

    def residual(v):
        _, zhat = oj.simulate(model, {"a": v[0], "b": v[1]}, v[2:], jnp.asarray(u))
        return (zhat - z).ravel()

    v = jnp.array([r.theta["a"], r.theta["b"], r.x0[0]])
    e, J = residual(v), jax.jacfwd(residual)(v)
    cosines = np.abs(J.T @ e) / (np.linalg.norm(J, axis=0) * np.linalg.norm(e))
    np.testing.assert_allclose(r.stop_info["first_order"], cosines.max(), rtol=1e-8)


def test_a_thinned_history_keeps_the_returned_iterate():
    """Held-out records of another system (a = 0.8; the fit's a = 0.9): the score is lowest
    midway along the second solver's path. A history of 4 rows per solver thins that
    iterate away; it is still a row of the history (where the full history has it: same
    solver, step, theta and score), and `stop_info` names its solver and step."""
    model = oj.Model(lambda x, u, th: th["a"] * x + u[0], lambda x, u, th: x)
    rng = np.random.default_rng(0)
    u, uv = rng.normal(size=(200, 1)), rng.normal(size=(200, 1))
    _, z = oj.simulate(model, {"a": 0.9}, jnp.zeros(1), u)
    _, zv = oj.simulate(model, {"a": 0.8}, jnp.zeros(1), uv)
    solver = [oj.Adam(lr_theta=5e-3, max_steps=50), oj.Adam(lr_theta=1e-2, max_steps=250)]
    val = oj.Validation(uv, zv, x0=jnp.zeros(1))
    fits = [
        oj.fit(model, {"a": 0.3}, jnp.zeros(1), u, z, solver=solver, validation=val, history=h)
        for h in (4, 1000)
    ]
    thin, full = fits
    assert len(full.history) == 302  # (every step of both solvers: nothing thinned)
    i = int(np.argmin(full.history.validation))
    stage, step = int(full.history.stage[i]), int(full.history.step[i])
    assert stage == 1 and 0 < step < 250
    for res in fits:
        assert res.stop_reason == oj.RESULTS.validation
        assert (res.stop_info["validation_stage"], res.stop_info["validation_step"]) == (
            stage,
            step,
        )
        h = res.history
        (row,) = np.flatnonzero((h.stage == stage) & (h.step == step))
        np.testing.assert_array_equal(h.theta["a"][row], res.theta["a"])
        assert h.validation[row] == res.validation_loss
        np.testing.assert_allclose(h.theta["a"][row], full.history.theta["a"][i], rtol=1e-14)
    # (rows in order: the thinned history's steps increase within each solver)
    h = thin.history
    assert len(h) < 20
    for s in (0, 1):
        assert np.all(np.diff(h.step[h.stage == s]) > 0)
