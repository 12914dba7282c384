"""The linearisation of the residuals at an iterate, and the damped Gauss-Newton step it
gives: the descent of `GaussNewton` and `LevenbergMarquardt` (`least_squares`).

J is the closed-form residual Jacobian (forward sensitivities, the forward twin of eq.
(17) and (20)). Theta's columns are shared by all trajectories (windows) and each
trajectory's x0 columns touch only its own residuals, so J^T J is an arrow matrix
[[A, B_1 .. B_N], [B_i^T, C_i]] whose x0 blocks are eliminated by a Schur complement
(`oneshot_jax._linalg.eliminate_x0`); the cost is linear in the number of trajectories.

Two kinds, one interface (`AbstractLinearisation`):

- `DenseLinearisation`: the Jacobian formed (one forward-sensitivity column per free
  parameter) and reduced to the blocks of J^T J and J^T r (`_linalg.normal_blocks`).
- `MatrixFreeLinearisation` (`linear_solver="cg"`): the theta block is never formed. The
  Schur complement system S h_theta = -(g_t - sum_i B_i C_i^{-1} g_i) is solved by
  preconditioned conjugate gradients (`pcg`), with S v = J_t^T (J_t v) + mu D_t v
  - sum_i B_i (C_i + mu D_i)^{-1} B_i^T v. J_t v is one forward sensitivity along v and
  J_t^T w the one-shot reverse recursion with output cotangents w
  (`_sensitivity.residual_jvp` / `residual_vjp`); the per-step Jacobians J^{x/x}_k are
  formed once per linearisation, so a product costs two vmapped model JVPs/VJPs and two
  small scans, whatever n_theta. The x0 blocks stay exact: each trajectory's m x0
  columns are formed (`_optimality.x0_columns`) and B_i = J_t^T J_{x,i} takes m reverse
  products. Marquardt's D_t = diag(J_t^T J_t) is exact (p forward sensitivities) while
  p <= `DIAG_PROBES`, and otherwise estimated from `DIAG_PROBES` Rademacher probes
  (`_optimality.rademacher_diagonal`). CG is preconditioned by diag(S) (Jacobi) formed
  from the exact D_t and the x0 blocks, or by (1 + mu) D_t with the estimate. CG stops at
  a relative residual `cg_rtol` or after `cg_max_steps` iterations: a truncated step is
  still a descent direction, and the step's decrease is measured with J s itself, so the
  globalisation is unchanged (an inexact Gauss-Newton / LM method).

Each provides the step for a damping mu and an active set (`step`), ||J s||^2 for the
predicted decrease (`curvature`), Marquardt's diagonal diag(J^T J) (`diag_t`, `diag_x`:
the column norms of the scaling and of `_optimality.first_order`) and the blocks of
J^T J for the covariance (`covariance_blocks`).
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from .._linalg import (
    eigh_solve,
    eliminate_x0,
    floor,
    normal_blocks,
    numerical_rank,
    psd_solve,
    scaled_eigh,
    schur_complement,
)
from .._optimality import first_order, rademacher_diagonal, stall_test, x0_columns
from .._problem import Params
from .._sensitivity import Trajectory

# Rademacher probes for Marquardt's diagonal in the matrix-free solve (exact when the
# number of free theta entries is at most this).
DIAG_PROBES = 16


class AbstractLinearisation(eqx.Module):
    """C = ||r||^2 and the blocks of J^T J, J^T r at an iterate (the x0 parts formed).

    **Fields:** `C`; `B` (N, p, m) = J_t,i^T J_x,i; `Cb` (N, m, m) = J_x,i^T J_x,i;
    `g_t` (p,) = J_t^T r; `g_x` (N, m) = J_x,i^T r_i.
    """

    C: eqx.AbstractVar[jax.Array]
    B: eqx.AbstractVar[jax.Array]
    Cb: eqx.AbstractVar[jax.Array]
    g_t: eqx.AbstractVar[jax.Array]
    g_x: eqx.AbstractVar[jax.Array]

    @abc.abstractmethod
    def diag_t(self) -> jax.Array:
        """diag(J_t^T J_t) (p,): Marquardt's diagonal of the theta columns."""

    @abc.abstractmethod
    def step(self, problem, params: Params, mu, active) -> Params:
        """The damped Gauss-Newton step h: (J^T J + mu D) h = -J^T r, D = diag(J^T J)
        floored (`_linalg.floor`; it makes the step invariant to parameter scaling), with
        the entries of theta in `active` (at a bound, pushed outwards) held at zero step.
        Pseudo-inverses: a direction without effect gets a zero step.

        **Arguments:** `problem` and `params` (the linearisation point), `mu` the
        damping (0 for Gauss-Newton), `active` (p,) bool.

        **Returns:** h as `Params`.
        """

    @abc.abstractmethod
    def curvature(self, problem, params: Params, st, sx) -> jax.Array:
        """||J s||^2 for a step s = (st, sx): the quadratic term of the linear model's
        decrease -(2 s^T J^T r + ||J s||^2)."""

    @abc.abstractmethod
    def gram_t(self, problem, params: Params, d) -> Params:
        """J^T J_t d for a move d (p,) of theta: (J_t^T J_t d, B_i^T d), the change of
        the gradient (g_t, g_x) that the move makes in the linear model."""

    def shifted(self, problem, params: Params, d):
        """This linearisation with its residuals moved to r + J_t d (the gradient
        J^T (r + J_t d)): its `step` with d's entries held is the step of the other
        entries after theta moves by d (a box's clip, `LeastSquares._descent`)."""
        g = self.gram_t(problem, params, d)
        return eqx.tree_at(lambda s: (s.g_t, s.g_x), self, (self.g_t + g.theta, self.g_x + g.x0))

    def holding_x0(self, held):
        """This linearisation with the x0 entries `held` (N, m) taken out of the step (a
        box on x0: entries at a bound that the gradient pushes outwards): their columns
        of B_i, rows and columns of C_i (its diagonal 1 there) and gradient entries zero,
        so that `step` gives them a zero step and the others the step of the problem
        reduced to them."""
        keep = 1.0 - held.astype(self.Cb.dtype)
        B = self.B * keep[:, None, :]
        Cb = self.Cb * keep[:, :, None] * keep[:, None, :] + jax.vmap(jnp.diag)(1.0 - keep)
        return eqx.tree_at(lambda s: (s.B, s.Cb, s.g_x), self, (B, Cb, self.g_x * keep))

    @abc.abstractmethod
    def covariance_blocks(self, sse):
        """(sse, A, B, C_i) for `_covariance.covariance`, or None where A is not formed."""

    # Whether J^T J is formed (`rank` is available; else the statistical stopping test
    # is off). A class constant: no annotation, so not a field.
    forms_normal_matrix = False

    def rank(self):
        """The numerical ranks of J and of its theta columns once the x0 columns are
        eliminated (`_linalg.numerical_rank`, the covariance's cutoff), or None where
        J^T J is not formed (`forms_normal_matrix` False)."""
        return None

    def diag_x(self) -> jax.Array:
        """diag(J_x,i^T J_x,i) (N, m): Marquardt's diagonal of the x0 columns."""
        return jax.vmap(jnp.diag)(self.Cb)

    def first_order(self, problem, params: Params):
        """The first-order measure at the linearisation point (`_optimality.first_order`)."""
        d_t, d_x = self.diagonals(params)
        return first_order(problem, params, self.C, Params(self.g_t, self.g_x), d_t, d_x)

    def diagonals(self, params: Params):
        """(diag_t, diag_x): Marquardt's diagonal of the theta and of the x0 columns."""
        return self.diag_t(), (self.diag_x() if params.x0.size else params.x0)

    def stall_test(self, problem, params: Params, top_t, top_x, fo):
        """The first-order test of a stall at the linearisation point, with the largest
        diagonals `top_t`, `top_x` of the columns along the fit and the point's measure
        `fo` (`_optimality.stall_test`)."""
        d_t, d_x = self.diagonals(params)
        g = Params(self.g_t, self.g_x)
        return stall_test(problem, params, self.C, g, d_t, d_x, top_t, top_x, fo)

    def scaled_norm(self, p: Params):
        """||D p|| with D = sqrt(diag(J^T J)) (floored), which does not depend on units."""
        d_t = jnp.sqrt(floor(self.diag_t()))
        d_x = jnp.sqrt(jax.vmap(lambda c: floor(jnp.diag(c)))(self.Cb)) if p.x0.size else p.x0
        return jnp.sqrt(jnp.sum((d_t * p.theta) ** 2) + jnp.sum((d_x * p.x0) ** 2))


