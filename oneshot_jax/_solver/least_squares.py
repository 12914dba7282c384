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

Box bounds are exact: each iterate is projected (clipped), and entries at a bound whose
gradient points outwards are held for the step (an active set), so a bound that is active
at the optimum neither stalls the other parameters nor is left.

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

Stopping: an accepted step converges when its scaled size ||D s|| (D = Marquardt's
sqrt(diag(J^T J)), which makes the test invariant to the parameters' units) is at most
rtol ||D p|| + atol AND the loss decreased by at most rtol C + atol; or when the decrease
the linear model predicts is at the round-off level of C. A penalty enters as residuals
sqrt(lambda h / T): lambda h must be non-negative, and the solver stops with
`RESULTS.negative_penalty` (reporting the true loss) when it is not.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._linalg import floor, normal_blocks, psd_solve
from .._problem import Params
from .._results import RESULTS
from .._sensitivity import Trajectory
from .._strategy import LINEAR_SOLVERS, STRATEGIES, least_squares_solver
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
    blocks: Blocks | MatrixFreeBlocks  # the last linearisation
    loss: jax.Array  # C at the current iterate (that of `blocks` but after a final step)
    h_min: jax.Array  # the smallest lambda h(x_k) at the last linearisation
    mu: jax.Array  # damping (0 for Gauss-Newton)
    nu: jax.Array  # Nielsen's damping growth
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
    max_steps: eqx.AbstractVar[int]
    strategy: eqx.AbstractVar[str]
    linear_solver: eqx.AbstractVar[str]
    cg_rtol: eqx.AbstractVar[float]
    cg_max_steps: eqx.AbstractVar[int]

    def _check(self):
        check_options(
            self, non_negative=("rtol", "atol", "cg_rtol"), integers=("max_steps", "cg_max_steps")
        )
        if self.strategy not in STRATEGIES:
            raise ValueError(
                f"`{type(self).__name__}(strategy=...)` must be one of {STRATEGIES}, "
                f"got {self.strategy!r}."
            )
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(
                f"`{type(self).__name__}(linear_solver=...)` must be one of {LINEAR_SOLVERS}, "
                f"got {self.linear_solver!r}."
            )
        if self.strategy == "parallel" and self.linear_solver == "cg":
            raise ValueError(
                f"`{type(self).__name__}(linear_solver='cg')` runs its Jacobian-vector "
                "products by sequential recursions and does not combine with "
                "strategy='parallel': take linear_solver='dense' (or 'auto') there."
            )

    def _matrix_free(self, params):
        # The parallel-in-time path forms the Jacobian (its sensitivities are associative
        # scans); the matrix-free products are sequential.
        if self.strategy == "parallel":
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

    def init(self, problem, params):
        blocks, h_min = self._linearise(problem, params)
        dtype = problem.dtype
        negative = h_min < 0
        return LSQState(
            blocks,
            blocks.C,
            h_min,
            self._mu0(dtype),
            jnp.array(2.0, dtype),
            negative,
            RESULTS.where(negative, RESULTS.negative_penalty, RESULTS.converged),
        )

    def trial(self, problem, params, step, alpha):
        """The projected point params + alpha step and its loss (inf where not finite)."""
        new = Params(
            problem.feasible(params.theta + alpha * step.theta), params.x0 + alpha * step.x0
        )
        r, _ = problem.residuals(new, strategy=self.strategy)
        C = jnp.sum(r**2)
        return new, jnp.where(jnp.isfinite(C), C, jnp.inf)

    def step(self, problem, params, state):
        b = state.blocks
        dtype = problem.dtype
        eps = jnp.finfo(dtype).eps
        act = self._active(problem, params.theta, b.g_t)
        h = self._solve(problem, params, b, state.mu, act)
        # The decrease of C the linear model predicts for the full projected step:
        # -(2 s^T J^T r + ||J s||^2).
        full = self.trial(problem, params, h, 1.0)
        st, sx = full[0].theta - params.theta, full[0].x0 - params.x0
        Js2 = self._model_curvature(problem, params, b, st, sx)
        pred = -(2.0 * (st @ b.g_t + jnp.sum(sx * b.g_x)) + Js2)
        t = self._search(problem, params, b, h, full, pred, state.mu, state.nu)

        s = Params(t.params.theta - params.theta, t.params.x0 - params.x0)
        small_step = _scaled_norm(b, s) <= self.rtol * _scaled_norm(b, params) + self.atol
        small_decrease = state.loss - t.loss <= self.rtol * state.loss + self.atol
        converged = t.accept & small_step & small_decrease
        # Nothing left to gain at this precision: the predicted decrease is at round-off
        # (MINPACK's ftol test at machine epsilon), or a full step at the round-off level
        # of the parameters cannot decrease C (matters in float32).
        size = jnp.sqrt(jnp.sum(params.theta**2) + jnp.sum(params.x0**2))
        hsize = jnp.sqrt(jnp.sum(h.theta**2) + jnp.sum(h.x0**2))
        at_precision = (pred <= 8 * eps * state.loss) | (
            ~t.accept & (hsize <= 10 * jnp.sqrt(eps) * jnp.maximum(size, 1e-300))
        )
        converged = converged | at_precision
        gave_up = t.gave_up & ~converged
        take = t.accept
        params = jax.tree_util.tree_map(lambda a, c: jnp.where(take, a, c), t.params, params)
        loss = jnp.where(take, t.loss, state.loss)
        # A converged step is taken without linearising again at its end point: that point
        # is within rtol (scaled) of the last linearisation, which the covariance uses.
        relinearise = take & ~converged
        blocks, h_min = jax.lax.cond(
            relinearise,
            lambda: self._linearise(problem, params),
            lambda: (b, state.h_min),
        )
        negative = h_min < 0
        done = converged | gave_up | negative
        result = RESULTS.where(
            negative,
            RESULTS.negative_penalty,
            RESULTS.where(gave_up, RESULTS.no_progress, RESULTS.converged),
        )
        return params, LSQState(blocks, loss, h_min, t.mu, t.nu, done, result)

    def terminate(self, problem, params, state):
        del problem, params
        return state.done, state.result

    def summary(self, state):
        b = state.blocks
        return state.loss, 2.0 * jnp.sqrt(jnp.sum(b.g_t**2) + jnp.sum(b.g_x**2))

    def postprocess(self, problem, params, state, result):
        b = state.blocks
        # With a negative lambda h the sum of squares is not C: report C itself.
        loss = jax.lax.cond(
            result == RESULTS.negative_penalty,
            lambda: problem.loss(params, self.strategy),
            lambda: state.loss,
        )
        dense = isinstance(b, Blocks) and problem.cost.penalty is None
        blocks = (state.loss, b.A, b.B, b.Cb) if dense else None
        return params, loss, blocks
