"""Structured Gauss-Newton / Levenberg-Marquardt on the closed-form residual Jacobian.

Both minimise C = ||r||^2 over the free variables (see `oneshot_jax._sensitivity` for r
and its Jacobian by forward sensitivities, the forward twin of eq. (17) and (20)). They
share everything but the globalisation, which each concrete solver supplies:
`GaussNewton` backtracks along the projected step, `LevenbergMarquardt` adapts its
damping (Nielsen's rule).

The linear algebra is structured: theta's columns are shared by all trajectories
(windows), each trajectory's x0 columns touch only its own residuals, so J^T J is an arrow
matrix and the x0 blocks are eliminated by a Schur complement (`structured_step`); the
cost is linear in the number of trajectories.

**Matrix-free normal equations** (`linear_solver="cg"`, chosen by "auto" above
`_strategy.MATRIX_FREE_MIN_THETA` free entries of theta). The theta block is never
formed: the Schur complement system S h_theta = -(g_t - sum_i B_i C_i^{-1} g_i) is solved
by preconditioned conjugate gradients (Hestenes and Stiefel 1952; Nocedal and Wright,
"Numerical optimization", Alg. 5.3), with S v = J_t^T (J_t v) + mu D_t v
- sum_i B_i (C_i + mu D_i)^{-1} B_i^T v. J_t v is one forward sensitivity along v and
J_t^T w the one-shot reverse recursion with output cotangents w
(`_sensitivity.residual_jvp` / `residual_vjp`); the per-step Jacobians J^{x/x}_k are
formed once per linearisation, so a product costs two vmapped model JVPs/VJPs and two
small scans, whatever n_theta. The x0 blocks stay exact: each trajectory's m x0 columns
are formed (m forward sensitivities) and B_i = J_t^T J_{x,i} takes m reverse products.
Marquardt's D_t = diag(J_t^T J_t) is exact (p forward sensitivities) while
p <= `DIAG_PROBES`, and otherwise estimated as the mean of (J_t^T w)^2 over
`DIAG_PROBES` Rademacher vectors w (E[(J^T w)(J^T w)^T] = J^T J; Bekas, Kokiopoulou and
Saad, "An estimator for the diagonal of a matrix", 2007), which is unbiased and scales
with the parameters' units as the exact one does. CG is preconditioned by diag(S)
(Jacobi) formed from the exact D_t and the x0 blocks, or by (1 + mu) D_t with the
estimate. CG stops at
a relative residual `cg_rtol` or after `cg_max_steps` iterations: a truncated step is
still a descent direction, and the step's decrease is measured with J s itself, so the
globalisation is unchanged (an inexact Gauss-Newton / LM method).

Bounds and projections: each iterate is projected (a box is clipped), and entries at a
bound whose gradient points outwards are held for the step (an active set). A step that
the projection clipped can predict no decrease (or fail) at any damping; it is then
replaced by a projected scaled-gradient step with an Armijo search along the projection
arc (`_gradient_arc`; Kanzow, Yamashita and Fukushima 2004), which decreases C at every
point that is not stationary. So a bound never stops the fit short of a solution.

Stopping (`oneshot_jax._optimality`): the fit converges (succeeds) when the first-order
measure at the current iterate, the scaled projected gradient, is at most `gtol`, or
when no step decreases C at round-off with the measure at most its round-off limit
10 sqrt(eps) (a loss known to relative precision eps resolves cosines down to about
sqrt(eps) only, so a slowly converging fit can stop a little above gtol = 1e-8); it
is `zero_residual` (success) when it can make no further progress with the loss at the
round-off level of the data. Every other stop is a failure that names its test:
`stalled` when no step decreases C while the linear model's predicted decrease is at
round-off (MINPACK's ftol test at machine epsilon) or the step is at the round-off
level of the parameters, or when the optional step test fired (rtol, atol: an accepted
step with ||D s|| <= rtol ||D p|| + atol and a decrease <= rtol C + atol, D =
sqrt(diag(J^T J))) before the first-order test; `no_progress` when LM's damping passes
1e20 or GN's backtracking 2^-30 and the gradient step fails too; `max_steps_reached`.
A penalty enters as residuals sqrt(lambda h / T): lambda h must be non-negative, and the
solver stops with `RESULTS.negative_penalty` (reporting the true loss) when it is not.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._linalg import floor, normal_blocks, psd_solve
from .._optimality import (
    Measures,
    data_scale,
    first_order,
    lazy_cond,
    roundoff_limit,
    zero_residual,
)
from .._problem import Params
from .._results import RESULTS
from .._sensitivity import Trajectory
from .._strategy import LINEAR_SOLVERS, ParallelInTime, as_strategy, least_squares_solver
from .base import AbstractSolver, check_options

# Rademacher probes for Marquardt's diagonal in the matrix-free solve (exact when the
# number of free theta entries is at most this).
DIAG_PROBES = 16


class Blocks(NamedTuple):
    """C and the blocks of J^T J, J^T r at the current iterate (see `normal_blocks`)."""

    C: jax.Array
    A: jax.Array
    B: jax.Array
    Cb: jax.Array
    g_t: jax.Array
    g_x: jax.Array


class MatrixFreeBlocks(NamedTuple):
    """The last linearisation of the matrix-free solve: what the dense `Blocks` hold, but
    the theta block as its linearisation point (`traj`) and Marquardt's diagonal `D_t`
    instead of A = J_t^T J_t; the x0 columns Jx (N, R, m) are formed."""

    C: jax.Array
    D_t: jax.Array  # (p,) diag(J_t^T J_t), exact or estimated
    B: jax.Array  # (N, p, m)
    Cb: jax.Array  # (N, m, m)
    g_t: jax.Array
    g_x: jax.Array
    Jx: jax.Array  # (N, R, m)
    traj: Trajectory  # batched over the N trajectories


class LSQState(NamedTuple):
    blocks: Blocks | MatrixFreeBlocks  # the linearisation at the current iterate
    loss: jax.Array  # C at the current iterate
    h_min: jax.Array  # the smallest lambda h(x_k) at the current iterate
    mu: jax.Array  # damping (0 for Gauss-Newton)
    nu: jax.Array  # Nielsen's damping growth
    scale: jax.Array  # the loss of predicting zero outputs (`_optimality.data_scale`)
    measures: Measures  # the first-order measure here, the last step and its prediction
    done: jax.Array
    result: RESULTS


class Trial(NamedTuple):
    """The outcome of a globalisation: the new point, its loss, whether it was accepted,
    the new damping and whether the globalisation gave up."""

    params: Params
    loss: jax.Array
    accept: jax.Array
    mu: jax.Array
    nu: jax.Array
    gave_up: jax.Array


def structured_step(A, B, Cb, g_t, g_x, mu, active):
    """Solve (J^T J + mu D) h = -J^T r by eliminating each trajectory's x0 block.

    With theta columns shared and x0_i columns only in trajectory i, J^T J is an arrow
    matrix [[A, B_1 .. B_N], [B_i^T, C_i]]. The Schur complement
    S = A + mu D_t - sum_i B_i (C_i + mu D_i)^{-1} B_i^T gives h_theta; then
    h_i = -(C_i + mu D_i)^{-1} (g_i + B_i^T h_theta). Cost O(N m^3 + p^3), linear in N.
    D is Marquardt's diag(J^T J), which makes the step invariant to parameter scaling.
    Entries of theta in `active` (at a bound, pushed outwards) are held at zero step.
    Pseudo-inverses throughout: a direction without effect gets a zero step.
    """
    m = Cb.shape[-1]
    D_t = floor(jnp.diag(A))
    if m:
        D_x = jax.vmap(lambda c: floor(jnp.diag(c)))(Cb)
        Cd = Cb + mu * jax.vmap(jnp.diag)(D_x)
        CinvBt = psd_solve(Cd, jnp.swapaxes(B, 1, 2))  # (N, m, p)
        Cinvg = psd_solve(Cd, g_x)  # (N, m)
        S = A + mu * jnp.diag(D_t) - jnp.einsum("npm,nmq->pq", B, CinvBt)
        rhs = g_t - jnp.einsum("npm,nm->p", B, Cinvg)
    else:
        S = A + mu * jnp.diag(D_t)
        rhs = g_t
    act = active.astype(S.dtype)
    keep = 1.0 - act
    S = S * keep[:, None] * keep[None, :] + jnp.diag(act)
    h_t = -psd_solve(S, rhs * keep) if S.shape[0] else rhs
    if m:
        h_x = -(Cinvg + jnp.einsum("nmp,p->nm", CinvBt, h_t))
    else:
        h_x = jnp.zeros_like(g_x)
    return Params(h_t, h_x)


def _diag_t(blocks):
    """diag(J_t^T J_t): of A, or the matrix-free solve's D_t."""
    return blocks.D_t if isinstance(blocks, MatrixFreeBlocks) else jnp.diag(blocks.A)


