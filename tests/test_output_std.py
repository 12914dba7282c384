"""`FitResult.output_std`: the standard errors of the simulated outputs.

References are computed here: the joint covariance sigma^2 (J^T Q J)^-1 of theta and x0
from `jax.jacfwd` of `oneshot_jax.simulate` (not the library's sensitivities), carried to
the outputs; and the spread of predictions of a new record over noise realisations of
the training data and of the new record's head.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

DT = 0.05
TRUTH = {"w0sq": 9.0, "b": 0.6}


def pendulum_rhs(x, u, th):
    return jnp.stack([x[1], -th["w0sq"] * jnp.sin(x[0]) - th["b"] * x[1] + u[0]])


def two_outputs(x, u, th):
    del u, th
    return jnp.stack([x[0], 0.2 * x[1]])


PENDULUM = oj.Model.from_ode(pendulum_rhs, DT, observe=two_outputs)
X0 = np.array([0.6, -0.4])
Q = np.array([4.0, 1.0])


def record(T, seed, noise, x0=X0):
    rng = np.random.default_rng(seed)
    u = 0.8 * np.sin(0.4 * np.arange(T) + rng.uniform(0, 6))[:, None]
    _, z = oj.simulate(PENDULUM, TRUTH, x0, u)
    return u, np.asarray(z) + noise * rng.standard_normal(np.shape(z))


def _outputs_of(u):
    def zhat(p):
        return oj.simulate(PENDULUM, {"b": p[0], "w0sq": p[1]}, p[2:], u)[1]

    return zhat


def joint_reference(result, u, z, q=Q):
    """sqrt(diag(J_z M J_z^T)), M = sigma^2 (J^T Q J)^-1 of (b, w0sq, x0) by jacfwd, the
    rows of missing samples, and the samples of an output of weight 0, left out of J and
    sigma^2."""
    p = jnp.array([result.theta["b"], result.theta["w0sq"], *result.x0])
    zhat = _outputs_of(u)
    Jz = np.asarray(jax.jacfwd(zhat)(p))  # (T, n_z, 4)
    seen = np.isfinite(z)
    e = np.where(seen, np.asarray(zhat(p)) - z, 0.0)
    J = np.where(seen[..., None], Jz, 0.0) * np.sqrt(q)[None, :, None]
    J = J.reshape(-1, 4)
    s2 = np.sum(q * e**2) / ((seen & (q > 0)).sum() - 4)
    M = s2 * np.linalg.inv(J.T @ J)
    return np.sqrt(np.einsum("kip,pq,kiq->ki", Jz, M, Jz))


def test_on_the_fitted_record_the_head_of_all_of_it_gives_the_joint_covariance():
    """With the whole fitted record as its head (a sample missing), the standard errors
    are those of the joint covariance of theta and x0: theta's covariance through the
    outputs and through x0's estimate, and x0's own part. Over a short record x0 and
    theta are correlated, so theta's part alone (x0 taken as known) differs."""
    u, z = record(60, 0, 0.02)
    z[7, 1] = np.nan
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0 + 0.1, u, z, weight=Q, missing="mask")
    assert result.success, result.message
    s = result.output_std(u, z_head=z)
    ref = joint_reference(result, u, z)
    np.testing.assert_allclose(s, ref, rtol=1e-7)
    known = result.output_std(u, x0=result.x0)
    assert np.max(np.abs(known - ref) / ref) > 0.5


def test_an_output_of_weight_zero_is_no_observation_of_the_heads_noise():
    """With an output of weight 0 (the rate, measured but not fitted), the band from the
    whole fitted record is still the joint covariance's: the head's noise variance counts
    the observations as the covariance does (it counted the ignored output's samples
    too: SSE / 116 instead of SSE / 56, a band up to 29 % narrow)."""
    u, z = record(60, 2, 0.02)
    q = np.array([1.0, 0.0])
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0 + 0.1, u, z, weight=q)
    s = result.output_std(u, z_head=z)
    np.testing.assert_allclose(s, joint_reference(result, u, z, q), rtol=1e-7)


def test_with_a_known_x0_the_band_is_theta_covariance_carried_to_the_outputs():
    u, z = record(60, 1, 0.02)
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0, u, z, estimate_x0=False)
    s = result.output_std(u, x0=X0)
    p = jnp.array([result.theta["b"], result.theta["w0sq"], *X0])
    Jt = np.asarray(jax.jacfwd(_outputs_of(u))(p))[..., :2]
    ref = np.sqrt(np.einsum("kip,pq,kiq->ki", Jt, result.covariance, Jt))
    assert np.all(s[0] == 0.0)  # (z_0 = g(x0) does not depend on theta)
    np.testing.assert_allclose(s[1:], ref[1:], rtol=1e-7)


