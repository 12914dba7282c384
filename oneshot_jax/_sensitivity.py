r"""Closed-form Jacobian of the stacked residuals, the forward twin of eq. (17) and (20).

The least-squares solvers minimise C = ||r||^2 with residuals

    r_k = Q^{1/2} e_k / sqrt(T N)                    (k = 0..T-1, N trajectories)
    r^h_k = sqrt(penalty_weight h(x_k, theta) / (T N))   (only when a penalty is given)

so that ||r||^2 is exactly the C of eq. (5)/(21). A penalty therefore has to be
non-negative in this form (an exponential barrier or a squared energy deviation is; a
signed h is clipped at 0).

The Jacobian of the states in the free parameters p = (theta, x0) follows the sensitivity
recursion

    S_0 = [0, I],    S_{k+1} = J^{x/x}_{k+1} S_k + [J^{x/theta}_{k+1}, 0],

which accumulates, forwards in time, the same chained products J^{x/x}_tau ... J^{x/x}_{k+1}
J^{x/theta}_k as eq. (17) (theta columns) and eq. (20) (x0 columns). Then
dr_k/dp = Q^{1/2} (J^{z/x}_k S_k + [J^{z/theta}_k, 0]) / sqrt(T N). Forward mode costs
O(T n_x^2 (n_theta + n_x0)) with formed Jacobians (O(T n_x (n_theta + n_x0)) JVPs
matrix-free) and gives every row of the Jacobian, which is what Gauss-Newton needs; the
reverse recursion of `value_and_grad` gives one row-sum (the gradient) in O(T n_x^2).
"""

import jax
import jax.numpy as jnp

from ._gradient import _JACOBIAN_MAX_NX, choose_strategy
from ._simulate import rollout

# Up to this state size the scan's A @ S is written elementwise (see `_matmul`).
_MATMUL_ELEMENTWISE_MAX = _JACOBIAN_MAX_NX
# "auto" forms the per-step Jacobians only while a step of the scan, over all N
# trajectories, moves at most this many sensitivity entries (N n_x n_cols): beyond it the
# in-scan JVPs are large vectorised operations anyway, and forming J^{x/x} costs more
# (on XLA:CPU with n_x = 2..3 and 5..6 columns the two cross between N = 16 and N = 64).
_JACOBIAN_MAX_BATCH_WORK = 512


def sensitivity_strategy(strategy, n_traj, n_x, n_cols, T, itemsize):
    """Resolve "auto" for the sensitivity recursion of N = `n_traj` trajectories (vmapped):
    formed Jacobians ("jacobian") for small states and small batches, where the scan is
    dominated by its per-step cost, matrix-free JVPs ("vjp") otherwise."""
    if strategy != "auto":
        return strategy
    if n_traj * n_x * n_cols > _JACOBIAN_MAX_BATCH_WORK:
        return "vjp"
    return choose_strategy(strategy, n_x, T, itemsize)


def trajectory_residuals(
    model, theta_of, p_theta, x0, u, z, sqrt_q, penalty, penalty_weight, scale
):
    """Residuals r (R,) of one trajectory, R = T n_z (+ T with a penalty)."""
    theta = theta_of(p_theta)
    xs = rollout(model, theta, x0, u)
    e = jax.vmap(model.observe, in_axes=(0, 0, None))(xs, u, theta) - z
    r = _weigh(e, sqrt_q) * scale
    r = r.reshape(-1)
    if penalty is not None:
        h = jax.vmap(penalty, in_axes=(0, None))(xs, theta)
        r = jnp.concatenate([r, jnp.sqrt(jnp.maximum(penalty_weight * h, 0.0)) * scale])
    return r


def _weigh(e, sqrt_q):
    if sqrt_q is None:
        return e
    if sqrt_q.ndim == 1:
        return e * sqrt_q
    return e @ sqrt_q.T


