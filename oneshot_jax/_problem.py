"""What a fit optimises: the data, the cost and the parametrisation of the free variables.

The free variables are two arrays, `Params.theta` (the free entries of the flattened
theta) and `Params.x0` (N, m) (the free entries of each trajectory's initial state).
Fixed entries are constants inside `FitProblem.theta_of` / `FitProblem.x0_of`, so they are
removed from the variables rather than masked (a masked variable leaves a singular
Jacobian).

A fit with a proximal regulariser g (`oneshot_jax.sparsity`, passed in `regulariser=`)
minimises C + g(theta). g is written on the user's theta; `FitProblem.prox` applies its
proximal map to the free entries with per-coordinate steps (zero on the fixed entries,
which a prox with a zero step leaves unchanged).
"""

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from . import _pytree
from ._cost import Cost, Mask
from ._gradient import value_and_grad_impl
from ._sensitivity import (
    Linearisation,
    Trajectory,
    linearise_trajectory,
    residual_jvp,
    residual_vjp,
    trajectory_jacobian,
    trajectory_residuals,
)
from ._simulate import loss_impl, sample_count
from ._strategy import as_strategy

# Rounds of Dykstra's projections where a general projection meets fixed entries
# (`FitProblem.feasible`): a halfspace that weights a fixed entry like the free ones
# leaves 3^-60 of the excess after 60 rounds.
DYKSTRA_STEPS = 60
# The most rounds of the Dykstra-like splitting that gives the prox of a regulariser plus
# a set's indicator where their composition is not it (`FitProblem.prox_feasible`); the
# rounds stop once an iterate and its corrections repeat to round-off.
PROX_ROUNDS = 500


class Params(NamedTuple):
    """The free variables of a fit: theta's free entries (p,) and x0's free entries (N, m)."""

    theta: jax.Array
    x0: jax.Array


class Regulariser(eqx.Module):
    """A `sparsity.ProximalTransformation` seen on theta's trainable part: the user's
    prox and value (written on the whole theta, `where` included) with theta's static part
    (functions and other non-numeric leaves of equinox modules) bound in."""

    prox_fn: Callable
    value_fn: Callable
    static: Any
    strength: float | None = eqx.field(static=True)
    learning_rate: Any
    # whether g is a sum of per-entry terms (`sparsity.l1`, `l2`): its prox then composes
    # with a box's clip into the prox of their sum (`FitProblem.prox_feasible`)
    separable: bool = eqx.field(static=True, default=False)

    def _whole(self, params):
        return _pytree.combine(params, self.static)

    def value(self, params):
        """g(theta)."""
        return self.value_fn(self._whole(params))

    def prox(self, params, steps):
        """prox of g at theta with per-coordinate steps (a pytree like `params`)."""
        new = self.prox_fn(self._whole(params), self._whole(steps))
        return eqx.filter(new, _pytree.is_parameter)


