r"""The one-shot closed-form gradient of the multi-step cost, Section 3 of the paper.

Notation (the paper's): x_{k+1} = f(x_k, u_k, theta), e_k = g(x_k) - z_k, and
L_k = (1/T) (e_k^T Q e_k + lambda h(x_k, theta)) (eq. 4, 21), C = sum_k L_k (eq. 5).

- J^{x/x}_k = d x_k / d x_{k-1} = f_x(x_{k-1}, u_{k-1}, theta)
- J^{x/theta}_k = the direct derivative of x_k = f(x_{k-1}, u_{k-1}, theta) in theta
- gamma_k = dL_k/dtheta (direct), Gamma_k = dL_k/de J^{e/z} J^{z/x} = dL_k/dx_k (eq. 14).

The paper's closed form (eq. 17 and 20) is

    grad_theta C = sum_k gamma_k + sum_k Gamma_k J^{x/theta}_k
                   + sum_k sum_{tau>k} Gamma_tau J^{x/x}_tau ... J^{x/x}_{k+1} J^{x/theta}_k,
    grad_x0 C    = sum_k Gamma_k J^{x/x}_k ... J^{x/x}_1,

a double sum with O(T^2) chained Jacobian products. `literal_value_and_grad` evaluates it
exactly as written; it is the reference for the tests. Grouping the products that share a
tail gives the O(T) recursion used everywhere else (the multiplier `lam`):

    lam_{T-1} = Gamma_{T-1}^T,   lam_k = Gamma_k^T + (J^{x/x}_{k+1})^T lam_{k+1},
    grad_theta C = sum_k gamma_k + sum_{k>=1} (J^{x/theta}_k)^T lam_k,   grad_x0 C = lam_0,

since lam_k^T = sum_{tau>=k} Gamma_tau J^{x/x}_tau ... J^{x/x}_{k+1} is exactly the bracket
that multiplies J^{x/theta}_k in eq. (17), and lam_0 is eq. (20).

On indices: the paper writes the sums of eq. (17) and (20) from k = 1, while C of eq. (5)
starts at k = 0. With x0 estimated, L_0 depends on x0 directly, so grad_x0 here includes
the k = 0 term Gamma_0 (an empty Jacobian product); grad_theta is unaffected except
through gamma_0 (a theta-dependent observation or penalty), which is included too.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ._checks import check_data, check_penalty, check_strategy, filter_jit
from ._simulate import check_penalty_output, rollout, step_loss

# Above this many bytes for the stacked J^{x/x}_k, "auto" switches to the vjp strategy.
_JACOBIAN_BYTES = 256 * 2**20
_JACOBIAN_MAX_NX = 64


def choose_strategy(strategy, n_x, T, itemsize):
    """Resolve "auto": stacked Jacobians for small states, in-scan VJPs for large ones."""
    if strategy != "auto":
        return strategy
    small = n_x <= _JACOBIAN_MAX_NX and T * n_x * n_x * itemsize <= _JACOBIAN_BYTES
    return "jacobian" if small else "vjp"


def _local_terms(model, theta, xs, u, z, weight, penalty, penalty_weight):
    """T L_k, Gamma_k and gamma_k (eq. 14) for every k at once (vmap), times T."""
    ell = lambda x, u, z, th: step_loss(  # noqa: E731
        model, th, x, u, z, weight, penalty, penalty_weight
    )
    grad_ell = jax.value_and_grad(ell, argnums=(0, 3))
    vals, (Gamma, gamma) = jax.vmap(grad_ell, in_axes=(0, 0, 0, None))(xs, u, z, theta)
    gamma = jax.tree_util.tree_map(lambda g: jnp.sum(g, axis=0), gamma)
    return vals, Gamma, gamma


def one_shot(model, theta, x0, u, z, weight, penalty, penalty_weight, strategy):
    """C and (grad_theta C, grad_x0 C) for one trajectory by the O(T) recursion above.

    `strategy="jacobian"`: J^{x/x}_k for all k at once (vmap of jacfwd) after the forward
    pass (the paper's Remark 1), then a reverse scan of small matrix-vector products; the
    theta term sum_k (J^{x/theta}_k)^T lam_k is one vmapped VJP after the scan.
    `strategy="vjp"`: each step of the reverse scan takes the VJP of f at (x_k, u_k) with
    lam_{k+1}, never forming J^{x/x}; memory O(T n_x) instead of O(T n_x^2).
    """
    T = u.shape[0]
    xs = rollout(model, theta, x0, u)
    vals, Gamma, gamma = _local_terms(model, theta, xs, u, z, weight, penalty, penalty_weight)
    strategy = choose_strategy(strategy, x0.shape[0], T, x0.dtype.itemsize)
    step = model.step

    if strategy == "jacobian":
        # A[j] = J^{x/x}_{j+1} = d f(x_j, u_j) / d x_j, j = 0..T-2.
        A = jax.vmap(jax.jacfwd(step, argnums=0), in_axes=(0, 0, None))(xs[:-1], u[:-1], theta)

        def body(lam_next, inp):
            A_j, Gamma_j = inp
            return Gamma_j + A_j.T @ lam_next, lam_next

        lam0, lam_next = jax.lax.scan(body, Gamma[-1], (A, Gamma[:-1]), reverse=True)
        # sum_{j} (J^{x/theta}_{j+1})^T lam_{j+1}, vmapped over j then summed.
        vjp_theta = lambda x, u_k, lam: jax.vjp(  # noqa: E731
            lambda th: step(x, u_k, th), theta
        )[1](lam)[0]
        theta_term = jax.vmap(vjp_theta, in_axes=(0, 0, 0))(xs[:-1], u[:-1], lam_next)
        theta_term = jax.tree_util.tree_map(lambda g: jnp.sum(g, axis=0), theta_term)
    elif strategy == "vjp":

        def body(carry, inp):
            lam_next, acc = carry
            x_j, u_j, Gamma_j = inp
            _, vjp_fn = jax.vjp(lambda x, th: step(x, u_j, th), x_j, theta)
            d_x, d_theta = vjp_fn(lam_next)
            acc = jax.tree_util.tree_map(jnp.add, acc, d_theta)
            return (Gamma_j + d_x, acc), None

        zeros = jax.tree_util.tree_map(jnp.zeros_like, theta)
        (lam0, theta_term), _ = jax.lax.scan(
            body, (Gamma[-1], zeros), (xs[:-1], u[:-1], Gamma[:-1]), reverse=True
        )
    else:
        raise ValueError(f"unknown strategy {strategy!r}")

    grad_theta = jax.tree_util.tree_map(lambda a, b: (a + b) / T, gamma, theta_term)
    return jnp.mean(vals), (grad_theta, lam0 / T)


@filter_jit
def value_and_grad_impl(model, theta, x0, u, z, weight, penalty, penalty_weight, batched, strategy):
    """Jitted `value_and_grad` on validated inputs (used by `fit`)."""
    fn = lambda x0, u, z: one_shot(  # noqa: E731
        model, theta, x0, u, z, weight, penalty, penalty_weight, strategy
    )
    if not batched:
        return fn(x0, u, z)
    N = x0.shape[0]
    C, (g_theta, g_x0) = jax.vmap(fn)(x0, u, z)
    g_theta = jax.tree_util.tree_map(lambda g: jnp.mean(g, axis=0), g_theta)
    return jnp.mean(C), (g_theta, g_x0 / N)


def value_and_grad(
    model, theta, x0, u, z, *, weight=None, penalty=None, penalty_weight=1.0, strategy="auto"
):
    """The cost C of eq. (5)/(21) and its one-shot closed-form gradient, eq. (17) and (20).

    The gradient is the O(T) recursion of this module's docstring: a forward pass for the
    states, then one reverse `lax.scan` that accumulates Gamma_k (eq. 14) and the chained
    J^{x/x} products of eq. (16)-(17) into the multiplier lam_k. Per-step Jacobians come
    from `jax.jacfwd`/`jax.vjp` of the user's `step` and `observe`; there is no
    differentiation of the whole rollout.

    **Arguments:**

    - `model`, `theta`, `x0`, `u`, `z`, `weight`, `penalty`, `penalty_weight`: as for `loss`.
    - `strategy`: `"jacobian"` (stacked J^{x/x}_k by vmap, best for small n_x), `"vjp"`
        (VJPs inside the reverse scan, memory O(T n_x), for large states) or `"auto"`
        (jacobian for n_x <= 64 when the stacked Jacobians fit in 256 MiB).

    **Returns:**

    `(C, (grad_theta, grad_x0))` with `grad_theta` shaped like `theta` and `grad_x0` like
    `x0`. For N trajectories C is the mean over trajectories and `grad_x0` has shape
    (N, n_x).
    """
    data = check_data(model, theta, x0, u, z, weight)
    penalty, penalty_weight = check_penalty(penalty, penalty_weight)
    check_penalty_output(model, penalty, data)
    strategy = check_strategy(strategy)
    return value_and_grad_impl(
        model, data.theta, data.x0, data.u, data.z, data.weight, penalty,
        jnp.asarray(penalty_weight, dtype=data.x0.dtype), data.batched, strategy,
    )


def literal_value_and_grad(model, theta, x0, u, z, *, weight=None, penalty=None, penalty_weight=1.0):
    """Eq. (17) and (20) evaluated literally, with the O(T^2) double sums (reference only).

    Forms every J^{x/x}_k and J^{x/theta}_k (jacfwd, flattened theta) and every chained
    product J^{x/x}_tau ... J^{x/x}_{k+1}. Use it to check `value_and_grad`, never to fit.
    Same arguments and returns as `value_and_grad` (one trajectory or N trajectories).
    """
    data = check_data(model, theta, x0, u, z, weight)
    penalty, penalty_weight = check_penalty(penalty, penalty_weight)
    flat, unravel = ravel_pytree(data.theta)
    pw = jnp.asarray(penalty_weight, dtype=data.x0.dtype)

    def one(x0, u, z):
        T = u.shape[0]
        xs = rollout(model, data.theta, x0, u)
        f = lambda x, u_k, th: model.step(x, u_k, unravel(th))  # noqa: E731
        ell = lambda x, u_k, z_k, th: step_loss(  # noqa: E731
            model, unravel(th), x, u_k, z_k, data.weight, penalty, pw
        )
        L = np.asarray(jax.vmap(ell, in_axes=(0, 0, 0, None))(xs, u, z, flat)) / T
        Gamma = np.asarray(jax.vmap(jax.grad(ell, 0), in_axes=(0, 0, 0, None))(xs, u, z, flat)) / T
        gamma = np.asarray(jax.vmap(jax.grad(ell, 3), in_axes=(0, 0, 0, None))(xs, u, z, flat)) / T
        # J[k] = J^{x/x}_k and B[k] = J^{x/theta}_k for k = 1..T-1 (index 0 unused).
        Jxx = np.asarray(jax.vmap(jax.jacfwd(f, 0), in_axes=(0, 0, None))(xs[:-1], u[:-1], flat))
        Jxt = np.asarray(jax.vmap(jax.jacfwd(f, 2), in_axes=(0, 0, None))(xs[:-1], u[:-1], flat))
        n_x = x0.shape[0]
        J = np.concatenate([np.zeros((1, n_x, n_x), Jxx.dtype), Jxx])
        B = np.concatenate([np.zeros((1, n_x, flat.size), Jxt.dtype), Jxt])

        def chain(tau, k):  # prod_{c=0}^{tau-k-1} J^{x/x}_{tau-c} = J_tau J_{tau-1} ... J_{k+1}
            P = np.eye(n_x, dtype=J.dtype)
            for c in range(tau - k):
                P = P @ J[tau - c]
            return P

        # eq. (17)
        g_theta = gamma.sum(axis=0)
        for k in range(1, T):
            g_theta = g_theta + Gamma[k] @ B[k]
            for tau in range(k + 1, T):
                g_theta = g_theta + (Gamma[tau] @ chain(tau, k)) @ B[k]
        # eq. (20), including k = 0 (see the module docstring)
        g_x0 = sum(Gamma[k] @ chain(k, 0) for k in range(T))
        return L.sum(), g_theta, g_x0

    if not data.batched:
        C, g_theta, g_x0 = one(data.x0, data.u, data.z)
        return jnp.asarray(C), (unravel(jnp.asarray(g_theta)), jnp.asarray(g_x0))
    outs = [one(data.x0[i], data.u[i], data.z[i]) for i in range(data.x0.shape[0])]
    N = len(outs)
    C = np.mean([o[0] for o in outs])
    g_theta = np.mean([o[1] for o in outs], axis=0)
    g_x0 = np.stack([o[2] for o in outs]) / N
    return jnp.asarray(C), (unravel(jnp.asarray(g_theta)), jnp.asarray(g_x0))
