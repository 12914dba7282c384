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

The sensitivity recursion is written once, `oneshot_jax._kernels.forward_sweep` (and the
reverse one, `_kernels.reverse_sweep`); the strategy object (`oneshot_jax._strategy`)
says how a step is applied and how the recursion runs (`AbstractStrategy.sensitivities`,
`tangents`, `reverse_sweep`).

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
from ._kernels import push
from ._simulate import outputs, rollout, states
from ._strategy import as_strategy


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
    model, cost, theta_of, p_theta, x0_of, p_x0, u, z, *, scale, strategy, mask=None, xs=None
):
    """The `Linearisation` of one trajectory's residuals in its free variables.

    `theta_of(p_theta)` maps the free parameter vector to the theta pytree, `x0_of(p_x0)`
    the free initial-state entries to x0 (fixed entries are constants inside both), so
    the columns are exactly the free variables.

    Masked entries (a `Mask`) are zero rows. `strategy` picks how the sensitivity recursion
    S_{k+1} = J^{x/x} S_k + [J^{x/theta}, 0] is evaluated (`AbstractStrategy.sensitivities`,
    the recursion itself is `_kernels.forward_sweep`): `Jacobian()` forms every J^{x/x}_k
    and J^{x/theta}_k at once after the forward pass (vmapped forward mode, the paper's
    Remark 1) and the scan is left with small matrix products; `VJP()` (matrix-free)
    pushes the columns of S_k through the step as JVPs inside the scan, never forming
    J^{x/x} (a banded or sparse step costs what its JVP costs), and stores only the
    output rows J^{z/x}_k S_k, not S_k; `ParallelInTime()` runs the recursion as an
    associative scan. `xs`: the states, if already known (not with `VJP()`, which rolls
    them out inside its scan).
    """
    x0 = x0_of(p_x0)
    theta = theta_of(p_theta)
    n_t, n_s = p_theta.shape[0], p_x0.shape[0]
    n_x = x0.shape[0]
    f_theta = lambda x, u_k, p: model.step(x, u_k, theta_of(p))  # noqa: E731
    # S_0 = d x0 / d (p_theta, p_x0) = [0, d x0/d p_x0]
    S0 = jnp.concatenate([jnp.zeros((n_x, n_t), x0.dtype), jax.jacfwd(x0_of)(p_x0)], axis=1)
    # Tangent of p for each column: e_j for the theta columns, 0 for the x0 columns.
    E = jnp.concatenate([jnp.eye(n_t, dtype=x0.dtype), jnp.zeros((n_t, n_s), x0.dtype)], 1)
    emit = emitter(model, cost, theta_of, p_theta, E)

    # One trajectory here; `FitProblem.jacobian` resolves "auto" for its whole batch.
    strategy = as_strategy(strategy).resolve(n_x, u.shape[0], x0.dtype.itemsize, 1, n_t + n_s)
    outs = strategy.sensitivities(model, theta, f_theta, p_theta, x0, S0, E, u, emit, xs)
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
        out = push(lambda x, p: g_theta(x, u_k, p), x, p_theta, S, E)
        if cost.penalty is None:
            return out
        return (*out, *push(lambda x, p: cost.penalty(x, theta_of(p)), x, p_theta, S, E))

    return emit


def _weigh_jac(Je, sqrt_q):
    if sqrt_q is None:
        return Je
    if sqrt_q.ndim == 1:
        return Je * sqrt_q[None, :, None]
    return jnp.einsum("ij,kjp->kip", sqrt_q, Je)


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
    """The strategy of `linearise_trajectory` and the products (that of the gradient, and
    sequential: the conjugate-gradient solve does not run with `ParallelInTime()`)."""
    return as_strategy(strategy).resolve(n_x, T, itemsize, sequential=True)


def linearise_trajectory(model, theta, x0, u, strategy) -> Trajectory:
    """Simulate once and keep what the products with J need: x_k and, for small states,
    every J^{x/x}_k (vmapped forward mode, the paper's Remark 1)."""
    xs = rollout(model, theta, x0, u)
    T, n_x = xs.shape
    strategy = product_strategy(strategy, n_x, T, xs.dtype.itemsize)
    return Trajectory(xs, strategy.jacobians_T(model.step, theta, xs, model.step_inputs(u)))


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
    strategy = product_strategy(strategy, n_x, T, xs.dtype.itemsize)
    ss = strategy.tangents(model, theta, xs, u, dx0, b, traj.At)
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
    one reverse-mode VJP of the vmapped step and output map (`_kernels.theta_term_vjp`).

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

    strategy = product_strategy(strategy, n_x, T, xs.dtype.itemsize)
    lam0, theta_term = strategy.reverse_sweep(
        model, theta, xs, u, Gamma, At=traj.At, theta_forward=False
    )
    return jax.tree_util.tree_map(lambda a, c: a + c, gamma, theta_term), lam0
