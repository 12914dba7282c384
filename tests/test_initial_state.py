"""`estimate_x0`, `predict`, `FitResult.predict` and the windows' starting states.

References are computed here: the least-squares x0 of a linear model by `np.linalg.lstsq`
on its output map (the outputs are affine in x0), and the spread of the estimates over
noise realisations against their reported standard deviations.
"""

import functools
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

#
# Models.
#

DT = 0.05
PEND_THETA = np.array([9.81, 0.4])


def pendulum_rhs(x, u, th):
    return jnp.stack([x[1], -th[0] * jnp.sin(x[0]) - th[1] * x[1] + u[0]])


def angle(x, u, th):
    del u, th
    return x[:1]


PENDULUM = oj.Model.from_ode(pendulum_rhs, DT, observe=angle, input="foh")

# A linear model whose third state never reaches the output (it is driven by u only).
A = np.array([[0.9, 0.2, 0.0], [-0.2, 0.8, 0.0], [0.0, 0.0, 0.7]])
B = np.array([[0.0], [1.0], [0.5]])
LINEAR = oj.Model(lambda x, u, th: th * (A @ x) + B @ u, lambda x, u, th: x[:1] + 0.0 * th)


def duffing_rhs(x, u, th):
    return jnp.stack([x[1], -th[0] * x[0] - th[1] * x[1] - th[2] * x[0] ** 3 + u[0]])


DUFFING = oj.Model.from_ode(duffing_rhs, DT, observe=angle)


def whole_state(x, u, th):
    del u, th
    return x


# The pendulum with its whole state measured by an `observe` of its own (and a zero-order
# hold): one model object for the tests of weighted heads, so that their equal
# configurations (a fit of 60 samples with a (2, 2) weight, a head of N_HEAD samples)
# share compiled programs.
PENDULUM_X = oj.Model.from_ode(pendulum_rhs, DT, observe=whole_state)
DUFFING_THETA = np.array([4.0, 0.3, 1.0])


def pendulum_record(T, seed, noise, x0=(0.8, -0.3)):
    rng = np.random.default_rng(seed)
    u = 0.5 * np.sin(0.3 * np.arange(T) + rng.uniform(0, 6))[:, None]
    x, z = oj.simulate(PENDULUM, PEND_THETA, np.asarray(x0), u)
    return u, np.asarray(z) + noise * rng.standard_normal((T, 1)), np.asarray(x)


#
# estimate_x0.
#

NOISE = 0.01
N_HEAD = 30  # one head length throughout: each new shape compiles the solvers again


def test_lsq_recovers_x0_to_the_noise_level():
    """Over 20 noise realisations, the errors divided by the reported std have mean square
    about 1 (chi-square with 40 degrees of freedom: 95 % of it in [0.61, 1.48])."""
    x0_true = np.array([0.8, -0.3])
    scores = []
    for seed in range(20):
        u, z, _ = pendulum_record(N_HEAD, seed, NOISE)
        est = oj.estimate_x0(PENDULUM, PEND_THETA, u, z, x0=np.zeros(2))
        assert est.success and est.method == "lsq" and est.n == N_HEAD
        assert est.covariance.shape == (2, 2) and np.all(est.identifiable)
        scores.append((est.x0 - x0_true) / est.std)
    scores = np.array(scores)
    assert np.max(np.abs(scores)) < 4.0, scores
    assert 0.5 < np.mean(scores**2) < 1.7, np.mean(scores**2)


def test_lsq_and_smoother_agree_within_their_std():
    u, z, _ = pendulum_record(40, 100, NOISE)
    lsq = oj.estimate_x0(PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=np.zeros(2))
    sm = oj.estimate_x0(
        PENDULUM,
        PEND_THETA,
        u,
        z,
        n=N_HEAD,
        x0=np.zeros(2),
        method="smoother",
        measurement_noise=NOISE**2,
    )
    assert sm.success and sm.stop_reason is None and sm.method == "smoother"
    assert np.all(np.abs(lsq.x0 - sm.x0) < np.minimum(lsq.std, sm.std)), (lsq.x0, sm.x0)
    assert np.all(sm.std < 2 * lsq.std) and np.all(lsq.std < 2 * sm.std), (lsq.std, sm.std)
    # The smoother's details: filtered and smoothed states over the head, whose k = 0 row
    # is the estimate; smoothing shrinks the filter's uncertainty at k = 0.
    k = sm.kalman
    assert k.smoothed_mean.shape == (N_HEAD, 2)
    assert k.filtered_covariance.shape == (N_HEAD, 2, 2)
    np.testing.assert_array_equal(k.smoothed_mean[0], sm.x0)
    np.testing.assert_array_equal(k.smoothed_mean[-1], k.filtered_mean[-1])
    assert np.all(np.diagonal(k.smoothed_covariance[0]) < np.diagonal(k.filtered_covariance[0]))
    # The head's loss from either estimate is at the noise level.
    assert lsq.loss <= sm.loss < 2 * NOISE**2


def _linear_posterior_x0(u, z, m0, P0, Qp, R):
    """The posterior mean and covariance of x0 of `LINEAR` (theta 1) given the measured
    entries of z (NaN: missing), by Gaussian conditioning on the stacked outputs: x_k =
    A^k x0 + sum_{j<k} A^(k-1-j) (B u_j + w_j), z_k = x_k[0] + v_k (what the extended RTS
    smoother computes exactly for a linear model)."""
    n, n_x = len(z), 3
    size = n_x * n  # xi = (x0, w_0, .., w_{n-2})
    rows, means = [], []
    for k in range(n):
        M, c = np.zeros((n_x, size)), np.zeros(n_x)
        M[:, :n_x] = np.linalg.matrix_power(A, k)
        for j in range(k):
            G = np.linalg.matrix_power(A, k - 1 - j)
            M[:, n_x * (j + 1) : n_x * (j + 2)] = G
            c += G @ (B @ u[j])
        rows.append(M[0])
        means.append(M[0, :n_x] @ m0 + c[0])
    seen = np.isfinite(z[:, 0])
    H, mean = np.array(rows)[seen], np.array(means)[seen]
    cov = np.zeros((size, size))
    cov[:n_x, :n_x] = P0
    for j in range(n - 1):
        cov[n_x * (j + 1) : n_x * (j + 2), n_x * (j + 1) : n_x * (j + 2)] = Qp
    S = H @ cov @ H.T + R * np.eye(len(H))
    K = cov[:n_x] @ H.T @ np.linalg.inv(S)
    return m0 + K @ (z[seen, 0] - mean), P0 - K @ H @ cov[:, :n_x]


