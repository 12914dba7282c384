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
from .._strategy import STRATEGIES
from .base import AbstractSolver, check_options


class Blocks(NamedTuple):
    """C and the blocks of J^T J, J^T r at the current iterate (see `normal_blocks`)."""

    C: jax.Array
    A: jax.Array
    B: jax.Array
    Cb: jax.Array
    g_t: jax.Array
    g_x: jax.Array


class LSQState(NamedTuple):
    blocks: Blocks  # the last linearisation
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


def _scaled_norm(blocks: Blocks, p: Params):
    """||D p|| with D = sqrt(diag(J^T J)) (floored), which does not depend on units."""
    d_t = jnp.sqrt(floor(jnp.diag(blocks.A)))
    d_x = jnp.sqrt(jax.vmap(lambda c: floor(jnp.diag(c)))(blocks.Cb)) if p.x0.size else p.x0
    return jnp.sqrt(jnp.sum((d_t * p.theta) ** 2) + jnp.sum((d_x * p.x0) ** 2))


class AbstractLeastSquares(AbstractSolver):
    """The structured least-squares loop; subclasses supply `_search` and `_mu0`."""

    rtol: eqx.AbstractVar[float]
    atol: eqx.AbstractVar[float]
    max_steps: eqx.AbstractVar[int]
    strategy: eqx.AbstractVar[str]

    def _check(self):
        check_options(self, non_negative=("rtol", "atol"), integers=("max_steps",))
        if self.strategy not in STRATEGIES:
            raise ValueError(
                f"`{type(self).__name__}(strategy=...)` must be one of {STRATEGIES}, "
                f"got {self.strategy!r}."
            )

    def _mu0(self, dtype):
        raise NotImplementedError

    def _search(self, problem, params, blocks, step, full, pred, mu, nu) -> Trial:
        """Globalise the step `step`; `full` = (point, loss) of the full projected step."""
        raise NotImplementedError

    def _linearise(self, problem, params):
        lin = problem.jacobian(params, self.strategy)
        return Blocks(jnp.sum(lin.r**2), *normal_blocks(lin.Jt, lin.Jx, lin.r)), lin.h_min

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
        h = structured_step(b.A, b.B, b.Cb, b.g_t, b.g_x, state.mu, act)
        # The decrease of C the linear model predicts for the full projected step:
        # -(2 s^T J^T r + ||J s||^2), with ||J s||^2 from the blocks.
        full = self.trial(problem, params, h, 1.0)
        st, sx = full[0].theta - params.theta, full[0].x0 - params.x0
        Js2 = (
            st @ b.A @ st
            + 2.0 * jnp.einsum("p,npm,nm->", st, b.B, sx)
            + jnp.einsum("nm,nml,nl->", sx, b.Cb, sx)
        )
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
        blocks = None if problem.cost.penalty is not None else (state.loss, b.A, b.B, b.Cb)
        return params, loss, blocks