class DenseLinearisation(AbstractLinearisation):
    """The Jacobian formed: the blocks A = J_t^T J_t, B_i, C_i, g_t, g_i
    (`_linalg.normal_blocks`), and the Schur complement S of the x0 blocks formed from the
    Jacobian (`_linalg.schur_complement`: the rank and the covariance)."""

    C: jax.Array
    A: jax.Array  # (p, p)
    B: jax.Array
    Cb: jax.Array
    g_t: jax.Array
    g_x: jax.Array
    S: jax.Array  # (p, p)

    def diag_t(self):
        return jnp.diag(self.A)

    def step(self, problem, params, mu, active):
        """The damped step by the x0 elimination (`_linalg.eliminate_x0`): the Schur
        complement S = A + mu D_t - sum_i B_i (C_i + mu D_i)^{-1} B_i^T gives h_theta,
        then h_i = -(C_i + mu D_i)^{-1} (g_i + B_i^T h_theta). Cost O(N m^3 + p^3)."""
        del problem, params
        D_t = floor(jnp.diag(self.A))
        elim = eliminate_x0(self.B, self.Cb, self.g_x, mu)
        S = elim.schur(self.A + mu * jnp.diag(D_t), self.B)
        rhs = elim.rhs(self.B, self.g_t)
        act = active.astype(S.dtype)
        keep = 1.0 - act
        S = S * keep[:, None] * keep[None, :] + jnp.diag(act)
        h_t = -psd_solve(S, rhs * keep) if S.shape[0] else rhs
        return Params(h_t, elim.back(h_t))

    def curvature(self, problem, params, st, sx):
        del problem, params
        return (
            st @ self.A @ st
            + 2.0 * jnp.einsum("p,npm,nm->", st, self.B, sx)
            + jnp.einsum("nm,nml,nl->", sx, self.Cb, sx)
        )

    def gram_t(self, problem, params, d):
        del problem, params
        return Params(self.A @ d, jnp.einsum("npm,p->nm", self.B, d))

    def covariance_blocks(self, sse):
        return sse, self.A, self.B, self.Cb, self.S

    forms_normal_matrix = True

    def rank(self):
        """(rank J, rank S): rank J = sum_i rank C_i + rank S, S the Schur complement of
        the x0 blocks (`_linalg.schur_complement`) judged against diag(A), as the
        covariance judges it."""
        p, m = self.A.shape[0], self.Cb.shape[-1]
        rank_x = jnp.sum(numerical_rank(self.Cb)) if m and self.Cb.shape[0] else 0
        rank_t = numerical_rank(self.S, jnp.diag(self.A)) if p else 0
        return jnp.asarray(rank_x + rank_t), jnp.asarray(rank_t)

    def rank_and_decrease(self):
        """(rank J, rank S, g^T (J^T J)^+ g): `rank`, and the decrease of C that the
        undamped Gauss-Newton step (the pseudo-inverse's, without bounds) predicts, from
        the same eigendecomposition of S: sum_i g_i^T C_i^+ g_i + q^T S^+ q with q the
        reduced right-hand side (`_linalg.Elimination.rhs`), S's null eigenvalues
        floored at the cut (`_linalg.eigh_solve(floored=True)`: a direction the data
        determine weakly, below the cut, counts with at least the decrease the cut
        gives it)."""
        p, m = self.A.shape[0], self.Cb.shape[-1]
        rank_x = jnp.sum(numerical_rank(self.Cb)) if m and self.Cb.shape[0] else 0
        elim = eliminate_x0(self.B, self.Cb, self.g_x)
        decrease = jnp.sum(self.g_x * elim.Cinvg) if m else jnp.zeros((), self.C.dtype)
        rank_t = 0
        if p:
            decomposition = scaled_eigh(self.S, jnp.diag(self.A))
            rank_t = jnp.sum(~decomposition.null)
            q = elim.rhs(self.B, self.g_t)
            decrease = decrease + q @ eigh_solve(decomposition, q, floored=True)
        return jnp.asarray(rank_x + rank_t), jnp.asarray(rank_t), decrease


