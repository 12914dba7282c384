"""Multi-step propagation of the model, eq. (2) and (7), and the loss of eq. (4), (5), (21)."""

import jax
import jax.numpy as jnp

from ._checks import check_data, check_penalty, filter_jit


def rollout(model, theta, x0, u):
    """States x[0..T-1] of eq. (7) for one trajectory: x[0] = x0, x[k+1] = f(x[k], u[k])."""

    def body(x, u_k):
        x_next = model.step(x, u_k, theta)
        return x_next, x_next

    _, xs = jax.lax.scan(body, x0, u[:-1])
    return jnp.concatenate([x0[None], xs], axis=0)


def step_loss(model, theta, x, u, z, weight, penalty, penalty_weight):
    """T times the local loss L_k of eq. (4) with the penalty of eq. (21):

    e^T Q e + penalty_weight * h(x, theta),  e = g(x, u, theta) - z  (eq. 3).
    """
    e = model.observe(x, u, theta) - z
    if weight is None:
        out = jnp.sum(e * e)
    elif weight.ndim == 1:
        out = jnp.sum(weight * e * e)
    else:
        out = e @ weight @ e
    if penalty is not None:
        out = out + penalty_weight * penalty(x, theta)
    return out


def trajectory_loss(model, theta, x0, u, z, weight, penalty, penalty_weight):
    """C of eq. (5)/(21) for one trajectory: the mean over k of `step_loss`."""
    xs = rollout(model, theta, x0, u)
    per_step = jax.vmap(step_loss, in_axes=(None, None, 0, 0, 0, None, None, None))(
        model, theta, xs, u, z, weight, penalty, penalty_weight
    )
    return jnp.mean(per_step)


@filter_jit
def _simulate(model, theta, x0, u, batched):
    def one(x0, u):
        xs = rollout(model, theta, x0, u)
        zs = jax.vmap(model.observe, in_axes=(0, 0, None))(xs, u, theta)
        return xs, zs

    return jax.vmap(one)(x0, u) if batched else one(x0, u)


@filter_jit
def _loss(model, theta, x0, u, z, weight, penalty, penalty_weight, batched):
    fn = lambda x0, u, z: trajectory_loss(  # noqa: E731
        model, theta, x0, u, z, weight, penalty, penalty_weight
    )
    return jnp.mean(jax.vmap(fn)(x0, u, z)) if batched else fn(x0, u, z)


def check_penalty_output(model, penalty, data):
    if penalty is None:
        return
    x = data.x0[0] if data.batched else data.x0
    out = jax.eval_shape(penalty, x, data.theta)
    if getattr(out, "shape", None) != ():
        raise ValueError(
            f"`penalty` must return a scalar h(x, theta), got shape {getattr(out, 'shape', out)}."
        )


def check_loss_args(model, theta, x0, u, z, weight, penalty, penalty_weight):
    """Validate the arguments shared by `loss` and the gradients: (data, penalty, lambda),
    with lambda as an array in the state's dtype."""
    data = check_data(model, theta, x0, u, z, weight)
    penalty, penalty_weight = check_penalty(penalty, penalty_weight)
    check_penalty_output(model, penalty, data)
    return data, penalty, jnp.asarray(penalty_weight, dtype=data.x0.dtype)


def simulate(model, theta, x0, u):
    """Simulate the model over the horizon of `u`, eq. (2).

    **Arguments:**

    - `model`: a `Model`.
    - `theta`: parameter pytree.
    - `x0`: initial state, shape (n_x,), or (N, n_x) for N trajectories.
    - `u`: inputs, shape (T, n_u), or (N, T, n_u).

    **Returns:**

    `(x, z)` with `x` of shape (T, n_x) (`x[0] = x0`, `x[k+1] = step(x[k], u[k], theta)`)
    and `z[k] = observe(x[k], u[k], theta)` of shape (T, n_z); with a leading N axis for
    several trajectories.
    """
    data = check_data(model, theta, x0, u)
    return _simulate(model, data.theta, data.x0, data.u, data.batched)


def loss(model, theta, x0, u, z, *, weight=None, penalty=None, penalty_weight=1.0):
    """The multi-step cost C of eq. (4), (5) and (21):

    C = (1/T) sum_{k=0}^{T-1} e_k^T Q e_k + (penalty_weight / T) sum_{k=0}^{T-1} h(x_k, theta),

    with e_k = zhat_k - z_k (eq. 3) the simulation (multi-step) error. For N trajectories
    it is the mean over trajectories of the single-trajectory C.

    **Arguments:**

    - `model`, `theta`, `x0`, `u`: as for `simulate`.
    - `z`: measured outputs, shape (T, n_z) or (N, T, n_z).
    - `weight`: Q of eq. (4), a (n_z,) vector (diagonal) or an (n_z, n_z) PSD matrix;
        identity by default.
    - `penalty`: h(x, theta) -> scalar of eq. (21), or None.
    - `penalty_weight`: the multiplier lambda of eq. (21).

    **Returns:**

    The scalar C.
    """
    data, penalty, lam = check_loss_args(model, theta, x0, u, z, weight, penalty, penalty_weight)
    return _loss(
        model, data.theta, data.x0, data.u, data.z, data.weight, penalty, lam, data.batched
    )
