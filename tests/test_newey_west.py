"""`fit(covariance=NeweyWest(lags))`: the Newey-West sandwich covariance of theta and x0.

Checked against a dense computation of the same estimator from the whole Jacobian
(x0 columns of every trajectory included, no elimination), and by Monte Carlo: with
residuals correlated in time, sigma^2 (J^T J)^+ understates the spread of the estimates
over noise draws and the sandwich does not."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj


def rhs(x, u, th):
    return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])


OSC = oj.Model.from_ode(rhs, 0.1, observe=lambda x, u, th: x[:1])


def ar1(rng, shape, phi, sigma):
    """AR(1) noise along axis -2 (time), stationary from the first sample."""
    w = rng.standard_normal(shape) * sigma
    e = np.empty(shape)
    e[..., 0, :] = w[..., 0, :] / np.sqrt(1 - phi**2)
    for k in range(1, shape[-2]):
        e[..., k, :] = phi * e[..., k - 1, :] + w[..., k, :]
    return e


def dense_sandwich(model, theta, x0, u, z, lags, free_x0):
    """The estimator written out from the dense Jacobian of all residuals in
    (c, k: theta's order, JAX sorts dict keys; each trajectory's free x0 entries):
    H^+ Omega H^+ n / (n - q)."""
    N, T, n_z = z.shape
    m = len(free_x0)

    def residuals(v):
        th = {"c": v[0], "k": v[1]}
        X0 = jnp.asarray(x0).at[:, free_x0].set(v[2:].reshape(N, m))
        _, zhat = jax.vmap(lambda a, b: oj.simulate(model, th, a, b))(X0, u)
        return (zhat - z).reshape(N, T * n_z)

    v = jnp.concatenate([jnp.stack([theta["c"], theta["k"]]), x0[:, free_x0].ravel()])
    # (the algebra in NumPy: JAX's slices and `.at[...].set`, run eagerly, compile a
    # program per new slice, hundreds of them)
    e = np.asarray(jax.jit(residuals)(v))
    J = np.asarray(jax.jit(jax.jacfwd(residuals))(v))  # (N, T n_z, q)
    q = J.shape[-1]
    H = np.einsum("nra,nrb->ab", J, J)
    s = np.einsum("ntoa,nto->nta", J.reshape(N, T, n_z, q), e.reshape(N, T, n_z))
    omega = np.einsum("nta,ntb->ab", s, s)
    for lag in range(1, lags + 1):
        g = np.einsum("nta,ntb->ab", s[:, lag:], s[:, :-lag])
        omega = omega + (1 - lag / (lags + 1)) * (g + g.T)
    Hinv = np.linalg.inv(H)
    n = N * T * n_z
    cov = Hinv @ omega @ Hinv * n / (n - q)
    # x0_i: its own part with the residuals' autocovariance pooled over every sample,
    # Gamma_l = sum e_k e_{k-l}^T / (N T), as a dense block-Toeplitz Sigma per trajectory;
    # its part through theta with theta's sandwich.
    ek = e.reshape(N, T, n_z)
    sigma = np.zeros((T * n_z, T * n_z))
    for lag in range(lags + 1):
        gamma = np.einsum("nto,ntp->op", ek[:, lag:], ek[:, : T - lag]) / (N * T)
        w = 1 - lag / (lags + 1)
        for k in range(lag, T):
            rows, cols = slice(k * n_z, (k + 1) * n_z), slice((k - lag) * n_z, (k - lag + 1) * n_z)
            sigma[rows, cols] = w * gamma
            sigma[cols, rows] = w * gamma.T
    x0_cov = []
    for i in range(N):
        rows = slice(2 + i * m, 2 + (i + 1) * m)
        W = -Hinv[rows, :2] @ np.linalg.inv(Hinv[:2, :2])  # C_i^+ B_i^T
        own = Hinv[rows] @ J[i].T  # x0_i's move per residual of trajectory i
        b = W @ (Hinv[:2] @ J[i].T)  # the part of it through theta
        a = own + b
        pooled = a @ sigma @ a.T - a @ sigma @ b.T - b @ sigma @ a.T
        x0_cov.append(pooled * n / (n - q) + W @ cov[:2, :2] @ W.T)
    return cov[:2, :2], np.stack(x0_cov)


@pytest.fixture(scope="module")
def records():
    rng = np.random.default_rng(3)
    N, T = 2, 150
    u = rng.standard_normal((N, T, 1))
    X0 = np.array([[0.5, 0.0], [-0.3, 0.4]])
    th = {"k": jnp.array(2.0), "c": jnp.array(0.4)}
    _, z = jax.vmap(lambda a, b: oj.simulate(OSC, th, a, b))(jnp.asarray(X0), jnp.asarray(u))
    z = np.asarray(z) + ar1(rng, z.shape, 0.8, 0.02)
    return u, z, X0


def test_sandwich_equals_the_dense_computation(records):
    """Two trajectories sharing theta, each with one of its two x0 entries estimated
    (eliminated per trajectory): the sandwich of the fit equals the one written out from
    the dense Jacobian (where the elimination, the x0 blocks' cross terms through theta,
    or the lag weights were wrong, they differ)."""
    u, z, X0 = records
    free = (1,)
    estimate = np.array([False, True])
    res = oj.fit(
        OSC,
        {"k": 1.5, "c": 0.3},
        X0 * 0.9,
        u,
        z,
        estimate_x0=estimate,
        covariance=oj.NeweyWest(lags=7),
    )
    assert res.success and res.names == ("c", "k")
    cov, x0_cov = dense_sandwich(OSC, res.theta, res.x0, u, z, 7, list(free))
    np.testing.assert_allclose(res.covariance, cov, rtol=1e-7)
    np.testing.assert_allclose(res.x0_covariance, x0_cov, rtol=1e-7, atol=1e-14)
    # The classical sigma^2 (J^T J)^+ differs here (the residuals are correlated).
    lag0, _ = dense_sandwich(OSC, res.theta, res.x0, u, z, 0, list(free))
    assert not np.allclose(lag0, cov, rtol=0.1)
    assert res.diagnostics["covariance_lags"] == 7
    assert "Newey-West sandwich over 7 lags" in str(res)


def test_sandwich_matches_the_spread_over_noise_draws():
    """x[k+1] = a x + b u with AR(1) noise (phi = 0.9) on the output: over 150 draws the
    classical standard errors of a and of x0 are less than half the estimates' spread;
    the sandwich's (30 lags) are within 25 % of it (x0's from the residuals'
    autocovariance pooled over the record: the sandwich of the head's few samples alone
    was far too small)."""

    def f(x, u, th):
        return jnp.stack([th["a"] * x[0] + th["b"] * u[0]])

    model = oj.Model(f, lambda x, u, th: x)
    rng = np.random.default_rng(0)
    T, draws = 400, 150
    u = rng.standard_normal((T, 1))
    _, z = oj.simulate(model, {"a": jnp.array(0.8), "b": jnp.array(0.5)}, jnp.ones(1), u)
    noise = ar1(rng, (draws, T, 1), 0.9, 0.02)
    a, se_classical, se_nw, x0, x0_se_classical, x0_se_nw = [], [], [], [], [], []
    for d in range(draws):
        zd = np.asarray(z) + noise[d]
        r = oj.fit(model, {"a": 0.8, "b": 0.5}, np.ones(1), u, zd)
        a.append(float(r.theta["a"]))
        se_classical.append(float(r.std["a"]))
        x0.append(float(r.x0[0]))
        x0_se_classical.append(float(r.x0_std[0]))
        r_nw = oj.fit(
            model, {"a": 0.8, "b": 0.5}, np.ones(1), u, zd, covariance=oj.NeweyWest(lags=30)
        )
        se_nw.append(float(r_nw.std["a"]))
        x0_se_nw.append(float(r_nw.x0_std[0]))
    for est, classical, nw in ((a, se_classical, se_nw), (x0, x0_se_classical, x0_se_nw)):
        spread = np.std(est, ddof=1)
        assert np.mean(classical) < 0.5 * spread
        assert abs(np.sqrt(np.mean(np.square(nw))) / spread - 1) < 0.25


def test_x0_of_an_output_with_missing_samples_is_not_shrunk():
    """White noise of one level on two decoupled outputs, the second measured at about
    10 % of the samples: with L = 0 the sandwich's x0 standard errors are about the
    classical ones. Pooled over all samples alike, the second output's autocovariance was
    divided by samples it does not have (x0[1]'s std 2 to 3 times too small, x0[0]'s 1.4
    times too large)."""

    def f(x, u, th):
        return jnp.stack([th["a"] * x[0] + u[0], th["b"] * x[1] + u[0]])

    model = oj.Model(f)
    T, truth, x0 = 200, {"a": 0.9, "b": 0.8}, jnp.array([1.0, -1.0])
    ratios = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        u = rng.normal(size=(T, 1))
        z = np.array(oj.simulate(model, truth, x0, u)[1]) + 0.1 * rng.normal(size=(T, 2))
        z[rng.random(T) > 0.1, 1] = np.nan
        classical = oj.fit(model, truth, x0, u, z, missing="mask")
        robust = oj.fit(model, truth, x0, u, z, missing="mask", covariance=oj.NeweyWest(lags=0))
        ratios.append(np.asarray(robust.x0_std) / np.asarray(classical.x0_std))
    ratios = np.array(ratios)
    assert np.all(np.abs(ratios[:, 0] - 1) < 0.05)
    assert 0.65 < np.mean(ratios[:, 1]) < 1.35


def test_x0_with_a_full_weight_and_missing_samples_takes_the_errors_autocovariance():
    """A full weight Q (its symmetric root mixes the outputs) with missing samples: the
    weighted residual r = Q^{1/2} e is not zero in the row of an output missing at that
    sample, and Gamma summed those rows over a count of the measured pairs (x0's std
    4 to 6 % too large, and another answer with another root of Q). Now Gamma is that
    of the errors e over their measured pairs, Q applied to the Jacobian's rows:
    sum_k (Q Je_k)^T Gamma_e,l (Q Je_k-l), written out here."""

    def f(x, u, th):
        return jnp.stack([th["a"] * x[0] + u[0], th["b"] * x[1] + 0.5 * x[0] + u[0]])

    model, T, L = oj.Model(f), 120, 3
    rng = np.random.default_rng(4)
    u = rng.normal(size=(T, 1))
    z = np.array(oj.simulate(model, {"a": 0.9, "b": 0.7}, jnp.array([1.0, -1.0]), u)[1])
    z = z + ar1(rng, (T, 2), 0.6, 0.05)
    z[rng.random(z.shape) < 0.3] = np.nan
    Q = np.array([[2.0, 0.9], [0.9, 1.0]])
    r = oj.fit(
        model,
        {"a": 0.8, "b": 0.6},
        jnp.zeros(2),
        u,
        z,
        weight=Q,
        missing="mask",
        covariance=oj.NeweyWest(lags=L),
    )
    measured = ~np.isnan(z)

    def errors(v, x0):  # e (T, 2), zero where missing
        _, zhat = oj.simulate(model, {"a": v[0], "b": v[1]}, x0, u)
        return jnp.where(measured, zhat - np.nan_to_num(z), 0.0)

    v, x0 = jnp.stack([r.theta["a"], r.theta["b"]]), jnp.asarray(r.x0)
    e = np.asarray(errors(v, x0))
    Et, Ex = (np.asarray(jax.jacfwd(errors, i)(v, x0)) for i in (0, 1))  # (T, 2, 2)
    root = np.linalg.cholesky(Q).T  # (any root: r = root e, rows root Je)
    Jt, Jx = (np.einsum("op,tpa->toa", root, E).reshape(-1, 2) for E in (Et, Ex))
    C_inv = np.linalg.inv(Jx.T @ Jx)
    W = C_inv @ Jx.T @ Jt  # C^+ B^T
    Jte = Jt - Jx @ W
    S_inv = np.linalg.inv(Jte.T @ Jte)
    psi = np.einsum("tzp,tz->tp", Jte.reshape(T, 2, 2), e @ root.T) @ S_inv
    sig = psi.T @ psi
    for lag in range(1, L + 1):
        g = psi[lag:].T @ psi[:-lag]
        sig = sig + (1 - lag / (L + 1)) * (g + g.T)
    s = measured.astype(float)
    Ax = np.einsum("op,tpa->toa", Q, Ex)
    Bx = np.einsum("op,tpa->toa", Q, (Et.reshape(-1, 2) - Ex.reshape(-1, 2) @ W).reshape(T, 2, 2))

    def K(X, Y):
        out = np.zeros((2, 2))
        for lag in range(L + 1):
            gamma = e[lag:].T @ e[: T - lag] * (T - lag)
            gamma = gamma / np.maximum(s[lag:].T @ s[: T - lag], 1.0) / T
            w = 1 - lag / (L + 1)
            out += w * np.einsum("toa,op,tpb->ab", X[lag:], gamma, Y[: T - lag])
            if lag:
                out += w * np.einsum("toa,op,tpb->ab", X[: T - lag], gamma.T, Y[lag:])
        return out

    mix = C_inv @ K(Ax, Bx) @ S_inv @ W.T
    x0_cov = C_inv @ K(Ax, Ax) @ C_inv - mix - mix.T + W @ sig @ W.T
    n = int(s.sum())
    np.testing.assert_allclose(r.x0_covariance, x0_cov * n / (n - 4), rtol=1e-7)


def test_default_lags_follow_the_newey_west_rule():
    assert oj.NeweyWest().resolved(100) == 4
    assert oj.NeweyWest().resolved(25000) == int(np.floor(4 * 250 ** (2 / 9)))
    assert oj.NeweyWest(lags=0).resolved(10) == 0


def test_bad_covariance_arguments_are_refused(records):
    u, z, X0 = records
    with pytest.raises(ValueError, match="lags"):
        oj.NeweyWest(lags=-1)
    with pytest.raises(ValueError, match="lags"):
        oj.NeweyWest(lags=2.5)
    with pytest.raises(ValueError, match="`covariance`"):
        oj.fit(OSC, {"k": 1.5, "c": 0.3}, X0, u, z, covariance="robust")
    with pytest.raises(ValueError, match="exceeds a trajectory's length"):
        oj.fit(OSC, {"k": 1.5, "c": 0.3}, X0, u, z, covariance=oj.NeweyWest(lags=150))
    with pytest.raises(ValueError, match="penalty"):
        oj.fit(
            OSC,
            {"k": 1.5, "c": 0.3},
            X0,
            u,
            z,
            penalty=lambda x, th: 1.0 - x[0] ** 2,
            covariance="newey_west",
        )


class _Damping(eqx.Module):
    """sum_h w2_h tanh(w1_h v + b1_h): with identical units, the differences between
    them leave the output unchanged (an exact null space of the network's weights)."""

    w1: jax.Array
    b1: jax.Array
    w2: jax.Array

    def __call__(self, v):
        return jnp.sum(self.w2 * jnp.tanh(self.w1 * v + self.b1))


def _hybrid_rhs(x, u, th):
    return jnp.stack([x[1], -th["k"] * x[0] - th["r"](x[1]) + u[0]])


HYBRID = oj.Model.from_ode(_hybrid_rhs, 0.1, observe=lambda x, u, th: x[:1])


def dense_marginal_sandwich(theta, x0, u, z, lags, free_x0):
    """The named parameter k's sandwich with the network's weights and the free x0
    entries as nuisance, written out from the dense Jacobian of all residuals: the
    influence of k's column with the nuisance columns' range projected out (an SVD
    basis), its Bartlett-weighted long-run variance, times n / (n - q)."""
    N, T, n_z = z.shape
    r_net = theta["r"]
    H = r_net.w1.shape[0]
    m = len(free_x0)

    def residuals(v):
        net = _Damping(v[1 : 1 + H], v[1 + H : 1 + 2 * H], v[1 + 2 * H : 1 + 3 * H])
        th = {"k": v[0], "r": net}
        X0 = jnp.asarray(x0).at[:, free_x0].set(v[1 + 3 * H :].reshape(N, m))
        _, zhat = jax.vmap(lambda a, b: oj.simulate(HYBRID, th, a, b))(X0, u)
        return (zhat - z).reshape(N * T * n_z)

    v = jnp.concatenate(
        [jnp.atleast_1d(theta["k"]), r_net.w1, r_net.b1, r_net.w2, x0[:, free_x0].ravel()]
    )
    # (the algebra in NumPy: JAX's slices and `.at[...].set`, run eagerly, compile a
    # program per new slice, hundreds of them)
    e = np.asarray(residuals(v))
    J = np.asarray(jax.jacfwd(residuals)(v))
    U, s, _ = np.linalg.svd(J[:, 1:], full_matrices=False)
    # the near-duplicate units' difference (about 1e-9 of the largest singular value, the
    # next one above 1e-4) is null, as the library judges it
    Q = U[:, s > 1e-6 * s[0]]
    jp = J[:, 0] - Q @ (Q.T @ J[:, 0])  # k's column, the nuisance range projected out
    psi = (jp * e).reshape(N, T * n_z) / (jp @ jp)
    omega = np.sum(psi * psi)
    for lag in range(1, lags + 1):
        omega += 2 * (1 - lag / (lags + 1)) * np.sum(psi[:, lag:] * psi[:, :-lag])
    n, q = e.size, J.shape[1]
    return omega * n / (n - q)


def test_hybrid_sandwich_projects_the_network_out():
    """A theta with a network of two alike units (a null space of its weights) under
    AR(1) noise: the fit reports a sandwich (it used to refuse one for a network); k's
    Newey-West variance equals the dense computation with the network's and x0's columns
    projected out (the projection of the classical marginal covariance), it is finite
    while the network's weights are not identifiable, and it differs from the classical
    variance (the residuals are correlated)."""
    u, z, X0 = records_of(np.random.default_rng(5))
    net = _Damping(jnp.array([1.0, 1.0]), jnp.array([0.0, 0.0]), jnp.array([0.2, 0.2]))
    theta0 = {"k": 1.5, "r": net}
    estimate = np.array([False, True])
    kw = dict(estimate_x0=estimate, solver=oj.LevenbergMarquardt(max_steps=20))
    res = oj.fit(HYBRID, theta0, X0, u, z, covariance=oj.NeweyWest(lags=7), **kw)
    r = res.theta["r"]
    np.testing.assert_allclose(r.w1[0], r.w1[1], rtol=1e-5)  # the units stayed alike
    var_k = dense_marginal_sandwich(res.theta, res.x0, u, z, 7, [1])
    np.testing.assert_allclose(res.std["k"] ** 2, var_k, rtol=1e-6)
    assert np.all(np.isinf(res.std["r"].w1))
    classical = oj.fit(HYBRID, theta0, X0, u, z, **kw)
    assert np.isfinite(classical.std["k"])
    assert not np.isclose(classical.std["k"], res.std["k"], rtol=0.1)
    assert "Newey-West sandwich over 7 lags" in str(res)


def records_of(rng):
    N, T = 2, 150
    u = rng.standard_normal((N, T, 1))
    X0 = np.array([[0.5, 0.0], [-0.3, 0.4]])
    th = {"k": jnp.array(2.0), "c": jnp.array(0.4)}
    _, z = jax.vmap(lambda a, b: oj.simulate(OSC, th, a, b))(jnp.asarray(X0), jnp.asarray(u))
    return u, np.asarray(z) + ar1(rng, z.shape, 0.8, 0.02), X0


def test_float32_data_give_float32_standard_errors():
    """float32 data (x64 on) give float32 standard errors and covariances: with a fixed
    entry of theta or x0, `assemble` scattered them into np.zeros (float64 by default);
    estimate_x0's covariance was float64 always."""
    f = np.float32
    rng = np.random.default_rng(0)
    u = rng.standard_normal((80, 1)).astype(f)
    _, z = oj.simulate(OSC, {"k": f(2.0), "c": f(0.5)}, np.array([1.0, 0.0], f), u)
    z = np.asarray(z) + f(0.01) * rng.standard_normal(z.shape).astype(f)
    th0, x0 = {"k": f(1.5), "c": f(0.8)}, np.array([0.8, 0.0], f)
    runs = [
        oj.fit(OSC, th0, x0, u, z, covariance="newey_west"),
        oj.fit(OSC, th0, x0, u, z, fixed={"c": True}),
        oj.fit(OSC, th0, np.array([1.0, 0.0], f), u, z, estimate_x0=[True, False]),
    ]
    for r in runs:
        arrays = [*r.std.values(), r.covariance, r.x0_std, r.x0_covariance]
        assert all(np.asarray(a).dtype == np.float32 for a in arrays), [a.dtype for a in arrays]
    est = oj.estimate_x0(OSC, runs[0].theta, u, z, n=20, x0=x0)
    assert est.std.dtype == np.float32 and est.covariance.dtype == np.float32
