"""Any optimistix least-squares solver or minimiser, fed the closed-form derivatives.

The residuals (for a least-squares solver) or the loss C (for a minimiser) are a function
with a custom JVP: the tangent is the closed-form residual Jacobian (forward sensitivities)
or the one-shot gradient applied to it, so optimistix never differentiates the rollout.
The solver's own `init`/`step`/`terminate` run inside `fit`'s compiled loop, so a fit is
one compiled call, multistart runs under vmap, and every step is recorded.

Box constraints: optimistix has no bounds, so the bridge keeps an active set. The model is
only ever simulated at the projected point P(y), and for LM and the minimisers the
derivatives are those of C(P(y)): zero along an entry that the box clips (`_flat`). When
the inner solve stops, every free entry at a bound whose gradient points outwards is held
at the bound (extra residuals y_i - bound_i, zero at the solution, keep the Jacobian's
rank), every held entry whose gradient points into the box is released, and the solver
starts again from there (the solvers that see the unclipped Jacobian, such as
Gauss-Newton and Dogleg, as soon as an entry is to be held), for at most 4 (p + 1)
rounds; where the inner solve stops with an entry beyond a bound (clipped) whose
gradient points into the box, it starts again from the bound. The returned point is
feasible (a diverged fit returns its last finite iterate); whether it satisfies the
optimality conditions on the box is the first-order test's to say (`converged`, or
`stalled` where it does not). A general projection (`constraints.project`) is applied as
P(y) without an active set; for LM and the minimisers the derivatives are those of
C(P(y)) through P's own (forward mode), and where the inner solve stops beyond the set it
starts again from P(y).
"""

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._counts import integral, real
from .._optimality import (
    Measures,
    column_norms,
    data_scale,
    first_order,
    gtol_at_least_resolution,
    lazy_cond,
    stall_limit,
    zero_residual,
)
from .._problem import FitProblem, Params
from .._results import RESULTS
from .._strategy import as_strategy
from .base import AbstractSolver, brief, check_options, grad_norm


class _Held(NamedTuple):
    mask: jax.Array  # (p,) entries of Params.theta held at a bound
    values: jax.Array  # (p,) the bound they are held at


def _point(problem: FitProblem, y, held: _Held) -> Params:
    theta = jnp.where(held.mask, held.values, problem.feasible(y[0]))
    return Params(theta, y[1])


def _flat(problem: FitProblem, y, held: _Held, beyond: bool):
    """Entries of theta whose tangent is zero: those held at a bound, and with `beyond`
    those that the box clips (beyond it, C(P(y)) does not change along them). The
    Jacobian of the unclipped model there sent optimistix's LM after a decrease that the
    clipped function does not have (it crept along an active bound). Only for solvers
    that damp their step (LM, the minimisers): the linear solves of Gauss-Newton and
    Dogleg fail on the zero columns."""
    if problem.lower is None or not beyond:
        return held.mask
    return held.mask | (y[0] < problem.lower) | (y[0] > problem.upper)


def _through_projection(problem: FitProblem, y, d_theta, beyond: bool):
    """The tangent of the model's theta P(y) along `d_theta`: for a general projection
    (`constraints.project`) and a solver that damps its step (`beyond`, as `_flat`), the
    projection's own derivative (forward mode through `FitProblem.feasible`), so that
    the derivatives are those of C(P(y)); `d_theta` itself otherwise (a box's clipped
    entries are `_flat`'s). With the unprojected tangent optimistix's LM went after
    decreases that P undoes, and stalled 2.8 to 3.5 % above the constrained optimum of
    a bound written as a clipping projection, which the same bound as a box reaches."""
    if problem.project is None or not beyond:
        return d_theta
    return jax.jvp(problem.feasible, (y[0],), (d_theta,))[1]


@eqx.filter_custom_jvp
def _residuals(y, *, problem, held, strategy, beyond):
    r, _ = problem.residuals(_point(problem, y, held), strategy=strategy)
    extra = jnp.where(held.mask, y[0] - held.values, 0.0)
    return jnp.concatenate([r.reshape(-1), extra])


