"""The one-shot gradient of eq. (17) and (20) against three independent references.

- Oracle A: `jax.grad` of the cost written out in the test (our own RK4 in a Python
  for-loop, our own sum of e^T Q e + lambda h), see `helpers.GradientCase.oracle_a_cost`.
- Oracle B: `jax.grad` through a diffrax rollout with classical RK4 given as a
  `ButcherTableau`, one `diffeqsolve` per sample interval (`helpers.diffrax_rollout`).
- The literal O(T^2) double sums of eq. (17) and (20), `literal_value_and_grad`.

Every case runs with both strategies; all agree to 1e-10 (norm-wise, per leaf) in float64.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    PROBLEMS,
    GradientCase,
    assert_tree_rel_close,
    cast,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oneshot_jax as oj

# float64: the three references and both strategies differ only by round-off.
RTOL = 1e-10
STRATEGIES = ["jacobian", "vjp"]
ORACLES = ["own_rk4_loop", "diffrax_rk4", "literal_eq17_eq20"]


@functools.cache
def problem(name) -> GradientCase:
    return PROBLEMS[name]()


@functools.cache
def one_shot(name, strategy):
    p = problem(name)
    return oj.value_and_grad(
        p.model(), p.theta, p.x0, p.u, p.z, strategy=strategy, **p.cost_kwargs()
    )


@functools.cache
def reference(name, oracle):
    p = problem(name)
    if oracle == "own_rk4_loop":
        return jax.value_and_grad(p.oracle_a_cost, argnums=(0, 1))(p.theta, p.x0)
    if oracle == "diffrax_rk4":
        return jax.jit(jax.value_and_grad(p.oracle_b_cost, argnums=(0, 1)))(p.theta, p.x0)
    if oracle == "literal_eq17_eq20":
        return oj.literal_value_and_grad(p.model(), p.theta, p.x0, p.u, p.z, **p.cost_kwargs())
    raise AssertionError(oracle)


def assert_value_and_grad_close(actual, expected, rtol=RTOL):
    C, (g_theta, g_x0) = actual
    C_ref, (g_theta_ref, g_x0_ref) = expected
    assert jnp.shape(C) == ()
    assert_tree_rel_close(C, C_ref, rtol=rtol)
    assert_tree_rel_close(g_theta, g_theta_ref, rtol=rtol)
    assert_tree_rel_close(g_x0, g_x0_ref, rtol=rtol)


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("oracle", ORACLES)
@pytest.mark.parametrize("case", list(PROBLEMS))
def test_one_shot_matches_references(case, oracle, strategy):
    assert_value_and_grad_close(one_shot(case, strategy), reference(case, oracle))


@pytest.mark.parametrize("case", list(PROBLEMS))
def test_cases_are_not_trivial(case):
    # Guards the comparisons above against passing vacuously: residuals are non-zero and
    # every gradient leaf that the model uses is non-zero.
    p = problem(case)
    C, (g_theta, g_x0) = reference(case, "own_rk4_loop")
    assert float(C) > 0
    assert g_x0.shape == jnp.shape(p.x0)
    assert np.all(np.linalg.norm(np.atleast_2d(g_x0), axis=-1) > 0)
    for path, leaf in jax.tree_util.tree_leaves_with_path(g_theta):
        if "unused" not in jax.tree_util.keystr(path):
            assert np.linalg.norm(leaf) > 0, f"zero gradient for theta{jax.tree_util.keystr(path)}"


@pytest.mark.parametrize("method", STRATEGIES + ["literal"])
def test_unused_theta_entry_has_exactly_zero_gradient(method):
    name = "observe_u_theta_unused_entry"
    if method == "literal":
        _, (g_theta, _) = reference(name, "literal_eq17_eq20")
    else:
        _, (g_theta, _) = one_shot(name, method)
    assert g_theta["unused"].shape == (2, 3)
    assert np.all(np.asarray(g_theta["unused"]) == 0.0)
    assert np.all(np.asarray(g_theta["R"]) != 0.0)


def test_satellite_is_the_paper_setup():
    # Section 4: T = 50 samples at 0.1 s, the gradient taken away from the true values.
    p = problem("satellite")
    assert p.u.shape == (50, 3) and p.z.shape == (50, 3) and p.dt == 0.1
    true_theta = jnp.array([0.0403, 0.0404, 0.0080])
    assert not np.allclose(p.theta, true_theta)
    assert abs(float(jnp.mean(p.u)) - 1e-5) < 1e-7


@pytest.mark.parametrize("case", ["satellite"])
def test_auto_strategy_small_state(case):
    # n_x = 3: "auto" picks the stacked Jacobians.
    p = problem(case)
    out = oj.value_and_grad(p.model(), p.theta, p.x0, p.u, p.z, strategy="auto", **p.cost_kwargs())
    assert_value_and_grad_close(out, one_shot(case, "jacobian"))


# Module-level (not closures), so that examples with equal shapes reuse compiled code.
def linear_step(x, u, theta):
    return theta["A"] @ x + theta["B"] @ u


def linear_observe(x, u, theta):
    return theta["C"] @ x + theta["D"] @ u


def _linear_problem(rng, T, n_x, n_u, n_z, weight_kind="none", N=None, rho=0.9):
    """x_{k+1} = A x + B u, z = C x + D u with A scaled to spectral radius `rho`."""
    A = rng.standard_normal((n_x, n_x))
    radius = np.max(np.abs(np.linalg.eigvals(A)))
    A = A * (rho / radius) if radius > 0 else A
    theta = {
        "A": jnp.asarray(A),
        "B": jnp.asarray(rng.standard_normal((n_x, n_u))),
        "C": jnp.asarray(rng.standard_normal((n_z, n_x))),
        "D": jnp.asarray(rng.standard_normal((n_z, n_u))),
    }
    lead = () if N is None else (N,)
    x0 = jnp.asarray(rng.standard_normal((*lead, n_x)))
    u = jnp.asarray(rng.standard_normal((*lead, T, n_u)))
    z = jnp.asarray(rng.standard_normal((*lead, T, n_z)))
    if weight_kind == "none":
        weight = None
    elif weight_kind == "diag":
        weight = jnp.asarray(rng.random(n_z))
    else:
        L = rng.standard_normal((n_z, max(n_z - 1, 1)))
        weight = jnp.asarray(L @ L.T)
    return GradientCase(
        "linear",
        theta,
        x0,
        u,
        z,
        step=linear_step,
        observe=linear_observe,
        weight=weight,
    )


# Shapes come from small sets, so that examples share compiled code (the eager oracle and
# the literal reference compile every primitive once per shape).
@settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    T=st.sampled_from([1, 2, 4, 7]),
    n_x=st.sampled_from([1, 2, 4]),
    n_u=st.sampled_from([1, 3]),
    n_z=st.sampled_from([1, 2, 3]),
    weight_kind=st.sampled_from(["none", "diag", "psd"]),
    N=st.sampled_from([None, 1, 3]),
    seed=st.integers(0, 2**32 - 1),
)
def test_random_linear_systems(T, n_x, n_u, n_z, weight_kind, N, seed):
    p = _linear_problem(np.random.default_rng(seed), T, n_x, n_u, n_z, weight_kind, N)
    expected = jax.value_and_grad(p.oracle_a_cost, argnums=(0, 1))(p.theta, p.x0)
    literal = oj.literal_value_and_grad(p.model(), p.theta, p.x0, p.u, p.z, weight=p.weight)
    assert_value_and_grad_close(literal, expected)
    for strategy in STRATEGIES:
        out = oj.value_and_grad(
            p.model(), p.theta, p.x0, p.u, p.z, weight=p.weight, strategy=strategy
        )
        assert_value_and_grad_close(out, expected)


def test_auto_strategy_large_state():
    # n_x = 70: "auto" switches to in-scan VJPs; the answer must not change.
    p = _linear_problem(np.random.default_rng(0), T=4, n_x=70, n_u=2, n_z=3)
    expected = jax.value_and_grad(p.oracle_a_cost, argnums=(0, 1))(p.theta, p.x0)
    for strategy in ["auto", "vjp", "jacobian"]:
        out = oj.value_and_grad(p.model(), p.theta, p.x0, p.u, p.z, strategy=strategy)
        assert_value_and_grad_close(out, expected)


def test_gradient_under_jit_and_vmap():
    # The gradient is traceable: jit over (theta, x0), and vmap over a batch of theta.
    p = problem("lotka_volterra")
    model, kw = p.model(), p.cost_kwargs()
    fn = lambda th, x0: oj.value_and_grad(model, th, x0, p.u, p.z, strategy="vjp", **kw)  # noqa: E731
    assert_value_and_grad_close(jax.jit(fn)(p.theta, p.x0), one_shot("lotka_volterra", "vjp"))
    thetas = jnp.stack([p.theta, 1.1 * p.theta])
    C, (g_theta, g_x0) = jax.vmap(fn, in_axes=(0, None))(thetas, p.x0)
    for i in range(2):
        assert_value_and_grad_close((C[i], (g_theta[i], g_x0[i])), fn(thetas[i], p.x0), rtol=1e-12)


#
# float32
#

# float32 tolerance: 1e-4 relative to the float64 gradient (norm-wise, per leaf). The
# inputs are rounded to float32 (~6e-8) and each of the T <= 50 steps of the rollout and of
# the reverse recursion rounds again; on these cases the float32 results differ from float64
# by at most ~5e-6, so 1e-4 leaves a 20x margin across platforms while still catching a
# wrong gradient. Output dtypes are checked too: a float32 call must not silently compute
# (or return) float64.
RTOL_FLOAT32 = 1e-4


@pytest.mark.parametrize(
    "case, method",
    [
        (case, method)
        for case in ["satellite", "observe_u_theta_unused_entry"]
        for method in STRATEGIES
    ]
    + [("satellite", "literal")],
)
def test_float32(case, method):
    p = problem(case)
    theta, x0, u, z, weight = cast((p.theta, p.x0, p.u, p.z, p.weight), jnp.float32)
    kw = dict(weight=weight, penalty=p.penalty, penalty_weight=p.penalty_weight)
    if method == "literal":
        out = oj.literal_value_and_grad(p.model(), theta, x0, u, z, **kw)
    else:
        out = oj.value_and_grad(p.model(), theta, x0, u, z, strategy=method, **kw)
    for leaf in jax.tree_util.tree_leaves(out):
        assert leaf.dtype == jnp.float32
    expected = one_shot(case, "jacobian")
    assert_value_and_grad_close(cast(out, jnp.float64), expected, rtol=RTOL_FLOAT32)
    x, z_hat = oj.simulate(p.model(), theta, x0, u)
    assert x.dtype == jnp.float32 and z_hat.dtype == jnp.float32
    assert oj.loss(p.model(), theta, x0, u, z, **kw).dtype == jnp.float32


def test_float32_with_python_scalar_penalty_weight():
    p = problem("satellite")
    theta, x0, u, z = cast((p.theta, p.x0, p.u, p.z), jnp.float32)
    pen = lambda x, th: jnp.sum(jnp.exp(-th / 0.01))  # noqa: E731
    C, (g_theta, g_x0) = oj.value_and_grad(
        p.model(), theta, x0, u, z, penalty=pen, penalty_weight=0.5
    )
    assert C.dtype == g_theta.dtype == g_x0.dtype == jnp.float32
    assert oj.loss(p.model(), theta, x0, u, z, penalty=pen, penalty_weight=0.5).dtype == (
        jnp.float32
    )


#
# Strategy objects: the strings are aliases of `oj.Auto()`, `oj.Jacobian()`, `oj.VJP()`.
#


@pytest.mark.parametrize(
    "alias, strategy", [("auto", oj.Auto()), ("jacobian", oj.Jacobian()), ("vjp", oj.VJP())]
)
@pytest.mark.parametrize("case", ["energy_penalty", "multi_trajectory"])
def test_string_aliases_equal_the_strategy_objects_bit_for_bit(case, alias, strategy):
    p = problem(case)
    got = oj.value_and_grad(
        p.model(), p.theta, p.x0, p.u, p.z, strategy=strategy, **p.cost_kwargs()
    )
    for a, b in zip(
        jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(one_shot(case, alias))
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for fn in (oj.simulate, oj.loss):
        args = (p.model(), p.theta, p.x0, p.u) + ((p.z,) if fn is oj.loss else ())
        kw = p.cost_kwargs() if fn is oj.loss else {}
        want = fn(*args, strategy=alias, **kw)
        have = fn(*args, strategy=strategy, **kw)
        for a, b in zip(jax.tree_util.tree_leaves(have), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_auto_resolves_by_size():
    """`Auto.resolve` is the one "auto" rule: small states stack Jacobians, large states
    and large sensitivity batches are matrix-free, and a CPU never goes parallel."""
    assert oj.Auto().resolve(3, 10**6, 8) == oj.Jacobian()
    assert oj.Auto().resolve(17, 100, 8) == oj.VJP()
    assert oj.Auto().resolve(3, 100, 8, n_traj=64, n_cols=6) == oj.VJP()
    assert oj.Auto().resolve(3, 100, 8, n_traj=16, n_cols=6) == oj.Jacobian()
    assert oj.Jacobian().resolve(100, 100, 8) == oj.Jacobian()
    assert oj.ParallelInTime(chunk_size=8).resolve(3, 100, 8) == oj.ParallelInTime(chunk_size=8)


@pytest.mark.parametrize("bad", ["adjoint", None, oj.Jacobian, 3])
def test_bad_strategy_names_the_argument(bad):
    with pytest.raises(ValueError, match=r"`strategy` must be 'auto'.*strategy object"):
        oj.simulate(
            *(lambda p: (p.model(), p.theta, p.x0, p.u))(problem("satellite")), strategy=bad
        )
    with pytest.raises(ValueError, match=r"`GaussNewton\(strategy=...\)` must be"):
        oj.GaussNewton(strategy=bad)