def trajectory_jacobian(
    model,
    theta_of,
    p_theta,
    x0_of,
    p_x0,
    u,
    z,
    sqrt_q,
    penalty,
    penalty_weight,
    scale,
    strategy="auto",
):
    """Residuals r (R,) and their Jacobians (R, n_p_theta), (R, n_p_x0) for one trajectory.

    `theta_of(p_theta)` maps the free parameter vector to the theta pytree, `x0_of(p_x0)`
    the free initial-state entries to x0 (fixed entries are constants inside both), so
    the columns are exactly the free variables.

    `strategy` picks how the sensitivity recursion S_{k+1} = J^{x/x} S_k + [J^{x/theta}, 0]
    is evaluated, with the same rule and names as the gradient (`choose_strategy`):
    `"jacobian"` forms every J^{x/x}_k and J^{x/theta}_k at once after the forward pass
    (vmapped forward mode, the paper's Remark 1) and the scan is left with small
    matrix products; `"vjp"` (matrix-free) pushes the columns of S_k through the step
    as JVPs inside the scan, never forming J^{x/x} (a banded or sparse step costs what
    its JVP costs), and stores only the output rows J^{z/x}_k S_k, not S_k.
    """
    x0 = x0_of(p_x0)
    n_t, n_s = p_theta.shape[0], p_x0.shape[0]
    n_x = x0.shape[0]
    f_theta = lambda x, u_k, p: model.step(x, u_k, theta_of(p))  # noqa: E731
    # S_0 = d x0 / d (p_theta, p_x0) = [0, d x0/d p_x0]
    S0 = jnp.concatenate([jnp.zeros((n_x, n_t), x0.dtype), jax.jacfwd(x0_of)(p_x0)], axis=1)
    # Tangent of p for each column: e_j for the theta columns, 0 for the x0 columns.
    E = jnp.concatenate([jnp.eye(n_t, dtype=x0.dtype), jnp.zeros((n_t, n_s), x0.dtype)], 1)
    g_theta = lambda x, u_k, p: model.observe(x, u_k, theta_of(p))  # noqa: E731
    h_theta = None if penalty is None else (lambda x, p: penalty(x, theta_of(p)))  # noqa: E731

    def outputs(x, u_k, S):
        """z_k and J^{z/x}_k S_k + [J^{z/theta}_k, 0] (and the same for the penalty h) as
        JVPs of the output map along the columns, without forming J^{z/x}."""
        out = _push(lambda x, p: g_theta(x, u_k, p), x, p_theta, S, E)
        return out if h_theta is None else (*out, *_push(h_theta, x, p_theta, S, E))

    # One trajectory here; `Problem.jacobian` resolves "auto" for its whole batch.
    strategy = sensitivity_strategy(strategy, 1, n_x, n_t + n_s, u.shape[0], x0.dtype.itemsize)
    if strategy == "jacobian":
        xs = rollout(model, theta_of(p_theta), x0, u)
        A, B = jax.vmap(jax.jacfwd(f_theta, argnums=(0, 2)), in_axes=(0, 0, None))(
            xs[:-1], u[:-1], p_theta
        )
        B = jnp.concatenate([B, jnp.zeros((*B.shape[:2], n_s), B.dtype)], axis=2)

        def body(S, AB):
            S_next = _matmul(AB[0], S) + AB[1]
            return S_next, S_next

        _, Ss = jax.lax.scan(body, S0, (A, B))
        Ss = jnp.concatenate([S0[None], Ss], axis=0)
        outs = jax.vmap(outputs)(xs, u, Ss)
    elif strategy == "vjp":
        # Each step emits the outputs of (x_k, S_k), then advances: only the (n_z, columns)
        # rows are stored, never S_k (the step past the last sample is not used).
        def body(carry, u_k):
            x, S = carry
            out = outputs(x, u_k, S)
            return _push(lambda x, p: f_theta(x, u_k, p), x, p_theta, S, E), out

        _, outs = jax.lax.scan(body, (x0, S0), u)
    else:
        raise ValueError(f"unknown strategy {strategy!r}")

    y, Je = outs[:2]
    e = y - z
    r = (_weigh(e, sqrt_q) * scale).reshape(-1)
    Jr = _weigh_jac(Je, sqrt_q) * scale
    Jr = Jr.reshape(-1, n_t + n_s)
    if penalty is not None:
        h, dh = outs[2:]
        ph = jnp.maximum(penalty_weight * h, 0.0)
        rh = jnp.sqrt(ph)
        # d sqrt(lambda h) = lambda h' / (2 sqrt(lambda h)); zero where the penalty is inactive.
        safe = jnp.where(rh > 0, rh, 1.0)
        Jh = jnp.where((rh > 0)[:, None], penalty_weight * dh / (2.0 * safe[:, None]), 0.0)
        r = jnp.concatenate([r, rh * scale])
        Jr = jnp.concatenate([Jr, Jh * scale], axis=0)
    return r, Jr[:, :n_t], Jr[:, n_t:]


def _weigh_jac(Je, sqrt_q):
    if sqrt_q is None:
        return Je
    if sqrt_q.ndim == 1:
        return Je * sqrt_q[None, :, None]
    return jnp.einsum("ij,kjp->kip", sqrt_q, Je)


def _push(fn, x, p, S, E):
    """fn(x, p) and its directional derivatives along the columns (S[:, j], E[:, j]):
    J^{fn/x} S + J^{fn/p} E by one vmapped JVP, with the columns last."""
    return jax.vmap(lambda s, e: jax.jvp(fn, (x, p), (s, e)), in_axes=1, out_axes=(None, -1))(S, E)


def _matmul(A, S):
    """A @ S; for a small A as a broadcast multiply and a sum, which XLA:CPU compiles into
    the scan's single loop kernel (a `dot` there runs as a separate call per step)."""
    if A.shape[-1] <= _MATMUL_ELEMENTWISE_MAX:
        return jnp.sum(A[:, :, None] * S[None, :, :], axis=1)
    return A @ S