class FitProblem(eqx.Module):
    """Data, cost and parametrisation of the free variables (built by `fit`)."""

    model: eqx.Module
    cost: Cost
    u: jax.Array  # (N, T, n_u)
    z: jax.Array  # (N, T, n_z)
    theta_base: jax.Array  # flat theta with the fixed values
    theta_free: tuple = eqx.field(static=True)  # indices of the free entries (tuple of int)
    unravel: Callable = eqx.field(static=True)
    x0_base: jax.Array  # (N, n_x) with the fixed values
    x0_free: tuple = eqx.field(static=True)
    project: Callable | None = eqx.field(static=True)  # a general projection, or None
    lower: jax.Array | None  # box bounds on Params.theta (or None)
    upper: jax.Array | None
    mask: Mask | None = None  # padded or missing samples (N, T, n_z) / (N, T), or None
    regulariser: Regulariser | None = None  # a proximal g of theta (objective C + g), or None
    # positions among the free entries of theta that belong to a network (equinox module):
    # nuisance parameters of the named ones' covariance (`_covariance.marginal`)
    nuisance: tuple = eqx.field(static=True, default=())
    validation: Any = None  # a `_validation.Monitor` (held-out records scored per iterate), or None
    # box bounds on Params.x0 (N, m), each trajectory's free x0 entries (-inf, inf where
    # unbounded), or None (`fit(x0_bounds=...)`, MATLAB's `InitialStates(i).Minimum`)
    x0_lower: jax.Array | None = None
    x0_upper: jax.Array | None = None
    # (N, m) the free x0 entries a record holds at its value (`fit` given a mask per
    # record, MATLAB's `InitialStates(i).Fixed` per experiment), or None: bounded above
    # and below by that value in `x0_lower`/`x0_upper` for the solvers, and counted
    # neither in the covariance nor in the degrees of freedom (`_covariance`)
    x0_held: jax.Array | None = None

    @property
    def dtype(self):
        return self.x0_base.dtype

    @property
    def n_traj(self):
        return self.u.shape[0]

    @property
    def constrained(self) -> bool:
        """Whether theta has bounds or a projection (static: known when tracing)."""
        return self.lower is not None or self.project is not None

    @property
    def x0_bounded(self) -> bool:
        """Whether x0 has box bounds (static: known when tracing)."""
        return self.x0_lower is not None

    def feasible_x0(self, p_x0):
        """Clip the free x0 entries p_x0 (N, m) into their box (unchanged without one)."""
        if self.x0_lower is None:
            return p_x0
        return jnp.clip(p_x0, self.x0_lower, self.x0_upper)

    def theta_of(self, p_theta):
        """theta (the parameters' pytree) with the free entries `p_theta`. A leaf whose
        entries are all held is the constant of `theta_base`: derivatives with respect to
        p_theta then never pass through it (an explicit zero tangent would still multiply
        a non-finite derivative, that of x**n with respect to a held n at x < 0)."""
        base = jnp.asarray(self.theta_base)
        if self.theta_free == tuple(range(base.shape[0])):  # all free: no scatter to trace
            return self.unravel(p_theta.astype(base.dtype))
        theta = self.unravel(base.at[np.asarray(self.theta_free, int)].set(p_theta))
        leaves, treedef = jax.tree_util.tree_flatten(theta)
        held = self._held_leaves(leaves)
        if not any(held):
            return theta
        constant = jax.tree_util.tree_leaves(self.unravel(base))
        return treedef.unflatten([c if h else v for v, c, h in zip(leaves, constant, held)])

    def _held_leaves(self, leaves):
        """Per leaf of theta (in `ravel_pytree`'s order), whether every entry is held."""
        free = np.zeros(self.theta_base.shape[0], bool)
        free[np.asarray(self.theta_free, int)] = True
        sizes = np.cumsum([0, *(int(np.size(leaf)) for leaf in leaves)])
        return [not free[a:b].any() for a, b in zip(sizes[:-1], sizes[1:])]

    def x0_of(self, p_x0):
        base = jnp.asarray(self.x0_base)
        if self.x0_free == tuple(range(base.shape[-1])):  # all free: no scatter to trace
            return p_x0.astype(base.dtype)
        return base.at[:, np.asarray(self.x0_free, int)].set(p_x0)

    def split(self, theta_flat, x0) -> Params:
        """The free variables of a flat theta and an (N, n_x) x0."""
        return Params(
            theta_flat[np.asarray(self.theta_free, int)], x0[:, np.asarray(self.x0_free, int)]
        )

    def feasible(self, p_theta):
        """Project p_theta onto the constraint set.

        A box alone is exact. A general projection P_C acts on the whole theta; with
        fixed entries the set is C intersected with {the fixed entries at their values}
        (A), and P_C followed by restoring the fixed entries leaves C wherever P_C moves
        a fixed entry (a constraint on a sum that includes one). Dykstra's alternating
        projections onto C and A (Boyle and Dykstra, 1986), `DYKSTRA_STEPS` rounds,
        converge to the projection onto the intersection: inside A exactly, and inside C
        up to the rate of the rounds (geometric for a halfspace)."""
        if self.lower is not None:
            p_theta = jnp.clip(p_theta, self.lower, self.upper)
        if self.project is not None:
            free = np.asarray(self.theta_free, int)

            def P_C(theta_flat):
                flat, _ = ravel_pytree(self.project(self.unravel(theta_flat)))
                return flat.astype(theta_flat.dtype)

            def P_A(theta_flat):
                return self.theta_base.at[free].set(theta_flat[free])

            if len(free) == self.theta_base.shape[0]:
                flat, _ = ravel_pytree(self.project(self.theta_of(p_theta)))
                p_theta = flat[free]
            else:

                def round_(_, carry):
                    x, p, q = carry
                    y = P_C(x + p)
                    p = x + p - y
                    x_new = P_A(y + q)
                    return x_new, p, y + q - x_new

                x = jnp.asarray(self.theta_base).at[free].set(p_theta)
                zero = jnp.zeros_like(x)
                x, _, _ = jax.lax.fori_loop(0, DYKSTRA_STEPS, round_, (x, zero, zero))
                p_theta = x[free]
            if self.lower is not None:
                p_theta = jnp.clip(p_theta, self.lower, self.upper)
        return p_theta

    def prox_feasible(self, v, steps):
        """The prox of g plus the constraint set's indicator at the free entries v, in the
        metric diag(1 / steps) (`steps` a scalar, or one per free entry for box bounds
        only), and whether it was resolved: the projected proximal step of Section 3.3
        with a regulariser.

        Where the set is a box and g is separable (or there is no set, or no g), the
        projection of g's prox is this prox. Elsewhere (a group lasso in a box, or any g
        with a general projection) it is not: its fixed points need not be stationary
        (an l1 term on a half-space stopped 0.014 from its optimum with the measure at
        0). There the Dykstra-like splitting of Bauschke and Combettes (2008), which
        alternates the two proxes with their corrections, converges to the prox of the
        sum; its rounds stop once an iterate and its two corrections repeat to
        round-off, at most `PROX_ROUNDS` (resolved False if they had not)."""
        exact = self.regulariser is None or (
            self.project is None and (self.lower is None or self.regulariser.separable)
        )
        if exact:
            return self.feasible(self.prox(v, steps)), jnp.array(True)
        eps = jnp.finfo(v.dtype).eps

        def cond(c):
            i, _, _, _, change = c
            return (i < PROX_ROUNDS) & (change > 0)

        def moved(a, b):  # entries that changed by more than their round-off
            return jnp.sum(jnp.abs(b - a) > 4 * eps * jnp.maximum(jnp.abs(a), jnp.abs(b)))

        def round_(c):
            i, x, p, q, _ = c
            y = self.prox(x + p, steps)
            p_new = x + p - y
            x_new = self.feasible(y + q)
            q_new = y + q - x_new
            # (x can repeat for a round while the corrections still move: an l1 term on
            # a half-space stopped at round 2 at the composition's point; the rounds end
            # where x and both corrections repeat)
            change = moved(x, x_new) + moved(p, p_new) + moved(q, q_new)
            return i + 1, x_new, p_new, q_new, change

        zero = jnp.zeros_like(v)
        start = (jnp.array(0), v, zero, zero, jnp.array(1))
        rounds, x, _, _, change = jax.lax.while_loop(cond, round_, start)
        del rounds
        return x, change == 0

    def g(self, p_theta):
        """The regulariser g(theta) at the free entries (0 without one)."""
        if self.regulariser is None:
            return jnp.zeros((), self.dtype)
        return jnp.asarray(self.regulariser.value(self.theta_of(p_theta)), self.dtype)

    def prox(self, p_theta, steps):
        """prox of g at the free entries p_theta in the metric diag(1 / steps):
        argmin_y g(y) + sum_i (y_i - p_i)^2 / (2 steps_i), with `steps` a scalar or one
        step per free entry (the fixed entries get step 0: unchanged). The identity
        without a regulariser."""
        if self.regulariser is None:
            return p_theta
        free = np.asarray(self.theta_free, int)
        steps = jnp.broadcast_to(jnp.asarray(steps, p_theta.dtype), p_theta.shape)
        full = jnp.zeros_like(self.theta_base).at[free].set(steps)
        new = self.regulariser.prox(self.theta_of(p_theta), self.unravel(full))
        flat, _ = ravel_pytree(new)
        return flat[free].astype(p_theta.dtype)

    def loss(self, params: Params, strategy="auto"):
        """C (eq. 5/21) at the free variables: one simulation."""
        return loss_impl(
            self.model,
            self.cost,
            self.theta_of(params.theta),
            self.x0_of(params.x0),
            self.u,
            self.z,
            True,
            self.mask,
            strategy,
        )

    def value_and_grad(self, params: Params, strategy):
        """C and its gradient in the free variables, by the one-shot recursion (eq. 17, 20)."""
        C, (g_theta, g_x0) = value_and_grad_impl(
            self.model,
            self.cost,
            self.theta_of(params.theta),
            self.x0_of(params.x0),
            self.u,
            self.z,
            True,
            strategy,
            self.mask,
        )
        g_flat, _ = ravel_pytree(g_theta)
        return C, Params(
            g_flat[np.asarray(self.theta_free, int)], g_x0[:, np.asarray(self.x0_free, int)]
        )

    def _scale(self):
        return 1.0 / jnp.sqrt(sample_count(self.u, self.mask, self.dtype))

    def residuals(self, params: Params, penalty=True, strategy="auto"):
        """Stacked residuals (N, R) with ||r||^2 = C (see `_sensitivity`), and the smallest
        lambda h(x_k) over all trajectories (+inf without a penalty)."""
        cost = self.cost if penalty else Cost(self.cost.weight, None, self.cost.penalty_weight)
        theta = self.theta_of(params.theta)
        x0 = self.x0_of(params.x0)
        fn = lambda x0, u, z, m: trajectory_residuals(  # noqa: E731
            self.model, cost, theta, x0, u, z, scale=self._scale(), mask=m, strategy=strategy
        )
        r, h_min = jax.vmap(fn)(x0, self.u, self.z, self.mask)
        return r, jnp.min(h_min)

    def jacobian(self, params: Params, strategy, penalty=True) -> Linearisation:
        """Residuals (N, R) and their closed-form Jacobians (N, R, p), (N, R, m)."""
        cost = self.cost if penalty else Cost(self.cost.weight, None, self.cost.penalty_weight)
        x0_free = np.asarray(self.x0_free, int)
        N, T = self.u.shape[:2]
        n_x = self.x0_base.shape[1]
        n_cols = params.theta.shape[0] + x0_free.size
        # The strategy for the whole batch (`Auto` counts the work of all N trajectories).
        strategy = as_strategy(strategy).resolve(n_x, T, self.dtype.itemsize, N, n_cols)

        def fn(base, p, u, z, m):
            return trajectory_jacobian(
                self.model,
                cost,
                self.theta_of,
                params.theta,
                lambda q: base.at[x0_free].set(q),
                p,
                u,
                z,
                scale=self._scale(),
                strategy=strategy,
                mask=m,
            )

        lin = jax.vmap(fn)(jnp.asarray(self.x0_base), params.x0, self.u, self.z, self.mask)
        return lin._replace(h_min=jnp.min(lin.h_min))

    # Matrix-free products with the Jacobian of `residuals` (see `_sensitivity`).

    def linearise(self, params: Params, strategy):
        """The residuals (N, R), the smallest lambda h, and each trajectory's linearisation
        point (`Trajectory`, batched) for `jvp` / `vjp`."""
        r, h_min = self.residuals(params)
        theta = self.theta_of(params.theta)
        x0 = self.x0_of(params.x0)
        traj = jax.vmap(lambda x0, u: linearise_trajectory(self.model, theta, x0, u, strategy))(
            x0, self.u
        )
        return r, h_min, traj

    def jvp(self, params: Params, traj: Trajectory, v_theta, v_x0, strategy):
        """J v for a direction in the free variables: v_theta (p,) and v_x0 (N, m). (N, R)."""
        theta = self.theta_of(params.theta)
        free = np.asarray(self.theta_free, int)
        dtheta = self.unravel(jnp.zeros_like(self.theta_base).at[free].set(v_theta))
        x0_free = np.asarray(self.x0_free, int)
        dx0 = jnp.zeros(self.x0_base.shape, self.dtype).at[:, x0_free].set(v_x0)

        def one(traj, u, dx0, m):
            return residual_jvp(
                self.model,
                self.cost,
                theta,
                traj,
                u,
                dtheta,
                dx0,
                scale=self._scale(),
                strategy=strategy,
                mask=m,
            )

        return jax.vmap(one)(traj, self.u, dx0, self.mask)

    def vjp(self, params: Params, traj: Trajectory, w, strategy):
        """J^T w for residual cotangents w (N, R): each trajectory's theta part (N, p) (sum
        them for J^T w) and its x0 part (N, m)."""
        theta = self.theta_of(params.theta)
        free = np.asarray(self.theta_free, int)
        x0_free = np.asarray(self.x0_free, int)

        def one(traj, u, w, m):
            g_theta, g_x0 = residual_vjp(
                self.model,
                self.cost,
                theta,
                traj,
                u,
                w,
                scale=self._scale(),
                strategy=strategy,
                mask=m,
            )
            return ravel_pytree(g_theta)[0][free], g_x0[x0_free]

        return jax.vmap(one)(traj, self.u, w, self.mask)
