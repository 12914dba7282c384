r"""The one-shot gradient and the residual Jacobian, parallel in time.

Both are the sequential library's formulas with each recursion over k replaced by an
associative scan:

- **Gradient** (`oneshot_jax._gradient`, the recursion that replaces eq. 17 and 20):

      lam_{T-1} = Gamma_{T-1}^T,   lam_k = Gamma_k^T + (J^{x/x}_{k+1})^T lam_{k+1},
      grad_theta C = sum_k gamma_k + sum_{k>=1} (J^{x/theta}_k)^T lam_k,   grad_x0 C = lam_0,

  with the states from `newton_rollout`, Gamma_k and gamma_k from the same local terms
  (`local_terms`: one VJP of the vmapped L_k, eq. 4, 14, 21), the transposed J^{x/x}_k
  stacked by vmapped forward mode and lam by `reverse_linear_recurrence`; the theta term is
  one VJP of the vmapped step with all lam_k at once.
- **Sensitivities** (`oneshot_jax._sensitivity`): S_0 = [0, dx0/dp_x0],
  S_{k+1} = J^{x/x}_{k+1} S_k + [J^{x/theta}_{k+1}, 0], by `matrix_linear_recurrence`,
  then the rows dr_k/dp = Q^{1/2} (J^{z/x}_k S_k + [J^{z/theta}_k, 0]) / sqrt(T N)
  (`_sensitivity.rows`, shared with the sequential path).

With `chunk_size = c` every scan runs chunk by chunk (the rollout forwards, lam backwards
carrying lam_{k+1} between chunks, S forwards carrying S_k), so the stacked Jacobians
take O(c n^2) (and O(c n n_p) for the sensitivities) instead of O(T n^2); the states,
O(T n), are kept. Unchunked, the memory is that of the sequential "jacobian" strategy.

`value_and_grad_of_states` and `sensitivities_of_states` take the states as an argument
(from `newton_rollout`, or any rollout), so that a caller that already has them (a loss
and its gradient at the same point, a line search) does not solve for them twice.
"""

import jax
import jax.numpy as jnp

from .._gradient import local_terms, stacked_jacobians_T, theta_term_vjp
from .._sensitivity import emitter, rows
from ._chunks import chunked_scan
from ._recurrence import matrix_linear_recurrence, reverse_linear_recurrence
from ._rollout import newton_rollout


def padded_step_inputs(model, u):
    """What the step sees for every sample k = 0..T-1 (`Model.step_inputs`, T-1 rows), with
    one more row for the step out of x_{T-1}, which is never used."""
    us = model.step_inputs(u)
    last = us[-1:] if us.shape[0] else jnp.zeros((1, *us.shape[1:]), us.dtype)
    return jnp.concatenate([us, last])


def rollout(model, theta, x0, u, newton=None):
    """The states x_0..x_{T-1} of eq. (7) by `newton_rollout`, and its `RolloutInfo`."""
    return newton_rollout(model.step, theta, x0, padded_step_inputs(model, u), **(newton or {}))


def value_and_grad_of_states(
    model, cost, theta, xs, u, z, *, mask=None, norm=None, chunk_size=None
):
    """C and (grad_theta C, grad_x0 C) of one trajectory from its states `xs` (T, n_x).

    The O(T) recursion of `oneshot_jax._gradient` (module docstring) with lam by
    `reverse_linear_recurrence`, chunk by chunk with `chunk_size`.

    **Arguments:**

    - `model`, `cost`, `theta`, `u` (T, n_u), `z` (T, n_z), `mask`, `norm`: as for
        `oneshot_jax._gradient.one_shot`.
    - `xs`: (T, n_x), the states x_0..x_{T-1} of eq. (7) at `theta`.
    - `chunk_size`: steps per reverse scan (None: the whole record).

    **Returns:**

    `(C, (grad_theta, grad_x0))`, as `one_shot` returns.
    """
    T, n_x = xs.shape
    S, Gamma, gamma = local_terms(model, cost, theta, xs, u, z, mask)
    us = padded_step_inputs(model, u)

    # Step j maps x_j to x_{j+1}: lam_j = Gamma_j + (J^{x/x}_{j+1})^T lam_{j+1}, and lam_{j+1}
    # multiplies J^{x/theta}_{j+1}. Every state gets a step; the one out of x_{T-1} (and
    # any chunk padding) is masked to zero, so that lam_T = 0 gives lam_{T-1} = Gamma_{T-1}.
    def ended(x, u_keep, th):
        u_j, keep = u_keep
        return jnp.where(keep, model.step(x, u_j, th), jnp.zeros_like(x))

    def chunk(carry, inp):
        lam_next, acc = carry
        (x_c, u_c, g_c, has_step), valid = inp
        u_keep = (u_c, has_step & valid)
        At = stacked_jacobians_T(ended, theta, x_c, u_keep, "x")
        lam = reverse_linear_recurrence(At, jnp.where(valid[:, None], g_c, 0.0), lam_next)
        lam_shift = jnp.concatenate([lam[1:], lam_next[None]])
        term = theta_term_vjp(ended, theta, x_c, u_keep, lam_shift)
        return (lam[0], jax.tree_util.tree_map(jnp.add, acc, term)), ((), ())

    init = (jnp.zeros((n_x,), Gamma.dtype), jax.tree_util.tree_map(jnp.zeros_like, theta))
    has_step = jnp.arange(T) < T - 1
    (lam0, theta_term), _, _ = chunked_scan(
        chunk, init, (xs, us, Gamma, has_step), chunk_size, reverse=True
    )
    norm = T if norm is None else norm
    grad_theta = jax.tree_util.tree_map(lambda a, b: (a + b) / norm, gamma, theta_term)
    return S / norm, (grad_theta, lam0 / norm)


