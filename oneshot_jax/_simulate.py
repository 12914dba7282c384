"""Multi-step propagation of the model, eq. (2) and (7), and the loss of eq. (4), (5), (21)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from ._aggregate import Aggregate, augment
from ._checks import check_cost, check_data
from ._jit import public_jit
from ._kernels import rollout as rollout
from ._parallel._report import counting, warn_counted
from ._strategy import AbstractStrategy, as_strategy, may_run_parallel


def outputs(model, theta, xs, u):
    """z[k] = g(x[k], u[k], theta) for every k (eq. 1)."""
    return jax.vmap(model.observe, in_axes=(0, 0, None))(xs, u, theta)


def trajectory_sum(model, cost, theta, x0, u, z, mask=None, strategy="auto"):
    """sum_k T L_k (eq. 4, 21) for one trajectory (masked terms excluded)."""
    xs = states(model, theta, x0, u, strategy)
    per_step = jax.vmap(cost.local, in_axes=(None, None, 0, 0, 0, 0))(model, theta, xs, u, z, mask)
    return jnp.sum(per_step)


def sample_count(u, mask, dtype):
    """The number of time points C is normalised by: N T, or the unpadded ones."""
    if mask is None:
        return jnp.asarray(np.prod(u.shape[:-1]), dtype)
    return jnp.sum(mask.samples).astype(dtype)


def states(model, theta, x0, u, strategy="auto"):
    """The states of eq. (7) for one trajectory, sequentially or parallel in time, as the
    strategy (resolved for this trajectory, `oneshot_jax._strategy`) rolls them out."""
    strategy = as_strategy(strategy).resolve(x0.shape[0], u.shape[0], x0.dtype.itemsize)
    return strategy.states(model, theta, x0, u)


def _simulate(model, theta, x0, u, batched, strategy="auto"):
    def one(x0, u):
        xs = states(model, theta, x0, u, strategy)
        return xs, outputs(model, theta, xs, u)

    return jax.vmap(one)(x0, u) if batched else one(x0, u)


def _loss(model, cost, theta, x0, u, z, batched, mask=None, strategy="auto"):
    """C of eq. (5)/(21): the sum of T L_k over trajectories and time points, divided by
    the number of time points (the mean over trajectories of each one's C when they are
    all of the same length and nothing is masked)."""
    fn = lambda x0, u, z, m: trajectory_sum(model, cost, theta, x0, u, z, m, strategy)  # noqa: E731
    total = jnp.sum(jax.vmap(fn)(x0, u, z, mask)) if batched else fn(x0, u, z, mask)
    return total / sample_count(u, mask, x0.dtype)


# (Inside the library's compiled calls, `fit`'s solve; the public functions take the
# compiled calls with the library's compiler options, `_jit.public_jit`.)
simulate_impl = eqx.filter_jit(_simulate)
loss_impl = eqx.filter_jit(_loss)
simulate_compiled = public_jit(_simulate)
loss_compiled = public_jit(_loss)


def simulate(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    *,
    strategy: str | AbstractStrategy = "auto",
    t: Float[ArrayLike, "*N T"] | None = None,
) -> tuple[Float[Array, "*N T n_x"], Float[Array, "*N T n_z"]]:
    """Simulate the model over the horizon of `u`, eq. (2).

    **Arguments:**

    - `model`: a `Model`.
    - `theta`: parameter pytree.
    - `x0`: initial state, shape (n_x,), or (N, n_x) for N trajectories.
    - `u`: inputs, shape (T, n_u), or (N, T, n_u), or a list of N arrays (T_i, n_u) of
        different lengths.
    - `strategy`: `ParallelInTime(...)` (`"parallel"`) computes the rollout parallel in
        time (Newton iterations over the whole record with associative scans, and a
        sequential fallback, reported by a warning, where they do not converge; its
        options are those of the Newton iterations); `Jacobian()` and `VJP()` are the
        sequential loop, and `Auto()` (`"auto"`) takes the parallel one on a GPU or TPU
        for long records (see `value_and_grad`).
    - `t`: the sample times, for a model of time-stamped records
        (`Model.from_ode(rhs, dt=None)`; required there, refused by any other model):
        shape (T,), or (N, T), or a list of N arrays (T_i,) like `u`; finite and strictly
        increasing. Step k integrates over t[k+1] - t[k]. (Traced `t`, under `jax.jit` or
        `vmap`, cannot be checked on the host: with `max_step`, an interval that is
        negative, not finite or needs more than `substeps + 1` steps gives NaN states from
        there on; without it, the values are taken as given.)

    **Returns:**

    `(x, z)` with `x` of shape (T, n_x) (`x[0] = x0`, `x[k+1] = step(x[k], u[k], theta)`)
    and `z[k] = observe(x[k], u[k], theta)` of shape (T, n_z); with a leading N axis for
    several trajectories (lists of arrays for a list `u` of records of different lengths;
    a list of records of one length gives the stacked arrays).
    """
    data = check_data(model, theta, x0, u, t=t)
    strategy = as_strategy(strategy)
    # (a parallel rollout's fallbacks: warned at the caller's line)
    with counting(may_run_parallel(strategy)) as counts:
        x, z = simulate_compiled(data.model, data.theta, data.x0, data.u, data.batched, strategy)
    warn_counted(counts, stacklevel=2)
    if data.lengths is not None:  # ragged lists in, ragged lists out
        return [x[i, :n] for i, n in enumerate(data.lengths)], [
            z[i, :n] for i, n in enumerate(data.lengths)
        ]
    return x, z


def loss(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    z: Float[ArrayLike, "*N T n_z"],
    *,
    weight: Float[ArrayLike, " n_z"] | Float[ArrayLike, "n_z n_z"] | None = None,
    penalty=None,
    penalty_weight: float = 1.0,
    missing: str = "raise",
    strategy: str | AbstractStrategy = "auto",
    aggregate: Aggregate | list | None = None,
    t: Float[ArrayLike, "*N T"] | None = None,
) -> Float[Array, ""]:
    """The multi-step cost C of eq. (4), (5) and (21):

    C = (1/T) sum_{k=0}^{T-1} e_k^T Q e_k + (penalty_weight / T) sum_{k=0}^{T-1} h(x_k, theta),

    with e_k = zhat_k - z_k (eq. 3) the simulation (multi-step) error. For N trajectories
    it is the sum over all of them divided by the number of time points N T (the mean of
    their C's); for trajectories of different lengths T_i it is divided by sum_i T_i, and
    missing output samples contribute zero.

    **Arguments:**

    - `model`, `theta`, `x0`, `u`: as for `simulate`.
    - `z`: measured outputs, shape (T, n_z) or (N, T, n_z), or a list like `u`.
    - `weight`: Q of eq. (4), a (n_z,) vector (diagonal) or an (n_z, n_z) PSD matrix
        (for one output also a scalar); identity by default. A vector's entries are
        >= 0; a matrix is symmetric positive semi-definite (its off-diagonal entries may
        be negative). Checked where concrete: a traced weight is taken as given.
    - `penalty`: h(x, theta) -> scalar of eq. (21), or None.
    - `penalty_weight`: the multiplier lambda of eq. (21), applied with the 1/T of the
        error (the paper's eq. (21) adds lambda h to the sum of the L_k without it: its
        lambda is `penalty_weight / T`). Without a `penalty` it multiplies nothing (so a
        sweep may pass `penalty=None` and a weight alike).
    - `missing`: `"raise"` (default) rejects NaN in z; `"mask"` takes NaN entries of z as
        missing samples, which contribute nothing to C (nor to its derivatives). Under
        `jax.jit` or `vmap` (traced z) `"mask"` masks the NaN as on the host, while
        `"raise"` cannot look at the values: a NaN in z gives a NaN C there.
    - `strategy`: how the rollout is computed, as for `simulate`.
    - `aggregate`: aggregated readings of some outputs, an `Aggregate` or a list of them
        (for N trajectories, a list of N entries, each an `Aggregate`, a list or None).
        Each reading i adds w_i (r_i - v_i)^2 to the sum before the division by the
        number of time points, with r_i its predicted aggregate (`Aggregate`).
    - `t`: the sample times of a timed model's records, as for `simulate`.

    **Returns:**

    The scalar C.
    """
    if z is None:
        raise ValueError("`z` is required: the measured outputs, shape (T, n_z).")
    data = check_data(model, theta, x0, u, z, weight, missing, t, aggregate is not None)
    if aggregate is not None:
        agg = augment(data, aggregate, model, x0, missing, t=t)
        data = check_data(agg.model, theta, agg.x0, agg.u, agg.z, agg.weight, "mask")
        penalty = agg.penalty(penalty)
    cost = check_cost(data, penalty, penalty_weight)
    # (validated here; an alias string goes on as given: one cache key)
    with counting(may_run_parallel(as_strategy(strategy))) as counts:
        C = loss_compiled(
            data.model, cost, data.theta, data.x0, data.u, data.z, data.batched, data.mask, strategy
        )
    warn_counted(counts, stacklevel=2)
    return C