def test_inf_in_the_first_row_of_the_head_is_named_as_a_bad_value():
    """An inf in z[0], the default guess of x0 of a model that observes its state, is a
    bad value of `z` (`z_head` for `FitResult.predict`), not a missing sample for which
    a guess of x0 would be needed."""
    model = oj.Model(lambda x, u, th: th * x + u)
    u, z = np.ones((10, 1)), np.linspace(1.0, 2.0, 10)[:, None]
    z[0] = np.inf
    with pytest.raises(ValueError, match=r"^`z` contains inf values \(in its first row"):
        oj.estimate_x0(model, 0.9, u, z, n=5)
    result = oj.fit(model, 0.5, np.ones(1), u[1:], z[1:])
    with pytest.raises(ValueError, match=r"^`z_head` contains inf values \(in its first row"):
        result.predict(u, z[:5])


def test_smoother_leaves_missing_samples_out_of_its_updates():
    """`estimate_x0(method="smoother", missing="mask")`: NaN in the head are missing
    measurements, left out of the filter's updates; the estimate and its covariance are
    the Gaussian posterior of x0 given the measured samples (a linear model, computed
    by conditioning here), not those of the head with the gaps filled. Without
    `missing="mask"` the NaN are refused, naming the option; `predict` and
    `FitResult.predict` take it too."""
    rng = np.random.default_rng(3)
    n = 20
    u = rng.standard_normal((n, 1))
    _, z = oj.simulate(LINEAR, 1.0, np.array([1.0, -0.5, 0.3]), u)
    z = np.asarray(z) + 0.05 * rng.standard_normal((n, 1))
    z[[2, 7, 8, 15]] = np.nan
    m0, P0, Qp, R = np.zeros(3), 4.0 * np.eye(3), 1e-3 * np.eye(3), 0.05**2
    kw = dict(n=n, x0=m0, method="smoother", prior_covariance=P0, process_noise=Qp,
              measurement_noise=R)  # fmt: skip
    est = oj.estimate_x0(LINEAR, 1.0, u, z, missing="mask", **kw)
    mean, cov = _linear_posterior_x0(u, z, m0, P0, Qp, R)
    np.testing.assert_allclose(est.x0, mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(est.covariance, cov, rtol=1e-8, atol=1e-12)
    filled = _linear_posterior_x0(u, np.nan_to_num(z), m0, P0, Qp, R)[0]
    assert np.max(np.abs(filled - mean)) > 1e-2  # (the gaps matter)
    assert np.isfinite(est.loss) and est.head is not None
    with pytest.raises(ValueError, match=r"pass missing=\"mask\" to treat NaN as a missing"):
        oj.estimate_x0(LINEAR, 1.0, u, z, **kw)
    pred = oj.predict(LINEAR, 1.0, u, z, missing="mask", **kw)
    np.testing.assert_array_equal(pred.x0, est.x0)


def test_smoother_is_less_biased_than_lsq_on_a_long_head_of_an_imperfect_model():
    """Parameters 3-10 % off over a head of 200 samples: the least-squares x0 fits one
    simulation of the whole head and is pulled far off; the smoother, whose process noise
    absorbs the model's drift, stays close. With the true parameters both are at the
    noise level."""
    T, x0_true = 200, np.array([0.5, -0.4])
    rng = np.random.default_rng(0)
    u = np.sin(0.03 * np.arange(T))[:, None] + 0.3 * rng.standard_normal((T, 1))
    _, z = oj.simulate(DUFFING, DUFFING_THETA, x0_true, u)
    z = np.asarray(z) + 0.005 * rng.standard_normal((T, 1))
    off = DUFFING_THETA * np.array([1.03, 0.9, 1.1])
    kw = dict(x0=np.zeros(2), measurement_noise=0.005**2)
    lsq = oj.estimate_x0(DUFFING, off, u, z, x0=np.zeros(2))
    sm = oj.estimate_x0(DUFFING, off, u, z, method="smoother", **kw)
    err_lsq, err_sm = np.abs(lsq.x0 - x0_true), np.abs(sm.x0 - x0_true)
    assert err_sm[1] < 0.6 * err_lsq[1], (err_lsq, err_sm)
    sm_true = oj.estimate_x0(DUFFING, DUFFING_THETA, u, z, method="smoother", **kw)
    assert np.all(np.abs(sm_true.x0 - x0_true) < 4 * sm_true.std)


@functools.cache
def linear_record():
    rng = np.random.default_rng(3)
    u = rng.standard_normal((25, 1))
    x0_true = np.array([1.0, -0.5, 2.0])
    _, z = oj.simulate(LINEAR, 1.0, x0_true, u)
    return u, np.asarray(z) + 0.01 * rng.standard_normal(z.shape)


def test_unobservable_entry_lsq_gives_the_minimum_norm_solution_and_warns():
    u, z = linear_record()
    n = 12
    with pytest.warns(UserWarning, match=r"\['x0\[2\]'\] are not determined by the first n = 12"):
        est = oj.estimate_x0(LINEAR, 1.0, u, z, n=n, x0=np.zeros(3))
    # The outputs are affine in x0: z_hat = c + J x0; lstsq gives the minimum-norm solution.
    c = np.asarray(oj.simulate(LINEAR, 1.0, np.zeros(3), u[:n])[1]).ravel()
    J = np.stack(
        [np.asarray(oj.simulate(LINEAR, 1.0, e, u[:n])[1]).ravel() - c for e in np.eye(3)], 1
    )
    ref = np.linalg.lstsq(J, z[:n].ravel() - c, rcond=None)[0]
    assert ref[2] == 0.0
    np.testing.assert_allclose(est.x0, ref, rtol=1e-8, atol=1e-12)
    assert est.x0[2] == 0.0
    assert list(est.identifiable) == [True, True, False]
    assert np.isinf(est.std[2]) and np.all(np.isfinite(est.std[:2]))


def test_unobservable_entry_smoother_keeps_the_prior_and_warns():
    u, z = linear_record()
    prior = np.array([4.0, 4.0, 9.0])
    with pytest.warns(UserWarning, match=r"x0\[2\].*leaves the estimate at the prior"):
        est = oj.estimate_x0(
            LINEAR,
            1.0,
            u,
            z,
            n=12,
            x0=np.array([0.0, 0.0, 0.7]),
            method="smoother",
            measurement_noise=1e-4,
            prior_covariance=prior,
        )
    assert est.x0[2] == pytest.approx(0.7, abs=1e-12)
    assert est.std[2] == pytest.approx(3.0, rel=1e-12)
    assert list(est.identifiable) == [True, True, False]
    assert np.all(np.abs(est.x0[:2] - np.array([1.0, -0.5])) < 4 * est.std[:2])


def test_one_sample_of_an_observed_state():
    """z = x: one sample determines x0 (lsq: exactly, with no degrees of freedom left
    for the noise level, so the std is inf; the smoother: up to its prior)."""
    model = oj.Model(lambda x, u, th: th * x + u)
    u, z = np.ones((5, 2)), np.array([[0.3, -1.2]] * 5)
    est = oj.estimate_x0(model, 0.5, u, z, n=1)
    np.testing.assert_allclose(est.x0, z[0], rtol=1e-12)
    assert np.all(np.isinf(est.std))
    sm = oj.estimate_x0(model, 0.5, u, z, n=1, method="smoother", measurement_noise=1e-6)
    np.testing.assert_allclose(sm.x0, z[0], rtol=1e-6)
    assert np.all(sm.std < 1.1e-3)


#
# predict.
#


def test_predict_round_trip_on_noise_free_data():
    """Noise-free record from a known x0: predict from its first 30 outputs reproduces
    the whole record, and uses nothing of z beyond the head."""
    x0_true = np.array([0.6, 0.4])
    u, z, x = pendulum_record(80, 7, 0.0, x0=x0_true)
    z_hidden = z.copy()
    z_hidden[N_HEAD:] = np.nan  # only the first n outputs may be used
    pred = oj.predict(PENDULUM, PEND_THETA, u, z_hidden, N_HEAD, x0=np.zeros(2))
    assert isinstance(pred, oj.Prediction) and isinstance(pred.estimate, oj.X0Estimate)
    np.testing.assert_allclose(pred.x0, x0_true, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(pred.z, z, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(pred.x, x, rtol=1e-8, atol=1e-10)
    scores = oj.metrics.benchmark_scores(z, pred.z, N_HEAD)
    assert np.all(scores.rmse < 1e-9)
    # The smoother (with a tiny noise floor) lands on the same record.
    sm = oj.predict(
        PENDULUM, PEND_THETA, u, z_hidden, N_HEAD, x0=np.zeros(2), method="smoother",
        measurement_noise=1e-12, process_noise=1e-14,
    )  # fmt: skip
    np.testing.assert_allclose(sm.x0, x0_true, atol=1e-4)


def test_fit_result_predict():
    """Fit on one record, predict another from its head: the same as `oj.predict` with the
    fitted model and theta, from the fitted x0 as the starting guess."""
    u, z, _ = pendulum_record(60, 11, 0.0)
    r = oj.fit(PENDULUM, np.array([9.0, 0.5]), np.array([0.7, -0.2]), u, z, solver="gauss_newton")
    assert r.success
    u_new, z_new, _ = pendulum_record(80, 12, 0.0, x0=(-0.5, 0.9))
    pred = r.predict(u_new, z_new[:N_HEAD])
    ref = oj.predict(PENDULUM, r.theta, u_new, z_new, N_HEAD, x0=r.x0)
    np.testing.assert_array_equal(pred.z, ref.z)
    np.testing.assert_allclose(pred.x0, [-0.5, 0.9], rtol=1e-7)
    np.testing.assert_allclose(pred.z, z_new, atol=1e-7)
    # MATLAB's predict(sys, data, K): the horizon is predict_ahead's (it said "takes 3
    # positional arguments but 4 were given")
    with pytest.raises(TypeError, match=r"is `result.predict_ahead\(u, z, K, process_noise"):
        r.predict(u_new, z_new, 5)


def test_one_record_of_a_multi_record_fit_is_named_by_its_row_of_x0():
    """After a fit on 2 records, `result.simulate(u)` of one record (no x0 given) said
    "`x0` of shape (2, 2) ... (np.ravel(x0))", which the user never passed; the messages
    now say that the result holds one initial state per record and how to pick one."""
    (u1, z1, _), (u2, z2, _) = pendulum_record(60, 1, 0.0), pendulum_record(60, 2, 0.0, (0, 1))
    U, Z = np.stack([u1, u2]), np.stack([z1, z2])
    r = oj.fit(PENDULUM, PEND_THETA, np.array([[0.8, -0.3], [0.0, 1.0]]), U, Z)
    rows = (
        r"this result holds 2 initial states, one per trajectory \(record\) of the fit "
        r"\(`result.x0` of shape \(2, 2\)\)"
    )
    for u, held in ((u1, "one record"), (U[:1], "one record"), ([u1, u2, u1[:30]], "3 records")):
        with pytest.raises(ValueError, match=rf"{rows}, and `u` holds {held}: pass `x0=result"):
            r.simulate(u)
    np.testing.assert_allclose(r.simulate(u2, x0=r.x0[1])[1], z2, atol=1e-7)
    with pytest.raises(ValueError, match=rf"\(n_x,\); {rows}: pass `x0=result.x0\[i\]`"):
        r.predict(u1, z1[:N_HEAD], x0=r.x0)
    np.testing.assert_allclose(r.predict(u2, z2[:N_HEAD], x0=r.x0[1]).x0, [0.0, 1.0], atol=1e-7)


def test_predict_of_several_records_predicts_each_from_its_own_head():
    """MATLAB's `predict` of multi-experiment data: `result.predict` of N records (stacked,
    or a list of different lengths) returns one `Prediction` per record, each from its own
    head (records from different initial states: a head given to another record would
    give that record's x0), with `x0=` one starting guess per record; a head count that
    does not match is named."""
    truth = ((0.8, -0.3), (-0.5, 0.9), (0.1, 0.4))
    recs = [
        pendulum_record(T, seed, 0.0, x0) for T, seed, x0 in zip((60, 60, 45), (1, 2, 3), truth)
    ]
    U, Z = np.stack([r[0] for r in recs[:2]]), np.stack([r[1] for r in recs[:2]])
    r = oj.fit(PENDULUM, PEND_THETA, np.array([[0.7, -0.2], [-0.4, 0.8]]), U, Z)
    stacked = r.predict(U, Z[:, :N_HEAD])
    heads = [c[1][:n] for c, n in zip(recs, (N_HEAD, N_HEAD, 20))]  # (heads of two lengths)
    ragged = r.predict([c[0] for c in recs], heads, x0=np.zeros((3, 2)))
    assert isinstance(stacked, list) and len(stacked) == 2 and len(ragged) == 3
    for preds in (stacked, ragged):
        for p, (u, z, _), x0 in zip(preds, recs, truth):
            assert isinstance(p, oj.Prediction) and p.z.shape == z.shape
            np.testing.assert_allclose(p.x0, x0, atol=1e-6)
            np.testing.assert_allclose(p.z, z, atol=1e-6)
    with pytest.raises(ValueError, match=r"`z_head` must hold one head per record of `u` \(2"):
        r.predict(U, Z[0, :N_HEAD])
    # (one head's rows are samples: it read "with 10 heads")
    with pytest.raises(ValueError, match=r"got ndarray of shape \(10, 1\), one head \(n, n_z\)\."):
        r.predict(U, Z[0, :10])
    with pytest.raises(ValueError, match=r"`x0` \(the starting guesses\) must have shape"):
        r.predict(U, Z[:, :N_HEAD], x0=np.zeros((3, 2)))


def test_fit_result_predict_estimates_the_entries_the_fit_held_unless_told():
    """The documented default (a docstring read as if predict held them): a new record's
    x0 is estimated whole; `estimate=result.x0_estimated` holds the fit's held entries at
    their values in `x0=`."""
    u, z, _ = pendulum_record(60, 11, 0.0)
    r = oj.fit(PENDULUM, PEND_THETA, np.array([0.7, -0.3]), u, z, estimate_x0=[True, False])
    assert r.x0_estimated.tolist() == [True, False] and float(r.x0[1]) == -0.3
    u_new, z_new, _ = pendulum_record(80, 12, 0.0, x0=(-0.5, 0.9))
    np.testing.assert_allclose(r.predict(u_new, z_new[:N_HEAD]).x0, [-0.5, 0.9], rtol=1e-7)
    held = r.predict(u_new, z_new[:N_HEAD], x0=r.x0, estimate=r.x0_estimated)
    assert float(held.x0[1]) == -0.3 and float(held.estimate.std[1]) == 0.0


def test_fit_result_predict_weights_the_head_as_the_fit_did(tmp_path):
    """An output the fit ignored (weight 0: a sensor with an offset of 5) stays ignored when
    `predict` estimates a new record's x0, also after save and load; it used the identity
    weight (FIT -118 % in a probe)."""
    model = PENDULUM_X
    q = np.diag([1.0, 0.0])

    def record(T, seed, x0):
        u = 0.5 * np.sin(0.3 * np.arange(T) + seed)[:, None]
        return u, np.asarray(oj.simulate(model, PEND_THETA, np.asarray(x0), u)[1]) + [0, 5]

    u, z = record(60, 1, (0.8, -0.3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = oj.fit(model, np.array([9.0, 0.5]), np.array([0.7, -0.2]), u, z, weight=q)
    # (the ignored output's FIT is -290 %: not a sign of a bad minimum)
    assert r.metrics["fit_percent"][1] < 0
    assert not [w for w in caught if "worse than that output's mean" in str(w.message)]
    u_new, z_new = record(80, 2, (-0.5, 0.9))
    ref = oj.predict(model, r.theta, u_new, z_new, N_HEAD, x0=r.x0, weight=q)
    np.testing.assert_allclose(ref.x0, [-0.5, 0.9], rtol=1e-6)
    r.save(tmp_path / "r.npz")
    for result in (r, oj.load_result(tmp_path / "r.npz", model=model)):
        pred = result.predict(u_new, z_new[:N_HEAD])
        np.testing.assert_array_equal(pred.x0, ref.x0)


def test_fit_result_predict_smoother_uses_the_noise_the_fit_estimated():
    """The smoother reads a weight as an inverse noise covariance, whose scale a fit does
    not set: a fit with weight W / 1e4 gave x0 off by 0.2 with std 30 (a probe).
    `FitResult.predict` gives it sigma^2 W^{-1} (sigma^2 = SSE / dof of the fit's weighted
    residuals): the same prediction for W, 1e4 W and 1e-4 W, and the same as
    `estimate_x0` with that noise computed here."""
    model = PENDULUM_X
    rng = np.random.default_rng(3)
    u = 0.5 * np.sin(0.3 * np.arange(60))[:, None]
    z = np.asarray(oj.simulate(model, PEND_THETA, np.array([0.8, -0.3]), u)[1])
    z = z + 0.01 * rng.standard_normal(z.shape)
    u_new = 0.5 * np.sin(0.3 * np.arange(80) + 2.0)[:, None]
    z_new = np.asarray(oj.simulate(model, PEND_THETA, np.array([-0.5, 0.9]), u_new)[1])
    z_new = z_new + 0.01 * rng.standard_normal(z_new.shape)
    w = np.array([[4.0, 0.5], [0.5, 0.25]])
    preds = []
    for c in (1.0, 1e4, 1e-4):
        r = oj.fit(model, np.array([9.0, 0.5]), np.array([0.7, -0.2]), u, z, weight=c * w)
        assert r.success
        preds.append(r.predict(u_new, z_new[:N_HEAD], method="smoother"))
        if c == 1.0:
            e = np.asarray(r.residuals)
            s2 = np.einsum("ki,ij,kj->", e, w, e) / (e.size - 2 - 2)
            ref = oj.estimate_x0(
                model, r.theta, u_new, z_new, n=N_HEAD, x0=r.x0, method="smoother",
                measurement_noise=s2 * np.linalg.inv(w),
            )  # fmt: skip
            np.testing.assert_array_equal(preds[0].x0, ref.x0)
            np.testing.assert_array_equal(preds[0].estimate.std, ref.std)
    for p in preds[1:]:
        np.testing.assert_allclose(p.x0, preds[0].x0, rtol=1e-6)
        np.testing.assert_allclose(p.estimate.std, preds[0].estimate.std, rtol=1e-6)
    assert np.all(np.abs(preds[0].x0 - [-0.5, 0.9]) < 4 * preds[0].estimate.std)


def test_fit_result_predict_smoother_after_a_fit_that_ignored_an_output():
    """A fit with weight diag(1, 0): the smoother got that singular weight and refused it
    ("needs a positive definite weight"), where the docstring promises `estimate_x0`'s
    defaults; it now gets them, the numbers of `estimate_x0` without a weight."""
    model = oj.Model(lambda x, u, th: th * x + u[0], lambda x, u, th: jnp.stack([x[0], 2 * x[0]]))
    rng = np.random.default_rng(0)
    u = rng.standard_normal((50, 1))
    _, z = oj.simulate(model, 0.8, np.array([1.0]), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal((50, 2))
    r = oj.fit(model, 0.5, np.zeros(1), u, z, weight=np.array([1.0, 0.0]))
    p = r.predict(u, z[:10], method="smoother")
    ref = oj.estimate_x0(model, r.theta, u, z, n=10, x0=r.x0, method="smoother")
    np.testing.assert_array_equal(p.x0, ref.x0)
    assert abs(p.x0[0] - 1.0) < 0.05


def test_lsq_is_the_x0_only_fit():
    """`estimate_x0` solves x0 below `fit`, with the numbers of the public x0-only fit
    (every parameter fixed) on the head: a weighted two-output head, Levenberg-Marquardt
    from zeros. A solve that dropped the weight would land elsewhere."""
    model = PENDULUM_X
    rng = np.random.default_rng(5)
    u = 0.5 * np.sin(0.3 * np.arange(40))[:, None]
    _, z = oj.simulate(model, PEND_THETA, np.array([0.8, -0.3]), u)
    z = np.asarray(z) + 0.05 * rng.standard_normal((40, 2))
    weight = np.array([[4.0, 0.5], [0.5, 0.25]])
    solver = oj.LevenbergMarquardt()
    est = oj.estimate_x0(
        model, PEND_THETA, u, z, n=N_HEAD, x0=np.zeros(2), weight=weight, solver=solver
    )
    ref = oj.fit(
        model,
        PEND_THETA,
        np.zeros(2),
        u[:N_HEAD],
        z[:N_HEAD],
        fixed=True,
        weight=weight,
        solver=solver,
    )
    np.testing.assert_array_equal(est.x0, ref.x0)
    np.testing.assert_array_equal(est.covariance, ref.x0_covariance)
    np.testing.assert_array_equal(est.loss, ref.loss)
    assert est.stop_reason == ref.stop_reason
    unweighted = oj.estimate_x0(model, PEND_THETA, u, z, n=N_HEAD, x0=np.zeros(2), solver=solver)
    assert np.max(np.abs(unweighted.x0 - est.x0)) > 1e-3


def test_lsq_holds_the_known_entries_as_the_masked_x0_only_fit():
    """`estimate=` (MATLAB's InitialStates(i).Fixed on new data): the held rate keeps its
    given value, and the angle has the numbers of fit(estimate_x0=mask) on the head; it
    differs from the estimate of both entries. predict and FitResult.predict pass it on."""
    u, z, _ = pendulum_record(60, 3, NOISE, x0=(0.8, 0.0))
    mask = np.array([True, False])
    guess = np.array([0.0, 0.0])
    held = oj.estimate_x0(PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess, estimate=mask)
    ref = oj.fit(
        PENDULUM, PEND_THETA, guess, u[:N_HEAD], z[:N_HEAD], fixed=True, estimate_x0=mask,
        solver=oj.GaussNewton(),
    )  # fmt: skip
    np.testing.assert_array_equal(held.x0, ref.x0)
    np.testing.assert_array_equal(held.covariance[:1, :1], ref.x0_covariance)  # its free block
    assert held.x0[1] == 0.0 and held.std[1] == 0.0 and held.identifiable.all()
    both = oj.estimate_x0(PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess)
    assert both.x0[1] != 0.0 and abs(both.x0[0] - held.x0[0]) > 1e-6
    pred = oj.predict(PENDULUM, PEND_THETA, u, z, N_HEAD, x0=guess, estimate=mask)
    np.testing.assert_array_equal(pred.x0, held.x0)
    # (`ref` is a FitResult of fit(estimate_x0=mask): its predict passes the mask on)
    np.testing.assert_array_equal(ref.x0_estimated, mask)
    again = ref.predict(u, z[:N_HEAD], x0=guess, estimate=ref.x0_estimated)
    assert again.x0[1] == 0.0
    with pytest.raises(ValueError, match=r"`estimate` holds some x0 entries.*give `x0`"):
        oj.estimate_x0(oj.Model(lambda x, u, th: th * x), 0.9, u, np.c_[z, z], n=5, estimate=mask)
    with pytest.raises(ValueError, match=r"`estimate` must be an \(n_x,\) = \(2,\) boolean"):
        oj.estimate_x0(PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess, estimate=[1, 0])
    with pytest.raises(TypeError, match=r"`estimate` must be an \(n_x,\)"):
        oj.estimate_x0(PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess, estimate=True)
    # Every entry held: x0 as given (the minimum over no variables), known exactly.
    none = oj.estimate_x0(
        PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess, estimate=np.zeros(2, bool)
    )
    np.testing.assert_array_equal(none.x0, guess)
    assert none.success and np.all(none.covariance == 0.0) and none.identifiable.all()
    _, zhat = oj.simulate(PENDULUM, PEND_THETA, guess, u[:N_HEAD])
    assert none.loss == pytest.approx(np.mean(np.sum((np.asarray(zhat) - z[:N_HEAD]) ** 2, 1)))
    with pytest.raises(ValueError, match=r"`estimate` .* applies to method='lsq'"):
        oj.estimate_x0(
            PENDULUM, PEND_THETA, u, z, n=N_HEAD, x0=guess, estimate=mask, method="smoother"
        )


def test_lsq_with_missing_head_samples_is_the_masked_x0_only_fit():
    """`missing="mask"`: NaN samples of the head leave the cost, as in `fit`; the two
    solves agree to the last digit, and differ from one that took the NaN as 0. Needs a
    guess where z[0] is missing, and the smoother refuses it."""
    model = oj.Model.from_ode(pendulum_rhs, DT)  # z = x
    rng = np.random.default_rng(5)
    u = 0.5 * np.sin(0.3 * np.arange(40))[:, None]
    _, z = oj.simulate(model, PEND_THETA, np.array([0.8, -0.3]), u)
    z = np.asarray(z) + 0.05 * rng.standard_normal((40, 2))
    z[[3, 11], 0] = np.nan
    z[7, 1] = np.nan
    kw = dict(x0=np.zeros(2), solver=oj.LevenbergMarquardt())
    est = oj.estimate_x0(model, PEND_THETA, u, z, n=25, missing="mask", **kw)
    ref = oj.fit(
        model,
        PEND_THETA,
        np.zeros(2),
        u[:25],
        z[:25],
        fixed=True,
        missing="mask",
        solver=kw["solver"],
    )
    np.testing.assert_array_equal(est.x0, ref.x0)
    zero = oj.estimate_x0(model, PEND_THETA, u, np.nan_to_num(z), n=25, **kw)
    assert np.max(np.abs(zero.x0 - est.x0)) > 1e-3
    pred = oj.predict(model, PEND_THETA, u, z, 25, missing="mask", **kw)
    np.testing.assert_array_equal(pred.x0, est.x0)
    with pytest.raises(ValueError, match=r"`z` contains NaN .*`estimate_x0` and `predict` take"):
        oj.estimate_x0(model, PEND_THETA, u, z, n=25, **kw)
    with pytest.raises(ValueError, match=r"take `missing=\"mask\"`[^\n]*\.$"):
        oj.estimate_x0(model, PEND_THETA, u, z, n=25)  # (no hint on z's columns: they fit)
    z[0, 1] = np.nan
    with pytest.raises(ValueError, match=r"`x0` .* is needed: z\[0\]"):
        oj.estimate_x0(model, PEND_THETA, u, z, n=25, missing="mask")


#
# Windows.
#


@functools.cache
def duffing_record(T=300):
    rng = np.random.default_rng(1)
    u = np.sin(0.025 * np.arange(T))[:, None]
    _, z = oj.simulate(DUFFING, DUFFING_THETA, np.array([0.5, 0.0]), u)
    return u, np.asarray(z) + 0.005 * rng.standard_normal((T, 1))


def test_windows_start_from_their_own_heads_when_theta0_is_unstable():
    """theta0 with negative damping and a softening spring: its simulation of the whole
    record reaches inf (the windows' starting states used to come from it, and the fit
    stopped there); each window's head gives its start instead, and the fit recovers
    theta."""
    u, z = duffing_record()
    theta0 = np.array([3.0, -0.5, -1.0])
    x, _ = oj.simulate(DUFFING, theta0, np.array([0.5, 0.0]), u)
    assert not np.all(np.isfinite(np.asarray(x)))
    r = oj.fit(DUFFING, theta0, np.zeros(2), u, z, window=30, solver="gauss_newton")
    assert r.success, r.message
    assert r.x0.shape == (10, 2)
    np.testing.assert_allclose(r.theta, DUFFING_THETA, rtol=0.2)
    np.testing.assert_allclose(r.x0[0], [0.5, 0.0], atol=0.05)


def test_windows_take_given_starting_states_and_name_a_blow_up():
    u, z = duffing_record()
    x0_w = np.tile([0.1, 0.2], (10, 1))
    r = oj.fit(
        DUFFING, DUFFING_THETA, x0_w, u, z, window=30, estimate_x0=False,
        solver=oj.GaussNewton(max_steps=1),
    )  # fmt: skip
    np.testing.assert_array_equal(r.x0, x0_w)  # not estimated: exactly the given ones
    with pytest.raises(ValueError, match="theta0 makes the model blow up .* within windows"):
        oj.fit(DUFFING, np.array([3.0, -40.0, -30.0]), np.zeros(2), u, z, window=30)


@pytest.mark.default_optimisation  # (two programs, equal to the bit: conftest.py)
def test_window_starts_are_the_x0_only_fit_of_all_windows():
    """The windows' starting states (partly observed state, missing samples, a weight)
    are those of one public x0-only fit of all windows together from the record's x0,
    the first window keeping the given x0: the same numbers, now solved below `fit`."""
    u, z = duffing_record()
    z = z.copy()
    z[::7] = np.nan
    theta0, x0, win = np.array([3.5, 0.2, 0.8]), np.array([0.4, 0.1]), 30
    r = oj.fit(
        DUFFING, theta0, x0, u, z, window=win, missing="mask", weight=np.array([2.0]),
        estimate_x0=False, solver=oj.GaussNewton(max_steps=1),
    )  # fmt: skip
    N = len(u) // win
    ref = oj.fit(
        DUFFING, theta0, np.tile(x0, (N, 1)), u.reshape(N, win, 1), z.reshape(N, win, 1),
        fixed=True, missing="mask", weight=np.array([2.0]), solver=oj.GaussNewton(),
    )  # fmt: skip
    np.testing.assert_array_equal(r.x0[0], x0)
    np.testing.assert_array_equal(r.x0[1:], ref.x0[1:])
    assert np.max(np.abs(r.x0[1:] - x0)) > 0.1  # estimated, not the guess


#
# Bad input.
#


def test_bad_input_errors():
    u, z = linear_record()
    x0 = np.zeros(3)
    est = functools.partial(oj.estimate_x0, LINEAR, 1.0, u, z)
    with pytest.raises(ValueError, match="`method` must be 'lsq' or 'smoother'"):
        est(x0=x0, method="kalman")
    # (an empty record: it said "`z` must have 1 to 0 rows")
    with pytest.raises(ValueError, match=r"`u` must hold at least one sample \(T >= 1\)"):
        oj.estimate_x0(LINEAR, 1.0, u[:0], z[:0], x0=x0)
    with pytest.raises(ValueError, match="`n`.* must be >= 1"):
        est(x0=x0, n=0)
    with pytest.raises(ValueError, match="`n` = 26 is more than the 25 samples of `z`"):
        est(x0=x0, n=26)
    # (z longer than u: its extra rows are another record's; only z[:n] would be read)
    with pytest.raises(ValueError, match="`z` has 25 rows, more than the 10 samples of `u`"):
        oj.estimate_x0(LINEAR, 1.0, u[:10], z, n=5, x0=x0)
    with pytest.raises(ValueError, match="`z` has 25 rows, more than the 10 samples of `u`"):
        oj.predict(LINEAR, 1.0, u[:10], z, 5, x0=x0)
    with pytest.raises(ValueError, match=r"samples of `u` \(is `u` transposed\? it has shape"):
        oj.predict(LINEAR, 1.0, u.T, z, 5, x0=x0)
    with pytest.raises(TypeError, match=r"`n` \(the number of head samples x0 is estimated"):
        oj.predict(LINEAR, 1.0, u, z, None, x0=x0)  # (estimate_x0's None: all of z)
    with pytest.raises(TypeError, match="`n`.* must be an integer"):
        est(x0=x0, n=2.5)
    with pytest.raises(ValueError, match=r"`u` must have shape \(T, n_u\)"):
        oj.estimate_x0(LINEAR, 1.0, u[:, 0], z, x0=x0)
    with pytest.raises(ValueError, match=r"several records: one call each, or `FitResult.pre"):
        oj.predict(LINEAR, 1.0, np.stack([u, u]), np.stack([z, z]), 5, x0=x0)
    with pytest.raises(ValueError, match=r"`z` must have shape \(T, n_z\)"):
        oj.estimate_x0(LINEAR, 1.0, u, z[None], x0=x0)
    # (records of unequal lengths in a list: NumPy's "inhomogeneous shape" before)
    with pytest.raises(ValueError, match=r"`u` .*got a list of 2 records \(several records"):
        oj.predict(LINEAR, 1.0, [u, u[:15]], [z, z[:15]], 5, x0=x0)
    with pytest.raises(ValueError, match=r"`z` .*got a list of 2 records"):
        oj.estimate_x0(LINEAR, 1.0, u, [z[:5], z[:4]], x0=x0)
    with pytest.raises(ValueError, match=r"`z` .*got a list of 2 records"):  # (1-D ones)
        oj.estimate_x0(LINEAR, 1.0, u, [z[:5, 0], z[:4, 0]], x0=x0)
    with pytest.raises(ValueError, match="`x0` .* is needed"):
        est()
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_x,\)"):
        est(x0=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="`measurement_noise` applies only to method='smooth"):
        est(x0=x0, measurement_noise=1.0)
    with pytest.raises(ValueError, match="`process_noise`, `measurement_noise` apply only to"):
        est(x0=x0, measurement_noise=1.0, process_noise=1.0)
    # (NaN in the head: the smoother's message names missing="mask" as the general one)
    gap = np.array(z, float)
    gap[3] = np.nan
    with pytest.raises(ValueError, match=r"`z` contains NaN: pass missing=\"mask\" to treat"):
        oj.estimate_x0(LINEAR, 1.0, u, gap, x0=x0, method="smoother")
    with pytest.raises(ValueError, match="`solver` only applies to method='lsq'"):
        est(x0=x0, method="smoother", solver=oj.GaussNewton())
    with pytest.raises(ValueError, match="`measurement_noise` must be positive definite"):
        est(x0=x0, method="smoother", measurement_noise=-1.0)
    with pytest.raises(ValueError, match=r"`process_noise` must be a scalar, a \(3,\) vector"):
        est(x0=x0, method="smoother", process_noise=np.ones(2))
    with pytest.raises(ValueError, match="`weight` must have shape"):
        est(x0=x0, weight=np.ones(3))
    with pytest.raises(TypeError, match="unexpected keyword arguments \\['x_0'\\]"):
        oj.predict(LINEAR, 1.0, u, z, 5, x_0=x0)
    # theta that makes the model blow up over the head: said so.
    with pytest.raises(ValueError, match="the model blows up over the head"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            oj.estimate_x0(LINEAR, 1e40, u, z, n=12, x0=np.ones(3))


def test_unobservable_combination_warning_names_a_direction_not_a_held_entry():
    # z = x[0] + x[1], both decaying alike: only the sum is observable; the entries move.
    m = oj.Model(lambda x, u, p: p * x + u[0], lambda x, u, p: x[:1] + x[1:])
    u = np.random.default_rng(0).standard_normal((30, 1))
    _, z = oj.simulate(m, 0.8, np.array([1.0, 2.0]), u)
    with pytest.warns(
        UserWarning,
        match=r"alone or together.*along that direction the estimate stays at the starting guess",
    ):
        est = oj.estimate_x0(m, 0.8, u, z, n=10, x0=np.array([5.0, 0.0]))
    np.testing.assert_allclose(est.x0, [4.0, -1.0], atol=1e-9)  # the sum fitted, (5, 0) + t(1, -1)
    assert not est.identifiable.any()


def test_holding_an_entry_of_a_combination_makes_the_other_identifiable():
    """Only x0[0] + 3 x0[1] reaches the outputs: held at its value, x0[1] leaves x0[0]
    determined. `estimate_x0` judged identifiability with every column free (both flagged,
    a warning, "(not determined by the head)"), though `predict` and the std did not."""
    A, C = np.diag([0.9, 0.9, 0.5]), np.array([[1.0, 3.0, 0.0], [0.0, 0.0, 1.0]])
    model = oj.Model(lambda x, u, th: th["A"] @ x + u[0], lambda x, u, th: th["C"] @ x)
    theta = {"A": A, "C": C}
    u = np.zeros((30, 1))
    _, z = oj.simulate(model, theta, np.array([1.0, 2.0, -1.0]), u)
    guess, mask = np.array([0.0, 2.0, 0.0]), np.array([True, False, True])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        est = oj.estimate_x0(model, theta, u, z, n=20, x0=guess, estimate=mask)
    np.testing.assert_allclose(est.x0, [1.0, 2.0, -1.0], atol=1e-12)
    assert list(est.identifiable) == [True, True, True]
    assert np.all(np.isfinite(est.std))
    with pytest.warns(UserWarning, match=r"\['x0\[0\]', 'x0\[1\]'\] are not determined"):
        free = oj.estimate_x0(model, theta, u, z, n=20, x0=guess)  # (both free: a direction)
    assert list(free.identifiable) == [False, False, True]


# (module-level: both cases of the test below reuse its compiled fit)
STATIC = oj.Model(lambda x, u, th: x, lambda x, u, th: th["d"] * u + th["e"])


@pytest.mark.parametrize("method", ["lsq", "smoother"])
def test_a_model_without_state_has_no_initial_state_to_estimate(method):
    """A static model (n_x = 0, z = d u + e): `estimate_x0` and `predict` return an empty
    x0 and the simulation (they failed with a ZeroDivisionError in a reshape), and the
    printout says the model has no state (it said x0 was fixed, for 0 trajectories)."""
    rng = np.random.default_rng(1)
    u = rng.standard_normal((20, 1))
    model = STATIC
    z = 1.5 * u + 0.3 + 0.01 * rng.standard_normal((20, 1))
    r = oj.fit(model, {"d": 1.0, "e": 0.0}, np.zeros(0), u, z)
    assert "(none: the model has no state, n_x = 0)" in str(r)
    p = r.predict(u, z[:3], method=method)
    assert p.x0.shape == (0,)
    np.testing.assert_array_equal(p.z, oj.simulate(model, r.theta, np.zeros(0), u)[1])
    est = oj.estimate_x0(model, r.theta, u, z, x0=np.zeros(0), method=method)
    assert est.x0.shape == (0,)


def test_a_model_without_state_fits_in_windows_and_predicts_ahead():
    """A static model in windows (`fit(window=...)`, `check_basin`) and ahead
    (`predict_ahead`): each window's x0 solve had no unknowns and failed in a reshape
    (ZeroDivisionError), the Kalman predictor's check of `process_noise` took the largest
    entry of an empty matrix. Windows change nothing without a state (the fit equals the
    whole record's), and the k-step prediction of a static model is its simulation."""
    rng = np.random.default_rng(1)
    u = rng.standard_normal((60, 1))
    z = 1.5 * u + 0.3 + 0.01 * rng.standard_normal((60, 1))
    whole = oj.fit(STATIC, {"d": 1.0, "e": 0.0}, np.zeros(0), u, z)
    windowed = oj.fit(STATIC, {"d": 1.0, "e": 0.0}, np.zeros(0), u, z, window=oj.Windows(20))
    assert windowed.success, windowed.message
    for k in ("d", "e"):
        assert float(windowed.theta[k]) == pytest.approx(float(whole.theta[k]), rel=1e-8)
    basin = oj.check_basin(whole, u, z, window=20)
    assert not basin.bad_basin and basin.windowed.success
    ahead = oj.predict_ahead(STATIC, whole.theta, u, z, 3, x0=np.zeros(0), process_noise=0.0)
    np.testing.assert_allclose(ahead.z, oj.simulate(STATIC, whole.theta, np.zeros(0), u)[1])


def _oscillator_rhs(x, u, th):
    return jnp.stack([x[1], u[0] - th["c"] * x[1] - th["k"] * x[0]])


# (module-level: the smoother tests below share its compiled programs)
OSCILLATOR = oj.Model.from_ode(_oscillator_rhs, 0.05, observe=angle)


def _smoother_case():
    """A damped oscillator, its position measured without noise over 60 samples: (model,
    theta, u, z, the generator for the noise)."""
    model = OSCILLATOR
    theta = {"c": 0.3, "k": 2.0}
    rng = np.random.default_rng(0)
    u = rng.standard_normal((60, 1))
    _, z = oj.simulate(model, theta, np.array([0.2, -0.1]), u)
    return model, theta, u, np.asarray(z), rng


def test_the_smoothers_default_noise_warns_where_the_residuals_are_far_above_it():
    """The smoother's default measurement noise is 1 % of each output's RMS over the head;
    on data of noise 0.01 at an output RMS of about 0.2 its std came out 5 times too small,
    silently. It now warns there, naming `measurement_noise`; with that given, or by
    method='lsq' (std from the residuals), it does not."""
    model, theta, u, z, rng = _smoother_case()
    z = z + 0.01 * rng.standard_normal(np.shape(z))
    with pytest.warns(
        UserWarning, match=r"assumed a measurement noise of 1 % .* `measurement_noise`"
    ):
        oj.estimate_x0(model, theta, u, z, n=40, method="smoother", x0=np.zeros(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        oj.estimate_x0(
            model, theta, u, z, n=40, method="smoother", x0=np.zeros(2), measurement_noise=1e-4
        )
        oj.estimate_x0(model, theta, u, z, n=40, x0=np.zeros(2))


@pytest.mark.parametrize("times", [1.0, 2.0])
def test_the_smoothers_default_noise_warns_from_twice_its_size(times):
    """Noise `times` 1 % of the head's output RMS: at the default's own size no warning;
    at twice it, where the smoother's std is about half the spread of its estimates, a
    warning (it came only from 3 times)."""
    model, theta, u, z, rng = _smoother_case()
    z = z + times * 0.01 * np.sqrt(np.mean(z[:40] ** 2)) * rng.standard_normal(np.shape(z))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        oj.estimate_x0(model, theta, u, z, n=40, method="smoother", x0=np.zeros(2))
    said = [w for w in caught if "assumed a measurement noise of 1 %" in str(w.message)]
    assert len(said) == (times > 1.5)


def test_an_x0_estimate_and_residual_correlations_print_readably():
    """`print` of an `X0Estimate` and of `ResidualCorrelations` gives a few lines with the
    numbers and verdicts (it dumped the equinox repr and the raw arrays)."""
    rng = np.random.default_rng(1)
    u = rng.standard_normal((200, 1))
    white = rng.standard_normal((200, 1))
    rc = oj.metrics.residual_correlations(white, u, 10)
    text = str(rc)
    assert text.splitlines()[0] == (
        "residual correlations over lags 1..10 (0..10 with the inputs), 99 % bands"
    )
    verdict = "white" if rc.white[0] else "not white"
    share = f"{100 * rc.auto_outside[0]:.0f} % of the lags outside +-{rc.bound[0]:.3g}"
    assert text.splitlines()[1].startswith(f"  output 0: {verdict} ({share}, n = 200); ")
    coloured = np.convolve(white[:, 0], np.ones(5), "same")[:, None]
    alone = str(oj.metrics.residual_correlations(coloured, None, 10, confidence=0.95))
    assert "output 0: not white" in alone
    # (without inputs the header names none: it said "(0..10 with the inputs)")
    assert alone.splitlines()[0] == "residual correlations over lags 1..10, 95 % bands"
    model = oj.Model.from_ode(pendulum_rhs, DT, observe=angle)
    _, z = oj.simulate(model, PEND_THETA, np.array([0.3, 0.0]), u[:40] * 0.1)
    e = oj.estimate_x0(model, PEND_THETA, u[:40] * 0.1, np.asarray(z), n=20, x0=np.zeros(2))
    lines = str(e).splitlines()
    assert lines[0].startswith("x0 from the first 20 samples by lsq (")
    assert lines[1].startswith("  x0[0]") and f"std {e.std[0]:.3g}" in lines[1]
    assert "numpy" not in str(e)
    assert repr(e) == str(e)
    # A prediction prints its shapes and that estimate (it dumped the arrays)
    pred = oj.predict(model, PEND_THETA, u[:40] * 0.1, np.asarray(z)[:20], 20, x0=np.zeros(2))
    lines = str(pred).splitlines()
    assert lines[0] == "Prediction of 40 samples (`z` (40, 1), `x` (40, 2)) from the estimated x0:"
    assert lines[1:] == str(pred.estimate).splitlines() and repr(pred) == str(pred)


def test_a_masked_fits_predict_takes_the_heads_nan_as_missing(tmp_path):
    """After `fit(missing="mask")`, `result.predict` masks the NaN of a new head as that
    fit masked its data (the same prediction as `missing="mask"` given), also after
    save and load; `missing="raise"` given still refuses them, and so does the predict
    of a fit without a mask."""
    u, z, _ = pendulum_record(120, seed=8, noise=0.01)
    z[[4, 50]] = np.nan
    theta0 = np.array([9.0, 0.5])
    masked = oj.fit(PENDULUM, theta0, np.array([0.8, -0.3]), u, z, missing="mask")
    u_new, z_new, _ = pendulum_record(80, seed=9, noise=0.01, x0=(0.5, 0.2))
    head = z_new[:20].copy()
    head[[3, 11]] = np.nan
    kw = dict(x0=np.array([0.4, 0.0]))
    inherited = masked.predict(u_new, head, **kw)
    given = masked.predict(u_new, head, missing="mask", **kw)
    np.testing.assert_array_equal(inherited.x0, given.x0)
    np.testing.assert_array_equal(inherited.z, given.z)
    assert np.all(np.isfinite(inherited.z))
    with pytest.raises(ValueError, match="`z_head` contains NaN"):
        masked.predict(u_new, head, missing="raise", **kw)
    loaded = oj.load_result(masked.save(tmp_path / "masked.npz"), model=PENDULUM)
    assert loaded.missing == "mask"
    np.testing.assert_array_equal(loaded.predict(u_new, head, **kw).z, inherited.z)
    full = oj.fit(PENDULUM, theta0, np.array([0.8, -0.3]), u[60:], z[60:])
    assert full.missing == "raise"
    with pytest.raises(ValueError, match="`z_head` contains NaN"):
        full.predict(u_new, head, **kw)