def parallel_value_and_grad(
    model, cost, theta, x0, u, z, *, mask=None, norm=None, newton=None, with_info=False
):
    """C and (grad_theta C, grad_x0 C) for one trajectory, as `_gradient.one_shot` returns:
    the states by `newton_rollout` (DEER, ELK, sequential fallback), then
    `value_and_grad_of_states`; every step is parallel over k.

    **Arguments:**

    - `model`, `cost`, `theta`, `x0` (n_x,), `u` (T, n_u), `z` (T, n_z), `mask`, `norm`: as
        for `oneshot_jax._gradient.one_shot`.
    - `newton`: a dict of keyword arguments of `newton_rollout` (`rtol`, `max_iter`,
        `damping`, `jacobian`, `fallback`, `chunk_size`); `chunk_size` also chunks the
        reverse recursion.
    - `with_info`: also return the rollout's `RolloutInfo`.

    **Returns:**

    `(C, (grad_theta, grad_x0))`, or `((C, (grad_theta, grad_x0)), info)` with `with_info`.
    """
    xs, info = rollout(model, theta, x0, u, newton)
    out = value_and_grad_of_states(
        model,
        cost,
        theta,
        xs,
        u,
        z,
        mask=mask,
        norm=norm,
        chunk_size=(newton or {}).get("chunk_size"),
    )
    return (out, info) if with_info else out


def sensitivities_of_states(
    model, cost, theta_of, p_theta, x0_of, p_x0, xs, u, z, *, scale, mask=None, chunk_size=None
):
    """The `Linearisation` of one trajectory's residuals from its states `xs` (T, n_x) at
    (theta_of(p_theta), x0_of(p_x0)): what `oneshot_jax._sensitivity.trajectory_jacobian`
    returns, with the sensitivity recursion by `matrix_linear_recurrence`, chunk by chunk
    with `chunk_size`.

    **Arguments:** as for `trajectory_jacobian` (without `strategy`), plus `xs`.
    """
    x0 = x0_of(p_x0)
    n_t, n_s = p_theta.shape[0], p_x0.shape[0]
    n_x = x0.shape[0]
    us = padded_step_inputs(model, u)
    f_theta = lambda x, u_k, p: model.step(x, u_k, theta_of(p))  # noqa: E731
    S0 = jnp.concatenate([jnp.zeros((n_x, n_t), x0.dtype), jax.jacfwd(x0_of)(p_x0)], axis=1)
    E = jnp.concatenate([jnp.eye(n_t, dtype=x0.dtype), jnp.zeros((n_t, n_s), x0.dtype)], 1)
    emit = emitter(model, cost, theta_of, p_theta, E)

    # A chunk holds the states x_a..x_b and the steps leaving them; S_a is carried in.
    def chunk(S_first, inp):
        (x_c, us_c, u_c), _ = inp  # rows of the padding are cut off by `chunked_scan`
        A, B = jax.vmap(jax.jacfwd(f_theta, argnums=(0, 2)), in_axes=(0, 0, None))(
            x_c, us_c, p_theta
        )
        B = jnp.concatenate([B, jnp.zeros((*B.shape[:2], n_s), B.dtype)], axis=2)
        S_next = matrix_linear_recurrence(A, B, S_first)  # S_{a+1}..S_{b+1}
        Ss = jnp.concatenate([S_first[None], S_next[:-1]])
        return S_next[-1], (jax.vmap(emit)(x_c, u_c, Ss), ())

    # The step past the last sample (S_T) is formed and not used, as in the "vjp" strategy.
    _, outs, _ = chunked_scan(chunk, S0, (xs, us, u), chunk_size)
    return rows(outs, z, cost, scale, mask, n_t, n_s)


def parallel_sensitivities(
    model,
    cost,
    theta_of,
    p_theta,
    x0_of,
    p_x0,
    u,
    z,
    *,
    scale,
    mask=None,
    newton=None,
    with_info=False,
):
    """The `Linearisation` of one trajectory's residuals, as
    `oneshot_jax._sensitivity.trajectory_jacobian` returns: the states by
    `newton_rollout`, then `sensitivities_of_states`.

    **Arguments:** as for `trajectory_jacobian` (without `strategy`), plus `newton` and
    `with_info` as for `parallel_value_and_grad`.

    **Returns:** the `Linearisation`, or `(linearisation, info)` with `with_info`.
    """
    xs, info = rollout(model, theta_of(p_theta), x0_of(p_x0), u, newton)
    out = sensitivities_of_states(
        model,
        cost,
        theta_of,
        p_theta,
        x0_of,
        p_x0,
        xs,
        u,
        z,
        scale=scale,
        mask=mask,
        chunk_size=(newton or {}).get("chunk_size"),
    )
    return (out, info) if with_info else out
