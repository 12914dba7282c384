r"""The derivative kernels shared by every strategy: the two recursions of the paper and
the per-step derivatives they consume.

Notation (the paper's, see `oneshot_jax._gradient`): x_{k+1} = f(x_k, u_k, theta),
J^{x/x}_{k+1} = f_x(x_k, u_k, theta), J^{x/theta}_{k+1} = f_theta(x_k, u_k, theta),
Gamma_k = dL_k/dx_k and gamma_k = dL_k/dtheta (eq. 14).

- **Reverse** (`reverse_sweep`): the recursion that groups the O(T^2) chained products
  of eq. (17) and (20),

      lam_K = lam_end,   lam_k = Gamma_k + (J^{x/x}_{k+1})^T lam_{k+1},
      theta term = sum_k (J^{x/theta}_{k+1})^T lam_{k+1},   grad_x0 = lam_0.

- **Forward** (`forward_sweep`): the sensitivity recursion of the same chained products,

      S_{k+1} = J^{x/x}_{k+1} S_k + B_k,   B_k = [J^{x/theta}_{k+1}, 0] (or J^{x/theta} v),

  whose rows J^{z/x}_k S_k + [J^{z/theta}_k, 0] are the residual Jacobian
  (`oneshot_jax._sensitivity`).

Each recursion is written once here; a strategy (`oneshot_jax._strategy`) says *how* a
step is applied (a small product with a stacked Jacobian, or a VJP / JVP of the step
inside the scan) and how the recursion runs (a sequential `lax.scan`, or an associative
scan of `oneshot_jax._parallel`).
"""

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

# Up to this contracted size a matrix-vector product is written elementwise, and up to
# `_MATMUL_ELEMENTWISE_MAX` a matrix-matrix product (see `small_product`).
_MATVEC_ELEMENTWISE_MAX = 32
_MATMUL_ELEMENTWISE_MAX = 16


def small_product(A, x, transpose=False):
    """A @ x (or A^T @ x with `transpose`) for A (n, n') and x a vector or a matrix.

    For a small contracted size, a broadcast multiply and a sum, which XLA:CPU keeps
    inside a loop that it compiles into a single kernel (a `dot` there runs as a separate
    call per step of a scan).
    """
    vector = x.ndim == 1
    n = A.shape[0] if transpose else A.shape[1]
    if n > (_MATVEC_ELEMENTWISE_MAX if vector else _MATMUL_ELEMENTWISE_MAX):
        return (A.T if transpose else A) @ x
    if vector:
        return jnp.sum(A * x[:, None], axis=0) if transpose else jnp.sum(A * x[None, :], axis=1)
    if transpose:
        return jnp.sum(A[:, :, None] * x[:, None, :], axis=0)
    return jnp.sum(A[:, :, None] * x[None, :, :], axis=1)


def rollout(model, theta, x0, u):
    """States x[0..T-1] of eq. (7) for one trajectory by the sequential loop: x[0] = x0,
    x[k+1] = f(x[k], u[k]) (f sees `model.step_inputs(u)[k]`, which is u[k] under a
    zero-order hold)."""

    def body(x, u_k):
        x_next = model.step(x, u_k, theta)
        return x_next, x_next

    _, xs = jax.lax.scan(body, x0, model.step_inputs(u))
    return jnp.concatenate([x0[None], xs], axis=0)


def local_terms(model, cost, theta, xs, u, z, mask=None):
    """sum_k T L_k, every T Gamma_k (eq. 14) and sum_k T gamma_k, by one VJP of the vmapped L_k.

    The pullback of a vmapped function with an unbatched theta sums the per-step gamma_k
    inside the transposed ops (a weight matrix Q, say, becomes one matrix product).
    """

    def total(xs, th):
        per_step = jax.vmap(cost.local, in_axes=(None, None, 0, 0, 0, 0))(model, th, xs, u, z, mask)
        return jnp.sum(per_step)

    S, (Gamma, gamma) = jax.value_and_grad(total, argnums=(0, 1))(xs, theta)
    return S, Gamma, gamma


