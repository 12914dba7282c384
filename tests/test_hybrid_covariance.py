"""Standard errors of the physical parameters of a hybrid model (`_covariance.marginal`).

A network in theta has directions that leave its output (nearly) unchanged. The
Moore-Penrose inverse of J^T J mixes those numerically null directions into every
parameter, so a well-determined physical parameter was reported "not identifiable" (std
inf). With the network's weights as nuisance parameters, the physical parameters'
covariance is (J_p^T (I - P_n) J_p)^+: checked here against NumPy on the autodiff
Jacobian, on a regular case (where it is the block of (J^T J)^{-1}), an over-parameterised
network (finite, and the interval holds the truth) and an exact confounding (inf).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.residual import MLP

DT, T = 0.02, 300
W0SQ = 9.0


def _truth_rhs(x, u, th):
    a, w = x
    return jnp.array([w, -th["w0sq"] * jnp.sin(a) - 0.4 * w - 0.5 * jnp.tanh(3 * w) + u[0]])


def _observe(x, u, th):
    return x[:1]


def _data(seed=0, noise=0.01):
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.normal(0.0, 3.0, T // 20 + 1), 20)[:T, None]
    model = oj.Model.from_ode(_truth_rhs, DT, observe=_observe)
    x0 = np.array([0.3, 0.0])
    _, z = oj.simulate(model, {"w0sq": W0SQ}, x0, u)
    return u, np.asarray(z) + noise * rng.normal(size=np.shape(z)), x0


def _autodiff_jacobian(model, result, u, z):
    """Residuals and their Jacobian in (theta's floating leaves, x0), by jax.jacfwd of a
    plain simulation: the oracle."""
    params, static = eqx.partition(result.theta, eqx.is_inexact_array)
    flat, unravel = ravel_pytree(params)
    n_x = np.size(result.x0)

    def residuals(v):
        theta = eqx.combine(unravel(v[:-n_x]), static)
        _, zhat = oj.simulate(model, theta, v[-n_x:], u)
        return (zhat - z).ravel()

    v = jnp.concatenate([flat, jnp.asarray(result.x0)])
    return np.asarray(residuals(v)), np.asarray(jax.jacfwd(residuals)(v)), np.asarray(flat)


def _marginal_std(r, J, i, cutoffs=(1e-8, 1e-7, 1e-6, 1e-5)):
    """NumPy's marginal std of variable i, one per cutoff: its column with its projection
    onto the range of the other columns (Jacobi-scaled, singular values above `cutoff`
    of the largest) removed, sigma^2 = r^T r / (R - n)."""
    s2 = r @ r / (r.size - J.shape[1])
    others = np.delete(J, i, axis=1)
    scale = np.linalg.norm(others, axis=0)
    U, S, _ = np.linalg.svd(others / np.where(scale > 0, scale, 1.0), full_matrices=False)
    refs = []
    for cutoff in cutoffs:
        Ur = U[:, S > cutoff * S[0]]
        perp = J[:, i] - Ur @ (Ur.T @ J[:, i])
        refs.append(np.sqrt(s2 / (perp @ perp)))
    return refs


def _index(flat, value):
    (i,) = np.flatnonzero(flat == value)
    return int(i)


def test_regular_module_std_is_the_block_of_the_inverse():
    # A module with a regular Jacobian (an affine map of the rate): the marginal
    # covariance must equal sigma^2 (J^T J)^{-1} of the whole Jacobian, every entry.
    def rhs(x, u, th):
        a, w = x
        return jnp.array([w, -th["w0sq"] * jnp.sin(a) - th["lin"](jnp.array([w]))[0] + u[0]])

    model = oj.Model.from_ode(rhs, DT, observe=_observe)
    u, z, x0 = _data()
    lin = eqx.nn.Linear(1, 1, key=jax.random.PRNGKey(0))
    lin = eqx.tree_at(lambda m: (m.weight, m.bias), lin, (jnp.array([[0.5]]), jnp.array([0.0])))
    res = oj.fit(model, {"w0sq": 8.0, "lin": lin}, x0, u, z)
    assert res.success
    r, J, flat = _autodiff_jacobian(model, res, u, z)
    s2 = r @ r / (r.size - J.shape[1])
    cov = s2 * np.linalg.inv(J.T @ J)
    i = _index(flat, res.theta["w0sq"])
    np.testing.assert_allclose(res.std["w0sq"], np.sqrt(cov[i, i]), rtol=1e-5)
    j = _index(flat, float(res.theta["lin"].weight[0, 0]))
    np.testing.assert_allclose(
        np.asarray(res.std["lin"].weight)[0, 0], np.sqrt(cov[j, j]), rtol=1e-5
    )


def test_over_parameterised_network_leaves_the_physics_identifiable():
    # The damping replaced by an MLP of the rate: 97 weights, many of them in numerically
    # null directions of J^T J.
    def rhs(x, u, th):
        a, w = x
        return jnp.array([w, -th["w0sq"] * jnp.sin(a) - th["net"](jnp.array([w]))[0] + u[0]])

    model = oj.Model.from_ode(rhs, DT, observe=_observe)
    u, z, x0 = _data()
    net = MLP(1, 1, widths=(8, 8), key=jax.random.PRNGKey(1))
    with pytest.warns(UserWarning, match="null space"):  # the network's weights
        res = oj.fit(
            model, {"w0sq": 9.5, "net": net}, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=40)
        )
    r, J, flat = _autodiff_jacobian(model, res, u, z)
    i = _index(flat, res.theta["w0sq"])

    # The case is one where the whole matrix's null space touches w0sq: the
    # Moore-Penrose flags (a null eigenvector with a w0sq component) would say inf.
    M = J.T @ J
    d = np.sqrt(np.diag(M))
    vals, vecs = np.linalg.eigh(M / np.outer(d, d))
    null = vals <= 1e3 * np.finfo(float).eps * np.max(np.abs(vals))
    assert null.any() and np.max(np.abs(vecs[i, null])) > 1e-6

    std = res.std["w0sq"]
    assert np.isfinite(std) and std > 0
    lo, hi = res.theta["w0sq"] - 1.96 * std, res.theta["w0sq"] + 1.96 * std
    assert lo < W0SQ < hi

    # NumPy's marginal std: w0sq's column with its projection onto the range of the other
    # columns (network and x0, Jacobi-scaled, singular values above a cutoff) removed. The
    # network's singular values decay without a gap, so the cutoff moves it: the reported
    # value must lie within the range given by cutoffs around the library's
    # (sqrt(1e3 eps) ~ 5e-7 relative).
    refs = _marginal_std(r, J, i)
    assert min(refs) * 0.9 <= std <= max(refs) * 1.1, (std, refs)
    # The initial states, which the outputs determine, keep finite standard errors: the
    # network's numerically null directions are not carried over to them.
    assert np.all(np.isfinite(res.x0_std)) and np.all(res.x0_std > 0)
    # A quantity of the physics alone carries its block (the covariances with the
    # network's weights are inf): sqrt(w0sq) has std / (2 sqrt(w0sq)), not inf.
    f0 = res.delta_method(lambda th: jnp.sqrt(th["w0sq"]))
    np.testing.assert_allclose(f0.std, std / (2 * np.sqrt(res.theta["w0sq"])), rtol=1e-12)
    assert np.isinf(res.delta_method(lambda th: th["net"](jnp.array([0.3]))[0]).std)


def test_exact_confounding_stays_not_identifiable():
    # A physical stiffness k a next to an affine map of the whole state: the map's weight
    # on a produces exactly what k does, so k is not identifiable and says so.
    def rhs(x, u, th):
        a, w = x
        return jnp.array([w, -th["k"] * a - th["lin"](x)[0] + u[0]])

    model = oj.Model.from_ode(rhs, DT, observe=_observe)
    u, z, x0 = _data()
    lin = eqx.nn.Linear(2, 1, key=jax.random.PRNGKey(0))
    with pytest.warns(UserWarning, match="null space"):
        res = oj.fit(model, {"k": 8.0, "lin": lin}, x0, u, z)
    assert np.isinf(res.std["k"])
    assert np.isinf(np.asarray(res.std["lin"].weight)[0, 0])
    assert np.isfinite(np.asarray(res.std["lin"].weight)[0, 1])


def _with_null_direction(component, determined, null=1e-13):
    """A PSD matrix (unit scaling) whose eigenvalue `null` (below the cutoff, 1e3 eps)
    has an eigenvector that is variable 0's but for `component` on variables 1 and 2,
    and whose other eigenvalues are `determined`."""
    v0 = np.array([1.0, component, -0.7 * component])
    basis, _ = np.linalg.qr(np.column_stack([v0, [0.0, 1.0, 0.3], [0.0, -0.2, 1.0]]))
    return basis @ np.diag([null, *determined]) @ basis.T


def test_a_small_share_of_a_null_direction_leaves_a_poorly_determined_variable_determined():
    # Variables 1 and 2 carry 2e-6 of a numerically null direction (above the 1e-6 the
    # rule used to stop at) whose eigenvalue is 1e-13, and their variances come from
    # eigenvalues of 1e-3: kept, that direction would add a share of 4e-12 / 1e-13 = 40 to
    # variances of about 1e3, so they are determined. The same share next to eigenvalues
    # of order 1, a share of 1e-3, or an exact null direction (eigenvalue 0: c + 2e-6 a
    # next to a and b entering as a * b) would dominate: not identifiable.
    ones = np.ones(3)
    flags = oj.internal.identifiable
    np.testing.assert_array_equal(
        flags(_with_null_direction(2e-6, (1e-3, 3e-3)), ones), [False, True, True]
    )
    for component, determined, null in (
        (2e-6, (0.5, 1.0), 1e-13),
        (1e-3, (1e-3, 3e-3), 1e-13),
        (2e-6, (1e-3, 3e-3), 0.0),
    ):
        matrix = _with_null_direction(component, determined, null)
        np.testing.assert_array_equal(flags(matrix, ones), [False, False, False])
    # In float32 the cut is 1.2e-4: a null direction of eigenvalue 1e-5 carrying 2e-3 of
    # variables 1 and 2 would add a share of 0.4 to variances of 3 to 10, but the
    # directions float32 sets aside carry too much (a hybrid's errors came out 2-3x
    # small): there the plain rule holds.
    matrix32 = jnp.asarray(_with_null_direction(2e-3, (0.1, 0.3), 1e-5), jnp.float32)
    np.testing.assert_array_equal(flags(matrix32, jnp.ones(3, jnp.float32)), [False] * 3)


def test_physics_next_to_a_nearly_confounded_damping_keeps_finite_errors():
    # A linear damping c next to an MLP of the rate: the network reproduces c w almost
    # exactly, so J^T J has a numerically null direction that is c's but for components
    # of about 1e-6 on w0sq and g. They are determined all the same (their NumPy marginal
    # standard errors are finite whatever the cutoff); they were reported inf.
    def rhs(x, u, th):
        a, w = x
        net = th["net"](jnp.array([w]))[0]
        return jnp.array([w, -th["w0sq"] * jnp.sin(a) - th["c"] * w - net + th["g"] * u[0]])

    model = oj.Model.from_ode(rhs, DT, observe=_observe)
    u, z, x0 = _data()
    theta0 = {"w0sq": 9.5, "c": 0.2, "g": 0.9, "net": MLP(1, 1, (8,), key=jax.random.PRNGKey(3))}
    with pytest.warns(UserWarning, match="null space"):
        res = oj.fit(model, theta0, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=200))
    assert not np.isfinite(res.std["c"]) or res.std["c"] > 100.0  # the network's share
    r, J, flat = _autodiff_jacobian(model, res, u, z)
    for name, truth in (("w0sq", W0SQ), ("g", 1.0)):
        i = _index(flat, res.theta[name])
        std = res.std[name]
        assert np.isfinite(std) and abs(res.theta[name] - truth) < 1.96 * std, (name, std)
        refs = _marginal_std(r, J, i)  # (c and the network among the other columns)
        assert min(refs) * 0.9 <= std <= max(refs) * 1.1, (name, std, refs)