class MatrixFreeLinearisation(AbstractLinearisation):
    """The theta block as its linearisation point (`traj`) and Marquardt's diagonal `D_t`
    instead of A = J_t^T J_t; the x0 columns Jx (N, R, m) are formed."""

    C: jax.Array
    D_t: jax.Array  # (p,) diag(J_t^T J_t), exact or estimated
    B: jax.Array  # (N, p, m)
    Cb: jax.Array  # (N, m, m)
    g_t: jax.Array
    g_x: jax.Array
    Jx: jax.Array  # (N, R, m)
    traj: Trajectory  # batched over the N trajectories
    strategy: str = eqx.field(static=True)
    cg_rtol: float = eqx.field(static=True)
    cg_max_steps: int = eqx.field(static=True)

    def diag_t(self):
        return self.D_t

    def step(self, problem, params, mu, active):
        """The damped step with S h_theta = -rhs solved by `pcg` on Jacobian-vector
        products (see the module docstring), the x0 blocks eliminated exactly
        (`_linalg.eliminate_x0`)."""
        m = self.Cb.shape[-1]
        D_t = floor(self.D_t)
        elim = eliminate_x0(self.B, self.Cb, self.g_x, mu)
        rhs = elim.rhs(self.B, self.g_t)
        keep = 1.0 - active.astype(D_t.dtype)
        zeros_x = jnp.zeros(params.x0.shape, params.x0.dtype)
        strategy = self.strategy

        def S(v):
            v = v * keep
            Jv = problem.jvp(params, self.traj, v, zeros_x, strategy)
            Sv = jnp.sum(problem.vjp(params, self.traj, Jv, strategy)[0], axis=0) + mu * D_t * v
            if m:
                Sv = Sv - elim.schur_correction(self.B, v)
            return Sv * keep + (1.0 - keep) * v

        # Jacobi. With the exact D_t, diag(S) itself, so that on a singular S the solve picks
        # the same minimum-norm step in the Jacobi-scaled metric as the dense pseudo-inverse;
        # with an estimated D_t, (1 + mu) D_t, which stays positive (the estimate of
        # diag(S) = diag(A) + mu D_t - diag(B C^-1 B^T) need not).
        diag_S = (1.0 + mu) * D_t
        if m and self.D_t.shape[0] <= DIAG_PROBES:
            diag_S = diag_S - elim.schur_diagonal(self.B)
        precond = keep / floor(diag_S) + (1.0 - keep)
        h_t, _ = pcg(S, rhs * keep, precond, self.cg_rtol, self.cg_max_steps)
        h_t = -h_t
        return Params(h_t, elim.back(h_t))

    def curvature(self, problem, params, st, sx):
        """One J v product (and the formed x0 columns)."""
        zeros_x = jnp.zeros(sx.shape, sx.dtype)
        Js = problem.jvp(params, self.traj, st, zeros_x, self.strategy)
        Js = Js + jnp.einsum("nrm,nm->nr", self.Jx, sx)
        return jnp.sum(Js**2)

    def gram_t(self, problem, params, d):
        """One J v product and one J^T v product (the x0 part by the formed B)."""
        zeros_x = jnp.zeros(params.x0.shape, params.x0.dtype)
        Jd = problem.jvp(params, self.traj, d, zeros_x, self.strategy)
        JtJd = jnp.sum(problem.vjp(params, self.traj, Jd, self.strategy)[0], axis=0)
        return Params(JtJd, jnp.einsum("npm,p->nm", self.B, d))

    def covariance_blocks(self, sse):
        del sse
        return None