def stacked_jacobians_T(step, theta, xs, us, wrt):
    """Transposed one-step Jacobians at every (xs[j], us[j]), by forward mode (vmapped JVPs).

    Slice j, row i is the JVP of f(x, us_j, theta) at x = xs[j] along the i-th basis vector
    of x (`wrt="x"`: slice j is (J^{x/x}_{j+1})^T) or of the flattened theta (`wrt="theta"`:
    (J^{x/theta}_{j+1})^T). Building the transposes directly saves the moveaxis copies of
    `jax.jacfwd`, and they are what the reverse recursion multiplies with anyway (the
    paper's Remark 1: every Jacobian at once after the forward pass).

    The rows of theta never mix the derivatives of different entries: a tangent that is an
    explicit zero would still multiply a non-finite derivative (that of x**n with respect
    to n at x < 0, a held exponent) into every row. Where theta has more entries than x or
    a leaf has more than one entry, they come by reverse mode (one VJP per state), else
    (scalar leaves) leaf by leaf by forward mode with the other leaves held as constants.
    """
    if wrt == "x":
        basis = jnp.eye(xs.shape[-1], dtype=xs.dtype)
        tangent = lambda x, u_j, e: jax.jvp(lambda x: step(x, u_j, theta), (x,), (e,))[1]  # noqa: E731
        return jax.vmap(lambda x, u_j: jax.vmap(lambda e: tangent(x, u_j, e))(basis))(xs, us)
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    n_x, n_theta = xs.shape[-1], sum(int(jnp.size(leaf)) for leaf in leaves)
    if not leaves:
        return jnp.zeros((xs.shape[0], 0, n_x), xs.dtype)
    if n_theta > n_x or any(jnp.size(leaf) > 1 for leaf in leaves):
        # (forward mode by leaf would mix a leaf's entries: one tangent per entry of it)

        def reverse(x, u_j):
            out, pull = jax.vjp(lambda th: step(x, u_j, th), theta)
            basis = jnp.eye(n_x, dtype=out.dtype)
            return jax.vmap(lambda e: ravel_pytree(pull(e)[0])[0], out_axes=1)(basis)

        return jax.vmap(reverse)(xs, us)

    def rows(i):
        leaf = jnp.asarray(leaves[i])

        def f(x, u_j, value):
            return step(x, u_j, treedef.unflatten([*leaves[:i], value, *leaves[i + 1 :]]))

        basis = jnp.eye(leaf.size, dtype=leaf.dtype).reshape(leaf.size, *leaf.shape)
        one = lambda x, u_j, e: jax.jvp(lambda v: f(x, u_j, v), (leaf,), (e,))[1]  # noqa: E731
        return jax.vmap(lambda x, u_j: jax.vmap(lambda e: one(x, u_j, e))(basis))(xs, us)

    return jnp.concatenate([rows(i) for i in range(len(leaves))], axis=1)


def stacked_jacobians(f, xs, us, p, n_cols):
    """J^{x/x}_{j+1} (K, n, n) and [J^{x/p}_{j+1}, 0] (K, n, n_cols) of `f(x, u, p)` at
    every (xs[j], us[j]), by vmapped forward mode (the paper's Remark 1): the drive of the
    sensitivity recursion, with zero columns for the x0 entries after the n_p of p."""
    A, B = jax.vmap(jax.jacfwd(f, argnums=(0, 2)), in_axes=(0, 0, None))(xs, us, p)
    B = jnp.concatenate([B, jnp.zeros((*B.shape[:2], n_cols - p.shape[0]), B.dtype)], axis=2)
    return A, B


def theta_term_vjp(step, theta, xs, us, lam):
    """sum_j (J^{x/theta}_{j+1})^T lam[j] as one reverse-mode VJP of the vmapped step.

    The sum over steps happens inside the pullback (for a matrix parameter it is one matrix
    product), so no per-step parameter-sized cotangent is ever materialised.
    """
    batched = lambda th: jax.vmap(step, in_axes=(0, 0, None))(xs, us, th)  # noqa: E731
    return jax.vjp(batched, theta)[1](lam)[0]


def push(fn, x, p, S, E):
    """fn(x, p) and its directional derivatives along the columns (S[:, j], E[:, j]):
    J^{fn/x} S + J^{fn/p} E by one vmapped JVP, with the columns last."""
    return jax.vmap(lambda s, e: jax.jvp(fn, (x, p), (s, e)), in_axes=1, out_axes=(None, -1))(S, E)


def step_vjp(step, theta):
    """`apply((x_j, u_j), lam) = (J^{x/x}_{j+1})^T lam`, the VJP of the step in x."""

    def apply(point, lam):
        x_j, u_j = point
        return jax.vjp(lambda x: step(x, u_j, theta), x_j)[1](lam)[0]

    return apply


def step_jvp(step, theta):
    """`apply((x_j, u_j), s) = J^{x/x}_{j+1} s`, the JVP of the step in x."""

    def apply(point, s):
        x_j, u_j = point
        return jax.jvp(lambda x: step(x, u_j, theta), (x_j,), (s,))[1]

    return apply