def pcg(matvec, b, precond, rtol, max_steps):
    """Preconditioned conjugate gradients for S x = b, S symmetric positive semi-definite
    (Nocedal and Wright, Alg. 5.3), from x = 0, with the diagonal preconditioner
    `precond` (~ diag(S)^{-1}). Stops at ||b - S x|| <= rtol ||b||, after `max_steps`
    iterations, or on a direction without curvature (S p = 0: the rest of b lies in the
    null space, which gets no step, like the dense pseudo-inverse). Returns x and the
    number of iterations."""
    tol = rtol * jnp.sqrt(jnp.sum(b * b))
    z = precond * b
    init = (jnp.zeros_like(b), b, z, jnp.sum(b * z), jnp.array(0), jnp.array(False))

    def cond(c):
        x, r, p, rz, k, stop = c
        return (k < max_steps) & ~stop & (jnp.sqrt(jnp.sum(r * r)) > tol)

    def body(c):
        x, r, p, rz, k, _ = c
        Sp = matvec(p)
        pSp = jnp.sum(p * Sp)
        stop = ~(pSp > 0)
        alpha = jnp.where(stop, 0.0, rz / jnp.where(stop, 1.0, pSp))
        x = x + alpha * p
        r = r - alpha * Sp
        z = precond * r
        rz_new = jnp.sum(r * z)
        beta = jnp.where(stop, 0.0, rz_new / jnp.where(rz > 0, rz, 1.0))
        return x, r, z + beta * p, rz_new, k + 1, stop

    x, _, _, _, k, _ = jax.lax.while_loop(cond, body, init)
    return x, k


