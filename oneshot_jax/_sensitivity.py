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
O(T n_x^2 (n_theta + n_x0)) and gives every row of the Jacobian, which is what
Gauss-Newton needs; the reverse recursion of `value_and_grad` gives one row-sum (the
gradient) in O(T n_x^2).
"""

import jax
import jax.numpy as jnp

from ._simulate import rollout


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
    model, theta_of, p_theta, x0_of, p_x0, u, z, sqrt_q, penalty, penalty_weight, scale
):
    """Residuals r (R,) and their Jacobians (R, n_p_theta), (R, n_p_x0) for one trajectory.

    `theta_of(p_theta)` maps the free parameter vector to the theta pytree, `x0_of(p_x0)`
    the free initial-state entries to x0 (fixed entries are constants inside both), so
    the columns are exactly the free variables.
    """
    x0 = x0_of(p_x0)
    n_t, n_s = p_theta.shape[0], p_x0.shape[0]
    f_theta = lambda x, u_k, p: model.step(x, u_k, theta_of(p))  # noqa: E731
    # S_0 = d x0 / d (p_theta, p_x0) = [0, d x0/d p_x0]
    S0 = jnp.concatenate([jnp.zeros((x0.shape[0], n_t), x0.dtype), jax.jacfwd(x0_of)(p_x0)], axis=1)

    def body(carry, u_k):
        x, S = carry
        # One forward pass gives x_{k+1}, J^{x/x}_{k+1} and J^{x/theta}_{k+1} together.
        x_next, (A, B) = _value_and_jac(f_theta, x, u_k, p_theta)
        S_next = A @ S + jnp.concatenate([B, jnp.zeros((x.shape[0], n_s), B.dtype)], axis=1)
        return (x_next, S_next), (x_next, S_next)

    _, (xs, Ss) = jax.lax.scan(body, (x0, S0), u[:-1])
    xs = jnp.concatenate([x0[None], xs], axis=0)
    Ss = jnp.concatenate([S0[None], Ss], axis=0)

    g_theta = lambda x, u_k, p: model.observe(x, u_k, theta_of(p))  # noqa: E731
    e = jax.vmap(g_theta, in_axes=(0, 0, None))(xs, u, p_theta) - z
    Gx, Gt = jax.vmap(jax.jacfwd(g_theta, argnums=(0, 2)), in_axes=(0, 0, None))(xs, u, p_theta)
    Je = jnp.einsum("kzx,kxp->kzp", Gx, Ss)
    Je = Je + jnp.concatenate([Gt, jnp.zeros((*Gt.shape[:2], n_s), Gt.dtype)], axis=2)
    r = (_weigh(e, sqrt_q) * scale).reshape(-1)
    Jr = _weigh_jac(Je, sqrt_q) * scale
    Jr = Jr.reshape(-1, n_t + n_s)
    if penalty is not None:
        h_theta = lambda x, p: penalty(x, theta_of(p))  # noqa: E731
        h = jax.vmap(h_theta, in_axes=(0, None))(xs, p_theta)
        hx, ht = jax.vmap(jax.grad(h_theta, argnums=(0, 1)), in_axes=(0, None))(xs, p_theta)
        dh = jnp.einsum("kx,kxp->kp", hx, Ss)
        dh = dh + jnp.concatenate([ht, jnp.zeros((ht.shape[0], n_s), ht.dtype)], axis=1)
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


def _value_and_jac(f, x, u_k, p):
    """f(x, u, p) with its Jacobians in x and p from one jacfwd (the primal rides along)."""

    def fx(x, p):
        y = f(x, u_k, p)
        return y, y

    (A, B), y = jax.jacfwd(fx, argnums=(0, 1), has_aux=True)(x, p)
    return y, (A, B)