def reverse_sweep(
    step, theta, xs, us, Gamma, lam_end, *, steps, apply_T=None, theta_rows=None, recurrence=None
):
    """The multiplier recursion that replaces the double sums of eq. (17) and (20):

        lam_K = lam_end,   lam_k = Gamma_k + (J^{x/x}_{k+1})^T lam_{k+1}   (k = K-1..0),
        theta term = sum_k (J^{x/theta}_{k+1})^T lam_{k+1}.

    **Arguments:**

    - `step`, `theta`: the step f(x, u, theta) and its parameters.
    - `xs`, `us`: (K, ...) the points x_k, u_k of the K steps (step k leaves x_k).
    - `Gamma`: (K, n), Gamma_k (eq. 14, or any cotangent of the states).
    - `lam_end`: (n,), lam_K.
    - `steps`: what `apply_T` reads per step (leading axis K): the stacked transposed
        Jacobians (K, n, n), or the points `(xs, us)` for an in-scan VJP; with
        `recurrence`, the stacked transposed Jacobians.
    - `apply_T`: `apply_T(steps[k], lam) = (J^{x/x}_{k+1})^T lam` (`small_product`, or
        `step_vjp`) for the sequential reverse `lax.scan`.
    - `theta_rows`: None, or the stacked (J^{x/theta}_{k+1})^T (K, p, n) (few parameters):
        the scan then also accumulates the theta term (forward mode); otherwise it is one
        VJP of the vmapped step after the scan (`theta_term_vjp`).
    - `recurrence`: None (sequential scan), or `reverse_linear_recurrence(At, g, lam_end)`
        of `oneshot_jax._parallel` (associative scan, O(log K) depth).

    **Returns:**

    `(lam_0, theta term)`: lam_0 (n,) (grad_x0 of eq. 20 when Gamma is dL/dx) and a pytree
    like theta.
    """
    if recurrence is not None:
        lam = recurrence(steps, Gamma, lam_end)
        lam0, lam_next = lam[0], jnp.concatenate([lam[1:], lam_end[None]])
    elif theta_rows is None:

        def body(lam_next, inp):
            step_k, Gamma_k = inp
            return Gamma_k + apply_T(step_k, lam_next), lam_next

        lam0, lam_next = jax.lax.scan(body, lam_end, (steps, Gamma), reverse=True)
    else:
        flat, unravel = ravel_pytree(theta)

        def body(carry, inp):
            lam_next, acc = carry
            step_k, Bt_k, Gamma_k = inp
            lam = Gamma_k + apply_T(step_k, lam_next)
            return (lam, acc + small_product(Bt_k, lam_next)), None

        init = (lam_end, jnp.zeros(flat.shape, jnp.result_type(flat, theta_rows)))
        (lam0, acc), _ = jax.lax.scan(body, init, (steps, theta_rows, Gamma), reverse=True)
        return lam0, unravel(acc.astype(flat.dtype))
    return lam0, theta_term_vjp(step, theta, xs, us, lam_next)


def forward_sweep(S0, steps, apply, drive=None, *, emit=None, recurrence=None):
    """The sensitivity recursion of eq. (17)/(20) forwards in time:

        S_{k+1} = J^{x/x}_{k+1} S_k + B_k   (k = 0..K-1),

    for a vector s_k (one direction) or a matrix S_k (one column per free variable).

    **Arguments:**

    - `S0`: S_0, (n,) or (n, m), or a pytree carried with it (see `emit`).
    - `steps`: what `apply` reads per step (leading axis K): stacked Jacobians (K, n, n)
        or the points of an in-scan JVP; with `recurrence`, the stacked J^{x/x}_{k+1}.
    - `apply`: `apply(steps[k], S) = J^{x/x}_{k+1} S` (`small_product`, `step_jvp`), or,
        with `drive=None`, the whole right-hand side.
    - `drive`: (K, n[, m]), the B_k, or None.
    - `emit`: None, or `emit(steps[k], S_k)`, evaluated inside the scan before the step:
        only what it returns is kept (the output rows of the residual Jacobian), never S_k.
    - `recurrence`: None (sequential `lax.scan`), or `matrix_linear_recurrence(A, B, S0)`
        of `oneshot_jax._parallel` (associative scan, O(log K) depth).

    **Returns:**

    Without `emit`: S_0..S_K stacked, (K+1, n[, m]). With it: `(S_K, outputs)` with the
    outputs of `emit` stacked over k = 0..K-1.
    """
    if recurrence is not None:
        return jnp.concatenate([S0[None], recurrence(steps, drive, S0)])
    if drive is None:
        advance = lambda step_k, S: apply(step_k, S)  # noqa: E731
        inputs = steps
    else:
        advance = lambda inp, S: apply(inp[0], S) + inp[1]  # noqa: E731
        inputs = (steps, drive)
    if emit is not None:

        def body(S, inp):
            out = emit(inp if drive is None else inp[0], S)
            return advance(inp, S), out

        return jax.lax.scan(body, S0, inputs)

    def body(S, inp):
        S_next = advance(inp, S)
        return S_next, S_next

    _, Ss = jax.lax.scan(body, S0, inputs)
    return jnp.concatenate([S0[None], Ss], axis=0)