@_residuals.def_jvp
def _residuals_jvp(primals, tangents, *, problem, held, strategy, beyond):
    """The closed-form Jacobian (forward sensitivities) applied to the tangent."""
    (y,) = primals
    (dy,) = tangents
    lin = problem.jacobian(_point(problem, y, held), strategy)
    extra = jnp.where(held.mask, y[0] - held.values, 0.0)
    out = jnp.concatenate([lin.r.reshape(-1), extra])
    d_theta, d_x0 = dy
    dr = jnp.zeros(lin.r.shape, lin.r.dtype)
    d_extra = jnp.zeros(extra.shape, extra.dtype)
    if d_theta is not None:
        flat = _flat(problem, y, held, beyond)
        d_model = _through_projection(problem, y, d_theta, beyond)
        dr = dr + jnp.einsum("nrp,p->nr", lin.Jt, jnp.where(flat, 0.0, d_model))
        d_extra = jnp.where(held.mask, d_theta, 0.0)
    if d_x0 is not None:
        dr = dr + jnp.einsum("nrm,nm->nr", lin.Jx, d_x0)
    return out, jnp.concatenate([dr.reshape(-1), d_extra])


@eqx.filter_custom_jvp
def _loss(y, *, problem, held, strategy, beyond):
    C = problem.loss(_point(problem, y, held), strategy)
    return C + jnp.sum(jnp.where(held.mask, y[0] - held.values, 0.0) ** 2)


@_loss.def_jvp
def _loss_jvp(primals, tangents, *, problem, held, strategy, beyond):
    """The one-shot gradient (eq. 17, 20) applied to the tangent."""
    (y,) = primals
    (dy,) = tangents
    C, g = problem.value_and_grad(_point(problem, y, held), strategy)
    extra = jnp.where(held.mask, y[0] - held.values, 0.0)
    d_theta, d_x0 = dy
    dC = jnp.zeros((), C.dtype)
    if d_theta is not None:
        slope = jnp.where(_flat(problem, y, held, beyond), 0.0, g.theta)
        d_model = _through_projection(problem, y, d_theta, beyond)
        dC = dC + jnp.sum(jnp.where(held.mask, 2.0 * extra * d_theta, slope * d_model))
    if d_x0 is not None:
        dC = dC + jnp.sum(g.x0 * d_x0)
    return C + jnp.sum(extra**2), dC


class _Fn(eqx.Module):
    """`fn(y, args) -> (out, aux)` as optimistix's solvers call it."""

    minimise: bool = eqx.field(static=True)
    strategy: str = eqx.field(static=True)
    beyond: bool = eqx.field(static=True)  # zero tangents beyond the box (`_flat`)

    def __call__(self, y, args):
        problem, held = args
        fn = _loss if self.minimise else _residuals
        out = fn(y, problem=problem, held=held, strategy=self.strategy, beyond=self.beyond)
        return out, None


# The failed steps in a row (the linear solve failed), each leaving the iterate where it
# was, after which the first-order measure is formed at every step, and the fit stops as
# a stall where it is within the round-off limit.
STUCK_STEPS = 10


class _OptxState(NamedTuple):
    y: Any  # optimistix's iterate (p_theta, p_x0), possibly outside the box
    inner: Any  # optimistix's solver state
    held: _Held
    loss: jax.Array
    gnorm: jax.Array
    done: jax.Array
    result: RESULTS
    rounds: jax.Array
    first_order: jax.Array  # the first-order measure where the inner solver stopped
    count: jax.Array  # the steps taken (the measure is also formed at the last one)
    own_test: jax.Array  # the optimistix solver's own test stopped the fit
    last: Params  # the last iterate with a finite loss and gradient, and its loss
    last_loss: jax.Array
    limit: jax.Array  # the round-off limit of a stall at the iterate (`_optimality.stall_limit`)
    idle: jax.Array  # the failed steps in a row that left the iterate where it was
    unmoved: jax.Array  # the failed steps in a row that left it there, finite or not