def _scaled_norm(blocks, p: Params):
    """||D p|| with D = sqrt(diag(J^T J)) (floored), which does not depend on units."""
    d_t = jnp.sqrt(floor(_diag_t(blocks)))
    d_x = jnp.sqrt(jax.vmap(lambda c: floor(jnp.diag(c)))(blocks.Cb)) if p.x0.size else p.x0
    return jnp.sqrt(jnp.sum((d_t * p.theta) ** 2) + jnp.sum((d_x * p.x0) ** 2))


class AbstractLeastSquares(AbstractSolver):
    """The structured least-squares loop; subclasses supply `_search` and `_mu0`."""

    rtol: eqx.AbstractVar[float]
    atol: eqx.AbstractVar[float]
    gtol: eqx.AbstractVar[float]
    max_steps: eqx.AbstractVar[int]
    strategy: eqx.AbstractVar[str]
    linear_solver: eqx.AbstractVar[str]
    cg_rtol: eqx.AbstractVar[float]
    cg_max_steps: eqx.AbstractVar[int]

    def _check(self):
        check_options(
            self,
            non_negative=("rtol", "atol", "gtol", "cg_rtol"),
            integers=("max_steps", "cg_max_steps"),
        )
        as_strategy(self.strategy, f"`{type(self).__name__}(strategy=...)`")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(
                f"`{type(self).__name__}(linear_solver=...)` must be one of {LINEAR_SOLVERS}, "
                f"got {self.linear_solver!r}."
            )
        if isinstance(as_strategy(self.strategy), ParallelInTime) and self.linear_solver == "cg":
            raise ValueError(
                f"`{type(self).__name__}(linear_solver='cg')` runs its Jacobian-vector "
                "products by sequential recursions and does not combine with "
                "strategy='parallel': take linear_solver='dense' (or 'auto') there."
            )

    def _matrix_free(self, params):
        # The parallel-in-time path forms the Jacobian (its sensitivities are associative
        # scans); the matrix-free products are sequential.
        if isinstance(as_strategy(self.strategy), ParallelInTime):
            return False
        return least_squares_solver(self.linear_solver, params.theta.shape[0]) == "cg"

    def _mu0(self, dtype):
        raise NotImplementedError

    def _search(self, problem, params, blocks, step, full, pred, mu, nu) -> Trial:
        """Globalise the step `step`; `full` = (point, loss) of the full projected step."""
        raise NotImplementedError

    def _linearise(self, problem, params):
        if self._matrix_free(params):
            return self._linearise_matrix_free(problem, params)
        lin = problem.jacobian(params, self.strategy)
        return Blocks(jnp.sum(lin.r**2), *normal_blocks(lin.Jt, lin.Jx, lin.r)), lin.h_min

    def _linearise_matrix_free(self, problem, params):
        """`MatrixFreeBlocks` at params: residuals, the x0 columns, the blocks that involve
        them, J^T r and Marquardt's diagonal (see the module docstring)."""
        strategy = self.strategy
        r, h_min, traj = problem.linearise(params, strategy)
        p, (N, m) = params.theta.shape[0], params.x0.shape
        dtype = problem.dtype
        zeros_t = jnp.zeros((p,), dtype)
        zeros_x = jnp.zeros((N, m), dtype)
        # Each trajectory's x0 columns: direction e_j in every trajectory's x0 at once.
        E_x = jnp.eye(m, dtype=dtype)
        Jx = jax.vmap(
            lambda e: problem.jvp(params, traj, zeros_t, jnp.broadcast_to(e, (N, m)), strategy)
        )(E_x)  # (m, N, R)
        Jx = jnp.moveaxis(Jx, 0, -1)
        gt_n, g_x = problem.vjp(params, traj, r, strategy)
        B = jax.vmap(lambda w: problem.vjp(params, traj, w, strategy)[0], in_axes=-1)(Jx)
        B = jnp.moveaxis(B, 0, -1)  # (N, p, m)
        Cb = jnp.einsum("nrm,nrl->nml", Jx, Jx)
        if p <= DIAG_PROBES:
            cols = jax.vmap(lambda e: problem.jvp(params, traj, e, zeros_x, strategy))(
                jnp.eye(p, dtype=dtype)
            )
            D_t = jnp.sum(cols**2, axis=(1, 2))
        else:
            signs = jax.random.rademacher(
                jax.random.PRNGKey(0), (DIAG_PROBES, *r.shape), dtype=dtype
            )
            W = jax.vmap(lambda w: jnp.sum(problem.vjp(params, traj, w, strategy)[0], 0))(signs)
            D_t = jnp.mean(W**2, axis=0)
        blocks = MatrixFreeBlocks(jnp.sum(r**2), D_t, B, Cb, jnp.sum(gt_n, axis=0), g_x, Jx, traj)
        return blocks, h_min

    def _solve(self, problem, params, b, mu, active):
        """The damped Gauss-Newton step: dense (`structured_step`) or matrix-free."""
        if not isinstance(b, MatrixFreeBlocks):
            return structured_step(b.A, b.B, b.Cb, b.g_t, b.g_x, mu, active)
        m = b.Cb.shape[-1]
        D_t = floor(b.D_t)
        if m:
            D_x = jax.vmap(lambda c: floor(jnp.diag(c)))(b.Cb)
            Cd = b.Cb + mu * jax.vmap(jnp.diag)(D_x)
            CinvBt = psd_solve(Cd, jnp.swapaxes(b.B, 1, 2))  # (N, m, p)
            Cinvg = psd_solve(Cd, b.g_x)  # (N, m)
            rhs = b.g_t - jnp.einsum("npm,nm->p", b.B, Cinvg)
        else:
            rhs = b.g_t
        keep = 1.0 - active.astype(D_t.dtype)
        zeros_x = jnp.zeros(params.x0.shape, params.x0.dtype)

        def S(v):
            v = v * keep
            Jv = problem.jvp(params, b.traj, v, zeros_x, self.strategy)
            Sv = jnp.sum(problem.vjp(params, b.traj, Jv, self.strategy)[0], axis=0) + mu * D_t * v
            if m:
                Sv = Sv - jnp.einsum("npm,nmq,q->p", b.B, CinvBt, v)
            return Sv * keep + (1.0 - keep) * v

        # Jacobi. With the exact D_t, diag(S) itself, so that on a singular S the solve picks
        # the same minimum-norm step in the Jacobi-scaled metric as the dense pseudo-inverse;
        # with an estimated D_t, (1 + mu) D_t, which stays positive (the estimate of
        # diag(S) = diag(A) + mu D_t - diag(B C^-1 B^T) need not).
        diag_S = (1.0 + mu) * D_t
        if m and b.D_t.shape[0] <= DIAG_PROBES:
            diag_S = diag_S - jnp.einsum("npm,nmp->p", b.B, CinvBt)
        precond = keep / floor(diag_S) + (1.0 - keep)
        h_t, _ = pcg(S, rhs * keep, precond, self.cg_rtol, self.cg_max_steps)
        h_t = -h_t
        if m:
            h_x = -(Cinvg + jnp.einsum("nmp,p->nm", CinvBt, h_t))
        else:
            h_x = jnp.zeros_like(b.g_x)
        return Params(h_t, h_x)

    def _model_curvature(self, problem, params, b, st, sx):
        """||J s||^2 for a step s = (st, sx): from the blocks, or one J v product."""
        if not isinstance(b, MatrixFreeBlocks):
            return (
                st @ b.A @ st
                + 2.0 * jnp.einsum("p,npm,nm->", st, b.B, sx)
                + jnp.einsum("nm,nml,nl->", sx, b.Cb, sx)
            )
        zeros_x = jnp.zeros(sx.shape, sx.dtype)
        Js = problem.jvp(params, b.traj, st, zeros_x, self.strategy)
        Js = Js + jnp.einsum("nrm,nm->nr", b.Jx, sx)
        return jnp.sum(Js**2)

    def _active(self, problem, p_theta, g_t):
        if problem.lower is None:
            return jnp.zeros(p_theta.shape, bool)
        return ((p_theta <= problem.lower) & (g_t > 0)) | ((p_theta >= problem.upper) & (g_t < 0))

    def _first_order(self, problem, params, b):
        """The first-order measure at the linearisation point of `b` (`_optimality`)."""
        d_x = jax.vmap(jnp.diag)(b.Cb) if params.x0.size else params.x0
        return first_order(problem, params, b.C, Params(b.g_t, b.g_x), _diag_t(b), d_x)

    def _fallback(self, clipped, pred):
        """Whether a rejected step is followed by a projected-gradient step."""
        raise NotImplementedError

    def init(self, problem, params):
        blocks, h_min = self._linearise(problem, params)
        dtype = problem.dtype
        fo = self._first_order(problem, params, blocks)
        nan = jnp.array(jnp.nan, dtype)
        negative = h_min < 0
        stationary = fo <= self.gtol
        return LSQState(
            blocks,
            blocks.C,
            h_min,
            self._mu0(dtype),
            jnp.array(2.0, dtype),
            data_scale(problem),
            Measures(fo, nan, nan),
            negative | stationary,
            RESULTS.where(negative, RESULTS.negative_penalty, RESULTS.converged),
        )

    def trial(self, problem, params, step, alpha):
        """The projected point params + alpha step and its loss (inf where not finite)."""
        new = Params(
            problem.feasible(params.theta + alpha * step.theta), params.x0 + alpha * step.x0
        )
        return new, self._loss(problem, new)

    def _loss(self, problem, params):
        r, _ = problem.residuals(params, strategy=self.strategy)
        C = jnp.sum(r**2)
        return jnp.where(jnp.isfinite(C), C, jnp.inf)

    def _gradient_arc(self, problem, params, b):
        """A projected scaled-gradient step with an Armijo search along the projection arc
        theta(t) = P(theta - t D^-2 g) (Bertsekas, "Nonlinear programming", 1999, Sec.
        2.3; the fallback of Kanzow, Yamashita and Fukushima 2004), from the Cauchy step
        length t0 = (g^T D^-2 g) / ||J D^-2 g||^2 of the linear model, halving t until
        C(t) <= C + 2 sigma g^T (theta(t) - theta), sigma = 1e-4. D is Marquardt's
        diagonal (a box commutes with it); a general projection takes the common step
        min_i D_ii^-2. It decreases C whenever theta is not stationary, so that a step
        clipped at a bound never ends the fit at a non-stationary point. Returns (point,
        loss, whether it decreased C)."""
        C = b.C
        inv_t = 1.0 / floor(_diag_t(b))
        if problem.project is not None:
            inv_t = jnp.full_like(inv_t, jnp.min(inv_t))
        inv_x = 1.0 / jax.vmap(lambda c: floor(jnp.diag(c)))(b.Cb) if params.x0.size else b.g_x
        dt, dx = -inv_t * b.g_t, -inv_x * b.g_x
        slope = -(b.g_t @ dt + jnp.sum(b.g_x * dx))
        curv = self._model_curvature(problem, params, b, dt, dx)
        t0 = jnp.where(curv > 0, slope / jnp.where(curv > 0, curv, 1.0), 1.0)
        t0 = jnp.where(jnp.isfinite(t0) & (t0 > 0), t0, 1.0)

        def point(t):
            new = Params(problem.feasible(params.theta + t * dt), params.x0 + t * dx)
            return new, self._loss(problem, new)

        def armijo(new, Cn):
            lin = b.g_t @ (new.theta - params.theta) + jnp.sum(b.g_x * (new.x0 - params.x0))
            return (Cn < C) & (Cn <= C + 2e-4 * lin)

        def cond(c):
            return ~c[3] & (c[4] < 40)

        def body(c):
            t = c[0] * jnp.where(c[4] > 0, 0.5, 1.0)
            new, Cn = point(t)
            return t, new, Cn, armijo(new, Cn), c[4] + 1

        init = (t0, params, C, jnp.array(False), jnp.array(0))
        _, new, Cn, ok, _ = jax.lax.while_loop(cond, body, init)
        return new, Cn, ok

    def step(self, problem, params, state):
        b = state.blocks
        dtype = problem.dtype
        eps = jnp.finfo(dtype).eps
        act = self._active(problem, params.theta, b.g_t)
        h = self._solve(problem, params, b, state.mu, act)
        full = self.trial(problem, params, h, 1.0)
        if problem.lower is not None or problem.project is not None:
            # Entries that the projection leaves where they are although the step moves
            # them (at a bound, pushed outwards by the coupling with the other entries,
            # or held by a general projection): hold them too and solve again, so that
            # the other entries take the step of the reduced problem.
            blocked = (full[0].theta == params.theta) & (h.theta != 0) & ~act

            def again():
                h2 = self._solve(problem, params, b, state.mu, act | blocked)
                return h2, self.trial(problem, params, h2, 1.0)

            h, full = lazy_cond(jnp.any(blocked), again, (h, full))
        # The decrease of C the linear model predicts for the full projected step:
        # -(2 s^T J^T r + ||J s||^2).
        st, sx = full[0].theta - params.theta, full[0].x0 - params.x0
        Js2 = self._model_curvature(problem, params, b, st, sx)
        pred = -(2.0 * (st @ b.g_t + jnp.sum(sx * b.g_x)) + Js2)
        t = self._search(problem, params, b, h, full, pred, state.mu, state.nu)
        # A step that the projection clipped (or whose model predicts no decrease) and
        # that failed: a projected-gradient step instead, which decreases C unless
        # theta is stationary.
        clipped = jnp.any(st != h.theta)
        need = ~t.accept & self._fallback(clipped, pred)
        arc = lazy_cond(
            need, lambda: self._gradient_arc(problem, params, b), (params, b.C, jnp.array(False))
        )
        take = t.accept | arc[2]
        new = jax.tree_util.tree_map(lambda a, c: jnp.where(t.accept, a, c), t.params, arc[0])
        new_loss = jnp.where(t.accept, t.loss, arc[1])
        old = params
        params = jax.tree_util.tree_map(lambda a, c: jnp.where(take, a, c), new, params)
        loss = jnp.where(take, new_loss, state.loss)
        blocks, h_min = lazy_cond(take, lambda: self._linearise(problem, params), (b, state.h_min))
        fo = self._first_order(problem, params, blocks)

        s = Params(params.theta - old.theta, params.x0 - old.x0)
        size_d = _scaled_norm(b, old)
        step_d = _scaled_norm(b, s)
        small_step = take & (step_d <= self.rtol * size_d + self.atol)
        small_step = small_step & (state.loss - loss <= self.rtol * state.loss + self.atol)
        # Nothing left to gain at this precision: nothing decreased C and the predicted
        # decrease is at round-off (MINPACK's ftol test at machine epsilon), or the step
        # is at the round-off level of the parameters (matters in float32).
        size = jnp.sqrt(jnp.sum(old.theta**2) + jnp.sum(old.x0**2))
        hsize = jnp.sqrt(jnp.sum(h.theta**2) + jnp.sum(h.x0**2))
        round_off = ~take & (
            (pred <= 8 * eps * state.loss)
            | (hsize <= 10 * jnp.sqrt(eps) * jnp.maximum(size, jnp.finfo(dtype).tiny))
        )
        gave_up = t.gave_up & ~take
        stalled = small_step | round_off | gave_up
        # At round-off, stationary to the precision of the loss (`_optimality`).
        stationary = (fo <= self.gtol) | (round_off & (fo <= roundoff_limit(dtype)))
        negative = h_min < 0
        done = stationary | stalled | negative
        result = RESULTS.where(
            stationary,
            RESULTS.converged,
            RESULTS.where(
                zero_residual(loss, state.scale),
                RESULTS.zero_residual,
                RESULTS.where(gave_up, RESULTS.no_progress, RESULTS.stalled),
            ),
        )
        result = RESULTS.where(negative, RESULTS.negative_penalty, result)
        tiny = jnp.finfo(dtype).tiny
        measures = Measures(
            fo,
            step_d / jnp.maximum(size_d, tiny),
            jnp.where(take, pred, jnp.maximum(pred, 0.0)) / jnp.maximum(state.loss, tiny),
        )
        state = LSQState(blocks, loss, h_min, t.mu, t.nu, state.scale, measures, done, result)
        return params, state

    def terminate(self, problem, params, state):
        del problem, params
        return state.done, state.result

    def summary(self, state):
        b = state.blocks
        return state.loss, 2.0 * jnp.sqrt(jnp.sum(b.g_t**2) + jnp.sum(b.g_x**2))

    def measures(self, state):
        return state.measures

    def postprocess(self, problem, params, state, result):
        b = state.blocks
        # With a negative lambda h the sum of squares is not C: report C itself (without
        # a penalty h_min is +inf and the stop never happens: nothing to trace).
        if problem.cost.penalty is None:
            loss = state.loss
        else:
            loss = jax.lax.cond(
                result == RESULTS.negative_penalty,
                lambda: problem.loss(params, self.strategy),
                lambda: state.loss,
            )
        dense = isinstance(b, Blocks) and problem.cost.penalty is None
        blocks = (state.loss, b.A, b.B, b.Cb) if dense else None
        return params, loss, blocks