def test_the_band_of_a_new_record_predicted_from_its_head_matches_the_spread():
    """Over noise realisations of the training record and of a new record's head, the
    spread of the predicted outputs about the truth matches the mean standard error,
    sample by sample, and 1.96 std covers 95 % of them. Without the head's own noise the
    first samples' errors would be far beyond their band; without theta's covariance the
    later ones."""
    T, n, runs = 60, 6, 150
    rng = np.random.default_rng(3)
    u, _ = record(T, 4, 0.0)
    u2, z2 = record(T, 5, 0.0, x0=np.array([-0.3, 0.5]))
    _, z_true = oj.simulate(PENDULUM, TRUTH, X0, u)
    errors, stds = [], []
    for _ in range(runs):
        z = np.asarray(z_true) + 0.05 * rng.standard_normal((T, 2))
        head = z2[:n] + 0.05 * rng.standard_normal((n, 2))
        result = oj.fit(PENDULUM, TRUTH, X0, u, z)
        errors.append(result.predict(u2, head).z - z2)
        stds.append(result.output_std(u2, z_head=head))
    errors, stds = np.array(errors), np.array(stds)
    ratio = errors.std(axis=0) / stds.mean(axis=0)
    assert 0.9 < np.median(ratio) < 1.1, np.median(ratio)
    assert np.all((ratio > 0.7) & (ratio < 1.35)), ratio
    covered = np.mean(np.abs(errors) <= 1.96 * stds)
    assert 0.93 < covered < 0.97, covered


def test_unknown_standard_errors_are_inf():
    u, z = record(40, 6, 0.02)
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0, u, z, covariance=None)
    s = result.output_std(u, x0=X0)
    assert np.all(s[0] == 0.0) and np.all(np.isinf(s[1:]))
    # a head of one sample of the angle alone does not determine the velocity
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, X0, u, z)
    head = np.array([[z[0, 0], np.nan]])
    with pytest.warns(UserWarning, match="not determine"):
        s = result.output_std(u, z_head=head)
    assert np.all(np.isinf(s[1:]))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({}, "neither"),
        ({"x0": X0, "z_head": np.zeros((5, 2))}, "both"),
        ({"x0": np.zeros(3)}, "x0"),
        ({"x0": np.zeros((2, 2))}, r"`x0` must be one initial state \(n_x,\)"),
    ],
)
def test_bad_arguments_are_named(kwargs, match):
    u, z = record(30, 7, 0.02)
    result = oj.fit(PENDULUM, TRUTH, X0, u, z)
    with pytest.raises(ValueError, match=match):
        result.output_std(u, **kwargs)


def test_several_records_take_the_joint_covariance_of_theta_and_every_x0():
    """On the N fitted records, each with all of it as its head, the standard errors are
    those of the joint covariance of theta and the N initial states: sigma^2 (J^T J)^-1
    of (b, w0sq, x0_1, x0_2) by jacfwd of both records' simulations, each record's rows
    through theta and its own x0 (a record given another's head, or theta's part alone,
    differs). With x0 known, one row of `x0` per record; a list of records of other
    lengths gives a list."""
    (u1, z1), (u2, z2) = record(50, 11, 0.02), record(50, 12, 0.02, x0=np.array([-0.3, 0.8]))
    U, Z = np.stack([u1, u2]), np.stack([z1, z2])
    x0 = np.array([X0, [-0.3, 0.8]])
    result = oj.fit(PENDULUM, {"w0sq": 7.0, "b": 0.3}, x0 + 0.1, U, Z)
    assert result.success, result.message
    p = jnp.array([result.theta["b"], result.theta["w0sq"], *result.x0.ravel()])

    def both(p):
        z_1 = _outputs_of(u1)(jnp.concatenate([p[:2], p[2:4]]))
        z_2 = _outputs_of(u2)(jnp.concatenate([p[:2], p[4:]]))
        return jnp.stack([z_1, z_2])

    Jz = np.asarray(jax.jacfwd(both)(p))  # (2, T, n_z, 6)
    e = np.asarray(both(p)) - Z
    J = Jz.reshape(-1, 6)
    M = np.sum(e**2) / (e.size - 6) * np.linalg.inv(J.T @ J)
    ref = np.sqrt(np.einsum("nkip,pq,nkiq->nki", Jz, M, Jz))
    s = result.output_std(U, z_head=Z)
    assert s.shape == (2, 50, 2)
    np.testing.assert_allclose(s, ref, rtol=1e-7)
    swapped = result.output_std(U, z_head=Z[::-1])
    assert np.max(np.abs(swapped - ref) / ref) > 0.1
    known = result.output_std(U, x0=result.x0)
    for i in range(2):
        np.testing.assert_array_equal(known[i], result.output_std(U[i], x0=result.x0[i]))
    assert np.max(np.abs(known - ref) / ref) > 0.5
    ragged = result.output_std([u1, u2[:30]], z_head=[z1[:20], z2[:10]])
    assert [a.shape for a in ragged] == [(50, 2), (30, 2)]
    np.testing.assert_array_equal(ragged[1], result.output_std(u2[:30], z_head=z2[:10]))
    with pytest.raises(ValueError, match=r"`x0` must have shape \(n_x,\) or \(2, n_x\)"):
        result.output_std(U, x0=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="`z_head` must hold one head per record"):
        result.output_std(U, z_head=z1)