def _differs(a, b):
    """Whether two pytrees of arrays differ in any entry."""
    leaves = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda x, y: jnp.any(x != y), a, b))
    return jnp.any(jnp.stack(leaves)) if leaves else jnp.array(False)


def _finite(tree):
    """Whether every entry of a pytree of arrays is finite."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


class Optimistix(AbstractSolver):
    """Any optimistix least-squares solver (`optx.GaussNewton`, `optx.LevenbergMarquardt`,
    `optx.Dogleg`, ...) or minimiser (`optx.BFGS`, ...), fed the closed-form Jacobian or
    gradient, run inside `fit`'s compiled loop.

    Remember that the multi-step loss can be tiny (1e-8 on the satellite): give the
    optimistix solver scale-aware tolerances, e.g. `optx.LevenbergMarquardt(rtol=1e-12,
    atol=1e-20)`.

    **Arguments:**

    - `solver`: an `optx.AbstractLeastSquaresSolver` or `optx.AbstractMinimiser`.
    - `max_steps`: the maximum number of the solver's steps (all active-set rounds
        together).
    - `gtol`: the first-order test applied where the optimistix solver stops: the fit
        is `converged` only if the scaled projected gradient there is at most `gtol`, or
        at most its round-off limit (see `oneshot_jax._optimality`); otherwise
        `stalled`. A step that optimistix reports as failed (its linear solve: capped
        conjugate gradients, or NaN) and that left the iterate where it was is a stall
        there: with the measure within the round-off limit the fit is `converged`, and
        after `STUCK_STEPS` (10) such steps in a row it stops.
    - `strategy`: how the derivatives are computed (`"auto"`, `"jacobian"`, `"vjp"`,
        `"parallel"`; see `oneshot_jax.value_and_grad`).
    """

    GTOL_AT_LEAST_RESOLUTION = True  # (at its last step and after a failure: no stall)
    TRACED_INTEGERS = ("max_steps",)

    solver: Any
    max_steps: int = eqx.field(default=256, converter=integral)
    gtol: float = eqx.field(default=1e-8, converter=real)
    strategy: str = "auto"

    def __check_init__(self):
        if not isinstance(self.solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
            raise TypeError(
                "`Optimistix(solver=...)` must be an optimistix least-squares solver or "
                f"minimiser (e.g. optx.LevenbergMarquardt(rtol, atol)), got {self.solver!r}."
            )
        check_options(self, integers=("max_steps",), fractions=("gtol",))
        as_strategy(self.strategy, "`Optimistix(strategy=...)`")

    def check_dtype(self, dtype):
        """optimistix's trust-region search (`ClassicalTrustRegion`: `LevenbergMarquardt`,
        `IndirectLevenbergMarquardt`, `Dogleg`) carries float64 scalars into a float32
        solve when `jax_enable_x64` is on, and fails inside lineax or `lax.cond` (optimistix
        0.1.0): refused here, with the ways out."""
        search = getattr(self.solver, "search", None)
        if (
            np.dtype(dtype) == np.float32
            and jax.config.read("jax_enable_x64")
            and isinstance(search, optx.ClassicalTrustRegion)
        ):
            raise ValueError(
                f"`solver`: oneshot_jax.Optimistix({type(self.solver).__name__}) cannot fit "
                "float32 data while jax_enable_x64 is on: optimistix's trust-region search "
                "mixes float64 into the float32 solve and fails inside it. Pass float64 "
                "data, x0 and theta0 (identification wants them), turn jax_enable_x64 off "
                "for a float32 fit, or use oneshot_jax.LevenbergMarquardt, which runs in "
                "float32 either way."
            )

    @property
    def _minimise(self):
        return isinstance(self.solver, optx.AbstractMinimiser)

    @property
    def _damped(self):
        """Whether the solver damps its step, so that it sees C(P(y)) (`_flat`)."""
        return self._minimise or isinstance(self.solver, optx.LevenbergMarquardt)

    def _fn(self):
        return _Fn(self._minimise, self.strategy, self._damped)

    def _inner_init(self, problem, y, held):
        fn = self._fn()
        args = (problem, held)
        f_struct = jax.eval_shape(lambda: fn(y, args)[0])
        return self.solver.init(fn, y, args, {}, f_struct, None, frozenset())

    def _first_order(self, problem, params, loss, g):
        """The first-order measure at `params` (`_optimality.first_order`, from the loss
        and its gradient g = 2 J^T r)."""
        half = Params(0.5 * g.theta, 0.5 * g.x0)
        return first_order(
            problem, params, loss, half, *column_norms(problem, params, self.strategy)
        )

    def init(self, problem, params):
        held = _Held(jnp.zeros(params.theta.shape, bool), params.theta)
        y = (params.theta, params.x0)
        loss, g = problem.value_and_grad(params, self.strategy)
        # The start is tested as `step` tests a point (as the other solvers test theirs):
        # a fit resumed at an optimum stops at step 0 with `converged`.
        fo = self._first_order(problem, params, loss, g)
        gtol = gtol_at_least_resolution(self.gtol, problem.dtype)
        done = (fo <= gtol) & jnp.isfinite(loss) & jnp.isfinite(grad_norm(g))
        done, result = self._negative_penalty(problem, params, done, RESULTS.converged)
        return _OptxState(
            y,
            self._inner_init(problem, y, held),
            held,
            loss,
            grad_norm(g),
            done,
            result,
            jnp.array(0),
            fo,
            jnp.array(0),
            jnp.array(False),
            params,
            loss,
            stall_limit(problem, loss),
            jnp.array(0),
            jnp.array(0),
        )

    def _negative_penalty(self, problem, params, done, result):
        """A least-squares solver's residuals hold sqrt(lambda h) (clipped at 0): where
        lambda h < 0 at `params` they no longer sum to C, and the fit stops there with
        `negative_penalty`, as the library's least-squares solvers do (a minimiser sees
        C itself: no test)."""
        if problem.cost.penalty is None or self._minimise:
            return done, result
        _, h_min = problem.residuals(params, strategy=self.strategy)
        negative = h_min < 0
        return done | negative, RESULTS.where(negative, RESULTS.negative_penalty, result)

    def step(self, problem, params, state):
        del params
        fn = self._fn()
        args = (problem, state.held)
        y, inner, _ = self.solver.step(fn, state.y, args, {}, state.inner, frozenset())
        inner_done, inner_result = self.solver.terminate(fn, y, args, {}, inner, frozenset())
        # A failed step (a linear solve that returned NaN, or that reached its own
        # max_steps) ends optimistix's own loop. Here the fit goes on where the step's
        # proposal is finite (an inexact solve: conjugate gradients capped at a few
        # iterations make an inexact Gauss-Newton method, whose rejected proposals
        # shrink as the damping grows), and stops once a failed step with a non-finite
        # proposal has left the iterate where it was after one that already had: it
        # would repeat (Dogleg, its linear solve NaN at the start, ran on there to
        # max_steps). (optimistix's first step never moves the iterate: one such
        # failure is not yet a stop.) A solver without a proposal in its state counts
        # every failed step that left the iterate where it was.
        moved = _differs(y, state.y)
        proposal = getattr(inner, "y_eval", None)
        hopeless = jnp.array(True) if proposal is None else ~_finite(proposal)
        failed = inner_result != optx.RESULTS.successful
        idle = jnp.where(failed & ~moved & hopeless, state.idle + 1, 0)
        unmoved = jnp.where(failed & ~moved, state.unmoved + 1, 0)
        inner_done = inner_done | (idle >= 2)
        params = _point(problem, y, state.held)
        loss, g = problem.value_and_grad(params, self.strategy)
        gnorm = grad_norm(g)

        # Active set: free entries at a bound whose gradient points outwards get held;
        # where the inner solve has stopped, held entries whose gradient points into the
        # box are released, and so are entries that the iterate left beyond a bound
        # (clipped, with a zero tangent for a damped solver: `_flat`) although their
        # gradient points into the box: the restart puts them back on the bound. A
        # solver fed the unclipped Jacobian (`_flat`: Gauss-Newton, Dogleg,
        # IndirectLevenbergMarquardt) is restarted as soon as an entry is to be held: it
        # would otherwise walk on outside the box, where C(P(y)) no longer changes, or
        # have every step rejected at a bound.
        stop = inner_done
        stuck = jnp.array(False)
        if problem.lower is not None:
            at_lo = params.theta <= problem.lower
            at_hi = params.theta >= problem.upper
            push = (at_lo & (g.theta > 0)) | (at_hi & (g.theta < 0))
            inward = (at_lo & (g.theta < 0)) | (at_hi & (g.theta > 0))
            release = state.held.mask & inward & (problem.lower < problem.upper)
            new_mask = state.held.mask | push
            new_mask = jnp.where(inner_done, new_mask & ~release, new_mask)
            beyond = (y[0] < problem.lower) | (y[0] > problem.upper)
            stuck = inner_done & jnp.any(beyond & inward & ~new_mask)
            if not self._damped:
                stop = stop | jnp.any(push & ~state.held.mask)
        else:
            new_mask = state.held.mask
        if problem.project is not None and self._damped:
            # A general projection: where the inner solve stops with its iterate beyond
            # the set (P moved it by more than round-off), it starts again from P(y), on
            # the set: beyond it, C(P(y)) has no slope back into the set
            # (`_through_projection`), where the optimum may lie.
            gap = jnp.abs(y[0] - params.theta) > 4 * jnp.finfo(problem.dtype).eps * jnp.abs(y[0])
            stuck = stuck | (inner_done & jnp.any(gap & ~state.held.mask))
        changed = jnp.any(new_mask != state.held.mask) | stuck
        n_rounds = 4 * (params.theta.shape[0] + 1)
        restart = stop & changed & (state.rounds < n_rounds)
        held = _Held(
            new_mask, jnp.where(new_mask & ~state.held.mask, params.theta, state.held.values)
        )
        y_restart = (jnp.where(held.mask, held.values, params.theta), y[1])
        fresh = self._inner_init(problem, y_restart, held)
        dyn_inner, static_inner = eqx.partition(inner, eqx.is_array)
        dyn_fresh, _ = eqx.partition(fresh, eqx.is_array)
        dyn = jax.tree_util.tree_map(lambda a, b: jnp.where(restart, a, b), dyn_fresh, dyn_inner)
        inner = eqx.combine(dyn, static_inner)
        y = jax.tree_util.tree_map(lambda a, b: jnp.where(restart, a, b), y_restart, y)
        held = jax.tree_util.tree_map(lambda a, b: jnp.where(restart, a, b), held, state.held)

        done = inner_done & ~restart
        idle = jnp.where(restart, 0, idle)  # (a fresh inner solve)
        unmoved = jnp.where(restart, 0, unmoved)
        ok = inner_result == optx.RESULTS.successful
        nonfinite = (inner_result == optx.RESULTS.nonfinite) | ~jnp.isfinite(loss)
        # optimistix stops on its step and loss tests: certify the point by the
        # first-order test (its stop counts as a stall: the round-off limit applies).
        # (formed at the last step too: the measure a max_steps stop reports)
        count = state.count + 1
        # (and after `STUCK_STEPS` failed steps in a row that left the iterate where it
        # was: a stall there, if the measure is within the round-off limit, below)
        probe = unmoved >= STUCK_STEPS
        fo = lazy_cond(
            done | (count >= self.max_steps) | probe,
            lambda: self._first_order(problem, params, loss, g),
            jnp.array(jnp.nan, loss.dtype),
        )
        limit = stall_limit(problem, loss)
        stationary = (fo <= self.gtol) | (fo <= limit)
        finite = jnp.isfinite(loss) & jnp.isfinite(gnorm)
        # Without a stall (below), a positive gtol counts as at least the measure's
        # resolution, as for the first-order solvers: in float32 a fit at 1e-6 said "not
        # a stationary point yet" with gtol 1e-8, below the resolution 1.7e-4.
        gtol = gtol_at_least_resolution(self.gtol, problem.dtype)
        # At the last step allowed, a point that meets the first-order test (on the box)
        # is a solution: the fit reported max_steps_reached at a measure of 5e-12 where
        # optimistix's own tolerances had not fired yet.
        # So is one where the solver's steps failed and left the iterate where it was,
        # at a measure within the round-off limit: a stall there, which ends the fit
        # after `STUCK_STEPS` such steps (LM with conjugate gradients capped at 2
        # iterations rejected every proposal from step 150 on, at a measure of 1.8e-8,
        # and reported max_steps_reached at step 300).
        stall = failed & ~moved & (fo <= limit) & finite
        at_limit = ~done & (count >= self.max_steps) & (((fo <= gtol) & finite) | stall)
        own_test = done & ok  # (not a failure of the optimistix solver)
        done = done | at_limit | (probe & stall)
        zero = zero_residual(loss, data_scale(problem))
        result = RESULTS.where(
            stationary,
            RESULTS.converged,
            RESULTS.where(zero, RESULTS.zero_residual, RESULTS.stalled),
        )
        # A failure of the optimistix solver (its linear solve, say) at a point that meets
        # the first-order test leaves a solution: LM with a capped conjugate-gradient
        # solve reported no_progress at a measure of 9.7e-9 (gtol 1e-8), at the optimum.
        solved = ((fo <= gtol) & finite) | stall
        result = RESULTS.where(
            ok | solved, result, RESULTS.where(nonfinite, RESULTS.diverged, RESULTS.no_progress)
        )
        done, result = self._negative_penalty(problem, params, done, result)
        last, last_loss = jax.tree_util.tree_map(
            lambda a, b: jnp.where(finite, a, b), (params, loss), (state.last, state.last_loss)
        )
        return params, _OptxState(
            y,
            inner,
            held,
            loss,
            gnorm,
            done,
            result,
            state.rounds + restart,
            fo,
            count,
            own_test,
            last,
            last_loss,
            limit,
            idle,
            unmoved,
        )

    def terminate(self, problem, params, state):
        del problem, params
        return state.done, state.result

    def summary(self, state):
        return state.loss, state.gnorm

    def measures(self, state):
        # optimistix's own termination test (its rtol/atol on the step and the loss) is
        # this solver's step test: it fired wherever the inner solver stopped successfully.
        nan = jnp.full_like(state.loss, jnp.nan)
        failed = (state.result == RESULTS.no_progress) | (state.result == RESULTS.diverged)
        false = jnp.array(False)
        own = state.own_test & ~failed
        return Measures(state.first_order, nan, nan, nan, own, false, false, state.limit)

    def postprocess(self, problem, params, state, result):
        """A diverged fit returns its last finite iterate (as the library's solvers do)."""
        del problem
        diverged = result == RESULTS.diverged
        params = jax.tree_util.tree_map(lambda a, b: jnp.where(diverged, a, b), state.last, params)
        return params, jnp.where(diverged, state.last_loss, state.loss), None

    def settings(self) -> dict:
        """The options, with the optimistix solver's own rtol and atol (its step test). The
        name says which optimistix solver ran, on one line (its repr spans several)."""
        out = super().settings()
        out["solver"] = f"Optimistix({brief(self.solver)})"
        for name in ("rtol", "atol"):
            value = getattr(self.solver, name, None)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                out[name] = float(value)
        return out