def placeholder(problem, params, strategy, matrix_free, cg_rtol, cg_max_steps):
    """Zeros with the structure of `linearise`'s output at `params` (a solver state's
    slot before its first linearisation). The dense blocks are built from their shapes;
    a matrix-free linearisation (whose trajectory's structure depends on the model) from
    `jax.eval_shape`, which traces `linearise` once more."""
    dtype = problem.dtype
    if not matrix_free:
        p, (N, m) = params.theta.shape[0], params.x0.shape
        zero = jnp.zeros((), dtype)
        blocks = DenseLinearisation(
            zero,
            jnp.zeros((p, p), dtype),
            jnp.zeros((N, p, m), dtype),
            jnp.zeros((N, m, m), dtype),
            jnp.zeros((p,), dtype),
            jnp.zeros((N, m), dtype),
            jnp.zeros((p, p), dtype),
        )
        return blocks, zero
    shapes = jax.eval_shape(
        lambda: linearise(problem, params, strategy, matrix_free, cg_rtol, cg_max_steps)
    )
    return jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)


def linearise(problem, params, strategy, matrix_free, cg_rtol, cg_max_steps):
    """The linearisation at `params` and the smallest lambda h(x_k) there.

    **Arguments:** `problem`, `params`; `strategy` (how the sensitivities are computed,
    `_strategy`); `matrix_free`: a `MatrixFreeLinearisation` (else dense);
    `cg_rtol`, `cg_max_steps`: its conjugate-gradient options.

    **Returns:** (`AbstractLinearisation`, h_min).
    """
    if not matrix_free:
        lin = problem.jacobian(params, strategy)
        C = jnp.sum(lin.r**2)
        blocks = normal_blocks(lin.Jt, lin.Jx, lin.r)
        S = schur_complement(lin.Jt, lin.Jx, blocks[0])
        return DenseLinearisation(C, *blocks, S), lin.h_min
    r, h_min, traj = problem.linearise(params, strategy)
    p, (N, m) = params.theta.shape[0], params.x0.shape
    dtype = problem.dtype
    zeros_x = jnp.zeros((N, m), dtype)
    Jx = jnp.moveaxis(x0_columns(problem, params, traj, strategy), 0, -1)  # (N, R, m)
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
        D_t = rademacher_diagonal(problem, params, traj, r, strategy, DIAG_PROBES)
    lin = MatrixFreeLinearisation(
        jnp.sum(r**2),
        D_t,
        B,
        Cb,
        jnp.sum(gt_n, axis=0),
        g_x,
        Jx,
        traj,
        strategy,
        cg_rtol,
        cg_max_steps,
    )
    return lin, h_min


def pcg(matvec, b, precond, rtol, max_steps):
    """Preconditioned conjugate gradients for S x = b, S symmetric positive semi-definite
    (Hestenes and Stiefel 1952; Nocedal and Wright, "Numerical optimization", Alg. 5.3),
    from x = 0, with the diagonal preconditioner `precond` (~ diag(S)^{-1}).

    Stops at ||b - S x|| <= rtol ||b||, after `max_steps` iterations, or on a direction
    without curvature (S p = 0: the rest of b lies in the null space, which gets no step,
    like the dense pseudo-inverse).

    **Returns:** x and the number of iterations.
    """
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
