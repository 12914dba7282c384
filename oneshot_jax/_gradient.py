r"""The one-shot closed-form gradient of the multi-step cost, Section 3 of the paper.

Notation (the paper's): x_{k+1} = f(x_k, u_k, theta), e_k = g(x_k) - z_k, and
L_k = (1/T) (e_k^T Q e_k + lambda h(x_k, theta)) (eq. 4, 21; the paper's lambda of
eq. 21 is lambda / T here), C = sum_k L_k (eq. 5).

- J^{x/x}_k = d x_k / d x_{k-1} = f_x(x_{k-1}, u_{k-1}, theta)
- J^{x/theta}_k = the direct derivative of x_k = f(x_{k-1}, u_{k-1}, theta) in theta
- gamma_k = dL_k/dtheta (direct), Gamma_k = dL_k/dx_k: dL_k/de J^{e/z} J^{z/x} (eq. 14),
  plus (lambda/T) dh/dx_k with a penalty on the states.

The paper's closed form (eq. 17 and 20) is

    grad_theta C = sum_k gamma_k + sum_k Gamma_k J^{x/theta}_k
                   + sum_k sum_{tau>k} Gamma_tau J^{x/x}_tau ... J^{x/x}_{k+1} J^{x/theta}_k,
    grad_x0 C    = sum_k Gamma_k J^{x/x}_k ... J^{x/x}_1,

a double sum of O(T^2) chained Jacobian products. `literal_value_and_grad` evaluates it
exactly as written, each chain formed anew (O(T^3) matrix products); it is the reference
for the tests. Grouping the products that share a
tail gives the O(T) recursion used everywhere else (the multiplier `lam`):

    lam_{T-1} = Gamma_{T-1}^T,   lam_k = Gamma_k^T + (J^{x/x}_{k+1})^T lam_{k+1},
    grad_theta C = sum_k gamma_k + sum_{k>=1} (J^{x/theta}_k)^T lam_k,   grad_x0 C = lam_0,

since lam_k^T = sum_{tau>=k} Gamma_tau J^{x/x}_tau ... J^{x/x}_{k+1} is exactly the bracket
that multiplies J^{x/theta}_k in eq. (17), and lam_0 is eq. (20).

The recursion is written once, `oneshot_jax._kernels.reverse_sweep`; the strategy object
(`oneshot_jax._strategy`) says how a step is applied and how the recursion runs
(`AbstractStrategy.reverse_sweep`).

On indices: the paper writes the sums of eq. (17) and (20) from k = 1, while C of eq. (5)
starts at k = 0. With x0 estimated, L_0 depends on x0 directly, so grad_x0 here includes
the k = 0 term Gamma_0 (an empty Jacobian product); grad_theta is unaffected except
through gamma_0 (a theta-dependent observation or penalty), which is included too.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Float, PyTree

from ._aggregate import Aggregate, augment
from ._checks import check_cost, check_data
from ._jit import forward_mode_error, public_jit
from ._kernels import local_terms
from ._parallel._report import counting, warn_counted
from ._simulate import rollout, sample_count
from ._strategy import AbstractStrategy, as_strategy, may_run_parallel


def value_and_grad_of_states(model, cost, theta, xs, u, z, strategy, mask=None, norm=None):
    """C and (grad_theta C, grad_x0 C) for one trajectory from its states `xs` (T, n_x), by
    the O(T) recursion above, with C = sum_k T L_k / norm (norm = T by default: eq. 5; the
    number of time points of all trajectories when `value_and_grad_impl` sums several, or
    masked ones).

    The local terms Gamma_k, gamma_k (eq. 14) are one VJP of the vmapped L_k
    (`_kernels.local_terms`); the reverse recursion lam_k = Gamma_k + (J^{x/x}_{k+1})^T
    lam_{k+1} and the theta term sum_k (J^{x/theta}_k)^T lam_k run as the (concrete)
    `strategy` says (`AbstractStrategy.reverse_sweep`): stacked transposed Jacobians and a
    reverse scan of small products (`Jacobian()`; for a small theta the scan also
    accumulates the theta term in forward mode), VJPs of the step inside the scan
    (`VJP()`), or associative scans (`ParallelInTime()`).
    """
    T = xs.shape[0]
    S, Gamma, gamma = local_terms(model, cost, theta, xs, u, z, mask)
    lam0, theta_term = strategy.reverse_sweep(model, theta, xs, u, Gamma)
    norm = T if norm is None else norm
    grad_theta = jax.tree_util.tree_map(lambda a, b: (a + b) / norm, gamma, theta_term)
    return S / norm, (grad_theta, lam0 / norm)


def one_shot(model, cost, theta, x0, u, z, strategy, mask=None, norm=None):
    """C and (grad_theta C, grad_x0 C) for one trajectory: the states as the strategy
    (resolved for this trajectory) rolls them out, then `value_and_grad_of_states`."""
    strategy = as_strategy(strategy).resolve(x0.shape[0], u.shape[0], x0.dtype.itemsize)
    xs = strategy.states(model, theta, x0, u)
    return value_and_grad_of_states(model, cost, theta, xs, u, z, strategy, mask, norm)


def _value_and_grad(model, cost, theta, x0, u, z, batched, strategy, mask=None):
    """`value_and_grad` on validated inputs (compiled: `value_and_grad_impl`, used by
    `fit`): the one-shot recursion per trajectory, each normalised by the number of time
    points of all of them."""
    norm = sample_count(u, mask, x0.dtype)
    fn = lambda x0, u, z, m: one_shot(model, cost, theta, x0, u, z, strategy, m, norm)  # noqa: E731
    if not batched:
        return fn(x0, u, z, mask)
    C, (g_theta, g_x0) = jax.vmap(fn)(x0, u, z, mask)
    g_theta = jax.tree_util.tree_map(lambda g: jnp.sum(g, axis=0), g_theta)
    return jnp.sum(C), (g_theta, g_x0)


value_and_grad_impl = eqx.filter_jit(_value_and_grad)
value_and_grad_compiled = public_jit(_value_and_grad)


def value_and_grad(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    z: Float[ArrayLike, "*N T n_z"],
    *,
    weight: Float[ArrayLike, " n_z"] | Float[ArrayLike, "n_z n_z"] | None = None,
    penalty=None,
    penalty_weight: float = 1.0,
    strategy: str | AbstractStrategy = "auto",
    missing: str = "raise",
    aggregate: Aggregate | list | None = None,
    t: Float[ArrayLike, "*N T"] | None = None,
) -> tuple[Float[Array, ""], tuple[PyTree, Float[Array, "*N n_x"]]]:
    """The cost C of eq. (5)/(21) and its one-shot closed-form gradient, eq. (17) and (20).

    The gradient is the O(T) recursion of this module's docstring: a forward pass for the
    states, then one reverse `lax.scan` that accumulates Gamma_k (eq. 14) and the chained
    J^{x/x} products of eq. (16)-(17) into the multiplier lam_k. Per-step Jacobians come
    from forward-mode JVPs (`jax.jvp`) or `jax.vjp` of the user's `step` and `observe`;
    there is no differentiation of the whole rollout.

    **Arguments:**

    - `model`, `theta`, `x0`, `u`, `z`, `weight`, `penalty`, `penalty_weight`, `missing`,
        `aggregate`, `t`: as for `loss` (a reading's error flows back through the recursion
        to every sample it aggregates; `t`: the sample times of a timed model's records;
        the intervals are data of the steps, so the gradient stays the exact eq. 17/20).
    - `strategy`: `Jacobian()` / `"jacobian"` (stacked J^{x/x}_k by vmap, best for small
        n_x), `VJP()` / `"vjp"` (VJPs inside the reverse scan, memory O(T n_x), for large
        states), `ParallelInTime(...)` / `"parallel"` (parallel in time: the rollout by
        Newton iterations with associative scans and the recursion as an associative
        scan, for GPUs and TPUs; a rollout that does not converge falls back to the
        sequential loop, with a warning) or `Auto()` / `"auto"` (for n_x <= 16 when the
        stacked Jacobians fit in 256 MiB: parallel on a GPU or TPU for T >= 512, else
        jacobian; vjp for larger states).

    **Returns:**

    `(C, (grad_theta, grad_x0))` with `grad_theta` shaped like `theta`'s parameters (None
    where theta holds non-numeric parts, as `equinox.filter_grad` gives) and `grad_x0`
    like `x0`. For N trajectories C is the sum over trajectories divided by their total
    number of time points (sum_i T_i: the mean over trajectories when they are of equal
    length, as for `loss`) and `grad_x0` has shape (N, n_x).
    """
    if z is None:
        raise ValueError("`z` is required: the measured outputs, shape (T, n_z).")
    data = check_data(model, theta, x0, u, z, weight, missing, t, aggregate is not None)
    if aggregate is not None:
        agg = augment(data, aggregate, model, x0, missing, t=t)
        data = check_data(agg.model, theta, agg.x0, agg.u, agg.z, agg.weight, "mask")
        penalty = agg.penalty(penalty)
    cost = check_cost(data, penalty, penalty_weight)
    strategy = as_strategy(strategy)
    try:
        # (a parallel rollout's fallbacks: warned at the caller's line)
        with counting(may_run_parallel(strategy)) as counts:
            C, (g_theta, g_x0) = value_and_grad_compiled(
                data.model,
                cost,
                data.theta,
                data.x0,
                data.u,
                data.z,
                data.batched,
                strategy,
                data.mask,
            )
    except TypeError as err:
        forward_mode_error(err)
        raise
    warn_counted(counts, stacklevel=2)
    if aggregate is not None:  # the accumulators' initial states are not variables
        g_x0 = g_x0[..., : agg.n_x]
    return C, (g_theta, g_x0)


def literal_value_and_grad(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    z: Float[ArrayLike, "*N T n_z"],
    *,
    weight=None,
    penalty=None,
    penalty_weight: float = 1.0,
    missing: str = "raise",
    t=None,
):
    """Eq. (17) and (20) evaluated literally, with the O(T^2) double sums (reference only;
    each chained product formed anew: O(T^3) matrix products, seconds at T = 300).

    Forms every J^{x/x}_k and J^{x/theta}_k (jacfwd, flattened theta) and every chained
    product J^{x/x}_tau ... J^{x/x}_{k+1}. Use it to check `value_and_grad`, never to fit.
    The arguments and returns of `value_and_grad` (`t` included; one trajectory or N
    trajectories), except `strategy` and `aggregate`, which it does not take.
    """
    data = check_data(model, theta, x0, u, z, weight, missing, t)
    cost = check_cost(data, penalty, penalty_weight)
    model = data.model
    flat, unravel = ravel_pytree(data.theta)
    norm = float(sample_count(data.u, data.mask, data.x0.dtype))

    def one(x0, u, z, m):
        T = u.shape[0]
        xs = rollout(model, data.theta, x0, u)
        us = model.step_inputs(u)
        f = lambda x, u_k, th: model.step(x, u_k, unravel(th))  # noqa: E731
        ell = lambda x, u_k, z_k, m_k, th: cost.local(model, unravel(th), x, u_k, z_k, m_k)  # noqa: E731
        axes = (0, 0, 0, 0, None)
        L = np.asarray(jax.vmap(ell, in_axes=axes)(xs, u, z, m, flat)) / norm
        Gamma = np.asarray(jax.vmap(jax.grad(ell, 0), in_axes=axes)(xs, u, z, m, flat)) / norm
        gamma = np.asarray(jax.vmap(jax.grad(ell, 4), in_axes=axes)(xs, u, z, m, flat)) / norm
        # J[k] = J^{x/x}_k and B[k] = J^{x/theta}_k for k = 1..T-1 (index 0 unused).
        Jxx = np.asarray(jax.vmap(jax.jacfwd(f, 0), in_axes=(0, 0, None))(xs[:-1], us, flat))
        Jxt = np.asarray(jax.vmap(jax.jacfwd(f, 2), in_axes=(0, 0, None))(xs[:-1], us, flat))
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
        C, g_theta, g_x0 = one(data.x0, data.u, data.z, data.mask)
        return jnp.asarray(C), (unravel(jnp.asarray(g_theta)), jnp.asarray(g_x0))
    masks = [
        None if data.mask is None else jax.tree_util.tree_map(lambda a, i=i: a[i], data.mask)
        for i in range(data.x0.shape[0])
    ]
    outs = [one(data.x0[i], data.u[i], data.z[i], masks[i]) for i in range(data.x0.shape[0])]
    C = np.sum([o[0] for o in outs])
    g_theta = np.sum([o[1] for o in outs], axis=0)
    g_x0 = np.stack([o[2] for o in outs])
    return jnp.asarray(C), (unravel(jnp.asarray(g_theta)), jnp.asarray(g_x0))
