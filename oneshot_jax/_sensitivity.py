r"""Closed-form Jacobian of the stacked residuals, the forward twin of eq. (17) and (20).

The least-squares solvers minimise C = ||r||^2 with residuals

    r_k = Q^{1/2} e_k / sqrt(T N)                    (k = 0..T-1, N trajectories)
    r^h_k = sqrt(penalty_weight h(x_k, theta) / (T N))   (only when a penalty is given)

so that ||r||^2 is exactly the C of eq. (5)/(21). A penalty therefore has to be
non-negative in this form (an exponential barrier or a squared energy deviation is); the
smallest lambda h(x_k) is returned with the Jacobian so that the least-squares solvers can
stop with a clear reason when it is negative.

The Jacobian of the states in the free parameters p = (theta, x0) follows the sensitivity
recursion

    S_0 = [0, I],    S_{k+1} = J^{x/x}_{k+1} S_k + [J^{x/theta}_{k+1}, 0],

which accumulates, forwards in time, the same chained products J^{x/x}_tau ... J^{x/x}_{k+1}
J^{x/theta}_k as eq. (17) (theta columns) and eq. (20) (x0 columns). Then
dr_k/dp = Q^{1/2} (J^{z/x}_k S_k + [J^{z/theta}_k, 0]) / sqrt(T N). Forward mode costs
O(T n_x^2 (n_theta + n_x0)) with formed Jacobians (O(T n_x (n_theta + n_x0)) JVPs
matrix-free) and gives every row of the Jacobian, which is what Gauss-Newton needs; the
reverse recursion of `value_and_grad` gives one row-sum (the gradient) in O(T n_x^2).

For a large theta the Jacobian is not formed: `residual_jvp` (J v, the recursion above
with one column) and `residual_vjp` (J^T w, the one-shot reverse recursion of eq. 17/20
with the output cotangents w in place of dL/dx) are the matrix-free products of the
conjugate-gradient normal-equation solve, each costing about one model evaluation per
step whatever n_theta.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._cost import weigh
from ._gradient import stacked_jacobians_T, theta_term_vjp
from ._simulate import outputs, rollout, states
from ._strategy import JACOBIAN_MAX_NX, gradient_strategy, sensitivity_strategy

# Up to this state size the scan's A @ S is written elementwise (see `_matmul`).
_MATMUL_ELEMENTWISE_MAX = JACOBIAN_MAX_NX


class Linearisation(NamedTuple):
    """Residuals r (R,), their Jacobians in the free theta entries (R, p) and in the free
    x0 entries (R, m), and the smallest lambda h(x_k) (+inf without a penalty)."""

    r: jax.Array
    Jt: jax.Array
    Jx: jax.Array
    h_min: jax.Array


def _penalty_rows(cost, xs, theta):
    lh = cost.penalty_weight * jax.vmap(cost.penalty, in_axes=(0, None))(xs, theta)
    return lh


def _masked(e, mask):
    return e if mask is None else e * mask.outputs


def _min_penalty(lh, mask):
    return jnp.min(lh if mask is None else jnp.where(mask.samples > 0, lh, jnp.inf))


def trajectory_residuals(model, cost, theta, x0, u, z, *, scale, mask=None, strategy="auto"):
    """Residuals r (R,) of one trajectory, R = T n_z (+ T with a penalty), and the
    smallest lambda h(x_k). Masked entries (a `Mask`) are zero rows."""
    xs = states(model, theta, x0, u, strategy)
    e = _masked(outputs(model, theta, xs, u) - z, mask)
    r = (weigh(e, cost.sqrt_weight()) * scale).reshape(-1)
    if cost.penalty is None:
        return r, jnp.array(jnp.inf, r.dtype)
    lh = _penalty_rows(cost, xs, theta)
    rh = jnp.sqrt(jnp.maximum(lh, 0.0)) * scale
    if mask is not None:
        rh = rh * mask.samples
    return jnp.concatenate([r, rh]), _min_penalty(lh, mask)


def trajectory_jacobian(
    model, cost, theta_of, p_theta, x0_of, p_x0, u, z, *, scale, strategy, mask=None
):
    """The `Linearisation` of one trajectory's residuals in its free variables.

    `theta_of(p_theta)` maps the free parameter vector to the theta pytree, `x0_of(p_x0)`
    the free initial-state entries to x0 (fixed entries are constants inside both), so
    the columns are exactly the free variables.

    Masked entries (a `Mask`) are zero rows. `strategy` picks how the sensitivity recursion
    S_{k+1} = J^{x/x} S_k + [J^{x/theta}, 0] is evaluated (see `_strategy`): `"jacobian"`
    forms every J^{x/x}_k and J^{x/theta}_k at once after the forward pass (vmapped
    forward mode, the paper's Remark 1) and the scan is left with small matrix products;
    `"vjp"` (matrix-free) pushes the columns of S_k through the step as JVPs inside the
    scan, never forming J^{x/x} (a banded or sparse step costs what its JVP costs), and
    stores only the output rows J^{z/x}_k S_k, not S_k.
    """
    x0 = x0_of(p_x0)
    n_t, n_s = p_theta.shape[0], p_x0.shape[0]
    n_x = x0.shape[0]
    us = model.step_inputs(u)
    f_theta = lambda x, u_k, p: model.step(x, u_k, theta_of(p))  # noqa: E731
    # S_0 = d x0 / d (p_theta, p_x0) = [0, d x0/d p_x0]
    S0 = jnp.concatenate([jnp.zeros((n_x, n_t), x0.dtype), jax.jacfwd(x0_of)(p_x0)], axis=1)
    # Tangent of p for each column: e_j for the theta columns, 0 for the x0 columns.
    E = jnp.concatenate([jnp.eye(n_t, dtype=x0.dtype), jnp.zeros((n_t, n_s), x0.dtype)], 1)
    emit = emitter(model, cost, theta_of, p_theta, E)

    # One trajectory here; `FitProblem.jacobian` resolves "auto" for its whole batch.
    strategy = sensitivity_strategy(strategy, 1, n_x, n_t + n_s, u.shape[0], x0.dtype.itemsize)
    if strategy == "jacobian":
        xs = rollout(model, theta_of(p_theta), x0, u)
        A, B = jax.vmap(jax.jacfwd(f_theta, argnums=(0, 2)), in_axes=(0, 0, None))(
            xs[:-1], us, p_theta
        )
        B = jnp.concatenate([B, jnp.zeros((*B.shape[:2], n_s), B.dtype)], axis=2)

        def body(S, AB):
            S_next = _matmul(AB[0], S) + AB[1]
            return S_next, S_next

        _, Ss = jax.lax.scan(body, S0, (A, B))
        Ss = jnp.concatenate([S0[None], Ss], axis=0)
        outs = jax.vmap(emit)(xs, u, Ss)
    elif strategy == "vjp":
        # Each step emits the outputs of (x_k, S_k), then advances: only the (n_z, columns)
        # rows are stored, never S_k.
        def body(carry, inp):
            x, S = carry
            u_step, u_k = inp
            out = emit(x, u_k, S)
            return _push(lambda x, p: f_theta(x, u_step, p), x, p_theta, S, E), out

        (x_last, S_last), outs = jax.lax.scan(body, (x0, S0), (us, u[:-1]))
        last = emit(x_last, u[-1], S_last)
        outs = jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b[None]], axis=0), outs, last
        )
    else:
        raise ValueError(f"unknown strategy {strategy!r}")

    return rows(outs, z, cost, scale, mask, n_t, n_s)


def rows(outs, z, cost, scale, mask, n_t, n_s) -> Linearisation:
    """The `Linearisation` from the emitted outputs of every sample: z_k and its column
    derivatives J^{z/x}_k S_k + [J^{z/theta}_k, 0] (and the same for the penalty h):
    weighted, scaled and masked residual rows, with the penalty rows sqrt(lambda h)."""
    sqrt_q = cost.sqrt_weight()
    y, Je = outs[:2]
    r = (weigh(_masked(y - z, mask), sqrt_q) * scale).reshape(-1)
    if mask is not None:
        Je = Je * mask.outputs[:, :, None]
    Jr = _weigh_jac(Je, sqrt_q) * scale
    Jr = Jr.reshape(-1, n_t + n_s)
    h_min = jnp.array(jnp.inf, r.dtype)
    if cost.penalty is not None:
        h, dh = outs[2:]
        lh = cost.penalty_weight * h
        h_min = _min_penalty(lh, mask)
        if mask is not None:
            lh = lh * mask.samples
        rh = jnp.sqrt(jnp.maximum(lh, 0.0))
        # d sqrt(lambda h) = lambda h' / (2 sqrt(lambda h)); zero where the penalty is 0.
        safe = jnp.where(rh > 0, rh, 1.0)
        Jh = jnp.where((rh > 0)[:, None], cost.penalty_weight * dh / (2.0 * safe[:, None]), 0.0)
        r = jnp.concatenate([r, rh * scale])
        Jr = jnp.concatenate([Jr, Jh * scale], axis=0)
    return Linearisation(r, Jr[:, :n_t], Jr[:, n_t:], h_min)


def emitter(model, cost, theta_of, p_theta, E):
    """`emit(x, u_k, S)`: z_k and J^{z/x}_k S_k + [J^{z/theta}_k, 0] (and the same for the
    penalty h) as JVPs of the output map along the columns, without forming J^{z/x}."""

    def g_theta(x, u_k, p):
        return model.observe(x, u_k, theta_of(p))

    def emit(x, u_k, S):
        out = _push(lambda x, p: g_theta(x, u_k, p), x, p_theta, S, E)
        if cost.penalty is None:
            return out
        return (*out, *_push(lambda x, p: cost.penalty(x, theta_of(p)), x, p_theta, S, E))

    return emit


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


#
# Matrix-free products with the residual Jacobian J, for normal equations solved by
# conjugate gradients when theta is large (`oneshot_jax._solver.least_squares`).
#


class Trajectory(NamedTuple):
    """One trajectory's linearisation point for `residual_jvp` / `residual_vjp`: its states
    xs (T, n_x) and, with the "jacobian" strategy, the transposed J^{x/x}_{k+1} (T-1, n_x,
    n_x) stacked after the forward pass (an empty (0, n_x, n_x) array with "vjp")."""

    xs: jax.Array
    At: jax.Array


def product_strategy(strategy, n_x, T, itemsize):
    """The strategy of `linearise_trajectory` and the products (that of the gradient)."""
    return gradient_strategy(strategy, n_x, T, itemsize)


def linearise_trajectory(model, theta, x0, u, strategy) -> Trajectory:
    """Simulate once and keep what the products with J need: x_k and, for small states,
    every J^{x/x}_k (vmapped forward mode, the paper's Remark 1)."""
    xs = rollout(model, theta, x0, u)
    T, n_x = xs.shape
    if product_strategy(strategy, n_x, T, xs.dtype.itemsize) == "jacobian":
        At = stacked_jacobians_T(model.step, theta, xs[:-1], model.step_inputs(u), "x")
    else:
        At = jnp.zeros((0, n_x, n_x), xs.dtype)
    return Trajectory(xs, At)


def _penalty_values(cost, xs, theta, mask):
    """lambda h(x_k) (masked) and sqrt of it, as in `trajectory_jacobian`."""
    lh = cost.penalty_weight * jax.vmap(cost.penalty, in_axes=(0, None))(xs, theta)
    if mask is not None:
        lh = lh * mask.samples
    return lh, jnp.sqrt(jnp.maximum(lh, 0.0))


def residual_jvp(model, cost, theta, traj, u, dtheta, dx0, *, scale, strategy, mask=None):
    """J v: the residuals' derivative along a direction (dtheta, dx0), one forward
    sensitivity.

    The states' tangent follows s_0 = dx0, s_{k+1} = J^{x/x}_{k+1} s_k + J^{x/theta}_{k+1}
    dtheta (the sensitivity recursion of this module's docstring with one column); the
    theta terms of every step are one vmapped JVP (parallel in time), the recursion a
    scan of small matrix-vector products (or in-scan JVPs in x for large states).
    Returns the (R,) tangent of `trajectory_residuals`, rows as there.
    """
    xs = traj.xs
    T, n_x = xs.shape
    us = model.step_inputs(u)
    step = model.step
    b = jax.vmap(lambda x, u_k: jax.jvp(lambda th: step(x, u_k, th), (theta,), (dtheta,))[1])(
        xs[:-1], us
    )
    if product_strategy(strategy, n_x, T, xs.dtype.itemsize) == "jacobian":

        def body(s, inp):
            At_k, b_k = inp
            s_next = jnp.einsum("ji,j->i", At_k, s) + b_k
            return s_next, s_next

        _, ss = jax.lax.scan(body, dx0, (traj.At, b))
    else:

        def body(s, inp):
            x_k, u_k, b_k = inp
            s_next = jax.jvp(lambda x: step(x, u_k, theta), (x_k,), (s,))[1] + b_k
            return s_next, s_next

        _, ss = jax.lax.scan(body, dx0, (xs[:-1], us, b))
    ss = jnp.concatenate([dx0[None], ss], axis=0)
    dy = jax.vmap(
        lambda x, u_k, s: jax.jvp(lambda x, th: model.observe(x, u_k, th), (x, theta), (s, dtheta))[
            1
        ]
    )(xs, u, ss)
    dr = (weigh(_masked(dy, mask), cost.sqrt_weight()) * scale).reshape(-1)
    if cost.penalty is None:
        return dr
    _, rh = _penalty_values(cost, xs, theta, mask)
    dh = jax.vmap(lambda x, s: jax.jvp(cost.penalty, (x, theta), (s, dtheta))[1])(xs, ss)
    safe = jnp.where(rh > 0, rh, 1.0)
    drh = jnp.where(rh > 0, cost.penalty_weight * dh / (2.0 * safe), 0.0)
    return jnp.concatenate([dr, drh * scale])


def residual_vjp(model, cost, theta, traj, u, w, *, scale, strategy, mask=None):
    """J^T w: the residuals' Jacobian transposed, applied to w (R,), by the one-shot
    reverse recursion of eq. (17) and (20) with Gamma_k = (d r_k / d x_k)^T w_k:

        lam_{T-1} = Gamma_{T-1},  lam_k = Gamma_k + (J^{x/x}_{k+1})^T lam_{k+1},
        J_theta^T w = sum_k (d r_k / d theta)^T w_k + sum_{k>=1} (J^{x/theta}_k)^T lam_k,
        J_x0^T w = lam_0.

    Its cost does not grow with n_theta beyond the model's own VJP: the theta terms are
    one reverse-mode VJP of the vmapped step and output map (`_gradient.theta_term_vjp`).

    **Returns:**

    `(theta cotangent (a pytree like theta), x0 cotangent (n_x,))`.
    """
    xs = traj.xs
    T, n_x = xs.shape
    n_z = (w.shape[0] - (T if cost.penalty is not None else 0)) // T
    sqrt_q = cost.sqrt_weight()
    w_e = w[: T * n_z].reshape(T, n_z) * scale
    if sqrt_q is not None:
        w_e = w_e * sqrt_q if sqrt_q.ndim == 1 else w_e @ sqrt_q
    ct_y = _masked(w_e, mask)

    def local(xs, th):
        y = jax.vmap(model.observe, in_axes=(0, 0, None))(xs, u, th)
        if cost.penalty is None:
            return y
        return y, jax.vmap(cost.penalty, in_axes=(0, None))(xs, th)

    if cost.penalty is None:
        cts = ct_y
    else:
        _, rh = _penalty_values(cost, xs, theta, mask)
        safe = jnp.where(rh > 0, rh, 1.0)
        w_h = w[T * n_z :] * scale
        cts = (ct_y, jnp.where(rh > 0, cost.penalty_weight * w_h / (2.0 * safe), 0.0))
    Gamma, gamma = jax.vjp(local, xs, theta)[1](cts)

    us = model.step_inputs(u)
    step = model.step
    if product_strategy(strategy, n_x, T, xs.dtype.itemsize) == "jacobian":

        def body(lam_next, inp):
            At_k, Gamma_k = inp
            return Gamma_k + At_k @ lam_next, lam_next

        lam0, lam_next = jax.lax.scan(body, Gamma[-1], (traj.At, Gamma[:-1]), reverse=True)
    else:

        def body(lam_next, inp):
            x_k, u_k, Gamma_k = inp
            _, vjp_x = jax.vjp(lambda x: step(x, u_k, theta), x_k)
            return Gamma_k + vjp_x(lam_next)[0], lam_next

        lam0, lam_next = jax.lax.scan(body, Gamma[-1], (xs[:-1], us, Gamma[:-1]), reverse=True)
    theta_term = theta_term_vjp(step, theta, xs[:-1], us, lam_next)
    return jax.tree_util.tree_map(lambda a, c: a + c, gamma, theta_term), lam0
